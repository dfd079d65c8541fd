"""The int8 PointPillars (training.pointpillars.quantize) loads through the registry
and, on a cloud rendered by the simulation, finds the cars the fp32 model finds."""

from __future__ import annotations

import numpy as np

from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars
from shared.detection.registry import lidar_detector
from shared.geometry.boxes import bev_iou_matrix

MIN_IOU = 0.8
SURE = 0.5  # a car one model scores this high ...
FOUND = 0.3  # ... the other must find at the detector's own threshold (0.3)
MIN_CARS = 3  # the rendered frame must show cars (the test is not vacuous)


def found_by(sure: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Per row of `sure`: whether a row of `other` overlaps it at BEV IoU >= MIN_IOU."""
    if len(other) == 0:
        return np.zeros(len(sure), bool)
    return bev_iou_matrix(sure[:, :7], other[:, :7]).max(axis=1) >= MIN_IOU


def test_int8_finds_the_cars_fp32_finds(agent_frame) -> None:
    fp32 = lidar_detector("pointpillars", threads=1)
    int8 = lidar_detector("pointpillars", threads=1, precision="int8")
    assert isinstance(int8, OnnxPointPillars) and isinstance(fp32, OnnxPointPillars)
    assert int8.model_path.name == "pointpillars_int8.onnx"
    assert int8.config == fp32.config  # the quantized model shares the fp32 model's config file
    a = fp32.detect(agent_frame.cloud)
    b = int8.detect(agent_frame.cloud)
    assert (a[:, 7] >= SURE).sum() >= MIN_CARS
    assert found_by(a[a[:, 7] >= SURE], b[b[:, 7] >= FOUND]).all()
    assert found_by(b[b[:, 7] >= SURE], a[a[:, 7] >= FOUND]).all()
