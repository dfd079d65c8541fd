"""Detection metrics: COCO-style 2D AP and KITTI-style R40 BEV / 3D AP, overall and by distance band.

Plain functions on arrays (no I/O). Inputs follow `shared/detection/interface.py`:

- 2D frame: ``(detections (N, 6) [x0, y0, x1, y1, score, class_id], gt (G, 4), ignore (I, 4))``, pixels.
- 3D frame: ``(detections (N, 9) [x, y, z, dx, dy, dz, yaw, score, class_id], gt (G, 7), ignore (I, 7))``,
  OpenPCDet boxes in the agent frame, metres / radians.

The sand table has one class, so evaluation is class-agnostic (the ``class_id`` column is not read).
Empty arrays of any shape (``np.zeros(0)``) are accepted for "nothing in this frame".

Matching (one frame, one overlap threshold ``t``)
-------------------------------------------------
Greedy by descending score (stable order for equal scores); each detection takes, among the boxes
still free, the one with the highest overlap ``>= t`` (equal overlaps: the later box, as pycocotools),
trying in turn:

1. counted ground truth (all GT for 2D and "all"; the GT whose centre is in the band for a band) -> TP;
2. uncounted ground truth (GT of another band) -> ignored (neither TP nor FP);
3. ignore boxes -> ignored. The overlap with an ignore box is the *fraction of the detection inside it*
   (intersection / detection area for 2D and BEV, / detection volume for 3D), so a detection that
   lies mostly (``>= t``) inside an ignore region is dropped even if it is much smaller than the
   region. This is pycocotools' ``iscrowd`` rule and the overlap KITTI uses for DontCare regions;
   ignore boxes may absorb any number of detections.

A detection left unmatched is a FP if it is counted (all detections for 2D and "all"; the detections
whose own centre is in the band for a band), otherwise ignored. Each GT is matched at most once.

Why numpy instead of pycocotools
--------------------------------
One code path serves 2D and 3D (rotated BEV / 3D IoU, distance bands, DontCare), takes the interface
arrays directly, and also returns per-frame matches and PR curves for other tools. The 2D result is
checked against pycocotools' COCOeval (ignore boxes as ``iscrowd`` annotations, area range "all",
100 detections per image) in the tests; COCO's small / medium / large area ranges are not computed.

Interpolation
-------------
AP is the mean, over fixed recall points ``r``, of the interpolated precision
``p(r) = max{precision_k : recall_k >= r}`` (0 where recall ``r`` is never reached):
COCO uses 101 points 0, 0.01, ..., 1; KITTI R40 uses 40 points 1/40, 2/40, ..., 1. The 3D metric ranks
all detections by score (VOC/COCO-style curve) rather than KITTI's 41 sampled score thresholds, so it
may differ from the official KITTI devkit: `evaluate_kitti(recall_sampling="devkit")` samples as the
devkit does (`devkit_thresholds`, `devkit_ap`), which with few ground-truth boxes differs a lot.

Empty inputs
------------
AP is NaN when there is no counted GT (overall or in a band); such results are reported as NaN, not
dropped. With GT but no detections AP is 0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from shared.geometry.boxes import bev_intersection_area_matrix, bev_iou_matrix, iou2d_matrix, iou3d_matrix

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# COCO: IoU 0.50:0.05:0.95 and 101 recall points, built exactly as pycocotools builds them.
COCO_IOU_THRESHOLDS: tuple[float, ...] = tuple(float(t) for t in np.linspace(0.5, 0.95, 10))
COCO_RECALL_POINTS: FloatArray = np.linspace(0.0, 1.0, 101)
COCO_MAX_DETECTIONS = 100
# KITTI R40: recall 1/40 ... 40/40 (recall 0 excluded).
R40_NUM_POINTS = 40
# k / 40 exactly (no linspace rounding), so recall 0.5 hits the 20th point.
R40_RECALL_POINTS: FloatArray = np.arange(1, R40_NUM_POINTS + 1) / R40_NUM_POINTS
KITTI_IOU_THRESHOLDS: tuple[float, ...] = (0.5, 0.7)
# The KITTI devkit's sampling: 41 score thresholds, AP R40 over the points 1..40 (`devkit_ap`).
DEVKIT_SAMPLE_POINTS = 41
RecallSampling = Literal["r40", "devkit"]
DEFAULT_DISTANCE_BANDS_M: tuple[tuple[float, float], ...] = ((0.0, 2.0), (2.0, 4.0), (4.0, float("inf")))
ALL_BAND = "all"
SCORE_COLUMN_2D = 4
SCORE_COLUMN_3D = 7
BoxKind = Literal["bev", "3d"]
BOX_KINDS: tuple[BoxKind, ...] = ("bev", "3d")

Frame = tuple[ArrayLike, ArrayLike, ArrayLike]


class MatchLabel(IntEnum):
    """Outcome of one detection in one frame."""

    FP = 0
    TP = 1
    IGNORED = 2


@dataclass(frozen=True)
class FrameMatch:
    """Matches of one frame at one threshold, detections in matching (descending score) order.

    Attributes
    ----------
    det_index : numpy.ndarray, shape (K,)
        Row of each kept detection in the input array.
    scores : numpy.ndarray, shape (K,)
        Their scores.
    labels : numpy.ndarray, shape (K,)
        `MatchLabel` values.
    matched_gt : numpy.ndarray, shape (K,)
        Index of the GT each detection matched, -1 for none (ignore-box matches are -1 too).
    num_gt : int
        Counted GT boxes of the frame (recall denominator).
    """

    det_index: IntArray
    scores: FloatArray
    labels: IntArray
    matched_gt: IntArray
    num_gt: int


@dataclass(frozen=True)
class PRCurve:
    """Precision / recall after each detection, ignored detections removed, descending score.

    Attributes
    ----------
    scores, precision, recall : numpy.ndarray, shape (K,)
        Score threshold, precision and recall at each step (recall is NaN without GT).
    """

    scores: FloatArray
    precision: FloatArray
    recall: FloatArray


@dataclass(frozen=True)
class APResult:
    """AP of one (threshold, box kind, band) with its counts and PR curve; ``ap`` is NaN without GT."""

    ap: float
    num_gt: int
    num_tp: int
    num_fp: int
    num_ignored: int
    curve: PRCurve


@dataclass(frozen=True)
class CocoSummary:
    """COCO-style 2D result: AP@0.5, AP@0.5:0.95 (mean over thresholds) and each threshold's result,
    keyed by the threshold rounded to 2 decimals (0.5, 0.55, ..., 0.95)."""

    ap50: float
    ap50_95: float
    per_threshold: dict[float, APResult]
    num_frames: int


@dataclass(frozen=True)
class KittiSummary:
    """KITTI-style R40 result, keyed by ``(kind, iou_threshold, band label)``; band ``"all"`` is overall."""

    results: dict[tuple[BoxKind, float, str], APResult]
    bands: tuple[str, ...]
    num_frames: int
    thresholds: tuple[float, ...]

    def ap(self, kind: BoxKind, iou_threshold: float, band: str = ALL_BAND) -> float:
        """AP of one entry (NaN when that band has no GT); KeyError for an entry not evaluated."""
        return self.results[(kind, iou_threshold, band)].ap

    def rows(self) -> list[dict[str, float | int | str]]:
        """One flat dict per entry (kind, iou, band, ap, num_gt, num_tp, num_fp) for tables / JSON."""
        return [
            {
                "kind": kind,
                "iou": iou,
                "band": band,
                "ap": res.ap,
                "num_gt": res.num_gt,
                "num_tp": res.num_tp,
                "num_fp": res.num_fp,
            }
            for (kind, iou, band), res in self.results.items()
        ]


# --- input checks -----------------------------------------------------------------------------------


def _rows(value: ArrayLike, ncols: int, name: str) -> FloatArray:
    """``value`` as a finite float64 (N, ncols) array; any empty array becomes (0, ncols)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return np.zeros((0, ncols))
    if arr.ndim != 2 or arr.shape[1] != ncols:
        raise ValueError(f"{name} must have shape (N, {ncols}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values")
    return arr


def _check_threshold(threshold: float) -> None:
    if not 0.0 < threshold <= 1.0:
        raise ValueError(f"overlap threshold must be in (0, 1], got {threshold}")


# --- building blocks ---------------------------------------------------------------------------------


def score_order(scores: ArrayLike, max_detections: int | None = None) -> IntArray:
    """Indices of detections by descending score, stable for ties, truncated to ``max_detections``.

    Parameters
    ----------
    scores : array_like, shape (N,)
    max_detections : int or None
        Keep only the best this many (COCO keeps 100 per image); None keeps all.

    Returns
    -------
    numpy.ndarray, shape (min(N, max_detections),)
    """
    order = np.argsort(-np.asarray(scores, dtype=np.float64), kind="mergesort").astype(np.int64)
    return order if max_detections is None else order[:max_detections]


def _best_free(overlap_row: FloatArray, free: NDArray[np.bool_], threshold: float) -> int:
    """Index of the free box with the largest overlap >= threshold (last on ties), or -1."""
    valid = free & (overlap_row >= threshold)
    if not valid.any():
        return -1
    candidates = np.flatnonzero(valid)
    values = overlap_row[candidates]
    return int(candidates[np.flatnonzero(values == values.max())[-1]])


def label_detections(
    overlap: ArrayLike,
    ignore_overlap: ArrayLike,
    order: ArrayLike,
    threshold: float,
    gt_counted: ArrayLike | None = None,
    det_counted: ArrayLike | None = None,
) -> tuple[IntArray, IntArray]:
    """Greedy matching of one frame (rules in the module docstring).

    Parameters
    ----------
    overlap : array_like, shape (N, G)
        Detection-to-GT IoU.
    ignore_overlap : array_like, shape (N, I)
        Fraction of each detection inside each ignore box.
    order : array_like of int, shape (K,)
        Detections to match, best first (see `score_order`).
    threshold : float
        Minimum overlap for a match, in (0, 1].
    gt_counted : array_like of bool, shape (G,), optional
        GT that count (TP / recall); default all.
    det_counted : array_like of bool, shape (N,), optional
        Detections whose unmatched outcome is a FP; default all.

    Returns
    -------
    labels : numpy.ndarray, shape (K,)
        `MatchLabel` per detection of ``order``.
    matched_gt : numpy.ndarray, shape (K,)
        GT index or -1.
    """
    _check_threshold(threshold)
    iou = np.asarray(overlap, dtype=np.float64)
    ign = np.asarray(ignore_overlap, dtype=np.float64)
    idx = np.asarray(order, dtype=np.int64)
    num_det, num_gt = iou.shape
    counted = np.ones(num_gt, bool) if gt_counted is None else np.asarray(gt_counted, bool)
    det_ok = np.ones(num_det, bool) if det_counted is None else np.asarray(det_counted, bool)
    free = np.ones(num_gt, bool)
    labels = np.full(idx.size, MatchLabel.FP, np.int64)
    matched = np.full(idx.size, -1, np.int64)
    for k, i in enumerate(idx):
        j = _best_free(iou[i], free & counted, threshold)
        if j < 0:
            j = _best_free(iou[i], free & ~counted, threshold)
        if j >= 0:
            free[j] = False
            matched[k] = j
            labels[k] = MatchLabel.TP if counted[j] else MatchLabel.IGNORED
        elif (ign.shape[1] > 0 and bool(np.any(ign[i] >= threshold))) or not det_ok[i]:
            labels[k] = MatchLabel.IGNORED
    return labels, matched


def precision_recall_curve(scores: ArrayLike, labels: ArrayLike, num_gt: int) -> PRCurve:
    """Precision and recall over detections pooled from many frames.

    Parameters
    ----------
    scores : array_like, shape (K,)
        Detection scores (frames concatenated in order).
    labels : array_like of int, shape (K,)
        `MatchLabel` of each detection; ignored ones are dropped.
    num_gt : int
        Counted GT over all frames.

    Returns
    -------
    PRCurve
        Sorted by descending score (stable, as pycocotools); recall is NaN if ``num_gt == 0``.
    """
    s = np.asarray(scores, dtype=np.float64)
    lab = np.asarray(labels, dtype=np.int64)
    keep = lab != MatchLabel.IGNORED
    order = np.argsort(-s[keep], kind="mergesort")
    tp = np.cumsum(lab[keep][order] == MatchLabel.TP).astype(np.float64)
    fp = np.cumsum(lab[keep][order] == MatchLabel.FP).astype(np.float64)
    total = tp + fp
    precision = np.divide(tp, total, out=np.zeros_like(tp), where=total > 0)
    recall = tp / num_gt if num_gt > 0 else np.full_like(tp, np.nan)
    return PRCurve(scores=s[keep][order], precision=precision, recall=recall)


def interpolated_ap(recall: ArrayLike, precision: ArrayLike, recall_points: ArrayLike) -> float:
    """Mean interpolated precision at fixed recall points.

    Parameters
    ----------
    recall, precision : array_like, shape (K,)
        Curve in descending-score order (recall non-decreasing).
    recall_points : array_like, shape (R,)
        E.g. `COCO_RECALL_POINTS` or `R40_RECALL_POINTS`.

    Returns
    -------
    float
        ``mean_r max{precision_k : recall_k >= r}``, a point never reached contributing 0.
    """
    rc = np.asarray(recall, dtype=np.float64)
    pr = np.asarray(precision, dtype=np.float64)
    pts = np.asarray(recall_points, dtype=np.float64)
    if rc.size == 0:
        return 0.0
    envelope = np.maximum.accumulate(pr[::-1])[::-1]
    idx = np.searchsorted(rc, pts, side="left")
    reached = idx < rc.size
    values = np.where(reached, envelope[np.minimum(idx, rc.size - 1)], 0.0)
    return float(values.mean())


def devkit_thresholds(
    tp_scores: ArrayLike, num_gt: int, num_points: int = DEVKIT_SAMPLE_POINTS
) -> FloatArray:
    """The score thresholds the KITTI devkit samples its precision at (its `getThresholds`).

    Walking the true positives' scores downwards, the i-th (recall ``(i+1)/num_gt``) is taken when it
    is at least as close to the next recall step as the one after it would be, the step then
    advancing by ``1 / (num_points - 1)``; the last true positive is always taken. Steps advance by
    one per threshold taken, not by the recall reached: with few ground-truth boxes each true positive
    takes one step while it adds far more recall (the devkit assumes many).
    """
    scores = np.sort(np.asarray(tp_scores, dtype=np.float64))[::-1]
    step, current = 1.0 / (num_points - 1), 0.0
    taken: list[float] = []
    for i, score in enumerate(scores):
        last = i == len(scores) - 1
        left = (i + 1) / num_gt
        right = left if last else (i + 2) / num_gt
        if not last and (right - current) < (current - left):
            continue
        taken.append(float(score))
        current += step
    return np.asarray(taken[:num_points])


def devkit_ap(
    scores: ArrayLike, labels: ArrayLike, num_gt: int, num_points: int = DEVKIT_SAMPLE_POINTS
) -> float:
    """AP R40 with the KITTI devkit's recall sampling, on this module's matching (`MatchLabel`s).

    Precision at each of `devkit_thresholds` (true and false positives with a score at or above it),
    made non-increasing from the right, zero beyond the last threshold; the mean over the points
    1..40 (the devkit's R40 skips point 0). NaN without ground truth. The devkit matches again at
    each threshold; here the matching is the one made once by score, so only the sampling is the
    devkit's.
    """
    if num_gt <= 0:
        return float("nan")
    s = np.asarray(scores, dtype=np.float64)
    lab = np.asarray(labels, dtype=np.int64)
    keep = lab != MatchLabel.IGNORED
    s, lab = s[keep], lab[keep]
    precision = np.zeros(num_points)
    for i, threshold in enumerate(devkit_thresholds(s[lab == MatchLabel.TP], num_gt, num_points)):
        above = s >= threshold
        tp = int(np.sum(lab[above] == MatchLabel.TP))
        fp = int(np.sum(lab[above] == MatchLabel.FP))
        precision[i] = tp / (tp + fp)
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    return float(precision[1:].mean())


def _ap_result(
    matches: Sequence[FrameMatch], recall_points: FloatArray, sampling: RecallSampling = "r40"
) -> APResult:
    num_gt = sum(m.num_gt for m in matches)
    scores = np.concatenate([m.scores for m in matches]) if matches else np.zeros(0)
    labels = np.concatenate([m.labels for m in matches]) if matches else np.zeros(0, np.int64)
    curve = precision_recall_curve(scores, labels, num_gt)
    if sampling == "devkit":
        ap = devkit_ap(scores, labels, num_gt)
    else:
        ap = interpolated_ap(curve.recall, curve.precision, recall_points) if num_gt > 0 else float("nan")
    return APResult(
        ap=ap,
        num_gt=num_gt,
        num_tp=int(np.sum(labels == MatchLabel.TP)),
        num_fp=int(np.sum(labels == MatchLabel.FP)),
        num_ignored=int(np.sum(labels == MatchLabel.IGNORED)),
        curve=curve,
    )


# --- overlaps ----------------------------------------------------------------------------------------


def fraction_inside_2d(dets: ArrayLike, regions: ArrayLike) -> FloatArray:
    """Fraction of each detection's area inside each region (0 for zero-area detections).

    Parameters
    ----------
    dets : array_like, shape (N, 4)
    regions : array_like, shape (I, 4)
        ``(x0, y0, x1, y1)`` pixels.

    Returns
    -------
    numpy.ndarray, shape (N, I)
    """
    a = _rows(dets, 4, "dets")
    b = _rows(regions, 4, "regions")
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0.0, None), axis=2)
    area = np.prod(np.clip(a[:, 2:] - a[:, :2], 0.0, None), axis=1)[:, None]
    return np.divide(inter, area, out=np.zeros_like(inter), where=area > 0)


def fraction_inside_3d(dets: ArrayLike, regions: ArrayLike, kind: BoxKind) -> FloatArray:
    """Fraction of each detection's BEV footprint (``kind="bev"``) or volume (``"3d"``) inside each region.

    Parameters
    ----------
    dets : array_like, shape (N, 7)
    regions : array_like, shape (I, 7)
        OpenPCDet boxes.
    kind : {"bev", "3d"}

    Returns
    -------
    numpy.ndarray, shape (N, I)
    """
    a = _rows(dets, 7, "dets")
    b = _rows(regions, 7, "regions")
    inter = bev_intersection_area_matrix(a, b)
    size = a[:, 3] * a[:, 4]
    if kind == "3d":
        top = np.minimum((a[:, 2] + a[:, 5] / 2)[:, None], (b[:, 2] + b[:, 5] / 2)[None, :])
        bottom = np.maximum((a[:, 2] - a[:, 5] / 2)[:, None], (b[:, 2] - b[:, 5] / 2)[None, :])
        inter = inter * np.clip(top - bottom, 0.0, None)
        size = size * a[:, 5]
    return np.divide(inter, size[:, None], out=np.zeros_like(inter), where=size[:, None] > 0)


# --- 2D (COCO) ---------------------------------------------------------------------------------------


def match_frame_2d(
    detections: ArrayLike,
    gt: ArrayLike,
    ignore: ArrayLike,
    iou_threshold: float,
    max_detections: int | None = COCO_MAX_DETECTIONS,
) -> FrameMatch:
    """Match one image's detections (N, 6) to its GT (G, 4) and ignore boxes (I, 4) at one IoU threshold."""
    dets = _rows(detections, 6, "detections")
    boxes = _rows(gt, 4, "gt")
    order = score_order(dets[:, SCORE_COLUMN_2D], max_detections)
    labels, matched = label_detections(
        iou2d_matrix(dets[:, :4], boxes), fraction_inside_2d(dets[:, :4], ignore), order, iou_threshold
    )
    return FrameMatch(order, dets[order, SCORE_COLUMN_2D], labels, matched, boxes.shape[0])


def evaluate_coco(
    frames: Sequence[Frame],
    iou_thresholds: Sequence[float] = COCO_IOU_THRESHOLDS,
    max_detections: int | None = COCO_MAX_DETECTIONS,
) -> CocoSummary:
    """COCO-style AP over frames (101-point interpolation, thresholds 0.50:0.05:0.95 by default).

    Parameters
    ----------
    frames : sequence of (detections (N, 6), gt (G, 4), ignore (I, 4))
    iou_thresholds : sequence of float
        Must contain 0.5 for ``ap50`` (else ``ap50`` is NaN).
    max_detections : int or None
        Best detections kept per image (COCO: 100).

    Returns
    -------
    CocoSummary
        ``ap50_95`` is the mean AP over ``iou_thresholds``; NaN without GT.
    """
    per: dict[float, APResult] = {}
    for t in iou_thresholds:
        matches = [match_frame_2d(d, g, i, t, max_detections) for d, g, i in frames]
        per[round(float(t), 2)] = _ap_result(matches, COCO_RECALL_POINTS)
    aps = [r.ap for r in per.values()]
    ap50_95 = float(np.mean(aps)) if aps and not np.isnan(aps).any() else float("nan")
    ap50 = per[0.5].ap if 0.5 in per else float("nan")
    return CocoSummary(ap50=ap50, ap50_95=ap50_95, per_threshold=per, num_frames=len(frames))


# --- 3D (KITTI R40) ----------------------------------------------------------------------------------


def band_label(band: tuple[float, float]) -> str:
    """Label of a distance band ``[lo, hi)`` in metres, e.g. ``"[0, 2)"``, ``"[4, inf)"``."""
    return f"[{band[0]:g}, {band[1]:g})"


def in_band(boxes: ArrayLike, band: tuple[float, float]) -> NDArray[np.bool_]:
    """Whether each box centre's BEV distance from the origin lies in ``[lo, hi)``.

    Parameters
    ----------
    boxes : array_like, shape (N, >=2)
        Rows starting with ``x, y`` (metres, agent frame).
    band : (float, float)
        ``(lo, hi)`` metres; ``hi`` may be ``inf``.

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
    """
    arr = np.asarray(boxes, dtype=np.float64)
    if arr.size == 0:
        return np.zeros(0, bool)
    if arr.ndim != 2 or arr.shape[1] < 2:
        raise ValueError(f"boxes must have shape (N, >=2), got {arr.shape}")
    dist = np.hypot(arr[:, 0], arr[:, 1])
    return (dist >= band[0]) & (dist < band[1])


@dataclass(frozen=True)
class _Frame3D:
    dets: FloatArray
    gt: FloatArray
    order: IntArray
    overlap: dict[BoxKind, FloatArray]
    ignore_overlap: dict[BoxKind, FloatArray]


def _prepare_3d(frame: Frame) -> _Frame3D:
    detections, gt, ignore = frame
    dets = _rows(detections, 9, "detections")
    boxes = _rows(gt, 7, "gt")
    ign = _rows(ignore, 7, "ignore")
    return _Frame3D(
        dets=dets,
        gt=boxes,
        order=score_order(dets[:, SCORE_COLUMN_3D]),
        overlap={"bev": bev_iou_matrix(dets[:, :7], boxes), "3d": iou3d_matrix(dets[:, :7], boxes)},
        ignore_overlap={k: fraction_inside_3d(dets[:, :7], ign, k) for k in BOX_KINDS},
    )


def _match_prepared(
    f: _Frame3D, kind: BoxKind, threshold: float, band: tuple[float, float] | None
) -> FrameMatch:
    gt_counted = None if band is None else in_band(f.gt, band)
    det_counted = None if band is None else in_band(f.dets, band)
    labels, matched = label_detections(
        f.overlap[kind], f.ignore_overlap[kind], f.order, threshold, gt_counted, det_counted
    )
    num_gt = f.gt.shape[0] if gt_counted is None else int(gt_counted.sum())
    return FrameMatch(f.order, f.dets[f.order, SCORE_COLUMN_3D], labels, matched, num_gt)


def match_frame_3d(
    detections: ArrayLike,
    gt: ArrayLike,
    ignore: ArrayLike,
    kind: BoxKind,
    iou_threshold: float,
    band: tuple[float, float] | None = None,
) -> FrameMatch:
    """Match one lidar frame's detections (N, 9) to GT (G, 7) and ignore boxes (I, 7).

    ``kind`` picks rotated BEV IoU or 3D IoU; ``band`` (metres, ``[lo, hi)``) restricts which GT count
    (by GT centre distance) and which unmatched detections are FP (by detection centre distance).
    """
    return _match_prepared(_prepare_3d((detections, gt, ignore)), kind, iou_threshold, band)


def evaluate_kitti(
    frames: Sequence[Frame],
    iou_thresholds: Sequence[float] = KITTI_IOU_THRESHOLDS,
    bands: Sequence[tuple[float, float]] = DEFAULT_DISTANCE_BANDS_M,
    kinds: Sequence[BoxKind] = BOX_KINDS,
    recall_sampling: RecallSampling = "r40",
) -> KittiSummary:
    """KITTI-style R40 AP for BEV and 3D boxes, overall (band ``"all"``) and per distance band.

    Parameters
    ----------
    frames : sequence of (detections (N, 9), gt (G, 7), ignore (I, 7))
        Agent frame, metres / radians.
    iou_thresholds : sequence of float
        Default (0.5, 0.7).
    bands : sequence of (lo, hi)
        BEV distance bands from the agent origin, metres, ``[lo, hi)``.
    kinds : sequence of {"bev", "3d"}
    recall_sampling : {"r40", "devkit"}
        "r40": precision interpolated at recall 1/40 .. 40/40 (this module's default); "devkit": at the
        KITTI devkit's 41 score thresholds (`devkit_ap`), to compare with the devkit number for number.

    Returns
    -------
    KittiSummary
        One `APResult` per (kind, threshold, band); AP is NaN where a band has no GT.
    """
    prepared = [_prepare_3d(f) for f in frames]
    labelled: list[tuple[str, tuple[float, float] | None]] = [(ALL_BAND, None)]
    labelled += [(band_label(b), b) for b in bands]
    results: dict[tuple[BoxKind, float, str], APResult] = {}
    for kind in kinds:
        for t in iou_thresholds:
            for label, band in labelled:
                matches = [_match_prepared(f, kind, t, band) for f in prepared]
                results[(kind, float(t), label)] = _ap_result(matches, R40_RECALL_POINTS, recall_sampling)
    return KittiSummary(
        results=results,
        bands=tuple(label for label, _ in labelled),
        num_frames=len(frames),
        thresholds=tuple(float(t) for t in iou_thresholds),
    )
