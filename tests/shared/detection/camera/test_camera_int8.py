"""The int8 camera model (training.camera.quantize) loads through the registry and, on images
rendered by the simulation, finds the cars the fp32 model finds."""

from __future__ import annotations

import numpy as np

from shared.detection.camera.onnx_detector import OnnxCameraDetector
from shared.detection.registry import camera_detector
from shared.geometry.boxes import iou2d_matrix

MIN_IOU = 0.8
SAME_CAR_IOU = 0.5  # int8 may add a second box a few px off a car both find (seen at 448x336: IoU 0.6)
SURE = 0.4  # a car one model scores this high ...
FOUND = 0.2  # ... the other must find above this (a margin for int8 rounding across CPUs)
MIN_CARS = 3  # the rendered frame must show cars (the test is not vacuous)


def found_by(sure: np.ndarray, other: np.ndarray, min_iou: float = MIN_IOU) -> np.ndarray:
    """Per row of `sure`: whether a row of `other` overlaps it at IoU >= `min_iou`."""
    if len(other) == 0:
        return np.zeros(len(sure), bool)
    return iou2d_matrix(sure[:, :4], other[:, :4]).max(axis=1) >= min_iou


def test_int8_finds_the_cars_fp32_finds(agent_frame) -> None:
    fp32 = camera_detector("onnx", threads=1)
    int8 = camera_detector("onnx", threads=1, precision="int8")
    assert isinstance(int8, OnnxCameraDetector) and isinstance(fp32, OnnxCameraDetector)
    a = fp32.detect(agent_frame.images)
    b = int8.detect(agent_frame.images)
    assert sum(int((d[:, 4] >= SURE).sum()) for d in a) >= MIN_CARS
    for x, y in zip(a, b, strict=True):
        assert found_by(x[x[:, 4] >= SURE], y[y[:, 4] >= FOUND]).all()  # every car, boxed as tightly
        assert found_by(y[y[:, 4] >= SURE], x[x[:, 4] >= FOUND], SAME_CAR_IOU).all()  # no invented car
