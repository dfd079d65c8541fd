"""Classical lidar detector: ground removal, BEV clustering and vehicle-prior box fitting.

Input: one agent's merged cloud in the agent frame (world axes, z = 0 on the table, metres). Steps:

1. Range crop: BEV distance to the nearest lidar (``sensor_xy_m``) in [min_range, max_range] and z in
   [z_min, z_max].
2. Table removal by height (``z <= table_z_m + ground_tolerance_m``; the table is flat and at a
   known height, see `shared.detection.lidar.ground`). With a fitted ground plane (`ground`: a real
   site's sloped or offset ground), heights (this removal, the z crop, the support of every point) are
   measured from that plane instead.
3. BEV clustering: single-linkage connected components (scipy KD-tree + sparse connected components)
   of points within a range-dependent ellipse aligned with the line of sight: across it
   ``clip(eps_per_m * range, eps_min, eps_max)`` (the azimuth step grows with range), along it
   ``clip(radial_eps_per_m2 * range^2, across, radial_eps_max)`` (a lidar above the vehicles sees its
   roof as rings whose BEV spacing grows with range squared). Clustering in BEV joins the rings of one
   vehicle's side faces, which are up to ~15 cm apart vertically at 2 m.
4. Elevated surfaces (`ground.peel_slabs`, shared with the MEC's lidar preprocessing): a cluster larger
   than a vehicle in BEV is searched for a near-horizontal plane (RANSAC); the slab around it (viaduct
   deck: top, sides, underside) is removed, points standing on it get the plane as their support
   height, and the rest is re-clustered. This repeats up to ``surfaces.max_peels`` times per cluster
   (ramps are several planes). Clusters that stay too large (buildings, a deck with nothing left to
   peel) are dropped.
5. Filters: point count, BEV extent (vehicle-sized, not a pole), height above the support surface.
6. Box: L-shape fit with the vehicle size as a prior (`box_fit`): the visible face(s) are extended to the
   prior size away from the sensor. z = support + height / 2. Score = ``n / (n + score_half_points)``
   for a cluster of ``n`` points.

Limits: vehicles closer than one clustering radius merge (then fail the size filter); a vehicle on the
deck seen only from below (the lidar under the deck level) may stay connected to the deck edge; when the
plane found is the deck's underside, the support height of vehicles on it is low by the deck thickness.
Yaw is in [-pi/2, pi/2) (front and back are indistinguishable).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from shared.detection.interface import CAR_CLASS_ID, check_points, empty_lidar_detections
from shared.detection.lidar.box_fit import BoxFitParams, FittedBox, fit_vehicle_box
from shared.detection.lidar.ground import (
    SEARCH,
    Plane,
    SlabSearch,
    Verdict,
    above_table,
    cell_keys,
    peel_slabs,
)
from shared.scene.model import SceneSpec
from shared.scene.scale import Length, PerLength, Ratio, SiteScale, at_scale, from_scene

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# cluster_grid: cells per smallest linking radius (2 sqrt(2) cells, two touching cells' span, < 1 radius).
_CELLS_PER_MIN_RADIUS = 4.0
# ring_radial_eps_per_m2: rings linked up to 1.5 gaps apart (one ring lost to noise or an edge: half more).
_RING_MARGIN = 1.5
# oversize_splits: each split links at half the radii of the step before.
_SPLIT_RADIUS = 0.5
# Guards the line-of-sight direction of a point at the sensor's own position, metres.
_MIN_RANGE_M = 1e-6


class ClusterLidarConfig(BaseModel):
    """Settings of `ClusterLidarDetector`: metres, radians, agent frame."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # range crop
    sensor_xy_m: Annotated[tuple[tuple[float, float], ...], from_scene("the agent's lidars")] = Field(
        ((0.0, 0.0),),
        min_length=1,
        description="xy of the agent's lidars in the agent frame (range, and the hidden side of a single "
        "face); the default, the agent origin, is exact for a one-lidar agent",
    )
    min_range_m: Length = Field(0.1, ge=0.0, description="drop points nearer (BEV) to a lidar than this")
    max_range_m: Length = Field(6.0, gt=0.0, description="drop points farther (BEV) from every lidar")
    z_min_m: Length = Field(-0.1, description="drop points below this height")
    z_max_m: Length = Field(1.0, description="drop points above this height")
    # table
    table_z_m: Length = Field(0.0, description="table surface height in the agent frame")
    ground_tolerance_m: Length = Field(
        0.02, ge=0.0, description="points up to this above the table are table"
    )
    # elevated surfaces (viaduct deck)
    surfaces: SlabSearch = Field(
        default_factory=SlabSearch, description="search for surfaces in clusters larger than a vehicle"
    )
    # clustering
    cluster_eps_min_m: Length = Field(0.05, gt=0.0, description="clustering radius near the lidar")
    cluster_eps_per_m: Ratio = Field(
        0.03,
        ge=0.0,
        description="radius growth per metre of range (~1.2x the 32-line lidar's 0.025 rad step)",
    )
    cluster_eps_max_m: Length = Field(0.12, gt=0.0, description="largest clustering radius")
    cluster_radial_eps_per_m2: PerLength = Field(
        0.06,
        ge=0.0,
        description="radius along the line of sight per squared metre of range: rings on a roof lie "
        "~range^2 * (0.023 rad channel step) / (0.41 m sensor height above the roof) apart",
    )
    cluster_radial_eps_max_m: Length = Field(
        0.25, gt=0.0, description="largest radius along the line of sight"
    )
    cluster_grid: bool | None = Field(
        None,
        description="link BEV cells of a quarter of the smallest radius (cluster_eps_min_m / 4) through "
        "their mean points instead of every pair of points: the points of one cell, and of two cells that "
        "touch, are within every radius (linked either way); cells farther apart are linked when their means "
        "are (an approximation within a cell's size). A dense lidar's near car has ~1500 points and "
        "~300 000 pairs within its radius, a few hundred cells. None: on for the `background` detector (a "
        "real-size site's dense foreground), off for `cluster` (the table's sparse clouds, exact)",
    )
    oversize_splits: int | None = Field(
        None,
        ge=0,
        description="a cluster longer (BEV diagonal) than the largest vehicle's length gate is clustered "
        "again with its radii halved, up to this many times, before the surface search: vehicles queued "
        "closer than a radius (a car 1 m behind a truck, 28 m from an RS-LiDAR-32: 1.1 m radial radius). "
        "None: 2 for the `background` detector, 0 for `cluster` (the table's deck clusters keep their "
        "surface search)",
    )
    min_points: int = Field(5, ge=1, description="fewest points of a vehicle cluster")
    # vehicle prior and filters
    vehicle_size_m: Annotated[tuple[float, float, float] | None, from_scene("the scene's vehicle")] = Field(
        None, description="length, width, height prior, m (the MEC sets the scene's vehicle; required)"
    )
    vehicle_classes_m: Annotated[
        tuple[tuple[float, float, float], ...], from_scene("its vehicle classes")
    ] = Field(
        (),
        description="length, width, height of the scene's further vehicle classes (vans, trucks), m: a "
        "cluster larger than the prior is boxed with the smallest class it fits (none: not a vehicle), "
        "and the size gates (max_length_m, max_width_m, max_height_m, stated for the prior) give each class "
        "the prior's margin over its size",
    )
    min_extent_m: Length = Field(0.08, ge=0.0, description="longest BEV side must reach this (rejects poles)")
    overhead_gap_m: Length = Field(
        0.055,
        gt=0.0,
        description="a cluster taller than its vehicle class's height gate, whose points leave a vertical "
        "gap this large, is a vehicle under an overhead structure (a signal head, a mast arm, a crown): "
        "the points above the lowest such gap are dropped (0.75 m at the intersection: a signal head "
        "hangs 3.1 m over a car's roof, a crown 1 m)",
    )
    max_length_m: Length = Field(0.45, gt=0.0, description="longest BEV side of a vehicle cluster")
    max_width_m: Length = Field(0.32, gt=0.0, description="shorter BEV side of a vehicle cluster")
    min_height_m: Length = Field(0.05, ge=0.0, description="cluster top above its support surface, at least")
    max_height_m: Length = Field(0.30, gt=0.0, description="cluster top above its support surface, at most")
    # box fit
    angle_step_rad: float = Field(math.radians(1.0), gt=0.0, description="coarse L-shape angle step")
    closeness_min_m: Length = Field(0.01, gt=0.0, description="d0 of the closeness criterion")
    flat_face_m: Length = Field(0.04, gt=0.0, description="cluster depth below which it is a single face")
    edge_band_m: Length = Field(0.02, gt=0.0, description="band at a rectangle edge for counting its points")
    edge_support_ratio: float = Field(2.0, ge=1.0, description="point ratio that marks the visible edge")
    size_tolerance_m: Length = Field(0.03, ge=0.0, description="measured sizes within this of the prior")
    face_quantile: Ratio = Field(
        0.5,
        ge=0.5,
        lt=1.0,
        description="where in its edge band a visible face lies, toward the edge: 0.5 the median (a face "
        "seen square); higher for a lidar looking down on roofs (shared/detection/lidar/box_fit.py)",
    )
    # score
    score_half_points: float = Field(20.0, gt=0.0, description="points at which the score is 0.5")

    @classmethod
    def for_scene(cls, spec: SceneSpec) -> ClusterLidarConfig:
        """The defaults at the scale of a scene, with its vehicle as the prior and its further classes
        (lidars at the origin of the frame: a dataset's agent frames; the MEC also sets its lidars,
        `MecSettings.for_site`)."""
        classes = tuple(c.size_m for c in spec.vehicle_classes)
        return at_scale(
            cls(vehicle_size_m=spec.vehicle.size_m, vehicle_classes_m=classes), SiteScale.of(spec)
        )

    @model_validator(mode="after")
    def _ranges(self) -> ClusterLidarConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError("min_range_m must be below max_range_m")
        if self.z_min_m >= self.z_max_m:
            raise ValueError("z_min_m must be below z_max_m")
        if self.cluster_eps_min_m > self.cluster_eps_max_m:
            raise ValueError("cluster_eps_min_m must not exceed cluster_eps_max_m")
        if self.vehicle_size_m is not None and min(self.vehicle_size_m) <= 0.0:
            raise ValueError("vehicle_size_m must be positive")
        return self


def ring_radial_eps_per_m2(
    elevations_rad: Sequence[FloatArray], heights_above_roof_m: Sequence[float]
) -> float:
    """Radius along the line of sight per squared metre of range that links a vehicle roof's rings, for
    the given lidars (their channel elevations, rad, and their heights above the roof, m): a lidar h above
    a roof sees its channels ``dEl`` apart there ``range^2 * dEl / h`` apart in BEV. ``dEl`` is the lidar's
    median gap between adjacent channels (a roadside unit's dense band, where it looks along the roads),
    times `_RING_MARGIN`; the largest over the lidars.

    Parameters
    ----------
    elevations_rad : sequence of numpy.ndarray
        Each lidar's channel elevations, radians.
    heights_above_roof_m : sequence of float
        Each lidar's height above a vehicle roof, metres (> 0).

    Returns
    -------
    float
        Per metre of range squared (``PerLength``).
    """
    out = 0.0
    for elevations, height in zip(elevations_rad, heights_above_roof_m, strict=True):
        gaps = np.diff(np.sort(np.asarray(elevations, np.float64)))
        if gaps.size == 0 or height <= 0.0:
            raise ValueError("a lidar needs two channels and a height above the roof to space its rings")
        out = max(out, _RING_MARGIN * float(np.median(gaps)) / height)
    return out


def nearest_sensor(xy: FloatArray, sensors: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Nearest of (S, 2) sensors to each of (N, 2) points: its position (N, 2) and BEV distance (N,), m."""
    dist = np.linalg.norm(xy[:, None, :] - sensors[None, :, :], axis=2)
    k = np.argmin(dist, axis=1)
    return sensors[k], dist[np.arange(xy.shape[0]), k]


def candidate_pairs(xy: FloatArray, reach_m: FloatArray) -> tuple[IntArray, IntArray]:
    """Pairs ``i < j`` of (N, 2) points closer than the larger of their two reaches (N,), metres.

    Each point's neighbours are searched within its own reach (one KD-tree ball query per point, the
    library's C loop), not within the largest reach of all: with radii that grow with range, the far
    points' reach would otherwise be searched around the dense near points too (pairs grow with the
    square of the radius). A pair found from both sides is listed twice.
    """
    neighbours = cKDTree(xy).query_ball_point(xy, reach_m, return_sorted=False)
    counts = np.fromiter(map(len, neighbours), dtype=np.int64, count=xy.shape[0])
    if counts.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    a = np.repeat(np.arange(xy.shape[0], dtype=np.int64), counts)
    b = np.concatenate(neighbours).astype(np.int64)
    other = a != b
    a, b = a[other], b[other]
    return np.minimum(a, b), np.maximum(a, b)


def bev_clusters(
    xy: FloatArray, origin_xy: FloatArray, tangential_m: FloatArray, radial_m: FloatArray
) -> list[IntArray]:
    """Connected components of points linked within an ellipse aligned with the line of sight.

    Two points ``i, j`` link when ``(dt / et)^2 + (dr / er)^2 <= 1``, where ``dr`` and ``dt`` are the
    components of ``xy[j] - xy[i]`` along and across the direction from ``origin_xy[i]`` to ``xy[i]``, and
    ``et``, ``er`` are the larger of the two points' tangential and radial radii.

    Parameters
    ----------
    xy : numpy.ndarray, shape (N, 2)
        Points, metres.
    origin_xy : numpy.ndarray, shape (N, 2)
        Lidar that saw each point (the nearest one), metres.
    tangential_m, radial_m : numpy.ndarray, shape (N,)
        Linking radii across and along the line of sight, metres (> 0).

    Returns
    -------
    list of numpy.ndarray
        Indices into ``xy`` of each component (singletons included), ascending within a component.
    """
    n = xy.shape[0]
    if n == 0:
        return []
    i, j = candidate_pairs(xy, np.maximum(tangential_m, radial_m))
    sight = xy[i] - origin_xy[i]
    sight /= np.maximum(np.linalg.norm(sight, axis=1, keepdims=True), _MIN_RANGE_M)
    delta = xy[j] - xy[i]
    dr = np.einsum("kd,kd->k", delta, sight)
    dt = delta[:, 0] * sight[:, 1] - delta[:, 1] * sight[:, 0]
    et = np.maximum(tangential_m[i], tangential_m[j])
    er = np.maximum(radial_m[i], radial_m[j])
    linked = (dt / et) ** 2 + (dr / er) ** 2 <= 1.0
    graph = coo_matrix((np.ones(int(linked.sum())), (i[linked], j[linked])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    order = np.argsort(labels, kind="stable")
    return [c.astype(np.int64) for c in np.split(order, np.flatnonzero(np.diff(labels[order])) + 1)]


class ClusterLidarDetector:
    """Clustering lidar detector (pipeline and limits in the module docstring).

    Parameters
    ----------
    config : ClusterLidarConfig
        With `vehicle_size_m` set (the MEC sets it, with the sensor positions, from the scene).
    """

    name = "cluster"

    def __init__(self, config: ClusterLidarConfig) -> None:
        if config.vehicle_size_m is None:
            raise ValueError("the cluster detector needs vehicle_size_m (the scene's vehicle)")
        self.config = config
        # The ground in the agent frame, when known from the data (the MEC fits it to the background
        # model's static points, `shared.perception.background.AgentGround`); None: the table at table_z_m.
        self.ground: Plane | None = None
        # Which lidar each point of the next cloud came from (an index into `sensor_xy_m`), when the
        # agent has several: set by the MEC before each `detect`, which takes it and clears it. A
        # cluster's visible faces and its points' linking radii are then those of the lidar that saw
        # them: a car beside one pole, under that lidar's lowest ring, may be seen only by the lidar
        # across the crossing. None (or a length that does not match the cloud): each point's nearest.
        self.point_sensor: IntArray | None = None
        self._src: IntArray | None = None
        self._prior_m: tuple[float, float, float] = config.vehicle_size_m
        cfg = self.config
        self._sensors = np.asarray(cfg.sensor_xy_m, dtype=np.float64).reshape(-1, 2)
        # The prior first, then the larger classes by length (a cluster takes the first it fits in).
        larger = sorted(
            c for c in cfg.vehicle_classes_m if c[0] > self._prior_m[0] or c[1] > self._prior_m[1]
        )
        self._classes = [self._prior_m, *larger]
        self._fits = [
            BoxFitParams(
                length_m=length,
                width_m=width,
                angle_step_rad=cfg.angle_step_rad,
                closeness_min_m=cfg.closeness_min_m,
                flat_face_m=cfg.flat_face_m,
                edge_band_m=cfg.edge_band_m,
                edge_support_ratio=cfg.edge_support_ratio,
                size_tolerance_m=cfg.size_tolerance_m,
                face_quantile=cfg.face_quantile,
            )
            for length, width, _ in self._classes
        ]
        # The gates are stated for the prior: the largest class gets the same margin over its size
        # (exactly the settings without further classes). The height gate is each class's own.
        self._max_length_m, self._max_width_m = cfg.max_length_m, cfg.max_width_m
        if larger:
            longest, widest = max(c[0] for c in larger), max(c[1] for c in larger)
            self._max_length_m = max(cfg.max_length_m, longest + cfg.max_length_m - self._prior_m[0])
            self._max_width_m = max(cfg.max_width_m, widest + cfg.max_width_m - self._prior_m[1])
        self._max_height_m = [cfg.max_height_m] + [
            h + cfg.max_height_m - self._prior_m[2] for *_, h in larger
        ]

    def detect(self, points: np.ndarray) -> np.ndarray:
        """Detect vehicles in one agent cloud.

        Parameters
        ----------
        points : numpy.ndarray, shape (N, 4)
            x, y, z, intensity in the agent frame, float32/float64.

        Returns
        -------
        numpy.ndarray, shape (M, 9), float32
            ``[x, y, z, dx, dy, dz, yaw, score, class_id]`` by descending score.

        Raises
        ------
        DetectorInputError
            Wrong shape / dtype or non-finite values.
        """
        check_points(points)
        cfg = self.config
        src, self.point_sensor = self.point_sensor, None
        if src is not None and (len(src) != len(points) or np.any((src < 0) | (src >= len(self._sensors)))):
            src = None
        xyz = np.asarray(points[:, :3], dtype=np.float64)
        ground_z = self._ground_z(xyz[:, :2])
        keep = self._in_range(xyz, ground_z, src) & above_table(xyz, ground_z, cfg.ground_tolerance_m)
        xyz, ground_z = xyz[keep], ground_z[keep]
        if xyz.shape[0] == 0:
            return empty_lidar_detections()
        self._src = None if src is None else np.asarray(src, np.int64)[keep]

        def leaf(idx: IntArray, support_m: FloatArray) -> list[float] | Literal[Verdict.SEARCH] | None:
            if idx.size < cfg.min_points:
                return None
            if self._src is None:
                sensor, _ = nearest_sensor(xyz[idx, :2].mean(axis=0, keepdims=True), self._sensors)
            else:  # the lidar that gave most of its points
                sensor = self._sensors[np.bincount(self._src[idx]).argmax()][None]
            fit = fit_vehicle_box(xyz[idx, :2], sensor[0], self._fits[0])
            if fit.extent_length > self._max_length_m or fit.extent_width > self._max_width_m:
                return SEARCH
            k = self._class_of(fit)
            if k is None:  # no vehicle class is that wide or long (a tree's crown, a wall)
                return None
            under = self._under_overhead(idx, xyz[idx, 2] - support_m[idx], self._max_height_m[k])
            if under.size < idx.size:  # fitted again without the overhead structure's points
                return leaf(under, support_m)
            if k > 0:  # larger than the prior: boxed with the class it fits
                fit = fit_vehicle_box(xyz[idx, :2], sensor[0], self._fits[k])
            return self._box_row(xyz[idx], support_m[idx], fit, k)

        try:
            peeled = peel_slabs(
                xyz,
                self._cluster(xyz, np.arange(xyz.shape[0])),
                cfg.surfaces,
                leaf=leaf,
                recluster=lambda idx: self._cluster(xyz, idx),
                base_z_m=ground_z,
            )
        finally:
            self._src = None  # this cloud's only
        rows = [row for row in peeled.leaves if row is not None]
        if not rows:
            return empty_lidar_detections()
        out = np.asarray(rows, dtype=np.float32)
        return out[np.argsort(-out[:, 7], kind="stable")]

    def _ground_z(self, xy: FloatArray) -> FloatArray:
        """Ground height under (N, 2) points: the table's, or the fitted ground plane's (`ground`), m."""
        if self.ground is None:
            return np.full(xy.shape[0], self.config.table_z_m)
        return self.ground.height_at(xy)

    def _in_range(self, xyz: FloatArray, ground_z: FloatArray, src: IntArray | None) -> NDArray[np.bool_]:
        cfg = self.config
        _, r = self._sensor_of(xyz[:, :2], src)
        # Heights in the agent frame on the table (z_min_m / z_max_m as given), above the ground's plane
        # where one was fitted.
        z = xyz[:, 2] if self.ground is None else xyz[:, 2] - ground_z
        return np.asarray(
            (r >= cfg.min_range_m) & (r <= cfg.max_range_m) & (z >= cfg.z_min_m) & (z <= cfg.z_max_m)
        )

    def _cluster(self, xyz: FloatArray, idx: IntArray) -> list[IntArray]:
        """Clusters (global indices) of the points ``idx``; one longer than any vehicle class is clustered
        again with its radii halved, up to `oversize_splits` times (vehicles queued closer than a radius)."""
        clusters = self._link(xyz, idx, 1.0)
        for step in range(1, (self.config.oversize_splits or 0) + 1):
            out: list[IntArray] = []
            for c in clusters:
                extent = np.ptp(xyz[c, :2], axis=0)
                too_long = c.size >= self.config.min_points and math.hypot(*extent) > self._max_length_m
                out += self._link(xyz, c, _SPLIT_RADIUS**step) if too_long else [c]
            clusters = out
        return clusters

    def _link(self, xyz: FloatArray, idx: IntArray, factor: float) -> list[IntArray]:
        """Connected components (global indices) of the points ``idx`` at `factor` times the radii."""
        cfg = self.config
        if idx.size == 0:  # a slab peeled off every point of a cluster: nothing left to link
            return []
        xy = xyz[idx, :2]
        src = None if self._src is None else self._src[idx]
        if not cfg.cluster_grid:
            return [idx[c] for c in bev_clusters(xy, *self._radii(xy, factor, src))]
        # One node per BEV cell (its mean point). Two points of one cell or of two cells that touch are at
        # most 2 sqrt(2) cells = 0.71 eps_min apart, within every point's radius: linked point by point
        # too, and so are their cells' means.
        cell_m = factor * cfg.cluster_eps_min_m / _CELLS_PER_MIN_RADIUS
        cells, point_cell = np.unique(cell_keys(xy, cell_m), return_inverse=True)
        count = np.bincount(point_cell, minlength=cells.size).astype(np.float64)
        means = np.column_stack(
            [np.bincount(point_cell, xy[:, k], minlength=cells.size) / count for k in range(2)]
        )
        cell_src = None
        if src is not None:  # a cell's lidar: the one that gave most of its points
            votes = np.bincount(
                point_cell * len(self._sensors) + src, minlength=cells.size * len(self._sensors)
            )
            cell_src = votes.reshape(cells.size, len(self._sensors)).argmax(axis=1)
        label = np.empty(cells.size, np.int64)
        for k, members in enumerate(bev_clusters(means, *self._radii(means, factor, cell_src))):
            label[members] = k
        point_label = label[point_cell]
        order = np.argsort(point_label, kind="stable")  # ascending indices within a cluster
        return [idx[c] for c in np.split(order, np.flatnonzero(np.diff(point_label[order])) + 1)]

    def _sensor_of(self, xy: FloatArray, src: IntArray | None) -> tuple[FloatArray, FloatArray]:
        """Each point's lidar (N, 2) and BEV distance to it (N,), m: `src`'s, else the nearest."""
        if src is None:
            return nearest_sensor(xy, self._sensors)
        origin = self._sensors[src]
        return origin, np.linalg.norm(xy - origin, axis=1)

    def _radii(
        self, xy: FloatArray, factor: float = 1.0, src: IntArray | None = None
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Each point's lidar (`src`, else the nearest) (N, 2) and the linking radii across and along its
        line of sight (N,) each, m, times `factor`."""
        cfg = self.config
        origin, r = self._sensor_of(xy, src)
        tangential = np.clip(cfg.cluster_eps_per_m * r, cfg.cluster_eps_min_m, cfg.cluster_eps_max_m)
        radial = np.clip(cfg.cluster_radial_eps_per_m2 * r**2, tangential, cfg.cluster_radial_eps_max_m)
        if factor == 1.0:
            return origin, tangential, radial
        return origin, tangential * factor, radial * factor

    def _under_overhead(self, idx: IntArray, height_m: FloatArray, gate_m: float) -> IntArray:
        """The points `idx` (heights `height_m` above their support) below the lowest vertical gap of
        `overhead_gap_m` when they reach above the height gate `gate_m` and start within that gap of
        their support, as a vehicle does (all of them otherwise: a tree's crown, 2.5 m up, is not cut
        into a car-sized piece)."""
        gap_m = self.config.overhead_gap_m
        if height_m.size == 0 or float(height_m.max()) <= gate_m or float(height_m.min()) > gap_m:
            return idx  # short enough, or standing on nothing (a tree's crown): the gates decide
        z = np.sort(height_m)
        gaps = np.flatnonzero(np.diff(z) > gap_m)
        if gaps.size == 0:
            return idx
        return idx[height_m <= z[gaps[0]]]

    def _class_of(self, fit: FittedBox) -> int | None:
        """Index into the classes (0: the prior) of the smallest whose length and width hold the fitted
        extents (within the size tolerance); with further classes None if none does, without them the
        prior (its gates decide)."""
        tol = self.config.size_tolerance_m
        for k, (length, width, _) in enumerate(self._classes):
            if fit.extent_length <= length + tol and fit.extent_width <= width + tol:
                return k
        return None if len(self._classes) > 1 else 0

    def _box_row(self, pts: FloatArray, support: FloatArray, fit: FittedBox, k: int) -> list[float] | None:
        """Detection row of a vehicle-sized cluster of class `k` (0: the prior), or None if it fails the
        extent / height filters (the height: its class's gate: a car's footprint 6 m tall is a mast)."""
        cfg = self.config
        if max(fit.extent_length, fit.extent_width) < cfg.min_extent_m:
            return None
        base = float(np.median(support))
        height = float(pts[:, 2].max()) - base
        if not cfg.min_height_m <= height <= self._max_height_m[k]:
            return None
        prior_h = self._classes[k][2]
        dz = prior_h if height <= prior_h + cfg.size_tolerance_m else height
        n = pts.shape[0]
        score = n / (n + cfg.score_half_points)
        return [fit.x, fit.y, base + dz / 2.0, fit.length, fit.width, dz, fit.yaw, score, float(CAR_CLASS_ID)]
