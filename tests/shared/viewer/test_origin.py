"""Host and Origin checks of the local web endpoints (issue 34, item 10)."""

from __future__ import annotations

from http import HTTPStatus

import pytest

from shared.viewer.origin import allowed_hosts, headers_problem, origin_listed, request_problem

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


def test_raw_headers_need_exactly_one_host_and_at_most_one_origin() -> None:
    assert headers_problem(["127.0.0.1:8080"], [], LOCAL) is None
    assert headers_problem([], [], LOCAL) == HTTPStatus.MISDIRECTED_REQUEST
    assert headers_problem(["127.0.0.1:8080"] * 2, [], LOCAL) == HTTPStatus.MISDIRECTED_REQUEST
    two = ["http://localhost:8080", "https://attacker.example"]
    assert headers_problem(["127.0.0.1:8080"], two, LOCAL) == HTTPStatus.FORBIDDEN


def test_a_listed_web_app_origin_is_allowed_but_is_no_host() -> None:
    app = ("https://app.foxglove.dev",)
    assert request_problem("127.0.0.1:8080", "https://app.foxglove.dev", LOCAL, app) is None
    assert request_problem("127.0.0.1:8080", "http://app.foxglove.dev", LOCAL, app) == HTTPStatus.FORBIDDEN
    assert request_problem("app.foxglove.dev", None, LOCAL, app) == HTTPStatus.MISDIRECTED_REQUEST


def test_a_port_wildcard_matches_any_port_of_that_name_only() -> None:
    local = ("http://127.0.0.1:*",)
    assert origin_listed("http://127.0.0.1:8090", local)
    assert not origin_listed("http://127.0.0.1", local)  # no port: not the pattern
    assert not origin_listed("http://127.0.0.1.attacker.example:8090", local)
    assert not origin_listed("https://127.0.0.1:8090", local)


@pytest.mark.parametrize("origin", ["http://127.0.0.1:abc", "http://[::1", "http://localhost:99999"])
def test_a_malformed_origin_is_refused_not_raised(origin: str) -> None:
    apps = ("http://127.0.0.1:*", "http://localhost:*")
    assert request_problem("127.0.0.1:8080", origin, LOCAL, apps) == HTTPStatus.FORBIDDEN
