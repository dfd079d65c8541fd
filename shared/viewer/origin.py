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

import hmac
import ipaddress
import os
import secrets
from collections.abc import Iterable
from http import HTTPStatus
from http.cookies import CookieError, SimpleCookie
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
ANY_ADDRESS = ("0.0.0.0", "::", "")


def allowed_hosts(bind_host: str, port: int, extra: Iterable[str] = ()) -> frozenset[str]:
    """Host header values the server answers: each name alone and with `:port`, lower case."""
    names = {*LOOPBACK_NAMES, *extra}
    if bind_host not in ANY_ADDRESS:
        names.add(f"[{bind_host}]" if ":" in bind_host else bind_host)
    names = {n.lower() for n in names}
    return frozenset(names | {f"{n}:{port}" for n in names})


#: The port `make view-web` serves the project's Foxglove web app on (the Makefile asks for it here).
VIEW_WEB_PORT = 8090
#: Web apps allowed to open the Foxglove WebSocket besides the server's own names, each named: Foxglove's
#: own, which a user opens in the browser to watch a local server (the desktop app sends no Origin), and
#: the project's web app from `make view-web`. Any other (another port, another local web app: any page
#: a local process serves could read the live view) only with `--allow-origin`, where `:*` stands for
#: any port.
FOXGLOVE_APP_ORIGINS = (
    "https://app.foxglove.dev",
    f"http://127.0.0.1:{VIEW_WEB_PORT}",
    f"http://localhost:{VIEW_WEB_PORT}",
)


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


# --- a token for any bind beyond loopback -------------------------------------------------------------

#: The cookie a browser keeps the token in once it opened a page with `?token=` (sent on later requests
#: and on the WebSocket handshakes to the same host, whatever the port).
TOKEN_COOKIE = "rmmdet_view_token"
TOKEN_QUERY = "token"


def is_loopback(host: str) -> bool:
    """Whether binding `host` serves this machine only."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def view_token(bind_host: str, token_file: Path) -> str | None:
    """The token a viewer bound to `bind_host` asks every request for: None on loopback (the Host and
    Origin checks suffice there); beyond it the one in `token_file`, made (0600, 256 random bits) if the
    file is not there. A host on the network could otherwise read the live view and its camera frames."""
    if is_loopback(bind_host):
        return None
    if not token_file.exists():
        token_file.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_urlsafe(32) + "\n")
    token = token_file.read_text().strip()
    if len(token) < 16:
        raise ValueError(f"{token_file}: a token of {len(token)} characters is too short (16 at least)")
    return token


def token_given(path: str, cookie_headers: list[str], token: str | None) -> bool | str:
    """Whether a request (its path with query, its Cookie headers) carries `token` (always, for None):
    True by cookie, "query" when by `?token=` (the caller sets the cookie), False when not at all."""
    if token is None:
        return True
    for value in parse_qs(urlsplit(path).query).get(TOKEN_QUERY, []):
        if hmac.compare_digest(value.encode(), token.encode()):
            return "query"
    for header in cookie_headers:
        jar: SimpleCookie = SimpleCookie()
        try:
            jar.load(header)
        except CookieError:
            continue
        morsel = jar.get(TOKEN_COOKIE)
        if morsel is not None and hmac.compare_digest(morsel.value.encode(), token.encode()):
            return True
    return False


def token_cookie(token: str) -> str:
    """The Set-Cookie value that keeps `token` in the browser for this host (not for scripts)."""
    return f"{TOKEN_COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict"
