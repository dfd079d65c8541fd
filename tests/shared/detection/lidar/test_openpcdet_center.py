"""OpenPCDet CenterPoint exports from a model card (issue 50 item 3): heatmap peaks decoded by hand from
OpenPCDet's definitions (`decode_bbox_from_heatmap`: cell + offset times stride times pillar size plus the
range's corner, exp of the log sizes, atan2 of sin and cos), two tasks with their own NMS, a class the
card drops, the limit range; a hand-built ONNX head run through the registry from its card; cards that
do not fit their model refused at load."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from pydantic import ValidationError

from shared.config import ConfigError
from shared.detection.card import LidarCard, save_card
from shared.detection.registry import lidar_detector

# 8 m x 4 m in 0.5 m pillars, feature map stride 2 (1 m cells): 4 rows x 8 columns.
TASKS = [
    {"classes": [0], "heatmap": "hm0", "center": "c0", "center_z": "z0", "dim": "d0", "rot": "r0"},
    {"classes": [1, 2], "heatmap": "hm1", "center": "c1", "center_z": "z1", "dim": "d1", "rot": "r1"},
]
CARD = {
    "kind": "lidar",
    "model": "center.onnx",
    "layout": "openpcdet_center",
    "num_classes": 3,
    "classes": {0: "car", 2: "car"},  # class 1 (a pedestrian to the model) is not the project's
    "grid": {
        "point_cloud_range_m": [-2, -1, -3, 6, 3, 1],
        "voxel_size_m": [0.5, 0.5, 4],
        "max_points_per_voxel": 2,
        "max_voxels": 8,
    },
    "center": {"tasks": TASKS, "feature_map_stride": 2, "max_objects": 10},
    "post": {"score_threshold": 0.3, "nms_iou": 0.1, "pre_nms_top_k": 64, "max_detections": 8},
}
ROWS, COLS = 4, 8


def sig_inv(p: float) -> float:
    return math.log(p / (1 - p))


def task_maps() -> list[np.ndarray]:
    """Task 0: a car at cell (row 1, col 5), score 0.9; a second peak one cell on (overlapping, 0.6),
    which NMS removes. Task 1: a pedestrian (class 1, not the project's) at (2, 2), score 0.95, and a
    truck (class 2) at (3, 0), score 0.8, heading pi/2."""
    out = []
    for classes in (1, 2):
        hm = np.full((1, classes, ROWS, COLS), -20.0)
        out += [hm, np.zeros((1, 2, ROWS, COLS)), np.zeros((1, 1, ROWS, COLS)), np.zeros((1, 3, ROWS, COLS))]
        rot = np.zeros((1, 2, ROWS, COLS))
        rot[0, 0] = 1.0  # cos 1, sin 0: heading 0
        out.append(rot)
    hm0, c0, z0, d0, _, hm1, _, _, d1, r1 = out
    hm0[0, 0, 1, 5] = sig_inv(0.9)
    c0[0, :, 1, 5] = [0.25, 0.5]
    z0[0, 0, 1, 5] = -1.5
    d0[0, :, 1, 5] = np.log([4.0, 2.0, 1.5])
    hm0[0, 0, 1, 6] = sig_inv(0.6)
    d0[0, :, 1, 6] = np.log([4.0, 2.0, 1.5])
    hm1[0, 0, 2, 2] = sig_inv(0.95)
    hm1[0, 1, 3, 0] = sig_inv(0.8)
    d1[0, :, 3, 0] = np.log([8.0, 2.5, 3.0])
    r1[0, :, 3, 0] = [0.0, 1.0]
    return out


def constant_center_head(path: Path, maps: list[np.ndarray], names: list[str] | None = None) -> Path:
    inputs = [
        helper.make_tensor_value_info("voxels", TensorProto.FLOAT, ["P", 2, 4]),
        helper.make_tensor_value_info("voxel_num_points", TensorProto.INT32, ["P"]),
        helper.make_tensor_value_info("voxel_coords", TensorProto.INT32, ["P", 4]),
    ]
    names = names or [
        n for t in TASKS for n in (t["heatmap"], t["center"], t["center_z"], t["dim"], t["rot"])
    ]
    nodes, outputs, inits = [], [], []
    for name, value in zip(names, maps, strict=True):
        inits.append(numpy_helper.from_array(value.astype(np.float32), f"{name}_value"))
        nodes.append(helper.make_node("Identity", [f"{name}_value"], [name]))
        outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(value.shape)))
    model = helper.make_model(
        helper.make_graph(nodes, "center", inputs, outputs, inits),
        opset_imports=[helper.make_opsetid("", 17)],
    )
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def detector(tmp_path: Path, maps: list[np.ndarray] | None = None, names=None, **override):
    constant_center_head(tmp_path / "center.onnx", maps or task_maps(), names)
    path = tmp_path / "card.yaml"
    save_card(path, LidarCard.model_validate({**CARD, **override}), "test card")
    return lidar_detector(str(path))


def test_heatmap_peaks_decode_to_their_boxes(tmp_path: Path) -> None:
    got = detector(tmp_path).detect(np.array([[0.0, 0.0, 0.0, 1.0]], np.float32))
    # car: x = (5 + 0.25) * 2 * 0.5 - 2 = 3.25, y = (1 + 0.5) * 2 * 0.5 - 1 = 0.5
    # truck: x = (0 + 0) * 1 - 2 = -2, y = (3 + 0) * 1 - 1 = 2, heading atan2(1, 0) = pi / 2
    expected = [
        [3.25, 0.5, -1.5, 4.0, 2.0, 1.5, 0.0, 0.9, 0],
        [-2.0, 2.0, 0.0, 8.0, 2.5, 3.0, math.pi / 2, 0.8, 0],
    ]
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


def test_the_limit_range_and_the_threshold_drop_boxes(tmp_path: Path) -> None:
    limited = {**CARD["center"], "post_center_limit_range_m": [0, -1, -3, 6, 3, 1]}  # x >= 0: no truck
    got = detector(tmp_path, center=limited).detect(np.array([[0.0, 0.0, 0.0, 1.0]], np.float32))
    np.testing.assert_allclose(got[:, :2], [[3.25, 0.5]], atol=1e-5)
    high = {**CARD["post"], "score_threshold": 0.85}
    (tmp_path / "b").mkdir()
    got = detector(tmp_path / "b", post=high).detect(np.array([[0.0, 0.0, 0.0, 1.0]], np.float32))
    assert got[:, 7].tolist() == pytest.approx([0.9])


def test_nothing_in_range_is_nothing_found(tmp_path: Path) -> None:
    assert len(detector(tmp_path).detect(np.array([[50.0, 50.0, 0.0, 1.0]], np.float32))) == 0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"center": {**CARD["center"], "tasks": [TASKS[0]]}}, "each of the 3 classes once"),
        ({"head": {"anchors": [{"class_name": "Car", "size_m": [1, 1, 1]}]}}, "no `head`"),
    ],
)
def test_a_card_that_contradicts_itself_is_refused(change: dict, message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        LidarCard.model_validate({**CARD, **change})


def test_a_card_that_does_not_fit_its_model_is_refused(tmp_path: Path) -> None:
    maps = task_maps()
    maps[5] = np.zeros((1, 3, ROWS, COLS))  # task 1's heatmap with 3 channels, the card says 2
    with pytest.raises(ConfigError, match=r"hm1 .* should have 2 channels"):
        detector(tmp_path, maps)
    names = [n for t in TASKS for n in (t["heatmap"], t["center"], t["center_z"], t["dim"], t["rot"])]
    names[0] = "heatmap"
    with pytest.raises(ConfigError, match="the card names"):
        detector(tmp_path, task_maps(), names)
