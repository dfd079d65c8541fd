"""Multi-object tracker of the edge service: GNN association, Kalman filtering and a track lifecycle.

One :meth:`MultiObjectTracker.step` per fused frame: predict every track to the frame stamp, associate
the frame's measurements (one per object, already fused across sensors) by the Hungarian algorithm
inside a gate, update the matched tracks (position, then radar range rate), start tentative tracks on
the unmatched measurements and age the unmatched tracks. No bus, no clock: the caller passes stamps.

Lifecycle (paper: new objects are hidden for stability, lost objects dropped after 3 misses)
------------------------------------------------------------------------------------------
- A new track is TENTATIVE; its birth frame counts as hit 1 and age 1.
- TENTATIVE -> CONFIRMED once it has ``confirm_hits`` hits within its first ``confirm_window`` frames
  (M-of-N). It is deleted as soon as that has become impossible, i.e. when
  ``hits + (confirm_window - age_frames) < confirm_hits``; with the default 3-of-3 this is "deleted on
  its first miss", like the reference code's fresh tracks.
- A missed CONFIRMED track becomes COASTING (predicted only); a hit makes it CONFIRMED again. It is
  deleted when ``consecutive_misses > max_misses``: with the default 3 it coasts through 3 missed frames
  and is deleted on the 4th (the reference code's behaviour).
- Published tracks (:meth:`MultiObjectTracker.confirmed`, the return value of ``step``) are CONFIRMED and
  COASTING ones. Ids count up from 1 and are never reused.

Heading
-------
Yaw measurements known only modulo pi (our lidar boxes) are averaged as unit vectors of the doubled
angle, so 0.1 and 0.1 + pi reinforce instead of cancelling. The sign is taken, in this order, from
measured full headings (``yaw_mod_pi=False``), from the velocity when the track moves clearly (speed
above ``heading_from_velocity_min_mps`` and ``heading_min_speed_sigmas`` standard deviations of its
estimate), else from the previous frame's resolved heading (a stopped car keeps its heading). A track
never measured a yaw (radar or camera only) takes the velocity heading, or the previous one.
"""

from __future__ import annotations

import collections
import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.optimize import linear_sum_assignment

from shared.tracking import kalman
from shared.tracking.kalman import POS, VX, VY, FloatArray, MotionKind, MotionModel

__all__ = [
    "MODALITIES",
    "Measurement",
    "MultiObjectTracker",
    "RangeRate",
    "Track",
    "TrackState",
    "TrackerConfig",
]

CAMERA, LIDAR, RADAR = "camera", "lidar", "radar"  # sensor kinds, as the scene names them
MODALITIES: frozenset[str] = frozenset({CAMERA, LIDAR, RADAR})


class TrackerConfig(BaseModel):
    """Tracker parameters. Positions in world metres, times in seconds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    motion_model: MotionKind = Field(
        "constant_velocity",
        description="constant_velocity (state x, y, vx, vy) or identity (the paper's A = I: position random "
        "walk, velocity fixed at 0)",
    )
    accel_std_mps2: float = Field(
        0.5,
        ge=0,
        description="constant velocity: white-noise acceleration std, m/s² (cars reach ~0.6 m/s and turn on "
        "~0.5 m radii, ~0.7 m/s² lateral)",
    )
    identity_process_std_m: float = Field(
        0.3,
        ge=0,
        description="identity model: position random-walk std after 1 s, m (Q = std² · dt per axis)",
    )
    initial_velocity_std_mps: float = Field(
        0.5, gt=0, description="velocity std of a new track, m/s (cars drive at <= ~0.6 m/s)"
    )
    gate_m: float = Field(
        0.5,
        gt=0,
        description="association gate: Euclidean distance from the predicted position, m (paper 0.5)",
    )
    gate_mahalanobis: float | None = Field(
        None,
        gt=0,
        description="optional second gate: chi² threshold (2 dof, e.g. 9.21 for 99 %) on the squared "
        "Mahalanobis distance of the position innovation; when set it is also the assignment cost",
    )
    confirm_hits: int = Field(3, ge=1, description="hits that confirm a tentative track (M of M-of-N)")
    confirm_window: int = Field(
        3,
        ge=1,
        description="frames since birth within which confirm_hits must occur (N of M-of-N); a tentative "
        "track is deleted once it cannot make it, so N = M deletes it on its first miss",
    )
    max_misses: int = Field(
        3,
        ge=0,
        description="consecutive missed frames a confirmed track coasts through; deleted on the next miss",
    )
    z_smoothing: float = Field(
        0.3, gt=0, le=1, description="weight of a new height measurement in the exponential average (1: none)"
    )
    size_smoothing: float = Field(
        0.2, gt=0, le=1, description="weight of a new box size in the exponential average (1: none)"
    )
    yaw_smoothing: float = Field(
        0.3,
        gt=0,
        le=1,
        description="weight of a new yaw in the exponential circular mean (of 2·yaw for yaw known mod pi)",
    )
    score_smoothing: float = Field(
        0.3, gt=0, le=1, description="weight of a new detection score in the exponential average (1: none)"
    )
    heading_from_velocity_min_mps: float = Field(
        0.05, ge=0, description="the velocity sets the heading sign only above this speed, m/s"
    )
    heading_min_speed_sigmas: float = Field(
        3.0,
        ge=0,
        description="... and only when the speed exceeds this many stds of its estimate (0: off), so a "
        "stopped car's velocity noise does not flip its heading",
    )
    range_rate_min_range_m: float = Field(
        0.05, gt=0, description="range-rate updates are skipped for targets closer to the radar, m"
    )
    max_tracks: int = Field(
        256, gt=0, description="tracks kept at most; further births are dropped (rejected['track_limit'])"
    )

    @model_validator(mode="after")
    def _window_fits_hits(self) -> TrackerConfig:
        if self.confirm_window < self.confirm_hits:
            raise ValueError(
                f"confirm_window ({self.confirm_window}) must be >= confirm_hits ({self.confirm_hits})"
            )
        return self

    def motion(self) -> MotionModel:
        """The Kalman process model these parameters describe."""
        return MotionModel(self.motion_model, self.accel_std_mps2, self.identity_process_std_m)


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


class TrackState(enum.IntEnum):
    """Lifecycle state of a track."""

    TENTATIVE = 0
    CONFIRMED = 1
    COASTING = 2


_STATES = tuple(TrackState)


@dataclass(slots=True, eq=False)
class Track:
    """Snapshot of one track after a step: a new object each step that the tracker never touches again
    (not frozen only because a frozen dataclass costs ~1 µs more per track to build); arrays are
    read-only copies.

    Attributes
    ----------
    track_id : int
        Unique id, counting from 1, never reused.
    state : TrackState
    x : numpy.ndarray, shape (4,)
        [x, y, vx, vy], world m and m/s.
    P : numpy.ndarray, shape (4, 4)
        Covariance of ``x``.
    z_m : float
        Smoothed centre height, m.
    size_m : numpy.ndarray, shape (3,), or None
        Smoothed length, width, height, m; None until a box was measured.
    yaw_rad : float or None
        Heading in (-pi, pi], rad; None when neither a yaw nor a clear motion was ever seen.
    heading_sign_known : bool
        False when ``yaw_rad`` is only known modulo pi (then it lies in (-pi/2, pi/2]).
    hits, age_frames, consecutive_misses : int
        Frames with an update, frames since birth (birth = 1), missed frames in a row.
    modalities : frozenset of str
        Sensor kinds of the latest update; empty when the track was missed this frame.
    sensor_ids : tuple of str
        Sensors of the latest update; empty when missed.
    score : float
        Smoothed detection score in [0, 1].
    existence_probability : float
        Heuristic in [0, 1]: ``score · min(1, hits / confirm_hits) · (1 - misses / (max_misses + 1))``.
        Not calibrated; it falls to 0 as the track reaches deletion.
    last_update_stamp_s : float
        Stamp of the latest update, s.
    """

    track_id: int
    state: TrackState
    x: FloatArray
    P: FloatArray
    z_m: float
    size_m: FloatArray | None
    yaw_rad: float | None
    heading_sign_known: bool
    hits: int
    age_frames: int
    consecutive_misses: int
    modalities: frozenset[str]
    sensor_ids: tuple[str, ...]
    score: float
    existence_probability: float
    last_update_stamp_s: float

    @property
    def position_m(self) -> FloatArray:
        """(2,) world x, y, m."""
        return self.x[POS]

    @property
    def velocity_mps(self) -> FloatArray:
        """(2,) world vx, vy, m/s."""
        return self.x[2:]

    @property
    def speed_mps(self) -> float:
        return math.hypot(float(self.x[VX]), float(self.x[VY]))

    @property
    def position_cov_m2(self) -> FloatArray:
        """(2, 2) position covariance, m²."""
        return self.P[:2, :2]

    @property
    def velocity_cov_m2ps2(self) -> FloatArray:
        """(2, 2) velocity covariance, m²/s²."""
        return self.P[2:, 2:]


NDBool = np.ndarray[Any, np.dtype[np.bool_]]
NDInt = np.ndarray[Any, np.dtype[np.int64]]


class _Frame(NamedTuple):
    """The valid measurements of one step, stacked (M rows)."""

    pos: FloatArray  # (M, 2)
    cov: FloatArray  # (M, 2, 2)
    attrs: FloatArray  # (M, _N_ATTRS): columns _Z, _SCORE, _SIZE, _AXIS2, _HEAD; NaN where unmeasured
    rr_xy: FloatArray  # (M, 2), NaN without a range rate
    rr: FloatArray  # (M,), NaN without a range rate
    rr_var: FloatArray  # (M,)
    modalities: list[frozenset[str]]
    sensor_ids: list[tuple[str, ...]]


# Smoothed per-track attributes share one array so a single exponential average updates them all:
# height, score, box size (3), mean of (cos 2yaw, sin 2yaw) over every yaw, mean of (cos yaw, sin yaw)
# over full headings. NaN: never measured.
_Z, _SCORE = 0, 1
_SIZE = slice(2, 5)
_AXIS2 = slice(5, 7)
_HEAD = slice(7, 9)
_N_ATTRS = 9
_COS, _SIN = 0, 1  # within _AXIS2 and _HEAD
# A measured range rate: the radar's x, y (m), the rate (m/s) and its variance (m²/s²).
_RR_SENSOR, _RR_RATE, _RR_VAR = slice(0, 2), 2, 3

_EMPTY_FRAME = _Frame(
    np.zeros((0, 2)),
    np.zeros((0, 2, 2)),
    np.zeros((0, _N_ATTRS)),
    np.zeros((0, 2)),
    np.zeros(0),
    np.zeros(0),
    [],
    [],
)

# Per-track columns, all with the track index as the first axis (compacted together on deletion).
_COLUMNS = ("ids", "state", "x", "P", "hits", "age", "misses", "attrs", "yaw", "sign_known", "last_update")


class _Table:
    """Struct-of-arrays storage of the tracks, so predict/update/lifecycle run vectorised."""

    def __init__(self) -> None:
        self.ids: NDInt = np.zeros(0, np.int64)
        self.state: NDInt = np.zeros(0, np.int64)
        self.x: FloatArray = np.zeros((0, 4))
        self.P: FloatArray = np.zeros((0, 4, 4))
        self.hits: NDInt = np.zeros(0, np.int64)
        self.age: NDInt = np.zeros(0, np.int64)
        self.misses: NDInt = np.zeros(0, np.int64)
        self.attrs: FloatArray = np.zeros((0, _N_ATTRS))
        self.yaw: FloatArray = np.zeros(0)  # resolved output yaw; NaN: unknown
        self.sign_known: NDBool = np.zeros(0, bool)
        self.last_update: FloatArray = np.zeros(0)
        self.modalities: list[frozenset[str]] = []
        self.sensor_ids: list[tuple[str, ...]] = []

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def keep(self, mask: NDBool) -> None:
        for name in _COLUMNS:
            setattr(self, name, getattr(self, name)[mask])
        idx = np.flatnonzero(mask).tolist()
        self.modalities = [self.modalities[i] for i in idx]
        self.sensor_ids = [self.sensor_ids[i] for i in idx]

    def append(self, other: _Table) -> None:
        for name in _COLUMNS:
            setattr(self, name, np.concatenate([getattr(self, name), getattr(other, name)]))
        self.modalities += other.modalities
        self.sensor_ids += other.sensor_ids


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


def _ema(old: FloatArray, new: FloatArray, alpha: FloatArray) -> FloatArray:
    """Exponential average where both are known, the known one otherwise (NaN marks unknown)."""
    mixed = (1.0 - alpha) * old + alpha * new
    return np.where(np.isnan(old), new, np.where(np.isnan(new), old, mixed))


def _wrap(a: FloatArray) -> FloatArray:
    # Same convention as shared.geometry.transforms.wrap_angle, (-pi, pi], but NaN-tolerant.
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


class MultiObjectTracker:
    """GNN multi-object tracker on a batched Kalman filter (see the module docstring).

    Parameters
    ----------
    config : TrackerConfig, optional
        Parameters; defaults follow the paper (0.5 m gate, 3 misses) with a constant-velocity model.

    Attributes
    ----------
    rejected : collections.Counter of str
        Inputs ignored, by reason: ``out_of_order_stamp`` and ``non_finite_stamp`` (whole steps);
        per measurement ``not_a_measurement``, ``bad_shape`` (wrong shape or a non-numeric value),
        ``non_finite``, ``bad_covariance`` (not symmetric positive definite), ``score_out_of_range``,
        ``bad_size`` (a box dimension <= 0), ``bad_range_rate`` (variance <= 0), ``unknown_modality``;
        ``track_limit`` for births over ``max_tracks``.
    """

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self._model = self.config.motion()
        c = self.config
        self._alphas = np.array(
            [c.z_smoothing, c.score_smoothing, *[c.size_smoothing] * 3, *[c.yaw_smoothing] * 4]
        )
        self.rejected: collections.Counter[str] = collections.Counter()
        self._next_id = 1
        self._tracks = _Table()
        self._last_stamp_s: float | None = None

    def reset(self) -> None:
        """Drop every track and the last stamp; ids keep counting (never reused) and ``rejected`` stays."""
        self._tracks = _Table()
        self._last_stamp_s = None

    @property
    def last_stamp_s(self) -> float | None:
        """Stamp of the last accepted step, s (None before the first)."""
        return self._last_stamp_s

    def __len__(self) -> int:
        return len(self._tracks)

    # --- public ----------------------------------------------------------------------------------------

    def step(self, stamp_s: float, measurements: Iterable[Measurement]) -> list[Track]:
        """Advance the tracks to ``stamp_s`` and fuse one frame of measurements.

        Parameters
        ----------
        stamp_s : float
            Frame time, s. Tracks are predicted by the time since the previous accepted step (not on the
            first step, nor when it is 0). A stamp older than the previous one is rejected: nothing
            changes and ``rejected['out_of_order_stamp']`` counts it.
        measurements : iterable of Measurement
            The frame's objects, at most one per real object. Malformed ones are skipped and counted.

        Returns
        -------
        list of Track
            The published tracks (CONFIRMED and COASTING) after the step, by id.
        """
        try:
            stamp = float(stamp_s)
        except (TypeError, ValueError):
            stamp = math.nan
        if not math.isfinite(stamp):
            self.rejected["non_finite_stamp"] += 1
            return self.confirmed()
        if self._last_stamp_s is not None and stamp < self._last_stamp_s:
            self.rejected["out_of_order_stamp"] += 1
            return self.confirmed()

        frame = self._validate(measurements)
        t = self._tracks
        if self._last_stamp_s is not None and stamp > self._last_stamp_s and len(t):
            t.x, t.P = kalman.predict(t.x, t.P, stamp - self._last_stamp_s, self._model)
        self._last_stamp_s = stamp

        rows, cols = self._associate(frame)
        self._update_matched(rows, cols, frame, stamp)
        self._age(rows)
        births = np.ones(frame.pos.shape[0], bool)
        births[cols] = False
        self._birth(np.flatnonzero(births), frame, stamp)
        self._resolve_yaw()
        return self.confirmed()

    def confirmed(self) -> list[Track]:
        """Tracks to publish: CONFIRMED and COASTING (tentative ones are hidden, as in the paper)."""
        return self._snapshot(np.flatnonzero(self._tracks.state != TrackState.TENTATIVE))

    def all_tracks(self) -> list[Track]:
        """Every track, tentative ones included (diagnostics)."""
        return self._snapshot(np.arange(len(self._tracks)))

    # --- steps -----------------------------------------------------------------------------------------

    def _validate(self, measurements: Iterable[Measurement]) -> _Frame:
        """Stack the well-formed measurements; count the others in ``rejected`` (first failed check)."""
        items = list(measurements)
        ms = [m for m in items if isinstance(m, Measurement)]
        if len(ms) < len(items):
            self.rejected["not_a_measurement"] += len(items) - len(ms)
        n = len(ms)
        if n == 0:
            return _EMPTY_FRAME
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
                    self.rejected[reason] += int(failed.sum())
                    pending &= passed

        attrs = np.empty((n, _N_ATTRS))
        attrs[:, _Z] = z
        attrs[:, _SCORE] = score
        attrs[:, _SIZE] = size
        yaw = np.where(np.isfinite(yaw), yaw, 0.0)  # rejected rows: keep cos/sin quiet
        attrs[:, _AXIS2] = np.column_stack([np.cos(2.0 * yaw), np.sin(2.0 * yaw)])
        attrs[:, _HEAD] = np.column_stack([np.cos(yaw), np.sin(yaw)])
        if not has_size.all():
            attrs[~has_size, _SIZE] = np.nan
        if not has_yaw.all():
            attrs[~has_yaw, _AXIS2] = np.nan
        attrs[~has_yaw | mod_pi, _HEAD] = np.nan
        if not has_rr.all():
            rr[~has_rr] = np.nan
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
        if not ok.all():
            idx = np.flatnonzero(ok)
            keep = idx.tolist()
            modalities = [modalities[i] for i in keep]
            sensor_ids = [sensor_ids[i] for i in keep]
            pos, cov, attrs, rr = pos[idx], cov[idx], attrs[idx], rr[idx]
        return _Frame(
            pos, cov, attrs, rr[:, _RR_SENSOR], rr[:, _RR_RATE], rr[:, _RR_VAR], modalities, sensor_ids
        )

    def _associate(self, frame: _Frame) -> tuple[NDInt, NDInt]:
        """Global nearest neighbour: Hungarian on gated costs; returns matched (track, measurement) rows."""
        t = self._tracks
        empty = np.zeros(0, np.int64)
        if len(t) == 0 or frame.pos.shape[0] == 0:
            return empty, empty
        diff = frame.pos[None, :, :] - t.x[:, None, POS]  # (N, M, 2)
        cost = np.hypot(diff[..., 0], diff[..., 1])
        feasible = cost <= self.config.gate_m
        if self.config.gate_mahalanobis is not None:
            S = t.P[:, None, :2, :2] + frame.cov[None]  # (N, M, 2, 2), symmetric positive definite
            a, b, d = S[..., 0, 0], S[..., 0, 1], S[..., 1, 1]
            dx, dy = diff[..., 0], diff[..., 1]
            cost = (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)
            feasible &= cost <= self.config.gate_mahalanobis
        if not feasible.any():
            return empty, empty
        # Infeasible pairs cost more than all feasible ones together, so the assignment first maximises
        # the number of gated matches, then minimises their total cost.
        big = 1.0 + float(cost[feasible].sum())
        rows, cols = linear_sum_assignment(np.where(feasible, cost, big))
        keep = feasible[rows, cols]
        return rows[keep].astype(np.int64), cols[keep].astype(np.int64)

    def _update_matched(self, rows: NDInt, cols: NDInt, frame: _Frame, stamp: float) -> None:
        if rows.size == 0:
            return
        t = self._tracks
        x, P, _, _ = kalman.update(t.x[rows], t.P[rows], frame.pos[cols], kalman.POSITION_H, frame.cov[cols])
        x, P = self._range_rate_update(x, P, cols, frame)
        t.x[rows], t.P[rows] = x, P
        t.attrs[rows] = _ema(t.attrs[rows], frame.attrs[cols], self._alphas)
        t.last_update[rows] = stamp
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            t.modalities[r] = frame.modalities[c]
            t.sensor_ids[r] = frame.sensor_ids[c]

    def _range_rate_update(
        self, x: FloatArray, P: FloatArray, cols: NDInt, frame: _Frame
    ) -> tuple[FloatArray, FloatArray]:
        """EKF range-rate update of the rows of ``x``/``P`` whose measurement ``cols`` carries one."""
        if self._model.kind != "constant_velocity":
            return x, P  # the identity model has no velocity to correct (the update would be a no-op)
        sub = np.flatnonzero(~np.isnan(frame.rr[cols]))
        if sub.size:
            c = cols[sub]
            upd = kalman.update_range_rate(
                x[sub],
                P[sub],
                frame.rr_xy[c],
                frame.rr[c],
                frame.rr_var[c],
                self.config.range_rate_min_range_m,
            )
            x[sub], P[sub] = upd.x, upd.P
        return x, P

    def _age(self, rows: NDInt) -> None:
        """Count hits and misses of the existing tracks, move their states on, delete the lost ones."""
        t = self._tracks
        if len(t) == 0:
            return
        cfg = self.config
        hit = np.zeros(len(t), bool)
        hit[rows] = True
        t.age += 1
        t.hits += hit
        t.misses = np.where(hit, 0, t.misses + 1)
        tentative = t.state == TrackState.TENTATIVE
        t.state = np.where(
            tentative,
            np.where(t.hits >= cfg.confirm_hits, TrackState.CONFIRMED, TrackState.TENTATIVE),
            np.where(hit, TrackState.CONFIRMED, TrackState.COASTING),
        ).astype(np.int64)
        for i in np.flatnonzero(~hit).tolist():
            t.modalities[i] = frozenset()
            t.sensor_ids[i] = ()
        unreachable = tentative & (t.hits + (cfg.confirm_window - t.age) < cfg.confirm_hits)
        dead = unreachable | (~tentative & (t.misses > cfg.max_misses))
        if dead.any():
            t.keep(~dead)

    def _birth(self, idx: NDInt, frame: _Frame, stamp: float) -> None:
        """Start tentative tracks on the unmatched measurements ``idx``."""
        room = max(self.config.max_tracks - len(self._tracks), 0)
        if idx.size > room:
            self.rejected["track_limit"] += int(idx.size - room)
            idx = idx[:room]
        k = int(idx.size)
        if k == 0:
            return
        cfg = self.config
        new = _Table()
        new.ids = np.arange(self._next_id, self._next_id + k, dtype=np.int64)
        self._next_id += k
        state = TrackState.CONFIRMED if cfg.confirm_hits <= 1 else TrackState.TENTATIVE
        new.state = np.full(k, state, np.int64)
        x = np.zeros((k, 4))
        x[:, :2] = frame.pos[idx]
        # Block diagonal, no position-velocity correlation (the reference's full 1e6 matrix was a bug).
        P = np.zeros((k, 4, 4))
        P[:, :2, :2] = frame.cov[idx]
        if self._model.kind == "constant_velocity":
            P[:, VX, VX] = P[:, VY, VY] = cfg.initial_velocity_std_mps**2
        # A radar birth starts from the measured radial velocity (shrunk towards 0 by the prior).
        new.x, new.P = self._range_rate_update(x, P, idx, frame)
        new.hits = np.ones(k, np.int64)
        new.age = np.ones(k, np.int64)
        new.misses = np.zeros(k, np.int64)
        new.attrs = frame.attrs[idx]
        new.yaw = np.full(k, np.nan)
        new.sign_known = np.zeros(k, bool)
        new.last_update = np.full(k, stamp)
        keep = idx.tolist()
        new.modalities = [frame.modalities[i] for i in keep]
        new.sensor_ids = [frame.sensor_ids[i] for i in keep]
        self._tracks.append(new)

    def _resolve_yaw(self) -> None:
        """Output yaw of every track: measured axis, sign from heading / motion / previous frame."""
        t = self._tracks
        if len(t) == 0:
            return
        cfg = self.config
        vx, vy = t.x[:, VX], t.x[:, VY]
        speed = np.hypot(vx, vy)
        speed_std = np.sqrt(np.maximum(0.5 * (t.P[:, VX, VX] + t.P[:, VY, VY]), 0.0))
        moving = speed > np.maximum(
            cfg.heading_from_velocity_min_mps, cfg.heading_min_speed_sigmas * speed_std
        )
        head, axis2 = t.attrs[:, _HEAD], t.attrs[:, _AXIS2]
        ref = np.where(
            ~np.isnan(head[:, _COS]),
            np.arctan2(head[:, _SIN], head[:, _COS]),
            np.where(moving, np.arctan2(vy, vx), np.where(t.sign_known, t.yaw, np.nan)),
        )
        has_ref = ~np.isnan(ref)
        axis = 0.5 * np.arctan2(axis2[:, _SIN], axis2[:, _COS])  # (-pi/2, pi/2]; NaN if never measured
        flip = np.abs(_wrap(np.where(has_ref, ref, 0.0) - axis)) > 0.5 * np.pi
        t.yaw = np.where(np.isnan(axis), ref, _wrap(axis + np.pi * (flip & has_ref)))
        t.sign_known = has_ref

    # --- output ----------------------------------------------------------------------------------------

    def _snapshot(self, idx: NDInt) -> list[Track]:
        t = self._tracks
        if idx.size == 0:
            return []
        cfg = self.config
        x, P, size = t.x[idx], t.P[idx], t.attrs[idx, _SIZE]  # fancy indexing copies
        for a in (x, P, size):
            a.setflags(write=False)
        has_size = (~np.isnan(size[:, 0])).tolist()
        existence = (
            t.attrs[idx, _SCORE]
            * np.minimum(1.0, t.hits[idx] / cfg.confirm_hits)
            * np.clip(1.0 - t.misses[idx] / (cfg.max_misses + 1.0), 0.0, 1.0)
        )
        yaw = [None if math.isnan(v) else v for v in t.yaw[idx].tolist()]
        modalities, sensor_ids = t.modalities, t.sensor_ids
        return [
            Track(
                track_id,
                _STATES[state],
                x[k],
                P[k],
                z_m,
                size[k] if has_size[k] else None,
                yaw[k],
                sign,
                hits,
                age,
                misses,
                modalities[i],
                sensor_ids[i],
                score,
                p_exist,
                last,
            )
            for k, (i, track_id, state, z_m, sign, hits, age, misses, score, p_exist, last) in enumerate(
                zip(
                    idx.tolist(),
                    t.ids[idx].tolist(),
                    t.state[idx].tolist(),
                    t.attrs[idx, _Z].tolist(),
                    t.sign_known[idx].tolist(),
                    t.hits[idx].tolist(),
                    t.age[idx].tolist(),
                    t.misses[idx].tolist(),
                    t.attrs[idx, _SCORE].tolist(),
                    existence.tolist(),
                    t.last_update[idx].tolist(),
                    strict=True,
                )
            )
        ]
