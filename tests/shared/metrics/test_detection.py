"""Known-answer tests for shared.metrics.detection (COCO-style 2D AP, KITTI-style R40 BEV / 3D AP)."""

from __future__ import annotations

import contextlib
import io
import math

import numpy as np
import pytest

from shared.metrics.detection import (
    COCO_IOU_THRESHOLDS,
    COCO_RECALL_POINTS,
    R40_RECALL_POINTS,
    MatchLabel,
    band_label,
    evaluate_coco,
    evaluate_kitti,
    fraction_inside_2d,
    fraction_inside_3d,
    in_band,
    interpolated_ap,
    label_detections,
    match_frame_2d,
    match_frame_3d,
    precision_recall_curve,
    score_order,
)

NO_BOXES_2D = np.zeros((0, 4))
NO_BOXES_3D = np.zeros((0, 7))
CAR = (0.33, 0.22, 0.21)


def det2d(box: list[float], score: float) -> list[float]:
    return [*box, score, 0.0]


def box3d(x: float, y: float, z: float = 0.105, yaw: float = 0.0) -> list[float]:
    return [x, y, z, *CAR, yaw]


def det3d(box: list[float], score: float) -> list[float]:
    return [*box, score, 0.0]


# Two GT and three detections: the FP's rank decides AP.
GT2 = np.array([[0.0, 0.0, 10.0, 10.0], [20.0, 20.0, 30.0, 30.0]])
TP_A = [0.0, 0.0, 10.0, 10.0]
TP_B = [20.0, 20.0, 30.0, 30.0]
FP_BOX = [50.0, 50.0, 60.0, 60.0]


def coco_frame(scores: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dets = np.array([det2d(FP_BOX, scores[0]), det2d(TP_A, scores[1]), det2d(TP_B, scores[2])])
    return dets, GT2, NO_BOXES_2D


# --- building blocks ---------------------------------------------------------------------------------


def test_score_order_is_stable_and_truncates() -> None:
    assert score_order([0.5, 0.9, 0.5, 0.1]).tolist() == [1, 0, 2, 3]
    assert score_order([0.5, 0.9, 0.5, 0.1], max_detections=2).tolist() == [1, 0]
    assert score_order([]).tolist() == []


def test_r40_interpolation_known_answer() -> None:
    # Envelope: 1 up to recall 0.25, 0.75 up to 0.75, never reached beyond.
    # R40: points 1..10 -> 1, 11..30 -> 0.75, 31..40 -> 0: (10 + 20 * 0.75) / 40 = 0.625.
    assert interpolated_ap([0.25, 0.5, 0.75], [1.0, 0.5, 0.75], R40_RECALL_POINTS) == pytest.approx(0.625)
    assert R40_RECALL_POINTS[0] == 1 / 40 and R40_RECALL_POINTS[-1] == 1.0 and R40_RECALL_POINTS.size == 40


def test_coco_101_interpolation_known_answer() -> None:
    # Recall 0.5 at precision 1, recall 1 at 2/3: 51 points (0..0.50) at 1, 50 points at 2/3.
    ap = interpolated_ap([0.5, 0.5, 1.0], [1.0, 0.5, 2 / 3], COCO_RECALL_POINTS)
    assert ap == pytest.approx((51 + 50 * 2 / 3) / 101)
    assert interpolated_ap([], [], COCO_RECALL_POINTS) == 0.0


def test_precision_recall_curve_drops_ignored_and_sorts() -> None:
    labels = [MatchLabel.FP, MatchLabel.TP, MatchLabel.IGNORED, MatchLabel.TP]
    curve = precision_recall_curve([0.2, 0.9, 0.95, 0.5], labels, num_gt=4)
    np.testing.assert_allclose(curve.scores, [0.9, 0.5, 0.2])
    np.testing.assert_allclose(curve.precision, [1.0, 1.0, 2 / 3])
    np.testing.assert_allclose(curve.recall, [0.25, 0.5, 0.5])
    assert np.isnan(precision_recall_curve([0.5], [MatchLabel.FP], num_gt=0).recall).all()


def test_label_detections_prefers_counted_gt_then_other_gt_then_ignore() -> None:
    # det 0 overlaps counted GT 0 and uncounted GT 1; det 1 only GT 1 left; det 2 an ignore box; det 3 none.
    overlap = np.array([[0.8, 0.9], [0.1, 0.7], [0.0, 0.0], [0.0, 0.0]])
    ignore = np.array([[0.0], [0.0], [0.6], [0.1]])
    labels, matched = label_detections(overlap, ignore, [0, 1, 2, 3], 0.5, gt_counted=[True, False])
    assert labels.tolist() == [MatchLabel.TP, MatchLabel.IGNORED, MatchLabel.IGNORED, MatchLabel.FP]
    assert matched.tolist() == [0, 1, -1, -1]
    # An unmatched detection that is not counted (other band) is ignored, not a FP.
    labels, _ = label_detections(overlap, ignore, [3], 0.5, det_counted=[True, True, True, False])
    assert labels.tolist() == [MatchLabel.IGNORED]
    with pytest.raises(ValueError, match="threshold"):
        label_detections(overlap, ignore, [0], 0.0)


def test_each_gt_matched_once_highest_score_first() -> None:
    overlap = np.array([[0.9], [0.95]])
    labels, matched = label_detections(overlap, np.zeros((2, 0)), score_order([0.9, 0.3]), 0.5)
    assert labels.tolist() == [MatchLabel.TP, MatchLabel.FP]  # det 0 (score 0.9) takes the GT
    assert matched.tolist() == [0, -1]


def test_fraction_inside_known_answers() -> None:
    frac = fraction_inside_2d([[0.0, 0.0, 2.0, 2.0], [5.0, 5.0, 5.0, 6.0]], [[1.0, 0.0, 10.0, 10.0]])
    np.testing.assert_allclose(frac, [[0.5], [0.0]])  # half inside; zero-area detection -> 0
    box = [0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 0.0]
    region = [0.5, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0]  # covers x in [0, 1], z in [0.5, 1.5]
    np.testing.assert_allclose(fraction_inside_3d([box], [region], "bev"), [[0.5]])
    np.testing.assert_allclose(fraction_inside_3d([box], [region], "3d"), [[0.25]])
    assert fraction_inside_3d(NO_BOXES_3D, [region], "3d").shape == (0, 1)


def test_band_helpers() -> None:
    assert band_label((0.0, 2.0)) == "[0, 2)"
    assert band_label((4.0, math.inf)) == "[4, inf)"
    boxes = np.array([box3d(1.0, 0.0), box3d(0.0, -2.0), box3d(3.0, 4.0)])  # distances 1, 2, 5
    assert in_band(boxes, (0.0, 2.0)).tolist() == [True, False, False]
    assert in_band(boxes, (2.0, math.inf)).tolist() == [False, True, True]
    assert in_band(NO_BOXES_3D, (0.0, 2.0)).shape == (0,)
    with pytest.raises(ValueError, match="shape"):
        in_band(np.zeros(3), (0.0, 2.0))


# --- 2D ----------------------------------------------------------------------------------------------


def test_coco_perfect_detections_give_ap_one() -> None:
    dets = np.array([det2d(TP_A, 0.9), det2d(TP_B, 0.8)])
    summary = evaluate_coco([(dets, GT2, NO_BOXES_2D), (dets, GT2, NO_BOXES_2D)])
    assert summary.ap50 == 1.0 and summary.ap50_95 == 1.0
    assert sorted(summary.per_threshold) == [round(t, 2) for t in COCO_IOU_THRESHOLDS]
    assert summary.per_threshold[0.5].num_tp == 4 and summary.num_frames == 2


def test_coco_fp_ranked_first_or_last() -> None:
    # FP first: precision 0, 1/2, 2/3 at recall 0, 1/2, 1 -> envelope 2/3 everywhere -> AP 2/3.
    assert evaluate_coco([coco_frame((0.9, 0.8, 0.7))]).ap50 == pytest.approx(2 / 3)
    # FP last: precision 1 up to recall 1 -> AP 1.
    assert evaluate_coco([coco_frame((0.1, 0.8, 0.7))]).ap50 == pytest.approx(1.0)
    # FP between: 51 points at 1, 50 at 2/3.
    assert evaluate_coco([coco_frame((0.75, 0.8, 0.7))]).ap50 == pytest.approx((51 + 50 * 2 / 3) / 101)


def test_coco_localisation_threshold_sweep() -> None:
    # Box shifted by 2 px on a 10 px box: IoU = 80 / 120 = 2/3 -> TP at 0.50..0.65, missed at 0.70..0.95.
    dets = np.array([det2d([2.0, 0.0, 12.0, 10.0], 0.9)])
    summary = evaluate_coco([(dets, GT2[:1], NO_BOXES_2D)])
    assert summary.ap50 == 1.0
    assert summary.ap50_95 == pytest.approx(4 / 10)


def test_coco_ignore_boxes_change_nothing_for_detections_on_them() -> None:
    ignore = np.array([[100.0, 100.0, 140.0, 140.0]])
    base = evaluate_coco([coco_frame((0.75, 0.8, 0.7))])
    inside = np.array([det2d([105.0, 105.0, 125.0, 125.0], 0.99), det2d([100.0, 100.0, 140.0, 140.0], 0.98)])
    dets = np.vstack([coco_frame((0.75, 0.8, 0.7))[0], inside])
    with_ignore = evaluate_coco([(dets, GT2, ignore)])
    assert with_ignore.ap50 == base.ap50 and with_ignore.ap50_95 == base.ap50_95
    assert all(r.num_ignored == 2 for r in with_ignore.per_threshold.values())
    # Without the ignore box they are FPs ranked first.
    assert evaluate_coco([(dets, GT2, NO_BOXES_2D)]).ap50 < base.ap50


def test_coco_ignore_rule_is_fraction_of_detection_inside() -> None:
    ignore = np.array([[100.0, 100.0, 140.0, 140.0]])
    half_inside = np.array([det2d([90.0, 100.0, 110.0, 120.0], 0.95)])
    # Half of it lies inside: ignored at threshold 0.5, a FP at 0.55 ("mostly inside" means >= t).
    assert match_frame_2d(half_inside, GT2, ignore, 0.5).labels.tolist() == [MatchLabel.IGNORED]
    assert match_frame_2d(half_inside, GT2, ignore, 0.55).labels.tolist() == [MatchLabel.FP]
    # A detection on a GT box that also lies in an ignore region is a TP (GT first).
    on_both = np.array([det2d(TP_A, 0.9)])
    assert match_frame_2d(on_both, GT2, np.array([[0.0, 0.0, 50.0, 50.0]]), 0.5).labels.tolist() == [
        MatchLabel.TP
    ]


def test_coco_max_detections_per_image() -> None:
    dets = np.array([det2d(FP_BOX, 0.9), det2d(TP_A, 0.8)])
    match = match_frame_2d(dets, GT2[:1], NO_BOXES_2D, 0.5, max_detections=1)
    assert match.det_index.tolist() == [0] and match.labels.tolist() == [MatchLabel.FP]
    assert match.num_gt == 1


def test_coco_empty_inputs() -> None:
    nothing = np.zeros((0, 6))
    assert math.isnan(evaluate_coco([]).ap50)
    assert math.isnan(evaluate_coco([(nothing, NO_BOXES_2D, NO_BOXES_2D)]).ap50_95)
    only_fp = evaluate_coco([(np.array([det2d(FP_BOX, 0.5)]), np.zeros(0), np.zeros(0))])
    assert math.isnan(only_fp.ap50) and only_fp.per_threshold[0.5].num_fp == 1
    missed = evaluate_coco([(nothing, GT2, NO_BOXES_2D)])
    assert missed.ap50 == 0.0 and missed.ap50_95 == 0.0


def test_coco_rejects_bad_shapes_and_nan() -> None:
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        evaluate_coco([(np.zeros((1, 5)), GT2, NO_BOXES_2D)])
    with pytest.raises(ValueError, match="finite"):
        evaluate_coco([(np.array([det2d(TP_A, np.nan)]), GT2, NO_BOXES_2D)])


def _random_frames(seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(12):
        g = int(rng.integers(0, 6))
        xy = rng.uniform(0, 500, (g, 2))
        gt = np.hstack([xy, xy + rng.uniform(15, 80, (g, 2))])
        # Detections: jittered GT (some missed), plus clutter.
        keep = gt[rng.random(g) < 0.8]
        jitter = keep + rng.normal(0, 6, keep.shape)
        clutter_xy = rng.uniform(0, 500, (int(rng.integers(0, 4)), 2))
        clutter = np.hstack([clutter_xy, clutter_xy + rng.uniform(15, 60, clutter_xy.shape)])
        boxes = np.vstack([jitter, clutter])
        boxes[:, 2:] = np.maximum(boxes[:, 2:], boxes[:, :2] + 1.0)
        scores = rng.random(len(boxes))
        dets = np.hstack([boxes, scores[:, None], np.zeros((len(boxes), 1))])
        ign_xy = rng.uniform(0, 500, (int(rng.integers(0, 3)), 2))
        ignore = np.hstack([ign_xy, ign_xy + rng.uniform(20, 120, ign_xy.shape)])
        # A detection inside each ignore region.
        inner = np.hstack([ign_xy + 2, ign_xy + 12, rng.random((len(ign_xy), 1)), np.zeros((len(ign_xy), 1))])
        frames.append((np.vstack([dets, inner]), gt, ignore))
    return frames


def _pycocotools_precision(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    coco = pytest.importorskip("pycocotools.coco")
    cocoeval = pytest.importorskip("pycocotools.cocoeval")

    def xywh(b: np.ndarray) -> list[float]:
        return [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])]

    images, anns, results = [], [], []
    for image_id, (dets, gt, ignore) in enumerate(frames, start=1):
        images.append({"id": image_id})
        for crowd, boxes in ((0, gt), (1, ignore)):
            for b in boxes:
                box = xywh(b)
                anns.append(
                    {"id": len(anns) + 1, "image_id": image_id, "category_id": 1, "bbox": box,
                     "area": box[2] * box[3], "iscrowd": crowd}
                )  # fmt: skip
        results += [
            {"image_id": image_id, "category_id": 1, "bbox": xywh(d), "score": float(d[4])} for d in dets
        ]
    with contextlib.redirect_stdout(io.StringIO()):
        gt_api = coco.COCO()
        gt_api.dataset = {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "car"}]}
        gt_api.createIndex()
        ev = cocoeval.COCOeval(gt_api, gt_api.loadRes(results), "bbox")
        ev.evaluate()
        ev.accumulate()
    # precision[T, R, K, A, M]: category 0, area "all", maxDets 100.
    return np.asarray(ev.eval["precision"][:, :, 0, 0, -1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_coco_matches_pycocotools(seed: int) -> None:
    frames = _random_frames(seed)
    precision = _pycocotools_precision(frames)
    summary = evaluate_coco(frames)
    expected = precision.mean(axis=1)
    ours = np.array([r.ap for r in summary.per_threshold.values()])
    np.testing.assert_allclose(ours, expected, atol=1e-9)
    assert summary.ap50_95 == pytest.approx(float(precision.mean()), abs=1e-9)


# --- 3D ----------------------------------------------------------------------------------------------


def test_kitti_perfect_detections_give_ap_one() -> None:
    gt = np.array([box3d(1.0, 0.5, yaw=0.3), box3d(3.0, -0.5, yaw=-1.0), box3d(-5.0, 0.0, yaw=2.0)])
    dets = np.array([det3d(list(b), 0.9 - 0.1 * i) for i, b in enumerate(gt)])
    summary = evaluate_kitti([(dets, gt, NO_BOXES_3D)])
    for kind in ("bev", "3d"):
        for t in (0.5, 0.7):
            for band in summary.bands:
                assert summary.ap(kind, t, band) == 1.0
    assert summary.bands == ("all", "[0, 2)", "[2, 4)", "[4, inf)")


def test_kitti_fp_ranked_first_and_last_r40() -> None:
    gt = np.array([box3d(1.0, 0.0), box3d(0.0, 1.0)])
    fp = box3d(-1.0, -1.0)
    first = np.array([det3d(fp, 0.9), det3d(list(gt[0]), 0.8), det3d(list(gt[1]), 0.7)])
    last = np.array([det3d(fp, 0.1), det3d(list(gt[0]), 0.8), det3d(list(gt[1]), 0.7)])
    assert evaluate_kitti([(first, gt, NO_BOXES_3D)]).ap("3d", 0.7) == pytest.approx(2 / 3)
    assert evaluate_kitti([(last, gt, NO_BOXES_3D)]).ap("3d", 0.7) == pytest.approx(1.0)
    # FP between the TPs: recall 1/2 at precision 1 (points 1..20), then 2/3 -> (20 + 20 * 2/3) / 40.
    middle = np.array([det3d(fp, 0.75), det3d(list(gt[0]), 0.8), det3d(list(gt[1]), 0.7)])
    assert evaluate_kitti([(middle, gt, NO_BOXES_3D)]).ap("bev", 0.5) == pytest.approx((20 + 40 / 3) / 40)


def test_kitti_iou_thresholds_bev_and_3d() -> None:
    # Unit cube; detection shifted 0.25 m in x -> BEV IoU 0.75 / 1.25 = 0.6.
    gt = np.array([[0.5, 0.5, 0.5, 1.0, 1.0, 1.0, 0.0]])
    shifted_x = np.array([[0.75, 0.5, 0.5, 1.0, 1.0, 1.0, 0.0, 0.9, 0.0]])
    summary = evaluate_kitti([(shifted_x, gt, NO_BOXES_3D)], bands=())
    assert summary.ap("bev", 0.5) == 1.0 and summary.ap("bev", 0.7) == 0.0
    assert summary.ap("3d", 0.5) == 1.0 and summary.ap("3d", 0.7) == 0.0
    # Shifted 0.25 m in z: BEV IoU 1, 3D IoU 0.6.
    shifted_z = np.array([[0.5, 0.5, 0.75, 1.0, 1.0, 1.0, 0.0, 0.9, 0.0]])
    summary = evaluate_kitti([(shifted_z, gt, NO_BOXES_3D)], bands=())
    assert summary.ap("bev", 0.7) == 1.0 and summary.ap("3d", 0.7) == 0.0 and summary.ap("3d", 0.5) == 1.0


def test_kitti_ignore_boxes_change_nothing_for_detections_on_them() -> None:
    gt = np.array([box3d(1.0, 0.0), box3d(0.0, 1.0)])
    ignore = np.array([box3d(-1.5, 0.0)])
    dets = np.array([det3d(list(gt[0]), 0.8), det3d(box3d(2.0, 2.0), 0.75), det3d(list(gt[1]), 0.7)])
    base = evaluate_kitti([(dets, gt, NO_BOXES_3D)])
    on_ignore = np.array([det3d(box3d(-1.5, 0.0), 0.99), det3d(box3d(-1.45, 0.02, yaw=0.1), 0.95)])
    summary = evaluate_kitti([(np.vstack([dets, on_ignore]), gt, ignore)])
    for key, res in base.results.items():
        assert summary.results[key].ap == pytest.approx(res.ap, nan_ok=True)
    assert summary.results[("3d", 0.7, "all")].num_ignored == 2
    # Without the ignore box the two become FPs ranked first.
    without = evaluate_kitti([(np.vstack([dets, on_ignore]), gt, NO_BOXES_3D)])
    assert without.ap("3d", 0.7) < base.ap("3d", 0.7)


def test_kitti_distance_bands_split_correctly() -> None:
    gt = np.array([box3d(1.0, 0.0), box3d(0.0, 3.0), box3d(-5.0, 0.0)])  # 1 m, 3 m, 5 m
    dets = np.array(
        [det3d(list(gt[0]), 0.9), det3d(list(gt[2]), 0.8), det3d(box3d(3.5, 0.0), 0.7)]  # FP at 3.5 m
    )
    bands = ((0.0, 2.0), (2.0, 4.0), (4.0, math.inf), (8.0, 9.0))
    summary = evaluate_kitti([(dets, gt, NO_BOXES_3D)], bands=bands)
    near, mid, far = (summary.results[("3d", 0.7, b)] for b in ("[0, 2)", "[2, 4)", "[4, inf)"))
    assert (near.ap, near.num_gt, near.num_tp, near.num_fp, near.num_ignored) == (1.0, 1, 1, 0, 2)
    assert (mid.ap, mid.num_gt, mid.num_tp, mid.num_fp) == (0.0, 1, 0, 1)
    assert (far.ap, far.num_gt, far.num_tp, far.num_fp) == (1.0, 1, 1, 0)
    empty_band = summary.results[("3d", 0.7, "[8, 9)")]
    assert math.isnan(empty_band.ap) and empty_band.num_gt == 0
    # Overall: TP, TP, FP at recall 1/3, 2/3, 2/3 -> points 1..26 (26/40 <= 2/3) at precision 1.
    assert summary.ap("3d", 0.7) == pytest.approx(26 / 40)


def test_kitti_band_boundary_uses_gt_centre_for_matches() -> None:
    # GT centre at 2.05 m (band [2, 4)); its detection's centre at 1.97 m (band [0, 2)).
    gt = np.array([box3d(2.05, 0.0)])
    dets = np.array([det3d(box3d(1.97, 0.0), 0.9)])
    near = match_frame_3d(dets, gt, NO_BOXES_3D, "bev", 0.5, band=(0.0, 2.0))
    mid = match_frame_3d(dets, gt, NO_BOXES_3D, "bev", 0.5, band=(2.0, 4.0))
    assert near.labels.tolist() == [MatchLabel.IGNORED] and near.num_gt == 0
    assert mid.labels.tolist() == [MatchLabel.TP] and mid.num_gt == 1
    overall = match_frame_3d(dets, gt, NO_BOXES_3D, "3d", 0.5)
    assert overall.matched_gt.tolist() == [0] and overall.scores.tolist() == [pytest.approx(0.9)]


def test_kitti_empty_inputs_and_rows() -> None:
    nothing = np.zeros((0, 9))
    summary = evaluate_kitti([(nothing, NO_BOXES_3D, NO_BOXES_3D)])
    assert all(math.isnan(r.ap) for r in summary.results.values())
    assert math.isnan(evaluate_kitti([]).ap("bev", 0.5))
    missed = evaluate_kitti([(nothing, np.array([box3d(1.0, 0.0)]), np.zeros(0))])
    assert missed.ap("3d", 0.5) == 0.0 and math.isnan(missed.ap("3d", 0.5, "[2, 4)"))
    rows = missed.rows()
    assert len(rows) == 2 * 2 * 4  # kinds x thresholds x (all + 3 bands)
    assert set(rows[0]) == {"kind", "iou", "band", "ap", "num_gt", "num_tp", "num_fp"}
    assert missed.thresholds == (0.5, 0.7) and missed.num_frames == 1
    with pytest.raises(KeyError):
        missed.ap("3d", 0.9)
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        evaluate_kitti([(nothing, np.zeros((1, 5)), NO_BOXES_3D)])


# --- the KITTI devkit's recall sampling (evaluate_kitti(recall_sampling="devkit")) ---------------------


def test_devkit_sampling_known_answers() -> None:
    """Worked by hand from the devkit's getThresholds rule. Few ground truth: 4 boxes, detections
    0.9 TP, 0.8 FP, 0.7 TP, 0.6 TP, 0.5 FP. Every true positive takes one threshold (0.9, 0.7, 0.6: one
    recall step of 1/40 each, though each adds 1/4 of recall); precision there 1, 2/3, 3/4 -> made
    non-increasing 1, 3/4, 3/4, then 0; AP = (3/4 + 3/4) / 40 = 0.0375, where R40 interpolation gives
    (10 x 1 + 20 x 3/4) / 40 = 0.625."""
    from shared.metrics.detection import devkit_ap, devkit_thresholds

    tp, fp = MatchLabel.TP, MatchLabel.FP
    scores, labels = [0.9, 0.8, 0.7, 0.6, 0.5], [tp, fp, tp, tp, fp]
    assert list(devkit_thresholds([0.9, 0.7, 0.6], 4)) == [0.9, 0.7, 0.6]
    assert devkit_ap(scores, labels, 4) == pytest.approx(0.0375)
    curve = precision_recall_curve(scores, labels, 4)
    assert interpolated_ap(curve.recall, curve.precision, R40_RECALL_POINTS) == pytest.approx(0.625)
    # 40 boxes all found, no false positive: 40 thresholds fill points 0..39, point 40 stays 0 -> 39/40
    perfect = np.linspace(1.0, 0.5, 40)
    assert devkit_ap(perfect, [tp] * 40, 40) == pytest.approx(39 / 40)
    # many boxes: a threshold about every 10th true positive, 41 in all, every point reached -> 1
    dense = np.linspace(1.0, 0.1, 400)
    assert len(devkit_thresholds(dense, 400)) == 41
    assert devkit_ap(dense, [tp] * 400, 400) == pytest.approx(1.0)
    assert math.isnan(devkit_ap([], [], 0))


def test_evaluate_kitti_can_sample_as_the_devkit() -> None:
    from shared.metrics.detection import devkit_ap, evaluate_kitti

    gt = np.array([[0.0, 0.0, 0.0, 0.3, 0.1, 0.1, 0.0], [1.0, 1.0, 0.0, 0.3, 0.1, 0.1, 0.0]])
    dets = np.array([[*gt[0], 0.9, 1], [5.0, 5.0, 0.0, 0.3, 0.1, 0.1, 0.0, 0.8, 1], [*gt[1], 0.7, 1]])
    frames = [(dets, gt, np.zeros((0, 7)))]
    r40 = evaluate_kitti(frames, bands=(), kinds=("bev",))
    devkit = evaluate_kitti(frames, bands=(), kinds=("bev",), recall_sampling="devkit")
    tp, fp = MatchLabel.TP, MatchLabel.FP
    for key, result in devkit.results.items():
        # 0.9 TP, 0.8 FP, 0.7 TP of 2 boxes: thresholds 0.9, 0.7; precision 1, 2/3 -> (2/3) / 40
        assert (
            result.ap == pytest.approx(devkit_ap([0.9, 0.8, 0.7], [tp, fp, tp], 2)) == pytest.approx(1 / 60)
        )
        assert r40.results[key].ap == pytest.approx((20 * 1 + 20 * 2 / 3) / 40), key  # the sampling differs
