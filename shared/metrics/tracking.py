"""CLEAR-MOT, identity and HOTA metrics (MOTA, MOTP, IDF1, ID switches; HOTA, DetA, AssA) for tracked
objects, via motmetrics and TrackEval.

`TrackingAccumulator` feeds one frame at a time (GT ids and positions, track ids and positions) to
``motmetrics.MOTAccumulator``, keeps the frame for TrackEval's HOTA, and reads both back as JSON-ready
numbers. Positions are BEV centres ``(x, y)`` in the world frame, metres.

Distances
---------
The distance of a GT / track pair is their Euclidean BEV centre distance in metres (not motmetrics'
squared-distance helper), so MOTP is the mean distance of the matched pairs in metres (lower is
better). Pairs farther apart than ``max_distance_m`` get NaN, which motmetrics reads as "may not be
matched". The default gate is the fusion matching gate
(`shared.metrics.fusion.DEFAULT_MATCH_DISTANCE_M`, 0.3 m: about one car length and just under half the
closest spacing of two queued cars), so detection and tracking results use the same notion of "found".
It is deliberately tighter than a tracker's own association gate (0.5 m), which must also absorb
prediction error during manoeuvres.

Definitions (motmetrics 1.4.0)
------------------------------
``MOTA = 1 - (misses + fp + id_switches) / num_gt``, where ``num_gt`` is the number of GT objects
summed over frames; ``IDF1 = 2 IDTP / (num_gt + num_predictions)`` with the identity-optimal
one-to-one GT <-> track assignment. An ID switch is a GT matched to a different track than at its last
match. motmetrics keeps a GT <-> track match from the previous frame as long as the pair stays inside
the gate, even if another pair is closer.

HOTA (TrackEval 1.3.0, `trackeval.metrics.HOTA`; Luiten et al., IJCV 2021) scores a GT / track pair
by a similarity in [0, 1] and averages over the thresholds 0.05, 0.10, ..., 0.95 on it. TrackEval's
benchmarks use box IoU; here the similarity is the centre distance's, ``max(0, 1 - d / max_distance_m)``
(1 at the same centre, 0 at the gate), so the same gate bounds every metric, and HOTA at threshold
``a`` counts a pair as found within ``(1 - a) * max_distance_m``. ``hota``, ``det_a``, ``ass_a``,
``loc_a`` are the means over the thresholds (TrackEval's summary values); ``hota_at_gate`` is HOTA at
the lowest threshold (0.05: pairs within 95 % of the gate).

Compatibility note: with pandas >= 2 / NumPy 2, motmetrics 1.4.0's ``distances.iou_matrix``
(``np.asfarray``) and ``MOTAccumulator.merge_event_dataframes`` (``DataFrame.append``) are broken; this
module uses neither (distances are computed here; sequences are summarised per accumulator, and
``metrics.compute_many`` still works for several).
"""

from __future__ import annotations

import math

import motmetrics as mm
import numpy as np
import trackeval
from numpy.typing import ArrayLike, NDArray

from shared.metrics.fusion import DEFAULT_MATCH_DISTANCE_M

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["DEFAULT_TRACK_DISTANCE_M", "TrackingAccumulator"]

DEFAULT_TRACK_DISTANCE_M = DEFAULT_MATCH_DISTANCE_M
XY_COLUMNS = 2

# Our summary key -> motmetrics metric name; float metrics may be undefined (None), counts are ints.
_FLOAT_METRICS = {
    "mota": "mota",
    "idf1": "idf1",
    "precision": "precision",
    "recall": "recall",
}
_MATCHED_EVENTS = ("MATCH", "SWITCH")  # motmetrics event types of a matched (object, track) pair
_COUNT_METRICS = {
    "id_switches": "num_switches",
    "fp": "num_false_positives",
    "misses": "num_misses",
    "num_gt": "num_objects",
    "num_predictions": "num_predictions",
    # motmetrics' num_matches excludes matches that are ID switches; num_detections includes them.
    "num_matches": "num_detections",
    "num_unique_objects": "num_unique_objects",
    "mostly_tracked": "mostly_tracked",
    "mostly_lost": "mostly_lost",
    "fragmentations": "num_fragmentations",
}


def _ids(value: ArrayLike, name: str) -> IntArray:
    """Unique integer ids, shape (N,); any empty array -> (0,)."""
    arr = np.asarray(value)
    if arr.size == 0:
        return np.zeros(0, np.int64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must have shape (N,), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must be integers, got dtype {arr.dtype}")
    if np.unique(arr).size != arr.size:
        raise ValueError(f"{name} must be unique within a frame, got {arr.tolist()}")
    return arr.astype(np.int64)


def _xy(value: ArrayLike, n: int, name: str) -> FloatArray:
    """Finite (n, 2) positions, metres; any empty array when ``n == 0`` -> (0, 2)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric ({n}, {XY_COLUMNS}) array: {exc}") from exc
    if arr.size == 0 and n == 0:
        return np.zeros((0, XY_COLUMNS))
    if arr.shape != (n, XY_COLUMNS):
        raise ValueError(f"{name} must have shape ({n}, {XY_COLUMNS}) (one row per id), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values (no NaN / inf)")
    return arr


class TrackingAccumulator:
    """Per-frame GT / track association for CLEAR-MOT and IDF1 over one sequence.

    Parameters
    ----------
    max_distance_m : float
        Gate on the BEV centre distance, metres: farther pairs are never matched (default 0.3 m, see
        the module docstring).
    """

    def __init__(self, max_distance_m: float = DEFAULT_TRACK_DISTANCE_M) -> None:
        gate = float(max_distance_m)
        if not (math.isfinite(gate) and gate > 0.0):
            raise ValueError(f"max_distance_m must be a positive finite number, got {max_distance_m}")
        self.max_distance_m = gate
        self.num_frames = 0
        # auto_id: frames are numbered 0, 1, ... in update order.
        self._acc = mm.MOTAccumulator(auto_id=True)
        self._merged: list[mm.MOTAccumulator] = []  # other sequences (`merge`)
        # HOTA's input, one list of frames (gt ids, track ids, similarity) per sequence.
        self._hota_frames: list[tuple[IntArray, IntArray, FloatArray]] = []
        self._hota_merged: list[list[tuple[IntArray, IntArray, FloatArray]]] = []

    def merge(self, other: TrackingAccumulator) -> None:
        """Add another sequence (its ids are its own: a track id in both never links them)."""
        if other.max_distance_m != self.max_distance_m:
            raise ValueError("cannot merge accumulators with different gates")
        self._merged += [other._acc, *other._merged]
        self._hota_merged += [other._hota_frames, *other._hota_merged]
        self.num_frames += other.num_frames

    def update(self, gt_ids: ArrayLike, gt_xy: ArrayLike, track_ids: ArrayLike, track_xy: ArrayLike) -> None:
        """Add one frame.

        Parameters
        ----------
        gt_ids : array_like of int, shape (G,)
            Persistent GT object ids, unique within the frame.
        gt_xy : array_like, shape (G, 2)
            GT BEV centres, metres.
        track_ids : array_like of int, shape (T,)
            Track ids, unique within the frame.
        track_xy : array_like, shape (T, 2)
            Track BEV centres, metres, same frame and time as the GT.

        Raises
        ------
        ValueError
            On a wrong shape, a NaN / inf, non-integer or duplicate ids.
        """
        oids = _ids(gt_ids, "gt_ids")
        hids = _ids(track_ids, "track_ids")
        objs = _xy(gt_xy, oids.size, "gt_xy")
        hyps = _xy(track_xy, hids.size, "track_xy")
        dist = np.hypot(objs[:, None, 0] - hyps[None, :, 0], objs[:, None, 1] - hyps[None, :, 1])
        self._hota_frames.append((oids, hids, np.clip(1.0 - dist / self.max_distance_m, 0.0, 1.0)))
        dist[dist > self.max_distance_m] = np.nan  # motmetrics: NaN = pair not allowed
        self._acc.update(oids.tolist(), hids.tolist(), dist)
        self.num_frames += 1

    @property
    def events(self) -> object:
        """motmetrics' per-frame event table (pandas DataFrame: MATCH, SWITCH, MISS, FP, ...)."""
        return self._acc.mot_events

    def summary(self) -> dict[str, float | int | None]:
        """Tracking metrics over all frames, JSON-ready.

        Returns
        -------
        dict
            ``mota``, ``motp_m`` (mean matched distance, metres), ``idf1``, ``precision``, ``recall``
            (float, None when undefined, e.g. no GT or no match); ``id_switches``, ``fp``, ``misses``,
            ``num_gt`` (GT objects summed over frames), ``num_predictions``, ``num_matches``,
            ``num_unique_objects``, ``mostly_tracked``, ``mostly_lost``, ``fragmentations``,
            ``num_frames`` (int); ``hota``, ``det_a``, ``ass_a``, ``loc_a``, ``hota_at_gate`` (float,
            None when no frame holds a GT object or a track).
        """
        names = [*_FLOAT_METRICS.values(), *_COUNT_METRICS.values()]
        accs = [self._acc, *self._merged]
        if len(accs) == 1:
            row = mm.metrics.create().compute(self._acc, metrics=names, name="sequence").iloc[0]
        else:  # several sequences: motmetrics sums events per sequence, ids never cross sequences
            table = mm.metrics.create().compute_many(
                accs, metrics=names, names=[f"seq{i}" for i in range(len(accs))], generate_overall=True
            )
            row = table.loc["OVERALL"]
        out: dict[str, float | int | None] = {}
        for key, name in _FLOAT_METRICS.items():
            value = float(row[name])
            out[key] = value if math.isfinite(value) else None
        for key, name in _COUNT_METRICS.items():
            out[key] = int(row[name])
        # motmetrics' overall MOTP averages per-sequence MOTPs and is NaN as soon as one sequence has no
        # match; the pooled mean over every matched pair (MATCH and SWITCH events) is the definition.
        matched = [acc.mot_events for acc in accs]
        distances = [ev.loc[ev["Type"].isin(_MATCHED_EVENTS), "D"].to_numpy(float) for ev in matched]
        pooled = np.concatenate(distances) if distances else np.zeros(0)
        out["motp_m"] = float(pooled.mean()) if pooled.size else None
        out["num_frames"] = self.num_frames
        out.update(self._hota())
        return out

    def _hota(self) -> dict[str, float | None]:
        """TrackEval's HOTA over every sequence (one sequence's ids never link to another's)."""
        metric = trackeval.metrics.HOTA()
        sequences = [self._hota_frames, *self._hota_merged]
        results = {str(i): metric.eval_sequence(_trackeval_sequence(f)) for i, f in enumerate(sequences)}
        res = results["0"] if len(results) == 1 else metric.combine_sequences(results)
        if not int(res["HOTA_TP"][0] + res["HOTA_FN"][0] + res["HOTA_FP"][0]):
            return dict.fromkeys(("hota", "det_a", "ass_a", "loc_a", "hota_at_gate"))
        return {
            "hota": float(np.mean(res["HOTA"])),
            "det_a": float(np.mean(res["DetA"])),
            "ass_a": float(np.mean(res["AssA"])),
            "loc_a": float(np.mean(res["LocA"])),
            "hota_at_gate": float(res["HOTA"][0]),
        }


def _trackeval_sequence(frames: list[tuple[IntArray, IntArray, FloatArray]]) -> dict[str, object]:
    """One sequence in TrackEval's layout: ids renumbered 0..n-1 (it indexes arrays by id)."""
    gt_all = np.unique(np.concatenate([f[0] for f in frames])) if frames else np.zeros(0, np.int64)
    tr_all = np.unique(np.concatenate([f[1] for f in frames])) if frames else np.zeros(0, np.int64)
    return {
        "num_gt_ids": int(gt_all.size),
        "num_tracker_ids": int(tr_all.size),
        "num_gt_dets": int(sum(f[0].size for f in frames)),
        "num_tracker_dets": int(sum(f[1].size for f in frames)),
        "gt_ids": [np.searchsorted(gt_all, f[0]) for f in frames],
        "tracker_ids": [np.searchsorted(tr_all, f[1]) for f in frames],
        "similarity_scores": [f[2] for f in frames],
    }
