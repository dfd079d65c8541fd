"""Live 3D view over the Foxglove WebSocket protocol (issue 18, first part): connect Foxglove or
Lichtblick to ws://127.0.0.1:8765 while the system runs.

    python -m services.viewer [--host 127.0.0.1] [--port 8765] [--publish-hz 10]

Channels (Foxglove protobuf schemas, drawn by `shared/viewer/scene.py`):
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
                            as they are, subscribed on the bus only while a client watches (`SensorFeeds`)
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

Cheap by default: nothing is drawn while no client subscribes (`Channel.has_sinks`), and at most
`--publish-hz` updates per channel are drawn, the newest of each stream (latest-wins queues). A slow or
gone client never slows the loop: the Foxglove server queues per client and drops what a client cannot
take. Binds to loopback unless told otherwise.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import queue
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import foxglove
import zenoh
from foxglove.websocket import ServerListener
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.message import Message
from rmmdet.v1 import perception_pb2 as pb
from rmmdet.v1.sensors_pb2 import RadarScan

from services.cli.health import Verdict, level_name, probe
from services.viewer.dashboard_server import DashboardServer
from services.viewer.ws_gate import OriginGate
from shared.bus.codec import Counters, MessageDecoder
from shared.bus.node import Node
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import SENSOR_STREAM, get_stream, limits
from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.service import run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime
from shared.traffic.messages import LatestRegionMaps
from shared.viewer.core import ViewerCore
from shared.viewer.dashboard import DashboardState
from shared.viewer.scene import image_annotations, radar_targets

log = logging.getLogger("services.viewer")

SERVICE = "viewer"
PLAN_QUEUE = 256  # pushed plans (or acks) between two draws (one per vehicle at most, normally)
OBJECT_QUEUE = 8  # object lists of one agent between two draws (all counted for its rate, the newest drawn)
REGION_MAP_QUEUE = 16  # region maps of a sharded coordinator between two draws (the newest per region kept)
HEALTH_EVERY_S = 2.0
# Nobody watching (no /health subscriber, no dashboard WebSocket or recent /api/state poll): health is
# probed and the dashboard's snapshot made this seldom (the first poll after a quiet spell may get a
# snapshot this old, its verdict up to twice; each says when it was taken).
IDLE_EVERY_S = 10.0
HEALTH_TIMEOUT_S = 1.0


def schema_of(message_type: type[Message]) -> foxglove.Schema:
    """The Foxglove protobuf schema of a message type: its name and a FileDescriptorSet of its file and
    every file it imports."""
    files: dict[str, bytes] = {}

    def add(fd) -> None:
        if fd.name in files:
            return
        for dep in fd.dependencies:
            add(dep)
        files[fd.name] = fd.serialized_pb

    add(message_type.DESCRIPTOR.file)
    fds = FileDescriptorSet()
    for data in files.values():
        fds.file.add().ParseFromString(data)
    return foxglove.Schema(
        name=message_type.DESCRIPTOR.full_name, encoding="protobuf", data=fds.SerializeToString()
    )


class Channels:
    """The viewer's Foxglove channels, made on first use (one per topic)."""

    def __init__(self, context: foxglove.Context) -> None:
        self._context = context
        self._channels: dict[str, foxglove.Channel] = {}

    def wants(self, topic: str, message_type: type[Message]) -> bool:
        """True if some client subscribes to `topic` (advertised from the first call on): draw only then."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = foxglove.Channel(
                topic, schema=schema_of(message_type), message_encoding="protobuf", context=self._context
            )
            self._channels[topic] = channel
        return channel.has_sinks()

    def log(self, topic: str, msg: Message, stamp_ns: int) -> None:
        self._channels[topic].log(msg.SerializeToString(), log_time=stamp_ns)


class SensorFeeds(ServerListener):
    """Camera images, lidar clouds and radar scans from the bus to the view, untouched (their payloads
    are Foxglove / rmmdet protobufs already), each camera's 2D detections as image annotations
    (`<camera topic>/detections`) and each radar's targets as spheres (`<radar topic>/targets`): a bus
    subscription exists only while some client subscribes to its channel, so an idle viewer costs
    nothing for them (and the MEC publishes no detections). A Foxglove ServerListener (its callbacks
    run on the server's threads; the bus callbacks on Zenoh's)."""

    def __init__(self, scene: Scene, context: foxglove.Context) -> None:
        self._counters: Counters | None = None
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()
        self._keys: dict[str, str] = {}  # topic -> bus key
        self._channels: dict[str, foxglove.Channel] = {}
        self._watchers: Counter[str] = Counter()
        self._subscribers: dict[str, Any] = {}
        # Topics drawn from a bus message rather than forwarded: its type and the drawing.
        self._convert: dict[str, tuple[type[Message], Callable[[Any, int], Message]]] = {}
        for spec in scene.spec.sensors:
            stream = get_stream(SENSOR_STREAM[spec.kind])
            topic = f"/agents/{spec.agent}/{spec.kind}/{spec.id}"
            self._add(context, topic, stream.key(agent=spec.agent, sensor=spec.id), stream.message_type)
            if spec.kind == "camera":
                key = get_stream("detections_2d").key(agent=spec.agent, sensor=spec.id)
                self._add(context, f"{topic}/detections", key, ImageAnnotations)
                self._convert[f"{topic}/detections"] = (pb.Detection2DArray, image_annotations)
            elif spec.kind == "radar":
                self._add(context, f"{topic}/targets", self._keys[topic], SceneUpdate)
                self._convert[f"{topic}/targets"] = (RadarScan, radar_targets)

    def _add(self, context: foxglove.Context, topic: str, key: str, message_type: type[Message]) -> None:
        self._keys[topic] = key
        self._channels[topic] = foxglove.Channel(
            topic, schema=schema_of(message_type), message_encoding="protobuf", context=context
        )

    def attach(self, session: zenoh.Session, counters: Counters) -> None:
        """The bus to subscribe on and the counters to count on (subscriptions asked for before are
        made now)."""
        with self._lock:
            self._session, self._counters = session, counters
            for topic, n in self._watchers.items():
                if n > 0 and topic not in self._subscribers:
                    self._subscribe(topic)

    def _subscribe(self, topic: str) -> None:
        assert self._session is not None and self._counters is not None
        channel, counters = self._channels[topic], self._counters
        if topic in self._convert:
            # Drawn from the bus message (2D detections: subscribing is what makes the MEC publish
            # them at all; radar targets: from the radar's own scans).
            message_type, drawing = self._convert[topic]
            decoder = MessageDecoder(message_type, counters)
            name = message_type.DESCRIPTOR.name

            def convert(sample: zenoh.Sample) -> None:
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                decoded = decoder.decode(sample.payload.to_bytes(), str(sample.encoding), attachment)
                if decoded is not None:
                    drawn = drawing(decoded.message, decoded.header.stamp.ToNanoseconds())
                    channel.log(drawn.SerializeToString(), log_time=time.time_ns())
                    counters.inc(f"drawn/{name}")

            self._subscribers[topic] = self._session.declare_subscriber(self._keys[topic], convert)
            return

        def forward(sample: zenoh.Sample) -> None:
            channel.log(sample.payload.to_bytes(), log_time=time.time_ns())
            counters.inc("forwarded/sensor")

        self._subscribers[topic] = self._session.declare_subscriber(self._keys[topic], forward)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            if channel.topic not in self._keys:
                return
            self._watchers[channel.topic] += 1
            if self._session is not None and channel.topic not in self._subscribers:
                self._subscribe(channel.topic)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._lock:
            if channel.topic not in self._keys or self._watchers[channel.topic] == 0:
                return
            self._watchers[channel.topic] -= 1
            if self._watchers[channel.topic] == 0 and (sub := self._subscribers.pop(channel.topic, None)):
                sub.undeclare()

    @property
    def topics(self) -> list[str]:
        """Every channel the feeds serve (sensor feeds and what is drawn from them)."""
        return sorted(self._channels)

    @property
    def subscribed(self) -> list[str]:
        """The topics subscribed on the bus right now."""
        with self._lock:
            return sorted(self._subscribers)

    def close(self) -> None:
        with self._lock:
            for sub in self._subscribers.values():
                sub.undeclare()
            self._subscribers.clear()


class HealthFeed:
    """`rmmdet health`'s verdict on the loop and every service's level as JSON on `/health` and for the
    dashboard: every HEALTH_EVERY_S while a client watches either, else every IDLE_EVERY_S; on its own
    thread (a probe waits for replies up to 1 s)."""

    TOPIC = "/health"

    def __init__(self, scene: Scene, context: foxglove.Context) -> None:
        self._scene = scene
        self._channel = foxglove.Channel(
            self.TOPIC, message_encoding="json", schema=HEALTH_SCHEMA, context=context
        )
        self.verdicts: queue.SimpleQueue[Verdict] = queue.SimpleQueue()  # for the dashboard

    def run(
        self, session: zenoh.Session, stop: threading.Event, watched: Callable[[], bool] = lambda: True
    ) -> None:
        last = -math.inf
        while not stop.wait(HEALTH_EVERY_S):
            now = time.monotonic()
            if not (self._channel.has_sinks() or watched()) and now - last < IDLE_EVERY_S:
                continue
            last = now
            verdict = probe(session, self._scene, timeout_s=HEALTH_TIMEOUT_S)
            self.verdicts.put(verdict)
            if self._channel.has_sinks():
                self._channel.log(health_json(verdict))


# What `/health` carries (health_json), as JSON Schema: viewers (Foxglove Studio 1.48) want a schema.
HEALTH_SCHEMA = foxglove.Schema(
    name="rmmdet.Health",
    encoding="jsonschema",
    data=json.dumps(
        {
            "type": "object",
            "properties": {
                "loop_ok": {"type": "boolean"},
                "summary": {"type": "string"},
                "services": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "properties": {
                            "service": {"type": "string"},
                            "level": {"type": "string"},
                            "message": {"type": "string"},
                            "loop_age_s": {"type": "number"},
                        },
                    },
                },
            },
        }
    ).encode(),
)


def health_json(verdict: Verdict) -> dict[str, Any]:
    """The verdict as the `/health` channel carries it."""
    return {
        "loop_ok": verdict.ok,
        "summary": verdict.summary(),
        "services": [
            {
                "service": f"{r.service}/{r.instance}",
                "level": level_name(r.level),
                "message": r.message,
                "loop_age_s": round(r.loop_age_s, 3),
            }
            for r in sorted(verdict.reports, key=lambda r: (r.service, r.instance))
        ],
    }


def start_view_server(
    context: foxglove.Context,
    feeds: SensorFeeds,
    host: str,
    port: int,
    host_names: Iterable[str] = (),
    origins: Iterable[str] = (),
) -> tuple[foxglove.WebSocketServer, OriginGate]:
    """The Foxglove WebSocket server of `context`'s channels, the sensor feeds listening to who
    subscribes, on a loopback port of its own, and the gate that serves it on `host:port` to the
    viewer's own names and Foxglove's web app only (services/viewer/ws_gate.py; port 0: any free one)."""
    inner = foxglove.start_server(
        name="rmmdet", host="127.0.0.1", port=0, context=context, server_listener=feeds
    )
    try:
        gate = OriginGate(host, port, inner.port, host_names, origins)
    except (OSError, RuntimeError):
        inner.stop()
        raise
    gate.start()
    return inner, gate


def map_of(scene: Scene, network: RoadNetwork) -> dict[str, Any]:
    """The dashboard's static map: every lane's centreline (x, y) and every junction's number."""
    return {
        "lanes": [
            {"id": lane_id, "points": [[round(float(p[0]), 3), round(float(p[1]), 3)] for p in path.points]}
            for lane_id, path in network.lanes.items()
        ],
        "junctions": [
            {"id": j.id, "number": j.number, "x": j.position_m[0], "y": j.position_m[1]}
            for j in scene.spec.junctions
        ],
    }


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    scene = Scene.load(args.scene)
    network = RoadNetwork(scene)
    context = foxglove.Context()
    feeds = SensorFeeds(scene, context)
    try:  # a port in use is a clear one-line exit, not a traceback
        dashboard = (
            DashboardServer(args.host, args.dashboard_port, map_of(scene, network), args.host_name or ())
            if args.dashboard_port
            else None
        )
        server, gate = start_view_server(
            context, feeds, args.host, args.port, args.host_name or (), args.allow_origin or ()
        )
    except (OSError, RuntimeError) as err:
        raise SystemExit(
            f"viewer: cannot serve on {args.host} ports {args.port}/{args.dashboard_port}: {err}"
        ) from None
    recording = foxglove.open_mcap(args.mcap, allow_overwrite=True, context=context) if args.mcap else None
    log.info("Foxglove WebSocket server on ws://%s:%d", args.host, gate.port)
    if dashboard is not None:
        dashboard.start()
        log.info("dashboard on http://%s:%d/", args.host, dashboard.port)
    channels = Channels(context)
    period_s = 1.0 / args.publish_hz
    try:
        with Node(conf, service=SERVICE, instance=args.instance, scope="site", stop=shutdown.event) as node:
            feeds.attach(node.session, node.counters)
            health_feed = HealthFeed(scene, context)

            def watched() -> bool:
                return dashboard is not None and dashboard.watched

            health = threading.Thread(
                target=health_feed.run, args=(node.session, shutdown.event, watched), daemon=True
            )
            health.start()
            clock = SimTime()  # stamps ahead of the clock of record are refused (`rejected/future`)
            node.follow_sim_time(clock)
            stamped = {"clock_s": clock.now_s, "max_future_s": limits().max_clock_skew_s}
            objects = {
                a: node.subscribe_stream("objects", agent=a, maxsize=OBJECT_QUEUE, **stamped)
                for a in scene.agents
            }
            acks = node.subscribe_stream("route_ack", maxsize=PLAN_QUEUE, **stamped)
            ground_truth = node.subscribe_stream("ground_truth", maxsize=1, **stamped)
            traffic = node.subscribe_stream("traffic_map", maxsize=1, **stamped)
            # A sharded coordinator's region maps (make up SHARDS=2), drawn merged.
            region_maps = node.subscribe_stream("region_map", maxsize=REGION_MAP_QUEUE, **stamped)
            regions = LatestRegionMaps()
            plans = node.subscribe_stream(
                "route_plan",
                queue=BoundedQueue(PLAN_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/plans"),
                **stamped,
            )
            served = node.subscribe_stream(  # plans vehicles asked for (the coordinator copies them)
                "route_plan_served",
                queue=BoundedQueue(
                    PLAN_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/served_plans"
                ),
                **stamped,
            )
            core = ViewerCore(scene, network)
            for topic, message_type in core.topics().items():
                channels.wants(topic, message_type)  # advertised now, before any client connects
            board = DashboardState(list(scene.agents))
            last_snapshot = -math.inf
            while not shutdown.requested:
                node.health.beat()
                t0 = time.monotonic()
                for agent, sub in objects.items():
                    items = sub.drain()
                    for item in items:
                        board.on_objects(agent, item.message, t0)
                    for item in items[-1:]:
                        core.on_tracks(agent, item.message, item.header.stamp.ToNanoseconds())
                for item in ground_truth.drain()[-1:]:
                    core.on_ground_truth(item.message, item.header.stamp.ToNanoseconds())
                    board.on_ground_truth(item.message)
                for item in plans.drain():
                    core.on_plan(item.message, t0)
                    board.on_plan(item.message)
                for item in served.drain():
                    core.on_plan(item.message, t0)
                    board.on_plan(item.message, served=True)
                for item in acks.drain():
                    board.on_ack(item.message)
                for item in traffic.drain()[-1:]:
                    core.on_traffic_map(item.message, item.header.stamp.ToNanoseconds())
                    board.on_traffic_map(item.message)
                arrived = region_maps.drain()
                for item in arrived:
                    regions.put(item.key, item.message, item.header.stamp.ToNanoseconds(), t0)
                if arrived and (merged := regions.merged(t0)) is not None:
                    core.on_traffic_map(*merged)
                    board.on_traffic_map(merged[0])
                while not health_feed.verdicts.empty():
                    verdict = health_feed.verdicts.get()
                    board.on_health(verdict.ok, verdict.summary(), verdict.problems)
                if dashboard is not None and (dashboard.watched or t0 - last_snapshot >= IDLE_EVERY_S):
                    last_snapshot = t0
                    dashboard.publish(board.snapshot(t0))
                    node.counters.publish(dashboard.counters.snapshot())  # refused requests, in health
                node.counters.publish(gate.counters.snapshot())
                for d in core.draw(t0, time.time_ns()):
                    if channels.wants(d.topic, d.message_type):
                        channels.log(d.topic, d.draw(), d.stamp_ns)
                node.counters.inc("draws")
                shutdown.wait(max(0.0, period_s - (time.monotonic() - t0)))
    finally:
        feeds.close()
        gate.stop()
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
    parser.add_argument("--mcap", type=Path, help="also write every channel into this MCAP file")
    parser.add_argument(
        "--dashboard-port", type=int, default=8080, help="browser dashboard's HTTP/WebSocket port (0: none)"
    )
    parser.add_argument("--publish-hz", type=positive, default=10.0, help="most draws per second per channel")


def positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def cli(argv: list[str] | None = None) -> int:
    return run_service(SERVICE, main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    sys.exit(cli())
