"""Fixtures of the PointPillars tests: a tiny config and synthetic sand-table-like clouds."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from shared.detection.lidar.pointpillars.config import (
    GridConfig,
    HeadConfig,
    NetConfig,
    PointPillarsConfig,
    TrainConfig,
)
from tests.shared.detection.lidar.samples import box_surface_points

VEHICLE_SIZE_M = (0.33, 0.22, 0.21)
GROUND_STEP_M = 0.04
SURFACE_POINTS = 120


@pytest.fixture
def tiny_config() -> PointPillarsConfig:
    """1.6 x 1.6 m grid of 0.05 m pillars (32 x 32), narrow network: fast to run and to train."""
    return PointPillarsConfig(
        grid=GridConfig(x_min_m=-0.8, x_max_m=0.8, y_min_m=-0.8, y_max_m=0.8, max_points_per_pillar=8),
        net=NetConfig(
            pfn_channels=16, stage_channels=(16, 32), stage_layers=(1, 1), neck_channels=16, head_channels=16
        ),
        head=HeadConfig(mean_size_m=(0.33, 0.22, 0.21)),  # the synthetic frames' vehicles
        train=TrainConfig(epochs=1, batch_size=4, lr=5e-3, crop_size_m=0.0, num_threads=1),
    )


@pytest.fixture
def synthetic_frame() -> Callable[[int, PointPillarsConfig], tuple[np.ndarray, np.ndarray]]:
    """Factory (seed, config) -> points (N, 4) float32, boxes (G, 7): ground grid + 1-3 vehicles on it."""

    def make(seed: int, config: PointPillarsConfig) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng(seed)
        g = config.grid
        gx, gy = np.meshgrid(
            np.arange(g.x_min_m, g.x_max_m, GROUND_STEP_M), np.arange(g.y_min_m, g.y_max_m, GROUND_STEP_M)
        )
        ground = np.stack(
            [gx.ravel(), gy.ravel(), rng.normal(0, 0.003, gx.size), np.full(gx.size, 0.15)], axis=1
        )
        boxes: list[np.ndarray] = []
        margin = 0.25
        count = rng.integers(1, 4)
        while len(boxes) < count:
            centre = rng.uniform(
                [g.x_min_m + margin, g.y_min_m + margin], [g.x_max_m - margin, g.y_max_m - margin]
            )
            if all(np.hypot(*(centre - b[:2])) > 0.4 for b in boxes):
                dx, dy, dz = VEHICLE_SIZE_M
                boxes.append(np.array([centre[0], centre[1], dz / 2, dx, dy, dz, rng.uniform(-np.pi, np.pi)]))
        cars = [
            np.concatenate([box_surface_points(b, SURFACE_POINTS, rng), np.full((SURFACE_POINTS, 1), 0.8)], 1)
            for b in boxes
        ]
        return np.concatenate([ground, *cars]).astype(np.float32), np.array(boxes)

    return make
