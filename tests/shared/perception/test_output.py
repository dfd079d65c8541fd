"""Detector rows -> Detection2DArray: known answers, and the message passes the bus's validator."""

from __future__ import annotations

import numpy as np
import pytest
from rmmdet.v1 import perception_pb2 as pb

import shared.bus.validators  # noqa: F401  (registers the range checks)
from shared.bus.codec import validate
from shared.detection.interface import empty_camera_detections
from shared.perception.output import detections_2d_message


def test_box_corners_become_centre_and_size() -> None:
    rows = np.array([[10, 20, 50, 40, 0.75, 0], [0, 0, 448, 336, 1.0, 0]], np.float32)
    msg = detections_2d_message("cam_2", rows, 448, 336)
    assert (msg.sensor_id, msg.image_width_px, msg.image_height_px) == ("cam_2", 448, 336)
    first = msg.detections[0]
    assert (first.box.center_u_px, first.box.center_v_px) == (30.0, 30.0)
    assert (first.box.width_px, first.box.height_px) == (40.0, 20.0)
    assert first.score == pytest.approx(0.75)
    assert first.classification[0].label == pb.OBJECT_CLASS_CAR
    assert msg.detections[1].box.width_px == 448.0
    validate(msg)  # raises Rejected on a problem


def test_no_detections_is_an_empty_array() -> None:
    msg = detections_2d_message("cam_2", empty_camera_detections(), 448, 336)
    assert len(msg.detections) == 0
    validate(msg)  # raises Rejected on a problem
