"""Known-answer tests of the gated global-nearest-neighbour assignment (shared.tracking.association)."""

from __future__ import annotations

import numpy as np

from shared.tracking.association import associate

EYE = np.eye(2)


def covs(n: int, var_m2: float = 0.01) -> np.ndarray:
    return np.broadcast_to(EYE * var_m2, (n, 2, 2)).copy()


def test_global_assignment_beats_greedy_nearest() -> None:
    # Greedy would give measurement 0 to track 0 (0.1 m) and leave track 1 unmatched (0.6 m > gate);
    # the assignment maximises matches first: track 0 <- meas 1 (0.3 m), track 1 <- meas 0 (0.3 m).
    tracks = np.array([[0.0, 0.0], [0.4, 0.0]])
    meas = np.array([[0.1, 0.0], [-0.3, 0.0]])
    rows, cols = associate(tracks, covs(2), meas, covs(2), gate_m=0.5)
    assert dict(zip(rows.tolist(), cols.tolist(), strict=True)) == {0: 1, 1: 0}


def test_pairs_outside_the_gate_are_never_matched() -> None:
    rows, cols = associate(np.zeros((1, 2)), covs(1), np.array([[0.51, 0.0]]), covs(1), gate_m=0.5)
    assert rows.size == cols.size == 0


def test_mahalanobis_gate_uses_both_covariances() -> None:
    tracks, meas = np.zeros((1, 2)), np.array([[0.3, 0.0]])
    # S = 0.01 + 0.01 = 0.02 m²: d² = 0.09 / 0.02 = 4.5 passes a 9.21 gate, fails a 4.0 gate.
    assert associate(tracks, covs(1), meas, covs(1), gate_m=0.5, gate_mahalanobis=9.21)[0].tolist() == [0]
    assert associate(tracks, covs(1), meas, covs(1), gate_m=0.5, gate_mahalanobis=4.0)[0].size == 0


def test_empty_inputs() -> None:
    rows, cols = associate(np.zeros((0, 2)), covs(0), np.zeros((3, 2)), covs(3), gate_m=0.5)
    assert rows.dtype == np.int64 and rows.size == cols.size == 0
