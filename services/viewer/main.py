"""Live 3D view over the Foxglove WebSocket protocol (issue 18, first part): connect Foxglove or
Lichtblick to ws://127.0.0.1:8765 while the system runs.

    python -m services.viewer [--host 127.0.0.1] [--port 8765] [--publish-hz 10]

Channels (Foxglove protobuf schemas, drawn by shared/viewer: `scene.py`, feeds and health beside it):
    /table                  SceneUpdate  lanes, junction numbers, sensors and their fields of view (every 2 s)
    /ground_truth           SceneUpdate  the simulated vehicles (a layer to hide)
    /agents/<agent>/tracks  SceneUpdate  each agent's tracked boxes, coloured by modality, ids, velocities
    /plans                  SceneUpdate  each vehicle's newest plan, pushed or served, along its lanes
                            (redrawn every 1 s until it expires)
    /traffic/grid           Grid         the coordinator's density / speed grid
    /health                 JSON         `rmmdet health`'s verdict and every service's level (every 2 s)
                            while watched here or on the dashboard, else every 10 s
    /agents/<agent>/<kind>/<sensor>      camera images (foxglove.CompressedImage), lidar clouds
                            (foxglove.PointCloud), radar scans (rmmdet.v1.RadarScan): the bus payloads
                            as they are, subscribed on the bus only while a client watches (SensorFeeds)
    /agents/<agent>/camera/<camera>/detections   ImageAnnotations  the MEC's 2D detections on that
                            image (boxes and scores, stamped as the image), also only while watched
    /agents/<agent>/radar/<radar>/targets        SceneUpdate  that radar's targets as spheres (red
                            approaching, blue receding), in its frame; also only while watched
    /tf                     FrameTransforms  world -> each lidar's and radar's frame (with the table)

A browser dashboard is served by the same process on `--dashboard-port` (services/viewer/
dashboard_server.py: http://127.0.0.1:8080/): coverage, rates and latencies per agent, live junction
counters, plans and acknowledgements, the density heat map over the lanes, the alarms.

`--mcap PATH` also writes every channel into an MCAP file (what is drawn, as drawn: playback in
Foxglove shows the same view; while it records, everything is drawn).

Cheap by default: nothing is drawn while no client subscribes (`Outlet.has_sinks`), and at most
`--publish-hz` updates per channel are drawn, the newest of each stream (latest-wins queues). A slow or
gone client never slows the loop: the viewer's WebSocket server (services/viewer/view_server.py, the
only port: Host, Origin and token checked) queues per client and drops the oldest of what a client
cannot take. Binds to loopback unless told otherwise.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from pathlib import Path

import foxglove
import zenoh

from services.viewer.dashboard_server import DashboardServer
from services.viewer.view_server import ViewServer
from shared.bus import names
from shared.bus.node import Node
from shared.paths import DEFAULT_SCENE, RUN_DIR
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.service import exit_process, positive_float, run_service
from shared.shutdown import GracefulShutdown
from shared.viewer.core import ViewerCore
from shared.viewer.dashboard import DashboardState, map_of
from shared.viewer.feeds import Channels, Outlets, SensorFeeds
from shared.viewer.foxglove_ws import ViewHub
from shared.viewer.health_feed import IDLE_EVERY_S, HealthFeed
from shared.viewer.inputs import ViewerInputs
from shared.viewer.origin import view_token

log = logging.getLogger("services.viewer")

SERVICE = names.VIEWER


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    scene = Scene.load(args.scene)
    network = RoadNetwork(scene)
    outlets = Outlets(ViewHub("rmmdet"))
    feeds = SensorFeeds(scene, outlets)
    outlets.hub.listener = feeds
    try:  # a port in use is a clear one-line exit, not a traceback
        token = view_token(args.host, args.token_file)
        dashboard = (
            DashboardServer(
                args.host, args.dashboard_port, map_of(scene, network), args.host_name or (), token
            )
            if args.dashboard_port
            else None
        )
        server = ViewServer(
            outlets.hub, args.host, args.port, args.host_name or (), args.allow_origin or (), token
        ).start()
    except (OSError, RuntimeError, ValueError) as err:
        raise SystemExit(
            f"viewer: cannot serve on {args.host} ports {args.port}/{args.dashboard_port}: {err}"
        ) from None
    recording = (
        foxglove.open_mcap(args.mcap, allow_overwrite=True, context=outlets.context) if args.mcap else None
    )
    log.info("Foxglove WebSocket server on ws://%s:%d", args.host, server.port)
    if token is not None:
        log.warning(
            "serving beyond loopback: every request needs the token in %s (?token=<it> once: the browser "
            "keeps it)",
            args.token_file,
        )
    if dashboard is not None:
        dashboard.start()
        log.info("dashboard on http://%s:%d/", args.host, dashboard.port)
    channels = Channels(outlets)
    period_s = 1.0 / args.publish_hz
    try:
        with Node(conf, service=SERVICE, instance=args.instance, scope="site", stop=shutdown.event) as node:
            feeds.attach(node.session, node.counters)
            health_feed = HealthFeed(scene, outlets)

            def watched() -> bool:
                return dashboard is not None and dashboard.watched

            threading.Thread(
                target=health_feed.run, args=(node.session, shutdown.event, watched), daemon=True
            ).start()
            inputs = ViewerInputs(node, scene)
            core = ViewerCore(scene, network)
            for topic, message_type in core.topics().items():
                channels.wants(topic, message_type)  # advertised now, before any client connects
            board = DashboardState(list(scene.agents))
            last_snapshot = -math.inf
            while not shutdown.requested:
                node.health.beat()
                t0 = time.monotonic()
                inputs.take(core, board, t0)
                while not health_feed.verdicts.empty():
                    verdict = health_feed.verdicts.get()
                    board.on_health(verdict.ok, verdict.summary(), verdict.problems)
                if dashboard is not None and (dashboard.watched or t0 - last_snapshot >= IDLE_EVERY_S):
                    last_snapshot = t0
                    dashboard.publish(board.snapshot(t0))
                    node.counters.publish(dashboard.counters.snapshot())  # refused requests, in health
                node.counters.publish(server.counters.snapshot())
                node.counters.publish(outlets.hub.counters.snapshot())
                for d in core.draw(t0, time.time_ns()):
                    if channels.wants(d.topic, d.message_type):
                        channels.log(d.topic, d.draw(), d.stamp_ns)
                node.counters.inc("draws")
                shutdown.wait(max(0.0, period_s - (time.monotonic() - t0)))
    finally:
        feeds.close()
        server.stop()
        if dashboard is not None:
            dashboard.stop()
        if recording is not None:
            recording.close()
            log.info("view recorded to %s", args.mcap)
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene YAML")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default: loopback only)")
    parser.add_argument(
        "--host-name",
        action="append",
        help="a name the dashboard is reached by besides loopback and --host (repeatable): other Host "
        "headers get 421, other Origins 403",
    )
    parser.add_argument("--port", type=int, default=8765, help="Foxglove WebSocket port (0: any free one)")
    parser.add_argument(
        "--allow-origin",
        action="append",
        help="a web app (scheme://name) allowed to open the Foxglove WebSocket besides the viewer's own "
        "names and https://app.foxglove.dev (repeatable)",
    )
    parser.add_argument(
        "--token-file",
        type=Path,
        default=RUN_DIR / "viewer.token",
        help="with --host beyond loopback: the token every request needs (made if missing)",
    )
    parser.add_argument("--mcap", type=Path, help="also write every channel into this MCAP file")
    parser.add_argument(
        "--dashboard-port", type=int, default=8080, help="browser dashboard's HTTP/WebSocket port (0: none)"
    )
    parser.add_argument(
        "--publish-hz", type=positive_float, default=10.0, help="most draws per second per channel"
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service(SERVICE, main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())
