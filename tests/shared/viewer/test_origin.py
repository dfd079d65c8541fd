"""Host and Origin checks of the local web endpoints (issue 34, item 10)."""

from __future__ import annotations

from http import HTTPStatus

from shared.viewer.origin import allowed_hosts, request_problem

LOCAL = allowed_hosts("127.0.0.1", 8080)


def test_its_own_names_with_or_without_the_port_are_answered() -> None:
    for host in ("127.0.0.1:8080", "localhost:8080", "LOCALHOST", "[::1]:8080"):
        assert request_problem(host, None, LOCAL) is None, host
    assert request_problem("127.0.0.1:8080", "http://localhost:8080", LOCAL) is None


def test_a_foreign_host_is_misdirected() -> None:
    """DNS rebinding: attacker.example resolved to 127.0.0.1, the browser sends its name."""
    assert request_problem("attacker.example:8080", None, LOCAL) == HTTPStatus.MISDIRECTED_REQUEST
    assert request_problem(None, None, LOCAL) == HTTPStatus.MISDIRECTED_REQUEST
    assert request_problem("127.0.0.1:9999", None, LOCAL) == HTTPStatus.MISDIRECTED_REQUEST


def test_a_foreign_origin_is_forbidden() -> None:
    """A page elsewhere opening ws://127.0.0.1:8080/ws: the Host is right, its Origin is not."""
    for origin in ("https://attacker.example", "null", "http://localhost:9999", "file://"):
        assert request_problem("127.0.0.1:8080", origin, LOCAL) == HTTPStatus.FORBIDDEN, origin


def test_a_server_on_every_address_answers_only_the_names_it_is_given() -> None:
    exposed = allowed_hosts("0.0.0.0", 8080, extra=["table-pc.lan"])
    assert request_problem("table-pc.lan:8080", "http://table-pc.lan:8080", exposed) is None
    assert request_problem("0.0.0.0:8080", None, exposed) == HTTPStatus.MISDIRECTED_REQUEST
    assert request_problem("10.0.0.5:8080", None, allowed_hosts("10.0.0.5", 8080)) is None
