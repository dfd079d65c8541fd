"""OnnxCameraDetector: input checks, original-pixel boxes (hand-built ONNX model with known output),
and export fidelity (onnxruntime == torch)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from shared.detection.camera.config import (
    CONFIG_FILE,
    ONNX_FILE,
    ONNX_INPUT,
    ONNX_OUTPUT,
    CameraDetectorConfig,
    InputConfig,
    NetConfig,
    PostprocessConfig,
)
from shared.detection.camera.onnx_detector import OnnxCameraDetector, measure_latency
from shared.detection.interface import CameraDetector, DetectorInputError
from tests.helpers import REPO_ROOT

SMALL = CameraDetectorConfig(
    input=InputConfig(width=64, height=48),
    net=NetConfig(widths=(8, 8, 16, 16, 16), blocks=(0, 1, 1, 1, 1), neck_width=16, head_convs=1),
    post=PostprocessConfig(score_threshold=0.3),
)
# Two cells in input px (64 x 48): a car and a low-score cell; plus a duplicate the NMS must remove.
KNOWN_CELLS = np.array(
    [[8, 4, 24, 20, 0.9], [9, 4, 25, 20, 0.7], [40, 30, 48, 40, 0.05]],
    np.float32,
)


def constant_model(path: Path, cfg: CameraDetectorConfig, cells: np.ndarray) -> Path:
    """ONNX graph with the detector's signature that outputs `cells` (N, 5) for every image."""
    h, w = cfg.input.height, cfg.input.width
    images = helper.make_tensor_value_info(ONNX_INPUT, TensorProto.UINT8, ["batch", h, w, 3])
    out = helper.make_tensor_value_info(ONNX_OUTPUT, TensorProto.FLOAT, ["batch", len(cells), 5])
    const = helper.make_tensor("cells", TensorProto.FLOAT, [1, *cells.shape], cells.reshape(-1).tolist())
    tail = helper.make_tensor("tail", TensorProto.INT64, [2], list(cells.shape))
    nodes = [
        helper.make_node("Shape", [ONNX_INPUT], ["shape"], start=0, end=1),
        helper.make_node("Concat", ["shape", "tail"], ["out_shape"], axis=0),
        helper.make_node("Expand", ["cells", "out_shape"], [ONNX_OUTPUT]),
    ]
    graph = helper.make_graph(nodes, "constant_detector", [images], [out], initializer=[const, tail])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    onnx.save(model, str(path / ONNX_FILE))
    cfg.save(path / CONFIG_FILE)
    return path / ONNX_FILE


@pytest.fixture(scope="module")
def constant_detector(tmp_path_factory: pytest.TempPathFactory) -> OnnxCameraDetector:
    path = constant_model(tmp_path_factory.mktemp("constant"), SMALL, KNOWN_CELLS)
    return OnnxCameraDetector(path, intra_op_threads=1)


def test_runtime_does_not_import_torch() -> None:
    code = "import sys, shared.detection.camera.onnx_detector; sys.exit('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, check=False).returncode == 0


def test_is_a_camera_detector(constant_detector: OnnxCameraDetector) -> None:
    detector: CameraDetector = constant_detector
    assert detector.name


def test_boxes_in_original_pixels(constant_detector: OnnxCameraDetector) -> None:
    # 640x480 -> scale 0.1; 128x192 (portrait) -> scale 0.25, padded on the right.
    images = [np.zeros((480, 640, 3), np.uint8), np.zeros((192, 128, 3), np.uint8)]
    out = constant_detector.detect(images)
    assert len(out) == 2
    np.testing.assert_allclose(out[0], [[80, 40, 240, 200, 0.9, 0]], rtol=1e-5)
    np.testing.assert_allclose(out[1], [[32, 16, 96, 80, 0.9, 0]], rtol=1e-5)
    assert all(o.dtype == np.float32 and o.shape[1] == 6 for o in out)


def test_batch_buffer_grows_and_shrinks(constant_detector: OnnxCameraDetector) -> None:
    img = np.zeros((480, 640, 3), np.uint8)
    assert len(constant_detector.detect([img] * 5)) == 5
    assert len(constant_detector.detect([img])) == 1


def test_config_from_the_argument_wins(tmp_path: Path) -> None:
    path = constant_model(tmp_path, SMALL, KNOWN_CELLS)
    low = SMALL.model_copy(update={"post": PostprocessConfig(score_threshold=0.01)})
    out = OnnxCameraDetector(path, low.card(), intra_op_threads=1).detect([np.zeros((48, 64, 3), np.uint8)])
    np.testing.assert_allclose(out[0][:, 4], [0.9, 0.05])


def test_input_size_mismatch_is_refused(tmp_path: Path) -> None:
    path = constant_model(tmp_path, SMALL, KNOWN_CELLS)
    other = CameraDetectorConfig(input=InputConfig(width=80, height=48))
    with pytest.raises(ValueError, match="does not fit the card"):
        OnnxCameraDetector(path, other.card())


@pytest.mark.parametrize(
    ("images", "message"),
    [
        ([], "no images"),
        (np.zeros((1, 48, 64, 3), np.uint8), "expected a list"),
        ([np.zeros((48, 64), np.uint8)], "image 0: expected \\(H, W, 3\\) uint8"),
        ([np.zeros((48, 64, 1), np.uint8)], "image 0"),
        ([np.zeros((48, 64, 4), np.uint8)], "image 0"),
        ([np.zeros((48, 64, 3), np.uint8), np.zeros((48, 64, 3), np.float32)], "image 1.*float32"),
        ([np.zeros((0, 64, 3), np.uint8)], "empty image"),
        (["not an image"], "image 0"),
    ],
)
def test_malformed_input_raises(constant_detector: OnnxCameraDetector, images: object, message: str) -> None:
    with pytest.raises(DetectorInputError, match=message):
        constant_detector.detect(images)  # type: ignore[arg-type]


def test_measure_latency_reports_percentiles(constant_detector: OnnxCameraDetector) -> None:
    stats = measure_latency(constant_detector, [np.zeros((480, 640, 3), np.uint8)] * 2, repeats=3, warmup=1)
    assert stats["batch"] == 2
    assert 0 < stats["p50_ms"] <= stats["p95_ms"]


# --- export fidelity: the real network ----------------------------------------------------------------


def test_onnx_matches_torch(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    from shared.detection.camera.geometry import letterbox_image, postprocess
    from training.camera.export import compare_with_torch, export_onnx
    from training.camera.net import CameraNet, ExportModel

    # Every cell kept (no top-k cut among near-equal scores): the comparison cannot flip on float noise.
    keep_all = PostprocessConfig(score_threshold=0.2, pre_nms_top_k=10_000, max_detections=10_000)
    cfg = CameraDetectorConfig(post=keep_all)
    torch.manual_seed(0)
    net = CameraNet(cfg).eval()
    with torch.no_grad():  # move every cell's score near 0.5 so that detections exist to compare
        net.pred.bias[0] = 0.0
    path = export_onnx(net, cfg, tmp_path)
    box_err, score_err = compare_with_torch(path, net, cfg)
    assert box_err < 1e-2 and score_err < 1e-4

    rng = np.random.default_rng(0)
    images = [
        rng.integers(0, 256, (480, 640, 3), dtype=np.uint8),
        rng.integers(0, 256, (300, 500, 3), np.uint8),
    ]
    got = OnnxCameraDetector(path, cfg.card(), intra_op_threads=1).detect(images)
    batch = np.zeros((2, cfg.input.height, cfg.input.width, 3), np.uint8)
    boxes = [letterbox_image(img, cfg.input, out=batch[i]) for i, img in enumerate(images)]
    with torch.no_grad():
        cells = ExportModel(net)(torch.from_numpy(batch)).numpy()
    expected = postprocess(cells, boxes, cfg.post)
    assert sum(len(e) for e in expected) > 0
    for g, e in zip(got, expected, strict=True):
        assert g.shape == e.shape
        # Same rows up to order (NMS ranks near-equal scores in either order): nearest row of each.
        nearest = np.abs(g[:, None, :] - e[None, :, :]).max(axis=2).min(axis=1)
        assert nearest.max() < 1e-2


def test_warm_up_runs_every_batch_size_without_memory_patterns(tmp_path: Path) -> None:
    """Batches of varying size must not each keep a memory pattern (RSS grew in steps in the soak);
    the warm-up runs each size once, largest first."""
    detector = OnnxCameraDetector(constant_model(tmp_path, SMALL, KNOWN_CELLS), intra_op_threads=1)
    assert not detector.session.get_session_options().enable_mem_pattern
    sizes: list[int] = []
    run = detector.session.run

    class Recording:
        def run(self, names, feeds):
            sizes.append(next(iter(feeds.values())).shape[0])
            return run(names, feeds)

    detector.session = Recording()  # type: ignore[assignment]
    detector.warm_up(3)
    assert sizes == [3, 2, 1]


# --- free-size graphs and the input tensor --------------------------------------------------------------


def test_a_free_size_graph_runs_at_the_size_asked_and_maps_boxes_back(tmp_path: Path) -> None:
    """The constant model with symbolic height and width: asked to run a 256 x 128 image at 128 x 64
    (scale 0.5), its input-px cells come back doubled; a fixed-size graph refuses another size."""
    path = constant_model(tmp_path, SMALL, KNOWN_CELLS)
    model = onnx.load(str(path))
    dims = model.graph.input[0].type.tensor_type.shape.dim
    dims[1].dim_param, dims[2].dim_param = "height", "width"
    onnx.save(model, str(path))
    free = OnnxCameraDetector(path, intra_op_threads=1)
    assert free.any_size
    out = free.detect([np.zeros((128, 256, 3), np.uint8)], size=(128, 64))
    np.testing.assert_allclose(out[0], [[16, 8, 48, 40, 0.9, 0]], rtol=1e-5)
    assert free.card_at((128, 64)).input.width == 128 and free.card.input.width == 64  # the card kept
    (tmp_path / "fixed").mkdir()
    fixed = OnnxCameraDetector(constant_model(tmp_path / "fixed", SMALL, KNOWN_CELLS), intra_op_threads=1)
    assert not fixed.any_size
    with pytest.raises(ValueError, match="fixed at 64 x 48"):
        fixed.detect([np.zeros((128, 256, 3), np.uint8)], size=(128, 64))


@pytest.mark.parametrize(
    ("colour", "scale", "mean", "std"),
    [
        ("bgr", 1.0, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
        ("rgb", 1 / 255, (0.485, 0.456, 0.406), (0.2, 0.3, 0.4)),
    ],
)
def test_the_input_tensor_is_the_cards_formula(colour: str, scale: float, mean: tuple, std: tuple) -> None:
    """tensor() against the card's formula written plainly: channel order, NCHW, x scale, - mean, / std."""
    card = SMALL.card()
    inp = {"tensor": "nchw_float32", "colour": colour, "scale": scale, "mean": mean, "std": std}
    card = card.model_copy(update={"input": card.input.model_copy(update=inp)})
    det = OnnxCameraDetector.__new__(OnnxCameraDetector)
    det.card = card
    det._mean = np.asarray(mean, np.float32).reshape(1, 3, 1, 1)
    det._std = np.asarray(std, np.float32).reshape(1, 3, 1, 1)
    det._normalise = colour == "rgb"
    batch = np.random.default_rng(1).integers(0, 256, (2, 48, 64, 3), np.uint8)
    ordered = batch[..., ::-1] if colour == "bgr" else batch
    want = (ordered.transpose(0, 3, 1, 2).astype(np.float32) * np.float32(scale) - det._mean) / det._std
    got = det.tensor(batch)
    assert got.shape == (2, 3, 48, 64) and got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
