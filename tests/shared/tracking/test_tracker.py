"""Scenario and known-answer tests for shared.tracking.tracker.MultiObjectTracker."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from shared.tracking.measurement import Measurement, RangeRate
from shared.tracking.track_table import Track, TrackState
from shared.tracking.tracker import MultiObjectTracker, TrackerConfig

DT = 0.1


def _m(xy: Any, sigma_m: float = 0.01, **kw: Any) -> Measurement:
    kw.setdefault("z_m", 0.1)
    kw.setdefault("modalities", frozenset({"lidar"}))
    return Measurement(np.asarray(xy, dtype=float), np.eye(2) * sigma_m**2, **kw)


def _by_id(tracks: list[Track]) -> dict[int, Track]:
    return {t.track_id: t for t in tracks}


def _run_static(trk: MultiObjectTracker, frames: int, xy: Any = (0.0, 0.0), t0: float = 0.0) -> list[Track]:
    out: list[Track] = []
    for f in range(frames):
        out = trk.step(t0 + f * DT, [_m(xy)])
    return out


# --- lifecycle ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("confirm_hits", [1, 2, 3, 5])
def test_confirmed_after_exactly_confirm_hits_frames(confirm_hits: int) -> None:
    trk = MultiObjectTracker(TrackerConfig(confirm_hits=confirm_hits, confirm_window=confirm_hits))
    for f in range(1, confirm_hits + 2):
        out = trk.step(f * DT, [_m((0.0, 0.0))])
        if f < confirm_hits:
            assert out == []  # tentative tracks are hidden
            (t,) = trk.all_tracks()
            assert t.state is TrackState.TENTATIVE and t.hits == f and t.age_frames == f
        else:
            (t,) = out
            assert t.state is TrackState.CONFIRMED and t.track_id == 1 and t.hits == f


def test_tentative_track_deleted_on_first_miss_by_default() -> None:
    trk = MultiObjectTracker()
    trk.step(0.0, [_m((0.0, 0.0))])
    trk.step(DT, [_m((0.0, 0.0))])
    assert trk.step(2 * DT, []) == []
    assert len(trk) == 0


def test_m_of_n_confirmation_tolerates_misses_while_reachable() -> None:
    cfg = TrackerConfig(confirm_hits=3, confirm_window=4)
    trk = MultiObjectTracker(cfg)
    hit = [_m((0.0, 0.0))]
    trk.step(0.0, hit)  # hits 1, age 1
    trk.step(DT, [])  # hits 1, age 2: 3 hits still reachable by frame 4
    assert len(trk) == 1
    assert trk.step(2 * DT, hit) == []  # hits 2, age 3
    (t,) = trk.step(3 * DT, hit)  # hits 3 within 4 frames
    assert t.state is TrackState.CONFIRMED

    trk = MultiObjectTracker(cfg)
    trk.step(0.0, hit)
    trk.step(DT, [])
    trk.step(2 * DT, [])  # 1 hit + 1 frame left < 3: deleted
    assert len(trk) == 0


@pytest.mark.parametrize("max_misses", [0, 1, 3])
def test_confirmed_track_coasts_max_misses_frames_then_is_deleted(max_misses: int) -> None:
    trk = MultiObjectTracker(TrackerConfig(max_misses=max_misses))
    _run_static(trk, 3)
    for miss in range(1, max_misses + 1):
        (t,) = trk.step((2 + miss) * DT, [])
        assert t.state is TrackState.COASTING and t.consecutive_misses == miss
        assert t.modalities == frozenset() and t.sensor_ids == ()
    assert trk.step((3 + max_misses) * DT, []) == []  # deleted when misses > max_misses
    assert len(trk) == 0


def test_coasting_track_is_predicted_and_recovers() -> None:
    cfg = TrackerConfig(accel_std_mps2=0.05)
    trk = MultiObjectTracker(cfg)
    v = np.array([0.3, -0.2])
    for f in range(20):
        (last,) = trk.step(f * DT, [_m(v * f * DT, sensor_ids=("lidar0",))]) or [None]
    assert last is not None and last.sensor_ids == ("lidar0",)
    coasted = trk.step(21 * DT, [])  # two frames later, nothing seen
    (t,) = coasted
    np.testing.assert_allclose(t.position_m, last.position_m + 2 * DT * last.velocity_mps, atol=1e-12)
    np.testing.assert_allclose(t.velocity_mps, last.velocity_mps, atol=1e-12)
    assert t.P[0, 0] > last.P[0, 0]
    assert t.last_update_stamp_s == pytest.approx(19 * DT)
    (t,) = trk.step(22 * DT, [_m(v * 22 * DT)])
    assert t.state is TrackState.CONFIRMED and t.consecutive_misses == 0 and t.track_id == last.track_id


def test_coast_predicts_without_missing_aging_or_deleting() -> None:
    """A frame no sensor delivered: the tracks move on their model; no miss, so none is deleted."""
    trk = MultiObjectTracker(TrackerConfig(max_misses=1, accel_std_mps2=0.05))
    v = np.array([0.3, -0.2])
    for f in range(10):
        (last,) = trk.step(f * DT, [_m(v * f * DT)]) or [None]
    assert last is not None
    for k in range(1, 6):  # more frames than max_misses
        (t,) = trk.coast((9 + k) * DT)
        assert (
            t.state is TrackState.CONFIRMED and t.consecutive_misses == 0 and t.age_frames == last.age_frames
        )
    np.testing.assert_allclose(t.position_m, last.position_m + 5 * DT * last.velocity_mps, atol=1e-12)
    assert t.P[0, 0] > last.P[0, 0]
    assert [x.track_id for x in trk.coast(DT)] == [t.track_id] and trk.rejected["out_of_order_stamp"] == 1
    (t,) = trk.step(15 * DT, [_m(v * 15 * DT)])
    assert t.track_id == last.track_id and t.consecutive_misses == 0


def test_ids_count_from_one_and_are_never_reused() -> None:
    trk = MultiObjectTracker()
    trk.step(0.0, [_m((0.0, 0.0)), _m((2.0, 0.0))])
    trk.step(DT, [])  # both tentative tracks die
    trk.reset()
    trk.step(0.0, [_m((0.0, 0.0))])
    assert [t.track_id for t in trk.all_tracks()] == [3]


# --- association -------------------------------------------------------------------------------------


def test_out_of_gate_measurement_spawns_a_new_track() -> None:
    trk = MultiObjectTracker(TrackerConfig(accel_std_mps2=0.01))
    _run_static(trk, 3)
    out = _by_id(trk.step(3 * DT, [_m((0.6, 0.0))]))  # 0.6 m > 0.5 m gate
    assert out[1].state is TrackState.COASTING
    assert [(t.track_id, t.state) for t in trk.all_tracks()] == [
        (1, TrackState.COASTING),
        (2, TrackState.TENTATIVE),
    ]
    (t,) = trk.step(4 * DT, [_m((0.3, 0.0)), _m((0.6, 0.0))])  # inside both gates: nearest wins
    assert t.track_id == 1 and t.state is TrackState.CONFIRMED
    assert trk.all_tracks()[1].hits == 2


def test_mahalanobis_gate_rejects_statistically_far_pairs() -> None:
    cfg = TrackerConfig(accel_std_mps2=0.01, gate_mahalanobis=9.21)
    trk = MultiObjectTracker(cfg)
    _run_static(trk, 5)
    # 0.2 m is within the 0.5 m Euclidean gate but ~14 sigma away for a 0.01 m track and measurement.
    trk.step(5 * DT, [_m((0.2, 0.0))])
    assert [t.track_id for t in trk.all_tracks()] == [1, 2]


def test_two_crossing_targets_keep_their_ids_and_velocities_converge() -> None:
    # Constant-velocity targets crossing at the origin at the same time (e.g. over and under the viaduct).
    rng = np.random.default_rng(0)
    trk = MultiObjectTracker(TrackerConfig(accel_std_mps2=0.02))
    v_a, v_b = np.array([0.4, 0.0]), np.array([0.0, 0.4])
    start_a, start_b = np.array([-1.2, 0.0]), np.array([0.0, -1.2])
    out: dict[int, Track] = {}
    for f in range(60):
        t = f * DT
        truth = {1: start_a + v_a * t, 2: start_b + v_b * t}
        meas = [_m(truth[i] + rng.normal(0.0, 0.01, 2)) for i in (1, 2)]
        out = _by_id(trk.step(t, meas[:: -1 if f % 2 else 1]))  # order must not matter (A born first)
        if f >= 2:
            assert sorted(out) == [1, 2]
            for i in (1, 2):
                assert np.linalg.norm(out[i].position_m - truth[i]) < 0.05
    assert np.linalg.norm(out[1].velocity_mps - v_a) < 0.02
    assert np.linalg.norm(out[2].velocity_mps - v_b) < 0.02


# --- heading -----------------------------------------------------------------------------------------


def test_mod_pi_yaw_sign_resolved_from_motion_and_kept_when_stopped() -> None:
    rng = np.random.default_rng(1)
    heading = 3 * np.pi / 4
    v = 0.3 * np.array([np.cos(heading), np.sin(heading)])
    trk = MultiObjectTracker(TrackerConfig(accel_std_mps2=0.1))
    out: list[Track] = []
    # The lidar reports the box axis modulo pi: heading - pi, plus noise.
    for f in range(30):
        out = trk.step(f * DT, [_m(v * f * DT, yaw_rad=heading - np.pi + rng.normal(0, 0.02))])
    (t,) = out
    assert t.heading_sign_known
    assert t.yaw_rad == pytest.approx(heading, abs=0.03)
    # The car stops: the velocity decays below the threshold but the heading keeps its sign.
    stop = v * 29 * DT
    for f in range(30, 80):
        out = trk.step(f * DT, [_m(stop, yaw_rad=heading - np.pi)])
    (t,) = out
    assert t.speed_mps < 0.05
    assert t.heading_sign_known and t.yaw_rad == pytest.approx(heading, abs=0.03)


def test_stationary_mod_pi_yaw_stays_unsigned_and_averages_on_the_doubled_angle() -> None:
    trk = MultiObjectTracker(TrackerConfig(yaw_smoothing=0.5))
    # pi/2 - 0.1 and -pi/2 + 0.1 describe axes 0.2 rad apart; their circular mean of 2*yaw is pi/2 exactly.
    for f in range(3):
        yaw = np.pi / 2 - 0.1 if f < 2 else -np.pi / 2 + 0.1
        out = trk.step(f * DT, [_m((0.0, 0.0), yaw_rad=yaw)])
    (t,) = out
    assert not t.heading_sign_known
    assert -np.pi / 2 < t.yaw_rad <= np.pi / 2  # type: ignore[operator]
    # EMA of unit vectors of 2*yaw: (pi - 0.2) twice then (-pi + 0.2) with weight 0.5 -> angle exactly pi.
    assert abs(t.yaw_rad) == pytest.approx(np.pi / 2, abs=1e-9)  # type: ignore[arg-type]


def test_full_heading_measurement_sets_the_sign() -> None:
    trk = MultiObjectTracker()
    for f in range(3):
        out = trk.step(f * DT, [_m((0.0, 0.0), yaw_rad=np.pi - 0.1, yaw_mod_pi=False)])
    (t,) = out
    assert t.heading_sign_known and t.yaw_rad == pytest.approx(np.pi - 0.1, abs=1e-9)


def test_yaw_without_yaw_measurements_comes_from_velocity() -> None:
    trk = MultiObjectTracker(TrackerConfig(accel_std_mps2=0.1))
    (t,) = _run_static(trk, 3)
    assert t.yaw_rad is None and not t.heading_sign_known and t.size_m is None
    trk = MultiObjectTracker(TrackerConfig(accel_std_mps2=0.1))
    v = np.array([-0.3, -0.3])
    for f in range(30):
        out = trk.step(f * DT, [_m(v * f * DT, modalities=frozenset({"radar"}))])
    (t,) = out
    assert t.heading_sign_known and t.yaw_rad == pytest.approx(-3 * np.pi / 4, abs=0.05)


# --- radar range rate --------------------------------------------------------------------------------


def test_range_rate_reduces_velocity_error_for_a_radial_target() -> None:
    sensor = np.array([0.0, 0.0])
    u = np.array([1.0, 1.0]) / np.sqrt(2.0)
    v = 0.5 * u  # moving straight away from the radar
    errors = {}
    for use_rr in (False, True):
        rng = np.random.default_rng(2)
        trk = MultiObjectTracker()
        err = []
        for f in range(25):
            truth = u + v * f * DT
            rr = RangeRate(sensor, v @ u + rng.normal(0, 0.01), 0.01**2)
            m = _m(truth + rng.normal(0, 0.05, 2), sigma_m=0.05, range_rate=rr if use_rr else None)
            trk.step(f * DT, [m])
            if f >= 2:
                (t,) = trk.all_tracks()
                err.append(abs(t.velocity_mps @ u - 0.5))
        errors[use_rr] = float(np.mean(err))
    assert errors[True] < 0.2 * errors[False]
    assert errors[True] < 0.02


def test_radar_birth_starts_with_the_radial_velocity() -> None:
    trk = MultiObjectTracker()
    trk.step(0.0, [_m((3.0, 4.0), range_rate=(np.zeros(2), 0.5, 1e-4))])
    (t,) = trk.all_tracks()
    # Prior std 0.5 m/s, measurement std 0.01 m/s: almost all of 0.5 m/s along u = (0.6, 0.8).
    np.testing.assert_allclose(t.velocity_mps, 0.5 * np.array([0.6, 0.8]) * 0.25 / (0.25 + 1e-4), atol=1e-9)


# --- identity model ----------------------------------------------------------------------------------


def test_identity_model_keeps_velocity_at_zero() -> None:
    trk = MultiObjectTracker(TrackerConfig(motion_model="identity"))
    for f in range(10):
        out = trk.step(f * DT, [_m((0.05 * f, 0.0), range_rate=(np.array([-1.0, 0.0]), 0.5, 1e-4))])
    (t,) = out
    np.testing.assert_array_equal(t.velocity_mps, 0.0)
    np.testing.assert_array_equal(t.P[2:, :], 0.0)
    assert 0.0 < t.position_m[0] < 0.45  # lags the moving target, as the paper's filter does


# --- smoothing and scores ----------------------------------------------------------------------------


def test_height_size_score_smoothing_and_existence_known_answers() -> None:
    cfg = TrackerConfig(z_smoothing=0.3, size_smoothing=0.5, score_smoothing=0.5)
    trk = MultiObjectTracker(cfg)
    trk.step(0.0, [_m((0.0, 0.0), z_m=0.10, score=0.8)])  # no box yet
    trk.step(DT, [_m((0.0, 0.0), z_m=0.20, score=0.6, size_m=np.array([0.3, 0.2, 0.2]))])
    (t,) = trk.step(2 * DT, [_m((0.0, 0.0), z_m=0.20, score=1.0, size_m=np.array([0.4, 0.2, 0.2]))])
    assert t.z_m == pytest.approx(0.7 * (0.7 * 0.1 + 0.3 * 0.2) + 0.3 * 0.2)
    np.testing.assert_allclose(t.size_m, [0.35, 0.2, 0.2])  # type: ignore[arg-type]
    assert t.score == pytest.approx(0.5 * (0.5 * 0.8 + 0.5 * 0.6) + 0.5)
    assert t.existence_probability == pytest.approx(t.score)  # 3/3 hits, no misses
    (t,) = trk.step(3 * DT, [])
    assert t.existence_probability == pytest.approx(t.score * 0.75)  # 1 miss of 3 allowed
    assert not t.x.flags.writeable and not t.P.flags.writeable


# --- robustness --------------------------------------------------------------------------------------


def test_malformed_measurements_are_rejected_and_counted_while_good_ones_update() -> None:
    trk = MultiObjectTracker()
    good = _m((0.0, 0.0))
    bad: list[Any] = [
        "not a measurement",
        _m((np.nan, 0.0)),
        _m((0.0, 0.0, 0.0)),
        Measurement(np.zeros(2), np.eye(3), 0.1),
        Measurement(np.zeros(2), [[1e-4, 2e-4], [2e-4, 1e-4]], 0.1),  # not positive definite
        Measurement(np.zeros(2), [[1e-4, 0.0], [1e-5, 1e-4]], 0.1),  # not symmetric
        _m((0.0, 0.0), score=1.5),
        _m((0.0, 0.0), modalities=frozenset({"sonar"})),
        _m((0.0, 0.0), size_m=np.array([0.3, -0.2, 0.2])),
        _m((0.0, 0.0), size_m=np.array([0.3, 0.2])),
        _m((0.0, 0.0), yaw_rad=np.inf),
        _m((0.0, 0.0), z_m="high"),
        _m((0.0, 0.0), range_rate=(np.zeros(2), 0.1, 0.0)),
        _m((0.0, 0.0), range_rate=(np.zeros(3), 0.1, 1e-4)),
        _m((0.0, 0.0), range_rate=(np.zeros(2), np.nan, 1e-4)),
    ]
    for f in range(3):
        out = trk.step(f * DT, [*bad[: 2 + f], good, *bad[2 + f :]])
    (t,) = out
    assert t.hits == 3 and len(trk) == 1
    assert trk.rejected == {
        "not_a_measurement": 3,
        "non_finite": 9,
        "bad_shape": 15,
        "bad_covariance": 6,
        "score_out_of_range": 3,
        "unknown_modality": 3,
        "bad_size": 3,
        "bad_range_rate": 3,
    }


def test_out_of_order_and_non_finite_stamps_are_rejected() -> None:
    trk = MultiObjectTracker()
    _run_static(trk, 3)  # stamps 0.0 .. 0.2
    (before,) = trk.confirmed()
    (after,) = trk.step(0.1, [_m((0.4, 0.0))])
    assert trk.rejected["out_of_order_stamp"] == 1
    assert after.hits == before.hits == 3 and len(trk) == 1
    trk.step(float("nan"), [_m((0.0, 0.0))])
    assert trk.rejected["non_finite_stamp"] == 1
    assert trk.last_stamp_s == pytest.approx(0.2)
    (t,) = trk.step(0.2, [_m((0.0, 0.0))])  # the same stamp again is fine: no prediction
    assert t.hits == 4


def test_track_limit_drops_births() -> None:
    trk = MultiObjectTracker(TrackerConfig(max_tracks=2))
    trk.step(0.0, [_m((0.0, 0.0)), _m((1.0, 0.0)), _m((2.0, 0.0))])
    assert len(trk) == 2 and trk.rejected["track_limit"] == 1


def test_config_is_frozen_strict_and_consistent() -> None:
    with pytest.raises(ValidationError):
        TrackerConfig(confirm_hits=3, confirm_window=2)
    with pytest.raises(ValidationError):
        TrackerConfig(gate=0.5)  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        TrackerConfig().gate_m = 1.0  # type: ignore[misc]
    for name, field in TrackerConfig.model_fields.items():
        assert field.description, name
