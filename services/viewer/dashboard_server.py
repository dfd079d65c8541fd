"""The browser dashboard's HTTP + WebSocket endpoints, one port (websockets' server):

    GET /            the page (services/viewer/static/dashboard.html: plain HTML/JS, no build step)
    GET /api/state   the latest snapshot (shared/viewer/dashboard.py) with `taken_unix_s`, JSON: after a
                     quiet spell the first may be up to the viewer's idle period old (10 s), then
                     snapshots are made at the draw rate while polls keep coming
    GET /api/table   the table's lanes and junctions for the map, JSON (static)
    WS  /ws          the snapshot again every time it changes (at most the viewer's draw rate)

A request whose Host is not one of the dashboard's names gets 421, one carrying a foreign Origin 403
(another site's page reading the live state; `shared/viewer/origin.py`), counted as
`rejected/http_421` / `rejected/http_403`. Anything else gets a clear 404, counted
(`rejected/http_not_found` in `counters`, which the viewer exports with its health); a plain GET on /ws
a 426 (upgrade required, from websockets); a message sent on /ws closes it with 1008 and a reason
(`rejected/ws_message`). Each connection has its own thread: a slow or stalled browser blocks only its
own socket, never the viewer.
Binds to loopback unless told otherwise.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Iterable
from http import HTTPStatus
from pathlib import Path
from typing import Any

from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.http11 import Request, Response
from websockets.sync.server import Server, ServerConnection, serve

from shared.bus.codec import Counters
from shared.viewer.origin import allowed_hosts, headers_problem, token_cookie, token_given

log = logging.getLogger("services.viewer.dashboard")

PAGE = Path(__file__).with_name("static") / "dashboard.html"
PUSH_POLL_S = 0.1  # how often a connection looks for a newer snapshot
POLLED_WATCHING_S = 10.0  # an /api/state request counts as someone watching for this long


def response(status: HTTPStatus, body: bytes, content_type: str, cookie: str | None = None) -> Response:
    headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body)))])
    headers["Cache-Control"] = "no-store"
    if cookie is not None:
        headers["Set-Cookie"] = cookie
    return Response(status.value, status.phrase, headers, body)


def token_refusal(request: Request, token: str | None, counters: Counters) -> Response | str | None:
    """A 401 (counted) for a request without the viewer's token (`origin.token_given`), "query" when it
    came in the query (a page response then sets the cookie), else None."""
    given = token_given(request.path, request.headers.get_all("Cookie"), token)
    if given:
        return "query" if given == "query" else None
    counters.inc("rejected/http_401")
    body = b"refused: this viewer serves beyond loopback and needs its token (?token=... once)\n"
    return response(HTTPStatus.UNAUTHORIZED, body, "text/plain; charset=utf-8")


class DashboardServer:
    """Serves `publish`ed snapshots; `table` is the static map (lanes, junctions)."""

    def __init__(
        self,
        host: str,
        port: int,
        table: dict[str, Any],
        host_names: Iterable[str] = (),
        token: str | None = None,
    ) -> None:
        """`token`: asked of every request (`origin.view_token`: a bind beyond loopback)."""
        self.token = token
        self._table = json.dumps(table).encode()
        self._page = PAGE.read_bytes()
        self._latest = b"{}"
        self._version = 0
        self._changed = threading.Condition()
        self._server: Server = serve(self._handle, host, port, process_request=self._route, compression=None)
        self.port = self._server.socket.getsockname()[1]
        self._allowed = allowed_hosts(host, self.port, host_names)
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True, name="dashboard")
        self.counters = Counters()  # thread-safe: the connections' threads count here
        self._watching = 0  # open WebSocket connections
        self._polled_s = -math.inf  # monotonic time of the last /api/state request

    @property
    def watched(self) -> bool:
        """True while some browser holds the live WebSocket open or polled /api/state lately."""
        with self._changed:
            return self._watching > 0 or time.monotonic() - self._polled_s < POLLED_WATCHING_S

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._server.shutdown()
        with self._changed:
            self._changed.notify_all()
        self._thread.join(5.0)

    def publish(self, snapshot: dict[str, Any]) -> None:
        """The state to serve from now on (the viewer's loop calls this; JSON is made once here)."""
        data = json.dumps({**snapshot, "taken_unix_s": round(time.time(), 3)}).encode()
        with self._changed:
            self._latest, self._version = data, self._version + 1
            self._changed.notify_all()

    def _route(self, connection: ServerConnection, request: Request) -> Response | None:
        headers = request.headers
        refused = headers_problem(headers.get_all("Host"), headers.get_all("Origin"), self._allowed)
        if refused is not None:  # another site's page, or a DNS-rebound name (shared/viewer/origin.py)
            self.counters.inc(f"rejected/http_{refused.value}")
            what = "Host" if refused == HTTPStatus.MISDIRECTED_REQUEST else "Origin"
            body = f"refused: {what} is not this dashboard's ({refused.phrase})\n".encode()
            return response(refused, body, "text/plain; charset=utf-8")
        by_token = token_refusal(request, self.token, self.counters)
        if isinstance(by_token, Response):
            return by_token
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            return None  # the WebSocket handshake goes on
        if path in ("/", "/index.html"):
            cookie = token_cookie(self.token) if by_token == "query" and self.token else None
            return response(HTTPStatus.OK, self._page, "text/html; charset=utf-8", cookie)
        if path == "/api/state":
            with self._changed:
                self._polled_s = time.monotonic()
                return response(HTTPStatus.OK, self._latest, "application/json")
        if path == "/api/table":
            return response(HTTPStatus.OK, self._table, "application/json")
        self.counters.inc("rejected/http_not_found")
        body = f"no such page: {path} (try /, /api/state, /api/table or the WebSocket /ws)\n".encode()
        return response(HTTPStatus.NOT_FOUND, body, "text/plain; charset=utf-8")

    def _client_spoke(self, connection: ServerConnection) -> bool:
        """The socket only sends: a message from the browser is refused, counted, and the connection
        closed with a reason (1008, policy violation), not left to pile up unread."""
        try:
            connection.recv(timeout=0)
        except TimeoutError:
            return False
        self.counters.inc("rejected/ws_message")
        connection.close(CloseCode.POLICY_VIOLATION, "/ws only sends snapshots; it takes no messages")
        return True

    def _handle(self, connection: ServerConnection) -> None:
        seen = -1
        with self._changed:
            self._watching += 1
        try:
            while True:
                with self._changed:
                    if self._version == seen:
                        self._changed.wait(PUSH_POLL_S)
                    data, version = self._latest, self._version
                if version != seen:
                    connection.send(data.decode())
                    seen = version
                if self._client_spoke(connection):
                    return
        except ConnectionClosed:
            return
        finally:
            with self._changed:
                self._watching -= 1
