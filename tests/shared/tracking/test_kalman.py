"""Known-answer tests for shared.tracking.kalman: step-for-step against filterpy, and closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

from shared.tracking.kalman import (
    POSITION_H,
    MotionModel,
    predict,
    process_noise,
    range_rate_jacobian,
    transition_matrix,
    update,
    update_range_rate,
)

TOL = {"rtol": 1e-9, "atol": 1e-9}


def _spd(rng: np.random.Generator, n: int, scale: float = 1.0) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def _filterpy_kf(x: np.ndarray, P: np.ndarray, dim_z: int) -> KalmanFilter:
    kf = KalmanFilter(dim_x=4, dim_z=dim_z)
    kf.x = x.reshape(4, 1).copy()
    kf.P = P.copy()
    return kf


# --- model matrices ----------------------------------------------------------------------------------


@pytest.mark.parametrize("dt", [0.0, 0.05, 0.1, 1.0, 2.5])
def test_constant_velocity_q_is_filterpy_white_noise(dt: float) -> None:
    model = MotionModel(accel_std_mps2=0.7)
    expected = Q_discrete_white_noise(2, dt=dt, var=0.49, block_size=2, order_by_dim=False)
    np.testing.assert_allclose(process_noise(dt, model), expected, **TOL)
    F = transition_matrix(dt, model)
    np.testing.assert_array_equal(F, [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]])


def test_identity_model_matrices() -> None:
    model = MotionModel("identity", identity_process_std_m=0.3)
    np.testing.assert_array_equal(transition_matrix(0.5, model), np.eye(4))
    np.testing.assert_allclose(process_noise(0.5, model), np.diag([0.045, 0.045, 0.0, 0.0]), **TOL)
    # Batched dt gives one matrix per track.
    Q = process_noise([0.0, 1.0], model)
    assert Q.shape == (2, 4, 4)
    np.testing.assert_allclose(Q[1], np.diag([0.09, 0.09, 0.0, 0.0]), **TOL)
    np.testing.assert_array_equal(Q[0], 0.0)


def test_bad_inputs_raise() -> None:
    x, P = np.zeros((2, 4)), np.tile(np.eye(4), (2, 1, 1))
    with pytest.raises(ValueError, match="dt_s"):
        predict(x, P, -0.1)
    with pytest.raises(ValueError, match="dt_s"):
        predict(x, P, [0.1, np.nan])
    with pytest.raises(ValueError, match="P must"):
        predict(x, P[:1], 0.1)
    with pytest.raises(ValueError, match="H must"):
        update(x, P, np.zeros((2, 2)), np.eye(4), np.eye(2))
    with pytest.raises(ValueError, match="variance"):
        update_range_rate(x, P, np.zeros(2), np.zeros(2), 0.0)
    with pytest.raises(ValueError, match="unknown motion model"):
        MotionModel("ctra")  # type: ignore[arg-type]


# --- predict / update vs filterpy --------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["constant_velocity", "identity"])
@pytest.mark.parametrize("dim_z", [2, 3])
def test_predict_update_match_filterpy_step_by_step(kind: str, dim_z: int) -> None:
    rng = np.random.default_rng(dim_z)
    model = MotionModel(kind, accel_std_mps2=0.4, identity_process_std_m=0.2)  # type: ignore[arg-type]
    x0 = rng.normal(size=4)
    P0 = _spd(rng, 4, 0.1)
    kf = _filterpy_kf(x0, P0, dim_z)
    x, P = x0[None], P0[None]
    for _ in range(25):
        dt = float(rng.uniform(0.0, 0.3))
        x, P = predict(x, P, dt, model)
        kf.predict(F=transition_matrix(dt, model), Q=process_noise(dt, model))
        np.testing.assert_allclose(x[0], kf.x.ravel(), **TOL)
        np.testing.assert_allclose(P[0], kf.P, **TOL)

        H = POSITION_H if dim_z == 2 else rng.normal(size=(dim_z, 4))
        R = _spd(rng, dim_z, 0.01)
        z = rng.normal(size=dim_z)
        x, P, y, S = update(x, P, z[None], H, R)
        kf.update(z.reshape(-1, 1), R=R, H=H)
        np.testing.assert_allclose(x[0], kf.x.ravel(), **TOL)
        np.testing.assert_allclose(P[0], kf.P, **TOL)
        np.testing.assert_allclose(y[0], kf.y.ravel(), **TOL)
        np.testing.assert_allclose(S[0], kf.S, **TOL)


def test_batch_equals_independent_filters() -> None:
    rng = np.random.default_rng(7)
    k, dim_z = 6, 3
    model = MotionModel(accel_std_mps2=0.3)
    x = rng.normal(size=(k, 4))
    P = np.stack([_spd(rng, 4, 0.05) for _ in range(k)])
    filters = [_filterpy_kf(x[i], P[i], dim_z) for i in range(k)]
    for _ in range(10):
        dt = rng.uniform(0.0, 0.2, k)  # one dt per track
        H = rng.normal(size=(k, dim_z, 4))
        R = np.stack([_spd(rng, dim_z, 0.02) for _ in range(k)])
        z = rng.normal(size=(k, dim_z))
        x, P = predict(x, P, dt, model)
        x, P, _, _ = update(x, P, z, H, R)
        for i, kf in enumerate(filters):
            kf.predict(F=transition_matrix(dt[i], model), Q=process_noise(dt[i], model))
            kf.update(z[i].reshape(-1, 1), R=R[i], H=H[i])
            np.testing.assert_allclose(x[i], kf.x.ravel(), **TOL)
            np.testing.assert_allclose(P[i], kf.P, **TOL)


def test_zero_dt_predict_is_noop_and_inputs_untouched() -> None:
    rng = np.random.default_rng(1)
    x = rng.normal(size=(3, 4))
    P = np.stack([_spd(rng, 4) for _ in range(3)])
    x_copy, P_copy = x.copy(), P.copy()
    x1, P1 = predict(x, P, 0.0)
    np.testing.assert_array_equal(x1, x)
    np.testing.assert_array_equal(P1, P)
    update(x, P, np.zeros((3, 2)), POSITION_H, np.eye(2))
    np.testing.assert_array_equal(x, x_copy)
    np.testing.assert_array_equal(P, P_copy)


def test_empty_batch() -> None:
    x, P = predict(np.zeros((0, 4)), np.zeros((0, 4, 4)), 0.1)
    assert x.shape == (0, 4) and P.shape == (0, 4, 4)
    out = update(x, P, np.zeros((0, 2)), POSITION_H, np.eye(2))
    assert out.x.shape == (0, 4) and out.S.shape == (0, 2, 2)


# --- range rate --------------------------------------------------------------------------------------


def _hx(x: np.ndarray, sensor: np.ndarray) -> np.ndarray:
    p, v = x[:2, 0], x[2:, 0]
    return np.array([[(p - sensor) @ v / np.linalg.norm(p - sensor)]])


def _hjac(x: np.ndarray, sensor: np.ndarray) -> np.ndarray:
    # Written out independently of the module: d(u.v)/dp = (v - (u.v) u) / r, d(u.v)/dv = u.
    p, v = x[:2, 0], x[2:, 0]
    r = np.linalg.norm(p - sensor)
    u = (p - sensor) / r
    return np.concatenate([(v - (u @ v) * u) / r, u])[None]


def test_range_rate_update_matches_filterpy_ekf() -> None:
    rng = np.random.default_rng(3)
    k = 8
    x = np.c_[rng.uniform(-3, 3, (k, 2)), rng.uniform(-0.6, 0.6, (k, 2))]
    P = np.stack([_spd(rng, 4, 0.02) for _ in range(k)])
    sensors = rng.uniform(-4, 4, (k, 2))
    ekfs = []
    for i in range(k):
        ekf = ExtendedKalmanFilter(dim_x=4, dim_z=1)
        ekf.x = x[i].reshape(4, 1).copy()
        ekf.P = P[i].copy()
        ekfs.append(ekf)
    for _ in range(5):
        rr = rng.normal(0.0, 0.5, k)
        var = rng.uniform(1e-4, 1e-2, k)
        x, P, y, S = update_range_rate(x, P, sensors, rr, var)
        for i, ekf in enumerate(ekfs):
            ekf.update(
                np.array([[rr[i]]]), _hjac, _hx, R=np.array([[var[i]]]), args=sensors[i], hx_args=sensors[i]
            )
            np.testing.assert_allclose(x[i], ekf.x.ravel(), **TOL)
            np.testing.assert_allclose(P[i], ekf.P, **TOL)
            np.testing.assert_allclose(y[i], ekf.y.ravel(), **TOL)
            np.testing.assert_allclose(S[i], ekf.S, **TOL)


def test_range_rate_jacobian_known_answer_and_finite_differences() -> None:
    # Target at (3, 4) (r = 5, u = (0.6, 0.8)) moving (1, 0): h = 0.6; dh/dp = ((1,0) - 0.6 u) / 5.
    h, H = range_rate_jacobian(np.array([[3.0, 4.0, 1.0, 0.0]]), np.zeros(2))
    np.testing.assert_allclose(h, [0.6], **TOL)
    np.testing.assert_allclose(H[0, 0], [(1 - 0.36) / 5, -0.48 / 5, 0.6, 0.8], **TOL)

    rng = np.random.default_rng(4)
    x = np.c_[rng.uniform(-2, 2, (5, 2)), rng.uniform(-1, 1, (5, 2))]
    sensor = np.array([0.3, -0.7])
    _, H = range_rate_jacobian(x, sensor)
    eps = 1e-6
    for j in range(4):
        dx = np.zeros(4)
        dx[j] = eps
        hp, _ = range_rate_jacobian(x + dx, sensor)
        hm, _ = range_rate_jacobian(x - dx, sensor)
        np.testing.assert_allclose(H[:, 0, j], (hp - hm) / (2 * eps), atol=1e-8)


def test_range_rate_at_the_sensor_is_a_noop() -> None:
    x = np.array([[1.0, 1.0, 0.3, 0.1]])
    P = np.eye(4)[None] * 0.1
    out = update_range_rate(x, P, np.array([1.0, 1.0]), np.array([0.5]), 0.01)
    np.testing.assert_array_equal(out.x, x)
    np.testing.assert_allclose(out.P, P, **TOL)


# --- steady state ------------------------------------------------------------------------------------


def test_identity_model_steady_state_paper_numbers() -> None:
    # Paper: A = H = I, Q = 1, R = 10. Posterior P solves P = (P + 1) R / (P + 1 + R): P^2 + P - 10 = 0.
    model = MotionModel("identity", identity_process_std_m=1.0)
    x = np.array([[0.5, -0.5, 0.0, 0.0]])
    P = np.diag([1e6, 1e6, 0.0, 0.0])[None]
    gain = np.nan
    for _ in range(60):
        x, P = predict(x, P, 1.0, model)
        prior = P[0, 0, 0]
        x, P, _, S = update(x, P, np.zeros((1, 2)), POSITION_H, 10.0 * np.eye(2))
        gain = prior / S[0, 0, 0]
    p_ss = (-1.0 + np.sqrt(41.0)) / 2.0
    np.testing.assert_allclose(P[0, 0, 0], p_ss, rtol=1e-9)
    np.testing.assert_allclose(P[0, 1, 1], p_ss, rtol=1e-9)
    np.testing.assert_allclose(gain, (p_ss + 1.0) / (p_ss + 11.0), rtol=1e-9)
    assert round(P[0, 0, 0], 2) == 2.70
    assert round(gain, 2) == 0.27
    np.testing.assert_array_equal(x[0, 2:], 0.0)  # velocity is not estimated
    np.testing.assert_array_equal(P[0, 2:, :], 0.0)
