"""`rmmdet eval real`: the production MEC over a public roadside dataset's frames, scored against the
dataset's own labels (issue 50).

Each site a reader gives (shared/datasets/roadside: OpenLABEL / TUMTraf, DAIR-V2X, Rope3D) is levelled
onto its ground and written as a scene from its calibration (`site.site_scene`); the MEC runs with the
settings of the project's real-size profile (`intersection`, as `make up SCENE=intersection` runs a site
of that scale), the detectors asked for in place of the profile's. Every frame's files go into a `MecCore` as
the messages its sensors would send, one tick per frame; a fresh core per frame where the frames are
independent instants (the vendored samples: two TUMTraf frames 5 s apart, one Rope3D image), one core
over a sequence (then the tracks are scored too).

Scored stages (all BEV boxes in the site frame, z up):
- `lidar`: the lidar detector's boxes; `camera`: camera-only objects on the ground (the baseline the
  simulator's study has); `fused`: the measurements the fusion step hands the tracker; `tracked`:
  the published tracks (sequences only: MOTA / IDF1 by motmetrics, HOTA by TrackEval).
- Truth: labelled vehicles (`VEHICLE_CATEGORIES`) with at least `SCORED_MIN_POINTS` lidar points in their
  box as labelled (counted here from the frame's cloud); with fewer, and every other labelled object, an
  ignore region (neither missed nor a false positive). A site without a lidar counts every labelled
  vehicle its cameras see.
- Per stage: precision, recall and centre error at the operating point (centre gate
  `EvalDistances.match_distance_m` at the site's scale), KITTI R40 BEV and 3D AP at IoU 0.5 and 0.25 by
  range band from the site's first lidar (else camera), recall by range band (the same bands) and by
  point count.
- `camera_2d`: each camera's 2D detections against the labels' 2D boxes (the dataset's, else the labelled
  cuboid projected and clipped), COCO AP@0.5; non-vehicles and vehicles seen in no lidar point as
  ignore regions are not used here: every labelled vehicle in the image counts.
- Labels that disagree with the sensors are counted, not scored as misses: vehicle boxes holding no
  lidar point (`no_points`), boxes in no sensor's view (`out_of_view`), a sensor's file more than one
  frame period from the labels' instant (`stamp_apart/<sensor>`: that camera's 2D boxes are not scored
  on that frame).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

from shared.config import ConfigError, with_overrides
from shared.datasets.roadside.dair import read_dair
from shared.datasets.roadside.model import (
    FRAME_PERIOD_NS,
    SENSOR_RATE_HZ,
    RoadsideDataset,
    RoadsideFormatError,
    RoadsideFrame,
    RoadsideLabel,
)
from shared.datasets.roadside.openlabel import read_openlabel
from shared.datasets.roadside.pcd import read_pcd
from shared.datasets.roadside.rope3d import read_rope3d
from shared.datasets.roadside.site import (
    AGENT_ID,
    fit_site_ground,
    frame_messages,
    level_to_ground,
    site_scene,
)
from shared.detection.interface import CameraDetector, LidarDetector
from shared.geometry.boxes import box3d_corners
from shared.geometry.camera import box3d_to_image_box
from shared.geometry.transforms import camera_optical_from_world, matrix_from_pose
from shared.machine import git_commit, machine_info
from shared.metrics.detection import MatchLabel, evaluate_coco, evaluate_kitti, precision_recall_curve
from shared.metrics.fusion import FusionAccumulator
from shared.metrics.tracking import TrackingAccumulator
from shared.perception.config import MecSettings
from shared.perception.core import MecCore
from shared.perception.decode import FrameDecoder
from shared.readme import GENERATED
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from studies.evaluation.fusion import EvalDistances, measurement_box, single_modality_measurements, track_box

FloatArray = np.ndarray

FORMATS = ("openlabel", "dair", "rope3d")
#: The project's real-size profile: its MEC settings are those a site of real size runs.
REAL_SIZE_PROFILE = "intersection"
#: Detectors of real frames by default: the COCO-trained camera card (the project's own camera model
#: learned the simulator's cars) and the clustering lidar detector (the background detector needs a
#: background model of the site, learned from its empty frames: a dataset of labelled frames has none).
DEFAULT_CAMERA = "coco"
DEFAULT_LIDAR = "cluster"
STAGES = ("lidar", "camera", "fused", "tracked")
#: A labelled vehicle is scored with at least this many lidar points in its box (the issue's bar; the
#: simulator's observability limit, shared.datasets.layout.MIN_LIDAR_POINTS, is a glimpse's few points,
#: which a real detector is not expected to box).
SCORED_MIN_POINTS = 20
AP_IOU_THRESHOLDS = (0.5, 0.25)  # 0.25: lidar-only boxes at range (the issue's)
RANGE_BANDS_M = ((0.0, 30.0), (30.0, 60.0), (60.0, float("inf")))  # a real crossing's near / mid / far
POINT_BANDS = ((SCORED_MIN_POINTS, 50.0), (50.0, 100.0), (100.0, float("inf")))  # labelled-box lidar points
#: Issue 50's acceptance for lidar vehicles with >= SCORED_MIN_POINTS points.
TARGET_RECALL = 0.90
TARGET_PRECISION = 0.80
TARGET_CENTRE_P95_M = 0.5
STEP_AFTER_S = 1.0  # a frame missing a sensor is released by the join's deadline: step this much later
ELEVATED_M = 1.0  # a box's bottom this far above the ground is no vehicle on the road (false_box_kinds)


@dataclass
class FrameTruthReal:
    """One frame's truth: counted vehicle boxes (G, 7), ignore regions (I, 7), points per counted box."""

    gt: FloatArray
    ignore: FloatArray
    points: list[int]
    ids: list[str]  # the dataset's object ids of the counted boxes (track ids in a sequence)


@dataclass
class SiteEvaluation:
    """Everything one dataset site's run accumulates."""

    accs: dict[str, FusionAccumulator]
    kitti: dict[str, list[tuple[FloatArray, FloatArray, FloatArray]]] = field(default_factory=dict)
    coco: dict[str, list[tuple[FloatArray, FloatArray, FloatArray]]] = field(default_factory=dict)
    recall_points: dict[str, list[tuple[int, bool]]] = field(default_factory=dict)  # stage -> (pts, found)
    recall_range: dict[str, list[tuple[float, bool]]] = field(default_factory=dict)  # stage -> (m, found)
    false_boxes: dict[str, list[FloatArray]] = field(default_factory=dict)  # stage -> per frame (F, 7)
    scored: dict[str, list[tuple[float, int]]] = field(default_factory=dict)  # stage -> (score, MatchLabel)
    counts: Counter[str] = field(default_factory=Counter)
    frame_ms: list[float] = field(default_factory=list)
    tracking: TrackingAccumulator | None = None  # sequences: the published tracks against the labels' ids
    object_numbers: dict[str, int] = field(default_factory=dict)
    latencies_s: dict[str, list[float]] = field(default_factory=dict)


def lidar_points_site(dataset: RoadsideDataset, frame: RoadsideFrame) -> FloatArray:
    """Every lidar point of the frame in the site frame, (N, 3)."""
    parts = [np.zeros((0, 3))]
    for sid, path in frame.clouds.items():
        T = dataset.sensors[sid].T_site_from_sensor
        parts.append(read_pcd(path).xyz_m @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(parts)


def in_camera_view(label: RoadsideLabel, scene: Scene, camera: str) -> FloatArray | None:
    """The label's 2D box in `camera`: the dataset's, else its cuboid projected and clipped; None when
    the box is not in the image."""
    if camera in label.boxes_px:
        return np.array(label.boxes_px[camera], np.float64)
    if not label.has_box:
        return None
    view = scene.sensors[camera]
    assert view.camera is not None and view.camera.intrinsics_px is not None
    fx, fy, cx, cy = view.camera.intrinsics_px
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    T = camera_optical_from_world(matrix_from_pose(view.pose.position_m, view.pose.quat_xyzw or (0, 0, 0, 1)))
    corners = box3d_corners(label.box_m[None])
    boxes, visible = box3d_to_image_box(corners, T, K, view.camera.width_px, view.camera.height_px)
    if not visible[0] or boxes[0, 2] <= boxes[0, 0] or boxes[0, 3] <= boxes[0, 1]:
        return None
    return np.asarray(boxes[0], np.float64)


def frame_truth(
    dataset: RoadsideDataset, scene: Scene, frame: RoadsideFrame, counts: Counter[str]
) -> FrameTruthReal:
    """Counted vehicles and ignore regions of one frame (see the module), disagreements counted."""
    has_lidar = bool(frame.clouds)
    xyz = lidar_points_site(dataset, frame) if has_lidar else np.zeros((0, 3))
    cameras = [s for s in dataset.sensors.values() if s.kind == "camera"]
    gt, ignore, points, ids = [], [], [], []
    for label in frame.labels:
        if not label.has_box:
            continue  # labelled in images only: 2D scoring only
        box = label.box_m
        n = int(label.contains(xyz).sum()) if has_lidar else 0
        seen_by_camera = any(in_camera_view(label, scene, c.id) is not None for c in cameras)
        if label.label is None:
            ignore.append(box)
            continue
        counts["labels/vehicles"] += 1
        if has_lidar and n == 0:
            counts["disagree/no_points"] += 1
        if n == 0 and not seen_by_camera:
            counts["disagree/out_of_view"] += 1
        counted = n >= SCORED_MIN_POINTS if has_lidar else seen_by_camera
        if counted:
            gt.append(box)
            points.append(n)
            ids.append(label.object_id)
        else:
            ignore.append(box)
    as_array = lambda rows: np.array(rows).reshape(-1, 7)  # noqa: E731
    return FrameTruthReal(as_array(gt), as_array(ignore), points, ids)


def _shift(boxes: FloatArray, origin_xy: FloatArray) -> FloatArray:
    out = np.array(boxes, np.float64, copy=True)
    if out.size:
        out[:, :2] -= origin_xy
    return out


def evaluate_site(
    dataset: RoadsideDataset,
    mec: MecSettings,
    cameras: CameraDetector | None = None,
    lidar: LidarDetector | None = None,
) -> dict[str, Any]:
    """Run and score one dataset site (see the module); a JSON-ready summary."""
    scene = Scene(site_scene(dataset))
    distances = EvalDistances.for_scene(scene)
    ev = SiteEvaluation(accs={s: FusionAccumulator(distances.match_distance_m) for s in STAGES})
    sensors = list(dataset.sensors.values())
    origin = next((s for s in sensors if s.kind == "lidar"), sensors[0]).T_site_from_sensor[:2, 3]
    decoder = FrameDecoder()
    core: MecCore | None = None
    for frame in dataset.frames:
        if core is None or not dataset.sequence:
            core = MecCore(scene, AGENT_ID, mec, cameras=cameras, lidar=lidar)
            core.tick_hz = SENSOR_RATE_HZ
            cameras = cast(CameraDetector | None, core.pipeline.camera_detector)  # built once, reused
            lidar = cast(LidarDetector | None, core.pipeline.lidar_detector)
        ev.counts.update(f"missing/{name}" for name in frame.missing)
        for sid, stamp in frame.sensor_stamps_ns.items():
            if abs(stamp - frame.stamp_ns) > FRAME_PERIOD_NS:
                ev.counts[f"disagree/stamp_apart/{sid}"] += 1
        messages = frame_messages(dataset, frame)
        if not messages:
            continue
        now_s = max(stamp for _, stamp, _ in messages) / NS_PER_S
        started = time.perf_counter()
        core.cadence(now_s)
        for sid, stamp, msg in messages:
            reason = core.receive(sid, stamp, frame.index, msg, now_s, stamp)
            if reason is not None:
                ev.counts[f"rejected/{reason}/{sid}"] += 1
        out = core.step(now_s) or core.step(now_s + STEP_AFTER_S)
        ev.frame_ms.append((time.perf_counter() - started) * 1e3)
        if out is None:
            ev.counts["frames/not_processed"] += 1
            continue
        ev.counts["frames/scored"] += 1
        result, pipeline = out.result, core.pipeline
        for stage, seconds in result.latencies_s.items():
            ev.latencies_s.setdefault(stage, []).append(seconds)
        images = {
            sid: decoder.image(sid, cast(CompressedImage, msg))
            for sid, _, msg in messages
            if dataset.sensors[sid].kind == "camera"
        }
        singles = single_modality_measurements(result, pipeline, out.inputs, images)
        truth = frame_truth(dataset, scene, frame, ev.counts)
        # stage -> (boxes (N, 7), scores (N,), yaw known (N,): a camera-only object off any lane has none)
        stage_boxes: dict[str, tuple[FloatArray, FloatArray, FloatArray]] = {}
        track_ids: list[int] = []
        if pipeline.lidar_ids:
            lb = result.lidar_boxes_world.reshape(-1, 9)
            stage_boxes["lidar"] = (lb[:, :7], lb[:, 7], np.ones(len(lb), bool))
        if "camera" in singles:
            stage_boxes["camera"] = _measurement_boxes(singles["camera"], pipeline.car_size_m)
        stage_boxes["fused"] = _measurement_boxes(result.measurements, pipeline.car_size_m)
        if dataset.sequence:
            tracks = result.tracks
            rows = [track_box(t, pipeline.car_size_m) for t in tracks]
            boxes = np.array([b for b, _ in rows]).reshape(-1, 7)
            yaw_ok = np.array([ok for _, ok in rows], bool)
            stage_boxes["tracked"] = (boxes, np.array([t.existence_probability for t in tracks]), yaw_ok)
            track_ids = [t.track_id for t in tracks]
        for stage, (boxes, scores, yaw_ok) in stage_boxes.items():
            match = ev.accs[stage].add_frame(
                boxes, truth.gt, yaw_valid=yaw_ok, scores=scores, gt_ignore=truth.ignore
            )
            dets = np.column_stack([boxes, scores, np.zeros(len(boxes))]).reshape(-1, 9)
            ev.kitti.setdefault(stage, []).append(
                (_shift(dets, origin), _shift(truth.gt, origin), _shift(truth.ignore, origin))
            )
            found = np.zeros(len(truth.gt), bool)
            found[match.gt_index] = True
            ev.recall_points.setdefault(stage, []).extend(zip(truth.points, found.tolist(), strict=True))
            ranges_m = np.hypot(*(truth.gt[:, :2] - origin).T).tolist() if len(truth.gt) else []
            ev.recall_range.setdefault(stage, []).extend(zip(ranges_m, found.tolist(), strict=True))
            ev.false_boxes.setdefault(stage, []).append(boxes[match.false_positives].reshape(-1, 7))
            labels = np.full(len(boxes), int(MatchLabel.IGNORED))
            labels[match.pred_index] = MatchLabel.TP
            labels[match.false_positives] = MatchLabel.FP
            ev.scored.setdefault(stage, []).extend(zip(scores.tolist(), labels.tolist(), strict=True))
            if stage == "tracked":
                # Tracks on ignore regions (a vehicle with few points, another class) are not scored.
                counted = np.ones(len(boxes), bool)
                counted[match.ignored] = False
                if ev.tracking is None:
                    ev.tracking = TrackingAccumulator(distances.track_distance_m)
                gt_numbers = [ev.object_numbers.setdefault(i, len(ev.object_numbers)) for i in truth.ids]
                kept = [t for t, c in zip(track_ids, counted, strict=True) if c]
                ev.tracking.update(gt_numbers, truth.gt[:, :2], kept, boxes[counted, :2])
        _score_2d(ev, dataset, scene, frame, result.camera_boxes, pipeline, images)
    ev.counts.update(core.counts() if core is not None else {})
    return summarise(dataset, scene, ev)


def _measurement_boxes(
    rows: Sequence[Any], car_size_m: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    boxes = [measurement_box(m, car_size_m) for m in rows]
    return (
        np.array([b for b, _ in boxes]).reshape(-1, 7),
        np.array([m.score for m in rows], np.float64),
        np.array([ok for _, ok in boxes], bool),
    )


def _score_2d(
    ev: SiteEvaluation,
    dataset: RoadsideDataset,
    scene: Scene,
    frame: RoadsideFrame,
    camera_boxes: dict[str, FloatArray],
    pipeline: Any,
    images: dict[str, FloatArray],
) -> None:
    """Each camera's 2D detections against the labels' 2D boxes (vehicles; others ignored)."""
    skipped = {c: img for c, img in images.items() if c not in camera_boxes}
    found = {**camera_boxes, **(pipeline.detect_2d(skipped) if skipped else {})}
    for cam, dets in found.items():
        if abs(frame.sensor_stamps_ns.get(cam, frame.stamp_ns) - frame.stamp_ns) > FRAME_PERIOD_NS:
            continue  # counted in disagree/stamp_apart: the labels are of another instant
        gt: list[FloatArray] = []
        ignore: list[FloatArray] = []
        for label in frame.labels:
            box = in_camera_view(label, scene, cam)
            if box is None:
                continue
            (gt if label.label is not None else ignore).append(box)
        ev.coco.setdefault(cam, []).append(
            (np.asarray(dets).reshape(-1, 6), np.array(gt).reshape(-1, 4), np.array(ignore).reshape(-1, 4))
        )


def _band_recall(
    rows: Sequence[tuple[float, bool]], bands: Sequence[tuple[float, float]]
) -> dict[str, dict[str, Any]]:
    """Recall per band of a value (points in the box, range in metres): ``{"[lo, hi)": {num_gt, recall}}``."""
    out = {}
    for lo, hi in bands:
        sel = [f for n, f in rows if lo <= n < hi]
        key = f"[{lo:g}, {hi:g})"
        out[key] = {"num_gt": len(sel), "recall": (sum(sel) / len(sel)) if sel else None}
    return out


def yaw_errors_deg(acc: FusionAccumulator) -> dict[str, float | None]:
    """p50 / p95 of the matched boxes' heading error, degrees, modulo 180 (a lidar box's heading is
    known modulo pi): from each pair's pi-invariant orientation similarity (1 + cos 2d) / 2."""
    terms = acc.aos_terms[np.isfinite(acc.aos_terms)]  # NaN: a box without a heading
    if terms.size == 0:
        return {"yaw_error_p50_deg": None, "yaw_error_p95_deg": None}
    err = np.degrees(np.arccos(np.clip(2 * terms - 1, -1.0, 1.0)) / 2)
    return {
        "yaw_error_p50_deg": float(np.percentile(err, 50)),
        "yaw_error_p95_deg": float(np.percentile(err, 95)),
    }


def recall_at_precision(scored: list[tuple[float, int]], num_gt: int, precision: float) -> float | None:
    """The most of the `num_gt` vehicles any score threshold finds while its precision stays at or above
    `precision` (centre-gate matches, ignored boxes left out); None without vehicles."""
    if num_gt == 0:
        return None
    if not scored:
        return 0.0
    scores, labels = zip(*scored, strict=True)
    curve = precision_recall_curve(scores, labels, num_gt)
    ok = curve.precision >= precision
    return float(curve.recall[ok].max()) if ok.any() else 0.0


def false_box_kinds(per_frame: list[FloatArray], gate_m: float) -> dict[str, int]:
    """What the false boxes are likely to be: `fp_recurring`, at the same place (within the centre gate)
    in another frame, i.e. something that stands still (a pole, a tree, a parked trailer no one
    labelled; in a sequence also a car waiting); `fp_elevated`, a box whose bottom is more than
    `ELEVATED_M` above the ground (a sign gantry, a tree crown), which no vehicle on the road has."""
    recurring = elevated = 0
    for i, boxes in enumerate(per_frame):
        others = [b for j, b in enumerate(per_frame) if j != i and len(b)]
        other = np.concatenate(others) if others else np.zeros((0, 7))
        for box in boxes:
            if len(other) and np.hypot(*(other[:, :2] - box[:2]).T).min() <= gate_m:
                recurring += 1
            if box[2] - box[5] / 2 > ELEVATED_M:
                elevated += 1
    return {"fp_recurring": recurring, "fp_elevated": elevated}


def _nan_none(v: float) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def summarise(dataset: RoadsideDataset, scene: Scene, ev: SiteEvaluation) -> dict[str, Any]:
    stages = {}
    for stage, acc in ev.accs.items():
        if stage not in ev.kitti:
            continue
        kitti = evaluate_kitti(ev.kitti[stage], iou_thresholds=AP_IOU_THRESHOLDS, bands=RANGE_BANDS_M)
        ap = {
            f"{kind}@{t:g}": {
                band: {
                    "ap": _nan_none(kitti.results[(kind, t, band)].ap),
                    "num_gt": kitti.results[(kind, t, band)].num_gt,
                }
                for band in kitti.bands
            }
            for kind in ("bev", "3d")
            for t in AP_IOU_THRESHOLDS
        }
        stages[stage] = {
            **acc.summary(with_ap=False),
            "ap": ap,
            "recall_by_points": _band_recall(ev.recall_points[stage], POINT_BANDS),
            "recall_by_range": _band_recall(ev.recall_range[stage], RANGE_BANDS_M),
            **false_box_kinds(ev.false_boxes[stage], acc.max_distance_m),
            "recall_at_target_precision": recall_at_precision(ev.scored[stage], acc.num_gt, TARGET_PRECISION),
            **yaw_errors_deg(acc),
        }
    camera_2d = {}
    for cam, frames in ev.coco.items():
        coco = evaluate_coco(frames, iou_thresholds=(0.5,))
        camera_2d[cam] = {
            "ap50": _nan_none(coco.ap50),
            "frames": len(frames),
            "num_gt": int(sum(len(g) for _, g, _ in frames)),
        }
    ms = np.array(ev.frame_ms) if ev.frame_ms else np.zeros(1)
    return {
        "dataset": dataset.name,
        "format": dataset.format,
        "site_frame": dataset.site_frame,
        "frames": len(dataset.frames),
        "sequence": dataset.sequence,
        "sensors": {s.id: s.kind for s in dataset.sensors.values()},
        "min_lidar_points": SCORED_MIN_POINTS,
        "match_distance_m": EvalDistances.for_scene(scene).match_distance_m,
        "stages": stages,
        "camera_2d": camera_2d,
        "tracking": ev.tracking.summary() if ev.tracking is not None else None,
        "frame_ms": {
            "p50": float(np.percentile(ms, 50)),
            "p95": float(np.percentile(ms, 95)),
            "max": float(ms.max()),
        },
        "counts": dict(sorted(ev.counts.items())),
    }


def with_detectors(mec: MecSettings, camera: str | None, lidar: str | None) -> MecSettings:
    """The settings with the detectors asked for in place of the configured ones. A camera detector
    given runs at fp32 (a card brought from elsewhere has no int8 model beside it). The clustering
    detector links a real lidar's dense cloud cell by cell, as the registry has the background detector
    do (`shared.detection.registry.lidar_detector`; a 49 835-point TUMTraf frame took 46 s pair by
    pair, 0.65 s by cells); nothing else of it is changed (no setting is chosen on the data scored)."""
    change: dict[str, Any] = {}
    if camera is not None:
        change["camera"] = camera
        change["camera_precision"] = "fp32"
    if lidar is not None:
        change["lidar"] = lidar
    if (lidar or mec.detectors.lidar) == "cluster":
        change["cluster"] = {"cluster_grid": True}
    return with_overrides(mec, {"detectors": change}) if change else mec


def read_sites(fmt: str, data: Path) -> list[RoadsideDataset]:
    """The dataset folder's sites in the format named, ground levelled (OpenLABEL, DAIR-V2X: the plane
    their lidar sees; Rope3D: the plane it states)."""
    if fmt == "openlabel":
        dataset = read_openlabel(data)
        return [level_to_ground(dataset, fit_site_ground(dataset))]
    if fmt == "dair":
        return [level_to_ground(site, fit_site_ground(site)) for site in read_dair(data)]
    if fmt == "rope3d":
        return read_rope3d(data)
    raise RoadsideFormatError(f"format {fmt!r}: one of {FORMATS}")


def run_study(fmt: str, data: Path, mec: MecSettings, detectors: dict[str, str | None]) -> dict[str, Any]:
    """Every site of the dataset folder evaluated; the results with the command's provenance. The
    background detector learns each lidar's static scene from a sequence of its frames (its first
    `warmup_frames` call nothing foreground): independent frames are refused for it (ConfigError)."""
    sites = read_sites(fmt, data)
    background = mec.detectors.background
    for site in sites:
        if mec.detectors.lidar == "background" and (
            not site.sequence or len(site.frames) <= background.warmup_frames
        ):
            raise ConfigError(
                f"{site.name}: the background detector learns each lidar's static scene over a sequence of "
                f"more than {background.warmup_frames} frames; these {len(site.frames)} frames are "
                f"{'a sequence' if site.sequence else 'independent'}: use --lidar cluster or a model card"
            )
    return {
        "format": fmt,
        "data": str(data),
        "detectors": detectors,
        "mec_profile": REAL_SIZE_PROFILE,
        "sites": [evaluate_site(site, mec) for site in sites],
        "commit": git_commit(ignore=GENERATED),  # the results and pages it writes are not changes
        "machine": machine_info(),
    }


def target_line(lidar: dict[str, Any]) -> str:
    """The lidar output against the acceptance targets, met or short by how much."""

    def verdict(value: float | None, target: float, above: bool) -> str:
        if value is None:
            return "-"
        met = value >= target if above else value <= target
        return f"{value:.3f} ({'met' if met else f'short by {abs(value - target):.3f}'})"

    at_target = lidar.get("recall_at_target_precision")
    return (
        f"recall at precision >= {TARGET_PRECISION:g} over score thresholds {_f(at_target)}; "
        f"targets: recall {verdict(lidar['recall'], TARGET_RECALL, True)} of >= {TARGET_RECALL:g} at "
        f"precision "
        f"{verdict(lidar['precision'], TARGET_PRECISION, True)} of >= {TARGET_PRECISION:g}; centre error p95 "
        f"{verdict(lidar['pose_error_p95_m'], TARGET_CENTRE_P95_M, False)} m of <= {TARGET_CENTRE_P95_M:g} m"
    )


def _f(value: float | None, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def markdown(results: dict[str, Any]) -> str:
    """The results as the docs show them: per site a table per stage, the 2D AP per camera, the targets
    and the labels set aside."""
    machine = results.get("machine", {})
    det = results["detectors"]
    lines = [
        f"`{results['data']}` ({results['format']}); detectors: camera `{det.get('camera')}`, lidar "
        f"`{det.get('lidar')}`; MEC settings of the `{results['mec_profile']}` profile; commit "
        f"{results['commit']}, {machine.get('cpu_model', '?')}."
    ]
    for site in results["sites"]:
        kind = "a sequence" if site["sequence"] else "independent"
        sensors = ", ".join(f"`{s}` ({k})" for s, k in site["sensors"].items())
        lines += [
            "",
            f"**{site['dataset']}**: {site['frames']} frames ({kind}), sensors {sensors}. Truth: labelled "
            f"vehicles with >= {site['min_lidar_points']} lidar points in their box (a camera-only site: "
            f"every labelled vehicle its camera sees); centre gate {site['match_distance_m']:.2f} m.",
            "",
            "| Output | Vehicles | Boxes | Precision | Recall | Centre error p50 / p95 | Yaw error p50 / p95 "
            "(mod 180°) | BEV AP@0.5 | BEV AP@0.25 | 3D AP@0.5 |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for stage, s in site["stages"].items():
            ap = {k: v["all"]["ap"] for k, v in s["ap"].items()}
            lines.append(
                f"| {stage} | {s['num_gt']} | {s['num_pred']} | {_f(s['precision'])} | {_f(s['recall'])} | "
                f"{_f(s['pose_error_p50_m'], '.2f')} / {_f(s['pose_error_p95_m'], '.2f')} m | "
                f"{_f(s['yaw_error_p50_deg'], '.1f')} / {_f(s['yaw_error_p95_deg'], '.1f')}° | "
                f"{_f(ap['bev@0.5'])} | {_f(ap['bev@0.25'])} | {_f(ap['3d@0.5'])} |"
            )
        lines.append("")
        for stage, s in site["stages"].items():
            by_points = ", ".join(
                f"{k} pts {_f(v['recall'], '.2f')} of {v['num_gt']}"
                for k, v in s["recall_by_points"].items()
                if v["num_gt"]
            )
            recall_by_range = ", ".join(
                f"{k} m {_f(v['recall'], '.2f')} of {v['num_gt']}"
                for k, v in s["recall_by_range"].items()
                if v["num_gt"]
            )
            by_range = ", ".join(
                f"{k} m {_f(v['ap'], '.2f')} ({v['num_gt']})"
                for k, v in s["ap"]["bev@0.25"].items()
                if k != "all" and v["num_gt"]
            )
            lines.append(
                f"- {stage}: recall by points {by_points or '-'}; recall by range {recall_by_range or '-'}; "
                f"BEV AP@0.25 by range {by_range or '-'}; "
                f"of its {s['fp']} false boxes {s['fp_recurring']} recur at the same place in another frame, "
                f"{s['fp_elevated']} float over {ELEVATED_M:g} m above the ground"
            )
        if "lidar" in site["stages"]:
            lines.append("- " + target_line(site["stages"]["lidar"]))
        if site.get("tracking"):
            t = site["tracking"]
            lines.append(
                f"- tracking (the published tracks against the labels' ids): MOTA {_f(t['mota'])}, IDF1 "
                f"{_f(t['idf1'])}, HOTA {_f(t['hota'])} (DetA {_f(t['det_a'])}, AssA {_f(t['ass_a'])}; "
                f"similarity 1 - centre distance / gate), {t['id_switches']} identity switches"
            )
        cams = ", ".join(
            f"`{c}` {_f(v['ap50'])} ({v['num_gt']} vehicles, {v['frames']} frames)"
            for c, v in site["camera_2d"].items()
        )
        lines.append(f"- camera 2D AP@0.5: {cams or '-'}")
        ms = site["frame_ms"]
        lines.append(
            f"- time per frame (the MEC core's, one process): p50 {ms['p50']:.0f} ms, p95 {ms['p95']:.0f} ms"
        )
        set_aside = {
            k: v
            for k, v in site["counts"].items()
            if k.startswith(("disagree/", "missing/", "rejected/", "late/", "stale/"))
        }
        lines.append(
            "- labels and files set aside: "
            + (", ".join(f"{k} {v}" for k, v in set_aside.items()) if set_aside else "none")
        )
    return "\n".join(lines)
