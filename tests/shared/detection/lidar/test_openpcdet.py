"""OpenPCDet anchor-head exports from a model card: anchors, residual decoding, the direction bins and
pillars worked by hand from OpenPCDet's definitions; a hand-built ONNX file with constant head maps
run through the registry from its card; cards that do not fit their model refused at load."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from shared.config import ConfigError
from shared.detection.card import LidarCard, save_card
from shared.detection.lidar.openpcdet import (
    apply_direction,
    decode_boxes,
    limit_period,
    make_anchors,
    voxelize,
)
from shared.detection.registry import lidar_detector

# 4 m x 2 m in 1 m pillars (4 columns, 2 rows), z in [-1, 1); one class, two rotations: A = 2.
CARD = {
    "kind": "lidar",
    "model": "head.onnx",
    "layout": "openpcdet_anchor",
    "num_classes": 2,
    "classes": {0: "car"},  # class 1 ("pedestrian" to the model) is not the project's
    "grid": {
        "point_cloud_range_m": [0, 0, -1, 4, 2, 1],
        "voxel_size_m": [1, 1, 2],
        "max_points_per_voxel": 2,
        "max_voxels": 8,
    },
    "head": {
        "anchors": [
            {
                "class_name": "Car",
                "size_m": [1.0, 0.5, 0.4],
                "rotations_rad": [0.0, 1.57],
                "bottom_height_m": -1.0,
            },
            {
                "class_name": "Pedestrian",
                "size_m": [0.3, 0.3, 0.6],
                "rotations_rad": [0.0],
                "bottom_height_m": -1.0,
            },
        ],
    },
    "post": {"score_threshold": 0.5, "nms_iou": 0.1, "pre_nms_top_k": 64, "max_detections": 8},
}
A = 3  # anchors per cell: car x 2 rotations, pedestrian x 1


def card(**override) -> LidarCard:
    data = {**CARD, **override}
    return LidarCard.model_validate(data)


def test_limit_period_brings_angles_into_one_period() -> None:
    np.testing.assert_allclose(
        limit_period(np.array([3.5, -0.5, 0.0]), 0.0, math.pi), [3.5 - math.pi, math.pi - 0.5, 0]
    )
    np.testing.assert_allclose(limit_period(np.array([2.0]), 0.5, math.pi), [2.0 - math.pi])


def test_anchors_span_the_range_in_row_column_class_rotation_order() -> None:
    anchors = make_anchors(card(), rows=2, cols=4).reshape(2, 4, A, 7)
    # align_center false: columns at 0, 4/3, 8/3, 4 m; rows at 0, 2 m; z = bottom + dz / 2.
    np.testing.assert_allclose(anchors[1, 2, 1], [8 / 3, 2, -0.8, 1.0, 0.5, 0.4, 1.57], rtol=1e-6)
    np.testing.assert_allclose(anchors[0, 3, 2], [4, 0, -0.7, 0.3, 0.3, 0.6, 0.0], rtol=1e-6)
    centred = card(head={**CARD["head"], "align_center": True})
    np.testing.assert_allclose(make_anchors(centred, 2, 4).reshape(2, 4, A, 7)[1, 2, 0, :2], [2.5, 1.5])


def test_residuals_decode_on_the_anchor_diagonal_and_sizes() -> None:
    anchor = np.array([[1, 2, -0.8, 3, 4, 0.4, 0.0]], np.float32)  # diagonal 5 m
    residual = np.array([[0.2, -0.1, 0.5, math.log(2), 0, 0, 0.3]], np.float32)
    np.testing.assert_allclose(decode_boxes(residual, anchor), [[2, 1.5, -0.6, 6, 4, 0.4, 0.3]], rtol=1e-6)


def test_the_direction_bin_picks_the_heading() -> None:
    """offset pi/4, 2 bins: the yaw is brought into [pi/4, 5 pi/4) and bin 1 adds pi."""
    c = card()
    yaw = np.array([1.0, 1.0, 0.3, 4.0])
    bins = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(
        apply_direction(yaw, bins, c), [1.0, 1.0 + math.pi, 0.3 + math.pi, 4.0 - math.pi], atol=1e-6
    )


def test_pillars_keep_first_points_in_order_and_first_pillars_first() -> None:
    c = card(grid={**CARD["grid"], "max_voxels": 2})
    points = np.array(
        [
            [3.5, 1.5, 0.0, 1.0],  # pillar (row 1, col 3): first seen
            [0.5, 0.5, 0.0, 2.0],  # pillar (0, 0)
            [3.2, 1.2, 0.5, 3.0],  # (1, 3) again
            [3.9, 1.9, 0.1, 4.0],  # (1, 3): a third point, over max_points_per_voxel
            [1.5, 0.5, 0.0, 5.0],  # (0, 1): a third pillar, over max_voxels
            [9.0, 0.5, 0.0, 6.0],  # outside the range
            [0.5, 0.5, 1.0, 7.0],  # z = 1: outside [-1, 1)
        ],
        np.float32,
    )
    voxels, num, coords = voxelize(points, c)
    np.testing.assert_array_equal(num, [2, 1])
    np.testing.assert_array_equal(coords, [[0, 0, 1, 3], [0, 0, 0, 0]])
    np.testing.assert_allclose(voxels[0], points[[0, 2]])
    np.testing.assert_allclose(voxels[1], [points[1], [0, 0, 0, 0]])
    aug = card(head={**CARD["head"], "point_features": "augmented"})
    feats, _, _ = voxelize(points[:3], aug)
    # pillar (1, 3): mean of its two points (3.35, 1.35, 0.25); centre (3.5, 1.5, 0.0)
    np.testing.assert_allclose(feats[0, 0], [3.5, 1.5, 0, 1, 0.15, 0.15, -0.25, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(feats[0, 1, 7:], [-0.3, -0.3, 0.5], atol=1e-6)
    assert not feats[1, 1].any()  # padding stays zero


def constant_head(path: Path, cls: np.ndarray, box: np.ndarray, direction: np.ndarray, names=None) -> Path:
    """An ONNX file with OpenPCDet's three inputs whose outputs are the given constant maps."""
    inputs = [
        helper.make_tensor_value_info("voxels", TensorProto.FLOAT, ["P", 2, 4]),
        helper.make_tensor_value_info("voxel_num_points", TensorProto.INT32, ["P"]),
        helper.make_tensor_value_info("voxel_coords", TensorProto.INT32, ["P", 4]),
    ]
    names = names or ("cls_preds", "box_preds", "dir_cls_preds")
    nodes, outputs, inits = [], [], []
    for name, value in zip(names, (cls, box, direction), strict=True):
        inits.append(numpy_helper.from_array(value.astype(np.float32), f"{name}_value"))
        nodes.append(helper.make_node("Identity", [f"{name}_value"], [name]))
        outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(value.shape)))
    graph = helper.make_graph(nodes, "head", inputs, outputs, inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def head_maps() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feature map 2 x 4. Lit: the car anchor of rotation 1.57 at (row 1, col 2), the car anchor of
    rotation 0 at (0, 0) weaker, and the pedestrian anchor at (0, 1) (not a project class)."""
    cls = np.full((1, 2, 4, A * 2), -10.0)
    box = np.zeros((1, 2, 4, A * 7))
    direction = np.zeros((1, 2, 4, A * 2))
    cls[0, 1, 2, 1 * 2 + 0] = 4.0  # anchor 1 (car, 1.57), class 0
    box[0, 1, 2, 1 * 7 : 2 * 7] = [0.1, 0, 0, math.log(2), 0, 0, 0.1]
    direction[0, 1, 2, 1 * 2 : 2 * 2] = [0, 1]  # bin 1
    cls[0, 0, 0, 0] = 1.0  # anchor 0 (car, 0.0): score 0.73
    cls[0, 0, 1, 2 * 2 + 1] = 6.0  # anchor 2 (pedestrian), class 1
    return cls, box, direction


def test_a_constant_head_decodes_to_its_boxes_through_the_registry(tmp_path: Path) -> None:
    constant_head(tmp_path / "head.onnx", *head_maps())
    path = tmp_path / "card.yaml"
    save_card(path, card(), "test card")
    detector = lidar_detector(str(path))
    got = detector.detect(np.array([[0.5, 0.5, 0.0, 1.0]], np.float32))
    diag = math.hypot(1.0, 0.5)
    yaw = 1.57 + 0.1  # already in [pi/4, 5 pi/4): bin 1 adds pi
    expected = [
        [8 / 3 + 0.1 * diag, 2, -0.8, 2.0, 0.5, 0.4, yaw + math.pi, 1 / (1 + math.exp(-4.0)), 0],
        [0, 0, -0.8, 1.0, 0.5, 0.4, math.pi, 1 / (1 + math.exp(-1.0)), 0],  # yaw 0 -> pi/4 .. : 0 + pi
    ]
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    assert len(detector.detect(np.array([[9.0, 9.0, 0.0, 1.0]], np.float32))) == 0  # nothing in range


@pytest.mark.parametrize(
    ("override", "names", "message"),
    [
        ({"head": {**CARD["head"], "num_dir_bins": 3}}, None, "direction bins"),
        ({"grid": {**CARD["grid"], "max_points_per_voxel": 32}}, None, "does not fit the card's pillars"),
        ({"head": {**CARD["head"], "point_features": "augmented"}}, None, "does not fit the card's pillars"),
        ({}, ("cls", "box_preds", "dir_cls_preds"), "the card names"),
    ],
)
def test_a_card_that_does_not_fit_its_model_is_refused(tmp_path: Path, override, names, message: str) -> None:
    constant_head(tmp_path / "head.onnx", *head_maps(), names=names)
    path = tmp_path / "card.yaml"
    save_card(path, card(**override), "test card")
    with pytest.raises(ConfigError, match=message):
        lidar_detector(str(path))


def test_the_projects_pointpillars_loads_through_its_card() -> None:
    detector = lidar_detector("pointpillars")
    assert detector.name == "pointpillars"
    assert len(detector.detect(np.zeros((0, 4), np.float32))) == 0
