"""The viewer's endpoints refuse bad requests clearly: the dashboard's push-only WebSocket closes with
1008 and a reason when a client talks to it (counted), and the Foxglove WebSocket server answers a
malformed or impossible request with an error status instead of dropping the connection."""

from __future__ import annotations

import http.client
import json
import time

import foxglove
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from services.viewer.dashboard_server import DashboardServer
from services.viewer.view_server import ViewServer
from shared.scene.scene import Scene
from shared.viewer.feeds import Outlets, SensorFeeds
from shared.viewer.foxglove_ws import ViewHub
from tests.integration.foxglove_client import SUBPROTOCOL


def _hub(scene: Scene) -> ViewHub:
    """The viewer's hub with the scene's sensor channels."""
    outlets = Outlets(ViewHub())
    outlets.hub.listener = SensorFeeds(scene, outlets)
    return outlets.hub


@pytest.fixture
def dashboard():
    server = DashboardServer("127.0.0.1", 0, {"lanes": [], "junctions": []})
    server.start()
    yield server
    server.stop()


def test_the_dashboard_socket_pushes_and_refuses_messages(dashboard: DashboardServer) -> None:
    dashboard.publish({"agents": []})
    with connect(f"ws://127.0.0.1:{dashboard.port}/ws", open_timeout=5) as ws:
        state = json.loads(ws.recv(timeout=5))
        assert state["agents"] == [] and state["taken_unix_s"] > 0
        assert dashboard.watched
        ws.send("hello")
        with pytest.raises(ConnectionClosed) as closed:
            ws.recv(timeout=5)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1008
    assert "takes no messages" in closed.value.rcvd.reason
    assert dashboard.counters.snapshot()["rejected/ws_message"] == 1
    deadline = time.monotonic() + 5
    while dashboard.watched and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not dashboard.watched


def test_the_dashboard_refuses_a_foreign_origin_and_a_foreign_host(dashboard: DashboardServer) -> None:
    """Issue 34, item 10: a page elsewhere opening the dashboard's socket (foreign Origin: 403) or
    reaching it through a DNS-rebound name (foreign Host: 421); its own page still loads."""
    import http.client

    def get(path: str, headers: dict[str, str]) -> int:
        conn = http.client.HTTPConnection("127.0.0.1", dashboard.port, timeout=5)
        try:
            conn.request("GET", path, headers=headers)
            return conn.getresponse().status
        finally:
            conn.close()

    own = f"127.0.0.1:{dashboard.port}"
    assert get("/api/state", {"Host": own}) == 200
    assert get("/api/state", {"Host": own, "Origin": f"http://localhost:{dashboard.port}"}) == 200
    assert get("/api/state", {"Host": own, "Origin": "https://attacker.example"}) == 403
    assert get("/api/state", {"Host": f"attacker.example:{dashboard.port}"}) == 421
    with pytest.raises(Exception, match="403"):
        connect(f"ws://127.0.0.1:{dashboard.port}/ws", origin="https://attacker.example", open_timeout=5)  # type: ignore[arg-type]
    counts = dashboard.counters.snapshot()
    assert counts["rejected/http_403"] == 2 and counts["rejected/http_421"] == 1


def test_the_foxglove_server_answers_bad_requests_with_errors(test_scene: Scene) -> None:
    viewer = ViewServer(_hub(test_scene), "127.0.0.1", 0).start()
    try:
        with connect(f"ws://127.0.0.1:{viewer.port}", subprotocols=[SUBPROTOCOL], open_timeout=5) as ws:  # type: ignore[list-item]
            ws.send("not json")
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 99999}]}))
            statuses = []
            deadline = time.monotonic() + 5
            while len(statuses) < 2 and time.monotonic() < deadline:
                frame = ws.recv(timeout=5)
                if isinstance(frame, str) and json.loads(frame).get("op") == "status":
                    statuses.append(json.loads(frame))
    finally:
        viewer.stop()
    assert len(statuses) == 2, statuses
    assert all(s["level"] == 2 and s["message"] for s in statuses), statuses  # 2: error


def test_the_foxglove_websocket_refuses_a_foreign_origin_or_host(test_scene: Scene) -> None:
    """Issue 34 item 10: a page on another site cannot open the Foxglove WebSocket in the user's browser
    (403), nor a DNS-rebound name (421); the viewer's own names, no Origin (the desktop app) and
    Foxglove's web app are let through to the server, which then speaks to them as before."""
    viewer = ViewServer(_hub(test_scene), "127.0.0.1", 0).start()
    url = f"ws://127.0.0.1:{viewer.port}"
    try:
        for origin in ("https://attacker.example", "http://127.0.0.1.attacker.example"):
            with pytest.raises(Exception, match="403"):
                connect(url, origin=origin, subprotocols=[SUBPROTOCOL], open_timeout=5)  # type: ignore[arg-type,list-item]
        for hosts in (
            [f"attacker.example:{viewer.port}"],
            [f"127.0.0.1:{viewer.port}"] * 2,
        ):  # rebound, doubled
            conn = http.client.HTTPConnection("127.0.0.1", viewer.port, timeout=5)
            try:
                conn.putrequest("GET", "/", skip_host=True)
                for host in hosts:
                    conn.putheader("Host", host)
                conn.endheaders()
                assert conn.getresponse().status == 421
            finally:
                conn.close()
        for origin in (
            None,
            f"http://localhost:{viewer.port}",
            "https://app.foxglove.dev",
            "http://127.0.0.1:8090",
        ):
            with connect(url, origin=origin, subprotocols=[SUBPROTOCOL], open_timeout=5) as ws:  # type: ignore[arg-type,list-item]
                hello = json.loads(ws.recv(timeout=5))
                assert hello["op"] == "serverInfo" and ws.subprotocol == SUBPROTOCOL, hello
    finally:
        viewer.stop()
    counts = viewer.counters.snapshot()
    assert (
        counts["rejected/http_403"] == 2 and counts["rejected/http_421"] == 2 and counts["connections"] == 4
    )


def test_beyond_loopback_a_token_is_needed_and_frames_are_capped(test_scene: Scene, tmp_path) -> None:
    """Issue 52 item 7: bound beyond loopback the dashboard and the Foxglove WebSocket served anyone who
    reached the port; a web app on any loopback port was an allowed origin; the viewer buffered client
    frames of any size. Now: a token (once in the query, then a cookie), the project's web app named
    (its port only), client frames over MAX_CLIENT_MESSAGE_BYTES closed."""
    import os
    import stat

    from services.viewer.view_server import MAX_CLIENT_MESSAGE_BYTES
    from shared.viewer.origin import FOXGLOVE_APP_ORIGINS, TOKEN_COOKIE, view_token

    token_file = tmp_path / "viewer.token"
    assert view_token("127.0.0.1", token_file) is None and not token_file.exists()
    token = view_token("0.0.0.0", token_file)
    assert token and stat.S_IMODE(os.stat(token_file).st_mode) == 0o600
    assert view_token("0.0.0.0", token_file) == token  # kept
    assert "http://127.0.0.1:3000" not in FOXGLOVE_APP_ORIGINS  # another local web app: not by default

    board = DashboardServer("0.0.0.0", 0, {"lanes": []}, token=token)
    board.start()
    viewer = ViewServer(_hub(test_scene), "0.0.0.0", 0, token=token).start()
    try:

        def get(path: str, headers: dict[str, str]) -> tuple[int, str | None]:
            conn = http.client.HTTPConnection("127.0.0.1", board.port, timeout=5)
            try:
                conn.request("GET", path, headers={"Host": f"127.0.0.1:{board.port}", **headers})
                got = conn.getresponse()
                return got.status, got.getheader("Set-Cookie")
            finally:
                conn.close()

        assert get("/api/state", {})[0] == 401
        assert get(f"/api/state?token={token[:-1]}x", {})[0] == 401
        status, cookie = get(f"/?token={token}", {})
        assert status == 200 and cookie is not None and cookie.startswith(f"{TOKEN_COOKIE}={token};")
        assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
        assert get("/api/state", {"Cookie": f"{TOKEN_COOKIE}={token}"})[0] == 200
        url = f"ws://127.0.0.1:{viewer.port}"
        with pytest.raises(Exception, match="401"):
            connect(url, subprotocols=[SUBPROTOCOL], open_timeout=5)  # type: ignore[list-item]
        with pytest.raises(Exception, match="403"):  # a local web app on another port
            connect(
                f"{url}/?token={token}",
                origin="http://127.0.0.1:3000",
                subprotocols=[SUBPROTOCOL],
                open_timeout=5,
            )  # type: ignore[list-item]
        with connect(f"{url}/?token={token}", subprotocols=[SUBPROTOCOL], open_timeout=5) as ws:  # type: ignore[list-item]
            assert json.loads(ws.recv(timeout=5))["op"] == "serverInfo"
            ws.send(b"\0" * (MAX_CLIENT_MESSAGE_BYTES + 1))
            with pytest.raises(ConnectionClosed):
                for _ in range(100):
                    ws.recv(timeout=5)
    finally:
        viewer.stop()
        board.stop()
    assert board.counters.snapshot()["rejected/http_401"] == 2
    assert viewer.counters.snapshot()["rejected/http_401"] == 1


def _listening_ports() -> set[int]:
    import psutil

    return {c.laddr.port for c in psutil.Process().net_connections("inet") if c.status == psutil.CONN_LISTEN}


def test_the_viewer_serves_foxglove_on_its_one_checked_port_only(test_scene: Scene) -> None:
    """Issue 52 item 7: the viewer ran foxglove-sdk's server on a loopback port of its own behind the
    checked one, and any local process could read the live view there unchecked. Now the checked port
    is the only one the viewer listens on."""
    before = _listening_ports()
    viewer = ViewServer(_hub(test_scene), "127.0.0.1", 0).start()
    try:
        assert _listening_ports() - before == {viewer.port}
    finally:
        viewer.stop()


#: What an advertisement says of a channel, compared (ids are each server's own; the SDK may add keys).
ADVERTISED = ("topic", "encoding", "schemaName", "schemaEncoding", "schema")


def _advertised(channel: dict) -> dict:
    """A channel's advertisement as compared: a protobuf schema by the files it describes (the SDK keeps
    one schema per name for the process, so within the whole suite it may send another test's encoding
    of the same FileDescriptorSet)."""
    import base64

    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    out = {k: channel.get(k) for k in ADVERTISED}
    if out["schemaEncoding"] == "protobuf":
        files = FileDescriptorSet.FromString(base64.b64decode(out["schema"])).file
        out["schema"] = sorted(f.name for f in files)
    return out


def test_the_frames_are_those_foxglove_sdk_sends(test_scene: Scene) -> None:
    """The reference: foxglove-sdk 0.30's own server, given the same channels and messages, sends the
    same advertisements (but for channel ids) and byte-identical message frames, under either name of
    the protocol. Differences, by cause: serverInfo's metadata names the SDK; a second subscription
    to a channel is a warning there (ignored) and an error here (also ignored)."""
    from foxglove_schemas_protobuf.Grid_pb2 import Grid

    from shared.viewer.feeds import Outlets
    from shared.viewer.foxglove_ws import SUBPROTOCOLS, protobuf_schema
    from shared.viewer.health_feed import HEALTH_SCHEMA

    grid = Grid(column_count=3, cell_stride=4, data=b"\x01\x02\x03")
    health = b'{"loop_ok": true}'
    context = foxglove.Context()
    reference_channels = [
        foxglove.Channel(
            t,
            schema=foxglove.Schema(name=s.name, encoding=s.encoding, data=s.data),
            message_encoding=s.message_encoding,
            context=context,
        )
        for t, s in (("/grid", protobuf_schema(Grid)), ("/health", HEALTH_SCHEMA))
    ]
    reference = foxglove.start_server(name="rmmdet", host="127.0.0.1", port=0, context=context)
    outlets = Outlets(ViewHub())
    ours = [outlets.open("/grid", protobuf_schema(Grid)), outlets.open("/health", HEALTH_SCHEMA)]
    viewer = ViewServer(outlets.hub, "127.0.0.1", 0).start()

    def session(port: int, subprotocol: str, log) -> tuple[list[dict], list[bytes]]:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol], open_timeout=5) as ws:  # type: ignore[list-item]
            info, advert = json.loads(ws.recv(timeout=5)), json.loads(ws.recv(timeout=5))
            assert (
                info["op"] == "serverInfo" and advert["op"] == "advertise" and ws.subprotocol == subprotocol
            )
            by_topic = {c["topic"]: c["id"] for c in advert["channels"]}
            wanted = [{"id": 7, "channelId": by_topic["/grid"]}, {"id": 8, "channelId": by_topic["/health"]}]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": wanted}))
            time.sleep(0.3)
            log()
            frames = [ws.recv(timeout=5), ws.recv(timeout=5)]
            ws.send("not json")
            level = json.loads(ws.recv(timeout=5))["level"]
        return [_advertised(c) for c in advert["channels"]] + [{"level": level}], frames  # type: ignore[return-value]

    def log_reference() -> None:
        reference_channels[0].log(grid.SerializeToString(), log_time=123)
        reference_channels[1].log(health, log_time=456)

    def log_ours() -> None:
        ours[0].log(grid.SerializeToString(), 123)
        ours[1].log(health, 456)

    try:
        expected = session(reference.port, "foxglove.sdk.v1", log_reference)
        for subprotocol in SUBPROTOCOLS:  # foxglove-sdk 0.30 refuses foxglove.websocket.v1 (HTTP 400)
            assert session(viewer.port, subprotocol, log_ours) == expected
    finally:
        viewer.stop()
        reference.stop()
