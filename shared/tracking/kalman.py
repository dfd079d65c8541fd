"""Batched linear Kalman filter on a planar [x, y, vx, vy] state, plus a radar range-rate EKF update.

Every function works on a batch of K independent tracks at once (leading axis K), so a tracker step
costs a handful of numpy calls instead of one small filter per track.

Conventions
-----------
State
    ``x[k] = [x, y, vx, vy]``: world position, m, and velocity, m/s. ``P[k]`` is its 4x4 covariance
    (m², m²/s, m²/s²).
Motion models (:class:`MotionModel`)
    ``"constant_velocity"``: ``F = [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]]`` and the
    discrete white-noise-acceleration ``Q`` per axis, ``accel_std_mps2² · [[dt⁴/4, dt³/2], [dt³/2, dt²]]``
    (filterpy's ``Q_discrete_white_noise(2, dt, var, block_size=2, order_by_dim=False)``).

    ``"identity"``: the paper's ``A = I`` on position. ``F = I₄`` and
    ``Q = diag(q, q, 0, 0)`` with ``q = identity_process_std_m² · dt``: a position random walk whose std
    grows by ``identity_process_std_m`` per square-root second (the paper's hand-set Q = 1 m² per frame
    is std 1 m at dt = 1 s). The velocity is not estimated: it keeps its value (0 in the tracker) and,
    with zero velocity covariance and no position-velocity cross terms, no update can change it.
Updates
    Joseph form, ``P = (I - K H) P (I - K H)ᵀ + K R Kᵀ``, like filterpy's ``KalmanFilter.update``: it
    stays symmetric positive semi-definite with an imperfect gain and matches filterpy to rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

# Named indices of the state x = [x, y, vx, vy].
X, Y, VX, VY = 0, 1, 2, 3
POS = slice(X, Y + 1)  # position, m
VEL = slice(VX, VY + 1)  # velocity, m/s

__all__ = [
    "POS",
    "POSITION_H",
    "VEL",
    "VX",
    "VY",
    "KalmanUpdate",
    "MotionKind",
    "MotionModel",
    "X",
    "Y",
    "predict",
    "process_noise",
    "range_rate_jacobian",
    "transition_matrix",
    "update",
    "update_range_rate",
]

MotionKind = Literal["constant_velocity", "identity"]

#: Measurement matrix of a planar position measurement: z = [x, y].
POSITION_H: FloatArray = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
POSITION_H.setflags(write=False)

_EYE4 = np.eye(4)
_EYE4.setflags(write=False)


@dataclass(frozen=True)
class MotionModel:
    """Process model of the [x, y, vx, vy] state (see the module docstring for F and Q).

    Parameters
    ----------
    kind : {"constant_velocity", "identity"}
        Constant velocity (default) or the paper's identity model (position random walk, no velocity).
    accel_std_mps2 : float
        Constant velocity: std of the white-noise acceleration, m/s².
    identity_process_std_m : float
        Identity: std of the position random walk after one second, m (variance grows with dt).
    """

    kind: MotionKind = "constant_velocity"
    accel_std_mps2: float = 0.5
    identity_process_std_m: float = 0.3

    def __post_init__(self) -> None:
        if self.kind not in ("constant_velocity", "identity"):
            raise ValueError(f"unknown motion model {self.kind!r}")
        if not (np.isfinite(self.accel_std_mps2) and self.accel_std_mps2 >= 0.0):
            raise ValueError(f"accel_std_mps2 must be finite and >= 0, got {self.accel_std_mps2}")
        if not (np.isfinite(self.identity_process_std_m) and self.identity_process_std_m >= 0.0):
            raise ValueError(
                f"identity_process_std_m must be finite and >= 0, got {self.identity_process_std_m}"
            )


_DEFAULT_MODEL = MotionModel()


class KalmanUpdate(NamedTuple):
    """Result of a measurement update of K tracks."""

    x: FloatArray
    """(K, 4) posterior states."""
    P: FloatArray
    """(K, 4, 4) posterior covariances."""
    innovation: FloatArray
    """(K, m) measurement residuals ``z - h(x⁻)``, measurement units."""
    S: FloatArray
    """(K, m, m) innovation covariances."""


def _dt_array(dt_s: ArrayLike, k: int) -> FloatArray:
    dt = np.asarray(dt_s, dtype=np.float64)
    if dt.ndim == 0:
        dt = np.full(k, float(dt))
    elif dt.shape != (k,):
        raise ValueError(f"dt_s must be a scalar or have shape ({k},), got {dt.shape}")
    if not np.all(np.isfinite(dt)) or np.any(dt < 0.0):
        raise ValueError("dt_s must be finite and >= 0")
    return dt


def _transition(dt: FloatArray, model: MotionModel) -> FloatArray:
    F = np.broadcast_to(_EYE4, (dt.size, 4, 4)).copy()
    if model.kind == "constant_velocity":
        F[:, 0, 2] = dt
        F[:, 1, 3] = dt
    return F


def _process_noise(dt: FloatArray, model: MotionModel) -> FloatArray:
    Q = np.zeros((dt.size, 4, 4))
    if model.kind == "constant_velocity":
        var = model.accel_std_mps2**2
        pp = 0.25 * dt**4 * var
        pv = 0.5 * dt**3 * var
        vv = dt**2 * var
        Q[:, 0, 0] = Q[:, 1, 1] = pp
        Q[:, 0, 2] = Q[:, 2, 0] = Q[:, 1, 3] = Q[:, 3, 1] = pv
        Q[:, 2, 2] = Q[:, 3, 3] = vv
    else:
        Q[:, 0, 0] = Q[:, 1, 1] = model.identity_process_std_m**2 * dt
    return Q


def _scalar_transition_noise(dt: float, model: MotionModel) -> tuple[FloatArray, FloatArray]:
    if not (math.isfinite(dt) and dt >= 0.0):
        raise ValueError(f"dt_s must be finite and >= 0, got {dt}")
    if model.kind == "identity":
        q = model.identity_process_std_m**2 * dt
        return _EYE4, np.diag([q, q, 0.0, 0.0])
    var = model.accel_std_mps2**2
    pp, pv, vv = 0.25 * dt**4 * var, 0.5 * dt**3 * var, dt**2 * var
    F = np.array([[1.0, 0.0, dt, 0.0], [0.0, 1.0, 0.0, dt], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    Q = np.array([[pp, 0.0, pv, 0.0], [0.0, pp, 0.0, pv], [pv, 0.0, vv, 0.0], [0.0, pv, 0.0, vv]])
    return F, Q


def transition_matrix(dt_s: ArrayLike, model: MotionModel | None = None) -> FloatArray:
    """State transition matrices F for time steps ``dt_s``.

    Parameters
    ----------
    dt_s : float or array_like, shape (K,)
        Time steps, s (>= 0).
    model : MotionModel, optional
        Process model; constant velocity by default.

    Returns
    -------
    numpy.ndarray, shape (4, 4) for a scalar ``dt_s``, else (K, 4, 4)
    """
    scalar = np.ndim(dt_s) == 0
    F = _transition(_dt_array(dt_s, 1 if scalar else int(np.shape(dt_s)[0])), model or _DEFAULT_MODEL)
    return F[0] if scalar else F


def process_noise(dt_s: ArrayLike, model: MotionModel | None = None) -> FloatArray:
    """Process noise covariances Q for time steps ``dt_s``.

    Parameters
    ----------
    dt_s : float or array_like, shape (K,)
        Time steps, s (>= 0).
    model : MotionModel, optional
        Process model; constant velocity by default.

    Returns
    -------
    numpy.ndarray, shape (4, 4) for a scalar ``dt_s``, else (K, 4, 4)
        m², m²/s, m²/s².
    """
    scalar = np.ndim(dt_s) == 0
    Q = _process_noise(_dt_array(dt_s, 1 if scalar else int(np.shape(dt_s)[0])), model or _DEFAULT_MODEL)
    return Q[0] if scalar else Q


def _check_state(x: ArrayLike, P: ArrayLike) -> tuple[FloatArray, FloatArray]:
    xa = np.asarray(x, dtype=np.float64)
    Pa = np.asarray(P, dtype=np.float64)
    if xa.ndim != 2 or xa.shape[1] != 4:
        raise ValueError(f"x must have shape (K, 4), got {xa.shape}")
    if Pa.shape != (xa.shape[0], 4, 4):
        raise ValueError(f"P must have shape ({xa.shape[0]}, 4, 4), got {Pa.shape}")
    return xa, Pa


def predict(
    x: ArrayLike, P: ArrayLike, dt_s: ArrayLike, model: MotionModel | None = None
) -> tuple[FloatArray, FloatArray]:
    """Propagate K tracks by ``dt_s``: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``.

    Parameters
    ----------
    x : array_like, shape (K, 4)
        States [x, y, vx, vy], m and m/s.
    P : array_like, shape (K, 4, 4)
        Covariances.
    dt_s : float or array_like, shape (K,)
        Time step of every track, s (>= 0; 0 leaves a track unchanged).
    model : MotionModel, optional
        Process model; constant velocity by default.

    Returns
    -------
    x, P : numpy.ndarray, shapes (K, 4) and (K, 4, 4)
        New arrays; the inputs are not modified.
    """
    xa, Pa = _check_state(x, P)
    model = model or _DEFAULT_MODEL
    if np.ndim(dt_s) == 0:
        # One step for all (the tracker's case): a single (4, 4) F and Q broadcast over the batch.
        F, Q = _scalar_transition_noise(float(np.asarray(dt_s)), model)
        return xa @ F.T, F @ Pa @ F.T + Q
    dt = _dt_array(dt_s, xa.shape[0])
    F = _transition(dt, model)
    Q = _process_noise(dt, model)
    x_new = (F @ xa[:, :, None])[:, :, 0]
    P_new = F @ Pa @ F.transpose(0, 2, 1) + Q
    return x_new, P_new


def _joseph_update(x: FloatArray, P: FloatArray, y: FloatArray, H: FloatArray, R: FloatArray) -> KalmanUpdate:
    """Update with residual ``y`` (K, m), Jacobian ``H`` and noise ``R`` (matmul broadcasts a shared one)."""
    PHt = P @ np.swapaxes(H, -1, -2)
    S = H @ PHt + R
    # K = P Hᵀ S⁻¹, solved rather than inverted; S and P are symmetric so Kᵀ = S⁻¹ (H P).
    gain = np.swapaxes(np.linalg.solve(S, np.swapaxes(PHt, -1, -2)), -1, -2)
    x_new = x + (gain @ y[:, :, None])[:, :, 0]
    I_KH = _EYE4 - gain @ H
    P_new = I_KH @ P @ np.swapaxes(I_KH, -1, -2) + gain @ R @ np.swapaxes(gain, -1, -2)
    return KalmanUpdate(x_new, P_new, y, S)


def update(x: ArrayLike, P: ArrayLike, z: ArrayLike, H: ArrayLike, R: ArrayLike) -> KalmanUpdate:
    """Linear measurement update of K tracks (Joseph form).

    Parameters
    ----------
    x : array_like, shape (K, 4)
        Prior states.
    P : array_like, shape (K, 4, 4)
        Prior covariances.
    z : array_like, shape (K, m)
        Measurements.
    H : array_like, shape (m, 4) or (K, m, 4)
        Measurement matrices (one shared by all tracks, or one per track); :data:`POSITION_H` for a
        position measurement.
    R : array_like, shape (m, m) or (K, m, m)
        Measurement noise covariances, measurement units squared.

    Returns
    -------
    KalmanUpdate
        ``(x, P, innovation, S)``: posterior (K, 4) and (K, 4, 4), residual ``z - H x⁻`` (K, m) and its
        covariance ``H P⁻ Hᵀ + R`` (K, m, m).
    """
    xa, Pa = _check_state(x, P)
    k = xa.shape[0]
    za = np.asarray(z, dtype=np.float64)
    if za.ndim != 2 or za.shape[0] != k:
        raise ValueError(f"z must have shape ({k}, m), got {za.shape}")
    m = za.shape[1]
    Ha = np.asarray(H, dtype=np.float64)
    Ra = np.asarray(R, dtype=np.float64)
    if Ha.shape not in ((m, 4), (k, m, 4)):
        raise ValueError(f"H must have shape ({m}, 4) or ({k}, {m}, 4), got {Ha.shape}")
    if Ra.shape not in ((m, m), (k, m, m)):
        raise ValueError(f"R must have shape ({m}, {m}) or ({k}, {m}, {m}), got {Ra.shape}")
    y = za - (Ha @ xa[:, :, None])[:, :, 0]
    return _joseph_update(xa, Pa, y, Ha, Ra)


def range_rate_jacobian(
    x: ArrayLike, sensor_xy_m: ArrayLike, min_range_m: float = 1e-6
) -> tuple[FloatArray, FloatArray]:
    """Predicted radial velocity ``h(x) = u · v`` and its exact Jacobian.

    ``u = (p - s) / r`` is the unit line of sight from the sensor ``s`` to the position ``p`` and
    ``r = |p - s|``; ``∂h/∂p = (v - (u · v) u) / r`` (the line of sight turns as the target moves
    sideways) and ``∂h/∂v = u``.

    Parameters
    ----------
    x : array_like, shape (K, 4)
        States [x, y, vx, vy].
    sensor_xy_m : array_like, shape (K, 2) or (2,)
        Sensor position in the world plane, m.
    min_range_m : float
        Tracks closer than this to the sensor get ``h = 0`` and a zero Jacobian (the line of sight is
        undefined), which makes the update a no-op.

    Returns
    -------
    h : numpy.ndarray, shape (K,)
        Predicted range rate, m/s (positive when moving away).
    H : numpy.ndarray, shape (K, 1, 4)
        Jacobian ``∂h/∂x``.
    """
    xa = np.asarray(x, dtype=np.float64)
    d = xa[:, :2] - np.asarray(sensor_xy_m, dtype=np.float64)
    r = np.hypot(d[:, 0], d[:, 1])
    ok = r >= min_range_m
    r_safe = np.where(ok, r, 1.0)
    u = d / r_safe[:, None] * ok[:, None]
    v = xa[:, VEL]
    h = np.einsum("ki,ki->k", u, v)
    H = np.empty((xa.shape[0], 1, 4))
    H[:, 0, :2] = (v - h[:, None] * u) / r_safe[:, None] * ok[:, None]
    H[:, 0, 2:] = u
    return h, H


def update_range_rate(
    x: ArrayLike,
    P: ArrayLike,
    sensor_xy_m: ArrayLike,
    range_rate_mps: ArrayLike,
    variance_m2ps2: ArrayLike,
    min_range_m: float = 1e-6,
) -> KalmanUpdate:
    """Extended Kalman update with radar radial velocities (Joseph form, exact Jacobian).

    Linearised at the prior: ``H = ∂h/∂x (x⁻)`` from :func:`range_rate_jacobian`, residual
    ``z - h(x⁻)``; identical to filterpy's ``ExtendedKalmanFilter.update``.

    Parameters
    ----------
    x : array_like, shape (K, 4)
        Prior states.
    P : array_like, shape (K, 4, 4)
        Prior covariances.
    sensor_xy_m : array_like, shape (K, 2) or (2,)
        Radar position in the world plane, m.
    range_rate_mps : array_like, shape (K,)
        Measured radial velocities, m/s, positive away from the sensor.
    variance_m2ps2 : float or array_like, shape (K,)
        Range-rate noise variances, m²/s² (> 0).
    min_range_m : float
        Tracks closer than this to the sensor are left unchanged.

    Returns
    -------
    KalmanUpdate
        Posterior states and covariances, residuals (K, 1) and innovation covariances (K, 1, 1).
    """
    xa, Pa = _check_state(x, P)
    k = xa.shape[0]
    rr = np.asarray(range_rate_mps, dtype=np.float64)
    if rr.shape != (k,):
        raise ValueError(f"range_rate_mps must have shape ({k},), got {rr.shape}")
    var = np.broadcast_to(np.asarray(variance_m2ps2, dtype=np.float64), (k,))
    if np.any(~(var > 0.0)):
        raise ValueError("variance_m2ps2 must be > 0")
    h, H = range_rate_jacobian(xa, sensor_xy_m, min_range_m)
    return _joseph_update(xa, Pa, (rr - h)[:, None], H, var[:, None, None])
