"""A tiny training run on synthetic clouds lowers the loss; augmentation keeps boxes on their points."""

from __future__ import annotations

import numpy as np
import torch

from shared.detection.lidar.pointpillars.config import PointPillarsConfig
from shared.geometry.boxes import box3d_corners
from training.pointpillars.data import (
    Frame,
    PillarDataset,
    augment,
    grid_bands,
    grid_labels,
    mirror_x,
    mirror_y,
)
from training.pointpillars.train import train

TRAIN_FRAMES = 16
STEPS = 40


def _frames(synthetic_frame, config: PointPillarsConfig, n: int) -> list[Frame]:
    out = []
    for seed in range(n):
        points, boxes = synthetic_frame(seed, config)
        out.append(Frame(f"f{seed}", points, boxes, np.zeros((0, 7))))
    return out


def _inside(points: np.ndarray, box: np.ndarray, margin: float = 1e-3) -> np.ndarray:
    c, s = np.cos(box[6]), np.sin(box[6])
    d = points[:, :3] - box[:3]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    return np.all(np.abs(local) <= box[3:6] / 2 + margin, axis=1)


def test_tiny_training_lowers_the_loss(tiny_config: PointPillarsConfig, synthetic_frame) -> None:
    torch.set_num_threads(1)
    config = tiny_config.model_copy(update={"train": tiny_config.train.model_copy(update={"epochs": 10})})
    frames = _frames(synthetic_frame, config, TRAIN_FRAMES)
    _, history = train(config, frames, [], out_dir=None, max_steps=STEPS)
    losses = [h["loss"] for h in history]
    assert sum(h["steps"] for h in history) == STEPS
    assert losses[-1] < 0.5 * losses[0], losses


def test_augmentation_moves_boxes_with_their_points(tiny_config: PointPillarsConfig, synthetic_frame) -> None:
    frame = _frames(synthetic_frame, tiny_config, 1)[0]
    rng = np.random.default_rng(3)
    for out in (mirror_x(frame), mirror_y(frame), augment(frame, tiny_config.augment, rng)):
        for before, after in zip(frame.boxes, out.boxes, strict=True):
            assert (
                _inside(out.points, after, margin=0.01).sum()
                == _inside(frame.points, before, margin=0.01).sum()
            )
        # corners stay consistent (valid boxes for shared.geometry)
        assert box3d_corners(out.boxes).shape == (len(out.boxes), 8, 3)


def test_training_windows_have_the_crop_grid(tiny_config: PointPillarsConfig, synthetic_frame) -> None:
    config = tiny_config.model_copy(
        update={"train": tiny_config.train.model_copy(update={"crop_size_m": 0.8})}
    )
    data = PillarDataset(_frames(synthetic_frame, config, 2), config, train=True)
    item = data[0]
    assert data.grid.nx == data.grid.ny == 16
    assert item["heatmap"].shape == (8, 8)
    assert item["coords"].max() < 16 * 16


def test_validation_scores_the_labels_within_the_grid_only() -> None:
    grid = PointPillarsConfig().grid  # x, y in [-4, 4)
    inside = [1.0, -2.0, 0.1, 0.33, 0.22, 0.21, 0.0]
    beyond = [4.5, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]  # on a ring road past the grid
    edge = [4.0, 0.0, 0.1, 0.33, 0.22, 0.21, 0.0]  # the grid's end is exclusive
    given = np.zeros((1, 7))
    frame = Frame("f", np.zeros((0, 4), np.float32), np.array([inside, beyond, edge]), given)
    ((labels, ignore),) = grid_labels([frame], grid)
    assert labels.tolist() == [inside]
    assert ignore.tolist() == [given[0].tolist(), beyond, edge]


def test_validation_bands_follow_the_grid() -> None:
    from shared.detection.lidar.pointpillars.config import GridConfig
    from shared.metrics.detection import DEFAULT_DISTANCE_BANDS_M

    assert grid_bands(PointPillarsConfig().grid) == DEFAULT_DISTANCE_BANDS_M  # the table's +-4 m
    site = GridConfig(x_min_m=-32.0, x_max_m=32.0, y_min_m=-40.0, y_max_m=40.0, pillar_size_m=0.4)
    assert grid_bands(site) == ((0.0, 16.0), (16.0, 32.0), (32.0, float("inf")))
