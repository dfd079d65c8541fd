"""Ground handling for the clustering lidar detector: the table plane and elevated slabs (viaduct deck).

The table is flat and, by construction of the agent frame, at ``z = 0`` (`shared.datasets.layout`), so
table points are removed with a height threshold (`above_table`): fitting a plane with RANSAC would
only re-estimate that known plane, cost time, and can lock onto something else when the table is
mostly occluded near a vehicle queue.

A real site's ground is neither flat nor at a known height in the agent frame (a sloped road, a lidar
pole's base above or below the crossing). With a background model (shared/perception/background.py) the
ground is part of the static scene: `fit_ground_plane` finds it once in a while in the model's static
points (open3d's RANSAC, the steepest ground ``max_tilt_rad``), and the clustering detector measures
heights from that plane instead of from ``z = table_z_m`` (`ClusterLidarDetector.ground`).

The viaduct deck (a 4 cm slab at up to ~0.4 m, with ramps) is not at a known height in an agent's
frame, so it is found in the data: `fit_horizontal_plane` is a RANSAC that only hypothesises planes
tilted at most ``max_tilt_rad`` from horizontal (walls can never win), refined by least squares.
`split_at_slab` then selects the slab around that plane: points within ``half_thickness_m`` of it (top
surface, side faces and underside, whichever side the lidar saw) and inside the plane's inlier
footprint on a BEV grid, so an extrapolated plane cannot cut objects elsewhere.

`peel_slabs` is the loop both users run (the clustering detector and the MEC's lidar preprocessing):
a cluster its caller finds too large for a vehicle is searched for a surface, the slab is removed,
points standing on it get the surface as their support height, and the rest is re-clustered by the
caller's rule, up to ``SlabSearch.max_peels`` times (ramps and deck are several planes).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Generic, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.scene.scale import LENGTH, Length

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]
T = TypeVar("T")

# Points per RANSAC hypothesis (a plane through 3 points).
_SAMPLE_SIZE = 3
# Cross products shorter than this (m^2) come from (nearly) collinear samples.
_DEGENERATE_AREA_M2 = 1e-9
# BEV cells are hashed as ix * _CELL_KEY_STRIDE + iy; valid while |iy| < stride / 2 (cells, not metres).
_CELL_KEY_STRIDE = 1 << 21


def above_table(xyz: FloatArray, table_z_m: float | FloatArray, tolerance_m: float) -> BoolArray:
    """Points higher than ``table_z_m + tolerance_m``.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Agent frame, metres.
    table_z_m : float or numpy.ndarray, shape (N,)
        Table (ground) height, metres: one, or the ground's under each point (a fitted plane).
    tolerance_m : float
        The band above it counted as table (lidar noise, paint), metres.

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


def fit_ground_plane(
    xyz: FloatArray, *, tolerance_m: float, max_tilt_rad: float, iterations: int, seed: int, attempts: int = 3
) -> Plane | None:
    """The ground: the largest plane tilted at most ``max_tilt_rad`` from horizontal (open3d's RANSAC,
    `segment_plane`). A steeper plane found first (a building's wall) is set aside with its inliers and the
    search repeated, ``attempts`` times at most.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Static points (a background model's), metres.
    tolerance_m : float
        Inlier distance to the plane, metres.
    max_tilt_rad : float
        Steepest ground, radians.
    iterations : int
        RANSAC hypotheses per search.
    seed : int
        open3d's random seed (the fit is reproducible).
    attempts : int
        Planes tried at most.

    Returns
    -------
    Plane or None
        Normal up; None when no near-horizontal plane of at least 3 points is found.
    """
    import open3d as o3d  # the MEC's background detector only: not loaded by the others

    o3d.utility.random.seed(seed)
    left = np.asarray(xyz, np.float64)
    for _ in range(attempts):
        if left.shape[0] < _SAMPLE_SIZE:
            return None
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(left))
        model, inliers = cloud.segment_plane(tolerance_m, _SAMPLE_SIZE, iterations)
        normal, offset = np.asarray(model[:3], np.float64), float(model[3])
        scale = float(np.linalg.norm(normal)) * (1.0 if normal[2] >= 0.0 else -1.0)
        plane = Plane(normal=normal / scale, offset=offset / scale)
        if plane.normal[2] >= math.cos(max_tilt_rad):
            return plane
        left = np.delete(left, np.asarray(inliers, np.int64), axis=0)
    return None


def cell_keys(xy: FloatArray, cell_m: float) -> NDArray[np.int64]:
    """One int64 key per (N, 2) point: its BEV cell of side ``cell_m`` (metres)."""
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
    base = np.unique(cell_keys(support_xy, cell_m))
    offsets = np.array([dx * _CELL_KEY_STRIDE + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1)], np.int64)
    dilated = np.unique((base[:, None] + offsets[None, :]).ravel())
    return np.asarray(np.isin(cell_keys(xy, cell_m), dilated))


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


class SlabSearch(BaseModel):
    """Settings of the elevated-surface search of `peel_slabs`: metres, radians."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    tolerance_m: Length = Field(0.015, gt=0.0, description="RANSAC inlier distance to a surface, m")
    max_tilt_rad: float = Field(
        0.3, ge=0.0, lt=math.pi / 2, description="steepest surface, rad (ramps are ~0.2 rad)"
    )
    thickness_m: Length = Field(0.04, ge=0.0, description="slab thickness removed around a surface, m")
    min_points: int = Field(15, ge=3, description="fewest inliers of a surface")
    cell_m: Length = Field(0.1, gt=0.0, description="BEV cell of a surface's inlier footprint, m")
    min_top_m: Annotated[float | None, LENGTH] = Field(
        None, description="a surface counts only if some inlier is at least this high, m (None: any height)"
    )
    max_peels: int = Field(4, ge=0, description="surfaces removed from one cluster at most (ramps + deck)")
    iterations: int = Field(200, ge=1, description="RANSAC hypotheses per surface search")
    max_points: int = Field(3000, ge=3, description="points scoring each RANSAC hypothesis (subset)")
    seed: int = Field(0, description="RANSAC seed: the search is deterministic")


class Verdict(enum.Enum):
    """What a `peel_slabs` caller's ``leaf`` rule says of a cluster that is not a leaf."""

    SEARCH = "search"  # larger than a vehicle: look for a surface in it


SEARCH = Verdict.SEARCH


@dataclass(frozen=True)
class Peeled(Generic[T]):
    """Result of `peel_slabs`."""

    leaves: list[T]  # the ``leaf`` rule's results, in the order the clusters were taken
    slab: BoolArray  # (N,) points removed as part of a surface's slab
    support_m: FloatArray  # (N,) height of the surface each point stands on (``base_z_m`` if none)


def peel_slabs(
    xyz: FloatArray,
    clusters: Sequence[IntArray],
    search: SlabSearch,
    *,
    leaf: Callable[[IntArray, FloatArray], T | Literal[Verdict.SEARCH]],
    recluster: Callable[[IntArray], list[IntArray]],
    base_z_m: float | FloatArray = 0.0,
) -> Peeled[T]:
    """Peel elevated slabs off the clusters that are too large to be objects.

    Parameters
    ----------
    xyz : numpy.ndarray, shape (N, 3)
        Points, metres.
    clusters : sequence of numpy.ndarray of int
        Initial clusters, indices into ``xyz`` (disjoint).
    search : SlabSearch
    leaf : callable
        ``leaf(idx, support_m)``: the caller's result for cluster ``idx`` (kept in ``leaves``), or
        `SEARCH` when the cluster is too large and is to be searched for a surface. ``support_m`` is
        final for ``idx`` when it is called (only an ancestor's surface can support its points).
    recluster : callable
        ``recluster(idx)``: clusters of the points ``idx`` left when a slab is removed.
    base_z_m : float or numpy.ndarray, shape (N,)
        Support height of points on no surface (the table, or the ground under each point), metres.

    Returns
    -------
    Peeled
        A cluster without a surface, or still too large after ``max_peels`` surfaces, yields no leaf
        and keeps its points (``slab`` False).
    """
    rng = np.random.default_rng(search.seed)
    slab = np.zeros(xyz.shape[0], dtype=bool)
    support = np.broadcast_to(np.asarray(base_z_m, np.float64), (xyz.shape[0],)).copy()
    leaves: list[T] = []
    queue = [(np.asarray(c, dtype=np.int64), search.max_peels) for c in clusters]
    while queue:
        idx, peels = queue.pop()
        verdict = leaf(idx, support)
        if verdict is not SEARCH:
            leaves.append(verdict)
            continue
        if peels == 0:
            continue
        pts = xyz[idx]
        found = fit_horizontal_plane(
            pts,
            rng,
            tolerance_m=search.tolerance_m,
            max_tilt_rad=search.max_tilt_rad,
            min_inliers=search.min_points,
            iterations=search.iterations,
            max_points=search.max_points,
        )
        if found is None:
            continue
        plane, inliers = found
        if search.min_top_m is not None and pts[inliers, 2].max() < search.min_top_m:
            continue
        split = split_at_slab(pts, plane, inliers, search.thickness_m + search.tolerance_m, search.cell_m)
        slab[idx[split.slab]] = True
        on_top = idx[split.above]
        support[on_top] = np.maximum(support[on_top], plane.height_at(xyz[on_top, :2]))
        queue += [(c, peels - 1) for c in recluster(idx[~split.slab])]
    return Peeled(leaves=leaves, slab=slab, support_m=support)
