"""The tracks as a struct of arrays (`TrackTable`), their lifecycle states and the published snapshot.

Rows are tracks; every column has the track index as its first axis, so predict / update / lifecycle run
vectorised and deletion compacts all columns together. `Track` is the immutable view handed out.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from shared.tracking.kalman import POS, VX, VY, FloatArray
from shared.tracking.measurement import N_ATTRS, SCORE, SIZE, NDBool, NDInt, Z


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


# Per-track columns, all with the track index as the first axis (compacted together on deletion).
_COLUMNS = ("ids", "state", "x", "P", "hits", "age", "misses", "attrs", "yaw", "sign_known", "last_update")


class TrackTable:
    """Struct-of-arrays storage of the tracks, so predict/update/lifecycle run vectorised."""

    def __init__(self) -> None:
        self.ids: NDInt = np.zeros(0, np.int64)
        self.state: NDInt = np.zeros(0, np.int64)
        self.x: FloatArray = np.zeros((0, 4))
        self.P: FloatArray = np.zeros((0, 4, 4))
        self.hits: NDInt = np.zeros(0, np.int64)
        self.age: NDInt = np.zeros(0, np.int64)
        self.misses: NDInt = np.zeros(0, np.int64)
        self.attrs: FloatArray = np.zeros((0, N_ATTRS))
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

    def append(self, other: TrackTable) -> None:
        for name in _COLUMNS:
            setattr(self, name, np.concatenate([getattr(self, name), getattr(other, name)]))
        self.modalities += other.modalities
        self.sensor_ids += other.sensor_ids

    def snapshot(self, idx: NDInt, confirm_hits: int, max_misses: int) -> list[Track]:
        """`Track` snapshots of the rows ``idx``; ``existence_probability`` from the lifecycle limits."""
        t = self
        if idx.size == 0:
            return []
        x, P, size = t.x[idx], t.P[idx], t.attrs[idx, SIZE]  # fancy indexing copies
        for a in (x, P, size):
            a.setflags(write=False)
        has_size = (~np.isnan(size[:, 0])).tolist()
        existence = (
            t.attrs[idx, SCORE]
            * np.minimum(1.0, t.hits[idx] / confirm_hits)
            * np.clip(1.0 - t.misses[idx] / (max_misses + 1.0), 0.0, 1.0)
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
                    t.attrs[idx, Z].tolist(),
                    t.sign_known[idx].tolist(),
                    t.hits[idx].tolist(),
                    t.age[idx].tolist(),
                    t.misses[idx].tolist(),
                    t.attrs[idx, SCORE].tolist(),
                    existence.tolist(),
                    t.last_update[idx].tolist(),
                    strict=True,
                )
            )
        ]


def ema(old: FloatArray, new: FloatArray, alpha: FloatArray) -> FloatArray:
    """Exponential average where both are known, the known one otherwise (NaN marks unknown)."""
    mixed = (1.0 - alpha) * old + alpha * new
    return np.where(np.isnan(old), new, np.where(np.isnan(new), old, mixed))
