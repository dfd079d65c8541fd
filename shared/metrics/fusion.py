"""Metrics for fused (and tracked) object boxes against ground truth: pose error, AOS, BEV IoU,
precision / recall with false positives counted, heat maps on a metric grid and KITTI-style AP-BEV.

Plain functions and an accumulator on arrays (no I/O except `save_heat_map_png`). Boxes follow the
OpenPCDet convention of `shared.geometry.boxes`: ``(x, y, z, dx, dy, dz, yaw)``, world frame, metres /
radians. Empty arrays of any shape (``np.zeros(0)``) mean "nothing in this frame".

Matching (one frame)
--------------------
Every predicted box is paired with at most one GT box and vice versa by the Hungarian algorithm on the
BEV (xy) centre distance. Pairs farther apart than ``max_distance_m`` may not be matched; among the
assignments allowed by this gate the matching first maximises the number of pairs, then minimises
their summed distance. Then:

- matched pair -> true positive (TP); its pose error, AOS term and BEV IoU are recorded;
- unmatched GT -> false negative (FN, a miss);
- unmatched prediction -> false positive (FP), unless it touches an ignore box (BEV footprints
  overlap with positive area, or the centres are at most ``max_distance_m`` apart), in which case it is
  *ignored* (neither TP nor FP). Ignore boxes never produce misses.

This fixes two gaps of the reference evaluation (which compared GT car 1 with prediction 0 and never
counted FP): all cars are matched jointly, and precision is defined.

Default gate: ``DEFAULT_MATCH_DISTANCE_M = 0.3`` m. It is about one car length (0.33 m, so a prediction
farther away barely overlaps the car's footprint and is no evidence of it) and just under half the
closest centre spacing of two queued cars (collision threshold 0.61 m), so one prediction can never lie
inside the gate of two queued cars. It is ~7x the paper's typical pose error (< 0.045 m), so a
sound but imprecise fusion output still counts as a TP and shows up in the pose-error statistics.

Orientation (AOS)
-----------------
The AOS term of a pair is ``(1 + cos 2Δθ) / 2`` with ``Δθ = yaw_pred - yaw_gt``: 1 for equal yaw,
0 for perpendicular boxes. Because ``cos 2Δθ`` has period π, it is the same for a heading flipped by
π: a yaw known only modulo π (a box without a front/back decision, or the reference's π-flipped
odometry convention) is scored correctly with no flip or wrap. The AOS mean is taken over matched pairs
whose prediction has a valid yaw (``yaw_valid``); predictions without an orientation at all (e.g. a
radar-only point) are excluded from AOS but still count for pose error, IoU, precision and recall.

Relation to AP-BEV
------------------
`FusionAccumulator.ap_bev` delegates to `shared.metrics.detection.evaluate_kitti` (R40, greedy
matching by score on rotated BEV IoU). Its TP/FP differ from the distance-gated counts here by design:
AP asks "is the box right?" (IoU >= 0.5 / 0.7), the counts ask "was the car found?". Its ignore rule is
also KITTI's: a detection is dropped if at least the IoU threshold of its footprint lies inside an
ignore box.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import linear_sum_assignment

from shared.detection.interface import CAR_CLASS_ID
from shared.geometry.boxes import bev_intersection_area_matrix, bev_iou_matrix
from shared.geometry.grid import CellGrid, grid_shape
from shared.metrics.detection import ALL_BAND, band_label, evaluate_kitti

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

__all__ = [
    "AP_BEV_IOU_THRESHOLDS",
    "DEFAULT_CELL_M",
    "DEFAULT_MATCH_DISTANCE_M",
    "HEAT_MAP_KEYS",
    "FrameMatch",
    "FusionAccumulator",
    "aos_kitti_term",
    "aos_term",
    "match_frame",
    "save_heat_map_png",
]

BOX_COLUMNS = 7
X, Y, YAW = 0, 1, 6
DX, DZ = 3, 5
# Centre-distance gate for prediction <-> GT matching, metres (rationale in the module docstring).
DEFAULT_MATCH_DISTANCE_M = 0.3
# Heat-map cell of the paper's maps (32 x 64 cells over 4 x 8 m), metres.
DEFAULT_CELL_M = 0.125
# KITTI-style AP-BEV thresholds reported for fused boxes (car-class "moderate" 0.7 and loose 0.5).
AP_BEV_IOU_THRESHOLDS: tuple[float, ...] = (0.7, 0.5)
# Score given to every prediction when the fusion output carries none (AP is then one operating point).
DEFAULT_SCORE = 1.0
# Class id column fed to evaluate_kitti (class-agnostic: never read).
# Percentiles of the pose and velocity errors reported by `FusionAccumulator.summary`.
POSE_PERCENTILES = (50.0, 95.0)
VELOCITY_PERCENTILES = POSE_PERCENTILES
# A grid span may differ from a whole number of cells by this fraction of a cell (float rounding).
HEAT_MAP_KEYS: tuple[str, ...] = ("pose_error_m", "aos", "bev_iou", "count", "num_gt", "recall")


# --- input checks -----------------------------------------------------------------------------------


def _boxes(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a finite (N, 7) float64 array with non-negative sizes; any empty array -> (0, 7)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric (N, {BOX_COLUMNS}) array: {exc}") from exc
    if arr.size == 0:
        return np.zeros((0, BOX_COLUMNS))
    if arr.ndim != 2 or arr.shape[1] != BOX_COLUMNS:
        raise ValueError(f"{name} must have shape (N, {BOX_COLUMNS}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values (no NaN / inf)")
    if np.any(arr[:, DX : DZ + 1] < 0.0):
        raise ValueError(f"{name} sizes (dx, dy, dz) must be non-negative")
    return arr


def _velocities(value: ArrayLike, n: int, name: str) -> FloatArray:
    """``value`` as an (n, 2) float64 array of BEV velocities (NaN rows allowed: unknown), m/s."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric ({n}, 2) array: {exc}") from exc
    if arr.size == 0 and n == 0:
        return np.zeros((0, 2))
    if arr.shape != (n, 2):
        raise ValueError(f"{name} must have shape ({n}, 2), got {arr.shape}")
    if np.isinf(arr).any():
        raise ValueError(f"{name} must not contain inf")
    return arr


def _joined(parts: list[FloatArray]) -> FloatArray:
    """Per-frame records of one kind concatenated (empty when there are none)."""
    return np.concatenate(parts) if parts else np.zeros(0)


def _finite(values: FloatArray) -> FloatArray:
    """The finite entries (NaN marks a pair without that quantity)."""
    return values[np.isfinite(values)]


def _stat_or_none(stat: Callable[..., Any], values: FloatArray, *args: float) -> float | None:
    """``stat(values, *args)`` as a float; None over no values (JSON-ready)."""
    return _float_or_none(stat(values, *args)) if values.size else None


def _per_box(value: ArrayLike | None, n: int, name: str, default: float | bool) -> NDArray[np.generic]:
    """Per-box vector of length ``n`` (``default`` everywhere when None), finite if numeric."""
    if value is None:
        return np.full(n, default)
    arr = np.asarray(value)
    if arr.size == 0 and n == 0:
        return np.full(0, default)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) (one entry per prediction), got {arr.shape}")
    if isinstance(default, bool):
        if arr.dtype != np.bool_:
            raise ValueError(f"{name} must be boolean, got dtype {arr.dtype}")
        return arr
    try:
        out = arr.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric: {exc}") from exc
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} must contain only finite values (no NaN / inf)")
    return out


def _positive(value: float, name: str) -> float:
    out = float(value)
    if not (math.isfinite(out) and out > 0.0):
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return out


# --- one frame ---------------------------------------------------------------------------------------


def aos_kitti_term(yaw_pred: ArrayLike, yaw_gt: ArrayLike) -> FloatArray:
    """KITTI's orientation similarity ``(1 + cos Δθ) / 2`` per pair, in [0, 1]: 0 for a box facing
    the wrong way (the heading sign counts).

    Parameters
    ----------
    yaw_pred, yaw_gt : array_like, shape (K,)
        Yaw, radians (any wrapping).

    Returns
    -------
    numpy.ndarray, shape (K,)
    """
    return _orientation_similarity(yaw_pred, yaw_gt, 1.0)


def aos_term(yaw_pred: ArrayLike, yaw_gt: ArrayLike) -> FloatArray:
    """Orientation similarity ``(1 + cos 2Δθ) / 2`` per pair, in [0, 1]; invariant to a π flip (the
    paper's measure; `aos_kitti_term` is the KITTI one).

    Parameters
    ----------
    yaw_pred, yaw_gt : array_like, shape (K,)
        Yaw, radians (any wrapping).

    Returns
    -------
    numpy.ndarray, shape (K,)
    """
    return _orientation_similarity(yaw_pred, yaw_gt, 2.0)


def _orientation_similarity(yaw_pred: ArrayLike, yaw_gt: ArrayLike, harmonic: float) -> FloatArray:
    """``(1 + cos(harmonic · Δθ)) / 2`` per pair: harmonic 1 is KITTI's, 2 the π-invariant one."""
    delta = np.asarray(yaw_pred, dtype=np.float64) - np.asarray(yaw_gt, dtype=np.float64)
    return np.asarray((1.0 + np.cos(harmonic * delta)) / 2.0, dtype=np.float64)


@dataclass(frozen=True)
class FrameMatch:
    """Distance-gated assignment of one frame's predictions to its GT.

    Attributes
    ----------
    pred_index, gt_index : numpy.ndarray of int, shape (K,)
        Matched pairs (TP), sorted by ``pred_index``.
    distance_m : numpy.ndarray, shape (K,)
        BEV centre distance of each pair, metres (<= the gate).
    false_positives : numpy.ndarray of int, shape (F,)
        Unmatched predictions counted as FP.
    ignored : numpy.ndarray of int, shape (J,)
        Unmatched predictions absorbed by an ignore box.
    misses : numpy.ndarray of int, shape (M,)
        Unmatched GT (FN).
    """

    pred_index: IntArray
    gt_index: IntArray
    distance_m: FloatArray
    false_positives: IntArray
    ignored: IntArray
    misses: IntArray


def _centre_distances(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.asarray(np.hypot(a[:, None, X] - b[None, :, X], a[:, None, Y] - b[None, :, Y]))


def match_frame(
    pred_boxes: ArrayLike,
    gt_boxes: ArrayLike,
    max_distance_m: float = DEFAULT_MATCH_DISTANCE_M,
    gt_ignore: ArrayLike | None = None,
) -> FrameMatch:
    """Match one frame's predictions to GT by Hungarian assignment on BEV centre distance.

    Parameters
    ----------
    pred_boxes : array_like, shape (P, 7)
        Predicted boxes, metres / radians.
    gt_boxes : array_like, shape (G, 7)
        Ground-truth boxes, same frame.
    max_distance_m : float
        Gate, metres: pairs farther apart are never matched (a pair exactly at the gate may be).
    gt_ignore : array_like, shape (I, 7), optional
        Ignore regions: an unmatched prediction that overlaps one (positive BEV intersection area) or
        whose centre is within ``max_distance_m`` of its centre is not a FP.

    Returns
    -------
    FrameMatch

    Raises
    ------
    ValueError
        On a wrong shape, a NaN / inf, a negative size or a non-positive gate.
    """
    gate = _positive(max_distance_m, "max_distance_m")
    preds = _boxes(pred_boxes, "pred_boxes")
    gts = _boxes(gt_boxes, "gt_boxes")
    ignore = _boxes(np.zeros(0) if gt_ignore is None else gt_ignore, "gt_ignore")
    dist = _centre_distances(preds, gts)
    allowed = dist <= gate
    pred_idx = np.zeros(0, np.int64)
    gt_idx = np.zeros(0, np.int64)
    if allowed.any():
        # A forbidden pair costs more than any set of allowed pairs can sum to (each <= gate), so the
        # optimum has the most allowed pairs and, among those, the least total distance.
        forbidden_cost = gate * (min(dist.shape) + 1)
        rows, cols = linear_sum_assignment(np.where(allowed, dist, forbidden_cost))
        keep = allowed[rows, cols]
        pred_idx, gt_idx = rows[keep].astype(np.int64), cols[keep].astype(np.int64)
    unmatched = np.setdiff1d(np.arange(preds.shape[0]), pred_idx)
    absorbed = np.zeros(unmatched.size, bool)
    if unmatched.size and ignore.shape[0]:
        near = _centre_distances(preds[unmatched], ignore) <= gate
        overlapping = bev_intersection_area_matrix(preds[unmatched], ignore) > 0.0
        absorbed = np.any(near | overlapping, axis=1)
    return FrameMatch(
        pred_index=pred_idx,
        gt_index=gt_idx,
        distance_m=dist[pred_idx, gt_idx],
        false_positives=unmatched[~absorbed].astype(np.int64),
        ignored=unmatched[absorbed].astype(np.int64),
        misses=np.setdiff1d(np.arange(gts.shape[0]), gt_idx).astype(np.int64),
    )


# --- accumulation over frames ------------------------------------------------------------------------


def _float_or_none(value: float | np.floating) -> float | None:
    """JSON-safe float: NaN / inf (an undefined metric) becomes None (``null``)."""
    out = float(value)
    return out if math.isfinite(out) else None


def _ratio_or_none(num: int, den: int) -> float | None:
    return num / den if den > 0 else None


def _cell_index(
    xy: FloatArray, x_range_m: tuple[float, float], y_range_m: tuple[float, float], cell_m: float
) -> tuple[IntArray, BoolArray]:
    """Flat ``iy * nx + ix`` cell of each point and whether it lies in ``[min, max)`` on both axes."""
    flat = CellGrid.spanning(x_range_m, y_range_m, cell_m).cells(xy)
    return flat, flat >= 0


def _cell_mean(flat: IntArray, values: FloatArray, num_cells: int) -> FloatArray:
    """Per-cell mean of ``values`` binned by flat cell index ``flat``, NaN where a cell is empty."""
    count = np.bincount(flat, minlength=num_cells).astype(np.float64)
    total = np.bincount(flat, weights=values, minlength=num_cells)
    mean = np.full(num_cells, np.nan)
    np.divide(total, count, out=mean, where=count > 0)
    return mean


class FusionAccumulator:
    """Accumulates per-frame matches of fused boxes against GT and summarises them.

    Parameters
    ----------
    max_distance_m : float
        Matching gate on the BEV centre distance, metres (see `match_frame`).

    Examples
    --------
    >>> acc = FusionAccumulator()
    >>> for preds, gts in frames:  # doctest: +SKIP
    ...     acc.add_frame(preds, gts)
    >>> acc.summary()  # doctest: +SKIP
    """

    def __init__(self, max_distance_m: float = DEFAULT_MATCH_DISTANCE_M) -> None:
        self.max_distance_m = _positive(max_distance_m, "max_distance_m")
        self._pose_error: list[FloatArray] = []
        self._aos: list[FloatArray] = []  # NaN where the prediction's yaw is not valid
        self._aos_kitti: list[FloatArray] = []  # as _aos, with the heading sign
        self._velocity_error: list[FloatArray] = []  # m/s, NaN where either velocity is not given
        self._iou: list[FloatArray] = []
        self._tp_gt_xy: list[FloatArray] = []
        self._fn_gt_xy: list[FloatArray] = []
        # Per frame (detections (N, 9) [box, score, class], gt (G, 7), ignore (I, 7)) for evaluate_kitti.
        self._kitti_frames: list[tuple[FloatArray, FloatArray, FloatArray]] = []
        self.num_frames = 0
        self.num_pred = 0
        self.num_gt = 0
        self.tp = 0
        self.fp = 0
        self.fn = 0
        self.num_ignored = 0

    _PER_PAIR = (
        "_pose_error",
        "_aos",
        "_aos_kitti",
        "_velocity_error",
        "_iou",
        "_tp_gt_xy",
        "_fn_gt_xy",
        "_kitti_frames",
    )

    def merge(self, other: FusionAccumulator) -> None:
        """Add every frame of `other` (e.g. another agent or seed evaluated in another process)."""
        if other.max_distance_m != self.max_distance_m:
            raise ValueError("cannot merge accumulators with different gates")
        for name in self._PER_PAIR:
            getattr(self, name).extend(getattr(other, name))
        for name in ("num_frames", "num_pred", "num_gt", "tp", "fp", "fn", "num_ignored"):
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def add_frame(
        self,
        pred_boxes: ArrayLike,
        gt_boxes: ArrayLike,
        *,
        yaw_valid: ArrayLike | None = None,
        scores: ArrayLike | None = None,
        gt_ignore: ArrayLike | None = None,
        pred_velocity_mps: ArrayLike | None = None,
        gt_velocity_mps: ArrayLike | None = None,
    ) -> FrameMatch:
        """Match one frame and record its pairs and counts.

        Parameters
        ----------
        pred_boxes : array_like, shape (P, 7)
            Fused / tracked boxes, metres / radians.
        gt_boxes : array_like, shape (G, 7)
            Ground truth, same frame and time.
        yaw_valid : array_like of bool, shape (P,), optional
            False for predictions with no orientation at all; they are left out of AOS only. A yaw
            known modulo π is *valid*: the AOS term is π-invariant. Default: all valid.
        scores : array_like, shape (P,), optional
            Confidence per prediction, used only for AP; default 1 for all.
        gt_ignore : array_like, shape (I, 7), optional
            Ignore regions (see `match_frame`).
        pred_velocity_mps, gt_velocity_mps : array_like, shapes (P, 2) and (G, 2), optional
            BEV velocities, m/s (rows of NaN: unknown); with both, the velocity error of every matched
            pair is recorded.

        Returns
        -------
        FrameMatch
            This frame's assignment.
        """
        preds = _boxes(pred_boxes, "pred_boxes")
        gts = _boxes(gt_boxes, "gt_boxes")
        ignore = _boxes(np.zeros(0) if gt_ignore is None else gt_ignore, "gt_ignore")
        valid = _per_box(yaw_valid, preds.shape[0], "yaw_valid", True)
        score = _per_box(scores, preds.shape[0], "scores", DEFAULT_SCORE).astype(np.float64)
        match = match_frame(preds, gts, self.max_distance_m, ignore)
        p, g = match.pred_index, match.gt_index
        self._pose_error.append(match.distance_m)
        self._aos.append(np.where(valid[p], aos_term(preds[p, YAW], gts[g, YAW]), np.nan))
        self._aos_kitti.append(np.where(valid[p], aos_kitti_term(preds[p, YAW], gts[g, YAW]), np.nan))
        if pred_velocity_mps is None or gt_velocity_mps is None:
            self._velocity_error.append(np.full(p.size, np.nan))
        else:
            v_pred = _velocities(pred_velocity_mps, preds.shape[0], "pred_velocity_mps")
            v_gt = _velocities(gt_velocity_mps, gts.shape[0], "gt_velocity_mps")
            self._velocity_error.append(np.linalg.norm(v_pred[p] - v_gt[g], axis=1))
        # Only the matched pairs' IoU is needed: the diagonal of the (K, K) matrix.
        self._iou.append(np.diagonal(bev_iou_matrix(preds[p], gts[g])).copy())
        self._tp_gt_xy.append(gts[g][:, [X, Y]])
        self._fn_gt_xy.append(gts[match.misses][:, [X, Y]])
        dets = np.column_stack([preds, score, np.full(preds.shape[0], CAR_CLASS_ID)])
        self._kitti_frames.append((dets, gts, ignore))
        self.num_frames += 1
        self.num_pred += preds.shape[0]
        self.num_gt += gts.shape[0]
        self.tp += p.size
        self.fp += match.false_positives.size
        self.fn += match.misses.size
        self.num_ignored += match.ignored.size
        return match

    # Concatenated per-pair records (TP order: frame by frame, then by prediction index).
    @property
    def pose_errors_m(self) -> FloatArray:
        """BEV centre distance of every matched pair, metres, shape (TP,)."""
        return _joined(self._pose_error)

    @property
    def aos_terms(self) -> FloatArray:
        """AOS term of every matched pair, NaN where the prediction's yaw is not valid, shape (TP,)."""
        return _joined(self._aos)

    @property
    def aos_kitti_terms(self) -> FloatArray:
        """KITTI AOS term (heading sign counts) of every matched pair, NaN as `aos_terms`, shape (TP,)."""
        return _joined(self._aos_kitti)

    @property
    def velocity_errors_mps(self) -> FloatArray:
        """BEV velocity error of every matched pair, m/s, NaN where a velocity is unknown, shape (TP,)."""
        return _joined(self._velocity_error)

    @property
    def bev_ious(self) -> FloatArray:
        """Rotated BEV IoU of every matched pair, shape (TP,)."""
        return _joined(self._iou)

    @property
    def matched_gt_xy(self) -> FloatArray:
        """GT centre of every matched pair, metres, shape (TP, 2)."""
        return np.concatenate(self._tp_gt_xy) if self._tp_gt_xy else np.zeros((0, 2))

    def summary(self, with_ap: bool = True) -> dict[str, float | int | None]:
        """Scalar metrics over all frames, JSON-ready (undefined values are None, not NaN).

        Parameters
        ----------
        with_ap : bool
            Also run `ap_bev` (the slowest part: one rotated IoU matrix per frame).

        Returns
        -------
        dict
            ``num_frames, num_gt, num_pred, tp, fp, fn, num_ignored`` (int); ``precision = tp / (tp +
            fp)``, ``recall = tp / (tp + fn)``, ``f1`` (at the output operating point: every box
            given); ``pose_error_mean_m, pose_error_p50_m, pose_error_p95_m, pose_error_max_m``
            (metres, over TP); ``aos_mean`` (the paper's, π-invariant), ``aos_kitti_mean`` (heading
            sign counts) and ``aos_count`` (TP with a valid yaw); ``velocity_error_p50_mps``,
            ``velocity_error_p95_mps`` and ``velocity_count`` (TP with both velocities);
            ``bev_iou_mean``; with ``with_ap`` also ``ap_bev_0.7`` and
            ``ap_bev_0.5`` (R40). A ratio with a zero denominator and a statistic over no pairs is None.
        """
        errors, iou = self.pose_errors_m, self.bev_ious
        aos = _finite(self.aos_terms)
        aos_kitti = _finite(self.aos_kitti_terms)
        velocity = _finite(self.velocity_errors_mps)
        out: dict[str, float | int | None] = {
            "num_frames": self.num_frames,
            "num_gt": self.num_gt,
            "num_pred": self.num_pred,
            "tp": self.tp,
            "fp": self.fp,
            "fn": self.fn,
            "num_ignored": self.num_ignored,
            "precision": _ratio_or_none(self.tp, self.tp + self.fp),
            "recall": _ratio_or_none(self.tp, self.tp + self.fn),
            "f1": _ratio_or_none(2 * self.tp, 2 * self.tp + self.fp + self.fn),
            "pose_error_mean_m": _stat_or_none(np.mean, errors),
        }
        for q in POSE_PERCENTILES:
            out[f"pose_error_p{q:g}_m"] = _stat_or_none(np.percentile, errors, q)
        out["pose_error_max_m"] = _stat_or_none(np.max, errors)
        out["aos_mean"] = _stat_or_none(np.mean, aos)
        out["aos_kitti_mean"] = _stat_or_none(np.mean, aos_kitti)
        out["aos_count"] = int(aos.size)
        for q in VELOCITY_PERCENTILES:
            out[f"velocity_error_p{q:g}_mps"] = _stat_or_none(np.percentile, velocity, q)
        out["velocity_count"] = int(velocity.size)
        out["bev_iou_mean"] = _stat_or_none(np.mean, iou)
        if with_ap:
            out.update(self.ap_bev())
        return out

    def ap_bev(self, iou_thresholds: Sequence[float] = AP_BEV_IOU_THRESHOLDS) -> dict[str, float | None]:
        """KITTI R40 AP-BEV over all accumulated frames via `shared.metrics.detection.evaluate_kitti`.

        Parameters
        ----------
        iou_thresholds : sequence of float
            Rotated BEV IoU thresholds, default (0.7, 0.5).

        Returns
        -------
        dict
            ``{"ap_bev_<t>": AP}`` per threshold (e.g. ``"ap_bev_0.7"``); None without any GT. No
            distance bands: fused boxes are in the world frame, where "distance from the origin" is not
            a sensor range.
        """
        result = evaluate_kitti(self._kitti_frames, iou_thresholds=iou_thresholds, bands=(), kinds=("bev",))
        return {f"ap_bev_{t:g}": _float_or_none(result.ap("bev", float(t))) for t in iou_thresholds}

    def ap_bev_by_range(
        self,
        origin_xy_m: tuple[float, float],
        bands_m: Sequence[tuple[float, float]],
        iou_threshold: float = AP_BEV_IOU_THRESHOLDS[0],
    ) -> dict[str, dict[str, float | int | None]]:
        """AP-BEV at `iou_threshold` per range band from a sensor at `origin_xy_m` (world frame,
        metres), to tell far misses from near ones: every box shifted so the sensor is the origin, then
        `evaluate_kitti`'s bands (a GT counts in the band of its centre's range, an unmatched prediction
        is a FP in the band of its own).

        Returns
        -------
        dict
            band (``"all"``, ``"[0, 27.3)"``, ...: edges to 3 significant digits) -> ``{"ap", "num_gt",
            "num_tp", "num_fp"}`` (AP None for a band without GT).
        """
        shift = np.array([origin_xy_m[0], origin_xy_m[1]], np.float64)

        def moved(boxes: FloatArray) -> FloatArray:
            out = np.array(boxes, np.float64, copy=True)
            if out.size:
                out[:, [X, Y]] -= shift
            return out

        frames = [(moved(d), moved(g), moved(i)) for d, g, i in self._kitti_frames]
        result = evaluate_kitti(frames, iou_thresholds=(iou_threshold,), bands=bands_m, kinds=("bev",))
        out: dict[str, dict[str, float | int | None]] = {}
        for label, band in [(ALL_BAND, None), *((band_label(b), b) for b in bands_m)]:
            res = result.results[("bev", float(iou_threshold), label)]
            # labels to 3 significant digits: a scaled edge (27.2727 m) reads as 27.3
            key = label if band is None else f"[{band[0]:.3g}, {band[1]:.3g})"
            out[key] = {"ap": _float_or_none(res.ap), "num_gt": res.num_gt, "num_tp": res.num_tp}
            out[key]["num_fp"] = res.num_fp
        return out

    def heat_maps(
        self,
        x_range_m: tuple[float, float],
        y_range_m: tuple[float, float],
        cell_m: float = DEFAULT_CELL_M,
    ) -> dict[str, FloatArray]:
        """Per-cell metrics binned by GT centre position.

        Parameters
        ----------
        x_range_m, y_range_m : (float, float)
            Grid extent ``[min, max)``, metres, each a whole number of cells (the paper: x from -2,
            y from -5, 32 x 64 cells). GT outside the grid is left out.
        cell_m : float
            Cell side, metres (default 0.125, as the paper).

        Returns
        -------
        dict of numpy.ndarray, each shape (ny, nx)
            Row ``iy`` covers ``y_min + iy * cell_m`` and column ``ix`` covers ``x_min + ix * cell_m``
            (an image with its origin at the lower left; see `save_heat_map_png`):

            - ``pose_error_m``, ``aos``, ``bev_iou``: mean over the TP whose GT lies in the cell
              (``aos`` over TP with a valid yaw), NaN where there is none;
            - ``count``: number of TP in the cell (0 where empty);
            - ``num_gt``: TP + FN in the cell;
            - ``recall``: ``count / num_gt``, NaN where there is no GT.
        """
        ny, nx = grid_shape(x_range_m, y_range_m, cell_m)
        cells = ny * nx
        flat, inside = _cell_index(self.matched_gt_xy, x_range_m, y_range_m, cell_m)
        aos = self.aos_terms
        has_aos = inside & np.isfinite(aos)
        out: dict[str, FloatArray] = {
            "pose_error_m": _cell_mean(flat[inside], self.pose_errors_m[inside], cells).reshape(ny, nx),
            "aos": _cell_mean(flat[has_aos], aos[has_aos], cells).reshape(ny, nx),
            "bev_iou": _cell_mean(flat[inside], self.bev_ious[inside], cells).reshape(ny, nx),
        }
        count = np.bincount(flat[inside], minlength=cells).astype(np.float64)
        fn_xy = np.concatenate(self._fn_gt_xy) if self._fn_gt_xy else np.zeros((0, 2))
        fn_flat, fn_inside = _cell_index(fn_xy, x_range_m, y_range_m, cell_m)
        num_gt = count + np.bincount(fn_flat[fn_inside], minlength=cells)
        recall = np.full(cells, np.nan)
        np.divide(count, num_gt, out=recall, where=num_gt > 0)
        out["count"] = count.reshape(ny, nx)
        out["num_gt"] = num_gt.reshape(ny, nx)
        out["recall"] = recall.reshape(ny, nx)
        return out


# --- plotting ----------------------------------------------------------------------------------------

# Figure size, inches, and resolution of saved heat maps; empty (NaN) cells are drawn in this grey.
FIGURE_SIZE_IN = (6.0, 8.0)
FIGURE_DPI = 120
EMPTY_CELL_COLOUR = "0.85"


def save_heat_map_png(
    map2d: ArrayLike,
    x_range_m: tuple[float, float],
    y_range_m: tuple[float, float],
    path: str | Path,
    title: str,
    vmin: float | None = None,
    vmax: float | None = None,
    cmap: str = "viridis",
    colorbar_label: str = "",
) -> Path:
    """Save one heat map (as returned by `FusionAccumulator.heat_maps`) as a PNG.

    Parameters
    ----------
    map2d : array_like, shape (ny, nx)
        Cell values, row = y, column = x; NaN cells are drawn grey ("no data").
    x_range_m, y_range_m : (float, float)
        Extent the grid covers, metres (the values given to `heat_maps`).
    path : str or pathlib.Path
        Output file; parent directories are created.
    title : str
        Plot title.
    vmin, vmax : float, optional
        Colour-scale limits (default: data range); fix them to compare maps, e.g. 0 and 1 for AOS.
    cmap : str
        Matplotlib colour map name.
    colorbar_label : str
        Colour-bar label with units, e.g. ``"pose error (m)"``.

    Returns
    -------
    pathlib.Path
        The written file.
    """
    # Imported here so the metrics load without matplotlib's start-up cost. Figure + Agg canvas
    # directly, not pyplot: no global backend state, safe headless and in threads.
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    values = np.asarray(map2d, dtype=np.float64)
    if values.ndim != 2 or values.size == 0:
        raise ValueError(f"map2d must be a non-empty 2D array (ny, nx), got shape {values.shape}")
    for name, (lo, hi) in (("x_range_m", x_range_m), ("y_range_m", y_range_m)):
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"{name} must be finite (min, max) with min < max, got {(lo, hi)}")
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=FIGURE_SIZE_IN, dpi=FIGURE_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    colours = colormaps[cmap].with_extremes(bad=EMPTY_CELL_COLOUR)
    image = ax.imshow(
        np.ma.masked_invalid(values),
        origin="lower",
        extent=(x_range_m[0], x_range_m[1], y_range_m[0], y_range_m[1]),
        aspect="equal",
        interpolation="nearest",
        cmap=colours,
        vmin=vmin,
        vmax=vmax,
    )
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    fig.colorbar(image, ax=ax, label=colorbar_label)
    fig.savefig(out, bbox_inches="tight")
    return out
