"""One agent's perception pipeline: detect, fuse and track one synchronised agent frame (no bus inside).

    AgentInputs (images, clouds, radar scans of one tick; absent sensors simply missing)
      -> 2D detection: all of the agent's images in one batched call (with a lidar live, only every
         `camera_every_n_with_lidar`-th frame: the lidar finds the cars, the camera confirms them;
         on sim ticks the frames `Scene.captures_on` names, one camera after another, which the MEC
         also asks the cameras to capture)
      -> lidar: merge clouds into the agent frame (full extrinsics), preprocess, 3D detection, to world
      -> radar + camera (Algorithm 1) for each radar and its paired camera
      -> lidar + camera (Algorithm 2 + merge) over the agent's cameras
      -> camera-only objects where no range sensor is available (degraded) or by policy
      -> tracker (constant-velocity Kalman filter, Hungarian association, confirm / coast / delete)
    AgentResult (confirmed tracks, the fused measurements, pre-fusion boxes, stage latencies)

What runs is decided per frame by which inputs arrived, so a dead sensor changes the path, never
stops it: without cameras the lidar (or radar) boxes go straight to the tracker; without the lidar
(or radar) the camera boxes are placed on the road surface.
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from shared.datasets.layout import agent_origin_m
from shared.detection.interface import CameraDetector, DetectorInputError, LidarDetector
from shared.detection.lidar.cluster import ClusterLidarDetector
from shared.detection.registry import camera_detector, lidar_detector
from shared.geometry.boxes import in_bev_boxes
from shared.perception import camera_only, lidar_camera, radar_camera
from shared.perception.background import AgentGround, RangeImage, site_background
from shared.perception.confidence import FUSED, ScoreCalibration
from shared.perception.config import MecSettings
from shared.perception.lidar_preprocess import agent_frame_transforms, merge_clouds, preprocess
from shared.perception.radar_camera import RadarTargets
from shared.perception.views import CameraView, RoadSurface
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.tracking.measurement import CAMERA, LIDAR, RADAR, Measurement
from shared.tracking.track_table import Track
from shared.tracking.tracker import MultiObjectTracker

FloatArray = NDArray[np.float64]


@dataclass
class AgentInputs:
    """One synchronised agent frame. Sensors without data this tick are absent from the dicts."""

    stamp_ns: int
    tick: int = 0
    images: dict[str, np.ndarray] = field(default_factory=dict)  # camera id -> (H, W, 3) uint8 RGB
    clouds: dict[str, np.ndarray] = field(default_factory=dict)  # lidar id -> (N, 4) sensor frame
    radar: dict[str, RadarTargets] = field(default_factory=dict)

    def add(self, kind: str, sensor_id: str, data: np.ndarray | RadarTargets) -> None:
        """File one decoded frame under its kind."""
        if kind == "camera":
            self.images[sensor_id] = data  # type: ignore[assignment]
        elif kind == "lidar":
            self.clouds[sensor_id] = data  # type: ignore[assignment]
        else:
            self.radar[sensor_id] = data  # type: ignore[assignment]


@dataclass
class AgentResult:
    stamp_ns: int
    tracks: list[Track]  # published: confirmed and coasting
    measurements: list[Measurement]  # what the tracker was given (post-fusion, per frame)
    lidar_boxes_world: FloatArray  # (M, 9) 3D detections before fusion (world frame)
    camera_boxes: dict[str, FloatArray]  # per camera (N, 6) 2D detections
    latencies_s: dict[str, float]
    counts: Counter[str]
    modalities_present: frozenset[str]


def lidar_measurement(
    box: FloatArray, score: float, modalities: frozenset[str], sensors: tuple[str, ...], position_std_m: float
) -> Measurement:
    """A lidar box as a tracker measurement; `position_std_m`: per-axis noise of its centre, m."""
    return Measurement(
        position_m=np.asarray(box[:2], float),
        position_cov_m2=np.eye(2) * position_std_m**2,
        z_m=float(box[2]),
        size_m=np.asarray(box[3:6], float),
        yaw_rad=float(box[6]),
        yaw_mod_pi=True,  # PointPillars' direction bit is at chance: yaw is known modulo pi
        range_rate=None,
        modalities=modalities,
        score=float(score),
        sensor_ids=sensors,
    )


def camera_measurement(obj: camera_only.CameraObject) -> Measurement:
    """A camera-only object as a tracker measurement (yaw: the lane's direction of travel, if known)."""
    return Measurement(
        position_m=obj.box[:2].copy(),
        position_cov_m2=obj.cov_xy_m2,
        z_m=float(obj.box[2]),
        size_m=obj.box[3:6].copy(),
        yaw_rad=float(obj.box[6]) if obj.yaw_known else None,
        yaw_mod_pi=False,
        range_rate=None,
        modalities=frozenset({CAMERA}),
        score=obj.score,
        sensor_ids=obj.sensor_ids,
    )


class AgentPipeline:
    """Detect-fuse-track for one agent. Detectors may be injected (tests, oracles)."""

    def __init__(
        self,
        scene: Scene,
        agent_id: str,
        settings: MecSettings,
        cameras: CameraDetector | None = None,
        lidar: LidarDetector | None = None,
        sensor_ids: Collection[str] | None = None,
    ) -> None:
        """`sensor_ids`: fuse only these of the agent's sensors (default all; tests, partial sites)."""
        settings = settings.for_site(scene, agent_id)  # the scene's scale and sizes (idempotent)
        self.scene = scene
        self.agent_id = agent_id
        self.cfg = settings
        specs = [s for s in scene.sensors_of(agent_id) if sensor_ids is None or s.id in sensor_ids]
        self.camera_ids = [s.id for s in specs if s.kind == "camera"]
        self.lidar_ids = [s.id for s in specs if s.kind == "lidar"]
        self.radar_specs = [s for s in specs if s.kind == "radar"]
        self.views = {c: CameraView.from_scene(scene, c) for c in self.camera_ids}
        self.surface = RoadSurface(
            scene, settings.surface_half_width_m, settings.surface_sample_step_m, agent_id
        )
        assert settings.camera_only.car_size_m is not None  # for_site fills it from the scene
        self.car_size_m = settings.camera_only.car_size_m
        det = settings.detectors
        self.camera_detector = cameras
        if self.camera_detector is None and self.camera_ids:
            self.camera_detector = camera_detector(
                det.camera, threads=det.camera_threads, precision=det.camera_precision
            )
            if hasattr(self.camera_detector, "warm_up"):  # the ONNX model: its arena at size from the start
                self.camera_detector.warm_up(len(self.camera_ids))
        self.lidar_detector = lidar
        if self.lidar_detector is None and self.lidar_ids:
            self.lidar_detector = lidar_detector(
                det.lidar,
                threads=det.lidar_threads,
                precision=det.lidar_precision,
                cluster=det.cluster,
                oracle=det.oracle_lidar,
            )
            if hasattr(self.lidar_detector, "warm_up"):  # the ONNX model: its arena at size from the start
                self.lidar_detector.warm_up()
        # The background detector: each lidar's static scene removed from its own cloud, before merging.
        self.backgrounds = {
            s.id: site_background(RangeImage.of(s.lidar), det.background, scene.scene_id, s.id)
            for s in specs
            if s.lidar is not None and det.lidar == "background"
        }
        # Their static points give the ground plane the cluster detector measures heights from.
        self.ground = AgentGround(
            det.background, det.cluster.ground_tolerance_m, det.cluster.surfaces.max_tilt_rad
        )
        self.origin_m = agent_origin_m(scene, agent_id) if self.lidar_ids else np.zeros(3)
        self.lidar_T = agent_frame_transforms(scene, agent_id) if self.lidar_ids else {}
        self.radar_T = {s.id: np.asarray(scene.T_world_from_sensor(s.id), float) for s in self.radar_specs}
        self.tracker = MultiObjectTracker(settings.tracker)
        path = settings.score_calibration
        self.calibration = ScoreCalibration.load(path) if path is not None else ScoreCalibration()
        self.counts: Counter[str] = Counter()
        # A saved background that could not be used (the lidar learns online): counted, so the health
        # report's rejections show it as well as the start-up log line.
        self.counts.update(
            "rejected/background_model" for b in self.backgrounds.values() if b.refused_model is not None
        )
        self.last_reduction = float("nan")
        self._lidar_frames = 0  # frames processed with a lidar live (camera cadence without ticks)
        # The sim's tick rate where frames come from a sim (set by the driver): the camera cadence is
        # then a function of the tick, shared with the cameras' capture demand.
        self.tick_hz: float | None = None
        self._2d_cache: dict[str, tuple[np.ndarray, FloatArray]] = {}  # camera -> (image, its boxes)
        self._ahead: set[str] = set()  # cameras whose cached boxes were detected ahead of their frame

    # --- stages ---------------------------------------------------------------------------------

    def camera_every_n(self, lidar_live: bool) -> int:
        """Every how many frames the camera detector runs: 1 without a live lidar, else
        `detectors.camera_every_n_with_lidar`."""
        return self.cfg.detectors.camera_every_n_with_lidar if lidar_live else 1

    def cameras_due(self, lidar_live: bool, tick: int) -> frozenset[str]:
        """The cameras whose images the detector runs on in the frame of `tick` (the MEC decodes only
        those). With `tick_hz` known: the cameras that capture on that tick (`Scene.captures_on`,
        staggered over the n frames); without (real sensors): all of them on every n-th processed
        frame, none in between."""
        n = self.camera_every_n(lidar_live)
        if self.tick_hz is not None:
            hz, scene = self.tick_hz, self.scene
            return frozenset(c for c in self.camera_ids if scene.captures_on(scene.sensor(c), tick, hz, n))
        return frozenset(self.camera_ids) if self._lidar_frames % n == 0 else frozenset()

    def lidar_live(self, sensor_ids: Collection[str]) -> bool:
        """True if any of `sensor_ids` is one of this agent's lidars."""
        return any(c in sensor_ids for c in self.lidar_ids)

    def detect_2d(self, images: dict[str, np.ndarray]) -> dict[str, FloatArray]:
        """2D boxes per camera, one batched detector call. A read-only image that is the very array
        this camera's boxes were last computed on (`FrameDecoder` hands a repeated frame back
        unchanged) reuses those boxes."""
        ids = [c for c in self.camera_ids if c in images]
        if not ids or self.camera_detector is None:
            return {}
        out: dict[str, FloatArray] = {}
        run = []
        for c in ids:
            cached = self._2d_cache.get(c)
            if cached is not None and cached[0] is images[c] and c in self._ahead:
                out[c] = cached[1]  # detected ahead (`detect_ahead`) on this very image
            elif cached is not None and cached[0] is images[c] and not images[c].flags.writeable:
                out[c] = cached[1]
                self.counts["camera/repeated_frame"] += 1
            else:
                run.append(c)
            self._ahead.discard(c)
        if run:
            self._detect(run, [images[c] for c in run])
            out.update((c, self._2d_cache[c][1]) for c in run)
        return {c: out[c] for c in ids}

    def detect_ahead(self, camera_id: str, image: np.ndarray) -> bool:
        """Detect one camera's image as soon as it arrives, while the agent's other sensors of that tick
        are still on their way; `detect_2d` on the joined frame then reuses the boxes (the image must be
        the very same array). Work moves off the frame's critical path; it is not saved. A repeated
        frame (see `detect_2d`), or one the detector rejects, is left for `detect_2d` (which counts
        the rejection with its frame). Returns whether boxes were made."""
        if self.camera_detector is None or camera_id not in self.camera_ids:
            return False
        cached = self._2d_cache.get(camera_id)
        if cached is not None and cached[0] is image and not image.flags.writeable:
            return False
        try:
            self._detect([camera_id], [image])
        except DetectorInputError:
            return False
        self._ahead.add(camera_id)
        return True

    def _detect(self, cameras: list[str], images: list[np.ndarray]) -> None:
        """One batched detector call; the boxes above the score threshold cached per camera."""
        min_score = self.cfg.detectors.camera_min_score
        for c, img, d in zip(cameras, images, self.camera_detector.detect(images), strict=True):  # type: ignore[union-attr]
            self._2d_cache[c] = (img, np.asarray(d[d[:, 4] >= min_score], float))

    def _point_sensors(self, ids: list[str], clouds: dict[str, np.ndarray]) -> NDArray[np.int64]:
        """For the merged cloud of `ids` (scan after scan): each point's lidar as the cluster detector
        numbers them (its `sensor_xy_m`, the agent frame: matched by position)."""
        assert isinstance(self.lidar_detector, ClusterLidarDetector)
        sensors = np.asarray(self.lidar_detector.config.sensor_xy_m, float).reshape(-1, 2)
        index = [int(np.argmin(np.linalg.norm(sensors - self.lidar_T[c][:2, 3], axis=1))) for c in ids]
        return np.repeat(np.asarray(index, np.int64), [len(clouds[c]) for c in ids])

    def detect_3d(self, clouds: dict[str, np.ndarray]) -> FloatArray:
        """(M, 9) world-frame boxes `[x, y, z, dx, dy, dz, yaw, score, class]` of the agent's lidars."""
        ids = [c for c in self.lidar_ids if c in clouds]
        if not ids or self.lidar_detector is None:
            return np.zeros((0, 9))
        seen = {c: self.backgrounds[c].classify(clouds[c][:, :3]) for c in ids if self.backgrounds}
        if seen:
            clouds = {c: clouds[c][seen[c].front] for c in ids}
            if isinstance(self.lidar_detector, ClusterLidarDetector):
                self.lidar_detector.ground = self.ground.update(self.backgrounds, self.lidar_T)
        merged = merge_clouds([(self.lidar_T[c], clouds[c]) for c in ids])
        if self.cfg.detectors.lidar_input == "preprocessed":
            pre = preprocess(merged, self.cfg.preprocess)
            self.last_reduction = pre.reduction_fraction
            merged = pre.points
        elif isinstance(self.lidar_detector, ClusterLidarDetector) and len(ids) > 1:
            self.lidar_detector.point_sensor = self._point_sensors(ids, clouds)
        boxes = np.asarray(self.lidar_detector.detect(merged), float)
        boxes = boxes[boxes[:, 7] >= self.cfg.detectors.lidar_min_score]
        for c, revolution in seen.items():  # learned now: a detected vehicle hides the background
            front = revolution.front
            hidden = np.zeros(len(front), bool)
            if len(boxes) and front.any():
                agent_xy = merge_clouds([(self.lidar_T[c], clouds[c])])[:, :2]
                hidden[front] = in_bev_boxes(
                    agent_xy, boxes[:, :7], self.cfg.detectors.background.vehicle_growth
                )
            self.backgrounds[c].learn(revolution, hidden)
        boxes[:, :3] += self.origin_m
        return boxes

    # --- one frame ------------------------------------------------------------------------------

    def process(self, frame: AgentInputs) -> AgentResult:
        lat: dict[str, float] = {}
        counts: Counter[str] = Counter()
        t0 = time.perf_counter()
        if not (frame.images or frame.clouds or frame.radar):  # nothing arrived: the tracks coast
            tracks = self.tracker.coast(frame.stamp_ns / NS_PER_S)
            lat["track"] = time.perf_counter() - t0
            self.counts["frames/coasted"] += 1
            return AgentResult(frame.stamp_ns, tracks, [], np.zeros((0, 9)), {}, lat, counts, frozenset())
        lidar_live = self.lidar_live(frame.clouds)
        dets2d: dict[str, FloatArray] = {}
        due = self.cameras_due(lidar_live, frame.tick)
        images = {c: img for c, img in frame.images.items() if c in due}
        if images:
            try:
                dets2d = self.detect_2d(images)
            except DetectorInputError:
                counts["rejected/camera_input"] += 1
        if len(images) < len(frame.images):
            counts["camera/skipped_with_lidar"] += 1
        self._lidar_frames += lidar_live
        t1 = time.perf_counter()
        lat["detect_2d"] = t1 - t0
        try:
            boxes3d = self.detect_3d(frame.clouds)
        except DetectorInputError:
            counts["rejected/lidar_input"] += 1
            boxes3d = np.zeros((0, 9))
        t2 = time.perf_counter()
        lat["detect_3d"] = t2 - t1
        measurements = self.calibration.apply(FUSED, self._fuse(frame, dets2d, boxes3d, counts), counts)
        t3 = time.perf_counter()
        lat["fuse"] = t3 - t2
        self.tracker.step(frame.stamp_ns / NS_PER_S, measurements)
        tracks = self.tracker.confirmed()
        lat["track"] = time.perf_counter() - t3
        present = frozenset(
            m
            for m, ok in (
                (CAMERA, bool(dets2d) or bool(frame.images)),
                (LIDAR, bool(frame.clouds)),
                (RADAR, bool(frame.radar)),
            )
            if ok
        )
        self.counts.update(counts)
        return AgentResult(frame.stamp_ns, tracks, measurements, boxes3d, dets2d, lat, counts, present)

    def _fuse(
        self, frame: AgentInputs, dets2d: dict[str, FloatArray], boxes3d: FloatArray, counts: Counter[str]
    ) -> list[Measurement]:
        out: list[Measurement] = []
        used_2d: dict[str, set[int]] = {c: set() for c in dets2d}
        have_lidar = bool(self.lidar_ids) and any(c in frame.clouds for c in self.lidar_ids)
        have_radar = bool(self.radar_specs) and any(r.id in frame.radar for r in self.radar_specs)
        lc = self.cfg.lidar_camera
        if have_lidar:
            views = [self.views[c] for c in dets2d]
            res = lidar_camera.match_boxes(boxes3d[:, :7], boxes3d[:, 7], views, dets2d, lc.min_iou)
            counts["lidar_camera/matched"] += len(res.matches)
            counts["lidar_camera/masked"] += res.masked
            for cam in {c for _, c, _, _ in res.matches}:
                pairs = [(i, j) for i, c, j, _ in res.matches if c == cam]
                rows, cols = [p[0] for p in pairs], [p[1] for p in pairs]
                used_2d[cam].update(cols)
                merged, applied = lidar_camera.merge_boxes(
                    boxes3d[rows, :7], dets2d[cam][cols], self.views[cam], lc
                )
                counts["lidar_camera/merged"] += int(applied.sum())
                for box, i, j in zip(merged, rows, cols, strict=True):
                    s_lidar, s_camera = float(boxes3d[i, 7]), float(dets2d[cam][j, 4])
                    if lc.matched_score == "noisy_or":  # two independent confirmations
                        score = 1.0 - (1.0 - s_lidar) * (1.0 - s_camera)
                    else:
                        score = max(s_lidar, s_camera)
                    modalities = frozenset({LIDAR, CAMERA})
                    sensors = (cam, *self.lidar_ids)
                    out.append(
                        lidar_measurement(box, score, modalities, sensors, self.cfg.lidar_position_std_m)
                    )
            # Without any camera there is nothing to confirm with: lidar boxes pass (degraded mode).
            # With cameras, a lidar box no camera confirmed must be confident on its own.
            if lc.keep_unmatched_lidar or not dets2d:
                min_score = lc.unmatched_lidar_min_score if dets2d else 0.0
                for i in [i for i in res.unmatched_3d if boxes3d[i, 7] >= min_score]:
                    out.append(
                        lidar_measurement(
                            boxes3d[i, :7],
                            boxes3d[i, 7],
                            frozenset({LIDAR}),
                            tuple(self.lidar_ids),
                            self.cfg.lidar_position_std_m,
                        )
                    )
            for cam, unused in res.unused_2d.items():
                used_2d[cam].update(set(range(len(dets2d[cam]))) - set(unused))
        per_radar = self.radar_measurements(frame, dets2d, used_2d, counts) if have_radar else []
        # Camera boxes no range sensor accounted for: kept when no range sensor covers that camera this
        # frame (degraded, or a camera without a paired radar), else by the unmatched-camera policy.
        paired = {r.paired_camera for r in self.radar_specs if r.id in frame.radar}
        leftovers = {}
        for c, d in dets2d.items():
            covered = have_lidar or c in paired
            if covered and not self.cfg.camera_only.keep_unconfirmed:
                continue
            leftovers[c] = d[[j for j in range(len(d)) if j not in used_2d[c]]]
        camera_list: list[Measurement] = []
        if leftovers:
            # With a range sensor live, a monocular position is trusted only if enough cameras agree.
            min_cameras = self.cfg.camera_only.min_cameras_with_range if (have_lidar or have_radar) else 1
            for obj in camera_only.locate(
                self.views, leftovers, self.surface, self.cfg.camera_only, self.car_size_m
            ):
                if len(obj.sensor_ids) < min_cameras:
                    counts["camera_only/single_camera_dropped"] += 1
                    continue
                counts["camera_only"] += 1
                camera_list.append(camera_measurement(obj))
        # One measurement per car: the radars' lists and the camera-only objects merge when close
        # (a car two radars see, or a radar car another camera sees too).
        if per_radar:
            out += merge_across_sensors(
                [*per_radar, camera_list], self.cfg.radar_camera.cross_radar_gate_m, counts
            )
        elif out and camera_list:
            # Lidar agent: a camera-only object near a lidar box is that box's car seen again, not a
            # car the lidar missed.
            lidar_xy = np.array([m.position_m for m in out])
            gate = self.cfg.camera_only.merge_radius_m
            for m in camera_list:
                if np.min(np.linalg.norm(lidar_xy - m.position_m, axis=1)) > gate:
                    out.append(m)
                    counts["camera_only/fill_in"] += 1
        else:
            out += camera_list
        return out

    def radar_measurements(
        self,
        frame: AgentInputs,
        dets2d: dict[str, FloatArray] | None = None,
        used_2d: dict[str, set[int]] | None = None,
        counts: Counter[str] | None = None,
    ) -> list[list[Measurement]]:
        """Algorithm 1 (`radar_camera.radar_measurements`) per radar and its paired camera: one
        measurement list per radar that delivered targets."""
        dets2d = {} if dets2d is None else dets2d
        used_2d = {c: set() for c in dets2d} if used_2d is None else used_2d
        counts = Counter() if counts is None else counts
        per_radar: list[list[Measurement]] = []
        for spec in self.radar_specs:
            targets = frame.radar.get(spec.id)
            if targets is None or len(targets) == 0:
                continue
            per_radar.append(
                radar_camera.radar_measurements(
                    spec,
                    targets,
                    self.radar_T[spec.id],
                    self.cfg.radar_camera,
                    self.surface,
                    self.views,
                    self.car_size_m,
                    dets2d,
                    used_2d,
                    counts,
                )
            )
        return per_radar


def merge_across_sensors(
    per_sensor: list[list[Measurement]], gate_m: float, counts: Counter[str]
) -> list[Measurement]:
    """One measurement per car when several radars see it: pair each sensor's list with the merged
    ones so far (Hungarian within `gate_m`) and fuse pairs by their covariances (the first's range rate
    is kept: one radial direction per measurement)."""
    merged: list[Measurement] = []
    for meas in per_sensor:
        pairs, _, new = radar_camera.pair_observations(
            np.array([m.position_m for m in merged]).reshape(-1, 2),
            np.array([m.position_m for m in meas]).reshape(-1, 2),
            gate_m,
        )
        counts["radar/cross_merged"] += len(pairs)
        for i, j in pairs:
            a, b = merged[i], meas[j]
            xy, cov = radar_camera.fuse_positions(
                a.position_m[None], a.position_cov_m2[None], b.position_m[None], b.position_cov_m2[None]
            )
            merged[i] = dataclasses.replace(
                a,
                position_m=xy[0],
                position_cov_m2=cov[0],
                modalities=a.modalities | b.modalities,
                score=max(a.score, b.score),
                sensor_ids=tuple(dict.fromkeys(a.sensor_ids + b.sensor_ids)),
            )
        merged += [meas[j] for j in new]
    return merged
