"""Configuration of one MEC (edge) agent: detectors, preprocessing, fusion, tracking, sync, health.

Loaded from `deploy/mec/mec.yaml` (env RMMDET_MEC_<FIELD>, nested with `__`); every field is typed,
has a default and says its unit. The scene file stays the single source of sensor geometry.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from shared.config import RmmdetSettings, settings_config
from shared.detection.precision import Precision
from shared.paths import REPO_ROOT
from shared.perception.camera_only import CameraOnlyConfig
from shared.perception.lidar_camera import LidarCameraConfig
from shared.perception.lidar_preprocess import LidarPreprocessConfig
from shared.perception.radar_camera import RadarCameraConfig
from shared.scene.cadence import MAX_EVERY_N
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
        description="lidar detector: pointpillars | cluster | oracle | the path of a model card (an "
        "OpenPCDet PointPillars export)",
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
    surface_half_width_m: float = Field(
        0.2, gt=0, description="road-surface lookup radius around lane samples"
    )
    score_calibration: Path | None = Field(
        DEFAULT_SCORE_CALIBRATION,
        description="calibrated-confidence tables (JSON, shared/perception/confidence.py); null: raw scores",
    )
    report_interval_s: float = Field(10.0, gt=0, description="log interval of rates and counters")
