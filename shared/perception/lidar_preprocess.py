"""Lidar preprocessing of the edge (MEC) service: merge an agent's lidars, then thin the cloud.

Merge (`merge_clouds`): every scan is mapped into one frame by its full SE(3) extrinsic (rotation
included) and all points of every scan are kept. The reference combiner applied translation-only
offsets, and only to the first ``len(cloud 2)`` points of each cloud (docs/references.md, the paper (C.3)).
`agent_frame_transforms` gives the extrinsics into an agent frame (world axes, origin at
`shared.datasets.layout.agent_origin_m`, table at ``z = 0``), so the merged cloud is the one the
lidar datasets were generated from.

Preprocess (`preprocess`), in order; each stage can be switched off in `LidarPreprocessConfig`:

1. Non-finite rows are dropped (and counted).
2. Crop to an agent-frame box (off by default: the table edge is agent-specific).
3. Statistical outlier removal (open3d; the paper's "Gaussian filter", PCL MeanK = 10,
   StddevMulThresh = 0.2): a point whose mean distance to its k nearest neighbours exceeds the
   cloud's mean of that distance by more than ``sor_std_ratio`` standard deviations is removed.
   The statistic is global while lidar density falls with range squared, and a vehicle 3-4 m away
   returns 5-10 points, so with k = 10 its neighbours lie on other objects and it looks like an
   outlier. Measured on 172 simulated frames each of agent1 / agent3 (vehicle points kept; vehicles
   of >= 5 points left with < 5, of 1009 / 988; points injected at random in the air removed):
   k = 10, ratio 0.2 (paper): 54 % / 67 %; 757 / 491; 100 % / 97 %.
   k = 10, ratio 6.0: 99.5 % / 98.8 %; 27 / 0; 79 % / 33 %.
   k = 4, ratio 6.0 (default): 99.2 % / 98.4 %; 10 / 0; 92 % / 70 %.
   k below the fewest points of a labelled vehicle (`shared.datasets.layout.MIN_LIDAR_POINTS`) lets
   a small vehicle be its own neighbourhood while a lone point still is not. The simulated lidar has
   no spurious returns, so the defaults favour vehicle points.
4. Table removal by height (`shared.detection.lidar.ground.above_table`): the table is flat and at
   ``z = 0`` in the agent frame, so a RANSAC for it (the reference) only re-estimates a known plane.
5. Viaduct deck removal: a RANSAC over the whole cloud for near-horizontal planes picks horizontal
   slices through walls and vehicle sides (every ring of a level lidar lies in one) and removed 71 %
   of vehicle points in a measurement. So, as in the clustering detector, only BEV clusters larger
   than a vehicle are searched, the slab around the plane found is removed within its inlier
   footprint (points standing on it are kept) and the rest is re-clustered, up to ``deck.max_peels``
   times (`ground.peel_slabs`, the loop of the clustering detector too). A plane whose inliers stay
   below ``deck.min_top_m`` is not a deck (vehicle roofs and wall slices at table level) and is left
   alone.
6. Voxel subsampling (off by default): one measured point per voxel, the one nearest the voxel's
   centroid (no synthetic points; intensity stays a measurement).

Limits: the slab is symmetric about the plane found, so when that plane is the deck's top surface the
lowest ~2.5 cm of a vehicle on the deck or a ramp go with it (1.2 % of agent1's vehicle points over
172 frames, all on the viaduct); deck parts seen as sparse, far rings may form clusters smaller than
``deck_min_extent_m`` and stay. The PointPillars model was trained on merged clouds without any of
these stages (`studies.dataset.generate`): give it `merge_clouds` output unless it is retrained on
`preprocess` output.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy import ndimage

from shared.datasets.layout import MIN_LIDAR_POINTS, agent_origin_m
from shared.detection.lidar.ground import SEARCH, SlabSearch, Verdict, above_table, peel_slabs
from shared.geometry._validate import rigid_transform
from shared.scene.scale import LENGTH, Length
from shared.scene.scene import Scene

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

# Columns of a cloud: x, y, z (metres) and intensity.
POINT_COLUMNS = ("x", "y", "z", "intensity")
_XYZ = 3

# Keys of `PreprocessResult.counts`: points left after each stage, in pipeline order ...
STAGES = ("input", "after_crop", "after_outliers", "after_table", "after_deck", "after_voxel")
# ... and the rows dropped for a NaN or infinite value (not a stage that can be switched off).
NON_FINITE = "non_finite"
# BEV cells touching by an edge or a corner belong to one component.
_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)


class LidarPreprocessConfig(BaseModel):
    """Settings of `preprocess`: metres and radians, agent frame (table at ``z = 0``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # crop
    crop_min_m: Annotated[tuple[float, float, float] | None, LENGTH] = Field(
        None, description="lower x, y, z corner of the kept box, m, agent frame (None, with crop_max_m: off)"
    )
    crop_max_m: Annotated[tuple[float, float, float] | None, LENGTH] = Field(
        None, description="upper x, y, z corner of the kept box, m, agent frame (None, with crop_min_m: off)"
    )
    # statistical outlier removal
    remove_outliers: bool = Field(True, description="run statistical outlier removal (open3d)")
    sor_neighbours: int = Field(
        MIN_LIDAR_POINTS - 1,
        ge=1,
        description="k nearest neighbours per point (paper: MeanK 10, which removes far vehicles of 5-10 "
        "points; below the fewest points of a labelled vehicle, a vehicle is its own neighbourhood)",
    )
    sor_std_ratio: float = Field(
        6.0,
        gt=0.0,
        description="remove points whose mean k-NN distance (m) exceeds the cloud's mean by this many "
        "standard deviations (paper: 0.2, which removes 33-46 % of vehicle points here; module docstring)",
    )
    # table
    remove_table: bool = Field(True, description="remove table points by height")
    table_z_m: Length = Field(0.0, description="table surface height in the agent frame, m")
    table_tolerance_m: Length = Field(
        0.02,
        ge=0.0,
        description="points up to this above the table are table, m (simulated table returns reach "
        "0.012 m, the lowest vehicle returns 0.029 m)",
    )
    # viaduct deck
    remove_deck: bool = Field(True, description="remove the viaduct deck (and ramps) found by RANSAC")
    deck_cluster_cell_m: Length = Field(
        0.1,
        gt=0.0,
        description="BEV grid cell of the clusters searched for a deck, m (cells touching by an edge or a "
        "corner join); larger joins more of a sparse far deck, and more vehicles on it",
    )
    deck_min_extent_m: Length = Field(
        0.6,
        gt=0.0,
        description="only clusters whose BEV bounding box is longer than this are searched, m "
        "(a 0.33 x 0.22 m vehicle spans at most 0.4 m)",
    )
    deck: SlabSearch = Field(
        default_factory=lambda: SlabSearch(min_top_m=0.3),  # a default: scaled with the site
        description="the surface search (`shared.detection.lidar.ground.SlabSearch`); min_top_m: a plane is "
        "a deck only if some inlier is at least this high, m (vehicle roofs: 0.21 m, buildings: <= 0.25 m; "
        "deck: 0.4 m)",
    )
    # voxel subsampling
    voxel_size_m: Length = Field(
        0.0, ge=0.0, description="voxel edge, m; keeps the point nearest each voxel's centroid (0: off)"
    )

    @model_validator(mode="after")
    def _crop_box(self) -> LidarPreprocessConfig:
        if (self.crop_min_m is None) != (self.crop_max_m is None):
            raise ValueError("crop_min_m and crop_max_m must be given together")
        lo, hi = self.crop_min_m, self.crop_max_m
        if lo is not None and hi is not None and any(a >= b for a, b in zip(lo, hi, strict=True)):
            raise ValueError("crop_min_m must be below crop_max_m on every axis")
        return self


@dataclass(frozen=True)
class PreprocessResult:
    """Output of `preprocess`.

    Attributes
    ----------
    points : numpy.ndarray, shape (M, 4), float32
        Kept rows of the input (x, y, z in metres, intensity), in input order.
    index : numpy.ndarray, shape (M,), int64
        Row of the input each kept point is (``points == input[index]`` as float32), e.g. to carry
        per-point labels along.
    counts : dict of str to int
        Points left after each stage of `STAGES` (a stage switched off leaves the previous count) and
        ``counts[NON_FINITE]``, the rows dropped for a NaN or infinite value.
    reduction_fraction : float
        ``1 - M / N`` for N input rows (0.0 for an empty input).
    """

    points: NDArray[np.float32]
    index: IntArray
    counts: dict[str, int]
    reduction_fraction: float


def _check_cloud(points: ArrayLike, name: str) -> FloatArray:
    """``points`` as a float64 (N, 4) array; NaN and inf pass (the caller decides), bad shapes raise."""
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != len(POINT_COLUMNS):
        raise ValueError(f"{name} must have shape (N, 4) (x, y, z, intensity), got {arr.shape}")
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be a real numeric array, got dtype {arr.dtype}")
    return np.asarray(arr, dtype=np.float64)


def merge_clouds(scans: Sequence[tuple[ArrayLike, ArrayLike]]) -> NDArray[np.float32]:
    """Map each scan into a common frame by its full SE(3) transform and concatenate all points.

    Parameters
    ----------
    scans : sequence of (T_frame_from_sensor, points)
        ``T_frame_from_sensor``: (4, 4) rigid transform; ``points``: (N_i, 4) x, y, z in the sensor
        frame (metres) and intensity.

    Returns
    -------
    numpy.ndarray, shape (sum N_i, 4), float32
        x, y, z in the common frame (metres) and intensity, scan after scan in input order. Non-finite
        values pass through (`preprocess` drops and counts them).

    Raises
    ------
    ValueError
        A transform that is not a 4x4 rigid transform, or points not shaped (N, 4).
    """
    merged: list[NDArray[np.float32]] = []
    for i, (T, points) in enumerate(scans):
        T_frame = rigid_transform(T, f"scans[{i}] transform")
        cloud = _check_cloud(points, f"scans[{i}] points")
        xyz = cloud[:, :_XYZ] @ T_frame[:3, :3].T + T_frame[:3, 3]
        merged.append(np.column_stack([xyz, cloud[:, _XYZ]]).astype(np.float32))
    if not merged:
        return np.zeros((0, len(POINT_COLUMNS)), np.float32)
    return np.concatenate(merged)


def agent_frame_transforms(scene: Scene, agent_id: str) -> dict[str, FloatArray]:
    """``T_agent_from_sensor`` of each lidar of an agent.

    The agent frame has world axes and its origin at `shared.datasets.layout.agent_origin_m` (mean lidar
    xy, table height), so ``T_agent_from_sensor = translate(-origin) @ T_world_from_sensor``: merging
    with these gives the clouds `studies.dataset.generate.merge_agent_scans` wrote for training, bit for bit
    except where the generator's ``(p + t_sensor) - origin`` cancels (a lidar at the origin): there a
    coordinate near 0 keeps a ~1e-16 m residue that the combined translation here does not have.

    Parameters
    ----------
    scene : Scene
    agent_id : str

    Returns
    -------
    dict of str to numpy.ndarray (4, 4)
        Keyed by lidar id, in scene order.

    Raises
    ------
    ValueError
        The agent has no lidar.
    """
    T_agent_from_world = np.eye(4)
    T_agent_from_world[:3, 3] = -agent_origin_m(scene, agent_id)
    return {
        s.id: T_agent_from_world @ np.asarray(scene.T_world_from_sensor(s.id))
        for s in scene.sensors_of(agent_id, "lidar")
    }


def _crop_mask(xyz: FloatArray, cfg: LidarPreprocessConfig) -> BoolArray:
    """Points inside the closed crop box (all of them without one), (N,)."""
    if cfg.crop_min_m is None or cfg.crop_max_m is None:
        return np.ones(xyz.shape[0], dtype=bool)
    return np.asarray(np.all((xyz >= cfg.crop_min_m) & (xyz <= cfg.crop_max_m), axis=1))


def _statistical_inliers(xyz: FloatArray, neighbours: int, std_ratio: float) -> BoolArray:
    """open3d statistical outlier removal as a mask, (N,); a cloud of at most ``neighbours`` points has
    no statistic to test against and is kept whole."""
    keep = np.ones(xyz.shape[0], dtype=bool)
    if xyz.shape[0] <= neighbours:
        return keep
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        _, kept = cloud.remove_statistical_outlier(nb_neighbors=neighbours, std_ratio=std_ratio)
    keep[:] = False
    keep[np.asarray(kept, dtype=np.int64)] = True
    return keep


def _bev_components(xyz: FloatArray, idx: IntArray, cell_m: float) -> list[IntArray]:
    """Connected components of points ``idx`` on a BEV grid (cells sharing an edge or a corner).

    Returns indices into ``xyz``, one array per component. A grid labelling instead of point-pair
    linking (`shared.detection.lidar.cluster.bev_clusters`): the dense rings near a lidar make
    millions of pairs, and the deck search only needs "larger than a vehicle or not".
    """
    if idx.size == 0:
        return []
    cells = np.floor(xyz[idx, :2] / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    grid = np.zeros(cells.max(axis=0) + 1, dtype=bool)
    grid[cells[:, 0], cells[:, 1]] = True
    labels, _ = ndimage.label(grid, structure=_EIGHT_CONNECTED)
    point_label = labels[cells[:, 0], cells[:, 1]]
    order = np.argsort(point_label, kind="stable")
    return np.split(idx[order], np.flatnonzero(np.diff(point_label[order])) + 1)


def _deck_mask(xyz: FloatArray, cfg: LidarPreprocessConfig) -> BoolArray:
    """Points that are not part of an elevated slab (viaduct deck, ramps), (N,); see the module docstring."""
    if xyz.shape[0] == 0:
        return np.ones(0, dtype=bool)

    def leaf(idx: IntArray, _support_m: FloatArray) -> Literal[Verdict.SEARCH] | None:
        # Vehicle-sized: never searched, so a lone vehicle cannot lose its roof.
        return None if np.ptp(xyz[idx, :2], axis=0).max() < cfg.deck_min_extent_m else SEARCH

    def components(idx: IntArray) -> list[IntArray]:
        return _bev_components(xyz, idx, cfg.deck_cluster_cell_m)

    peeled = peel_slabs(xyz, components(np.arange(xyz.shape[0])), cfg.deck, leaf=leaf, recluster=components)
    return np.asarray(~peeled.slab)


def _voxel_mask(xyz: FloatArray, voxel_m: float) -> BoolArray:
    """One point per occupied voxel, the one nearest the voxel's centroid, (N,)."""
    keep = np.zeros(xyz.shape[0], dtype=bool)
    if xyz.shape[0] == 0:
        return keep
    keys = np.floor(xyz / voxel_m).astype(np.int64)
    _, voxel, size = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    voxel = voxel.reshape(-1)
    centroid = np.column_stack([np.bincount(voxel, weights=xyz[:, d]) for d in range(_XYZ)]) / size[:, None]
    distance = np.sum((xyz - centroid[voxel]) ** 2, axis=1)
    order = np.lexsort((distance, voxel))  # by voxel, nearest first; ties keep input order
    keep[order[np.flatnonzero(np.diff(voxel[order], prepend=-1))]] = True
    return keep


def preprocess(points: ArrayLike, config: LidarPreprocessConfig | None = None) -> PreprocessResult:
    """Crop, remove outliers, the table and the viaduct deck, optionally voxel-subsample.

    Parameters
    ----------
    points : array_like, shape (N, 4)
        x, y, z in the agent frame (metres, table at ``z = 0``) and intensity, e.g. from `merge_clouds`.
        Rows with a NaN or infinite value are dropped and counted.
    config : LidarPreprocessConfig, optional
        Defaults to ``LidarPreprocessConfig()``.

    Returns
    -------
    PreprocessResult
        Kept points (possibly none), their input rows, per-stage counts and the reduction fraction.

    Raises
    ------
    ValueError
        ``points`` is not a real numeric (N, 4) array.
    """
    cfg = config or LidarPreprocessConfig()
    cloud = _check_cloud(points, "points")
    n_input = cloud.shape[0]
    index = np.flatnonzero(np.isfinite(cloud).all(axis=1)).astype(np.int64)
    counts = {STAGES[0]: n_input, NON_FINITE: n_input - index.size}
    xyz = cloud[:, :_XYZ]
    stages: tuple[tuple[str, bool, Callable[[FloatArray], BoolArray]], ...] = (
        ("after_crop", cfg.crop_min_m is not None, lambda p: _crop_mask(p, cfg)),
        (
            "after_outliers",
            cfg.remove_outliers,
            lambda p: _statistical_inliers(p, cfg.sor_neighbours, cfg.sor_std_ratio),
        ),
        ("after_table", cfg.remove_table, lambda p: above_table(p, cfg.table_z_m, cfg.table_tolerance_m)),
        ("after_deck", cfg.remove_deck, lambda p: _deck_mask(p, cfg)),
        ("after_voxel", cfg.voxel_size_m > 0.0, lambda p: _voxel_mask(p, cfg.voxel_size_m)),
    )
    for stage, enabled, mask in stages:
        if enabled:
            index = index[mask(xyz[index])]
        counts[stage] = int(index.size)
    return PreprocessResult(
        points=cloud[index].astype(np.float32),
        index=index,
        counts=counts,
        reduction_fraction=1.0 - index.size / n_input if n_input else 0.0,
    )
