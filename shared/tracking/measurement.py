"""What the tracker consumes: one fused object per `Measurement`, stacked per frame and validated.

`stack_measurements` turns a frame's measurements into arrays (`MeasurementFrame`), rejecting malformed
ones with a counted reason. Box size, yaw and the radar range rate are optional; the smoothed
attributes a track carries share one row layout (the ``*_COLS`` indices below), NaN where unmeasured.
"""

from __future__ import annotations

import collections
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from shared.tracking.kalman import FloatArray

CAMERA, LIDAR, RADAR = "camera", "lidar", "radar"  # sensor kinds, as the scene names them
MODALITIES: frozenset[str] = frozenset({CAMERA, LIDAR, RADAR})

NDBool = np.ndarray[Any, np.dtype[np.bool_]]
NDInt = np.ndarray[Any, np.dtype[np.int64]]

# Smoothed attributes of a measurement / track share one row, so a single exponential average updates
# them all: height (m), score, box size (3, m), (cos 2yaw, sin 2yaw) of any yaw, (cos yaw, sin yaw) of
# a full heading. NaN: never measured.
Z, SCORE = 0, 1
SIZE = slice(2, 5)
AXIS2 = slice(5, 7)
HEAD = slice(7, 9)
N_ATTRS = 9
COS, SIN = 0, 1  # within AXIS2 and HEAD
# A measured range rate while stacking: the radar's x, y (m), the rate (m/s) and its variance (m²/s²).
_RR_SENSOR, _RR_RATE, _RR_VAR = slice(0, 2), 2, 3


class RangeRate(NamedTuple):
    """A radar radial velocity attached to a measurement."""

    sensor_xy_m: Any
    """(2,) radar position in the world plane, m."""
    range_rate_mps: float
    """Radial velocity, m/s, positive away from the radar."""
    variance_m2ps2: float
    """Noise variance, m²/s² (> 0)."""


@dataclass(frozen=True, slots=True)
class Measurement:
    """One object seen in one fused frame. Not validated here: the tracker rejects malformed ones.

    Attributes
    ----------
    position_m : array_like, shape (2,)
        World x, y, m.
    position_cov_m2 : array_like, shape (2, 2)
        Position covariance, m² (symmetric positive definite).
    z_m : float
        World height of the object centre, m.
    size_m : array_like, shape (3,), optional
        Box length, width, height, m (> 0); None when the sensor gives no box (radar, camera).
    yaw_rad : float, optional
        Heading, rad, counter-clockwise from +x; None when unmeasured.
    yaw_mod_pi : bool
        True when the yaw is only known modulo pi (lidar boxes), False for a full heading.
    range_rate : RangeRate or tuple, optional
        ``(sensor_xy_m, range_rate_mps, variance_m2ps2)`` from a radar.
    modalities : frozenset of str
        Sensor kinds that saw the object, a subset of {"camera", "lidar", "radar"}.
    score : float
        Detection confidence in [0, 1].
    sensor_ids : tuple of str
        Sensors that saw the object (carried to the track for diagnostics).
    """

    position_m: Any
    position_cov_m2: Any
    z_m: float
    size_m: Any = None
    yaw_rad: float | None = None
    yaw_mod_pi: bool = True
    range_rate: RangeRate | tuple[Any, float, float] | None = None
    modalities: frozenset[str] = frozenset()
    score: float = 1.0
    sensor_ids: tuple[str, ...] = ()


class MeasurementFrame(NamedTuple):
    """The valid measurements of one step, stacked (M rows)."""

    pos: FloatArray  # (M, 2) world x, y, m
    cov: FloatArray  # (M, 2, 2) m², symmetrised
    attrs: FloatArray  # (M, N_ATTRS): columns Z, SCORE, SIZE, AXIS2, HEAD; NaN where unmeasured
    rr_xy: FloatArray  # (M, 2) radar x, y, m; NaN without a range rate
    rr: FloatArray  # (M,) m/s, NaN without a range rate
    rr_var: FloatArray  # (M,) m²/s²
    modalities: list[frozenset[str]]
    sensor_ids: list[tuple[str, ...]]


EMPTY_FRAME = MeasurementFrame(
    np.zeros((0, 2)),
    np.zeros((0, 2, 2)),
    np.zeros((0, N_ATTRS)),
    np.zeros((0, 2)),
    np.zeros(0),
    np.zeros(0),
    [],
    [],
)

_ONES3 = np.ones(3)
_ONES3.setflags(write=False)


def _stack(values: list[Any], shape: tuple[int, ...], ok: NDBool) -> FloatArray:
    """Stack values into a float64 (M, *shape) array; rows that do not fit become NaN, ``ok[row] = False``.

    One ``np.array`` call when every value fits (the normal case), a per-value fallback otherwise.
    """
    n = len(values)
    try:
        stacked = np.array(values, dtype=np.float64)
        if stacked.shape == (n, *shape):
            return stacked
    except (TypeError, ValueError):
        pass
    out = np.full((n, *shape), np.nan)
    for i, value in enumerate(values):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            ok[i] = False
            continue
        if arr.shape == shape:
            out[i] = arr
        else:
            ok[i] = False
    return out


def stack_measurements(
    measurements: Iterable[Measurement], rejected: collections.Counter[str]
) -> MeasurementFrame:
    """Stack the well-formed measurements; count the others in ``rejected`` under the first check failed.

    Reasons: ``not_a_measurement``, ``bad_shape`` (wrong shape or a non-numeric value), ``non_finite``,
    ``bad_covariance`` (not symmetric positive definite), ``score_out_of_range``, ``bad_size`` (a box
    dimension <= 0), ``bad_range_rate`` (variance <= 0), ``unknown_modality``.
    """
    items = list(measurements)
    ms = [m for m in items if isinstance(m, Measurement)]
    if len(ms) < len(items):
        rejected["not_a_measurement"] += len(items) - len(ms)
    n = len(ms)
    if n == 0:
        return EMPTY_FRAME
    # Absent optional fields get finite placeholders that pass every check (flagged by has_*), so
    # one isfinite covers the whole frame; they become NaN ("unmeasured") at the end.
    shape_ok = np.ones(n, bool)
    pos = _stack([m.position_m for m in ms], (2,), shape_ok)
    cov = _stack([m.position_cov_m2 for m in ms], (2, 2), shape_ok)
    has_size = np.array([m.size_m is not None for m in ms], dtype=bool)
    size = _stack([_ONES3 if m.size_m is None else m.size_m for m in ms], (3,), shape_ok)
    has_yaw = np.array([m.yaw_rad is not None for m in ms], dtype=bool)
    yaw = _stack([0.0 if m.yaw_rad is None else m.yaw_rad for m in ms], (), shape_ok)
    mod_pi = np.array([bool(m.yaw_mod_pi) for m in ms], dtype=bool)
    z = _stack([m.z_m for m in ms], (), shape_ok)
    score = _stack([m.score for m in ms], (), shape_ok)

    has_rr = np.array([m.range_rate is not None for m in ms], dtype=bool)
    rr = np.zeros((n, 4))  # columns _RR_SENSOR (x, y), _RR_RATE, _RR_VAR
    rr[:, _RR_VAR] = 1.0
    for i in np.flatnonzero(has_rr).tolist():
        try:
            sensor, rate, var = ms[i].range_rate  # type: ignore[misc]
            sensor_xy = np.asarray(sensor, dtype=np.float64)
            rr[i, _RR_RATE], rr[i, _RR_VAR] = float(rate), float(var)
        except (TypeError, ValueError):
            shape_ok[i] = False
            continue
        if sensor_xy.shape == (2,):
            rr[i, _RR_SENSOR] = sensor_xy
        else:
            shape_ok[i] = False

    known_modality = np.ones(n, bool)
    modalities: list[frozenset[str]] = []
    sensor_ids: list[tuple[str, ...]] = []
    for i, m in enumerate(ms):
        mods, ids = m.modalities, m.sensor_ids
        try:
            mods = mods if type(mods) is frozenset else frozenset(mods)
            ids = ids if type(ids) is tuple else tuple(ids)
        except TypeError:
            shape_ok[i] = False
            mods, ids = frozenset(), ()
        known_modality[i] = mods <= MODALITIES
        modalities.append(mods)
        sensor_ids.append(ids)

    values = np.concatenate(
        [pos, cov.reshape(n, 4), size, rr, z[:, None], score[:, None], yaw[:, None]], axis=1
    )
    c00, c01, c10, c11 = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 0], cov[:, 1, 1]
    with np.errstate(invalid="ignore", over="ignore"):
        # Tolerant symmetry test: covariances often travel as float32.
        symmetric = np.abs(c01 - c10) <= 1e-6 * (np.abs(c00) + np.abs(c11))
        checks = (
            ("bad_shape", shape_ok),
            ("unknown_modality", known_modality),
            ("non_finite", np.isfinite(values).all(axis=1)),
            ("bad_covariance", symmetric & (c00 > 0.0) & (c11 > 0.0) & (c00 * c11 - c01 * c10 > 0.0)),
            ("score_out_of_range", (score >= 0.0) & (score <= 1.0)),
            ("bad_size", (size > 0.0).all(axis=1)),
            ("bad_range_rate", rr[:, _RR_VAR] > 0.0),
        )
    ok = checks[0][1].copy()
    for _, passed in checks[1:]:
        ok &= passed
    if not ok.all():
        # Count each rejected measurement once, under the first check it fails.
        pending = ~ok
        for reason, passed in checks:
            failed = pending & ~passed
            if failed.any():
                rejected[reason] += int(failed.sum())
                pending &= passed

    attrs = np.empty((n, N_ATTRS))
    attrs[:, Z] = z
    attrs[:, SCORE] = score
    attrs[:, SIZE] = size
    yaw = np.where(np.isfinite(yaw), yaw, 0.0)  # rejected rows: keep cos/sin quiet
    attrs[:, AXIS2] = np.column_stack([np.cos(2.0 * yaw), np.sin(2.0 * yaw)])
    attrs[:, HEAD] = np.column_stack([np.cos(yaw), np.sin(yaw)])
    if not has_size.all():
        attrs[~has_size, SIZE] = np.nan
    if not has_yaw.all():
        attrs[~has_yaw, AXIS2] = np.nan
    attrs[~has_yaw | mod_pi, HEAD] = np.nan
    if not has_rr.all():
        rr[~has_rr] = np.nan
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    if not ok.all():
        idx = np.flatnonzero(ok)
        keep = idx.tolist()
        modalities = [modalities[i] for i in keep]
        sensor_ids = [sensor_ids[i] for i in keep]
        pos, cov, attrs, rr = pos[idx], cov[idx], attrs[idx], rr[idx]
    return MeasurementFrame(
        pos, cov, attrs, rr[:, _RR_SENSOR], rr[:, _RR_RATE], rr[:, _RR_VAR], modalities, sensor_ids
    )
