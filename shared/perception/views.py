"""Sensor geometry the fusion steps need, derived once from the scene (no offsets anywhere else).

`CameraView`: intrinsics, extrinsics both ways, image size and centre of one camera, with the three
operations fusion uses: project 3D boxes to image boxes, back-project pixels onto a horizontal plane,
and tell whether an image box touches the image border (a truncated detection).

`RoadSurface`: the height of the driving surface under a point, from the scene's lane centrelines (the
table, the viaduct deck and its ramps), or, at a site without a lane map, the bare ground around the
agent's sensors. A camera-only detection is placed where its viewing ray first meets a lane surface, so
a car on the deck is not projected down to the table.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from shared.geometry.boxes import box2d_centres, box3d_corners
from shared.geometry.camera import box3d_to_image_box, pixel_to_world_on_plane, project_points
from shared.scene.scene import Scene

FloatArray = NDArray[np.float64]

# Fixed-point steps of `CameraView.fit_centre` (the residual shrinks ~10x per step).
CENTRE_FIT_ITERATIONS = 3
# Slack on k-d tree search radii so rounding never drops a sample at the exact limit, metres.
NEAR_M = 1e-6


@dataclass(frozen=True)
class CameraView:
    sensor_id: str
    K: FloatArray
    T_optical_from_world: FloatArray
    T_world_from_optical: FloatArray
    width_px: int
    height_px: int
    distortion: FloatArray | None = None

    @classmethod
    def from_scene(cls, scene: Scene, camera_id: str) -> CameraView:
        spec = scene.sensor(camera_id)
        assert spec.camera is not None
        return cls(
            camera_id,
            np.asarray(scene.K(camera_id), float),
            np.asarray(scene.T_optical_from_world(camera_id), float),
            np.asarray(scene.T_world_from_optical(camera_id), float),
            spec.camera.width_px,
            spec.camera.height_px,
            None if scene.distortion(camera_id) is None else np.asarray(scene.distortion(camera_id), float),
        )

    @property
    def center_m(self) -> FloatArray:
        return self.T_world_from_optical[:3, 3]

    def project(self, points_world: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(N, 3) world points -> (N, 2) pixels and (N,) optical depth (NaN behind the camera)."""
        return project_points(points_world, self.T_optical_from_world, self.K)

    def _project_pinhole(self, points_world: FloatArray) -> tuple[FloatArray, FloatArray]:
        """`project` for an undistorted camera without per-call validation (the view was validated
        once when built): the fusion hot path projects thousands of corners per frame."""
        T = self.T_optical_from_world
        cam = points_world @ T[:3, :3].T + T[:3, 3]
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = (cam[:, :2] / depth[:, None]) * np.diag(self.K)[:2] + self.K[:2, 2]
        uv[~(depth > 0)] = np.nan
        return uv, depth

    def image_boxes(self, boxes3d: FloatArray) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
        """(N, 7) world boxes -> (N, 4) image boxes clamped to the image, visible flags, and `inside`
        flags (every corner in front of the camera and inside the image: not cut by the border).
        Same boxes as `shared.geometry.camera.box3d_to_image_box` (tested)."""
        return self.corner_boxes(box3d_corners(boxes3d).reshape(-1, 8, 3))

    def corner_boxes(self, corners: FloatArray) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
        """`image_boxes` from (N, 8, 3) world corners (compute the corners once for many cameras)."""
        size = np.array([self.width_px, self.height_px], float)
        if self.distortion is not None:
            boxes, visible = box3d_to_image_box(
                corners, self.T_optical_from_world, self.K, self.width_px, self.height_px, self.distortion
            )
            uv, depth = self.project(corners.reshape(-1, 3))
            uv, depth = uv.reshape(-1, 8, 2), depth.reshape(-1, 8)
        else:
            uv, depth = self._project_pinhole(corners.reshape(-1, 3))
            uv, depth = uv.reshape(-1, 8, 2), depth.reshape(-1, 8)
            boxes = np.zeros((len(corners), 4))
            in_front = np.isfinite(uv[:, :, 0]).any(axis=1)
            if in_front.any():
                lo = np.clip(np.nanmin(uv[in_front], axis=1), 0.0, size)
                hi = np.clip(np.nanmax(uv[in_front], axis=1), 0.0, size)
                boxes[in_front] = np.concatenate([lo, hi], axis=1)
            visible = in_front & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        with np.errstate(invalid="ignore"):
            inside = np.all(depth > 0, axis=1) & np.all((uv >= 0) & (uv <= size), axis=(1, 2))
        return boxes, visible, inside

    def to_plane(self, uv_px: FloatArray, z_m: float | FloatArray) -> FloatArray:
        """Pixels -> world points on horizontal planes z = z_m (scalar or one per pixel); NaN rows where
        the ray is parallel to the plane or meets it behind the camera. Undistorted pinhole (the
        scene's cameras); `shared.geometry.camera.pixel_to_world_on_plane` is the validated
        general form (tested equal)."""
        if self.distortion is not None:
            uv = np.asarray(uv_px, float).reshape(-1, 2)
            z = np.broadcast_to(np.asarray(z_m, float), (len(uv),))
            out = np.full((len(uv), 3), np.nan)
            for level in np.unique(z):
                rows = z == level
                out[rows] = pixel_to_world_on_plane(
                    uv[rows],
                    self.T_world_from_optical,
                    self.K,
                    plane_offset=level,
                    distortion=self.distortion,
                )[0]
            return out
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        rays_optical = np.column_stack([(uv - self.K[:2, 2]) / np.diag(self.K)[:2], np.ones(len(uv))])
        rays = rays_optical @ self.T_world_from_optical[:3, :3].T
        origin = self.T_world_from_optical[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (np.asarray(z_m, float) - origin[2]) / rays[:, 2]
        t = np.where(np.isfinite(t) & (t > 0), t, np.nan)
        return origin + t[:, None] * rays

    def fit_centres(self, boxes3d: FloatArray, boxes2d: FloatArray) -> FloatArray:
        """Per row, the xy where `boxes3d[i]` (size, yaw, height kept) projects to a box centred on the
        detected `boxes2d[i]` centre: the box moves by the offset, on the plane of its centre height,
        between the two box centres, repeated (one step is off by the perspective curvature, ~10 % of
        the shift). Comparing box centre with box centre cancels the perspective offset between a 2D
        box's centre and its 3D centre's projection. NaN rows where a viewing ray misses the plane."""
        boxes = np.array(boxes3d, float, copy=True).reshape(-1, 7)
        target = self.to_plane(box2d_centres(boxes2d), boxes[:, 2])
        lost = ~np.isfinite(target).all(axis=1)
        for _ in range(CENTRE_FIT_ITERATIONS):
            proj, visible, _ = self.image_boxes(boxes)
            at = self.to_plane(box2d_centres(proj), boxes[:, 2])
            step = target[:, :2] - at[:, :2]
            lost |= ~visible | ~np.isfinite(step).all(axis=1)
            boxes[~lost, :2] += step[~lost]  # lost rows stay finite (and are reported NaN)
        out = boxes[:, :2]
        out[lost] = np.nan
        return out

    def fit_centre(self, box3d: FloatArray, box2d: FloatArray) -> FloatArray | None:
        """`fit_centres` for one box; None when a ray misses."""
        xy = self.fit_centres(np.asarray(box3d, float)[None], np.asarray(box2d, float)[None, :4])[0]
        return xy if np.isfinite(xy).all() else None

    def touches_border(self, boxes_xyxy: FloatArray, margin_px: float) -> NDArray[np.bool_]:
        b = np.asarray(boxes_xyxy, float).reshape(-1, 4)
        return np.asarray(
            (b[:, 0] <= margin_px)
            | (b[:, 1] <= margin_px)
            | (b[:, 2] >= self.width_px - margin_px)
            | (b[:, 3] >= self.height_px - margin_px)
        )


class RoadSurface:
    """Driving-surface heights sampled along every lane of the scene (or over the bare ground of a site
    without a lane map: z = 0, no direction of travel).

    Parameters
    ----------
    scene : Scene
    half_width_m : float
        A point belongs to a lane sample within this xy distance (half a lane plus margin), metres.
    sample_step_m : float
        Spacing of the samples along lane centrelines and over junction discs, metres (the site's scale:
        `MecSettings.surface_sample_step_m`).
    agent_id : str, optional
        Without a lane map, the ground is sampled around this agent's sensors (default: every sensor).
    """

    def __init__(
        self, scene: Scene, half_width_m: float, sample_step_m: float, agent_id: str | None = None
    ) -> None:
        if not (half_width_m > 0 and sample_step_m > 0):
            raise ValueError(f"half width and sample step must be > 0, got {half_width_m}, {sample_step_m}")
        samples, headings = [], []
        for lane in scene.spec.lanes:
            line = np.asarray(scene.lane_centreline(lane.id), float)
            seg = np.diff(line, axis=0)
            for p, d in zip(line[:-1], seg, strict=True):
                n = max(1, int(np.ceil(np.linalg.norm(d[:2]) / sample_step_m)))
                samples.append(p + np.outer(np.arange(n) / n, d))
                headings.append(np.full(n, np.arctan2(d[1], d[0])))
        # Junction discs (lanes stop at their edge): surface samples without a direction of travel.
        for j in scene.spec.junctions:
            disc = _disc_grid(j.radius_m, sample_step_m)
            samples.append(np.column_stack([disc + j.position_m[:2], np.full(len(disc), j.position_m[2])]))
            headings.append(np.full(len(disc), np.nan))
        if not scene.spec.lanes:
            ground = bare_ground_m(scene, half_width_m, agent_id)
            samples.append(ground)
            headings.append(np.full(len(ground), np.nan))
        self.points_m = np.concatenate(samples)
        self.heading_rad = np.concatenate(headings)  # direction of travel of the lane at each sample
        self.half_width_m = half_width_m
        self._tree = cKDTree(self.points_m[:, :2])  # xy lookups: per radar target, every frame
        # Box any lane hit lies in: the samples' xy extent grown by the half width, their z range.
        reach_xy = np.array([self.half_width_m, self.half_width_m, 0.0])
        self._reach_lo = self.points_m.min(axis=0) - reach_xy
        self._reach_hi = self.points_m.max(axis=0) + reach_xy

    def nearest_sample(self, xy_m: FloatArray, z_range_m: FloatArray | None = None) -> NDArray[np.int64]:
        """Index of the nearest lane sample within `half_width_m` of each (N, 2) point; -1 off-road.

        `z_range_m` (N, 2) `[low, high]`: for points whose height was measured (a radar target), only
        samples with their surface height in that range count, so a car under the deck is not put on
        it (nor one on the deck under it). A point with no sample of its level keeps the nearest one.
        """
        xy = np.asarray(xy_m, float).reshape(-1, 2)
        nearest = np.full(len(xy), -1, dtype=np.int64)
        if len(xy) == 0:
            return nearest
        z_range = None if z_range_m is None else np.asarray(z_range_m, float).reshape(-1, 2)
        # The samples within reach of each point (a few dozen of the ~6000), from the k-d tree.
        for i, cand in enumerate(self._tree.query_ball_point(xy, self.half_width_m)):
            if not cand:
                continue
            idx = np.asarray(cand, dtype=np.int64)
            pts = self.points_m[idx]
            d2 = ((pts[:, :2] - xy[i]) ** 2).sum(axis=1)
            if z_range is not None:
                level = (pts[:, 2] >= z_range[i, 0]) & (pts[:, 2] <= z_range[i, 1])
                if level.any():
                    idx, d2 = idx[level], d2[level]
            nearest[i] = idx[np.argmin(d2)]
        return nearest

    def lane_heading(self, xy_m: FloatArray, z_range_m: FloatArray | None = None) -> FloatArray:
        """Direction of travel of the nearest lane at each (N, 2) point, rad; NaN off-road
        (`z_range_m`: see `nearest_sample`)."""
        idx = self.nearest_sample(xy_m, z_range_m)
        return np.where(idx >= 0, self.heading_rad[idx], np.nan)

    def heights_near(self, xy_m: FloatArray, z_range_m: FloatArray | None = None) -> FloatArray:
        """Surface height under each (N, 2) point: the nearest lane sample's z; NaN off-road
        (`z_range_m`: see `nearest_sample`)."""
        idx = self.nearest_sample(xy_m, z_range_m)
        return np.where(idx >= 0, self.points_m[idx, 2], np.nan)

    def first_hit(self, origin_m: FloatArray, rays_world: FloatArray, height_above_m: float) -> FloatArray:
        """Where each (N, 3) ray from `origin_m` first reaches `height_above_m` over a lane surface.

        Every lane sample defines a candidate plane z = sample z + height_above_m; the ray's crossing
        of that plane counts when it lies within `half_width_m` of the sample. The nearest crossing
        along the ray wins (a ray passes over the deck before reaching the table beneath). NaN rows:
        the ray never meets a lane.
        """
        rays = np.asarray(rays_world, float).reshape(-1, 3)
        o = np.asarray(origin_m, float)
        out = np.full((len(rays), 3), np.nan)
        z = self.points_m[:, 2]
        # Every crossing lies where the ray is between the lowest and the highest plane and within
        # `half_width_m` of the samples' xy extent: only samples within reach of that stretch of the
        # ray can be hit (k-d tree), a few hundred of the ~6000.
        lift = np.array([0.0, 0.0, height_above_m])
        lo, hi = self._reach_lo + lift, self._reach_hi + lift
        with np.errstate(all="ignore"):  # rays (nearly) parallel to a slab divide by ~0
            slabs = np.sort(np.stack([(lo - o) / rays, (hi - o) / rays], axis=-1), axis=-1)  # (N, 3, 2)
            parallel = rays == 0  # parallel to a slab: inside it all along, or never
            slabs[parallel] = [-np.inf, np.inf]
            t_in = np.maximum(slabs[:, :, 0].max(axis=1), 0.0)
            t_out = slabs[:, :, 1].min(axis=1)
            ok = (
                np.isfinite(rays).all(axis=1)
                & ~parallel[:, 2]
                & ~(parallel & ((o < lo) | (o > hi))).any(axis=1)
                & (t_in <= t_out)
                & np.isfinite(t_out)  # a (sub)normal ray so close to level that its crossing overflows
            )
            rows = np.flatnonzero(ok)
            ends = o[None, None, :2] + np.stack([t_in, t_out], axis=1)[rows, :, None] * rays[rows, None, :2]
            reach = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1) / 2 + self.half_width_m + NEAR_M
            near = self._tree.query_ball_point(ends.mean(axis=1), reach) if len(rows) else []
            for i, cand in zip(rows, near, strict=True):
                idx = np.asarray(cand, np.int64)
                ray = rays[i]
                t = (z[idx] + height_above_m - o[2]) / ray[2]
                d2 = ((o[:2] + t[:, None] * ray[:2] - self.points_m[idx, :2]) ** 2).sum(-1)
                t = np.where((t > 0) & (d2 <= self.half_width_m**2), t, np.inf)
                if len(t) and np.isfinite(t_best := t.min()):
                    out[i] = o + t_best * ray
        return out


def _disc_grid(radius_m: float, step_m: float) -> FloatArray:
    """(N, 2) points of a square grid of `step_m` inside a disc of `radius_m` about the origin."""
    r = np.arange(-radius_m, radius_m + 1e-9, step_m)
    gx, gy = np.meshgrid(r, r)
    disc = np.column_stack([gx.ravel(), gy.ravel()])
    return disc[(disc**2).sum(1) <= radius_m**2]


def bare_ground_m(scene: Scene, half_width_m: float, agent_id: str | None = None) -> FloatArray:
    """(N, 3) samples of the ground (z = 0) of a site without a lane map: a grid over the disc around each
    of the agent's sensors (every sensor without `agent_id`) as far as it sees (a lidar's or radar's
    max_range_m, a camera's far_m). The grid spacing is `half_width_m`, so every point of the disc lies
    within `half_width_m` of a sample and the size of the grid follows the site's scale."""
    parts = []
    for s in scene.sensors_of(agent_id):
        reach_m = s.camera.far_m if s.camera is not None else (s.lidar or s.radar).max_range_m  # type: ignore[union-attr]
        parts.append(_disc_grid(reach_m, half_width_m) + np.asarray(scene.T_world_from_sensor(s.id))[:2, 3])
    if not parts:
        raise ValueError(f"scene {scene.scene_id} has neither lanes nor sensors: no surface to sample")
    xy = np.unique(np.round(np.concatenate(parts) / half_width_m).astype(np.int64), axis=0) * half_width_m
    return np.column_stack([xy, np.zeros(len(xy))])
