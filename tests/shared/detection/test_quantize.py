"""Int8 quantization tooling: model file names by precision, the registry and the MEC setting that pick
them, the training-seeds-only calibration rule, the fp32-vs-int8 comparison, and `quantize_model` on a
small convolutional graph."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper
from pydantic import ValidationError

from shared.detection.lidar.pointpillars.onnx_detector import config_path_for
from shared.detection.precision import PRECISIONS, fp32_file, model_file
from shared.detection.registry import CAMERA_MODEL, LIDAR_MODEL, camera_detector, lidar_detector
from shared.geometry.boxes import iou2d_matrix
from shared.perception.config import DetectorsConfig, MecSettings
from tests.helpers import REPO_ROOT
from training.quantize import check_training_seeds, compare_outputs, quantize_model


def test_model_file_names() -> None:
    assert PRECISIONS == ("fp32", "int8")
    assert model_file(Path("m/model.onnx"), "fp32") == Path("m/model.onnx")
    assert model_file(Path("m/model.onnx"), "int8") == Path("m/model_int8.onnx")
    assert fp32_file(Path("m/pointpillars_int8.onnx")) == Path("m/pointpillars.onnx")
    assert fp32_file(Path("m/pointpillars.onnx")) == Path("m/pointpillars.onnx")
    assert config_path_for(Path("m/pointpillars_int8.onnx")) == Path("m/pointpillars.json")
    with pytest.raises(ValueError, match="unknown precision"):
        model_file(Path("m/model.onnx"), "int4")


def test_registry_refuses_unknown_and_missing_models(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown precision"):
        camera_detector("onnx", precision="fp16")
    with pytest.raises(FileNotFoundError, match=r"training\.camera\.quantize"):
        camera_detector("onnx", models_dir=tmp_path, precision="int8")
    with pytest.raises(FileNotFoundError, match=r"training\.pointpillars\.quantize"):
        lidar_detector("pointpillars", models_dir=tmp_path, precision="int8")
    # Ground-truth detectors have no model file: the precision does not concern them.
    assert lidar_detector("oracle", precision="int8").name


def test_committed_int8_models_exist() -> None:
    models = REPO_ROOT / "deploy" / "models"
    for model in (CAMERA_MODEL, LIDAR_MODEL):
        assert model_file(models / model, "int8").is_file()


def test_precision_setting_defaults_to_fp32_and_validates(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = DetectorsConfig()
    assert (cfg.camera_precision, cfg.lidar_precision) == ("fp32", "fp32")
    with pytest.raises(ValidationError):
        DetectorsConfig(camera_precision="int4")
    monkeypatch.setenv("RMMDET_MEC_DETECTORS__LIDAR_PRECISION", "int8")
    settings = MecSettings(detectors={"camera": "oracle"})
    assert settings.detectors.lidar_precision == "int8" and settings.detectors.camera == "oracle"


def test_calibration_takes_training_seeds_only() -> None:
    assert check_training_seeds([1, 24]) == [1, 24]
    for seeds in ([1, 101], [201], []):
        with pytest.raises(ValueError, match="training seeds"):
            check_training_seeds(seeds)


def test_compare_outputs() -> None:
    fp32 = [np.array([[0, 0, 10, 10, 0.9], [20, 20, 30, 30, 0.5]]), np.zeros((0, 5))]
    int8 = [np.array([[0, 0, 10, 10.5, 0.88], [50, 50, 60, 60, 0.4]]), np.array([[0, 0, 5, 5, 0.3]])]
    out = compare_outputs(fp32, int8, lambda a, b: iou2d_matrix(a[:, :4], b[:, :4]), 0.8, slice(0, 4), 4)
    assert out["fp32_detections"] == 2 and out["matched_share"] == 0.5 and out["int8_unmatched"] == 2
    assert out["box_dev_max"] == pytest.approx(0.5) and out["score_dev_max"] == pytest.approx(0.02)
    yaw = compare_outputs(
        [np.array([[0, 0, 1, 1, 3.1, 0.9]])],
        [np.array([[0, 0, 1, 1, -3.1, 0.9]])],
        lambda a, b: np.ones((len(a), len(b))),
        0.8,
        slice(0, 4),
        5,
        angle_col=4,
    )
    assert yaw["angle_dev_max"] == pytest.approx(2 * np.pi - 6.2)


# --- quantize_model on a small graph -----------------------------------------------------------------


def conv_model(path: Path) -> Path:
    """x (N, 3, 16, 16) -> Conv 3->8 -> Relu -> Conv 8->4 (named "head") -> y."""
    rng = np.random.default_rng(0)
    w1 = numpy_helper.from_array(rng.normal(0, 0.3, (8, 3, 3, 3)).astype(np.float32), "w1")
    w2 = numpy_helper.from_array(rng.normal(0, 0.3, (4, 8, 1, 1)).astype(np.float32), "w2")
    nodes = [
        helper.make_node("Conv", ["x", "w1"], ["c1"], name="body", pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"], name="act"),
        helper.make_node("Conv", ["r1", "w2"], ["y"], name="head"),
    ]
    graph = helper.make_graph(
        nodes,
        "small",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", 3, 16, 16])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 4, 16, 16])],
        initializer=[w1, w2],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.save(model, str(path))
    return path


def test_quantize_model_keeps_the_listed_nodes_float(tmp_path: Path) -> None:
    src = conv_model(tmp_path / "small.onnx")
    rng = np.random.default_rng(1)
    feeds = [{"x": rng.uniform(0, 1, (1, 3, 16, 16)).astype(np.float32)} for _ in range(8)]
    out = quantize_model(src, tmp_path / "small_int8.onnx", feeds, ("Conv", "Relu"), ("head",))
    graph = onnx.load(str(out)).graph
    assert any(n.op_type == "QuantizeLinear" for n in graph.node)
    head = next(n for n in graph.node if n.name == "head")
    assert head.input[1] == "w2"  # float weights, no DequantizeLinear in front
    x = feeds[0]["x"]
    expected = ort.InferenceSession(str(src)).run(None, {"x": x})[0]
    got = ort.InferenceSession(str(out)).run(None, {"x": x})[0]
    assert np.abs(got - expected).max() < 0.05 * np.abs(expected).max()
    with pytest.raises(ValueError, match="not in the graph"):
        quantize_model(src, tmp_path / "other.onnx", feeds, ("Conv",), ("no_such_node",))
    with pytest.raises(ValueError, match="no calibration inputs"):
        quantize_model(src, tmp_path / "other.onnx", [], ("Conv",))


@pytest.mark.parametrize("count", [16, 17, 33])
def test_every_calibration_input_counts(tmp_path: Path, count: int) -> None:
    """The calibrated range covers every input, not only the last `count % 16` (onnxruntime's
    `CalibMaxIntermediateOutputs` drops each full batch of 16 uncounted): the first inputs reach 10x
    higher than the last, and a bright input is reproduced after quantization. 16 inputs failed outright."""
    src = conv_model(tmp_path / "small.onnx")
    rng = np.random.default_rng(2)
    feeds = [
        {"x": rng.uniform(0, 10 if i < 16 else 1, (1, 3, 16, 16)).astype(np.float32)} for i in range(count)
    ]
    out = quantize_model(src, tmp_path / "small_int8.onnx", feeds, ("Conv", "Relu"), ("head",))
    x = feeds[0]["x"]
    expected = ort.InferenceSession(str(src)).run(None, {"x": x})[0]
    got = ort.InferenceSession(str(out)).run(None, {"x": x})[0]
    assert np.abs(got - expected).max() < 0.05 * np.abs(expected).max()


def test_quantize_tools_do_not_import_torch() -> None:
    code = (
        "import sys, training.camera.quantize, training.pointpillars.quantize; "
        "sys.exit('torch' in sys.modules)"
    )
    assert subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, check=False).returncode == 0
