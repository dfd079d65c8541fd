"""`rmmdet train camera|lidar --data DIR --out DIR`: a detector trained on a site's own labelled data
(YOLO or KITTI format, or a generated dataset: `shared.datasets.sources`), end to end.

    train split -> the project's training (training.camera.train / training.pointpillars.train)
    -> ONNX export with its model card beside it (what the MEC loads: `detectors.camera: DIR/model.yaml`)
    -> int8 quantization calibrated on the training split's own frames
    -> metrics.json: the exported fp32 and int8 models scored on the validation split through their card

A dataset without a validation split is split here (`DataSource.val_fraction`). The model directory
holds everything the registry needs; nothing here is specific to the sand table but the default network
configs (give `--config` for another scale, e.g. a lidar grid of tens of metres).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.datasets.sources import DataSource, camera_items
from shared.detection.camera.config import CARD_FILE, ONNX_FILE, ONNX_INPUT, CameraDetectorConfig
from shared.detection.card import LidarCard, save_card
from shared.detection.lidar.pointpillars.config import PointPillarsConfig
from shared.detection.precision import model_file
from shared.detection.registry import LIDAR_CARD as LIDAR_CARD_PATH
from shared.detection.registry import LIDAR_MODEL
from shared.machine import git_commit, machine_info

log = logging.getLogger(__name__)

METRICS_FILE = "metrics.json"
LIDAR_ONNX = LIDAR_MODEL.name  # the names the registry knows the project's own by
LIDAR_CARD = LIDAR_CARD_PATH.name
CALIBRATION_FRAMES = 64  # training-split inputs the int8 calibration sees (evenly spaced)
CAMERA_AP_IOU = 0.5
CARD_NOTE = "model card written by `rmmdet train`"


def evenly(items: list, count: int) -> list:
    if len(items) <= count:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, count).round().astype(int)]


def train_camera(
    data: Path, out: Path, source: DataSource, cfg: CameraDetectorConfig, quantize: bool = True
) -> dict[str, Any]:
    """Train, export (model.onnx + model.yaml), quantize and score a camera detector; returns the metrics
    also written to `out/metrics.json`."""
    from shared.datasets.images import read_rgb
    from shared.detection.camera.geometry import letterbox_image
    from shared.detection.camera.onnx_detector import OnnxCameraDetector
    from shared.metrics.detection import evaluate_coco
    from training.camera.export import export_onnx
    from training.camera.quantize import KEEP_FLOAT, OP_TYPES
    from training.camera.train import train
    from training.quantize import quantize_calibrated

    t0 = time.perf_counter()
    model, record = train(cfg, data, out, source=source)
    export_onnx(model, cfg, out)  # writes the card too
    fp32 = out / ONNX_FILE
    train_items = camera_items(data, "train", source)

    def feeds() -> list[dict[str, np.ndarray]]:
        out_feeds = []
        for item in evenly(train_items, CALIBRATION_FRAMES):
            batch = np.empty((1, cfg.input.height, cfg.input.width, 3), np.uint8)
            letterbox_image(read_rgb(item.image), cfg.input, out=batch[0])
            out_feeds.append({ONNX_INPUT: batch})
        return out_feeds

    if quantize:
        quantize_calibrated(fp32, None, feeds, OP_TYPES, KEEP_FLOAT, "images")
    val_items = camera_items(data, "val", source)
    scores: dict[str, Any] = {}
    for precision in ("fp32", "int8") if quantize else ("fp32",):
        detector = OnnxCameraDetector.from_card(out / CARD_FILE, precision, intra_op_threads=1)
        frames = []
        for item in val_items:
            rgb = read_rgb(item.image)
            boxes, ignore = item.labels(rgb.shape[1], rgb.shape[0])
            frames.append((detector.detect([rgb])[0], boxes, ignore))
        scores[precision] = {"ap50": evaluate_coco(frames, (CAMERA_AP_IOU,)).ap50} if frames else None
    metrics = {
        "kind": "camera",
        "data": str(data),
        "format": source.format_of(data),
        "train_images": record["train_images"],
        "val_images": len(val_items),
        "steps": record["steps"],
        "val": scores,
        "history": record["history"],
    }
    return write_metrics(out, metrics, t0)


def train_lidar(
    data: Path, out: Path, source: DataSource, config: PointPillarsConfig, quantize: bool = True
) -> dict[str, Any]:
    """Train, export (pointpillars.onnx + its JSON + pointpillars.yaml), quantize and score a PointPillars
    detector; returns the metrics also written to `out/metrics.json`."""
    import torch

    from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars
    from training.pointpillars.data import grid_accuracy, read_split, with_mean_size
    from training.pointpillars.export import export_onnx
    from training.pointpillars.quantize import KEEP_FLOAT, OP_TYPES
    from training.pointpillars.train import train
    from training.quantize import quantize_calibrated

    t0 = time.perf_counter()
    torch.set_num_threads(config.train.num_threads)
    train_frames = read_split(data, "train", source=source)
    val_frames = read_split(data, "val", source=source)
    if not train_frames:
        raise FileNotFoundError(f"{data}: no training frames")
    out.mkdir(parents=True, exist_ok=True)
    config = with_mean_size(config, train_frames)
    model, history = train(config, train_frames, val_frames, out)
    fp32 = out / LIDAR_ONNX
    example = next((f.points for f in train_frames if len(f.points)), None)
    export_onnx(model, config, fp32, example)
    card = LidarCard(kind="lidar", model=LIDAR_ONNX, layout="rmmdet_pointpillars", classes={0: "car"})
    save_card(out / LIDAR_CARD, card, CARD_NOTE)
    if quantize:
        detector = OnnxPointPillars(fp32)

        def feeds() -> list[dict[str, np.ndarray]]:
            pillars = (detector.pillarize(f.points) for f in evenly(train_frames, CALIBRATION_FRAMES))
            return [detector.feeds(p) for p in pillars if len(p)]

        quantize_calibrated(fp32, None, feeds, OP_TYPES, KEEP_FLOAT, "frames")
    scores: dict[str, Any] = {}
    for precision in ("fp32", "int8") if quantize else ("fp32",):
        detector = OnnxPointPillars(model_file(fp32, precision))
        dets = [detector.detect(f.points) for f in val_frames]
        scores[precision] = grid_accuracy(dets, val_frames, config.grid) if val_frames else None
    metrics = {
        "kind": "lidar",
        "data": str(data),
        "format": source.format_of(data),
        "train_frames": len(train_frames),
        "val_frames": len(val_frames),
        "val": scores,
        "history": history,
    }
    return write_metrics(out, metrics, t0)


def write_metrics(out: Path, metrics: dict[str, Any], t0: float) -> dict[str, Any]:
    metrics.update(seconds=time.perf_counter() - t0, commit=git_commit(), machine=machine_info())
    (out / METRICS_FILE).write_text(json.dumps(metrics, indent=1, default=float) + "\n")
    log.info("wrote %s", out / METRICS_FILE)
    return metrics
