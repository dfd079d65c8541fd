"""Camera output layouts decoded on hand-made tensors (known answers worked by hand), the class map, the
centred letterbox, and model cards' validation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from shared.config import ConfigError
from shared.detection.camera.geometry import letterbox_for, letterbox_image
from shared.detection.camera.layouts import decode, expected_output, project_scores
from shared.detection.card import CameraCard, load_card


def card(layout: str, num_classes: int = 3, width: int = 64, height: int = 32, **extra) -> CameraCard:
    return CameraCard.model_validate(
        {
            "kind": "camera",
            "model": "m.onnx",
            "layout": layout,
            "input": {"width": width, "height": height, "tensor": "nchw_float32"},
            "num_classes": num_classes,
            "classes": {num_classes - 1: "car"},
            **extra,
        }
    )


def test_yolov8_columns_are_centre_size_then_class_scores() -> None:
    out = np.zeros((1, 7, 2), np.float32)
    out[0, :, 0] = [32, 16, 10, 20, 0.1, 0.9, 0.2]  # box 27..37 x 6..26, class 1 best
    out[0, :, 1] = [5, 5, 2, 2, 0.0, 0.0, 0.7]
    boxes, scores = decode(card("yolov8"), out)
    np.testing.assert_allclose(boxes[0], [[27, 6, 37, 26], [4, 4, 6, 6]])
    np.testing.assert_allclose(scores[0], [[0.1, 0.9, 0.2], [0.0, 0.0, 0.7]])
    assert expected_output(card("yolov8")) == (None, 7, None)


def test_yolov5_rows_score_objectness_times_class() -> None:
    out = np.array([[[10, 10, 4, 4, 0.5, 0.2, 0.8, 0.1]]], np.float32)
    boxes, scores = decode(card("yolov5"), out)
    np.testing.assert_allclose(boxes[0], [[8, 8, 12, 12]])
    np.testing.assert_allclose(scores[0], [[0.1, 0.4, 0.05]])
    assert expected_output(card("yolov5")) == (None, None, 8)


def test_yolox_raw_rows_are_decoded_on_their_stride_grids() -> None:
    """64 x 32 input, strides 8 and 16: 8 x 4 = 32 cells at stride 8, then 4 x 2 = 8 at stride 16, each
    grid row-major. Row 9 is (column 1, row 1) at stride 8; row 37 is (column 1, row 1) at stride 16."""
    c = card("yolox", num_classes=1, yolox={"strides": [8, 16]})
    assert expected_output(c) == (None, 40, 6)
    out = np.zeros((1, 40, 6), np.float32)
    out[0, 9] = [0.5, 0.25, np.log(2.0), 0.0, 0.5, 0.6]  # centre (1.5, 1.25) x 8 = (12, 10), 16 x 8 px
    out[0, 37] = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0]  # centre (16, 16), 16 x 16 px
    boxes, scores = decode(c, out)
    np.testing.assert_allclose(boxes[0, 9], [4, 6, 20, 14], atol=1e-5)
    np.testing.assert_allclose(boxes[0, 37], [8, 8, 24, 24], atol=1e-5)
    np.testing.assert_allclose(scores[0, [9, 37], 0], [0.3, 1.0])
    out[0, 0, 2] = 1e6  # a runaway size logit gives a huge box, not inf / NaN
    assert np.isfinite(decode(c, out)[0]).all()


def test_rmmdet_rows_are_boxes_and_one_score() -> None:
    out = np.array([[[1, 2, 3, 4, 0.7]]], np.float32)
    rmmdet = CameraCard.model_validate(
        {
            "kind": "camera",
            "model": "m.onnx",
            "layout": "rmmdet",
            "input": {"width": 8, "height": 8, "tensor": "nhwc_uint8"},
            "classes": {0: "car"},
        }
    )
    boxes, scores = decode(rmmdet, out)
    np.testing.assert_allclose(boxes[0], [[1, 2, 3, 4]])
    np.testing.assert_allclose(scores[0], [[0.7]])


def test_model_classes_map_to_the_projects_by_their_best_score() -> None:
    """COCO car (2), bus (5), truck (7) all count as the project's car; a person (0) does not."""
    scores = np.zeros((2, 8), np.float32)
    scores[0, [0, 2, 7]] = [0.99, 0.3, 0.6]
    scores[1, 0] = 0.99
    got = project_scores(scores, {2: "car", 5: "car", 7: "car"}, ("car",))
    np.testing.assert_allclose(got, [[0.6], [0.0]])


def test_a_centred_letterbox_splits_the_padding_and_maps_boxes_back() -> None:
    """640 x 320 into 64 x 64: scale 0.1, 64 x 32 image, 16 px of padding above and below."""
    c = card("yolov8", width=64, height=64).input
    box = letterbox_for(640, 320, c, centre=True)
    assert (box.scale, box.left, box.top) == (0.1, 0, 16)
    np.testing.assert_allclose(box.to_input([[100, 50, 200, 150]]), [[10, 21, 20, 31]])
    np.testing.assert_allclose(box.to_original([[10, 21, 20, 31]]), [[100, 50, 200, 150]], atol=1e-4)
    image = np.full((320, 640, 3), 7, np.uint8)
    out = np.zeros((64, 64, 3), np.uint8)
    letterbox_image(image, c, out, centre=True)
    assert (out[:16] == 114).all() and (out[48:] == 114).all() and (out[16:48] == 7).all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"layout": "yolov9"}, "layout"),
        ({"classes": {3: "car"}}, "outside the model's 3 classes"),
        ({"classes": {0: "pedestrian"}}, "project's classes"),
        ({"classes": {}}, "would find nothing"),
        ({"input": {"width": 64, "height": 32, "tensor": "nhwc_uint8", "scale": 0.5}}, "as they are"),
        ({"input": {"width": 64, "height": 32, "tensor": "nchw_float32", "std": [1, 0, 1]}}, "std"),
        ({"surprise": 1}, "surprise"),
    ],
)
def test_bad_cards_are_config_errors_naming_the_field(tmp_path: Path, change: dict, message: str) -> None:
    data = {
        "kind": "camera",
        "model": "m.onnx",
        "layout": "yolov8",
        "input": {"width": 64, "height": 32, "tensor": "nchw_float32"},
        "num_classes": 3,
        "classes": {2: "car"},
        **change,
    }
    path = tmp_path / "card.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=message):
        load_card(path)
