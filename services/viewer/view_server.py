"""The viewer's Foxglove WebSocket server: one port, checked before a client gets a byte.

A handshake whose Host is not one of the viewer's names is refused with 421, one whose Origin is neither
one of them nor a web app that may watch (Foxglove's, or the project's own served from loopback by
`make view-web`: `FOXGLOVE_APP_ORIGINS`, more with `--allow-origin`) with 403 (`shared/viewer/origin.py`,
the dashboard's rule); bound beyond loopback, one without the viewer's token with 401; past
MAX_CLIENTS connections, 503. All counted. An accepted client speaks the Foxglove protocol with the
viewer's ViewHub (shared/viewer/foxglove_ws.py).

This process serves the protocol itself: foxglove-sdk's server (which it used behind a gate before)
takes every handshake on its own port, and that port stayed open to any local process.

Each client has two threads (reading its requests, sending its frames) and a queue between the hub and
the socket: a slow or stalled client never slows the viewer; it loses its oldest messages beyond
MAX_QUEUED_MESSAGES / MAX_QUEUED_BYTES (`dropped/slow_client`), and a client that sends requests but
does not read their answers is closed (1008) once MAX_QUEUED_ANSWERS pile up.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Iterable
from http import HTTPStatus

from websockets.exceptions import ConnectionClosed
from websockets.frames import CloseCode
from websockets.http11 import Request, Response
from websockets.sync.server import Server, ServerConnection, serve

from services.viewer.dashboard_server import response, token_refusal
from shared.bus.codec import Counters
from shared.viewer.foxglove_ws import SUBPROTOCOLS, Frame, ViewHub
from shared.viewer.origin import FOXGLOVE_APP_ORIGINS, allowed_hosts, headers_problem

log = logging.getLogger(__name__)

#: What a viewing client sends is subscriptions and the like (JSON of a few kB): a larger frame closes
#: its connection (1009) before it is buffered whole.
MAX_CLIENT_MESSAGE_BYTES = 1024 * 1024
#: Viewing clients at once (each holds two threads and a queue); more get 503.
MAX_CLIENTS = 16
#: A client's unsent messages: the oldest go first beyond either bound (a second of every channel at
#: the draw rate, and room for a few camera frames and clouds).
MAX_QUEUED_MESSAGES = 512
MAX_QUEUED_BYTES = 64 * 1024 * 1024
#: A client's unsent answers (advertisements, error statuses): a client that asks and never reads is
#: closed beyond this.
MAX_QUEUED_ANSWERS = 256


class _Outbox:
    """One client's frames on their way to its socket: answers (text) before messages (binary)."""

    def __init__(self, counters: Counters) -> None:
        self._counters = counters
        self._answers: deque[str] = deque()
        self._messages: deque[bytes] = deque()
        self._queued_bytes = 0
        self._ready = threading.Condition()
        self.closed = False
        self.overflowed = False

    def put(self, frame: Frame) -> None:
        with self._ready:
            if self.closed:
                return
            if isinstance(frame, str):
                if len(self._answers) >= MAX_QUEUED_ANSWERS:
                    self.overflowed = self.closed = True
                else:
                    self._answers.append(frame)
            else:
                self._messages.append(frame)
                self._queued_bytes += len(frame)
                while len(self._messages) > MAX_QUEUED_MESSAGES or self._queued_bytes > MAX_QUEUED_BYTES:
                    self._queued_bytes -= len(self._messages.popleft())
                    self._counters.inc("dropped/slow_client")
            self._ready.notify()

    def take(self) -> Frame | None:
        """The next frame, waiting for one; None once closed."""
        with self._ready:
            while not (self.closed or self._answers or self._messages):
                self._ready.wait()
            if self.closed:
                return None
            if self._answers:
                return self._answers.popleft()
            frame = self._messages.popleft()
            self._queued_bytes -= len(frame)
            return frame

    def close(self) -> None:
        with self._ready:
            self.closed = True
            self._ready.notify()


class ViewServer:
    """Serves `hub` on `host:port` to the viewer's own names and the web apps allowed."""

    def __init__(
        self,
        hub: ViewHub,
        host: str,
        port: int,
        host_names: Iterable[str] = (),
        origins: Iterable[str] = (),
        token: str | None = None,
    ) -> None:
        self.hub = hub
        self.token = token
        self.origins = (*FOXGLOVE_APP_ORIGINS, *origins)
        self.counters = Counters()
        self._lock = threading.Lock()
        self._connections: set[ServerConnection] = set()
        self._server: Server = serve(
            self._handle,
            host,
            port,
            process_request=self._check,
            subprotocols=list(SUBPROTOCOLS),  # type: ignore[arg-type]
            compression=None,
            max_size=MAX_CLIENT_MESSAGE_BYTES,
        )
        self.port = self._server.socket.getsockname()[1]
        self._allowed = allowed_hosts(host, self.port, host_names)
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True, name="view-server")

    def start(self) -> ViewServer:
        """Serve from now on (a thread of its own); the server itself."""
        self._thread.start()
        return self

    def stop(self) -> None:
        self._server.shutdown()
        with self._lock:
            connections = list(self._connections)
        for connection in connections:
            connection.close(CloseCode.GOING_AWAY, "viewer stopping")
        self._thread.join(5.0)

    def _check(self, connection: ServerConnection, request: Request) -> Response | None:
        headers = request.headers
        refused = headers_problem(
            headers.get_all("Host"), headers.get_all("Origin"), self._allowed, self.origins
        )
        if refused is None:
            by_token = token_refusal(request, self.token, self.counters)
            if isinstance(by_token, Response):
                return by_token
            if self.hub.clients >= MAX_CLIENTS:
                self.counters.inc("rejected/http_503")
                body = f"refused: {MAX_CLIENTS} viewers are connected already\n".encode()
                return response(HTTPStatus.SERVICE_UNAVAILABLE, body, "text/plain")
            return None
        self.counters.inc(f"rejected/http_{refused.value}")
        what = "Host" if refused == HTTPStatus.MISDIRECTED_REQUEST else "Origin"
        return response(refused, f"refused: {what} not allowed ({refused.phrase})\n".encode(), "text/plain")

    def _handle(self, connection: ServerConnection) -> None:
        if connection.subprotocol is None:  # the client named none of SUBPROTOCOLS
            self.counters.inc("rejected/subprotocol")
            connection.close(CloseCode.PROTOCOL_ERROR, f"speak one of {', '.join(SUBPROTOCOLS)}")
            return
        outbox = _Outbox(self.counters)
        client_id = self.hub.connect(outbox.put)
        self.counters.inc("connections")
        sender = threading.Thread(target=_send, args=(connection, outbox), daemon=True, name="view-send")
        with self._lock:
            self._connections.add(connection)
        sender.start()
        try:
            for frame in connection:
                self.hub.receive(client_id, frame)
                if outbox.overflowed:
                    self.counters.inc("rejected/unread_answers")
                    connection.close(CloseCode.POLICY_VIOLATION, "answers left unread")
                    break
        except ConnectionClosed:
            pass
        finally:
            self.hub.disconnect(client_id)
            outbox.close()
            sender.join(5.0)
            with self._lock:
                self._connections.discard(connection)


def _send(connection: ServerConnection, outbox: _Outbox) -> None:
    """The client's frames to its socket until either closes."""
    try:
        while (frame := outbox.take()) is not None:
            connection.send(frame)
    except ConnectionClosed:
        pass
    finally:
        outbox.close()
        connection.close()
