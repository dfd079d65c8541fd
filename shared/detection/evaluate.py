"""Detector evaluation on a generated dataset's split (`rmmdet eval detectors`).

Camera: every image of the split, batched per (seed, tick) like an agent's cameras; COCO AP@0.5 and
AP@0.5:0.95 against the labelled boxes, with the meta file's ignore boxes as ignore regions.
Lidar: every agent frame of the split; KITTI R40 AP for BEV and 3D at IoU 0.5 and 0.7, overall and
by distance band from the agent origin, with the meta file's ignore boxes as DontCare.
Latency: p50 / p95 of `detect` per call (camera: per image, batch 1; lidar: per agent frame), with
pre- and post-processing, measured on the split's first frames.
Oracle detectors get the labels of each frame as their truth (`set_truth`) before `detect`.
"""

from __future__ import annotations

import json
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.datasets import openpcdet, yolo
from shared.datasets.images import read_rgb
from shared.datasets.layout import DatasetLayout
from shared.detection.interface import CameraDetector, LidarDetector
from shared.metrics.detection import RecallSampling, evaluate_coco, evaluate_kitti

LATENCY_WARMUP = 5
NS_PER_MS = 1e6


@dataclass(frozen=True)
class CameraSample:
    stem: str
    image: np.ndarray  # (H, W, 3) RGB
    boxes: np.ndarray  # (G, 4)
    ignore: np.ndarray  # (I, 4)


@dataclass(frozen=True)
class LidarSample:
    stem: str
    points: np.ndarray  # (N, 4)
    boxes: np.ndarray  # (G, 7)
    ignore: np.ndarray  # (I, 7)


def camera_samples(layout: DatasetLayout, split: str, limit: int | None = None) -> Iterator[CameraSample]:
    for stem in layout.camera_stems(split)[:limit]:
        image = read_rgb(layout.camera_image(split, stem))
        height, width = image.shape[:2]
        boxes, _ = yolo.read_yolo(layout.yolo_label(split, stem), width, height)
        meta = json.loads(layout.camera_meta(split, stem).read_text())
        yield CameraSample(stem, image, boxes, np.asarray(meta["ignore"], float).reshape(-1, 4))


def lidar_samples(layout: DatasetLayout, split: str, limit: int | None = None) -> Iterator[LidarSample]:
    for stem in layout.lidar_stems(split)[:limit]:
        boxes, _ = openpcdet.read_labels(layout.pcdet_label(stem))
        meta = json.loads(layout.lidar_meta(stem).read_text())
        yield LidarSample(
            stem,
            openpcdet.read_points(layout.pcdet_points(stem)),
            boxes,
            np.asarray(meta["ignore"], float).reshape(-1, 7),
        )


def tick_key(stem: str) -> str:
    """`s0001_t000240_cam_43` -> `s0001_t000240`: the images of one tick form one batch."""
    return "_".join(stem.split("_")[:2])


def _set_truth(detector: Any, truth: Any) -> None:
    if hasattr(detector, "set_truth"):
        detector.set_truth(truth)


def evaluate_camera(
    detector: CameraDetector, layout: DatasetLayout, split: str, limit: int | None = None
) -> dict[str, Any]:
    batches: dict[str, list[CameraSample]] = defaultdict(list)
    for sample in camera_samples(layout, split, limit):
        batches[tick_key(sample.stem)].append(sample)
    frames = []
    for batch in batches.values():
        _set_truth(detector, [s.boxes for s in batch])
        for sample, dets in zip(batch, detector.detect([s.image for s in batch]), strict=True):
            frames.append((dets, sample.boxes, sample.ignore))
    summary = evaluate_coco(frames)
    return {
        "detector": detector.name,
        "split": split,
        "images": len(frames),
        "gt_boxes": int(sum(len(f[1]) for f in frames)),
        "ap50": summary.ap50,
        "ap50_95": summary.ap50_95,
    }


def camera_latency(detector: CameraDetector, samples: list[CameraSample]) -> dict[str, float]:
    """Per-image latency (batch of 1), pre- and post-processing included."""

    def call(sample: CameraSample) -> None:
        _set_truth(detector, [sample.boxes])
        detector.detect([sample.image])

    return latency(call, samples)


def lidar_latency(detector: LidarDetector, samples: list[LidarSample]) -> dict[str, float]:
    """Per-agent-frame latency, pre- and post-processing included."""

    def call(sample: LidarSample) -> None:
        _set_truth(detector, sample.boxes)
        detector.detect(sample.points)

    return latency(call, samples)


def evaluate_lidar(
    detector: LidarDetector,
    layout: DatasetLayout,
    split: str,
    limit: int | None = None,
    recall_sampling: RecallSampling = "r40",
) -> dict[str, Any]:
    """KITTI-style AP of `detector` on a split; `recall_sampling="devkit"` samples as the KITTI devkit
    (shared/metrics/detection.py `devkit_ap`), to compare with it number for number."""
    frames = []
    samples = list(lidar_samples(layout, split, limit))
    for sample in samples:
        _set_truth(detector, sample.boxes)
        frames.append((detector.detect(sample.points), sample.boxes, sample.ignore))
    summary = evaluate_kitti(frames, recall_sampling=recall_sampling)
    return {
        "detector": detector.name,
        "recall_sampling": recall_sampling,
        "split": split,
        "frames": len(frames),
        "gt_boxes": int(sum(len(f[1]) for f in frames)),
        "ap": summary.rows(),
        "bev_ap70": summary.ap("bev", 0.7),
        "bev_ap50": summary.ap("bev", 0.5),
        "ap3d_70": summary.ap("3d", 0.7),
    }


def latency(call: Callable[[Any], Any], samples: list[Any]) -> dict[str, float]:
    """p50 / p95 wall time of `call(sample)` over the samples after a short warm-up, milliseconds."""
    if not samples:
        return {"p50": float("nan"), "p95": float("nan"), "n": 0}
    for s in samples[:LATENCY_WARMUP]:
        call(s)
    times = []
    for s in samples:
        t0 = time.perf_counter_ns()
        call(s)
        times.append((time.perf_counter_ns() - t0) / NS_PER_MS)
    return {"p50": float(np.percentile(times, 50)), "p95": float(np.percentile(times, 95)), "n": len(times)}
