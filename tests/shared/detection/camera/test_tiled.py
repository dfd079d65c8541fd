"""The COCO card (YOLOX-Nano, deploy/models/coco/yolox_nano) and the tiled camera detector: the card
loads and fits its graph with COCO car, bus, truck mapped to car; tile windows cover the image with the
card's overlap; strips run each band whole at its scale (a free-size graph, re-derived here from the
vendored one); boxes go back to full-image pixels; a car on a tile border is kept once."""

from __future__ import annotations

import hashlib
import itertools

import numpy as np
import pytest

from shared.config import ConfigError
from shared.detection.camera.onnx_detector import OnnxCameraDetector
from shared.detection.camera.tiled import Tile, TiledCameraDetector, merge, strip_windows, tile_windows
from shared.detection.card import CameraCard, CameraTiles, load_card
from shared.detection.registry import COCO_CARD, MODELS_DIR, camera_detector

CARD = MODELS_DIR / COCO_CARD
SHA256 = "4903c9058f6e2553834e9905be1ae5d67e262cb6321964dbc57a49edc6fa10da"


def test_vendored_model_is_the_recorded_file() -> None:
    model = CARD.parent / "model.onnx"
    assert hashlib.sha256(model.read_bytes()).hexdigest() == SHA256
    assert (CARD.parent / "LICENSE").read_text().startswith(" " * 33 + "Apache License")
    assert SHA256 in (CARD.parent / "SOURCE.md").read_text()


def test_the_any_size_model_is_the_vendored_one_with_free_sizes() -> None:
    """model_any_size.onnx is what training.camera.any_size makes of the vendored file: the same nodes
    and weights, only the declared input height and width and the output rows left free."""
    onnx = pytest.importorskip("onnx")
    from training.camera.any_size import any_size_path, free_input_size

    original = onnx.load(str(CARD.parent / "model.onnx"))
    shipped = any_size_path(CARD.parent / "model.onnx")
    assert free_input_size(original).SerializeToString() == shipped.read_bytes()
    freed = onnx.load(str(shipped))
    assert freed.graph.node == original.graph.node and freed.graph.initializer == original.graph.initializer
    assert [d.dim_param for d in freed.graph.input[0].type.tensor_type.shape.dim[2:]] == ["height", "width"]


def test_card_maps_coco_vehicles_to_car_and_fits_the_graph() -> None:
    card = load_card(CARD)
    assert isinstance(card, CameraCard)
    assert card.num_classes == 80 and card.classes == {2: "car", 5: "car", 7: "car"}
    assert (card.input.width, card.input.height, card.input.colour, card.input.scale) == (
        416,
        416,
        "bgr",
        1.0,
    )
    assert card.input.letterbox == "top_left" and card.layout == "yolox"
    detector = camera_detector("coco", threads=1)
    assert isinstance(detector, TiledCameraDetector)
    assert detector.name == "onnx-camera-tiled:coco"
    assert detector.detect([np.full((1200, 1920, 3), 114, np.uint8)])[0].shape == (0, 6)


def test_a_card_with_the_wrong_class_count_stops_at_load(tmp_path) -> None:
    text = (
        CARD.read_text()
        .replace("num_classes: 80", "num_classes: 20")
        .replace("model: model_any_size.onnx", "model: x.onnx")
    )
    (tmp_path / "x.onnx").write_bytes((CARD.parent / "model_any_size.onnx").read_bytes())
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(ConfigError, match="does not fit layout yolox"):
        camera_detector(str(tmp_path / "bad.yaml"), threads=1)


def layout(**band: float) -> CameraTiles:
    return CameraTiles(
        image_width_px=1920,
        image_height_px=1200,
        bands=[{"y0_px": 150, "y1_px": 566, "scale": 0.8, "min_overlap_px": 150, **band}],
    )


def test_tiles_cover_the_band_with_the_overlap() -> None:
    tiles = tile_windows(layout(), 1920, 1200, 416, 416)
    band, whole = tiles[:-1], tiles[-1]
    assert (whole.x0, whole.y0, whole.x1, whole.y1, whole.inner) == (0, 0, 1920, 1200, (False,) * 4)
    assert [(t.x1 - t.x0, t.y1 - t.y0) for t in band] == [(520, 520)] * len(band)  # 416 / 0.8
    assert band[0].x0 == 0 and band[-1].x1 == 1920 and all(t.y0 == 150 for t in band)
    overlaps = [a.x1 - b.x0 for a, b in itertools.pairwise(band)]
    assert min(overlaps) >= 150 and len(band) == 5  # 4 tiles would overlap 60 px
    assert band[0].inner == (False, True, True, True) and band[-1].inner == (True, True, False, True)
    # Another image size scales the layout: a half-size image has the same tiles at half size.
    half = tile_windows(layout(), 960, 600, 416, 416)
    assert [(t.x0, t.y0, t.x1, t.y1) for t in half] == [
        (round(t.x0 / 2), round(t.y0 / 2), round(t.x1 / 2), round(t.y1 / 2)) for t in tiles
    ]


def test_overlap_not_below_the_tile_is_an_error() -> None:
    with pytest.raises(ConfigError, match="overlap"):
        tile_windows(layout(min_overlap_px=600), 1920, 1200, 416, 416)


def test_box_round_trips_to_image_pixels() -> None:
    tile = Tile(350, 150, 870, 670, (True, True, True, True))
    det = np.array([[10.0, 20.0, 110.0, 80.0, 0.9, 0.0]], np.float32)
    full = tile.to_image(det)
    np.testing.assert_array_equal(full[0, :4], [360, 170, 460, 230])
    np.testing.assert_array_equal(full[0, 4:], det[0, 4:])
    assert det[0, 0] == 10.0  # a copy


def test_box_on_a_tile_border_is_kept_once() -> None:
    """A car across the border x = 520 of tiles [0, 520) and [350, 870): the first sees it cut (dropped),
    the second whole; the whole image sees it too (merged by NMS): one detection, the whole one."""
    left = Tile(0, 150, 520, 670, (False, True, True, True))
    right = Tile(350, 150, 870, 670, (True, True, True, True))
    car = np.array([480.0, 300.0, 600.0, 380.0])
    cut = np.array([[480.0, 150.0, 520.0, 230.0, 0.8, 0.0]], np.float32)  # tile px, at the right edge
    whole = np.array([[*(car - [350, 150, 350, 150]), 0.7, 0.0]], np.float32)
    assert len(left.uncut(cut, 2.0)) == 0
    assert len(right.uncut(whole, 2.0)) == 1
    from_whole_image = np.array([[482.0, 301.0, 598.0, 381.0, 0.6, 0.0]], np.float32)
    found = merge(
        np.concatenate([left.to_image(left.uncut(cut, 2.0)), right.to_image(whole), from_whole_image]),
        0.5,
        300,
    )
    assert len(found) == 1
    np.testing.assert_allclose(found[0, :4], car)
    assert found[0, 4] == pytest.approx(0.7)
    # Without dropping the cut box, it survives NMS beside the whole one (IoU 40x80 / 120x80 = 0.33).
    both = merge(np.concatenate([left.to_image(cut), right.to_image(whole)]), 0.5, 300)
    assert len(both) == 2


def strips(**kw: object) -> CameraTiles:
    return CameraTiles(
        image_width_px=1920,
        image_height_px=1200,
        strips=True,
        bands=[{"y0_px": 150, "y1_px": 470, "scale": 0.7}],
        **kw,
    )


def test_strips_run_each_band_whole_at_its_scale() -> None:
    """A band of rows 150..470 at 0.7: one window of the full width, network 1344 x 224 (1920 x 0.7 =
    1344, 320 x 0.7 = 224: multiples of 32); the whole image at 0.25: 480 x 320 (300 rounded up)."""
    band, whole = strip_windows(strips(whole_image_scale=0.25), 1920, 1200, 32)
    assert (band.x0, band.y0, band.x1, band.y1, band.size) == (0, 150, 1920, 470, (1344, 224))
    assert band.inner == (False, True, False, True)  # cut by its top and bottom only
    assert (whole.x0, whole.y0, whole.x1, whole.y1, whole.size) == (0, 0, 1920, 1200, (480, 320))
    # A half-size image: the same network sizes (the layout scales with the image).
    half = strip_windows(strips(whole_image_scale=0.25), 960, 600, 32)
    assert [(t.y0, t.y1, t.size) for t in half] == [(75, 235, (1344, 224)), (0, 600, (480, 320))]
    # Without whole_image_scale the whole image goes letterboxed to the card's input (size None).
    assert strip_windows(strips(), 1920, 1200, 32)[-1].size is None


def test_strips_need_a_free_size_model_and_whole_image_scale_needs_strips() -> None:
    fixed = OnnxCameraDetector(CARD.parent / "model.onnx", load_card(CARD), intra_op_threads=1)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="input size is fixed"):
        TiledCameraDetector(fixed, strips())
    with pytest.raises(ValueError, match="whole_image_scale"):
        CameraTiles(image_width_px=1920, image_height_px=1200, whole_image_scale=0.25)
