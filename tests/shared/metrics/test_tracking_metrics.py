"""Known-answer tests for shared.metrics.tracking (MOTA, MOTP, IDF1, ID switches via motmetrics)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.metrics.tracking import DEFAULT_TRACK_DISTANCE_M, TrackingAccumulator

GT_IDS = [1, 2]
GT_XY = [[0.0, 0.0], [2.0, 0.0]]


def test_perfect_tracks() -> None:
    acc = TrackingAccumulator()
    for _ in range(3):
        acc.update(GT_IDS, GT_XY, [10, 20], GT_XY)
    s = acc.summary()
    assert s["mota"] == 1.0 and s["idf1"] == 1.0 and s["motp_m"] == 0.0
    assert (s["id_switches"], s["fp"], s["misses"], s["num_gt"], s["num_frames"]) == (0, 0, 0, 6, 3)
    json.dumps(s, allow_nan=False)


def test_hand_built_scenario_with_one_id_switch() -> None:
    acc = TrackingAccumulator()
    # Frame 0: both objects tracked (distances 0.1 and 0.05 m).
    acc.update(GT_IDS, GT_XY, [10, 20], [[0.1, 0.0], [2.0, 0.05]])
    # Frame 1: object 2 missed; track 30 is a false positive far from everything.
    acc.update(GT_IDS, GT_XY, [10, 30], [[0.05, 0.0], [5.0, 5.0]])
    # Frame 2: object 1 now carried by a new track 11 -> one ID switch; object 2 back on track 20.
    acc.update(GT_IDS, GT_XY, [11, 20], [[0.0, 0.1], [2.0, 0.0]])
    s = acc.summary()
    assert (s["id_switches"], s["fp"], s["misses"], s["num_gt"], s["num_matches"]) == (1, 1, 1, 6, 5)
    # MOTA = 1 - (FN + FP + IDSW) / num_gt = 1 - 3 / 6.
    fn, fp, idsw, num_gt = (int(s[k] or 0) for k in ("misses", "fp", "id_switches", "num_gt"))
    assert s["mota"] == pytest.approx(1 - (fn + fp + idsw) / num_gt)
    assert s["mota"] == pytest.approx(0.5)
    assert s["motp_m"] == pytest.approx((0.1 + 0.05 + 0.05 + 0.1 + 0.0) / 5)
    # Identity-optimal mapping 1 <-> 10, 2 <-> 20: IDTP 4; IDF1 = 2 * 4 / (6 GT + 6 predictions).
    assert s["idf1"] == pytest.approx(2 / 3)
    assert s["num_frames"] == 3 and s["num_predictions"] == 6
    assert s["precision"] == pytest.approx(5 / 6) and s["recall"] == pytest.approx(5 / 6)


def test_gate_turns_a_far_track_into_fp_and_miss() -> None:
    assert DEFAULT_TRACK_DISTANCE_M == 0.3
    near = TrackingAccumulator()
    near.update([1], [[0.0, 0.0]], [7], [[0.25, 0.0]])
    assert near.summary()["num_matches"] == 1
    far = TrackingAccumulator()
    far.update([1], [[0.0, 0.0]], [7], [[0.35, 0.0]])
    s = far.summary()
    assert (s["num_matches"], s["fp"], s["misses"]) == (0, 1, 1)
    assert s["mota"] == pytest.approx(-1.0) and s["motp_m"] is None
    wide = TrackingAccumulator(max_distance_m=0.5)
    wide.update([1], [[0.0, 0.0]], [7], [[0.35, 0.0]])
    assert wide.summary()["num_matches"] == 1


def test_empty_frames_and_empty_summary() -> None:
    acc = TrackingAccumulator()
    s = acc.summary()
    assert s["mota"] is None and s["idf1"] is None and s["num_frames"] == 0
    acc.update([], np.zeros((0, 2)), [], [])
    acc.update([1], [[0.0, 0.0]], [], np.zeros(0))
    s = acc.summary()
    assert (s["num_frames"], s["misses"], s["num_gt"], s["mota"]) == (2, 1, 1, 0.0)
    json.dumps(s, allow_nan=False)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (([1, 2], [[0.0, 0.0]], [], []), r"gt_xy must have shape \(2, 2\)"),
        (([1], [[0.0, np.nan]], [], []), "gt_xy must contain only finite"),
        (([1, 1], GT_XY, [], []), "gt_ids must be unique"),
        (([1], [[0.0, 0.0]], [0.5], [[0.0, 0.0]]), "track_ids must be integers"),
        (([1], [[0.0, 0.0]], [[3]], [[0.0, 0.0]]), r"track_ids must have shape \(N,\)"),
        (([1], [[0.0, 0.0]], [3], [[0.0, 0.0, 0.0]]), r"track_xy must have shape \(1, 2\)"),
    ],
)
def test_malformed_input_raises(args: tuple[object, object, object, object], message: str) -> None:
    acc = TrackingAccumulator()
    with pytest.raises(ValueError, match=message):
        acc.update(*args)  # type: ignore[arg-type]
    assert acc.num_frames == 0


def test_bad_gate_raises() -> None:
    with pytest.raises(ValueError, match="max_distance_m"):
        TrackingAccumulator(max_distance_m=-1.0)


def test_merged_sequences_sum_their_events_and_never_link_ids() -> None:
    a, b = TrackingAccumulator(), TrackingAccumulator()
    for _ in range(3):
        a.update([1], [[0.0, 0.0]], [7], [[0.0, 0.0]])
    # The same ids in another sequence: a new object and track there, not a switch.
    b.update([1], [[5.0, 5.0]], [8], [[5.0, 5.0]])
    b.update([1], [[5.0, 5.0]], [], np.zeros((0, 2)))
    a.merge(b)
    s = a.summary()
    assert s["num_frames"] == 5 and s["num_gt"] == 5 and s["misses"] == 1 and s["id_switches"] == 0
    assert s["mota"] == pytest.approx(1 - 1 / 5)


def test_motp_pools_every_matched_pair_even_with_a_matchless_sequence() -> None:
    # motmetrics' own overall MOTP is NaN here (one sequence has no match); the pooled mean is defined.
    a, b, c = TrackingAccumulator(), TrackingAccumulator(), TrackingAccumulator()
    a.update([1, 2], [[0.0, 0.0], [1.0, 1.0]], [7, 8], [[0.01, 0.0], [1.0, 1.03]])
    b.update([1], [[0.0, 0.0]], [9], [[0.02, 0.0]])
    c.update([1], [[0.0, 0.0]], [], np.zeros((0, 2)))
    a.merge(b)
    a.merge(c)
    assert a.summary()["motp_m"] == pytest.approx((0.01 + 0.03 + 0.02) / 3)
    assert TrackingAccumulator().summary()["motp_m"] is None


# HOTA (TrackEval): known answers worked by hand from its definition (Luiten et al. 2021, eqs. 2-9),
# similarity 1 - d / gate, averaged over the 19 thresholds 0.05 .. 0.95.
HOTA_THRESHOLDS = 19


def test_hota_of_perfect_tracks_is_one() -> None:
    acc = TrackingAccumulator(max_distance_m=1.0)
    for _ in range(3):
        acc.update([1, 2], [[0.0, 0.0], [5.0, 0.0]], [7, 8], [[0.0, 0.0], [5.0, 0.0]])
    s = acc.summary()
    assert s["hota"] == pytest.approx(1.0)
    assert s["det_a"] == pytest.approx(1.0) and s["ass_a"] == pytest.approx(1.0)


def test_hota_of_one_switch_halfway_is_root_half() -> None:
    # One object, 4 frames, found exactly; track 7 for two frames, then track 9: every detection is a
    # TP (DetA 1), each TP's association IoU is 2 / (4 + 2 - 2) = 0.5 (AssA 0.5), HOTA = sqrt(0.5).
    acc = TrackingAccumulator(max_distance_m=1.0)
    for tid in (7, 7, 9, 9):
        acc.update([1], [[3.0, 4.0]], [tid], [[3.0, 4.0]])
    s = acc.summary()
    assert s["det_a"] == pytest.approx(1.0)
    assert s["ass_a"] == pytest.approx(0.5)
    assert s["hota"] == pytest.approx(0.5**0.5)


def test_hota_counts_a_false_track_in_det_a() -> None:
    # Every frame: the object found exactly plus one false track: DetA = TP / (TP + FN + FP) = 1 / 2.
    acc = TrackingAccumulator(max_distance_m=1.0)
    for _ in range(2):
        acc.update([1], [[0.0, 0.0]], [7, 8], [[0.0, 0.0], [20.0, 0.0]])
    s = acc.summary()
    assert s["det_a"] == pytest.approx(0.5) and s["ass_a"] == pytest.approx(1.0)
    assert s["hota"] == pytest.approx(0.5**0.5)


def test_hota_localisation_half_the_gate_is_found_at_half_the_thresholds() -> None:
    # d = 0.5 gate: similarity 0.5, a match at the 10 thresholds 0.05 .. 0.50, none at the 9 above.
    acc = TrackingAccumulator(max_distance_m=2.0)
    acc.update([1], [[0.0, 0.0]], [7], [[1.0, 0.0]])
    s = acc.summary()
    assert s["hota"] == pytest.approx(10 / HOTA_THRESHOLDS)
    assert s["hota_at_gate"] == pytest.approx(1.0)


def test_hota_beyond_the_gate_finds_nothing_and_empty_is_none() -> None:
    acc = TrackingAccumulator(max_distance_m=1.0)
    acc.update([1], [[0.0, 0.0]], [7], [[1.5, 0.0]])
    assert acc.summary()["hota"] == pytest.approx(0.0)
    empty = TrackingAccumulator()
    empty.update([], [], [], [])
    assert empty.summary()["hota"] is None


def test_hota_of_merged_sequences_never_links_their_ids() -> None:
    # The same ids in two sequences: each is perfect on its own, so the pooled HOTA is 1, not a switch.
    a, b = TrackingAccumulator(max_distance_m=1.0), TrackingAccumulator(max_distance_m=1.0)
    a.update([1], [[0.0, 0.0]], [7], [[0.0, 0.0]])
    b.update([1], [[9.0, 0.0]], [7], [[9.0, 0.0]])
    a.merge(b)
    assert a.summary()["hota"] == pytest.approx(1.0)
