"""Ground handling for the clustering lidar detector: the table plane and elevated slabs (viaduct deck).

The table is flat and, by construction of the agent frame, at ``z = 0`` (`shared.datasets.layout`), so
table points are removed with a height threshold (`above_table`): fitting a plane with RANSAC would
only re-estimate that known plane, cost time, and can lock onto something else when the table is
mostly occluded near a vehicle queue.

The viaduct deck (a 4 cm slab at up to ~0.4 m, with ramps) is not at a known height in an agent's
frame, so it is found in the data: `fit_horizontal_plane` is a RANSAC that only hypothesises planes
tilted at most ``max_tilt_rad`` from horizontal (walls can never win), refined by least squares.
`split_at_slab` then selects the slab around that plane: points within ``half_thickness_m`` of it (top
surface, side faces and underside, whichever side the lidar saw) and inside the plane's inlier
footprint on a BEV grid, so an extrapolated plane cannot cut objects elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# Points per RANSAC hypothesis (a plane through 3 points).
_SAMPLE_SIZE = 3
# Cross products shorter than this (m^2) come from (nearly) collinear samples.
_DEGENERATE_AREA_M2 = 1e-9
# BEV cells are hashed as ix * _CELL_KEY_STRIDE + iy; valid while |iy| < stride / 2 (cells, not metres).
_CELL_KEY_STRIDE = 1 << 21


def above_table(xyz: FloatArray, table_z_m: float, tolerance_m: float) -> BoolArray:
    """Points higher than ``table_z_m + tolerance_m``.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Agent frame, metres.
    table_z_m, tolerance_m : float
        Table height and the band above it counted as table (lidar noise, paint), metres.

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
    """
    return np.asarray(xyz[:, 2] > table_z_m + tolerance_m)


@dataclass(frozen=True)
class Plane:
    """Plane ``normal . p + offset = 0`` with a unit normal pointing up (``normal[2] > 0``)."""

    normal: FloatArray
    offset: float

    def signed_distance(self, xyz: FloatArray) -> FloatArray:
        """Distance of (N, 3) points above (+) or below (-) the plane, metres, shape (N,)."""
        return np.asarray(xyz @ self.normal + self.offset)

    def height_at(self, xy: FloatArray) -> FloatArray:
        """Plane z at (N, 2) BEV positions, metres, shape (N,)."""
        return np.asarray(-(xy @ self.normal[:2] + self.offset) / self.normal[2])


def _plane_through(points: FloatArray) -> Plane | None:
    """Least-squares plane of (N >= 3, 3) points (SVD), normal up; None if degenerate (collinear)."""
    centroid = points.mean(axis=0)
    _, singular, vt = np.linalg.svd(points - centroid, full_matrices=False)
    if singular.size < _SAMPLE_SIZE or singular[1] <= 0.0:
        return None
    normal = vt[-1] if vt[-1][2] >= 0.0 else -vt[-1]
    return Plane(normal=normal, offset=float(-normal @ centroid))


def fit_horizontal_plane(
    xyz: FloatArray,
    rng: np.random.Generator,
    *,
    tolerance_m: float,
    max_tilt_rad: float,
    min_inliers: int,
    iterations: int,
    max_points: int,
) -> tuple[Plane, BoolArray] | None:
    """RANSAC for the best near-horizontal plane.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Points, metres.
    rng : numpy.random.Generator
        Source of the samples (seed it for reproducible results).
    tolerance_m : float
        Inlier distance to the plane, metres.
    max_tilt_rad : float
        Largest angle between the plane normal and +z (ramps are a few degrees).
    min_inliers : int
        Fewest inliers for a plane to be returned.
    iterations : int
        Number of 3-point hypotheses.
    max_points : int
        Hypotheses are scored on a random subset of at most this many points (speed); the final
        inliers are computed on all points.

    Returns
    -------
    (Plane, numpy.ndarray of bool (N,)) or None
        The refined plane and its inliers, or None when no hypothesis within the tilt limit reaches
        ``min_inliers``.
    """
    n = xyz.shape[0]
    if n < max(min_inliers, _SAMPLE_SIZE):
        return None
    samples = xyz[rng.integers(0, n, (iterations, _SAMPLE_SIZE))]
    normals = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])
    length = np.linalg.norm(normals, axis=1)
    ok = length > _DEGENERATE_AREA_M2
    normals = normals[ok] / length[ok, None]
    normals *= np.where(normals[:, 2] < 0.0, -1.0, 1.0)[:, None]
    flat = normals[:, 2] >= np.cos(max_tilt_rad)
    normals, anchors = normals[flat], samples[ok][flat, 0]
    if normals.shape[0] == 0:
        return None
    subset = xyz if n <= max_points else xyz[rng.choice(n, max_points, replace=False)]
    offsets = -np.einsum("kd,kd->k", normals, anchors)
    counts = (np.abs(subset @ normals.T + offsets) <= tolerance_m).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = np.abs(xyz @ normals[best] + offsets[best]) <= tolerance_m
    refined = _plane_through(xyz[inliers]) if inliers.sum() >= _SAMPLE_SIZE else None
    if refined is not None and refined.normal[2] >= np.cos(max_tilt_rad):
        inliers = np.abs(refined.signed_distance(xyz)) <= tolerance_m
        plane = refined
    else:
        plane = Plane(normal=normals[best], offset=float(offsets[best]))
    if inliers.sum() < min_inliers:
        return None
    return plane, inliers


def _cell_keys(xy: FloatArray, cell_m: float) -> NDArray[np.int64]:
    cells = np.floor(xy / cell_m).astype(np.int64)
    return np.asarray(cells[:, 0] * _CELL_KEY_STRIDE + cells[:, 1])


def footprint_mask(xy: FloatArray, support_xy: FloatArray, cell_m: float) -> BoolArray:
    """Points whose BEV cell is a cell of ``support_xy`` or one of its 8 neighbours.

    Parameters
    ----------
    xy : numpy.ndarray, shape (N, 2)
        Points to test, metres.
    support_xy : numpy.ndarray, shape (M, 2)
        Points defining the footprint, metres.
    cell_m : float
        Grid cell size, metres.

    Returns
    -------
    numpy.ndarray of bool, shape (N,)
    """
    base = np.unique(_cell_keys(support_xy, cell_m))
    offsets = np.array([dx * _CELL_KEY_STRIDE + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)], np.int64)
    dilated = np.unique((base[:, None] + offsets[None, :]).ravel())
    return np.asarray(np.isin(_cell_keys(xy, cell_m), dilated))


@dataclass(frozen=True)
class SlabSplit:
    """Result of `split_at_slab`: boolean masks, shape (N,) each."""

    slab: BoolArray
    above: BoolArray


def split_at_slab(
    xyz: FloatArray, plane: Plane, inliers: BoolArray, half_thickness_m: float, cell_m: float
) -> SlabSplit:
    """The slab around ``plane`` and what stands on it, within the footprint of the plane's inliers.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
    plane : Plane
    inliers : numpy.ndarray of bool, shape (N,)
        The plane's inliers (they define the footprint).
    half_thickness_m : float
        Slab thickness plus inlier tolerance, metres: covers the deck's side faces and underside
        whether the plane found is its top or its underside.
    cell_m : float
        Footprint grid cell, metres.

    Returns
    -------
    SlabSplit
        ``slab``: in the footprint and within ``half_thickness_m`` of the plane; ``above``: in the
        footprint and higher than that (objects standing on the surface).
    """
    distance = plane.signed_distance(xyz)
    inside = footprint_mask(xyz[:, :2], xyz[inliers, :2], cell_m)
    return SlabSplit(
        slab=inside & (np.abs(distance) <= half_thickness_m), above=inside & (distance > half_thickness_m)
    )
