"""Detectors built from model cards (issue 36): the project's camera model re-exported as YOLOv8, YOLOv5
and YOLOX files (`exports.wrap_as`, NCHW float input, RGB or BGR, scaled or not, the car at a COCO-like
class index among several), each loaded through the registry from a card alone, give the project's
own detections on simulated frames and, through the MEC's production core, its object lists. A card
that does not fit its model is refused at load, naming what does not fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.config import ConfigError
from shared.detection.camera.config import CONFIG_FILE, CameraDetectorConfig
from shared.detection.card import CameraCard, load_card, save_card
from shared.detection.registry import CAMERA_CARD, LIDAR_CARD, MODELS_DIR, camera_detector, lidar_detector
from shared.paths import DEFAULT_SCENE
from shared.perception.config import MecSettings, SyncConfig
from shared.perception.core import MecCore
from shared.perception.decode import image_to_array
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from tests.shared.detection.camera.exports import wrap_as

AGENT = "agent2"  # five cameras and two radars: every object list depends on the camera detector
DURATION_S = 1.0
NUM_CLASSES = 8  # COCO-like: the car is class 2 of 8 (5 and 7 mapped as well, never lit)
CAR = 2
# layout -> how the file wants its input (tensor, colour, scale, letterbox)
EXPORTS = {
    "yolov8": {"tensor": "nchw_float32", "colour": "rgb", "scale": 1 / 255, "letterbox": "centre"},
    "yolov5": {"tensor": "nchw_float32", "colour": "rgb", "scale": 1 / 255, "letterbox": "centre"},
    "yolox": {"tensor": "nchw_float32", "colour": "bgr", "scale": 1.0, "letterbox": "top_left"},
}


def write_card(tmp: Path, layout: str, **override) -> Path:
    inp = EXPORTS[layout]
    wrap_as(layout, tmp / f"{layout}.onnx", num_classes=NUM_CLASSES, car_index=CAR, scale=inp["scale"],
            colour=inp["colour"])  # fmt: skip
    data = {
        "kind": "camera",
        "model": f"{layout}.onnx",
        "layout": layout,
        "input": {"width": 448, "height": 336, **inp},
        "num_classes": NUM_CLASSES,
        "classes": {CAR: "car", 5: "car", 7: "car"},
        "post": {"score_threshold": 0.05, "nms_iou": 0.6, "pre_nms_top_k": 1000, "max_detections": 300},
        **({"yolox": {"strides": [8]}} if layout == "yolox" else {}),
    }
    data.update(override)
    path = tmp / f"{layout}.yaml"
    save_card(path, CameraCard.model_validate(data), f"the project's model as a {layout} export (test)")
    return path


@pytest.fixture(scope="module")
def frames() -> list[tuple[str, int, object]]:
    scene = Scene.load(DEFAULT_SCENE)
    settings = load_sim_settings(seed=3)
    ids = [s.id for s in scene.sensors_of(AGENT)]
    out = []
    with LockstepSim(scene, settings, sensor_ids=ids) as sim:
        for _ in range(round(DURATION_S * settings.tick_hz)):
            out += [(c.spec.id, c.stamp_ns, c.message) for c in sim.step().captures]
    return out


@pytest.fixture(scope="module")
def cards(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("cards")
    return {layout: write_card(tmp, layout) for layout in EXPORTS}


def summary(o) -> tuple:
    """An object as compared: track id, centre x, y (m), existence probability (4 decimals)."""
    return (o.track_id, *(round(v, 4) for v in (o.box.center_m.x, o.box.center_m.y, o.existence_probability)))


def object_lists(frames, cameras) -> list[tuple]:
    """The frames through a fresh MecCore with camera detector `cameras`: every list published."""
    scene = Scene.load(DEFAULT_SCENE)
    settings = MecSettings(sync=SyncConfig(collector="bounded_wait"))  # joined by stamp, as a recording
    core = MecCore(scene, AGENT, settings, cameras=cameras, now_s=frames[0][1] / NS_PER_S)
    out = []
    for sensor, stamp_ns, message in frames:
        now_s = stamp_ns / NS_PER_S
        core.cadence(now_s)
        core.receive(sensor, stamp_ns, None, message, now_s, stamp_ns)
        result = core.step(now_s)
        if result is not None:
            out.append([summary(o) for o in result.message.objects])
    return out


def test_cards_of_three_export_layouts_detect_what_the_projects_model_does(frames, cards) -> None:
    own = camera_detector("onnx", threads=1)
    images = [image_to_array(m) for _, _, m in frames if hasattr(m, "format")][:10]
    expected = own.detect(images)
    assert sum(len(d) for d in expected) > 0, "no car in the frames: the comparison would prove nothing"
    for layout, path in cards.items():
        got = camera_detector(str(path), threads=1).detect(images)
        for e, g in zip(expected, got, strict=True):
            assert g.shape == e.shape, layout
            np.testing.assert_allclose(g, e, atol=2e-3, err_msg=layout)


def test_card_detectors_through_the_mec_give_its_object_lists(frames, cards) -> None:
    expected = object_lists(frames, camera_detector("onnx", threads=1))
    assert any(expected), "no objects published: the comparison would prove nothing"
    for layout, path in cards.items():
        assert object_lists(frames, camera_detector(str(path), threads=1)) == expected, layout


@pytest.mark.parametrize(
    ("layout", "override", "message"),
    [
        ("yolov8", {"num_classes": 80}, "does not fit layout yolov8 with 80 classes"),
        ("yolov5", {"num_classes": 3}, "does not fit layout yolov5"),
        ("yolox", {"yolox": {"strides": [8, 16, 32]}}, "does not fit layout yolox"),
        (
            "yolov8",
            {"input": {"width": 640, "height": 640, "tensor": "nchw_float32"}},
            "does not fit the card",
        ),
        ("yolov5", {"input": {"width": 448, "height": 336, "tensor": "nhwc_uint8"}}, "does not fit the card"),
    ],
)
def test_a_card_that_does_not_fit_its_model_is_refused_at_load(
    tmp_path: Path, layout: str, override: dict, message: str
) -> None:
    if "num_classes" in override:
        override["classes"] = {0: "car"}
    path = write_card(tmp_path, layout, **override)
    with pytest.raises(ConfigError, match=message):
        camera_detector(str(path))


def test_the_committed_card_is_the_one_its_training_config_gives() -> None:
    """deploy/models/camera/model.yaml is written by the export from config.json: they must agree."""
    config = CameraDetectorConfig.load(MODELS_DIR / "camera" / CONFIG_FILE)
    assert load_card(MODELS_DIR / CAMERA_CARD) == config.card()


def test_a_card_of_the_other_kind_is_refused() -> None:
    with pytest.raises(ConfigError, match="a lidar card, not a camera detector's"):
        camera_detector(str(MODELS_DIR / LIDAR_CARD))
    with pytest.raises(ConfigError, match="a camera card, not a lidar detector's"):
        lidar_detector(str(MODELS_DIR / CAMERA_CARD))
