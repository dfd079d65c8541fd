"""Known-answer tests for shared.metrics.fusion (pose error, AOS, BEV IoU, P/R, heat maps, AP-BEV)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from shared.geometry.grid import grid_shape
from shared.metrics.fusion import (
    DEFAULT_CELL_M,
    DEFAULT_MATCH_DISTANCE_M,
    HEAT_MAP_KEYS,
    FusionAccumulator,
    aos_kitti_term,
    aos_term,
    match_frame,
    save_heat_map_png,
)

CAR = (0.33, 0.22, 0.21)
NO_BOXES = np.zeros((0, 7))
# The paper's heat-map grid: x in [-2, 2), y in [-5, 3), 0.125 m cells -> 32 x 64.
X_RANGE = (-2.0, 2.0)
Y_RANGE = (-5.0, 3.0)


def car(x: float, y: float, yaw: float = 0.0, size: tuple[float, float, float] = CAR) -> list[float]:
    return [x, y, size[2] / 2, *size, yaw]


def cars(*rows: list[float]) -> np.ndarray:
    return np.array(rows, dtype=np.float64)


GT3 = cars(car(0.0, 0.0, 0.3), car(1.0, -2.0, -1.2), car(-1.5, 2.0, 3.0))


# --- matching ----------------------------------------------------------------------------------------


def test_match_frame_perfect_and_empty() -> None:
    m = match_frame(GT3[::-1], GT3)
    assert m.pred_index.tolist() == [0, 1, 2] and m.gt_index.tolist() == [2, 1, 0]
    assert np.allclose(m.distance_m, 0.0)
    assert m.false_positives.size == m.misses.size == m.ignored.size == 0
    empty = match_frame(np.zeros(0), np.zeros(0))
    assert empty.pred_index.size == empty.misses.size == empty.false_positives.size == 0
    only_gt = match_frame(NO_BOXES, GT3)
    assert only_gt.misses.tolist() == [0, 1, 2]


def test_gate_is_inclusive_below_and_exclusive_above() -> None:
    assert DEFAULT_MATCH_DISTANCE_M == 0.3
    gt = cars(car(0.0, 0.0))
    inside = match_frame(cars(car(0.0, 0.29)), gt)
    assert inside.pred_index.tolist() == [0] and inside.distance_m[0] == pytest.approx(0.29)
    outside = match_frame(cars(car(0.0, 0.31)), gt)
    assert outside.pred_index.size == 0
    assert outside.false_positives.tolist() == [0] and outside.misses.tolist() == [0]
    assert match_frame(cars(car(0.0, 0.31)), gt, max_distance_m=0.5).pred_index.tolist() == [0]


def test_hungarian_maximises_matches_before_distance() -> None:
    # Greedy nearest-first would pair p (0.22 from a) with a and leave q (only near a) unmatched; the
    # assignment must instead give q -> a (0.25) and p -> b (0.28), both inside the 0.3 m gate.
    gt = cars(car(0.0, 0.0), car(0.5, 0.0))
    preds = cars(car(0.22, 0.0), car(-0.25, 0.0))
    m = match_frame(preds, gt)
    assert dict(zip(m.pred_index.tolist(), m.gt_index.tolist(), strict=True)) == {0: 1, 1: 0}
    assert np.allclose(m.distance_m, [0.28, 0.25])
    assert m.false_positives.size == m.misses.size == 0


def test_ignore_region_suppresses_false_positive() -> None:
    gt = cars(car(0.0, 0.0))
    preds = cars(car(0.0, 0.0), car(1.0, 1.0), car(-1.0, 1.2), car(1.5, -1.5))
    # A large region overlapping pred 1 and a zero-size region 0.2 m from pred 2 (centre rule).
    ignore = cars(car(1.3, 1.0, size=(0.5, 0.5, 0.2)), car(-1.0, 1.0, size=(0.0, 0.0, 0.0)))
    m = match_frame(preds, gt, gt_ignore=ignore)
    assert m.pred_index.tolist() == [0]
    assert m.ignored.tolist() == [1, 2] and m.false_positives.tolist() == [3]
    assert match_frame(preds, gt).false_positives.tolist() == [1, 2, 3]


# --- accumulator: known answers ----------------------------------------------------------------------


def test_perfect_predictions() -> None:
    acc = FusionAccumulator()
    for _ in range(2):
        acc.add_frame(GT3.copy(), GT3, scores=[0.9, 0.8, 0.7])
    s = acc.summary()
    assert s["tp"] == 6 and s["fp"] == 0 and s["fn"] == 0 and s["num_frames"] == 2
    assert s["precision"] == 1.0 and s["recall"] == 1.0
    assert s["pose_error_mean_m"] == 0.0 and s["pose_error_p95_m"] == 0.0
    assert s["aos_mean"] == pytest.approx(1.0) and s["aos_count"] == 6
    assert s["bev_iou_mean"] == pytest.approx(1.0)
    assert s["ap_bev_0.7"] == pytest.approx(1.0) and s["ap_bev_0.5"] == pytest.approx(1.0)
    json.dumps(s, allow_nan=False)  # JSON-ready: no NaN


def test_yaw_off_by_pi_scores_full_aos() -> None:
    acc = FusionAccumulator()
    preds = GT3.copy()
    preds[:, 6] += math.pi
    acc.add_frame(preds, GT3)
    s = acc.summary(with_ap=False)
    assert s["aos_mean"] == pytest.approx(1.0)
    assert s["aos_kitti_mean"] == pytest.approx(0.0, abs=1e-12)  # KITTI: facing the wrong way scores 0
    assert s["bev_iou_mean"] == pytest.approx(1.0)  # a π flip leaves the footprint unchanged


def test_yaw_off_by_half_pi_scores_zero_aos_and_exact_iou() -> None:
    acc = FusionAccumulator()
    acc.add_frame(cars(car(0.0, 0.0, math.pi / 2)), cars(car(0.0, 0.0, 0.0)))
    s = acc.summary(with_ap=False)
    assert s["aos_mean"] == pytest.approx(0.0, abs=1e-12)
    # Crossed 0.33 x 0.22 footprints share a 0.22 x 0.22 square: 0.22² / (2·0.33·0.22 - 0.22²) = 0.5.
    assert s["bev_iou_mean"] == pytest.approx(0.5)
    assert aos_term([0.1, math.pi / 4], [0.1 + 2 * math.pi, 0.0]) == pytest.approx([1.0, 0.5])


@pytest.mark.parametrize("yaw", [0.0, math.pi / 3, -2.0])
def test_shift_along_heading_gives_pose_error_and_exact_iou(yaw: float) -> None:
    shift = 0.1
    pred = car(shift * math.cos(yaw), shift * math.sin(yaw), yaw)
    acc = FusionAccumulator()
    acc.add_frame(cars(pred), cars(car(0.0, 0.0, yaw)))
    s = acc.summary()
    assert s["pose_error_mean_m"] == pytest.approx(shift)
    assert s["pose_error_p50_m"] == pytest.approx(shift) and s["pose_error_max_m"] == pytest.approx(shift)
    # Overlap 0.23 x 0.22, union 2·0.33·0.22 - 0.23·0.22 = 0.43·0.22.
    assert s["bev_iou_mean"] == pytest.approx(0.23 / 0.43)
    assert s["aos_mean"] == pytest.approx(1.0)
    assert s["ap_bev_0.7"] == 0.0 and s["ap_bev_0.5"] == pytest.approx(1.0)


def test_false_positives_and_misses_counted() -> None:
    acc = FusionAccumulator()
    gt = cars(car(0.0, 0.0), car(1.0, 1.0))
    acc.add_frame(cars(car(0.05, 0.0), car(-1.0, -1.0)), gt)  # 1 TP, 1 FP, 1 FN
    acc.add_frame(NO_BOXES, gt)  # 2 FN
    acc.add_frame(cars(car(0.0, 2.0)), NO_BOXES)  # 1 FP
    s = acc.summary()
    assert (s["tp"], s["fp"], s["fn"], s["num_gt"], s["num_pred"]) == (1, 2, 3, 4, 3)
    assert s["precision"] == pytest.approx(1 / 3) and s["recall"] == pytest.approx(1 / 4)
    assert s["pose_error_mean_m"] == pytest.approx(0.05)


def test_ignored_prediction_is_neither_tp_nor_fp() -> None:
    acc = FusionAccumulator()
    ignore = cars(car(1.0, 1.0, size=(1.0, 1.0, 0.3)))
    acc.add_frame(cars(car(0.0, 0.0), car(1.1, 1.0)), cars(car(0.0, 0.0)), gt_ignore=ignore)
    s = acc.summary()
    assert (s["tp"], s["fp"], s["fn"], s["num_ignored"]) == (1, 0, 0, 1)
    assert s["precision"] == 1.0
    assert s["ap_bev_0.5"] == pytest.approx(1.0)  # evaluate_kitti's own ignore rule drops it too


def test_invalid_yaw_is_left_out_of_aos_only() -> None:
    acc = FusionAccumulator()
    gt = cars(car(0.0, 0.0), car(1.0, 0.0))
    preds = cars(car(0.0, 0.0), car(1.0, 0.0, math.pi / 2))  # second has no real yaw
    acc.add_frame(preds, gt, yaw_valid=np.array([True, False]))
    s = acc.summary(with_ap=False)
    assert s["aos_mean"] == pytest.approx(1.0) and s["aos_count"] == 1
    assert s["tp"] == 2 and s["bev_iou_mean"] == pytest.approx(0.75)  # (1 + 0.5) / 2
    assert np.isnan(acc.aos_terms[1])


def test_ap_bev_uses_scores() -> None:
    # One GT; the FP outranks the TP, so precision is 1/2 at recall 1 -> R40 AP 0.5.
    acc = FusionAccumulator()
    acc.add_frame(cars(car(0.0, 0.0), car(1.0, 1.0)), cars(car(0.0, 0.0)), scores=[0.5, 0.9])
    assert acc.ap_bev() == pytest.approx({"ap_bev_0.7": 0.5, "ap_bev_0.5": 0.5})
    assert acc.ap_bev(iou_thresholds=(0.3,)).keys() == {"ap_bev_0.3"}


def test_empty_summary_is_json_ready_with_nulls() -> None:
    s = FusionAccumulator().summary()
    assert s["precision"] is None and s["pose_error_p95_m"] is None and s["ap_bev_0.7"] is None
    assert s["tp"] == 0 and s["aos_count"] == 0
    json.dumps(s, allow_nan=False)


# --- heat maps ---------------------------------------------------------------------------------------


def test_grid_shape_matches_paper_grid() -> None:
    assert grid_shape(X_RANGE, Y_RANGE, DEFAULT_CELL_M) == (64, 32)
    with pytest.raises(ValueError, match="whole number"):
        grid_shape((0.0, 1.0), (0.0, 1.0), 0.3)
    with pytest.raises(ValueError, match="min < max"):
        grid_shape((1.0, 0.0), (0.0, 1.0), 0.125)
    with pytest.raises(ValueError, match="cell_m"):
        grid_shape((0.0, 1.0), (0.0, 1.0), 0.0)


def test_heat_map_cells_hold_their_values_and_empty_cells_are_nan() -> None:
    acc = FusionAccumulator()
    # GT (0.3, -1.1) -> column floor(2.3 / 0.125) = 18, row floor(3.9 / 0.125) = 31.
    gt = cars(car(0.3, -1.1), car(-1.9, 2.9), car(5.0, 0.0))  # the last is off the grid
    pred = cars(car(0.4, -1.1, math.pi / 4), car(5.0, 0.0))
    acc.add_frame(pred, gt)  # GT 0 matched (error 0.1, AOS 0.5), GT 1 missed, GT 2 matched off-grid
    maps = acc.heat_maps(X_RANGE, Y_RANGE)
    assert tuple(maps) == HEAT_MAP_KEYS
    assert all(m.shape == (64, 32) for m in maps.values())
    assert maps["pose_error_m"][31, 18] == pytest.approx(0.1)
    assert maps["aos"][31, 18] == pytest.approx(0.5)
    assert maps["bev_iou"][31, 18] == pytest.approx(acc.bev_ious[0])
    assert maps["count"][31, 18] == 1 and maps["recall"][31, 18] == 1.0
    # The missed GT (-1.9, 2.9) sits in row 63, column 0: recall 0, no pose data.
    assert maps["num_gt"][63, 0] == 1 and maps["recall"][63, 0] == 0.0
    assert np.isnan(maps["pose_error_m"][63, 0])
    assert maps["count"].sum() == 1 and maps["num_gt"].sum() == 2
    for key in ("pose_error_m", "aos", "bev_iou"):
        assert np.isfinite(maps[key]).sum() == 1
    assert np.isnan(maps["recall"]).sum() == 64 * 32 - 2


def test_heat_map_averages_pairs_in_one_cell() -> None:
    acc = FusionAccumulator()
    acc.add_frame(cars(car(0.01, 0.0)), cars(car(0.0, 0.0)))
    acc.add_frame(cars(car(0.06, 0.05)), cars(car(0.02, 0.02)))  # error 0.05, same cell
    maps = acc.heat_maps(X_RANGE, Y_RANGE)
    assert maps["pose_error_m"][40, 16] == pytest.approx(0.03)
    assert maps["count"][40, 16] == 2


def test_save_heat_map_png(tmp_path) -> None:
    acc = FusionAccumulator()
    acc.add_frame(GT3, GT3)
    maps = acc.heat_maps(X_RANGE, Y_RANGE)
    out = save_heat_map_png(
        maps["aos"], X_RANGE, Y_RANGE, tmp_path / "sub" / "aos.png", "AOS", vmin=0.0, vmax=1.0
    )
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="2D"):
        save_heat_map_png(np.zeros(3), X_RANGE, Y_RANGE, tmp_path / "bad.png", "bad")


# --- malformed input ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"pred_boxes": np.zeros((2, 6))}, r"pred_boxes must have shape \(N, 7\)"),
        ({"gt_boxes": [[0.0, 0.0, 0.1, 0.33, 0.22, 0.21, np.nan]]}, "gt_boxes must contain only finite"),
        ({"gt_boxes": [car(0.0, 0.0, size=(-0.3, 0.2, 0.2))]}, "non-negative"),
        ({"yaw_valid": [True]}, r"yaw_valid must have shape \(2,\)"),
        ({"yaw_valid": [1, 0]}, "yaw_valid must be boolean"),
        ({"scores": [0.5, np.inf]}, "scores must contain only finite"),
        ({"gt_ignore": np.zeros((1, 3))}, r"gt_ignore must have shape \(N, 7\)"),
        ({"pred_boxes": "abc"}, "pred_boxes must be a numeric"),
    ],
)
def test_malformed_input_raises(kwargs: dict[str, object], message: str) -> None:
    args: dict[str, object] = {"pred_boxes": cars(car(0.0, 0.0), car(1.0, 0.0)), "gt_boxes": NO_BOXES}
    args.update(kwargs)
    acc = FusionAccumulator()
    with pytest.raises(ValueError, match=message):
        acc.add_frame(**args)  # type: ignore[arg-type]
    assert acc.num_frames == 0  # nothing recorded


def test_bad_gate_raises() -> None:
    with pytest.raises(ValueError, match="max_distance_m"):
        FusionAccumulator(max_distance_m=0.0)
    with pytest.raises(ValueError, match="max_distance_m"):
        match_frame(NO_BOXES, NO_BOXES, max_distance_m=float("nan"))


def test_merge_equals_one_accumulator_over_all_frames() -> None:
    gt = np.array([[0.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]])
    shifted = gt + np.array([0.05, 0, 0, 0, 0, 0, 0])
    one, a, b = FusionAccumulator(), FusionAccumulator(), FusionAccumulator()
    for acc in (one, a):
        acc.add_frame(gt, gt)
    for acc in (one, b):
        acc.add_frame(shifted, gt)
        acc.add_frame(np.zeros((0, 7)), gt)
    a.merge(b)
    assert a.summary() == one.summary()


def test_kitti_aos_term_known_answers() -> None:
    got = aos_kitti_term([0.1, math.pi / 2, math.pi, 0.0], [0.1 + 2 * math.pi, 0.0, 0.0, 0.0])
    assert got == pytest.approx([1.0, 0.5, 0.0, 1.0])


def test_f1_and_velocity_error_of_matched_pairs() -> None:
    acc = FusionAccumulator()
    preds = cars(car(0.0, 0.0), car(1.0, -2.0), car(3.0, 3.0))  # frame 1: 2 TP, 1 FP, 1 FN
    v_pred = np.array([[0.3, 0.0], [0.0, np.nan], [1.0, 1.0]])  # the second: velocity unknown
    v_gt = np.array([[0.0, 0.4], [0.1, 0.0], [0.0, 0.0]])
    acc.add_frame(preds, GT3, pred_velocity_mps=v_pred, gt_velocity_mps=v_gt)
    acc.add_frame(preds[:1], GT3[:1])  # no velocities given: nothing recorded
    s = acc.summary(with_ap=False)
    assert (s["tp"], s["fp"], s["fn"]) == (3, 1, 1)
    assert s["f1"] == pytest.approx(2 * 3 / (2 * 3 + 1 + 1))
    assert s["velocity_count"] == 1 and s["velocity_error_p50_mps"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="pred_velocity_mps"):
        acc.add_frame(preds, GT3, pred_velocity_mps=np.zeros((2, 2)), gt_velocity_mps=v_gt)


def test_ap_by_range_measures_range_from_the_sensor_not_the_world_origin() -> None:
    # A sensor at (100, 0): a car 1 m from it found exactly, a car 3 m from it missed. The bands are
    # from the sensor, so the near band is perfect and the far one empty-handed; from the world origin
    # both would fall in the last band.
    acc = FusionAccumulator()
    near = [101.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]
    far = [103.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]
    for _ in range(3):
        acc.add_frame(np.array([near]), np.array([near, far]))
    bands = acc.ap_bev_by_range((100.0, 0.0), [(0.0, 2.0), (2.0, 4.0), (4.0, float("inf"))])
    assert bands["[0, 2)"]["ap"] == pytest.approx(1.0) and bands["[0, 2)"]["num_gt"] == 3
    assert bands["[2, 4)"]["ap"] == pytest.approx(0.0) and bands["[2, 4)"]["num_gt"] == 3
    assert bands["[4, inf)"]["ap"] is None and bands["all"]["num_gt"] == 6
