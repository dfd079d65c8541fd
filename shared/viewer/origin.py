"""Which Host and Origin a local web endpoint (the dashboard) answers: its own names only.

A page on any web site can make the browser fetch http://127.0.0.1:8080/api/state (or open the
WebSocket), and a DNS-rebinding name can point at 127.0.0.1 while the page believes it talks to its own
server. Two checks close both: the request's Host must be one of the server's own names (loopback and
the address it binds; others only as configured), else 421 Misdirected Request; and a request that
carries an Origin (browsers send it on WebSocket handshakes and cross-site requests) must come from one
of those names too, else 403. A request without Origin (curl, scripts, a same-origin page load) is
let through on its Host.
"""

from __future__ import annotations

from collections.abc import Iterable
from http import HTTPStatus
from urllib.parse import urlsplit

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
ANY_ADDRESS = ("0.0.0.0", "::", "")


def allowed_hosts(bind_host: str, port: int, extra: Iterable[str] = ()) -> frozenset[str]:
    """Host header values the server answers: each name alone and with `:port`, lower case."""
    names = {*LOOPBACK_NAMES, *extra}
    if bind_host not in ANY_ADDRESS:
        names.add(f"[{bind_host}]" if ":" in bind_host else bind_host)
    names = {n.lower() for n in names}
    return frozenset(names | {f"{n}:{port}" for n in names})


#: Web apps allowed to open the Foxglove WebSocket besides the server's own names: Foxglove's own, which
#: a user opens in the browser to watch a local server (the desktop app sends no Origin), and a web app
#: served from this machine's loopback on any port (`make view-web`); `:*` matches any port.
FOXGLOVE_APP_ORIGINS = ("https://app.foxglove.dev", "http://127.0.0.1:*", "http://localhost:*")


def origin_listed(origin: str, origins: Iterable[str]) -> bool:
    """`origin` (scheme://name[:port]) is one of `origins`, where `scheme://name:*` stands for any port."""
    origin = origin.strip().lower()
    for allowed in (o.lower() for o in origins):
        if origin == allowed:
            return True
        if allowed.endswith(":*"):
            try:
                parts = urlsplit(origin)
                port = parts.port  # ValueError for a port that is no number or out of range
            except ValueError:
                return False
            if f"{parts.scheme}://{parts.hostname}:*" == allowed and port is not None:
                return True
    return False


def request_problem(
    host: str | None, origin: str | None, allowed: frozenset[str], origins: Iterable[str] = ()
) -> HTTPStatus | None:
    """None if the request may be answered, else the status to refuse it with. `origins`: whole
    origins (scheme://name) allowed besides the server's own names."""
    if host is None or host.strip().lower() not in allowed:
        return HTTPStatus.MISDIRECTED_REQUEST
    if origin is not None:
        try:
            parts = urlsplit(origin.strip())
        except ValueError:  # not a URL at all (an unclosed IPv6 bracket): no origin of ours
            return HTTPStatus.FORBIDDEN
        if origin_listed(origin, origins):
            return None
        if parts.scheme not in ("http", "https") or parts.netloc.lower() not in allowed:
            return HTTPStatus.FORBIDDEN
    return None


def headers_problem(
    hosts: list[str], origin_values: list[str], allowed: frozenset[str], origins: Iterable[str] = ()
) -> HTTPStatus | None:
    """`request_problem` on a request's raw header values: a request without exactly one Host (421) or
    with more than one Origin (403) is refused rather than judged on one of them."""
    if len(hosts) != 1:
        return HTTPStatus.MISDIRECTED_REQUEST
    if len(origin_values) > 1:
        return HTTPStatus.FORBIDDEN
    return request_problem(hosts[0], origin_values[0] if origin_values else None, allowed, origins)
