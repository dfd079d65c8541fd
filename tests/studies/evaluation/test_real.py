"""`rmmdet eval real` on the vendored real frames (issue 50): the production MEC core over two labelled
TUMTraf A9 frames (lidar + two cameras) and a Rope3D frame (camera only), scored against the datasets'
labels; labels that disagree with the sensors set aside and counted; bad input refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from services.cli.main import app
from studies.evaluation import real
from studies.evaluation.run import eval_site
from tests.shared.datasets.roadside.conftest import ROPE3D, TUMTRAF


@pytest.fixture(scope="module")
def tumtraf_results() -> dict:
    mec = real.with_detectors(
        eval_site(real.REAL_SIZE_PROFILE).mec(), real.DEFAULT_CAMERA, real.DEFAULT_LIDAR
    )
    results = real.run_study("openlabel", TUMTRAF, mec, {"camera": "coco", "lidar": "cluster"})
    (site,) = results["sites"]
    return site


def test_every_output_is_scored_against_the_labels(tumtraf_results: dict) -> None:
    site = tumtraf_results
    assert site["frames"] == 2 and not site["sequence"]
    assert set(site["stages"]) == {"lidar", "camera", "fused"}  # tracks: sequences only
    lidar = site["stages"]["lidar"]
    # 16 labelled vehicles with >= 20 points in the two frames; the clustering detector finds 14 of them
    # (its misses and its false boxes: docs/real-data.md)
    assert lidar["num_gt"] == 16 and lidar["tp"] >= 13
    assert lidar["pose_error_p50_m"] < 0.6
    assert set(lidar["ap"]) == {"bev@0.5", "bev@0.25", "3d@0.5", "3d@0.25"}
    assert sum(v["num_gt"] for v in lidar["recall_by_points"].values()) == 16
    # recall by range: the KITTI AP's bands, every vehicle in one, the bands' recalls pool to the recall
    by_range = lidar["recall_by_range"]
    assert {k: v["num_gt"] for k, v in by_range.items()} == {
        k: v["num_gt"] for k, v in lidar["ap"]["bev@0.5"].items() if k != "all"
    }
    found = sum(v["recall"] * v["num_gt"] for v in by_range.values() if v["num_gt"])
    assert found == pytest.approx(lidar["recall"] * 16)
    assert 0 < lidar["fp_recurring"] <= lidar["fp"]  # static structure boxed in both frames
    # the fused output never recalls less than its best single branch
    recalls = {s: site["stages"][s]["recall"] for s in ("lidar", "camera", "fused")}
    assert recalls["fused"] >= max(recalls["lidar"], recalls["camera"])
    cams = site["camera_2d"]
    assert set(cams) == {"s110_camera_basler_south1_8mm", "s110_camera_basler_south2_8mm"}
    assert all(v["ap50"] > 0.5 for v in cams.values())


def test_labels_that_disagree_with_the_sensors_are_counted_not_scored(tumtraf_results: dict) -> None:
    counts = tumtraf_results["counts"]
    assert counts["disagree/no_points"] == 1  # frame 2's car at 100 m: its box holds no point
    # frame 2's south2 image is 109 ms after the lidar's sweep: its 2D boxes are not scored on it
    assert counts["disagree/stamp_apart/s110_camera_basler_south2_8mm"] == 1
    assert tumtraf_results["camera_2d"]["s110_camera_basler_south2_8mm"]["frames"] == 1
    assert counts["missing/1646667315_484371032_s110_camera_basler_south1_8mm.jpg"] == 1
    assert counts["frames/scored"] == 2


def test_the_cli_writes_results_and_the_docs_section(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Rope3D, camera only: results, summary and (with --readme) the page section."""
    page = tmp_path / "real-data.md"
    page.write_text("<!-- eval-real-rope3d:begin -->\n<!-- eval-real-rope3d:end -->\n")
    monkeypatch.setattr("shared.readme.section_file", lambda name, root=None: page)
    out = tmp_path / "out"
    args = ["eval", "real", "--format", "rope3d", "--data", str(ROPE3D), "--out", str(out), "--readme"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    (site,) = json.loads((out / "results.json").read_text())["sites"]
    assert site["camera_2d"]["camera"]["num_gt"] == 15 and site["camera_2d"]["camera"]["ap50"] > 0.5
    assert site["stages"]["camera"]["num_gt"] == 15
    assert "| camera | 15 |" in page.read_text() and "_Written by" in page.read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--format", "kitti", "--data", str(ROPE3D)], "--format kitti: one of openlabel, dair, rope3d"),
        (["--format", "rope3d", "--data", str(TUMTRAF)], "not a Rope3D folder"),
        (["--format", "openlabel", "--data", str(ROPE3D / "calib")], "no OpenLABEL"),
        (
            ["--format", "openlabel", "--data", str(TUMTRAF), "--lidar", "background"],
            "these 2 frames are independent",
        ),
    ],
)
def test_wrong_input_is_refused_in_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = CliRunner().invoke(app, ["eval", "real", *args, "--out", str(tmp_path)])
    assert result.exit_code == 2 and message in " ".join(result.output.split()), result.output


def test_false_boxes_are_told_apart_by_where_they_stand() -> None:
    """Known answer: a box at the same place in the other frame recurs; one floating 3 m up is elevated."""
    car = [10.0, 0.0, 0.75, 4.5, 1.8, 1.5, 0.0]
    sign = [30.0, 5.0, 3.5, 4.0, 0.5, 1.0, 0.0]  # its bottom 3 m up
    frames = [np.array([car, sign]), np.array([[10.5, 0.2, 0.75, 4.5, 1.8, 1.5, 0.0]]), np.zeros((0, 7))]
    assert real.false_box_kinds(frames, gate_m=1.0) == {"fp_recurring": 2, "fp_elevated": 1}
    assert real.false_box_kinds(frames, gate_m=0.1) == {"fp_recurring": 0, "fp_elevated": 1}


def test_a_dair_layout_runs_through_the_same_study(tumtraf_results: dict, tmp_path: Path) -> None:
    """The first TUMTraf frame written in DAIR-V2X-I's layout (test_dair.write_dair) scores as TUMTraf's
    own first frame does: the same lidar boxes found among the same labelled vehicles."""
    from shared.datasets.roadside.openlabel import read_openlabel
    from tests.shared.datasets.roadside.test_dair import write_dair

    root = write_dair(read_openlabel(TUMTRAF), tmp_path / "single-infrastructure-side")
    mec = real.with_detectors(
        eval_site(real.REAL_SIZE_PROFILE).mec(), real.DEFAULT_CAMERA, real.DEFAULT_LIDAR
    )
    (site,) = real.run_study("dair", root, mec, {"camera": "coco", "lidar": "cluster"})["sites"]
    lidar = site["stages"]["lidar"]
    assert site["frames"] == 1 and lidar["num_gt"] == 8 and lidar["tp"] >= 6


def test_a_sequence_scores_its_tracks() -> None:
    """Frames of one sequence go through one core: its published tracks are scored (AP and MOTA / IDF1
    against the labels' object ids, which TUMTraf keeps across frames). The two vendored frames are
    5.4 s apart, so few tracks confirm; the path, not the figure, is what this checks."""
    import dataclasses

    (site,) = real.read_sites("openlabel", TUMTRAF)
    mec = real.with_detectors(
        eval_site(real.REAL_SIZE_PROFILE).mec(), real.DEFAULT_CAMERA, real.DEFAULT_LIDAR
    )
    out = real.evaluate_site(dataclasses.replace(site, sequence=True), mec)
    assert "tracked" in out["stages"] and out["stages"]["tracked"]["num_gt"] == 16
    assert out["tracking"] is not None and set(out["tracking"]) >= {"mota", "idf1", "hota", "id_switches"}
    assert "MOTA" in real.markdown({"data": "x", "format": "openlabel", "detectors": {}, "mec_profile": "p",
                                    "commit": "c", "sites": [out]})  # fmt: skip


def test_recall_at_a_precision_reads_the_score_ranked_curve() -> None:
    """Known answer: TP 0.9, FP 0.8, TP 0.7, TP 0.6, FP 0.5 of 5 vehicles: at precision >= 0.75 the best
    threshold keeps the first four (3 of 4 true): recall 3/5; at >= 0.9 only the first: 1/5."""
    scored = [(0.9, 1), (0.8, 0), (0.7, 1), (0.6, 1), (0.5, 0), (0.95, 2)]  # the 0.95 box is ignored
    assert real.recall_at_precision(scored, 5, 0.75) == pytest.approx(0.6)
    assert real.recall_at_precision(scored, 5, 0.9) == pytest.approx(0.2)
    assert real.recall_at_precision([], 5, 0.8) == 0.0 and real.recall_at_precision(scored, 0, 0.8) is None


def test_yaw_errors_read_the_orientation_similarity() -> None:
    """Known answer: boxes 10 and 170 degrees off a vehicle's heading are both 10 degrees off modulo 180."""
    from shared.metrics.fusion import FusionAccumulator

    acc = FusionAccumulator(5.0)
    gt = np.array([[0.0, 0.0, 0.75, 4.5, 1.8, 1.5, 0.0], [20.0, 0.0, 0.75, 4.5, 1.8, 1.5, 0.0]])
    pred = gt.copy()
    pred[:, 6] = np.radians([10.0, 170.0])
    acc.add_frame(pred, gt)
    got = real.yaw_errors_deg(acc)
    assert got["yaw_error_p50_deg"] == pytest.approx(10.0) and got["yaw_error_p95_deg"] == pytest.approx(10.0)
    headless = FusionAccumulator(5.0)
    headless.add_frame(pred, gt, yaw_valid=[False, False])  # a camera-only object off any lane
    assert real.yaw_errors_deg(headless) == {"yaw_error_p50_deg": None, "yaw_error_p95_deg": None}
