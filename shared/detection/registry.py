"""Detectors by name or by model card, so services and tools swap them through configuration.

Camera: `onnx` (the committed model in deploy/models/camera, through its card), `coco` (YOLOX-Nano
trained on COCO, deploy/models/coco/yolox_nano, in tiles), `oracle` (noisy ground truth), or the path
of any camera model card (`*.yaml`, `shared.detection.card`: a YOLO-family export, a site's own model;
a card with `tiles` runs in tiles, `shared.detection.camera.tiled`).
Lidar: `pointpillars` (deploy/models/lidar), `cluster` (classical), `oracle`
(noisy ground truth), or the path of a lidar model card (an OpenPCDet PointPillars export).
Learned models load from `models_dir` (default deploy/models) in `precision` fp32 (the export) or int8
(its static quantization beside it, `training.quantize`; shared.detection.precision names the
file); onnxruntime uses `threads` intra-op threads. Imports are lazy: building one detector never
loads the others' libraries.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from shared.detection.camera.config import CARD_FILE, ONNX_FILE
from shared.detection.card import is_card
from shared.detection.interface import CameraDetector, LidarDetector
from shared.detection.precision import model_file
from shared.paths import DEPLOY_DIR

if TYPE_CHECKING:
    from shared.detection.lidar.cluster import ClusterLidarConfig
    from shared.detection.oracle import OracleLidarConfig

MODELS_DIR = DEPLOY_DIR / "models"
CAMERA_DETECTORS = ("onnx", "coco", "oracle")
LIDAR_DETECTORS = ("pointpillars", "cluster", "background", "oracle")
CAMERA_MODEL = Path("camera") / ONNX_FILE
CAMERA_CARD = Path("camera") / CARD_FILE
#: `coco`: YOLOX-Nano trained on COCO (deploy/models/coco/yolox_nano/SOURCE.md), tiled for 1920-px cameras.
COCO_CARD = Path("coco") / "yolox_nano" / CARD_FILE
LIDAR_MODEL = Path("lidar") / "pointpillars.onnx"
LIDAR_CARD = Path("lidar") / "pointpillars.yaml"
QUANTIZE_TOOLS = {
    CAMERA_MODEL: "training.camera.quantize",
    LIDAR_MODEL: "training.pointpillars.quantize",
}


def learned_model(models_dir: Path, model: Path, precision: str) -> Path:
    """The file of `model` (CAMERA_MODEL, LIDAR_MODEL) in `precision` (ValueError if unknown); a
    missing quantized file raises FileNotFoundError naming the tool that writes it."""
    path = model_file(models_dir / model, precision)
    if precision != "fp32" and not path.is_file():
        raise FileNotFoundError(f"no {precision} model {path}: `python -m {QUANTIZE_TOOLS[model]}` writes it")
    return path


def camera_detector(
    name: str, threads: int = 2, seed: int = 0, models_dir: Path = MODELS_DIR, precision: str = "fp32"
) -> CameraDetector:
    if name in ("onnx", "coco") or is_card(name):
        from shared.detection.camera.onnx_detector import OnnxCameraDetector
        from shared.detection.camera.tiled import TiledCameraDetector
        from shared.detection.card import CameraCard, load_card_and_model

        if name == "onnx":
            learned_model(models_dir, CAMERA_MODEL, precision)  # names the tool that writes a missing one
        card = {"onnx": models_dir / CAMERA_CARD, "coco": models_dir / COCO_CARD}.get(name, Path(name))
        parsed, _ = load_card_and_model(card, CameraCard, precision)
        detector: OnnxCameraDetector | TiledCameraDetector
        if parsed.tiles is not None:  # a large image in tiles (shared.detection.camera.tiled)
            detector = TiledCameraDetector.from_card(card, precision, intra_op_threads=threads)
        else:
            detector = OnnxCameraDetector.from_card(card, precision, intra_op_threads=threads)
        if name != "onnx":
            detector.name = f"{detector.name}:{name}"  # results tell the cards apart
        return detector
    if name == "oracle":
        from shared.detection.oracle import OracleCameraDetector

        return OracleCameraDetector(seed=seed)
    raise ValueError(
        f"unknown camera detector {name!r}: expected one of {CAMERA_DETECTORS} or a card (.yaml)"
    )


def lidar_detector(
    name: str,
    threads: int = 1,
    seed: int = 0,
    models_dir: Path = MODELS_DIR,
    precision: str = "fp32",
    cluster: ClusterLidarConfig | None = None,
    oracle: OracleLidarConfig | None = None,
) -> LidarDetector:
    """`cluster` is required for the cluster and background detectors (their settings at the site's scale,
    with the scene's vehicle and lidars: `MecSettings.for_site`; the background detector's static-scene
    removal is the MEC's, per lidar: `shared.perception.background`); `oracle` configures the oracle."""
    if name == "pointpillars" or is_card(name):
        if name == "pointpillars":
            learned_model(models_dir, LIDAR_MODEL, precision)  # names the tool that writes a missing one
        card = models_dir / LIDAR_CARD if name == "pointpillars" else Path(name)
        lidar = lidar_from_card(card, precision, threads)
        if name != "pointpillars":
            lidar.name = f"{lidar.name}:{name}"  # results tell the cards apart
        return lidar
    if name in ("cluster", "background"):  # background: the MEC removes each lidar's static scene first
        from shared.detection.lidar.cluster import ClusterLidarDetector

        if cluster is None:
            raise ValueError(f"the {name} detector needs its settings for the site (the scene's vehicle)")
        # A real lidar's dense foreground is linked cell by cell, and close queues split; the table's
        # cluster detector links every pair and searches a too large cluster for the deck.
        real = name == "background"
        if cluster.cluster_grid is None:
            cluster = cluster.model_copy(update={"cluster_grid": real})
        if cluster.oversize_splits is None:
            cluster = cluster.model_copy(update={"oversize_splits": 2 if real else 0})
        detector = ClusterLidarDetector(cluster)
        detector.name = name
        return detector
    if name == "oracle":
        from shared.detection.oracle import OracleLidarDetector

        return OracleLidarDetector(oracle, seed=seed)
    raise ValueError(f"unknown lidar detector {name!r}: expected one of {LIDAR_DETECTORS} or a card (.yaml)")


def lidar_from_card(card_path: Path, precision: str = "fp32", threads: int = 1) -> LidarDetector:
    """The lidar detector a card describes: the project's PointPillars (its grid and head from the JSON
    beside the model), an OpenPCDet anchor-head export (`shared.detection.lidar.openpcdet`) or an
    OpenPCDet CenterPoint export (`shared.detection.lidar.openpcdet_center`)."""
    from shared.detection.card import LidarCard, load_card_and_model

    card, path = load_card_and_model(card_path, LidarCard, precision)
    if card.layout == "rmmdet_pointpillars":
        from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars

        return OnnxPointPillars(path, threads=threads)
    if card.layout == "openpcdet_center":
        from shared.detection.lidar.openpcdet_center import OpenPCDetCenterPoint

        return OpenPCDetCenterPoint(path, card, threads=threads)
    from shared.detection.lidar.openpcdet import OpenPCDetPointPillars

    return OpenPCDetPointPillars(path, card, threads=threads)
