"""One agent's edge perception as a bus-free core: what the MEC service runs and the studies drive.

    core = MecCore(scene, "agent1", settings)
    core.receive(sensor_id, stamp_ns, tick, message, now_s, arrival_ns)   # every sensor message
    out = core.step(now_s)                                                 # a processed frame or None

`MecCore` owns every decision between a sensor message and a `TrackedObjects` message:
- input health (`SensorMonitor`): frames older than `health.max_age_s` on arrival are dropped and
  counted as stale; a sensor that stops is MISSING after `health.missing_after_periods` of its periods,
  at once if its process left (`mark_gone`);
- the join of one agent frame (`sync.collector`): `TickJoiner` on the sim tick, waiting at most
  `sync.max_wait_s` and only for the inputs alive and due; or `BoundedWaitCollector` for asynchronous
  real sensors, triggered by `sync.trigger` with the others joined by nearest stamp within
  `sync.tolerance_s`;
- the camera cadence: with a lidar live the camera detector runs on every
  `detectors.camera_every_n_with_lidar`-th frame (`cadence` says what to ask the cameras for);
- decoding, with each due camera image decoded and detected on arrival (`detect_2d_ahead`) rather
  than after the last sensor of its frame;
- `AgentPipeline` (detect, fuse, track); latest-wins when behind (skipped frames counted);
- the FULL / DEGRADED / UNAVAILABLE status with hysteresis and the output message.

Times: `now_s` on the clock of record (sim time under a sim, else the wall clock), stamps and
`arrival_ns` in ns on that clock. The caller owns the bus: subscriptions, presence, capture demand.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
from rmmdet.v1.perception_pb2 import TrackedObjects

from shared.bus.health import CRITICAL, DEGRADED, NOMINAL
from shared.bus.ordering import reset_after_ticks
from shared.detection.interface import CameraDetector, LidarDetector
from shared.perception.config import MecSettings
from shared.perception.decode import FrameDecoder, max_cloud_points
from shared.perception.inputs import InputState, SensorMonitor, Status, StatusHysteresis
from shared.perception.output import tracked_objects_message
from shared.perception.pipeline import AgentInputs, AgentPipeline, AgentResult
from shared.perception.sync import BoundedWaitCollector, JoinedFrame, Sample, TickJoiner
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S

log = logging.getLogger(__name__)

ERROR_LOG_EVERY = 100  # log the first pipeline error, then every 100th


@dataclass(frozen=True)
class Ahead:
    """A camera image decoded and detected on arrival, before its frame was complete."""

    stamp_ns: int
    image: np.ndarray
    seconds: float  # decode + detection


@dataclass
class MecOutput:
    """One processed agent frame."""

    frame: JoinedFrame
    inputs: AgentInputs
    result: AgentResult
    status: Status
    message: TrackedObjects
    fused: dict[str, bool] = field(default_factory=dict)  # per input: delivered (or not due) this frame
    skipped: int = 0  # older ready frames skipped for this one (latest wins)
    started_ns: int = 0  # wall clock when the frame's own work began (decode), for processing stamps


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


def default_trigger(kinds: Mapping[str, str]) -> str:
    """The sensor that starts an asynchronous frame: the first lidar, else radar, else camera."""
    for kind in ("lidar", "radar", "camera"):
        for sensor_id, k in kinds.items():
            if k == kind:
                return sensor_id
    raise ValueError("an agent without sensors has no trigger")


class MecCore:
    """Input health, join, cadence, decode, pipeline, status and output message of one agent.

    Parameters
    ----------
    scene, agent_id, settings
        The agent and its MEC settings.
    sensor_ids : collection of str, optional
        Fuse only these of the agent's sensors (default all).
    cameras, lidar : detectors, optional
        Injected detectors (tests, oracles); default the ones `settings.detectors` names.
    now_s : float
        Clock of record at start (the input monitor's grace starts here).
    """

    def __init__(
        self,
        scene: Scene,
        agent_id: str,
        settings: MecSettings,
        sensor_ids: Collection[str] | None = None,
        cameras: CameraDetector | None = None,
        lidar: LidarDetector | None = None,
        now_s: float = 0.0,
    ) -> None:
        specs = [s for s in scene.sensors_of(agent_id) if sensor_ids is None or s.id in sensor_ids]
        unknown = set(sensor_ids or ()) - {s.id for s in specs}
        if unknown:
            raise ValueError(f"{sorted(unknown)} are not sensors of {agent_id}")
        self.agent_id = agent_id
        settings = settings.for_site(scene, agent_id)  # at the scene's scale, its sizes filled in
        self.settings = settings
        self.kinds = {s.id: s.kind for s in specs}
        self._scene, self._specs = scene, specs
        self._rates_hz = {s.id: s.rate_hz for s in specs}
        self.camera_ids = frozenset(s.id for s in specs if s.kind == "camera")
        self.pipeline = AgentPipeline(
            scene, agent_id, settings, cameras=cameras, lidar=lidar, sensor_ids=list(self.kinds)
        )
        self.decoder = FrameDecoder(
            image_sizes={
                s.id: (s.camera.width_px, s.camera.height_px) for s in specs if s.camera is not None
            },
            max_points={
                s.id: max_cloud_points(s.lidar.channels, s.lidar.horizontal_samples)
                for s in specs
                if s.lidar is not None
            },
        )
        self.status = StatusHysteresis(settings.health.recover_frames)
        self.counters: Counter[str] = Counter()
        self.every_n = 1  # camera cadence asked for and expected
        self.last_tick = -1
        self._ahead: dict[str, Ahead] = {}  # camera -> its newest image, decoded and detected on arrival
        self._ready: list[JoinedFrame] = []
        self._newest_images: dict[str, Sample] = {}
        self.reset(now_s)

    # --- clock and inputs -----------------------------------------------------------------------

    @property
    def tick_hz(self) -> float | None:
        return self.pipeline.tick_hz

    @tick_hz.setter
    def tick_hz(self, hz: float | None) -> None:
        """The sim's tick rate (None with real sensors): the camera cadence follows the ticks."""
        self.pipeline.tick_hz = hz
        if hz is not None and isinstance(self._joiner, TickJoiner):
            self._joiner.reset_after_ticks = reset_after_ticks(hz)

    def reset(self, now_s: float) -> None:
        """Start the input monitor and the join afresh (the clock of record changed: their times were
        on the other clock)."""
        self.monitor = SensorMonitor(
            self.rates_hz(), self.settings.health.missing_after_periods, self.settings.health.max_age_s, now_s
        )
        sync = self.settings.sync
        if sync.collector == "tick":
            self._joiner: TickJoiner | BoundedWaitCollector = TickJoiner(
                self.kinds,
                sync.max_wait_s,
                sync.max_pending_ticks,
                reset_after_ticks(self.tick_hz),
                sync.min_wait_s,
                sync.wait_factor,
                frame_tick=lambda tick, tick_hz: any(
                    self._scene.captures_on(spec, tick, tick_hz) for spec in self._specs
                ),
            )
        else:
            trigger = sync.trigger or default_trigger(self.kinds)
            if trigger not in self.kinds:
                raise ValueError(f"sync.trigger {trigger!r} is not a sensor of {self.agent_id}")
            others = {s: sync.max_wait_s for s in self.kinds if s != trigger}
            self._joiner = BoundedWaitCollector(trigger, others, sync.tolerance_s)
        self._ready.clear()

    def rates_hz(self) -> dict[str, float]:
        """Expected input rates, Hz: cameras at the cadence asked of them."""
        return {s: r / (self.every_n if s in self.camera_ids else 1) for s, r in self._rates_hz.items()}

    def mark_gone(self, sensor_id: str) -> None:
        """`sensor_id`'s process left: MISSING at once (unknown ids are ignored)."""
        if sensor_id in self.kinds:
            self.monitor.mark_gone(sensor_id)

    def cadence(self, now_s: float) -> tuple[int, bool]:
        """Every how many frames the cameras are needed now, and whether that changed (the expected
        camera rates follow). Only under a sim (`tick_hz` known) are cameras asked for less."""
        if self.tick_hz is None or not self.camera_ids:
            return self.every_n, False
        every_n = self.pipeline.camera_every_n(self.pipeline.lidar_live(self.monitor.alive(now_s)))
        if every_n == self.every_n:
            return every_n, False
        self.every_n = every_n
        for sensor_id, rate_hz in self.rates_hz().items():
            self.monitor.set_rate(sensor_id, rate_hz, now_s)
        return every_n, True

    def expected(self, alive: Collection[str]) -> Callable[[int], Collection[str]]:
        """The inputs a tick waits for: the live ones, less the cameras not due on it."""
        live = frozenset(alive)
        lidar_live = self.pipeline.lidar_live(live)
        return lambda tick: live - (self.camera_ids - self.pipeline.cameras_due(lidar_live, tick))

    def receive(
        self,
        sensor_id: str,
        stamp_ns: int,
        tick: int,
        message: object,
        now_s: float,
        arrival_ns: int,
        epoch: int = 0,
    ) -> str | None:
        """One sensor message; the reason it was rejected ("unknown_sensor", "stale"; counted), or None."""
        if sensor_id not in self.kinds:
            self.counters["rejected/unknown_sensor"] += 1
            return "unknown_sensor"
        # Staleness is judged at arrival (sensor + transport lag), not after our own backlog.
        if not self.monitor.accept(sensor_id, stamp_ns, now_s, arrival_ns):
            self.counters[f"stale/{sensor_id}"] += 1
            return "stale"
        sample = Sample(sensor_id, stamp_ns, message, tick, arrival_ns / NS_PER_S, epoch)
        if isinstance(self._joiner, TickJoiner):
            self._ready += self._joiner.add(sample, self.expected(self.monitor.alive(now_s)), now_s)
        else:
            self._ready += self._joiner.add(sample, now_s)
        if sensor_id in self.camera_ids:
            self._newest_images[sensor_id] = sample
        return None

    def wait_s(self, now_s: float, speed: float, idle_s: float) -> float:
        """Wall seconds to wait for input before the next `step`: until the first pending frame times
        out (`now_s` and the deadline on the clock of record, which runs at `speed`), at most `idle_s`."""
        deadline = self.next_deadline_s(now_s)
        return idle_s if deadline is None else min(idle_s, max(0.0, (deadline - now_s) / speed))

    def next_deadline_s(self, now_s: float) -> float | None:
        """When the first pending frame times out (None if none pending), on the clock of record."""
        if isinstance(self._joiner, TickJoiner):
            return self._joiner.next_deadline_s(self.expected(self.monitor.alive(now_s)), self.tick_hz)
        return None

    # --- one frame ------------------------------------------------------------------------------

    def _detect_arrivals(self, alive: Collection[str]) -> None:
        """A camera group publishes its images one after another: detect each as it comes instead of
        all of them after the last one, so the frame is done soon after it is complete."""
        lidar_live = self.pipeline.lidar_live(alive)
        for sensor_id, sample in self._newest_images.items():
            if sensor_id not in self.pipeline.cameras_due(lidar_live, sample.tick):
                continue
            t0 = time.perf_counter()
            try:
                image = self.decoder.image(sensor_id, sample.data)
            except ValueError:
                continue  # rejected and counted when its frame is decoded
            try:
                self.pipeline.detect_ahead(sensor_id, image)
            except Exception:  # a detector bug: the frame's own detection meets it again, counted there
                self.counters["errors/detect_ahead"] += 1
                if self.counters["errors/detect_ahead"] % ERROR_LOG_EVERY == 1:
                    log.exception("%s: detection on arrival failed", sensor_id)
                continue
            self._ahead[sensor_id] = Ahead(sample.stamp_ns, image, time.perf_counter() - t0)
        self._newest_images.clear()

    def step(self, now_s: float) -> MecOutput | None:
        """Process the newest ready frame (older ready ones are skipped, counted); None if none is ready
        or the pipeline failed on it (counted, logged)."""
        alive = self.monitor.alive(now_s)
        self._detect_arrivals(alive)
        if isinstance(self._joiner, TickJoiner):
            self._ready += self._joiner.poll(self.expected(alive), now_s, self.tick_hz)
        else:
            self._ready += self._joiner.poll(now_s)
        if not self._ready:
            return None
        frame, skipped = self._ready[-1], len(self._ready) - 1
        self._ready.clear()
        if skipped:
            self.counters["frames/skipped"] += skipped
        started_ns = time.time_ns()
        t0 = time.perf_counter()
        due = self.pipeline.cameras_due(self.pipeline.lidar_live(frame.samples), frame.tick)
        inputs, delivered = decode_frame(frame, self.kinds, self.counters, self.decoder, due, self._ahead)
        ahead_s = sum(
            a.seconds for c, a in self._ahead.items() if c in frame.samples and a.stamp_ns == frame.stamp_ns
        )
        decode_s = time.perf_counter() - t0
        try:
            result = self.pipeline.process(inputs)
        except Exception:  # a bug on one frame must not take the agent's perception down
            self.counters["errors/pipeline"] += 1
            n = self.counters["errors/pipeline"]
            if n == 1 or n % ERROR_LOG_EVERY == 0:
                log.exception("frame %d failed (%d so far)", frame.tick, n)
            return None
        result.latencies_s = {"detect_2d_ahead": ahead_s, "decode": decode_s, **result.latencies_s}
        # A camera not due on this frame is fine while it is alive at its own cadence.
        waited = self.expected(alive)(frame.tick) if isinstance(self._joiner, TickJoiner) else self.kinds
        fused = {s: s in delivered or (s in alive and s not in waited) for s in self.kinds}
        before = self.status.status
        state = self.status.update(fused)
        if state is not before:
            missing = sorted(s for s, ok in fused.items() if not ok)
            log.warning("status %s -> %s (missing: %s)", before.value, state.value, missing or "none")
        self.counters[f"status/{state.value}"] += 1
        # An input left out of this frame (it did not arrive in its wait) is named MISSING in it even
        # before the monitor's missing_after_periods: the frame's status is DEGRADED because of it.
        reports = [
            r if fused[r.sensor_id] or r.state is not InputState.OK else replace(r, state=InputState.MISSING)
            for r in self.monitor.report(now_s)
        ]
        message = tracked_objects_message(
            result, self.agent_id, state, reports, self.kinds, self.pipeline.car_size_m
        )
        self.counters["frames/published"] += 1
        self.last_tick = frame.tick
        return MecOutput(frame, inputs, result, state, message, fused, skipped, started_ns)

    # --- reporting ------------------------------------------------------------------------------

    def health(self, now_s: float) -> tuple[int, str]:
        """Health level and one line for the service's health report."""
        bad = [f"{r.sensor_id}: {r.state.value}" for r in self.monitor.report(now_s) if r.state.value != "ok"]
        level = {Status.FULL: NOMINAL, Status.DEGRADED: DEGRADED}.get(self.status.status, CRITICAL)
        text = (
            f"{self.status.status.value}, tick {self.last_tick}, {self.counters['frames/published']} frames, "
            f"cameras every {self.every_n} frame(s)"
        )
        return level, text + (f"; {', '.join(bad)}" if bad else "")

    def counts(self) -> Counter[str]:
        """Every counter of the core, its pipeline and its join."""
        late = getattr(self._joiner, "late_by_sensor", Counter())
        return self.counters + self.pipeline.counts + Counter({f"late/{k}": v for k, v in late.items()})
