"""The Foxglove WebSocket behind a Host and Origin check (issue 34, item 10).

foxglove-sdk's server takes every WebSocket handshake (it has no hook that sees the request's headers),
so a page on any web site could open ws://127.0.0.1:8765 in the user's browser and read the live state
and the camera frames. The viewer therefore runs that server on a loopback port of its own and serves
the public port here: a handshake whose Host is not one of the viewer's names is refused with 421, one
whose Origin is neither one of them nor a web app that may watch (Foxglove's, or one served from this
machine's loopback by `make view-web`: `FOXGLOVE_APP_ORIGINS`, more with `--allow-origin`) with 403
(`shared/viewer/origin.py`, the dashboard's rule), counted; bound beyond loopback, a handshake without
the viewer's token is refused with 401; an accepted one is joined to the inner server with the same
subprotocol and every message is passed on as it is, both ways (a client's at most
MAX_CLIENT_MESSAGE_BYTES). The inner server's loopback port stays open to local processes: the SDK has
no hook to refuse them.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from http import HTTPStatus

import foxglove
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.sync.client import ClientConnection, connect
from websockets.sync.server import Server, ServerConnection, serve

from services.viewer.dashboard_server import response, token_refusal
from shared.bus.codec import DEFAULT_MAX_PAYLOAD_BYTES, Counters
from shared.viewer.feeds import SensorFeeds
from shared.viewer.origin import FOXGLOVE_APP_ORIGINS, allowed_hosts, headers_problem

log = logging.getLogger(__name__)

#: The Foxglove WebSocket protocols (the SDK's and the older one); the client's choice is passed on.
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
#: What a viewing client sends is subscriptions and the like (JSON of a few kB): a larger frame closes
#: its connection (1009) before it is buffered whole.
MAX_CLIENT_MESSAGE_BYTES = 1024 * 1024
#: What the viewer's own server sends: a message of the bus at most (a camera frame) and its framing, or
#: a channel advertisement with its schemas.
MAX_VIEW_MESSAGE_BYTES = 4 * DEFAULT_MAX_PAYLOAD_BYTES


class OriginGate:
    """Serves `host:port` and passes accepted connections on to the server at 127.0.0.1:`inner_port`."""

    def __init__(
        self,
        host: str,
        port: int,
        inner_port: int,
        host_names: Iterable[str] = (),
        origins: Iterable[str] = (),
        token: str | None = None,
    ) -> None:
        self.inner_port = inner_port
        self.token = token
        self.origins = (*FOXGLOVE_APP_ORIGINS, *origins)
        self.counters = Counters()
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
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True, name="ws-gate")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._server.shutdown()
        self._thread.join(5.0)

    def _check(self, connection: ServerConnection, request: Request) -> Response | None:
        headers = request.headers
        refused = headers_problem(
            headers.get_all("Host"), headers.get_all("Origin"), self._allowed, self.origins
        )
        if refused is None:
            by_token = token_refusal(request, self.token, self.counters)
            return by_token if isinstance(by_token, Response) else None
        self.counters.inc(f"rejected/http_{refused.value}")
        what = "Host" if refused == HTTPStatus.MISDIRECTED_REQUEST else "Origin"
        return response(refused, f"refused: {what} not allowed ({refused.phrase})\n".encode(), "text/plain")

    def _handle(self, client: ServerConnection) -> None:
        protocols = [client.subprotocol] if client.subprotocol else list(SUBPROTOCOLS)
        try:
            inner = connect(
                f"ws://127.0.0.1:{self.inner_port}",
                subprotocols=protocols,  # type: ignore[arg-type]
                compression=None,
                max_size=MAX_VIEW_MESSAGE_BYTES,
            )
        except (OSError, ConnectionClosed) as err:
            self.counters.inc("errors/inner_connect")
            log.warning("Foxglove server not reachable on port %d: %s", self.inner_port, err)
            return
        self.counters.inc("connections")
        with inner:
            upstream = threading.Thread(target=_pump, args=(client, inner), daemon=True, name="ws-gate-up")
            upstream.start()
            _pump(inner, client)
            upstream.join(5.0)


def _pump(source: ServerConnection | ClientConnection, sink: ServerConnection | ClientConnection) -> None:
    """Every message of `source` to `sink` until either closes; then close the other."""
    try:
        for message in source:
            sink.send(message)
    except ConnectionClosed:
        pass
    finally:
        source.close()
        sink.close()


def start_view_server(
    context: foxglove.Context,
    feeds: SensorFeeds,
    host: str,
    port: int,
    host_names: Iterable[str] = (),
    origins: Iterable[str] = (),
    token: str | None = None,
) -> tuple[foxglove.WebSocketServer, OriginGate]:
    """The Foxglove WebSocket server of `context`'s channels, the sensor feeds listening to who
    subscribes, on a loopback port of its own, and the gate that serves it on `host:port` to the
    viewer's own names and Foxglove's web app only (services/viewer/ws_gate.py; port 0: any free one)."""
    inner = foxglove.start_server(
        name="rmmdet", host="127.0.0.1", port=0, context=context, server_listener=feeds
    )
    try:
        gate = OriginGate(host, port, inner.port, host_names, origins, token)
    except (OSError, RuntimeError):
        inner.stop()
        raise
    gate.start()
    return inner, gate
