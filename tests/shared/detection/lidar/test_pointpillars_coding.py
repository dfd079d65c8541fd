"""Box coding: target encoding, decode known answers, heading split, NMS; the accuracy summary."""

from __future__ import annotations

import numpy as np
import pytest

from shared.detection.lidar.pointpillars.coding import (
    NUM_REG_CHANNELS,
    REG_COS2,
    REG_DIRECTION,
    REG_LOG_SIZE,
    REG_OFFSET_X,
    REG_OFFSET_Y,
    REG_SIN2,
    REG_Z,
    axis_and_direction,
    decode,
    encode_targets,
    rotated_nms,
    wrap_angle,
)
from shared.detection.lidar.pointpillars.config import GridConfig, HeadConfig, PostConfig
from training.pointpillars.evaluation import accuracy, centre_errors

GRID = GridConfig(
    x_min_m=-0.8, x_max_m=0.8, y_min_m=-0.8, y_max_m=0.8, pillar_size_m=0.05
)  # head 16x16, 0.1 m
HEAD = HeadConfig(mean_size_m=(0.33, 0.22, 0.21))
POST = PostConfig(score_threshold=0.3)


def test_decode_known_answer() -> None:
    peaks = np.zeros((GRID.head_ny, GRID.head_nx), np.float32)
    reg = np.zeros((NUM_REG_CHANNELS, GRID.head_ny, GRID.head_nx), np.float32)
    r, c = 10, 3  # cell centre x = -0.8 + 3.5 * 0.1 = -0.45, y = -0.8 + 10.5 * 0.1 = 0.25
    peaks[r, c] = 0.9
    peaks[2, 2] = 0.2  # below the threshold
    reg[REG_OFFSET_X, r, c] = 0.3
    reg[REG_OFFSET_Y, r, c] = -0.2
    reg[REG_Z, r, c] = 1.05  # 0.105 m in 0.1 m cells
    reg[REG_LOG_SIZE, r, c] = [0.0, np.log(2.0), 0.0]
    reg[REG_SIN2, r, c], reg[REG_COS2, r, c] = 1.0, 0.0  # axis pi/4
    reg[REG_DIRECTION, r, c] = 3.0  # logit > 0: heading = axis + pi
    boxes = decode(peaks, reg, GRID, HEAD, POST)
    np.testing.assert_allclose(
        boxes,
        [[-0.42, 0.23, 0.105, 0.33, 0.44, 0.21, wrap_angle(np.pi / 4 + np.pi), 0.9]],
        atol=1e-5,
    )


@pytest.mark.parametrize("yaw", [-3.1, -np.pi / 2, -0.7, 0.0, 0.3, np.pi / 2, np.pi * 0.75, 3.1])
def test_encode_then_decode_returns_the_box(yaw: float) -> None:
    box = np.array([[0.123, -0.271, 0.505, 0.33, 0.22, 0.21, yaw]])
    t = encode_targets(box, np.zeros((0, 7)), GRID, HEAD)
    assert t.heatmap.max() == 1.0 and t.heatmap.sum() > 1.0
    # As the network would output: peak at the centre cell, direction bit as a large logit.
    reg = t.regression.copy()
    reg[REG_DIRECTION] = np.where(reg[REG_DIRECTION] > 0.5, 10.0, -10.0)
    peaks = np.where(t.heatmap == 1.0, t.heatmap, 0.0)
    out = decode(peaks, reg, GRID, HEAD, POST)
    assert len(out) == 1
    np.testing.assert_allclose(out[0, :6], box[0, :6], atol=1e-5)
    assert abs(wrap_angle(out[0, 6] - yaw)) < 1e-5
    # Every cell within the regression radius decodes the same box.
    cells = np.argwhere(t.regression_mask > 0)
    assert len(cells) > 1
    for r, c in cells:
        single = np.zeros_like(peaks)
        single[r, c] = 1.0
        np.testing.assert_allclose(decode(single, reg, GRID, HEAD, POST)[0, :3], box[0, :3], atol=1e-5)


def test_heading_split_flips_only_on_the_diagonals() -> None:
    offset = HEAD.direction_offset_rad
    yaws = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2, 0.1, -3.0])
    axis, bit = axis_and_direction(yaws, offset)
    np.testing.assert_allclose(wrap_angle(axis + np.pi * bit - yaws), 0.0, atol=1e-6)
    assert np.all((axis >= offset - np.pi / 2) & (axis < offset + np.pi / 2))
    np.testing.assert_array_equal(bit, [0, 0, 1, 1, 0, 1])


def test_ignore_boxes_and_off_grid_boxes_mask_the_heatmap_loss() -> None:
    ignore = np.array([[0.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]])
    off_grid = np.array([[0.85, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]])
    t = encode_targets(off_grid, ignore, GRID, HEAD)
    assert t.heatmap.max() == 0.0 and t.regression_mask.sum() == 0
    assert t.heatmap_weight[8, 8] == 0.0 and t.heatmap_weight[8, 15] == 0.0 and t.heatmap_weight[0, 0] == 1.0


def test_rotated_nms_suppresses_overlaps_only() -> None:
    boxes = np.array(
        [
            [0.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0, 0.9],
            [0.02, 0.01, 0.1, 0.33, 0.22, 0.21, 0.1, 0.8],  # overlaps the first
            [1.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0, 0.7],
        ],
        np.float32,
    )
    np.testing.assert_array_equal(rotated_nms(boxes, 0.1, 10), [0, 2])
    np.testing.assert_array_equal(rotated_nms(boxes, 0.1, 1), [0])
    assert rotated_nms(boxes[:0], 0.1, 10).shape == (0,)


def test_accuracy_of_perfect_and_shifted_detections() -> None:
    labels = np.array([[0.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0], [1.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]])
    ignore = np.zeros((0, 7))
    perfect = np.column_stack([labels, [0.9, 0.8], [0.0, 0.0]])
    result = accuracy([perfect], [(labels, ignore)], bands=())
    assert result["bev_ap_07"] == pytest.approx(1.0) and result["ap3d_07"] == pytest.approx(1.0)
    assert result["centre_error_m"] == pytest.approx(0.0) and result["labels"] == 2
    shifted = perfect.copy()
    shifted[:, 0] += 0.01  # BEV IoU 0.94: still a match, 1 cm off
    np.testing.assert_allclose(centre_errors(shifted, labels, ignore, 0.7), [0.01, 0.01], atol=1e-9)
