"""MEC (edge) service: one agent's detection, fusion and tracking.

    python -m services.mec --instance agent1

Subscribes to every sensor of the agent (`rmmdet/@v1/<agent>/sensor/<kind>/<id>`) into one queue,
joins the frames of one sim tick (`TickJoiner`: waits at most `sync.max_wait_s` of sim time, and only
for inputs that are alive and due), decodes them, runs `AgentPipeline` (detectors, radar-camera and
lidar-camera fusion, tracker) and publishes `rmmdet.v1.TrackedObjects` on `rmmdet/@v1/<agent>/objects`
with the tick's stamp, the FULL / DEGRADED status, the state of every input and per-stage latencies.

While a lidar is live the camera detector runs on every `detectors.camera_every_n_with_lidar`-th frame
only; under a sim the MEC asks its cameras for just those frames (`capture_demand`, renewed every
second) and neither waits for nor decodes the others.

A sensor that stops is MISSING after 3 of its periods; output continues from the other inputs, flagged
DEGRADED with that input named, and returns to FULL after `health.recover_frames` complete frames.
Frames older than `health.max_age_s` on arrival are dropped and counted as stale. If processing falls
behind, only the newest ready frame is processed (latest-wins) and the skipped ones are counted.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections import Counter
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from queue import SimpleQueue

import numpy as np
import zenoh
from rmmdet.v1.sensors_pb2 import CaptureDemand

from shared.bus.health import CRITICAL, DEGRADED, NOMINAL
from shared.bus.liveliness import LivelinessMonitor, source_of_token
from shared.bus.node import Node, Received, processing_stamp
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import SENSOR_STREAM, get_stream, sensor_group_source
from shared.config import load_settings
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.perception.decode import FrameDecoder
from shared.perception.inputs import SensorMonitor, Status, StatusHysteresis
from shared.perception.output import tracked_objects_message
from shared.perception.pipeline import AgentInputs, AgentPipeline
from shared.perception.sync import JoinedFrame, Sample, TickJoiner
from shared.scene.scene import Scene
from shared.service import run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime
from sim.config import DEFAULT_SCENE

log = logging.getLogger("services.mec")

QUEUE_PER_SENSOR = 4  # latest-wins: a few frames per sensor, oldest dropped
IDLE_WAIT_S = 0.1
DEMAND_RENEW_S = 1.0  # capture demand: renewed this often ...
DEMAND_VALID_S = 3.0  # ... and lapses (cameras back to every frame) if the MEC is gone this long
ERROR_LOG_EVERY = 100  # log the first pipeline error, then every 100th


@dataclass(frozen=True)
class Ahead:
    """A camera image decoded and detected on arrival, before its tick's frame was complete."""

    stamp_ns: int
    image: np.ndarray
    seconds: float  # decode + detection


def decode_frame(
    frame: JoinedFrame,
    kinds: Mapping[str, str],
    counters: Counter[str],
    decoder: FrameDecoder,
    cameras: Collection[str] | None = None,
    ahead: Mapping[str, Ahead] | None = None,
) -> tuple[AgentInputs, set[str]]:
    """Decode the joined messages; a frame that does not decode is left out and counted. Only the
    images of `cameras` (default all) are decoded: the pipeline will not look at the others this frame;
    an image already decoded on arrival (`ahead`, same stamp) is taken as it is.
    Returns the inputs and the sensors that delivered a usable (or unneeded) frame."""
    inputs = AgentInputs(stamp_ns=frame.stamp_ns, tick=frame.tick)
    delivered = set()
    for sensor_id, sample in frame.samples.items():
        kind = kinds[sensor_id]
        if kind == "camera" and cameras is not None and sensor_id not in cameras:
            delivered.add(sensor_id)
            continue
        early = (ahead or {}).get(sensor_id)
        if early is not None and early.stamp_ns == sample.stamp_ns:
            inputs.add(kind, sensor_id, early.image)
            delivered.add(sensor_id)
            continue
        try:
            inputs.add(kind, sensor_id, decoder.decode(kind, sensor_id, sample.data))
            delivered.add(sensor_id)
        except ValueError as err:
            counters[f"rejected/{kind}_decode"] += 1
            log.debug("%s frame rejected: %s", sensor_id, err)
    return inputs, delivered


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    scene = Scene.load(args.scene)
    agent = args.instance
    if agent not in scene.agents:
        raise SystemExit(f"unknown agent {agent!r}: scene has {sorted(scene.agents)}")
    overrides = {}
    if args.camera_detector or args.lidar_detector:
        overrides["detectors"] = {
            k: v for k, v in (("camera", args.camera_detector), ("lidar", args.lidar_detector)) if v
        }
    settings = load_settings(MecSettings, args.settings, **overrides)
    specs = scene.sensors_of(agent)
    if args.sensors:
        wanted = set(args.sensors.split(","))
        unknown = wanted - {s.id for s in specs}
        if unknown:
            raise SystemExit(f"--sensors: {sorted(unknown)} are not sensors of {agent}")
        specs = [s for s in specs if s.id in wanted]
    kinds = {s.id: s.kind for s in specs}
    t0 = time.perf_counter()
    pipeline = AgentPipeline(scene, agent, settings, sensor_ids=list(kinds))
    log.info("agent %s: %d sensors, pipeline ready in %.2f s", agent, len(specs), time.perf_counter() - t0)

    with Node(conf, service="mec", instance=agent, scope=agent, stop=shutdown.event) as node:
        objects_pub = node.publisher("objects", agent=agent, source_id=f"{agent}/mec")
        queue: BoundedQueue[Received] = BoundedQueue(
            QUEUE_PER_SENSOR * len(specs), OverflowPolicy.DROP_OLDEST
        )
        # No expected rate on the bus-level monitors: a missing sensor makes this MEC DEGRADED (its
        # status below names it), not CRITICAL; the rates are still reported per input.
        for s in specs:
            node.subscribe_stream(SENSOR_STREAM[s.kind], agent=agent, sensor=s.id, queue=queue)
        # Input health is judged on the clock of record (sim time when a sim runs): a slow host slows
        # the sim, not the verdict. The monitor starts afresh when the sim clock is first heard.
        sim_time = SimTime()
        node.follow_sim_time(sim_time)

        camera_ids = frozenset(s.id for s in specs if s.kind == "camera")
        demand_pub = node.publisher("capture_demand", agent=agent, kind="camera") if camera_ids else None
        cadence = {"every_n": 1, "sent_s": -DEMAND_RENEW_S}

        def rates_hz() -> dict[str, float]:
            """Expected input rates: cameras at the cadence asked of them."""
            return {s.id: s.rate_hz / (cadence["every_n"] if s.id in camera_ids else 1) for s in specs}

        def new_monitor() -> SensorMonitor:
            return SensorMonitor(
                rates_hz(),
                settings.health.missing_after_periods,
                settings.health.max_age_s,
                start_s=sim_time.now_s(),
            )

        monitor = new_monitor()
        # A sensor service that leaves the bus (killed, crashed) takes its sensors with it at once: its
        # presence token vanishes long before 3 periods (3 s) of a camera asked for every 10th frame.
        groups = {
            sensor_group_source(agent, k): [s.id for s in specs if s.kind == k] for k in set(kinds.values())
        }
        gone: SimpleQueue[str] = SimpleQueue()
        presence = LivelinessMonitor(
            node.session,
            get_stream("alive").pattern(scope=agent, service="sensor"),
            on_change=lambda key, alive: None if alive else gone.put(key),
        )
        node.adopt(presence)
        following = sim_time.following
        decoder = FrameDecoder()

        def new_joiner() -> TickJoiner:
            return TickJoiner(kinds, settings.sync.max_wait_s, settings.sync.max_pending_ticks)

        joiner = new_joiner()
        ahead: dict[str, Ahead] = {}  # camera -> its newest image, decoded and detected on arrival
        status = StatusHysteresis(settings.health.recover_frames)
        counters: Counter[str] = Counter()
        last_status = Status.FULL
        last_tick = -1

        def update_cadence(alive: Collection[str], now: float) -> None:
            """Under a sim: ask the cameras for the frames the detector will run on (renewed every
            DEMAND_RENEW_S, at once on a change) and expect them at that rate."""
            pipeline.tick_hz = sim_time.tick_hz
            if demand_pub is None or pipeline.tick_hz is None:
                return
            every_n = pipeline.camera_every_n(pipeline.lidar_live(alive))
            changed = every_n != cadence["every_n"]
            reason = "lidar live" if every_n > 1 else "no lidar"
            if changed or now - cadence["sent_s"] >= DEMAND_RENEW_S:
                demand_pub.put(CaptureDemand(every_n=every_n, valid_for_s=DEMAND_VALID_S, reason=reason))
                cadence["sent_s"] = now
            if changed:
                log.info("cameras: every %d frame(s) (%s)", every_n, reason)
                cadence["every_n"] = every_n
                for sensor_id, rate_hz in rates_hz().items():
                    monitor.set_rate(sensor_id, rate_hz)

        def expected(alive: Collection[str]) -> Callable[[int], Collection[str]]:
            """The inputs a tick waits for: the live ones, less the cameras not due on it."""
            live = frozenset(alive)
            lidar_live = pipeline.lidar_live(live)
            return lambda tick: live - (camera_ids - pipeline.cameras_due(lidar_live, tick))

        def health() -> tuple[int, str]:
            now = sim_time.now_s()
            bad = [f"{r.sensor_id}: {r.state.value}" for r in monitor.report(now) if r.state.value != "ok"]
            level = {Status.FULL: NOMINAL, Status.DEGRADED: DEGRADED}.get(status.status, CRITICAL)
            text = (
                f"{status.status.value}, tick {last_tick}, {counters['frames/published']} frames, "
                f"cameras every {cadence['every_n']} frame(s)"
            )
            return level, text + (f"; {', '.join(bad)}" if bad else "")

        node.health.set_status(health)
        last_log = time.monotonic()
        while not shutdown.requested:
            # The join waits on the clock of record: a sim held back by a slow consumer holds the
            # wait too, so an input late only because the host is busy is not dropped.
            deadline = joiner.next_deadline_s()
            clock_s = sim_time.now_s()
            if deadline is None:
                wait = IDLE_WAIT_S
            else:
                wait = min(IDLE_WAIT_S, max(0.0, (deadline - clock_s) / sim_time.speed))
            received = queue.get(timeout=wait)
            items = ([received] if received is not None else []) + queue.drain()
            ready: list[JoinedFrame] = []
            now = time.monotonic()
            if sim_time.following != following:
                following = sim_time.following
                monitor = new_monitor()
                joiner = new_joiner()  # its pending ticks were timed on the other clock
            clock_s = sim_time.now_s()
            while not gone.empty():
                for sensor_id in groups.get(source_of_token(gone.get_nowait()) or "", []):
                    monitor.mark_gone(sensor_id)
                    log.warning("%s: its sensor service left the bus", sensor_id)
            update_cadence(monitor.alive(clock_s), now)
            newest_images: dict[str, Sample] = {}
            for item in items:
                sensor_id = item.key.rsplit("/", 1)[-1]
                if sensor_id not in kinds:
                    counters["rejected/unknown_sensor"] += 1
                    continue
                stamp_ns = item.header.stamp.ToNanoseconds()
                # Staleness is judged at arrival (sensor + transport lag), not after our own backlog.
                arrival_ns = sim_time.now_ns(item.received_wall_ns)
                if not monitor.accept(sensor_id, stamp_ns, clock_s, arrival_ns):
                    counters[f"stale/{sensor_id}"] += 1
                    node.counters.inc("rejected/stale")
                    continue
                sample = Sample(sensor_id, stamp_ns, item.message, item.header.tick, clock_s)
                ready += joiner.add(sample, expected(monitor.alive(clock_s)), clock_s)
                if sensor_id in camera_ids:
                    newest_images[sensor_id] = sample
            alive = monitor.alive(clock_s)
            # A camera group publishes its images one after another: detect each as it comes instead
            # of all of them after the last one, so the frame is done soon after it is complete.
            lidar_live = pipeline.lidar_live(alive)
            for sensor_id, sample in newest_images.items():
                if sensor_id in pipeline.cameras_due(lidar_live, sample.tick):
                    t_ahead = time.perf_counter()
                    try:
                        image = decoder.image(sensor_id, sample.data)
                    except ValueError:
                        continue  # rejected and counted when its frame is decoded
                    pipeline.detect_ahead(sensor_id, image)
                    ahead[sensor_id] = Ahead(sample.stamp_ns, image, time.perf_counter() - t_ahead)
            ready += joiner.poll(expected(alive), clock_s)
            if not ready:
                continue
            if len(ready) > 1:
                counters["frames/skipped"] += len(ready) - 1
                node.counters.inc("frames/skipped", len(ready) - 1)
            frame = ready[-1]
            start_ns = time.time_ns()
            due = pipeline.cameras_due(pipeline.lidar_live(frame.samples), frame.tick)
            inputs, delivered = decode_frame(frame, kinds, counters, decoder, due, ahead)
            ahead_s = sum(
                a.seconds for c, a in ahead.items() if c in frame.samples and a.stamp_ns == frame.stamp_ns
            )
            decoded_ns = time.time_ns()
            try:
                result = pipeline.process(inputs)
            except Exception:  # a bug on one frame must not take the agent's perception down
                counters["errors/pipeline"] += 1
                node.counters.inc("errors/pipeline")
                if counters["errors/pipeline"] == 1 or counters["errors/pipeline"] % ERROR_LOG_EVERY == 0:
                    log.exception("frame %d failed (%d so far)", frame.tick, counters["errors/pipeline"])
                continue
            result.latencies_s = {
                "detect_2d_ahead": ahead_s,
                "decode": (decoded_ns - start_ns) / 1e9,
                **result.latencies_s,
            }
            now = time.monotonic()
            # A camera not due on this tick is fine while it is alive at its own cadence.
            waited = expected(alive)(frame.tick)
            fused = {s: s in delivered or (s in alive and s not in waited) for s in kinds}
            state = status.update(fused)
            if state is not last_status:
                missing = sorted(s for s, ok in fused.items() if not ok)
                log.warning(
                    "status %s -> %s (missing: %s)", last_status.value, state.value, missing or "none"
                )
                last_status = state
            msg = tracked_objects_message(result, agent, state, monitor.report(sim_time.now_s()), kinds)
            header = objects_pub.next_header(stamp_ns=frame.stamp_ns, tick=frame.tick, frame_id="world")
            stages = [processing_stamp("mec/process", start_ns, time.time_ns())]
            objects_pub.put(msg, header, stages=stages)
            counters["frames/published"] += 1
            last_tick = frame.tick
            now = time.monotonic()
            if now - last_log >= settings.report_interval_s:
                log.info(
                    "%d frames published, status %s, %d tracks, counters %s",
                    counters["frames/published"],
                    state.value,
                    len(result.tracks),
                    dict(
                        counters
                        + pipeline.counts
                        + Counter({f"late/{k}": v for k, v in joiner.late_by_sensor.items()})
                    ),
                )
                last_log = now
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene YAML")
    parser.add_argument("--settings", type=Path, default=DEFAULT_MEC_CONFIG, help="MEC settings YAML")
    parser.add_argument(
        "--sensors", help="comma-separated subset of the agent's sensors to fuse (default all)"
    )
    parser.add_argument("--camera-detector", help="override detectors.camera (onnx | oracle)")
    parser.add_argument("--lidar-detector", help="override detectors.lidar (pointpillars | cluster | oracle)")


def cli(argv: list[str] | None = None) -> int:
    return run_service("mec", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    sys.exit(cli())
