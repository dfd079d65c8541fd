"""Known-answer tests of the heading resolution (shared.tracking.heading)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.tracking.heading import resolve_yaw, wrap
from shared.tracking.measurement import AXIS2, HEAD, N_ATTRS

KW = {"min_speed_mps": 0.05, "min_speed_sigmas": 3.0}


def track(axis_rad: float | None, v_mps: tuple[float, float], head_rad: float | None = None) -> tuple:
    x = np.array([[0.0, 0.0, *v_mps]])
    P = np.eye(4)[None] * 1e-4  # velocity std 0.01 m/s
    attrs = np.full((1, N_ATTRS), np.nan)
    if axis_rad is not None:
        attrs[0, AXIS2] = [math.cos(2 * axis_rad), math.sin(2 * axis_rad)]
    if head_rad is not None:
        attrs[0, HEAD] = [math.cos(head_rad), math.sin(head_rad)]
    return x, P, attrs


def test_wrap_is_half_open_and_nan_tolerant() -> None:
    got = wrap(np.array([math.pi, -math.pi, 3 * math.pi / 2, np.nan]))
    np.testing.assert_allclose(got[:3], [math.pi, math.pi, -math.pi / 2])
    assert math.isnan(got[3])


def test_axis_sign_from_motion() -> None:
    x, P, attrs = track(0.1, (-0.3, -0.03))  # moving towards -x: the axis 0.1 points backwards
    yaw, known = resolve_yaw(x, P, attrs, np.array([np.nan]), np.array([False]), **KW)
    assert known[0] and yaw[0] == pytest.approx(0.1 - math.pi)


def test_a_full_heading_beats_the_motion() -> None:
    x, P, attrs = track(0.1, (-0.3, 0.0), head_rad=0.12)  # driving backwards, heading measured
    yaw, known = resolve_yaw(x, P, attrs, np.array([np.nan]), np.array([False]), **KW)
    assert known[0] and yaw[0] == pytest.approx(0.1)


def test_a_stopped_track_keeps_its_previous_sign() -> None:
    x, P, attrs = track(0.1, (0.0, 0.0))
    yaw, known = resolve_yaw(x, P, attrs, np.array([0.1 - math.pi]), np.array([True]), **KW)
    assert known[0] and yaw[0] == pytest.approx(0.1 - math.pi)
    yaw, known = resolve_yaw(x, P, attrs, np.array([np.nan]), np.array([False]), **KW)
    assert not known[0] and yaw[0] == pytest.approx(0.1)  # mod pi only


def test_slow_motion_within_its_noise_gives_no_sign() -> None:
    x, P, attrs = track(None, (0.06, 0.0))
    P[0, 2, 2] = P[0, 3, 3] = 0.03**2  # 0.06 m/s is 2 sigma: not clearly moving
    yaw, known = resolve_yaw(x, P, attrs, np.array([np.nan]), np.array([False]), **KW)
    assert not known[0] and math.isnan(yaw[0])
