"""Synthetic lidar returns for tests: points on the surfaces of a box."""

from __future__ import annotations

import numpy as np


def box_surface_points(box: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points on the four sides and the top of a (7,) box, world frame."""
    x, y, z, dx, dy, dz, yaw = box
    u = rng.uniform(-0.5, 0.5, (n, 3)) * [dx, dy, dz]
    face = rng.integers(0, 5, n)
    u[face == 0, 0], u[face == 1, 0] = dx / 2, -dx / 2
    u[face == 2, 1], u[face == 3, 1] = dy / 2, -dy / 2
    u[face == 4, 2] = dz / 2
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([x + c * u[:, 0] - s * u[:, 1], y + s * u[:, 0] + c * u[:, 1], z + u[:, 2]], axis=1)
