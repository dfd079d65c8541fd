"""ONNX export vs torch, the ONNX detector's interface (input errors, empty clouds, output rows)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from shared.detection.interface import LIDAR_COLUMNS, DetectorInputError
from shared.detection.lidar.pointpillars.config import PointPillarsConfig
from shared.detection.lidar.pointpillars.onnx_detector import OnnxPointPillars, config_path_for, make_session
from shared.detection.lidar.pointpillars.pillars import pillarize
from training.pointpillars.export import compare, export_onnx, torch_outputs
from training.pointpillars.net import PointPillarsNet

TOLERANCE = 1e-4


@pytest.fixture
def exported(
    tmp_path: Path, tiny_config: PointPillarsConfig, synthetic_frame
) -> tuple[Path, PointPillarsNet]:
    torch.manual_seed(0)
    torch.set_num_threads(1)
    model = PointPillarsNet(tiny_config).eval()
    # Non-trivial BatchNorm statistics so the check is not of an identity-normalised network.
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm1d | torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 2.0)
    points, _ = synthetic_frame(0, tiny_config)
    path = tmp_path / "pp.onnx"
    report = export_onnx(model, tiny_config, path, points, tolerance=TOLERANCE)
    assert report.num_pillars > 0 and report.max_abs_diff_regression <= TOLERANCE and report.peak_flips == 0
    return path, model


def test_onnx_matches_torch_on_another_frame(
    exported, tiny_config: PointPillarsConfig, synthetic_frame
) -> None:
    import onnxruntime as ort

    path, model = exported
    points, _ = synthetic_frame(7, tiny_config)  # a different number of pillars than at export
    pillars = pillarize(points, tiny_config.grid)
    expected = torch_outputs(model, pillars, tiny_config)
    detector = OnnxPointPillars(path)
    assert isinstance(detector.session, ort.InferenceSession)
    scores_o, reg_o = detector.infer(pillars)
    np.testing.assert_allclose(reg_o, expected.regression[0], atol=TOLERANCE)
    diff_scores, diff_regression, flips = compare(scores_o[None, None], reg_o[None], expected, TOLERANCE)
    assert diff_scores <= TOLERANCE and diff_regression <= TOLERANCE and flips == 0
    assert config_path_for(path).exists()
    assert PointPillarsConfig.load(config_path_for(path)) == tiny_config


def test_detector_output_rows(exported, tiny_config: PointPillarsConfig, synthetic_frame) -> None:
    path, _ = exported
    low_threshold = tiny_config.model_copy(
        update={"post": tiny_config.post.model_copy(update={"score_threshold": 0.0})}
    )
    detector = OnnxPointPillars(path, low_threshold)
    points, _ = synthetic_frame(1, tiny_config)
    out = detector.detect(points.astype(np.float64))
    assert out.dtype == np.float32 and out.shape[1] == len(LIDAR_COLUMNS)
    assert 0 < len(out) <= tiny_config.post.max_detections
    assert np.all(np.diff(out[:, 7]) <= 0) and np.all(out[:, 8] == 0)
    assert np.all(out[:, 3:6] > 0)


def test_empty_and_out_of_range_clouds_give_no_rows(exported) -> None:
    detector = OnnxPointPillars(exported[0])
    assert detector.detect(np.zeros((0, 4), np.float32)).shape == (0, len(LIDAR_COLUMNS))
    far = np.array([[50.0, 0.0, 0.1, 1.0]], np.float32)
    assert detector.detect(far).shape == (0, len(LIDAR_COLUMNS))


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((5, 3), np.float32),
        np.zeros((5,), np.float32),
        np.zeros((5, 4), np.int32),
        np.array([[0.1, 0.2, np.nan, 1.0]], np.float32),
        np.array([[0.1, np.inf, 0.1, 1.0]], np.float64),
        [[0.1, 0.2, 0.1, 1.0]],
    ],
    ids=["3-columns", "1-d", "int", "nan", "inf", "list"],
)
def test_malformed_input_raises(exported, points) -> None:
    with pytest.raises(DetectorInputError):
        OnnxPointPillars(exported[0]).detect(points)


def test_onnx_detector_does_not_import_torch() -> None:
    import subprocess

    code = (
        "import sys; import shared.detection.lidar.pointpillars.onnx_detector; "
        "sys.exit(1 if 'torch' in sys.modules else 0)"
    )
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_sessions_keep_no_memory_pattern_per_cloud_size(exported) -> None:
    """Every sweep has its own pillar count: a memory pattern per shape grew RSS in steps
    (tests/bench/memory_bench.py)."""
    path, _ = exported
    assert not make_session(path, threads=1).get_session_options().enable_mem_pattern
    assert make_session(path, threads=1, mem_pattern=True).get_session_options().enable_mem_pattern


def test_warm_up_runs_the_most_pillars_first_then_fewer(exported) -> None:
    """The arena is sized by the densest frame at start (it grew in steps at dense frames in the soak)."""
    path, _ = exported
    detector = OnnxPointPillars(path)
    grid = detector.config.grid
    counts: list[int] = []
    infer = detector.infer

    def recording(pillars):
        counts.append(len(pillars))
        return infer(pillars)

    detector.infer = recording  # type: ignore[method-assign]
    detector.warm_up(steps=4)
    most = min(grid.max_pillars, grid.nx * grid.ny)
    assert counts[0] == most and counts[-1] == 1 and len(counts) == 5
    assert counts == sorted(counts, reverse=True)
