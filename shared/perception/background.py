"""Background model of a roadside lidar's static scene: what is always there is not a vehicle.

A pole-mounted lidar sees the same ground, buildings, trees, poles and signs on every revolution. Each of
its rays (a cell of its range image: channel x azimuth bin) keeps a histogram of the ranges it returned,
on log-spaced range bins, as exponentially weighted frequencies: the weight of a bin is the share of
recent revolutions in which the ray returned there. The ray's *background* is the nearest range bin
whose share reaches ``background_fraction``: the ground or a wall (nearly every revolution), a tree's
leaves (often enough, even though the ray sometimes passes through). A return nearer than its ray's
background by more than ``margin_bins`` is *foreground* (a vehicle, a pedestrian); a ray with no
background (it never hits anything, e.g. above the horizon) makes every return foreground.

Learning
--------
- From nothing, online: the first ``warmup_frames`` revolutions are averaged with equal weight (the
  shares are exact frequencies), and no point is called foreground until then.
- Then slowly: each revolution adds ``learn_rate`` to the bin it returned in and decays the rest, so a
  new static object (a skip, road works) becomes background (time constant 1 / learn_rate revolutions).
  The points on a detected vehicle are learned as returns at their ray's background (`learn(xyz,
  hidden)`): a vehicle hides the background, it does not replace it. Without that, the rays over a
  stop line where one queued car follows another reach the 15 % share within a minute (1 - (1 -
  learn_rate)^n = 0.15 after n = 325 revolutions, 33 s at 10 Hz) and the cars waiting there are no
  longer seen (tests/shared/perception/test_background.py). A parked car, detected, stays a vehicle.
- A ray that returns *farther* than its background on ``clear_after_frames`` revolutions in a row saw
  through it: its nearer bins are forgotten, so the background of an object that left (a skip, a
  parked car never detected) goes in seconds, not minutes. A porous tree, seen through now and then
  but not for that many revolutions in a row, keeps its share.
- Saved with the site (`save` / `load`, a NumPy .npz), e.g. learned from a recorded empty period.

Units: metres, radians; points in the lidar's own frame (+x forward, z up), as the sensor sends them.
Cost: O(points) NumPy per revolution: each point's cell and range bin, one comparison, one histogram
update; the decay of all weights is a running scale, not a pass over them, and one of ``refresh_frames``
blocks of rays has its background re-derived per revolution (each ray every ``refresh_frames``), so no
revolution pays for the whole image.
"""

from __future__ import annotations

import logging
import math
import zipfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.detection.lidar.ground import Plane, fit_ground_plane
from shared.devices.robosense import MODELS
from shared.paths import DEPLOY_DIR
from shared.scene.model import LidarModel

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

MODEL_FORMAT = 1  # version of the saved model's layout
#: Where the MEC looks for a site's saved backgrounds, per scene (`BackgroundConfig.models_dir`).
BACKGROUND_MODELS_DIR = DEPLOY_DIR / "models" / "background"
# The weights' running scale is folded back in above this (float32 keeps 7 digits: the shares of ~1e-4
# that matter stay exact relative to it); at the default learn rate every ~28 000 revolutions.
_RESCALE_ABOVE = 1e6
# learn_period: a warm-up no period reaches (an equal-weight average of every revolution).
_WHOLE_PERIOD = 2**62


class BackgroundConfig(BaseModel):
    """Settings of `RangeBackground` (scale-free: ranges are binned relative to the lidar's own span)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    range_bins: int = Field(
        256,
        ge=8,
        le=1024,
        description="log-spaced range bins over the lidar's span (0.4-120 m: 2.2 % of the range each). A "
        "car's side seen from a pole stands in front of the ground by the share its height is of the "
        "pole's: from 8 m, 0.35 m up is 4.4 %, two bins; with 128 bins (4.5 %) and a 2-bin margin only "
        "65 % of a car's points at the intersection were foreground, with 256 and 1 bin 99 %",
    )
    warmup_frames: int = Field(
        30, ge=1, description="revolutions averaged with equal weight before any point is called foreground"
    )
    learn_rate: float = Field(
        0.0005,
        gt=0,
        lt=1,
        description="weight of a new revolution after warm-up: a static object standing for ~1 / rate "
        "revolutions (200 s at 10 Hz) joins the background (the points on detected vehicles are not "
        "learned as they are: `RangeBackground.learn`)",
    )
    clear_after_frames: int = Field(
        20,
        ge=1,
        description="revolutions in a row a ray must return beyond its background before the nearer bins "
        "are forgotten (a parked car that left; a tree seen through 40 % of the time: 0.4^20 ~ 1e-8)",
    )
    background_fraction: float = Field(
        0.15, gt=0, lt=1, description="a range returned in at least this share of revolutions is background"
    )
    margin_bins: int = Field(
        1,
        ge=0,
        description="foreground: nearer than the background by more than this many range bins (0: the "
        "range noise of the near ground crosses into the bin in front, ~70 false points a revolution at "
        "the intersection; 1: ~3)",
    )
    refresh_frames: int = Field(10, ge=1, description="the background is re-derived every n revolutions")
    vehicle_growth: float = Field(
        0.1,
        ge=0,
        description="a point within a detected vehicle's box grown by this share of its length and width "
        "is on the vehicle: learned as its ray's background (`RangeBackground.learn`)",
    )
    ground_refit_frames: int = Field(
        100,
        ge=1,
        description="the ground plane is fitted again to the static points every n revolutions (a slow "
        "change: the learned background), `AgentGround`",
    )
    ground_sample_points: int = Field(
        5000,
        ge=3,
        description="static points (a random subset of the rays' backgrounds) the ground is fitted to",
    )
    ground_iterations: int = Field(200, ge=1, description="RANSAC hypotheses of the ground fit")
    models_dir: Path | None = Field(
        BACKGROUND_MODELS_DIR,
        description="saved models to start from, `<scene id>/<lidar id>.npz` each (`rmmdet background "
        "learn` writes them, from a simulated or recorded period); a lidar without one learns online; "
        "null: always online",
    )


@dataclass(frozen=True)
class RangeImage:
    """The ray layout of one lidar: its channels' elevations and its azimuth bins."""

    elevations_rad: FloatArray  # (C,) ascending
    azimuth_bins: int
    min_range_m: float
    max_range_m: float

    @classmethod
    def of(cls, model: LidarModel) -> RangeImage:
        if model.device is not None:
            elevations = np.sort(np.radians(np.asarray(MODELS[model.device].example_vertical_deg, float)))
        else:
            lo, hi = model.vertical_range_rad
            elevations = np.linspace(lo, hi, model.channels)
        return cls(elevations, model.horizontal_samples, max(model.min_range_m, 1e-3), model.max_range_m)

    def ray_points(self, cells: IntArray, range_m: FloatArray) -> FloatArray:
        """(N, 3) points at `range_m` along the centre ray of each of the cells (channel x azimuth bin)."""
        channel, column = np.divmod(cells, self.azimuth_bins)
        elevation = self.elevations_rad[channel]
        azimuth = (column + 0.5) / self.azimuth_bins * 2 * math.pi - math.pi
        flat = range_m * np.cos(elevation)
        return np.column_stack([flat * np.cos(azimuth), flat * np.sin(azimuth), range_m * np.sin(elevation)])

    @property
    def cells(self) -> int:
        return len(self.elevations_rad) * self.azimuth_bins

    def cell_of(self, xyz: FloatArray) -> tuple[IntArray, FloatArray]:
        """Range-image cell (channel x azimuth bin) and range of each (N, 3) point."""
        horizontal = np.hypot(xyz[:, 0], xyz[:, 1])
        rng = np.hypot(horizontal, xyz[:, 2])
        elevation = np.arctan2(xyz[:, 2], horizontal)
        edges = (self.elevations_rad[1:] + self.elevations_rad[:-1]) / 2  # nearest channel
        channel = np.searchsorted(edges, elevation)
        azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
        column = np.floor((azimuth + math.pi) / (2 * math.pi) * self.azimuth_bins).astype(np.int64)
        column = np.clip(column, 0, self.azimuth_bins - 1)
        return channel * self.azimuth_bins + column, rng


@dataclass(frozen=True)
class Revolution:
    """One revolution as a background model sees it (`RangeBackground.classify`): each point's ray
    (range-image cell), range bin, and whether it stands in front of the background."""

    cell: IntArray
    bin: IntArray
    front: BoolArray


class RangeBackground:
    """The background model of one lidar (module docstring). `foreground(xyz)` classifies one
    revolution's points and learns from them; `classify` then `learn` do the same in two steps, the
    detector's boxes between them."""

    def __init__(self, layout: RangeImage, config: BackgroundConfig, model_path: Path | None = None) -> None:
        self.layout = layout
        self.config = config
        self._log_lo = math.log(layout.min_range_m)
        self._per_bin = (math.log(layout.max_range_m) - self._log_lo) / config.range_bins
        # The weights are kept multiplied by `_scale`: decaying every weight is then one division of the
        # scale, not a pass over cells x range_bins floats (67 MB for a 64 x 2048 lidar at 128 bins, the
        # cost of a frame); `_RESCALE_ABOVE` folds the scale back in, once every ~45 min at the default
        # rate. `shares()` gives the true weights.
        self.weights = np.zeros((layout.cells, config.range_bins), np.float32)
        self._scale = 1.0
        self.frames = 0
        self.background_bin = np.full(layout.cells, config.range_bins, np.int64)  # none: all foreground
        self.through_streak = np.zeros(layout.cells, np.int32)  # revolutions in a row seen beyond it
        # Each revolution re-derives the background of one of `refresh_frames` blocks of rays in turn, so
        # the cost is spread evenly instead of one whole-image pass every `refresh_frames` revolutions.
        self._refresh_blocks = np.array_split(np.arange(layout.cells), config.refresh_frames)
        self.refused_model: Path | None = None  # a saved model that was refused (`site_background`)
        if model_path is not None:
            self.load(model_path)

    @property
    def ready(self) -> bool:
        """True once warm-up is over (a loaded model is)."""
        return self.frames >= self.config.warmup_frames

    def shares(self) -> NDArray[np.float32]:
        """(cells, range_bins) the share of recent revolutions each ray returned in each range bin."""
        return (self.weights / np.float32(self._scale)).astype(np.float32)

    def range_bin(self, range_m: FloatArray) -> IntArray:
        b = np.floor((np.log(np.maximum(range_m, 1e-9)) - self._log_lo) / self._per_bin)
        return np.clip(b, 0, self.config.range_bins - 1).astype(np.int64)

    def classify(self, xyz: FloatArray) -> Revolution:
        """One revolution's (N, 3) points: which stand in front of the background (all False during
        warm-up). Learns nothing (`learn` it after). O(points)."""
        cell, b = self._cells_and_bins(xyz)
        if self.ready:
            front = b < self.background_bin[cell] - self.config.margin_bins
        else:
            front = np.zeros(len(b), bool)
        return Revolution(cell, b, front)

    def foreground(self, xyz: FloatArray, learn: bool = True) -> BoolArray:
        """(N,) True where a point of this revolution stands in front of the background (`classify`);
        then, with `learn`, the revolution is learned (`learn`). O(points) plus one block of rays
        re-derived (`refresh_frames`)."""
        seen = self.classify(xyz)
        if learn:
            self._learn(seen.cell, seen.bin)
        return seen.front

    def learn(self, seen: FloatArray | Revolution, hidden: BoolArray | None = None) -> None:
        """Learn one revolution: its (N, 3) points, or what `classify` made of them (the rays and range
        bins not computed twice: they are half the cost of a 130k-point revolution). `hidden` (N,): the
        points on a detected vehicle, which hides the ray's background rather than replacing it: they
        are learned as a return at the ray's background (none: not learned), so cars queued at a stop
        line for most of an hour never become background (module docstring: *Learning*)."""
        cell, b = (seen.cell, seen.bin) if isinstance(seen, Revolution) else self._cells_and_bins(seen)
        if hidden is not None and hidden.any():
            known = self.background_bin[cell] < self.config.range_bins
            b = np.where(hidden & known, self.background_bin[cell], b)
            keep = ~hidden | known
            cell, b = cell[keep], b[keep]
        self._learn(cell, b)

    def _cells_and_bins(self, xyz: FloatArray) -> tuple[IntArray, IntArray]:
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        cell, rng = self.layout.cell_of(xyz)
        return cell, self.range_bin(rng)

    def _learn(self, cell: IntArray, b: IntArray) -> None:
        cfg = self.config
        self.frames += 1
        warm = self.frames <= cfg.warmup_frames
        rate = 1.0 / self.frames if warm else cfg.learn_rate
        if warm:  # an exact average: the weights are counts over a scale of the revolutions seen
            self._scale = float(self.frames)
        else:  # every weight decays by (1 - rate)
            self._scale /= 1.0 - rate
        cleared_rows = np.zeros(0, np.int64)
        if not warm:
            through = b > self.background_bin[cell] + cfg.margin_bins
            self.through_streak[cell] = np.where(through, self.through_streak[cell] + 1, 0)
            cleared = through & (self.through_streak[cell] >= cfg.clear_after_frames)
            if cleared.any():
                rows, reach = cell[cleared], b[cleared] - cfg.margin_bins
                nearer = np.arange(cfg.range_bins)[None, :] < reach[:, None]
                self.weights[rows] = np.where(nearer, np.float32(0.0), self.weights[rows])
                self.through_streak[rows] = 0
                cleared_rows = rows
        self.weights[cell, b] += np.float32(rate * self._scale)
        if cleared_rows.size:
            self._refresh_rows(cleared_rows)  # at once: the ray's background is gone now
        if self._scale > _RESCALE_ABOVE:
            self.weights /= np.float32(self._scale)
            self._scale = 1.0
        if self.frames == cfg.warmup_frames:
            self.refresh()  # the whole background, once, when it is first used
        elif not warm:
            self._refresh_rows(self._refresh_blocks[self.frames % cfg.refresh_frames])

    def refresh(self) -> None:
        """Re-derive each ray's background bin from its weights."""
        self._refresh_rows(np.arange(self.layout.cells))

    def _refresh_rows(self, rows: IntArray) -> None:
        above = self.weights[rows] >= np.float32(self.config.background_fraction * self._scale)
        self.background_bin[rows] = np.where(above.any(axis=1), above.argmax(axis=1), self.config.range_bins)

    def static_points(self, max_points: int, rng: np.random.Generator) -> FloatArray:
        """(M <= max_points, 3) points of the static scene in the lidar frame: a random subset of the rays
        with a background, each at its background bin's centre range along the ray's centre."""
        rows = np.flatnonzero(self.background_bin < self.config.range_bins)
        if rows.size > max_points:
            rows = np.sort(rng.choice(rows, max_points, replace=False))
        return self.layout.ray_points(
            rows, np.exp(self._log_lo + (self.background_bin[rows] + 0.5) * self._per_bin)
        )

    def save(self, path: Path) -> None:
        """Write the model (weights, frames, layout) to `path` (.npz)."""
        np.savez_compressed(
            path,
            format=MODEL_FORMAT,
            weights=self.shares(),
            frames=self.frames,
            elevations_rad=self.layout.elevations_rad,
            azimuth_bins=self.layout.azimuth_bins,
            range_span_m=(self.layout.min_range_m, self.layout.max_range_m),
        )

    def load(self, path: Path) -> None:
        """Start from a saved model; ValueError if it was learned for another ray layout."""
        with np.load(path) as saved:
            if int(saved["format"]) != MODEL_FORMAT:
                raise ValueError(
                    f"{path}: background model format {int(saved['format'])}, not {MODEL_FORMAT}"
                )
            same = (
                int(saved["azimuth_bins"]) == self.layout.azimuth_bins
                and np.allclose(saved["elevations_rad"], self.layout.elevations_rad)
                and np.allclose(saved["range_span_m"], (self.layout.min_range_m, self.layout.max_range_m))
                and saved["weights"].shape == self.weights.shape
            )
            if not same:
                raise ValueError(f"{path}: a background model of another lidar layout or range binning")
            self.weights = saved["weights"].astype(np.float32)
            self._scale = 1.0
            self.frames = max(int(saved["frames"]), self.config.warmup_frames)
        self.refresh()


def model_path(models_dir: Path, scene_id: str, lidar_id: str) -> Path:
    """Where the background of `lidar_id` of scene `scene_id` is saved under `models_dir`."""
    return models_dir / scene_id / f"{lidar_id}.npz"


def saved_background(config: BackgroundConfig, scene_id: str, lidar_id: str) -> Path | None:
    """The saved model of `lidar_id` of scene `scene_id` in `config.models_dir`, if there is one."""
    if config.models_dir is None:
        return None
    path = model_path(config.models_dir, scene_id, lidar_id)
    return path if path.is_file() else None


def site_background(
    layout: RangeImage, config: BackgroundConfig, scene_id: str, lidar_id: str
) -> RangeBackground:
    """`lidar_id`'s background, from its saved model if there is one. A saved model that cannot be used
    (another lidar layout or range binning: the lidar was changed and the model not learned again; a
    damaged file) is refused with a warning naming it, and the lidar learns online: the MEC starts."""
    path = saved_background(config, scene_id, lidar_id)
    if path is None:
        return RangeBackground(layout, config)
    try:
        return RangeBackground(layout, config, path)
    except (ValueError, KeyError, OSError, zipfile.BadZipFile) as err:
        log.warning("%s: saved background %s refused (%s); learning online", lidar_id, path, err)
        background = RangeBackground(layout, config)
        background.refused_model = path
        return background


def learn_period(
    layouts: Mapping[str, RangeImage], config: BackgroundConfig, revolutions: Iterable[tuple[str, FloatArray]]
) -> dict[str, RangeBackground]:
    """Each lidar's background learned from a period (an empty one, or with traffic that keeps moving):
    every revolution of the period with equal weight (the warm-up average, however long), so what is
    there in at least `background_fraction` of it is background. `revolutions`: (lidar id, (N, 3) points
    in its frame); a lidar not in `layouts` is skipped. Lidars without a revolution are left out."""
    averaging = config.model_copy(update={"warmup_frames": _WHOLE_PERIOD})
    models: dict[str, RangeBackground] = {}
    for lidar_id, xyz in revolutions:
        if lidar_id not in layouts:
            continue
        if lidar_id not in models:
            models[lidar_id] = RangeBackground(layouts[lidar_id], averaging)
        models[lidar_id].foreground(xyz)
    for model in models.values():
        model.config = config
        model.frames = max(model.frames, config.warmup_frames)  # a learned period is a finished warm-up
        model.refresh()
    return models


class AgentGround:
    """The ground under an agent's lidars in the agent frame: a plane fitted (`fit_ground_plane`, open3d's
    RANSAC) to the static points of their background models, again every `ground_refit_frames` calls;
    None until every model is ready. Real sites' ground is sloped, or not at z = 0 of the agent frame
    (shared/detection/lidar/ground.py).

    Parameters
    ----------
    config : BackgroundConfig
    tolerance_m : float
        Inlier distance to the plane, metres (the cluster detector's ground tolerance).
    max_tilt_rad : float
        Steepest ground, radians (the cluster detector's surfaces' tilt limit).
    """

    def __init__(self, config: BackgroundConfig, tolerance_m: float, max_tilt_rad: float) -> None:
        self.config = config
        self.tolerance_m = tolerance_m
        self.max_tilt_rad = max_tilt_rad
        self.plane: Plane | None = None
        self._calls = 0
        self._rng = np.random.default_rng(0)  # which static points: reproducible

    def update(
        self, backgrounds: Mapping[str, RangeBackground], T_agent_from_lidar: Mapping[str, FloatArray]
    ) -> Plane | None:
        """The ground plane after this revolution (refitted when due)."""
        self._calls += 1
        due = self.plane is None or self._calls % self.config.ground_refit_frames == 0
        if not due or not backgrounds or not all(b.ready for b in backgrounds.values()):
            return self.plane
        per_lidar = max(self.config.ground_sample_points // len(backgrounds), 1)
        parts = []
        for lidar_id, model in backgrounds.items():
            T = np.asarray(T_agent_from_lidar[lidar_id], np.float64)
            parts.append(model.static_points(per_lidar, self._rng) @ T[:3, :3].T + T[:3, 3])
        self.plane = fit_ground_plane(
            np.concatenate(parts),
            tolerance_m=self.tolerance_m,
            max_tilt_rad=self.max_tilt_rad,
            iterations=self.config.ground_iterations,
            seed=0,
        )
        return self.plane
