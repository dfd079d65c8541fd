"""Training data: frames of a dataset (the project's OpenPCDet custom layout, or KITTI; read by
shared.datasets.sources) -> pillars + targets.

Frames are read once and kept in memory (a 10k-point frame is 160 kB); each `__getitem__` augments a copy
(global flip, rotation, scaling, shift of points and boxes together), pillarises it and encodes the head
targets, so an epoch costs one numpy pass per frame on top of the network.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from shared.config import with_overrides
from shared.datasets.sources import DEFAULT_SOURCE, DataSource, lidar_items
from shared.detection.lidar.pointpillars.coding import BOX_COLUMNS, encode_targets
from shared.detection.lidar.pointpillars.config import AugmentConfig, GridConfig, PointPillarsConfig
from shared.detection.lidar.pointpillars.pillars import flat_coords, pillarize
from training.pointpillars.evaluation import accuracy

YAW = 6
QUARTER_TURN = np.pi / 2
TURNS = 4


@dataclass(frozen=True)
class Frame:
    """One agent frame: points (N, 4) float32, labelled boxes (G, 7) and ignore boxes (I, 7), float64."""

    stem: str
    points: np.ndarray
    boxes: np.ndarray
    ignore: np.ndarray


def read_split(
    root: Path, split: str, max_frames: int | None = None, source: DataSource = DEFAULT_SOURCE
) -> list[Frame]:
    """The frames of one split of any dataset `shared.datasets.sources` reads (the project's generated
    ones, KITTI), in memory."""
    items = lidar_items(root, split, source)
    if max_frames is not None:
        items = items[:max_frames]
    return [Frame(i.stem, i.points().astype(np.float32, copy=False), i.boxes, i.ignore) for i in items]


def with_mean_size(config: PointPillarsConfig, frames: list[Frame]) -> PointPillarsConfig:
    """`config` with `head.mean_size_m` fixed: as given, else the median (dx, dy, dz) of the labelled boxes
    of `frames` (the training split), so the size prior is the site's vehicles at any scale."""
    if config.head.mean_size_m is not None:
        return config
    sizes = np.concatenate([f.boxes[:, 3:6] for f in frames if len(f.boxes)] or [np.zeros((0, 3))])
    if not len(sizes):
        raise ValueError("no labelled boxes to take the size prior from: set head.mean_size_m")
    median = tuple(float(v) for v in np.median(sizes, axis=0))
    return with_overrides(config, {"head": {"mean_size_m": median}})


# --- augmentation (points (N, 4) and boxes (G, 7) transformed together) ---------------------------


def mirror_y(frame: Frame) -> Frame:
    """Mirror about the x axis: y -> -y, yaw -> -yaw."""
    pts = frame.points.copy()
    pts[:, 1] *= -1
    out = []
    for b in (frame.boxes, frame.ignore):
        b = b.copy()
        b[:, 1] *= -1
        b[:, YAW] *= -1
        out.append(b)
    return replace(frame, points=pts, boxes=out[0], ignore=out[1])


def mirror_x(frame: Frame) -> Frame:
    """Mirror about the y axis: x -> -x, yaw -> pi - yaw."""
    pts = frame.points.copy()
    pts[:, 0] *= -1
    out = []
    for b in (frame.boxes, frame.ignore):
        b = b.copy()
        b[:, 0] *= -1
        b[:, YAW] = np.pi - b[:, YAW]
        out.append(b)
    return replace(frame, points=pts, boxes=out[0], ignore=out[1])


def rotate_scale_shift(frame: Frame, angle: float, scale: float, shift_xy: np.ndarray) -> Frame:
    """Rotate about z by `angle` (rad), scale about the origin, then shift x, y by `shift_xy` (m)."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    pts = frame.points.copy()
    pts[:, :2] = (pts[:, :2] @ rot.T * scale + shift_xy).astype(np.float32)
    pts[:, 2] *= np.float32(scale)
    out = []
    for b in (frame.boxes, frame.ignore):
        b = b.copy()
        b[:, :2] = b[:, :2] @ rot.T * scale + shift_xy
        b[:, 2:6] *= scale
        b[:, YAW] = (b[:, YAW] + angle + np.pi) % (2 * np.pi) - np.pi
        out.append(b)
    return replace(frame, points=pts, boxes=out[0], ignore=out[1])


def grid_accuracy(detections: list[np.ndarray], frames: list[Frame], grid: GridConfig) -> dict[str, Any]:
    """`evaluation.accuracy` of a model with `grid` over `frames`: the labels within its grid
    (`grid_labels`), by the bands of its reach (`grid_bands`). Training's validation, the trained
    model's scores."""
    return accuracy(detections, grid_labels(frames, grid), grid_bands(grid))


def grid_labels(frames: list[Frame], grid: GridConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each frame's (labels, ignore boxes) for scoring a model with `grid`: labels centred outside it are
    ignored, as a model is scored over its range (a real-size site's dataset labels the cars on a ring
    road beyond the grid that covers the agent's areas)."""
    x_range, y_range = (grid.x_min_m, grid.x_max_m), (grid.y_min_m, grid.y_max_m)
    return [split_by_range(f.boxes, f.ignore, x_range, y_range) for f in frames]


def grid_bands(grid: GridConfig) -> tuple[tuple[float, float], ...]:
    """Distance bands (m from the agent origin) for scoring a model with `grid`: out to half its reach,
    to its reach, beyond (corners); the reach is the grid's shortest half-extent. The sand table's grid
    (+-4 m) gives the detector evaluation's bands, shared.metrics.detection.DEFAULT_DISTANCE_BANDS_M."""
    reach = min(-grid.x_min_m, grid.x_max_m, -grid.y_min_m, grid.y_max_m)
    return ((0.0, reach / 2), (reach / 2, reach), (reach, float("inf")))


def split_by_range(
    boxes: np.ndarray, ignore: np.ndarray, x_range: tuple[float, float], y_range: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (G, 7) whose centre lies outside [x0, x1) x [y0, y1) move to the ignore boxes (I, 7)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, BOX_COLUMNS)
    x, y = boxes[:, 0], boxes[:, 1]
    inside = (x >= x_range[0]) & (x < x_range[1]) & (y >= y_range[0]) & (y < y_range[1])
    ignore = np.concatenate([np.asarray(ignore, np.float64).reshape(-1, BOX_COLUMNS), boxes[~inside]])
    return boxes[inside], ignore


def crop_window(frame: Frame, grid: GridConfig, rng: np.random.Generator) -> Frame:
    """Keep the points inside the detection grid (as at inference), move labels centred outside it to
    ignore, then shift a uniformly drawn point of the grid to the origin (the centre of the window)."""
    p = frame.points
    inside = (
        (p[:, 0] >= grid.x_min_m)
        & (p[:, 0] < grid.x_max_m)
        & (p[:, 1] >= grid.y_min_m)
        & (p[:, 1] < grid.y_max_m)
    )
    boxes, ignore = split_by_range(
        frame.boxes, frame.ignore, (grid.x_min_m, grid.x_max_m), (grid.y_min_m, grid.y_max_m)
    )
    centre = rng.uniform([grid.x_min_m, grid.y_min_m], [grid.x_max_m, grid.y_max_m])
    frame = replace(frame, points=p[inside], boxes=boxes, ignore=ignore)
    return rotate_scale_shift(frame, 0.0, 1.0, -centre)


def augment(frame: Frame, cfg: AugmentConfig, rng: np.random.Generator) -> Frame:
    if rng.random() < cfg.mirror_y_prob:
        frame = mirror_y(frame)
    if rng.random() < cfg.mirror_x_prob:
        frame = mirror_x(frame)
    angle = rng.uniform(-cfg.rotation_max_rad, cfg.rotation_max_rad)
    if cfg.quarter_turns:
        angle += QUARTER_TURN * rng.integers(0, TURNS)
    scale = rng.uniform(cfg.scale_min, cfg.scale_max)
    shift = rng.normal(0.0, cfg.translation_std_m, 2)
    return rotate_scale_shift(frame, angle, scale, shift)


# --- dataset ------------------------------------------------------------------------------------


class PillarDataset(Dataset):
    """Frames -> dict of numpy arrays: features (P, M, 7), num_points (P,), coords (P,) flat index,
    heatmap / heatmap_weight / regression_mask (H, W), regression (9, H, W).

    Training (`train=True`): augmented, then cut to a random window of `config.train_grid()` (the whole
    grid when `train.crop_size_m` is 0). Otherwise: the frame as is on the detection grid."""

    def __init__(self, frames: list[Frame], config: PointPillarsConfig, train: bool, seed: int = 0) -> None:
        self.frames = frames
        self.config = config
        self.train = train
        self.crop = train and config.train.crop_size_m > 0
        self.grid = config.train_grid() if self.crop else config.grid
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        frame = self.frames[i]
        if self.train:
            frame = augment(frame, self.config.augment, self.rng)
        if self.crop:
            frame = crop_window(frame, self.config.grid, self.rng)
        pillars = pillarize(frame.points, self.grid)
        targets = encode_targets(frame.boxes, frame.ignore, self.grid, self.config.head)
        return {
            "features": pillars.features,
            "num_points": pillars.num_points,
            "coords": flat_coords(pillars.coords, self.grid),
            "heatmap": targets.heatmap,
            "heatmap_weight": targets.heatmap_weight,
            "regression": targets.regression,
            "regression_mask": targets.regression_mask,
        }


def collate(batch: list[dict[str, np.ndarray]], cells_per_frame: int) -> dict[str, torch.Tensor]:
    """Concatenate pillars (coords offset by frame * cells_per_frame) and stack the dense targets."""
    offsets = [np.full(len(b["coords"]), i * cells_per_frame, np.int64) for i, b in enumerate(batch)]
    out = {
        "features": torch.from_numpy(np.concatenate([b["features"] for b in batch])),
        "num_points": torch.from_numpy(np.concatenate([b["num_points"] for b in batch])),
        "coords": torch.from_numpy(np.concatenate([b["coords"] for b in batch]) + np.concatenate(offsets)),
    }
    for key in ("heatmap", "heatmap_weight", "regression_mask"):
        out[key] = torch.from_numpy(np.stack([b[key] for b in batch]))[:, None]
    out["regression"] = torch.from_numpy(np.stack([b["regression"] for b in batch]))
    return out
