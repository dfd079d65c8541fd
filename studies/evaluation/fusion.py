"""`rmmdet eval fusion`: the MEC pipeline against simulation ground truth, pre- and post-fusion.

For each (agent, seed) the lock-step simulation renders the agent's sensors at their live rates under
the seed's conditions (`studies.dataset.conditions.SeedConditions`: traffic density, sensor noise,
lighting, colours); every tick's messages (JPEG, point cloud, radar scan) go into the MEC's core
(`MecCore`: input health, join, decode, pipeline), exactly as the MEC service feeds it. Splits
(`--split`): `test`, held out, and `tuning`, on which the settings were chosen
(`studies/dataset/config.py` `SplitSeeds`). Per agent frame the result is scored as:

- `lidar`: the 3D detector's boxes (pre-fusion, agents with a lidar);
- `radar`: radar targets on the road (pre-fusion, the viaduct agent);
- `camera`: camera-only objects placed on the road surface (every agent);
- `fused`: the measurements the fusion step hands to the tracker (post-fusion);
- `tracked`: the published tracks (post-fusion and tracking), and MOTA / IDF1 against vehicle ids;
- `tracked_<modality>`: the same tracker fed one modality alone, so "fusion vs the best single
  modality" compares like with like.

Ground truth: vehicles the agent can observe (>= MIN_LIDAR_POINTS lidar points, or >= min_visible_px
pixels in one of its cameras, or a radar return) are scored; vehicles glimpsed below those limits are
ignore regions (neither missed nor a false positive when detected). The paper's metrics (pose error,
AOS, BEV IoU, heat maps on its 0.125 m grid) come from `shared.metrics.fusion`, MOTA / IDF1 from
motmetrics (`shared.metrics.tracking`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, cast

import numpy as np
import shapely
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from shared.config import deep_merge, with_overrides
from shared.datasets.layout import MIN_LIDAR_POINTS, min_visible_px
from shared.detection.interface import CameraDetector, LidarDetector
from shared.geometry.boxes import bev_iou_matrix
from shared.metrics.detection import DEFAULT_DISTANCE_BANDS_M
from shared.metrics.fusion import DEFAULT_CELL_M, DEFAULT_MATCH_DISTANCE_M, FusionAccumulator
from shared.metrics.tracking import DEFAULT_TRACK_DISTANCE_M, TrackingAccumulator
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.perception import camera_only
from shared.perception.confidence import ALONE, FUSED, ScoreCalibration, evidence_key
from shared.perception.config import MecSettings
from shared.perception.core import MecCore, MecOutput
from shared.perception.decode import FrameDecoder
from shared.perception.pipeline import (
    AgentInputs,
    AgentPipeline,
    AgentResult,
    camera_measurement,
    lidar_measurement,
    merge_across_sensors,
)
from shared.scene.scale import LENGTH, Length, SiteScale, Speed, at_scale
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.tracking.measurement import Measurement
from shared.tracking.track_table import Track
from shared.tracking.tracker import MultiObjectTracker
from sim.config import SimSettings
from sim.lockstep import LockstepSim
from sim.sensors.camera import CameraFrame
from sim.sensors.lidar import LidarScan
from sim.sensors.rig import Capture
from studies.dataset.conditions import SeedConditions
from studies.dataset.config import Variation
from studies.evaluation import robustness
from studies.parallel import run_jobs

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
SINGLE_MODALITIES = ("lidar", "camera", "radar")
# Ground truth this close outside the agent's areas is an ignore region; predictions beyond are dropped.
SCOPE_MARGIN_M = 0.3
# The same margin in height, for areas bounded in z (the viaduct): the ramps climb 0.4 m over 2 m, so
# 0.3 m along a ramp is 0.06 m of height.
SCOPE_MARGIN_Z_M = 0.06
#: A confirmed track unmatched to any vehicle and slower than this is a static false track (the sand
#: table's 0.05 m/s: a tenth of its top speed; scaled with the scene).
STATIC_TRACK_SPEED_MPS = 0.05
#: Static false tracks longer than this are counted (issue 49: none may last more than 1 s).
STATIC_TRACK_LIMIT_S = 1.0
PLOT_POSE_ERROR_MAX_M = 0.05  # colour scale of the pose-error heat map
#: Range bands of the tracked output's AP (from the agent's range sensors): the detector evaluation's
#: bands on the table (0-2, 2-4, 4+ m from the lidar), as their inner edges.
RANGE_BAND_EDGES_M = tuple(lo for lo, _ in DEFAULT_DISTANCE_BANDS_M[1:])


class EvalDistances(BaseModel):
    """The evaluation's sizes: the sand table's values, scaled to the scene evaluated (`for_scene`), so
    a gate means the same share of a car and of a lane at every site."""

    model_config = ConfigDict(extra="forbid")

    match_distance_m: Length = Field(DEFAULT_MATCH_DISTANCE_M, gt=0, description="BEV centre gate")
    track_distance_m: Length = Field(DEFAULT_TRACK_DISTANCE_M, gt=0, description="MOT centre gate")
    cell_m: Length = Field(DEFAULT_CELL_M, gt=0, description="heat-map cell")
    scope_margin_m: Length = Field(SCOPE_MARGIN_M, ge=0, description="ignore band outside the areas")
    scope_margin_z_m: Length = Field(SCOPE_MARGIN_Z_M, ge=0, description="the same band in height")
    static_track_speed_mps: Speed = Field(STATIC_TRACK_SPEED_MPS, gt=0, description="static below this")
    plot_pose_error_max_m: Length = Field(PLOT_POSE_ERROR_MAX_M, gt=0, description="heat-map colour top")
    range_band_edges_m: Annotated[tuple[float, ...], LENGTH] = Field(
        RANGE_BAND_EDGES_M, description="inner edges of the AP range bands, from the agent's range sensors"
    )

    def range_bands_m(self) -> list[tuple[float, float]]:
        """[lo, hi) bands from 0 through the edges to infinity."""
        edges = (0.0, *self.range_band_edges_m, float("inf"))
        return list(itertools.pairwise(edges))

    @classmethod
    def for_scene(cls, scene: Scene) -> EvalDistances:
        return at_scale(cls(), SiteScale.of(scene.spec))


#: A measurement counts as a true box at this BEV IoU with its matched vehicle (the AP-BEV@0.7 criterion).
CALIBRATION_IOU = 0.7


@dataclass
class FrameTruth:
    boxes: dict[str, FloatArray]  # observable vehicle id -> (7,) world box
    ignore: list[FloatArray]  # glimpsed vehicles' boxes
    velocities_mps: dict[str, FloatArray] = field(default_factory=dict)  # vehicle id -> (2,) world vx, vy
    lidar_points: dict[str, int] = field(default_factory=dict)  # scored vehicle id -> its lidar points


def vehicle_velocities(gt: Any) -> dict[str, FloatArray]:
    """Vehicle id -> (2,) world BEV velocity, m/s, of a GroundTruth message."""
    return {v.vehicle_id: np.array([v.velocity_mps.x, v.velocity_mps.y]) for v in gt.vehicles}


def vehicle_boxes(gt: Any) -> dict[str, FloatArray]:
    out = {}
    for v in gt.vehicles:
        c, s = v.box.center_m, v.box.size_m
        out[v.vehicle_id] = np.array([c.x, c.y, c.z, s.x, s.y, s.z, v.box.yaw_rad])
    return out


class AgentScope:
    """The agent's areas (its responsibility on the table): ground truth inside is scored, within
    `margin_m` (`margin_z_m` in height) outside it is an ignore region, predictions beyond the margin
    are not the agent's. Like `Scene.area_of` (the ground truth's area id), the height tested is the
    road surface under the car, its box bottom: a car on the floor has its centre 0.105 m up, above
    the viaduct's 0.1 m floor, and would count as on the viaduct by its centre."""

    def __init__(self, scene: Scene, agent_id: str, margin_m: float, margin_z_m: float = 0.0) -> None:
        areas = [a for a in scene.spec.areas if a.id in scene.agents[agent_id].areas]
        self._areas = [(shapely.Polygon(a.polygon_m), a.z_min_m, a.z_max_m) for a in areas]
        self._buffered = [(p.buffer(margin_m), lo - margin_z_m, hi + margin_z_m) for p, lo, hi in self._areas]

    @staticmethod
    def _test(shapes: list[tuple[Any, float, float]], boxes: FloatArray) -> NDArray[np.bool_]:
        out = np.zeros(len(boxes), bool)
        surface_z = boxes[:, 2] - boxes[:, 5] / 2
        for poly, lo, hi in shapes:
            xy_in = shapely.contains_xy(poly, boxes[:, 0], boxes[:, 1])
            out |= xy_in & (surface_z >= lo) & (surface_z <= hi)
        return out

    def inside(self, boxes: FloatArray) -> NDArray[np.bool_]:
        return self._test(self._areas, np.asarray(boxes, float).reshape(-1, 7))

    def near(self, boxes: FloatArray) -> NDArray[np.bool_]:
        return self._test(self._buffered, np.asarray(boxes, float).reshape(-1, 7))


def observable(gt: Any, captures: list[Capture], scope: AgentScope) -> FrameTruth:
    """Vehicles of the agent's areas its sensors of this tick can see (labels), and the ignore
    regions: vehicles only glimpsed, and vehicles seen just outside the areas."""
    seen: set[str] = set()
    glimpsed: set[str] = set()
    lidar_points: Counter[str] = Counter()
    for c in captures:
        if isinstance(c.data, CameraFrame):
            least_px = min_visible_px(c.data.rgb.shape[1], c.data.rgb.shape[0])
            for vid, px in c.data.visible_px.items():
                (seen if px >= least_px else glimpsed).add(vid)
        elif isinstance(c.data, LidarScan):
            ids, counts = np.unique(c.data.vehicle_ids[c.data.vehicle_ids != ""], return_counts=True)
            lidar_points.update(dict(zip(ids.tolist(), counts.tolist(), strict=True)))
        else:
            seen.update(t.vehicle_id for t in c.data if t.vehicle_id)
    for vid, n in lidar_points.items():
        (seen if n >= MIN_LIDAR_POINTS else glimpsed).add(vid)
    boxes = {v: b for v, b in vehicle_boxes(gt).items() if v in seen | glimpsed}
    vehicle_ids = list(boxes)
    stacked = np.stack([boxes[v] for v in vehicle_ids]) if vehicle_ids else np.zeros((0, 7))
    inside, near = scope.inside(stacked), scope.near(stacked)
    scored = {v: boxes[v] for v, i in zip(vehicle_ids, inside, strict=True) if i and v in seen}
    ignore = [boxes[v] for v, i, n in zip(vehicle_ids, inside, near, strict=True) if n and v not in scored]
    velocities = vehicle_velocities(gt)
    return FrameTruth(
        scored, ignore, {v: velocities[v] for v in scored}, {v: lidar_points.get(v, 0) for v in scored}
    )


def sensor_origin_xy_m(scene: Scene, agent_id: str) -> tuple[float, float]:
    """Where an agent's ranges are measured from: the centre of its lidars (else of all its sensors)."""
    sensors = scene.sensors_of(agent_id)
    ranged = [s for s in sensors if s.kind == "lidar"] or sensors
    xy = np.mean([s.pose.position_m[:2] for s in ranged], axis=0)
    return float(xy[0]), float(xy[1])


class RangeDelay:
    """Lidar and radar frames `delay_s` old in place of the current ones (cameras untouched): what
    the MEC receives when those sensors lag by an unmodelled latency but are stamped as new. Until a
    sensor has a frame that old, its current one passes (the first `delay_s` of a run)."""

    def __init__(self, delay_s: float) -> None:
        self.delay_ns = round(delay_s * NS_PER_S)
        self._history: dict[str, list[Capture]] = {}

    def captures(self, stamp_ns: int, captures: list[Capture]) -> list[Capture]:
        if self.delay_ns <= 0:
            return captures
        out = []
        for c in captures:
            if c.spec.kind == "camera":
                out.append(c)
                continue
            history = self._history.setdefault(c.spec.id, [])
            history.append(c)
            old = [h for h in history if h.stamp_ns <= stamp_ns - self.delay_ns]
            out.append(old[-1] if old else c)
            del history[: max(0, len(old) - 1)]  # keep the newest old-enough frame and what follows
        return out


def feed_tick(core: MecCore, tick_stamp_ns: int, tick: int, captures: list[Capture]) -> MecOutput | None:
    """One lock-step tick's captures through the MEC's core, as the live MEC receives them: the bus
    messages in on the clock of record (the tick's stamp; nothing is late or stale in lock step), then
    the frame joined, decoded, processed and published with its status. None if no frame was ready."""
    now_s = tick_stamp_ns / NS_PER_S
    core.cadence(now_s)
    for c in captures:
        core.receive(c.spec.id, tick_stamp_ns, tick, c.message, now_s, tick_stamp_ns)
    return core.step(now_s)


def measurement_box(m: Measurement, default_size_m: tuple[float, float, float]) -> tuple[FloatArray, bool]:
    size = m.size_m if m.size_m is not None else default_size_m
    yaw = m.yaw_rad if m.yaw_rad is not None else 0.0
    return np.array([m.position_m[0], m.position_m[1], m.z_m, *size, yaw]), m.yaw_rad is not None


def track_box(t: Track, default_size_m: tuple[float, float, float]) -> tuple[FloatArray, bool]:
    size = t.size_m if t.size_m is not None else default_size_m
    yaw = t.yaw_rad if t.yaw_rad is not None else 0.0
    p = t.position_m
    return np.array([p[0], p[1], t.z_m, *size, yaw]), t.yaw_rad is not None


def _stack(rows: list[tuple[FloatArray, bool]]) -> tuple[FloatArray, NDArray[np.bool_]]:
    if not rows:
        return np.zeros((0, 7)), np.zeros(0, bool)
    return np.stack([r[0] for r in rows]), np.array([r[1] for r in rows])


@dataclass
class TracedFrame:
    """One frame of the tracked output as scored (for diagnosis): ground truth (scored vehicles, their
    lidar points), the tracks in the agent's scope and the match."""

    stamp_s: float
    gt_ids: list[str]
    gt: FloatArray  # (G, 7)
    gt_lidar_points: list[int]
    track_ids: list[int]
    tracks: FloatArray  # (P, 7)
    velocities_mps: FloatArray  # (P, 2)
    pred_index: NDArray[np.int64]
    gt_index: NDArray[np.int64]
    false_positives: NDArray[np.int64]
    misses: NDArray[np.int64]


@dataclass
class AgentEvaluation:
    """Accumulators of one agent (or of all agents, merged by adding frames)."""

    fusion: dict[str, FusionAccumulator] = field(default_factory=dict)
    tracking: dict[str, TrackingAccumulator] = field(default_factory=dict)
    latencies_s: dict[str, list[float]] = field(default_factory=dict)
    counts: Counter[str] = field(default_factory=Counter)
    frames: int = 0
    # evidence key -> per frame (K, 2) [score, 1 if a true box (BEV IoU >= CALIBRATION_IOU) else 0] of
    # the measurements (pipeline output and single modalities): calibration and its check
    score_samples: dict[str, list[FloatArray]] = field(default_factory=dict)
    distances: EvalDistances = field(default_factory=EvalDistances)
    # Static false tracks of the tracked output: track id -> (first, last) stamp s of its current run
    # unmatched and static; the length of every finished run.
    static_runs: dict[int, tuple[float, float]] = field(default_factory=dict)
    static_run_s: list[float] = field(default_factory=list)
    # The agent's range origin (`sensor_origin_xy_m`) for the AP range bands; None over several agents.
    origin_xy_m: tuple[float, float] | None = None
    # With a list: every frame of the tracked output kept for diagnosis (studies/evaluation/diagnose.py).
    trace: list[TracedFrame] | None = None

    def samples(self, key: str) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(scores, is a true box) of every measurement of evidence `key`."""
        rows = np.concatenate(self.score_samples.get(key) or [np.zeros((0, 2))])
        return rows[:, 0], rows[:, 1] > 0.5

    def acc(self, name: str) -> FusionAccumulator:
        return self.fusion.setdefault(name, FusionAccumulator(self.distances.match_distance_m))

    def trk(self, name: str) -> TrackingAccumulator:
        return self.tracking.setdefault(name, TrackingAccumulator(self.distances.track_distance_m))

    def static_tracks(self, stamp_s: float, static_unmatched: set[int]) -> None:
        """One frame of the tracked output: the ids of its confirmed tracks that match no vehicle (nor
        an ignore region) and move slower than `distances.static_track_speed_mps`."""
        for track_id in list(self.static_runs):
            if track_id not in static_unmatched:
                first, last = self.static_runs.pop(track_id)
                self.static_run_s.append(last - first)
        for track_id in static_unmatched:
            first, _ = self.static_runs.get(track_id, (stamp_s, stamp_s))
            self.static_runs[track_id] = (first, stamp_s)

    def static_track_summary(self) -> dict[str, float | int]:
        """Static false tracks: the longest run (s, frame stamps first to last) and how many ran over
        STATIC_TRACK_LIMIT_S, runs still open included."""
        runs = self.static_run_s + [last - first for first, last in self.static_runs.values()]
        return {
            "runs": len(runs),
            "max_s": max(runs, default=0.0),
            "over_limit": sum(r > STATIC_TRACK_LIMIT_S for r in runs),
        }

    def merge(self, other: AgentEvaluation) -> None:
        if not self.frames and not self.fusion:
            self.distances = other.distances  # an empty evaluation takes the scene of what it merges
            self.origin_xy_m = other.origin_xy_m
        elif self.origin_xy_m != other.origin_xy_m:
            self.origin_xy_m = None  # several agents: no one range origin
        for name, acc in other.fusion.items():
            self.acc(name).merge(acc)
        for name, trk in other.tracking.items():
            self.trk(name).merge(trk)
        for stage, values in other.latencies_s.items():
            self.latencies_s.setdefault(stage, []).extend(values)
        self.counts.update(other.counts)
        self.frames += other.frames
        for key, rows in other.score_samples.items():
            self.score_samples.setdefault(key, []).extend(rows)
        # runs of different (agent, seed) evaluations never continue each other
        self.static_run_s += other.static_run_s + [b - a for a, b in other.static_runs.values()]


def single_modality_measurements(
    result: AgentResult, pipeline: AgentPipeline, inputs: AgentInputs, images: dict[str, np.ndarray]
) -> dict[str, list[Measurement]]:
    """What each modality alone would give the tracker this frame (radar: its targets without any
    camera, one measurement per car across the radars). `images`: every camera image of the frame,
    the ones the MEC did not decode (camera cadence) included: a camera-only system sees them all."""
    out: dict[str, list[Measurement]] = {}
    if pipeline.lidar_ids:
        std_m = pipeline.cfg.lidar_position_std_m
        only = frozenset({"lidar"})
        out["lidar"] = [
            lidar_measurement(b[:7], b[7], only, tuple(pipeline.lidar_ids), std_m)
            for b in result.lidar_boxes_world
        ]
    camera_boxes = dict(result.camera_boxes)
    skipped = {c: img for c, img in images.items() if c not in camera_boxes}
    if skipped:
        # The pipeline's camera cadence skipped the detector on these images; the baseline runs it.
        camera_boxes.update(pipeline.detect_2d(skipped))
    if camera_boxes:
        objs = camera_only.locate(
            pipeline.views,
            camera_boxes,
            pipeline.surface,
            pipeline.cfg.camera_only,
            pipeline.car_size_m,
        )
        out["camera"] = [camera_measurement(o) for o in objs]
    if pipeline.radar_specs:
        per_radar = pipeline.radar_measurements(inputs)
        out["radar"] = merge_across_sensors(
            per_radar, pipeline.cfg.radar_camera.cross_radar_gate_m, Counter()
        )
    # Scores mean the same as the pipeline's: each modality alone has its own calibrated evidence key.
    return {m: pipeline.calibration.apply(ALONE, ms) for m, ms in out.items()}


def evaluate_run(
    scene: Scene,
    agent_id: str,
    sim_settings: SimSettings,
    mec: MecSettings,
    duration_s: float,
    warmup_s: float,
    cameras: CameraDetector | None = None,
    lidar: LidarDetector | None = None,
    conditions: SeedConditions | None = None,
    mec_scene: Scene | None = None,
    range_delay_s: float = 0.0,
    transform: Callable[[list[Capture]], list[Capture]] | None = None,
    trace: bool = False,
) -> AgentEvaluation:
    """Run one seed for one agent: its frames scored (one MOT sequence per run); with `trace`, every
    frame of the tracked output kept in `trace` (diagnosis). `conditions` (sensor
    noise, lighting, colours) apply to the sim; without them the sensors run as the scene defines.
    Perturbations (studies/evaluation/robustness.py): the MEC calibrated on `mec_scene` instead of
    the true scene; its lidar and radar frames `range_delay_s` old but stamped as new; every capture
    through `transform` before the MEC (e.g. its device's wire format and back); truth always from the
    untouched captures."""
    distances = EvalDistances.for_scene(scene)
    ev = AgentEvaluation(
        distances=distances, origin_xy_m=sensor_origin_xy_m(scene, agent_id), trace=[] if trace else None
    )
    vehicle_index: dict[str, int] = {}
    sensor_ids = [s.id for s in scene.sensors_of(agent_id)]
    core = MecCore(mec_scene or scene, agent_id, mec, cameras=cameras, lidar=lidar)
    delayed = RangeDelay(range_delay_s)
    core.tick_hz = sim_settings.tick_hz  # the camera cadence of the live MEC (on sim ticks)
    pipeline = core.pipeline
    baseline_decoder = FrameDecoder()  # the images the MEC skips, for the camera-only baseline
    single_trackers = {m: MultiObjectTracker(core.settings.tracker) for m in SINGLE_MODALITIES}  # at scale
    scope = AgentScope(scene, agent_id, distances.scope_margin_m, distances.scope_margin_z_m)
    kwargs: dict[str, Any] = {"sensor_ids": sensor_ids, "labels": True}
    if conditions is not None:
        lockstep = conditions.lockstep(scene, sim_settings, **kwargs)
    else:
        lockstep = LockstepSim(scene, sim_settings, **kwargs)
    with lockstep as sim:
        tick_hz = sim_settings.tick_hz
        warmup_ticks = round(warmup_s * tick_hz)
        total_ticks = warmup_ticks + round(duration_s * tick_hz)
        for _ in range(total_ticks):
            tick = sim.step()
            if not tick.captures:
                continue
            gt = tick.ground_truth
            stamp_ns = gt.header.stamp.ToNanoseconds()
            fed = delayed.captures(stamp_ns, tick.captures)
            out = feed_tick(core, stamp_ns, gt.header.tick, transform(fed) if transform else fed)
            if out is None or out.frame.tick != gt.header.tick:
                # Every sensor of an agent captures on the agent's ticks: a lock-step frame is complete
                # at once. Anything else is a bug of the join, not a frame to score late.
                raise RuntimeError(f"{agent_id}: tick {gt.header.tick} not joined at once")
            result, inputs = out.result, out.inputs
            images = {
                c.spec.id: inputs.images[c.spec.id]
                if c.spec.id in inputs.images
                else baseline_decoder.image(c.spec.id, cast(CompressedImage, c.message))
                for c in tick.captures
                if c.spec.kind == "camera"
            }
            singles = single_modality_measurements(result, pipeline, inputs, images)
            for m, tracker in single_trackers.items():
                if m in singles:
                    tracker.step(stamp_ns / NS_PER_S, singles[m])
            if gt.header.tick < warmup_ticks:
                continue  # tracks settle in; frames are scored after the warm-up
            truth = observable(gt, tick.captures, scope)
            single_tracks = {m: t.confirmed() for m, t in single_trackers.items() if m in singles}
            ids = {v: vehicle_index.setdefault(v, len(vehicle_index)) for v in truth.boxes}
            _score_frame(
                ev,
                scope,
                truth,
                ids,
                result,
                singles,
                single_tracks,
                pipeline.car_size_m,
                stamp_ns / NS_PER_S,
            )
    ev.counts.update(core.counts())
    return ev


def _score_frame(
    ev: AgentEvaluation,
    scope: AgentScope,
    truth: FrameTruth,
    gt_numbers: dict[str, int],
    result: AgentResult,
    singles: dict[str, list[Measurement]],
    single_tracks: dict[str, list[Track]],
    car_size_m: tuple[float, float, float],
    stamp_s: float,
) -> None:
    ev.frames += 1
    gt_ids = list(truth.boxes)
    gt = np.stack([truth.boxes[v] for v in gt_ids]) if gt_ids else np.zeros((0, 7))
    gt_velocity = np.stack([truth.velocities_mps[v] for v in gt_ids]) if gt_ids else np.zeros((0, 2))
    ignore = np.stack(truth.ignore) if truth.ignore else np.zeros((0, 7))
    for stage, seconds in result.latencies_s.items():
        ev.latencies_s.setdefault(stage, []).append(seconds)
    # name -> (boxes with yaw validity, scores, track ids, velocities (tracks only: measurements have none))
    sets: dict[
        str, tuple[list[tuple[FloatArray, bool]], list[float], list[int] | None, FloatArray | None]
    ] = {}
    evidence: dict[str, list[str]] = {}  # measurement sets: evidence key per row
    for name, rows in {**singles, "fused": result.measurements}.items():
        sets[name] = ([measurement_box(m, car_size_m) for m in rows], [m.score for m in rows], None, None)
        source = FUSED if name == "fused" else ALONE
        evidence[name] = [evidence_key(source, m.modalities) for m in rows]
    for name, tracks in {
        "tracked": result.tracks,
        **{f"tracked_{m}": t for m, t in single_tracks.items()},
    }.items():
        sets[name] = (
            [track_box(t, car_size_m) for t in tracks],
            [t.existence_probability for t in tracks],
            [t.track_id for t in tracks],
            np.array([t.velocity_mps for t in tracks]).reshape(-1, 2),
        )
    for name, (box_rows, score_list, track_ids, velocity) in sets.items():
        boxes, yaw_ok = _stack(box_rows)
        keep = scope.near(boxes)  # objects beyond the agent's areas are another agent's business
        boxes, yaw_ok, scores = boxes[keep], yaw_ok[keep], np.asarray(score_list, float).reshape(-1)[keep]
        match = ev.acc(name).add_frame(
            boxes,
            gt,
            yaw_valid=yaw_ok,
            scores=scores,
            gt_ignore=ignore,
            pred_velocity_mps=None if velocity is None else velocity[keep],
            gt_velocity_mps=gt_velocity,
        )
        if name in evidence:
            keys = [k for k, kept in zip(evidence[name], keep, strict=True) if kept]
            _record_scores(ev, keys, scores, boxes, gt, match)
        if track_ids is not None:
            # Tracks on ignore regions (glimpsed cars, cars just outside the areas) are not scored.
            counted = np.ones(len(boxes), bool)
            counted[match.ignored] = False
            ids = [t for t, k in zip(track_ids, keep, strict=True) if k]
            kept_ids = ids
            ids = [i for i, c in zip(ids, counted, strict=True) if c]
            ev.trk(name).update([gt_numbers[v] for v in gt_ids], gt[:, :2], ids, boxes[counted, :2])
            if name == "tracked":
                assert velocity is not None
                unmatched = counted.copy()
                unmatched[match.pred_index] = False
                slow = np.hypot(*velocity[keep].T) < ev.distances.static_track_speed_mps
                ev.static_tracks(
                    stamp_s, {t for t, u, s in zip(kept_ids, unmatched, slow, strict=True) if u and s}
                )
                if ev.trace is not None:
                    ev.trace.append(
                        TracedFrame(
                            stamp_s,
                            gt_ids,
                            gt,
                            [truth.lidar_points.get(v, 0) for v in gt_ids],
                            kept_ids,
                            boxes,
                            velocity[keep],
                            match.pred_index,
                            match.gt_index,
                            match.false_positives,
                            match.misses,
                        )
                    )


def _record_scores(
    ev: AgentEvaluation, keys: list[str], scores: FloatArray, boxes: FloatArray, gt: FloatArray, match: Any
) -> None:
    """Each scored measurement's (score, true box?) under its evidence key; ignored ones are left out."""
    true_box = np.zeros(len(boxes), bool)
    p, g = match.pred_index, match.gt_index
    true_box[p] = np.diagonal(bev_iou_matrix(boxes[p], gt[g])) >= CALIBRATION_IOU
    counted = np.ones(len(boxes), bool)
    counted[match.ignored] = False
    for key in set(keys):
        rows = np.flatnonzero(counted & (np.asarray(keys) == key))
        ev.score_samples.setdefault(key, []).append(np.column_stack([scores[rows], true_box[rows]]))


def calibration_check(ev: AgentEvaluation, bins: int = 10) -> dict[str, dict[str, float]]:
    """Per evidence key: measurements, mean score, share of true boxes, and the expected calibration
    error (mean |score - true share| over `bins` equal-width score bins, weighted by their counts)."""
    out = {}
    for key in sorted(ev.score_samples):
        score, true_box = ev.samples(key)
        if len(score) == 0:
            continue
        k = np.minimum((score * bins).astype(int), bins - 1)
        ece = sum(
            abs(score[k == b].mean() - true_box[k == b].mean()) * np.count_nonzero(k == b)
            for b in range(bins)
            if np.any(k == b)
        ) / len(score)
        out[key] = {
            "n": len(score),
            "mean_score": float(score.mean()),
            "true_share": float(true_box.mean()),
            "ece": float(ece),
        }
    return out


def fit_calibration(ev: AgentEvaluation) -> ScoreCalibration:
    """Calibrated-score curves from raw-score samples (an evaluation run without calibration)."""
    return ScoreCalibration.fit({key: ev.samples(key) for key in ev.score_samples})


def summarise(ev: AgentEvaluation) -> dict[str, Any]:
    out: dict[str, Any] = {"frames": ev.frames}
    for name, acc in sorted(ev.fusion.items()):
        out[name] = acc.summary()
    if ev.origin_xy_m is not None and "tracked" in ev.fusion:
        out["tracked"]["ap_bev_0.7_by_range"] = ev.fusion["tracked"].ap_bev_by_range(
            ev.origin_xy_m, ev.distances.range_bands_m()
        )
    for name, trk in sorted(ev.tracking.items()):
        out[name]["tracking"] = trk.summary()
    out["latency_ms"] = {
        stage: {"p50": float(np.percentile(v, 50) * 1e3), "p95": float(np.percentile(v, 95) * 1e3)}
        for stage, v in ev.latencies_s.items()
    }
    out["counts"] = dict(ev.counts)
    out["static_false_tracks"] = ev.static_track_summary()
    out["score_calibration"] = calibration_check(ev)
    return out


def timed(fn: Any, *args: Any, **kwargs: Any) -> tuple[Any, float]:
    t0 = time.perf_counter()
    return fn(*args, **kwargs), time.perf_counter() - t0


# --- the whole evaluation ---------------------------------------------------------------------------


def _run_worker(
    job: tuple[str, int, float, float, str, str, str, str],
) -> tuple[str, int, AgentEvaluation, float]:
    """One (agent, seed) run in a worker process (spawned: PyBullet and onnxruntime are per process),
    under the seed's conditions (density, sensor noise, lighting, colours) and a perturbation."""
    agent, seed, duration_s, warmup_s, mec_json, variation_json, perturbation_json, scene_json = job
    from sim.config import load_sim_settings

    site = json.loads(scene_json)  # the scene file and the sim settings' overrides (its profile's)
    scene = Scene.load(Path(site["scene"]))
    mec = MecSettings.model_validate_json(mec_json)
    variation = Variation.model_validate_json(variation_json)
    perturbation = robustness.Perturbation(**json.loads(perturbation_json))
    transform = None
    if perturbation.site:
        from shared.devices.site import SiteFile
        from studies.evaluation.wire_path import WireRoundTrip

        site = SiteFile.load(REPO_ROOT / perturbation.site)
        scene = site.simulated_scene(scene)
        if perturbation.wire:
            transform = WireRoundTrip(site, scene.sensors_of(agent)).captures
    conditions = perturbation.conditions(SeedConditions.draw(variation, seed), variation)
    mec_scene = perturbation.mec_scene(scene, seed)
    if perturbation.calibration:
        from shared.devices.site import SiteFile

        mec_scene = SiteFile.load(REPO_ROOT / perturbation.calibration).calibrated_scene(mec_scene)
    if perturbation.radar_noise == "ars408":
        from studies.evaluation.wire_path import with_ars408_noise

        mec_scene = with_ars408_noise(mec_scene)
    t0 = time.perf_counter()
    ev = evaluate_run(
        scene,
        agent,
        load_sim_settings(
            vehicles=conditions.vehicles,
            seed=seed,
            **deep_merge(site["sim_overrides"], {"scene": site["scene"]}),
        ),
        mec,
        duration_s,
        warmup_s,
        conditions=conditions,
        mec_scene=mec_scene,
        range_delay_s=perturbation.range_delay_s,
        transform=transform,
    )
    return agent, seed, ev, time.perf_counter() - t0


def evaluate(
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    mec: MecSettings,
    workers: int,
    variation: Variation,
    perturbation: robustness.Perturbation = robustness.CLEAN,
    per_seed: dict[str, dict[str, dict[str, float | None]]] | None = None,
    scene_path: Path = DEFAULT_SCENE,
    sim_overrides: dict[str, Any] | None = None,
    placements: list[dict[str, Any]] | None = None,
) -> dict[str, AgentEvaluation]:
    """Every (agent, seed) run under the seed's conditions drawn from `variation` (and `perturbation`),
    merged per agent and over all agents (key "all"); with `per_seed`, each run's `seed_row` is put
    there as per_seed[agent][str(seed)] (for paired comparisons over seeds); with `placements`, where
    each run ran (studies/parallel.py: this machine's pool or a Dask cluster)."""
    if workers > 1:
        # One onnxruntime thread per model and process: spinning ORT threads of parallel workers
        # oversubscribe the cores and run many times slower.
        mec = with_overrides(mec, {"detectors": {"camera_threads": 1, "lidar_threads": 1}})
    perturbation_json = json.dumps(
        dataclasses.asdict(perturbation)
    )  # any perturbation, not just the named ones
    site = json.dumps({"scene": str(scene_path), "sim_overrides": sim_overrides or {}})
    # Only what was set: a value dumped explicitly would be taken as written and never scaled to the
    # scene (at the intersection every size stayed the sand table's: no lidar detection at all).
    mec_json = mec.model_dump_json(exclude_unset=True)
    jobs = [
        (
            a,
            s,
            duration_s,
            warmup_s,
            mec_json,
            variation.model_dump_json(),
            perturbation_json,
            site,
        )
        for a in agents
        for s in seeds
    ]
    per_agent: dict[str, AgentEvaluation] = {a: AgentEvaluation() for a in agents}

    def add(agent: str, seed: int, ev: AgentEvaluation, wall_s: float) -> None:
        log.info("%s seed %d: %d frames in %.0f s", agent, seed, ev.frames, wall_s)
        per_agent[agent].merge(ev)
        if per_seed is not None:
            per_seed.setdefault(agent, {})[str(seed)] = seed_row(ev)
        bar.update()

    # A progress bar on a terminal (tqdm disables itself when stderr is not one: logs stay clean).
    bar = tqdm(total=len(jobs), desc="agent runs", unit="run", disable=None)
    for result in run_jobs(_run_worker, jobs, workers, placements):
        add(*result)
    bar.close()
    return {**per_agent, "all": merge_agents(per_agent)}


def seed_row(ev: AgentEvaluation, output: str = "tracked") -> dict[str, float | None]:
    """One run's `output` by the figures compared across seeds: AP-BEV@0.7 and MOTA (None where the
    run has nothing to score)."""
    acc = ev.fusion.get(output)
    trk = ev.tracking.get(output)
    mota = trk.summary()["mota"] if trk is not None else None
    return {
        "ap_bev_0.7": acc.ap_bev((0.7,))["ap_bev_0.7"] if acc is not None else None,
        "mota": None if mota is None else float(mota),
    }


TRACKED_SINGLE = "tracked_"
BEST_SINGLE = "tracked_best_single"


def best_single_modality(ev: AgentEvaluation) -> str | None:
    """The agent's tracked single modality with the highest AP-BEV@0.7 (None if it has none)."""
    scores: dict[str, float] = {}
    for name, acc in ev.fusion.items():
        if name.startswith(TRACKED_SINGLE) and name != BEST_SINGLE:
            ap = acc.ap_bev((0.7,))["ap_bev_0.7"]
            if ap is not None:
                scores[name] = ap
    return max(scores, key=scores.__getitem__) if scores else None


def merge_agents(per_agent: dict[str, AgentEvaluation]) -> AgentEvaluation:
    """All agents as one system. A modality's tracker exists only on the agents that have it, so the
    per-modality rows are not system baselines; the system's single-modality baseline is each agent's
    best single modality (lidar on the lidar agents, radar on the viaduct), `tracked_best_single`."""
    overall = AgentEvaluation()
    for ev in per_agent.values():
        overall.merge(ev)
    for name in [n for n in overall.fusion if n.startswith(TRACKED_SINGLE)]:
        del overall.fusion[name]
        overall.tracking.pop(name, None)
    for agent, ev in per_agent.items():
        best = best_single_modality(ev)
        if best is None:
            continue
        overall.acc(BEST_SINGLE).merge(ev.fusion[best])
        if best in ev.tracking:
            overall.trk(BEST_SINGLE).merge(ev.tracking[best])
        overall.counts[f"best_single/{agent}/{best.removeprefix(TRACKED_SINGLE)}"] += 1
    return overall


def fusion_gain(summary: dict[str, Any]) -> dict[str, Any]:
    """Tracked fusion against the best tracked single modality, by AP-BEV@0.7 and MOTA."""
    singles = {k: v for k, v in summary.items() if k.startswith("tracked_") and isinstance(v, dict)}
    out: dict[str, Any] = {}
    for metric, get in (
        ("ap_bev_0.7", lambda d: d.get("ap_bev_0.7")),
        ("mota", lambda d: d.get("tracking", {}).get("mota")),
        ("pose_error_p95_m", lambda d: d.get("pose_error_p95_m")),
    ):
        values = {k: get(v) for k, v in singles.items() if get(v) is not None}
        fused = get(summary.get("tracked", {}))
        if not values or fused is None:
            continue
        lower_is_better = metric.startswith("pose")
        best_name = (min if lower_is_better else max)(values, key=values.__getitem__)
        out[metric] = {
            "fused": fused,
            "best_single": best_name,
            "best_single_value": values[best_name],
            "gain": (values[best_name] - fused) if lower_is_better else (fused - values[best_name]),
        }
    return out


def write_heat_maps(ev: AgentEvaluation, scene: Scene, out_dir: Any, name: str = "tracked") -> list[str]:
    """Pose error, AOS and BEV IoU heat maps (the paper's 0.125 m grid over the table) as PNG."""
    from pathlib import Path

    from shared.metrics.fusion import save_heat_map_png

    acc = ev.fusion.get(name)
    if acc is None:
        return []
    cell_m = ev.distances.cell_m
    t = scene.spec.table
    x0, y0 = t.origin_m
    x_range = (x0, x0 + np.ceil(t.size_x_m / cell_m) * cell_m)
    y_range = (y0, y0 + np.ceil(t.size_y_m / cell_m) * cell_m)
    maps = acc.heat_maps(x_range, y_range, cell_m)
    written = []
    for key, title, vmin, vmax in (
        ("pose_error_m", "pose error, m", 0.0, ev.distances.plot_pose_error_max_m),
        ("aos", "AOS", 0.8, 1.0),
        ("bev_iou", "BEV IoU", 0.5, 1.0),
    ):
        path = Path(out_dir) / f"heat_{name}_{key}.png"
        save_heat_map_png(maps[key], x_range, y_range, path, f"{name}: {title}", vmin, vmax)
        written.append(str(path))
    return written


#: What each split of the fusion evaluation is (`rmmdet eval fusion --split`).
SPLIT_LABELS = {
    "test": "held-out fusion test split (nothing chosen on it; scored once per change)",
    "tuning": "fusion tuning split (the fusion and tracking settings were chosen on it)",
}

#: Outputs in the order they are reported: before fusion, fused, then tracked.
REPORTED_OUTPUTS = (
    "lidar",
    "radar",
    "camera",
    "fused",
    "tracked_lidar",
    "tracked_radar",
    "tracked_camera",
    "tracked",
)
TABLE_COLUMNS = (
    "agent",
    "output",
    "pose p50 / p95 m",
    "AOS paper / KITTI",
    "BEV IoU",
    "AP-BEV@0.7",
    "P / R / F1",
    "MOTA",
    "MOTP m",
    "velocity error p50 / p95 m/s",
)


def _fmt(value: float | None, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def table_rows(results: dict[str, Any], agents: list[str]) -> list[list[str]]:
    """One row per (agent or "all", output) that was scored: the columns of `TABLE_COLUMNS`."""
    rows = []
    for name in [*agents, "all"]:
        summary = results[name]
        for output in REPORTED_OUTPUTS:
            row = summary.get(output)
            if not isinstance(row, dict) or row.get("pose_error_p50_m") is None:
                continue
            tracking = row.get("tracking", {})
            velocity = "-"
            if row.get("velocity_error_p50_mps") is not None:
                velocity = f"{row['velocity_error_p50_mps']:.3f} / {row['velocity_error_p95_mps']:.3f}"
            rows.append(
                [
                    name,
                    output,
                    f"{row['pose_error_p50_m']:.3f} / {row['pose_error_p95_m']:.3f}",
                    f"{_fmt(row['aos_mean'])} / {_fmt(row.get('aos_kitti_mean'))}",
                    f"{row['bev_iou_mean']:.3f}",
                    f"{row['ap_bev_0.7']:.3f}",
                    f"{row['precision']:.3f} / {row['recall']:.3f} / {_fmt(row.get('f1'))}",
                    _fmt(tracking.get("mota")),
                    _fmt(tracking.get("motp_m")),
                    velocity,
                ]
            )
    return rows


def markdown_table(results: dict[str, Any], agents: list[str]) -> str:
    """The README's fusion table: what was run, where, and one line per scored output."""
    split = SPLIT_LABELS.get(results.get("split", ""), "chosen seeds")
    head = (
        f"{split.capitalize()}: seeds {results['seeds']} x {results['duration_s']:g} s after "
        f"{results['warmup_s']:g} s, each under its own conditions (density, sensor noise, lighting, "
        f"colours: `SeedConditions`), "
        f"{results['all']['frames']} agent frames, {results['wall_s']:g} s wall; commit "
        f"{results.get('commit', '?')}, {results.get('machine', {}).get('cpu_model', '?')} "
        f"({', '.join(results.get('machine', {}).get('cpu_vector_flags', []))})."
    )
    lines = [head, "", "| " + " | ".join(TABLE_COLUMNS) + " |", "|" + "---|" * len(TABLE_COLUMNS)]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(results, agents)]
    check = results["all"].get("score_calibration")
    if check:
        lines += [
            "",
            "Scores against what they claim, all agents (`fused/`: the pipeline's output by evidence, "
            "`alone/`: one modality by itself; a true box has BEV IoU >= 0.7 with its vehicle; ECE: mean "
            "|score - true share| over 10 score bins):",
            "",
            "| evidence | measurements | mean score | true share | ECE |",
            "|---|---|---|---|---|",
            *(
                f"| {key} | {c['n']} | {c['mean_score']:.3f} | {c['true_share']:.3f} | {c['ece']:.3f} |"
                for key, c in check.items()
            ),
        ]
    return "\n".join(lines)


#: Issue 49's bar for a real-size site, per agent on held-out seeds (tracked output).
TARGET_AP_BEV_07 = 0.85
TARGET_MOTA = 0.85


def scene_notes(results: dict[str, Any]) -> str:
    """What a scene's fusion table adds (`rmmdet eval fusion --scene`): per agent the tracked output's
    IDF1, its AP-BEV@0.7 by range from the agent's range sensors, its static false tracks, and whether
    it meets issue 49's bar (AP-BEV@0.7 and MOTA >= 0.85, no static false track over 1 s)."""
    lines = [
        f"Tracked output per agent against issue 49's bar (AP-BEV@0.7 >= {TARGET_AP_BEV_07:g}, "
        f"MOTA >= {TARGET_MOTA:g}, no static false track over {STATIC_TRACK_LIMIT_S:g} s; a static "
        f"false track: a confirmed track matching no vehicle and slower than "
        f"{results['static_track_speed_mps']:.3g} m/s, timed first to last frame):",
        "",
        "| agent | AP-BEV@0.7 | MOTA | IDF1 | AP-BEV@0.7 by range, m (GT) | static false tracks: runs / "
        "longest s / over limit | meets the bar |",
        "|---|---|---|---|---|---|---|",
    ]
    for agent in results["agents"]:
        summary = results[agent]
        tracked = summary.get("tracked", {})
        tracking = tracked.get("tracking", {})
        ap, mota = tracked.get("ap_bev_0.7"), tracking.get("mota")
        bands = tracked.get("ap_bev_0.7_by_range", {})
        by_range = ", ".join(
            f"{band} {_fmt(b['ap'])} ({b['num_gt']})" for band, b in bands.items() if band != "all"
        )
        static = summary["static_false_tracks"]
        meets = (
            ap is not None
            and mota is not None
            and ap >= TARGET_AP_BEV_07
            and mota >= TARGET_MOTA
            and static["over_limit"] == 0
        )
        lines.append(
            f"| {agent} | {_fmt(ap)} | {_fmt(mota)} | {_fmt(tracking.get('idf1'))} | {by_range or '-'} | "
            f"{static['runs']} / {static['max_s']:.1f} / {static['over_limit']} | "
            f"{'yes' if meets else 'no'} |"
        )
    return "\n".join(lines)
