"""Association of a frame's measurements with the tracks: global nearest neighbour inside a gate.

The cost is the Euclidean distance of a measurement from a track's predicted position (the paper's
0.5 m gate), or, with a chi² gate set, the squared Mahalanobis distance of the position innovation
(which then also gates). The assignment is scipy's Hungarian solver (`linear_sum_assignment`).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from shared.tracking.kalman import FloatArray
from shared.tracking.measurement import NDInt


def associate(
    track_pos_m: FloatArray,
    track_cov_m2: FloatArray,
    meas_pos_m: FloatArray,
    meas_cov_m2: FloatArray,
    *,
    gate_m: float,
    gate_mahalanobis: float | None = None,
) -> tuple[NDInt, NDInt]:
    """Matched (track row, measurement row) pairs of the gated minimum-cost assignment.

    Parameters
    ----------
    track_pos_m, track_cov_m2 : numpy.ndarray, shapes (N, 2) and (N, 2, 2)
        Predicted track positions (m) and their covariances (m²).
    meas_pos_m, meas_cov_m2 : numpy.ndarray, shapes (M, 2) and (M, 2, 2)
        Measured positions (m) and covariances (m²), symmetric positive definite.
    gate_m : float
        Largest distance of a match, m.
    gate_mahalanobis : float, optional
        Largest squared Mahalanobis distance of a match (chi², 2 dof); when set it is the cost.

    Returns
    -------
    (rows, cols) : numpy.ndarray of int64, shape (K,) each
        Track and measurement indices of the K matches; the assignment first maximises the number of
        gated matches, then minimises their total cost.
    """
    empty = np.zeros(0, np.int64)
    if track_pos_m.shape[0] == 0 or meas_pos_m.shape[0] == 0:
        return empty, empty
    diff = meas_pos_m[None, :, :] - track_pos_m[:, None, :]  # (N, M, 2)
    cost = np.hypot(diff[..., 0], diff[..., 1])
    feasible = cost <= gate_m
    if gate_mahalanobis is not None:
        S = track_cov_m2[:, None] + meas_cov_m2[None]  # (N, M, 2, 2), symmetric positive definite
        a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
        dx, dy = diff[..., 0], diff[..., 1]
        cost = (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)
        feasible &= cost <= gate_mahalanobis
    if not feasible.any():
        return empty, empty
    # Infeasible pairs cost more than all feasible ones together.
    big = 1.0 + float(cost[feasible].sum())
    rows, cols = linear_sum_assignment(np.where(feasible, cost, big))
    keep = feasible[rows, cols]
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)
