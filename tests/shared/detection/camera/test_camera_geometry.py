"""Known-answer tests of the camera detector's pre- and post-processing (numpy + OpenCV, no torch)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.detection.camera.config import InputConfig, PostprocessConfig
from shared.detection.camera.geometry import (
    Letterbox,
    letterbox_for,
    letterbox_image,
    nms,
    postprocess,
    select_detections,
)

INPUT = InputConfig(width=320, height=240, pad_value=114)


# --- letterbox -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("w", "h", "scale"),
    [(640, 480, 0.5), (320, 240, 1.0), (1280, 480, 0.25), (400, 600, 0.4), (160, 120, 2.0)],
)
def test_letterbox_scale_fits_the_input(w: int, h: int, scale: float) -> None:
    assert letterbox_for(w, h, INPUT).scale == pytest.approx(scale)


def test_letterbox_image_places_top_left_and_pads() -> None:
    # 400 x 600 (portrait) -> scale 0.4 -> 160 x 240 at the left; columns 160.. are padding.
    img = np.full((600, 400, 3), 10, np.uint8)
    out = np.zeros((240, 320, 3), np.uint8)
    box = letterbox_image(img, INPUT, out=out)
    assert box == Letterbox(0.4, 400, 600)
    assert (out[:, :160] == 10).all()
    assert (out[:, 160:] == INPUT.pad_value).all()


def test_letterbox_image_same_size_is_a_copy() -> None:
    img = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    out = np.zeros_like(img)
    letterbox_image(img, INPUT, out=out)
    np.testing.assert_array_equal(out, img)


def test_letterbox_accepts_a_flipped_view() -> None:
    img = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    a = np.zeros((240, 320, 3), np.uint8)
    b = np.zeros_like(a)
    letterbox_image(img[:, ::-1], INPUT, out=a)
    letterbox_image(np.ascontiguousarray(img[:, ::-1]), INPUT, out=b)
    np.testing.assert_array_equal(a, b)


def test_box_mapping_round_trip_and_clip() -> None:
    box = Letterbox(0.5, 640, 480)
    orig = np.array([[100.0, 50.0, 300.0, 250.0]], np.float32)
    np.testing.assert_allclose(box.to_input(orig), [[50, 25, 150, 125]])
    np.testing.assert_allclose(box.to_original(box.to_input(orig)), orig)
    # A box reaching into the padding / past the border is clipped to the original image.
    np.testing.assert_allclose(box.to_original([[-4.0, 230.0, 330.0, 250.0]]), [[0, 460, 640, 480]])


# --- NMS and post-processing --------------------------------------------------------------------------


def test_nms_known_answer() -> None:
    boxes = np.array(
        [[0, 0, 10, 10], [1, 0, 11, 10], [20, 20, 30, 30], [0, 0, 10, 10.5], [21, 20, 31, 30]], np.float32
    )
    scores = np.array([0.9, 0.8, 0.7, 0.95, 0.3], np.float32)
    # 3 (0.95) suppresses 0 and 1 (IoU > 0.5); 2 suppresses 4 (IoU 0.82).
    np.testing.assert_array_equal(nms(boxes, scores, 0.5, 100), [3, 2])
    np.testing.assert_array_equal(nms(boxes, scores, 0.5, 1), [3])
    assert nms(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), 0.5, 10).shape == (0,)


def test_select_detections_threshold_topk_nms() -> None:
    dets = np.array(
        [
            [0, 0, 10, 10, 0.9],
            [1, 0, 11, 10, 0.8],  # duplicate of row 0
            [50, 50, 60, 60, 0.6],
            [80, 80, 90, 90, 0.1],  # below threshold
        ],
        np.float32,
    )
    cfg = PostprocessConfig(score_threshold=0.3, nms_iou=0.5, pre_nms_top_k=10, max_detections=10)
    np.testing.assert_allclose(select_detections(dets, cfg), dets[[0, 2]])
    top1 = PostprocessConfig(score_threshold=0.3, nms_iou=0.5, pre_nms_top_k=1, max_detections=10)
    np.testing.assert_allclose(select_detections(dets, top1), dets[[0]])


def test_postprocess_maps_each_image_to_its_pixels() -> None:
    # Same input-px cell for two images of different sizes: 640x480 (scale 0.5), 400x600 (scale 0.4).
    cell = np.array([[40, 20, 80, 60, 0.8], [0, 0, 8, 8, 0.01]], np.float32)
    dets = np.stack([cell, cell])
    boxes = [letterbox_for(640, 480, INPUT), letterbox_for(400, 600, INPUT)]
    out = postprocess(dets, boxes, PostprocessConfig(score_threshold=0.5))
    assert [o.shape for o in out] == [(1, 6), (1, 6)]
    assert out[0].dtype == np.float32
    np.testing.assert_allclose(out[0], [[80, 40, 160, 120, 0.8, 0]], rtol=1e-6)
    np.testing.assert_allclose(out[1], [[100, 50, 200, 150, 0.8, 0]], rtol=1e-6)


def test_postprocess_drops_boxes_in_the_padding_only() -> None:
    # 400x600 fills input columns 0..160; a box at columns 200..240 lies in the padding.
    dets = np.array([[[200, 20, 240, 60, 0.9]]], np.float32)
    out = postprocess(dets, [letterbox_for(400, 600, INPUT)], PostprocessConfig())
    assert out[0].shape == (0, 6)
