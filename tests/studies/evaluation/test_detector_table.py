"""The README's detector table: figures read from the results file, the previous models' beside them."""

from __future__ import annotations

import pytest

from studies.evaluation import detectors


def _camera(ap50: float, p50: float = 5.0) -> dict[str, object]:
    latency = {"p50": p50, "p95": p50 + 1, "n": 10}
    return {
        "detector": "onnx-camera", "images": 2340, "ap50": ap50, "ap50_95": 0.85,
        "latency_ms": {"1_threads": latency, "2_threads": latency},
    }  # fmt: skip


def _lidar(name: str, bev70: float) -> dict[str, object]:
    scored = ((0.7, "all", bev70), (0.7, "[0, 2)", 0.97134), (0.7, "[4, inf)", 0.6297), (0.5, "[0, 2)", 0.99))
    bands = [{"kind": "bev", "iou": iou, "band": band, "ap": ap} for iou, band, ap in scored]
    return {
        "detector": name,
        "frames": 600,
        "bev_ap70": bev70,
        "bev_ap50": 0.97,
        "ap3d_70": 0.81,
        "ap": bands,
    }


def _results(commit: str, camera_ap: float, lidar: list[dict[str, object]]) -> dict[str, object]:
    oracle = {"detector": "oracle-camera", "images": 2340, "ap50": 1.0, "ap50_95": 1.0}
    return {
        "split": "test", "data": "data/datasets/default", "commit": commit,
        "machine": {"cpu_model": "Test CPU"}, "camera": [_camera(camera_ap), oracle], "lidar": lidar,
    }  # fmt: skip


def test_rows_and_the_previous_models_beside_them() -> None:
    new = _results("bbb", 0.9612, [_lidar("pointpillars", 0.8801), _lidar("cluster", 0.449)])
    old = _results("aaa", 0.9587, [_lidar("pointpillars", 0.8786)])
    lines = detectors.markdown_table(new, old).splitlines()
    assert "commit bbb, Test CPU" in lines[0]
    assert lines[2].startswith("| Detector | Test data | AP | previous models (commit aaa) |")
    camera = next(line for line in lines if line.startswith("| camera CNN"))
    assert "| 2,340 images | AP@0.5 **0.961**, AP@0.5:0.95 0.850 |" in camera
    assert "| AP@0.5 0.959, AP@0.5:0.95 0.850 |" in camera
    assert camera.endswith("| 5.0 / 6.0 ms | 5.0 / 6.0 ms |")
    pillars = next(line for line in lines if line.startswith("| PointPillars"))
    assert "BEV AP@0.7 **0.880**" in pillars and "BEV AP@0.7 0.879" in pillars
    cluster = next(line for line in lines if line.startswith("| clustering"))
    assert "| - | - | - |" in cluster  # no previous figures, no latency measured
    assert not any("oracle" in line for line in lines)  # noisy truth is not a detector
    assert lines[-1] == (
        "Lidar BEV AP@0.7 by distance from the agent origin (m): PointPillars (`pointpillars`) `[0, 2)` "
        "0.971, `[4, inf)` 0.630; clustering, no learning (`cluster`) `[0, 2)` 0.971, `[4, inf)` 0.630."
    )


def test_without_previous_no_column_and_another_split_is_refused() -> None:
    new = _results("bbb", 0.96, [])
    assert "previous" not in detectors.markdown_table(new)
    other = {**_results("aaa", 0.95, []), "split": "val"}
    with pytest.raises(ValueError, match="split 'val'"):
        detectors.markdown_table(new, other)
