"""A small spinning-lidar ray caster for synthetic test clouds: oriented boxes on a flat table.

Rays go out on ``channels`` elevations x ``samples`` azimuths from the sensor; each returns its first
hit among the boxes (vehicles, a deck slab, pillars, a pole: OpenPCDet boxes) and the plane z = 0, with
Gaussian range noise. Occlusion between objects is therefore real, as in the simulator's lidars.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INTENSITY = 0.5


@dataclass(frozen=True)
class Lidar:
    """Spinning lidar: position (m), elevation range (rad), channels x samples rays, range limits (m)."""

    position: tuple[float, float, float]
    channels: int = 32
    samples: int = 250
    elevation_min: float = -0.5353
    elevation_max: float = 0.1862
    max_range: float = 12.0
    range_noise: float = 0.006

    def directions(self) -> np.ndarray:
        elev = np.linspace(self.elevation_min, self.elevation_max, self.channels)
        azim = np.arange(self.samples) * (2 * np.pi / self.samples)
        e, a = np.meshgrid(elev, azim, indexing="ij")
        return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)


def ray_box_distance(origin: np.ndarray, dirs: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Distance along each (R, 3) unit ray to an OpenPCDet box (7,), inf where missed."""
    c, s = np.cos(box[6]), np.sin(box[6])
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box frame
    o = rot @ (origin - box[:3])
    d = dirs @ rot.T
    half = box[3:6] / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    t1 = np.where(np.isnan(t1), -np.inf, t1)
    t2 = np.where(np.isnan(t2), np.inf, t2)
    near = np.minimum(t1, t2).max(axis=1)
    far = np.maximum(t1, t2).min(axis=1)
    hit = (near <= far) & (near > 0)
    return np.where(hit, near, np.inf)


def scan(lidar: Lidar, boxes: np.ndarray, rng: np.random.Generator, table: bool = True) -> np.ndarray:
    """(N, 4) float32 cloud x, y, z, intensity of one revolution over ``boxes`` (K, 7) and the table."""
    origin = np.asarray(lidar.position, dtype=np.float64)
    dirs = lidar.directions()
    dist = np.full(dirs.shape[0], np.inf)
    for box in np.asarray(boxes, dtype=np.float64).reshape(-1, 7):
        dist = np.minimum(dist, ray_box_distance(origin, dirs, box))
    if table:
        with np.errstate(divide="ignore"):
            t_table = np.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], np.inf)
        dist = np.minimum(dist, t_table)
    hit = dist <= lidar.max_range
    r = dist[hit] + rng.normal(0.0, lidar.range_noise, int(hit.sum()))
    xyz = origin + dirs[hit] * r[:, None]
    return np.hstack([xyz, np.full((xyz.shape[0], 1), INTENSITY)]).astype(np.float32)
