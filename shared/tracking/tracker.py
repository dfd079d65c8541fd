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

Modules
-------
What one step does lives beside this file: `measurement` (the input and its validation), `association`
(gated Hungarian), `kalman` (motion model, updates), `track_table` (per-track columns, lifecycle
states, snapshots) and `heading` (yaw sign from heading, motion or the previous frame).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.scene.scale import Acceleration, Length, Speed
from shared.tracking import kalman
from shared.tracking.association import associate
from shared.tracking.heading import resolve_yaw
from shared.tracking.kalman import POS, VX, VY, FloatArray, MotionKind, MotionModel
from shared.tracking.measurement import Measurement, MeasurementFrame, NDInt, stack_measurements
from shared.tracking.track_table import Track, TrackState, TrackTable, ema


class TrackerConfig(BaseModel):
    """Tracker parameters. Positions in world metres, times in seconds."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    motion_model: MotionKind = Field(
        "constant_velocity",
        description="constant_velocity (state x, y, vx, vy) or identity (the paper's A = I: position random "
        "walk, velocity fixed at 0)",
    )
    accel_std_mps2: Acceleration = Field(
        0.5,
        ge=0,
        description="constant velocity: white-noise acceleration std, m/s² (cars reach ~0.6 m/s and turn on "
        "~0.5 m radii, ~0.7 m/s² lateral)",
    )
    identity_process_std_m: Length = Field(
        0.3,
        ge=0,
        description="identity model: position random-walk std after 1 s, m (Q = std² · dt per axis)",
    )
    initial_velocity_std_mps: Speed = Field(
        0.5, gt=0, description="velocity std of a new track, m/s (cars drive at <= ~0.6 m/s)"
    )
    gate_m: Length = Field(
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
    heading_from_velocity_min_mps: Speed = Field(
        0.05, ge=0, description="the velocity sets the heading sign only above this speed, m/s"
    )
    heading_min_speed_sigmas: float = Field(
        3.0,
        ge=0,
        description="... and only when the speed exceeds this many stds of its estimate (0: off), so a "
        "stopped car's velocity noise does not flip its heading",
    )
    range_rate_min_range_m: Length = Field(
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
        self._tracks = TrackTable()
        self._last_stamp_s: float | None = None

    def reset(self) -> None:
        """Drop every track and the last stamp; ids keep counting (never reused) and ``rejected`` stays."""
        self._tracks = TrackTable()
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

        frame = stack_measurements(measurements, self.rejected)
        t = self._tracks
        if self._last_stamp_s is not None and stamp > self._last_stamp_s and len(t):
            t.x, t.P = kalman.predict(t.x, t.P, stamp - self._last_stamp_s, self._model)
        self._last_stamp_s = stamp

        rows, cols = associate(
            t.x[:, POS],
            t.P[:, POS, POS],
            frame.pos,
            frame.cov,
            gate_m=self.config.gate_m,
            gate_mahalanobis=self.config.gate_mahalanobis,
        )
        self._update_matched(rows, cols, frame, stamp)
        self._age(rows)
        births = np.ones(frame.pos.shape[0], bool)
        births[cols] = False
        self._birth(np.flatnonzero(births), frame, stamp)
        self._resolve_yaw()
        return self.confirmed()

    def coast(self, stamp_s: float) -> list[Track]:
        """Advance the tracks to ``stamp_s`` on their motion model alone: a frame no sensor delivered
        (every input late or missing) is no evidence against any track, so nothing is missed, aged,
        born or deleted. Non-finite or out-of-order stamps are rejected and counted as in `step`."""
        stamp = float(stamp_s)
        if not math.isfinite(stamp):
            self.rejected["non_finite_stamp"] += 1
        elif self._last_stamp_s is not None and stamp < self._last_stamp_s:
            self.rejected["out_of_order_stamp"] += 1
        else:
            t = self._tracks
            if self._last_stamp_s is not None and stamp > self._last_stamp_s and len(t):
                t.x, t.P = kalman.predict(t.x, t.P, stamp - self._last_stamp_s, self._model)
            self._last_stamp_s = stamp
        return self.confirmed()

    def confirmed(self) -> list[Track]:
        """Tracks to publish: CONFIRMED and COASTING (tentative ones are hidden, as in the paper)."""
        return self._snapshot(np.flatnonzero(self._tracks.state != TrackState.TENTATIVE))

    def all_tracks(self) -> list[Track]:
        """Every track, tentative ones included (diagnostics)."""
        return self._snapshot(np.arange(len(self._tracks)))

    # --- steps -----------------------------------------------------------------------------------------

    def _update_matched(self, rows: NDInt, cols: NDInt, frame: MeasurementFrame, stamp: float) -> None:
        if rows.size == 0:
            return
        t = self._tracks
        x, P, _, _ = kalman.update(t.x[rows], t.P[rows], frame.pos[cols], kalman.POSITION_H, frame.cov[cols])
        x, P = self._range_rate_update(x, P, cols, frame)
        t.x[rows], t.P[rows] = x, P
        t.attrs[rows] = ema(t.attrs[rows], frame.attrs[cols], self._alphas)
        t.last_update[rows] = stamp
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            t.modalities[r] = frame.modalities[c]
            t.sensor_ids[r] = frame.sensor_ids[c]

    def _range_rate_update(
        self, x: FloatArray, P: FloatArray, cols: NDInt, frame: MeasurementFrame
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

    def _birth(self, idx: NDInt, frame: MeasurementFrame, stamp: float) -> None:
        """Start tentative tracks on the unmatched measurements ``idx``."""
        room = max(self.config.max_tracks - len(self._tracks), 0)
        if idx.size > room:
            self.rejected["track_limit"] += int(idx.size - room)
            idx = idx[:room]
        k = int(idx.size)
        if k == 0:
            return
        cfg = self.config
        new = TrackTable()
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
        t = self._tracks
        if len(t) == 0:
            return
        t.yaw, t.sign_known = resolve_yaw(
            t.x,
            t.P,
            t.attrs,
            t.yaw,
            t.sign_known,
            min_speed_mps=self.config.heading_from_velocity_min_mps,
            min_speed_sigmas=self.config.heading_min_speed_sigmas,
        )

    # --- output ----------------------------------------------------------------------------------------

    def _snapshot(self, idx: NDInt) -> list[Track]:
        return self._tracks.snapshot(idx, self.config.confirm_hits, self.config.max_misses)
