"""Configuration of one MEC (edge) agent: detectors, preprocessing, fusion, tracking, sync, health.

Loaded from `deploy/mec/mec.yaml` (env RMMDET_MEC_<FIELD>, nested with `__`); every field is typed,
has a default and says its unit. The scene file stays the single source of sensor geometry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.config import RmmdetSettings, settings_config, with_overrides
from shared.datasets.layout import agent_origin_m
from shared.detection.lidar.cluster import ClusterLidarConfig, ring_radial_eps_per_m2
from shared.detection.oracle import OracleLidarConfig
from shared.detection.precision import Precision
from shared.paths import REPO_ROOT
from shared.perception.background import BackgroundConfig, RangeImage
from shared.perception.camera_only import CameraOnlyConfig
from shared.perception.lidar_camera import LidarCameraConfig
from shared.perception.lidar_preprocess import LidarPreprocessConfig
from shared.perception.radar_camera import RadarCameraConfig
from shared.scene.cadence import MAX_EVERY_N
from shared.scene.scale import Length, SiteScale, at_scale
from shared.scene.scene import Scene
from shared.tracking.tracker import TrackerConfig

DEFAULT_MEC_CONFIG = REPO_ROOT / "deploy" / "mec" / "mec.yaml"
#: Written by `rmmdet eval calibrate-scores` (tuning seeds); shared/perception/confidence.py.
DEFAULT_SCORE_CALIBRATION = REPO_ROOT / "deploy" / "mec" / "score_calibration.json"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DetectorsConfig(_Model):
    camera: str = Field(
        "onnx",
        description="camera detector (shared.detection.registry): onnx | oracle | the path of a model card "
        "(a YOLOv5/v8/X or other export described by its .yaml, shared.detection.card)",
    )
    lidar: str = Field(
        "pointpillars",
        description="lidar detector: pointpillars | cluster | background (a model of each lidar's static "
        "scene, its foreground clustered) | oracle | the path of a model card (an OpenPCDet PointPillars "
        "export)",
    )
    camera_threads: int = Field(2, ge=1, description="onnxruntime intra-op threads of the camera model")
    lidar_threads: int = Field(2, ge=1, description="onnxruntime intra-op threads of the lidar model")
    camera_precision: Precision = Field(
        "fp32", description="camera model (onnx): fp32 model.onnx | int8 model_int8.onnx (quantized)"
    )
    lidar_precision: Precision = Field(
        "fp32", description="lidar model (pointpillars): fp32 pointpillars.onnx | int8 pointpillars_int8.onnx"
    )
    camera_min_score: float = Field(0.3, ge=0, le=1, description="2D boxes below this score are not fused")
    lidar_min_score: float = Field(0.3, ge=0, le=1, description="3D boxes below this score are not fused")
    camera_every_n_with_lidar: int = Field(
        10,
        ge=1,
        le=MAX_EVERY_N,  # what a sensor group accepts in a capture demand
        description="with a lidar live, run the camera detector on every n-th frame only: the lidar finds "
        "and boxes the cars, the camera only confirms them; 1 = every frame. 10 (each camera at 1 Hz, "
        "staggered) against 5: tracked AP-BEV@0.7 / MOTA / IDF1 within 0.0005 on agents 1 and 3, tuning "
        "seeds 101-103 (docs/eval/camera_cadence)",
    )
    lidar_input: str = Field(
        "merged",
        pattern="^(merged|preprocessed)$",
        description="cloud given to the 3D detector: merged (PointPillars was trained on it) or preprocessed",
    )
    cluster: ClusterLidarConfig = Field(
        default_factory=ClusterLidarConfig,
        description="the `cluster` and `background` lidar detectors' clustering and box fit (vehicle prior "
        "and lidar positions from the scene)",
    )
    background: BackgroundConfig = Field(
        default_factory=BackgroundConfig,
        description="the `background` lidar detector's model of the static scene, per lidar "
        "(shared/perception/background.py); its foreground goes to the cluster detector",
    )
    oracle_lidar: OracleLidarConfig = Field(
        default_factory=OracleLidarConfig, description="the `oracle` lidar detector's error model"
    )


class SyncConfig(_Model):
    collector: str = Field(
        "tick",
        pattern="^(tick|bounded_wait)$",
        description="how an agent frame is joined: tick (simulated sensors: exact join on the sim tick) | "
        "bounded_wait (asynchronous real sensors: frames triggered by `trigger`, the others joined by "
        "nearest stamp within `tolerance_s`, each waited for at most `max_wait_s`)",
    )
    trigger: str | None = Field(
        None,
        description="bounded_wait: sensor whose frames start an agent frame (default first lidar, "
        "else radar, else camera)",
    )
    tolerance_s: float = Field(
        0.05, gt=0, description="bounded_wait: largest |stamp - trigger stamp| of a joined frame, s"
    )
    max_wait_s: float = Field(
        0.2,
        gt=0,
        description="longest wait for an agent frame's expected sensors after its first sample, s of the "
        "clock of record (sim time under a sim)",
    )
    wait_factor: float = Field(
        2.0,
        ge=0,
        description="tick: a frame waits for a sensor this many times the latest it arrived after its "
        "tick's first sample over its recent ticks (within [min_wait_s, max_wait_s]); 0 = max_wait_s always",
    )
    min_wait_s: float = Field(0.03, ge=0, description="tick: shortest learnt wait for a sensor, s")
    max_pending_ticks: int = Field(4, ge=1, description="ticks held at once by the joiner")


class HealthConfig(_Model):
    missing_after_periods: float = Field(3.0, gt=0, description="periods without a frame -> input MISSING")
    max_age_s: float = Field(
        0.2, ge=0, description="frames older than this on arrival are stale (dropped, counted); 0 = off"
    )
    recover_frames: int = Field(3, ge=1, description="all-OK output frames needed to return to FULL")


class MecSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_MEC_")

    detectors: DetectorsConfig = DetectorsConfig()
    preprocess: LidarPreprocessConfig = LidarPreprocessConfig()
    radar_camera: RadarCameraConfig = RadarCameraConfig()
    lidar_camera: LidarCameraConfig = LidarCameraConfig()
    camera_only: CameraOnlyConfig = CameraOnlyConfig()
    tracker: TrackerConfig = TrackerConfig()
    sync: SyncConfig = SyncConfig()
    health: HealthConfig = HealthConfig()
    surface_half_width_m: Length = Field(
        0.2, gt=0, description="road-surface lookup radius around lane samples"
    )
    surface_sample_step_m: Length = Field(
        0.05, gt=0, description="lane centrelines (or a site's bare ground) are sampled at this spacing"
    )
    lidar_position_std_m: Length = Field(
        0.02, gt=0, description="per-axis noise of a lidar box centre given to the tracker (PointPillars)"
    )
    score_calibration: Path | None = Field(
        DEFAULT_SCORE_CALIBRATION,
        description="calibrated-confidence tables (JSON, shared/perception/confidence.py); null: raw scores",
    )
    report_interval_s: float = Field(10.0, gt=0, description="log interval of rates and counters")

    def for_site(self, scene: Scene, agent_id: str) -> MecSettings:
        """These settings for one agent of `scene`: every scaled default at the scene's scale
        (shared/scene/scale.py), and what the scene says filled in: the vehicle prior of the cluster
        detector, of the oracle's false positives and of camera-only objects, the agent's lidar positions
        (agent frame) and their reach. Building them again changes nothing."""
        settings = at_scale(self, SiteScale.of(scene.spec))
        car = scene.spec.vehicle.size_m
        det = settings.detectors
        cluster = det.cluster
        lidars = scene.sensors_of(agent_id, "lidar")
        cluster_fill: dict[str, object] = {"vehicle_size_m": cluster.vehicle_size_m or car}
        if "vehicle_classes_m" not in cluster.model_fields_set:  # the scene's vans and trucks
            cluster_fill["vehicle_classes_m"] = tuple(c.size_m for c in scene.spec.vehicle_classes)
        unset = "cluster_radial_eps_per_m2" not in self.detectors.cluster.model_fields_set
        if det.lidar == "background" and lidars and unset:  # a real lidar's own ring spacing
            roofs = [float(scene.T_world_from_sensor(s.id)[2, 3]) - car[2] for s in lidars]
            layouts = [RangeImage.of(s.lidar).elevations_rad for s in lidars if s.lidar is not None]
            cluster_fill["cluster_radial_eps_per_m2"] = ring_radial_eps_per_m2(layouts, roofs)
        if lidars and "sensor_xy_m" not in cluster.model_fields_set:
            origin = agent_origin_m(scene, agent_id)
            xy = [np.asarray(scene.T_world_from_sensor(s.id))[:2, 3] - origin[:2] for s in lidars]
            cluster_fill["sensor_xy_m"] = tuple((float(x), float(y)) for x, y in xy)
            reach_m = max(s.lidar.max_range_m for s in lidars if s.lidar is not None)
            cluster_fill["max_range_m"] = min(cluster.max_range_m, reach_m)  # no farther than any lidar sees
        oracle = det.oracle_lidar
        return with_overrides(
            settings,
            {
                "detectors": {
                    "cluster": cluster_fill,
                    "oracle_lidar": {"fp_size_m": oracle.fp_size_m or car},
                },
                "camera_only": {"car_size_m": settings.camera_only.car_size_m or car},
            },
        )
