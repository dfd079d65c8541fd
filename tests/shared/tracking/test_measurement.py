"""Tests of measurement stacking and counted rejection (shared.tracking.measurement)."""

from __future__ import annotations

import collections
import math

import numpy as np

from shared.tracking.measurement import (
    AXIS2,
    HEAD,
    SCORE,
    SIZE,
    Measurement,
    RangeRate,
    Z,
    stack_measurements,
)


def good(**kw: object) -> Measurement:
    return Measurement(np.array([1.0, 2.0]), np.eye(2) * 0.01, 0.1, **kw)  # type: ignore[arg-type]


def test_fields_land_in_their_columns() -> None:
    rejected: collections.Counter[str] = collections.Counter()
    frame = stack_measurements(
        [
            good(size_m=(0.33, 0.22, 0.21), yaw_rad=0.3, yaw_mod_pi=False, score=0.8),
            good(range_rate=RangeRate((0.0, 0.0), -0.2, 0.04), modalities=frozenset({"radar"})),
        ],
        rejected,
    )
    assert not rejected
    np.testing.assert_allclose(frame.attrs[0, [Z, SCORE]], [0.1, 0.8])
    np.testing.assert_allclose(frame.attrs[0, SIZE], [0.33, 0.22, 0.21])
    np.testing.assert_allclose(frame.attrs[0, AXIS2], [math.cos(0.6), math.sin(0.6)])
    np.testing.assert_allclose(frame.attrs[0, HEAD], [math.cos(0.3), math.sin(0.3)])
    assert np.isnan(frame.attrs[1, SIZE]).all() and np.isnan(frame.attrs[1, AXIS2]).all()
    assert np.isnan(frame.rr[0]) and frame.rr[1] == -0.2 and frame.rr_var[1] == 0.04
    assert frame.modalities[1] == frozenset({"radar"})


def test_each_bad_measurement_is_counted_once_under_its_first_failure() -> None:
    rejected: collections.Counter[str] = collections.Counter()
    bad = [
        "not a measurement",
        Measurement(np.array([1.0, 2.0, 3.0]), np.eye(2), 0.1),
        Measurement(np.array([np.nan, 0.0]), np.eye(2), 0.1),
        Measurement(np.zeros(2), np.array([[1.0, 2.0], [2.0, 1.0]]), 0.1),  # not positive definite
        good(score=1.5),
        good(size_m=(0.3, 0.0, 0.2)),
        good(range_rate=((0.0, 0.0), 0.1, 0.0)),
        good(modalities=frozenset({"sonar"}), score=-1.0),  # modality is checked first
    ]
    frame = stack_measurements([good(), *bad], rejected)  # type: ignore[list-item]
    assert frame.pos.shape == (1, 2)
    assert rejected == {
        "not_a_measurement": 1,
        "bad_shape": 1,
        "non_finite": 1,
        "bad_covariance": 1,
        "score_out_of_range": 1,
        "bad_size": 1,
        "bad_range_rate": 1,
        "unknown_modality": 1,
    }
