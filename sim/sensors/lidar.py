"""Lidar model: spinning multi-channel lidar, fast because the scene is static.

At construction every ray of one revolution is ray-cast once against the static world and its range
kept. A generic lidar's rays start at the sensor origin: channels evenly spaced from
`vertical_min_rad` to `vertical_max_rad` inclusive, `horizontal_samples` azimuths over 360 deg,
azimuth 0 = sensor +x, counter-clockwise. A device lidar (`LidarModel.device`, a Robosense unit) fires
the device's rays: azimuth sample i is the device's firing `firing_of_sample` (clockwise from +x, as
the unit spins), each channel at the example unit's calibrated angles, from the lens centre, so the
emulated unit's packets describe exactly these rays (range = distance from the lens). Each scan, only the
rays that can reach a vehicle (ray vs the vehicle's oriented box, vectorised) are cast against the
vehicle world, each truncated at its static range, so static obstacles occlude vehicles and vehicles
occlude the scene. Gaussian range noise is added along the ray; returns outside
[min_range_m, max_range_m] are dropped.

Points are in the sensor frame (+x forward, +y left, +z up), metres. Ray index = channel *
horizontal_samples + azimuth index. Intensity is a fixed reflectivity in [0, 1] per kind of surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pybullet as pb
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from scipy.spatial.transform import Rotation

from shared.devices import robosense
from shared.perception.decode import point_cloud_message
from shared.scene.model import LidarModel
from shared.scene.scene import Scene
from sim.world import StaticWorld, VehiclePose, VehicleWorld

RAY_BATCH_SIZE = pb.MAX_RAY_INTERSECTION_BATCH_SIZE - 1  # PyBullet's limit per rayTestBatch call
NO_HIT_BODY = -1  # rayTestBatch objectUniqueId of a ray that hit nothing
MIN_DIRECTION = 1e-12  # direction components below this are clamped (slab test without 0 / 0)

# Reflectivity per surface kind (static kinds are StaticWorld.body_kind values; others are objects).
INTENSITY_VEHICLE = 0.8
INTENSITY_TABLE = 0.15
INTENSITY_STRUCTURE = 0.45  # viaduct deck, pillars
INTENSITY_OBJECT = 0.6  # buildings, poles, other static objects
STATIC_INTENSITY = {"table": INTENSITY_TABLE, "viaduct": INTENSITY_STRUCTURE, "pillar": INTENSITY_STRUCTURE}


@dataclass(frozen=True)
class LidarScan:
    """One revolution's returns (N points)."""

    sensor_id: str
    points_m: np.ndarray  # (N, 3) float32, sensor frame
    intensity: np.ndarray  # (N,) float32 in [0, 1]
    vehicle_ids: np.ndarray  # (N,) str: vehicle hit, "" for the static scene (ground truth)
    ray_index: np.ndarray  # (N,) int32, channel * horizontal_samples + azimuth index
    channel: np.ndarray  # (N,) int32
    range_m: np.ndarray  # (N,) float32, measured (noisy) range

    def __len__(self) -> int:
        return len(self.range_m)


@dataclass(frozen=True)
class RayHits:
    """Noise-free first hit of every ray: range (inf = none within max range), vehicle index into the
    poses (-1 = static scene or nothing)."""

    range_m: np.ndarray  # (R,) float64
    vehicle: np.ndarray  # (R,) int64


def ray_directions(model: LidarModel) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions (R, 3) in the sensor frame and each ray's channel (R,), channel-major."""
    elevation = np.linspace(model.vertical_min_rad, model.vertical_max_rad, model.channels)
    azimuth = np.arange(model.horizontal_samples) * (2 * np.pi / model.horizontal_samples)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    channel = np.repeat(np.arange(model.channels, dtype=np.int32), model.horizontal_samples)
    return dirs.reshape(-1, 3), channel


def ray_layout(model: LidarModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray origins (R, 3), unit directions (R, 3) in the sensor frame and each ray's channel (R,),
    channel-major (ray = channel * horizontal_samples + azimuth sample)."""
    if model.device is None:
        dirs, channel = ray_directions(model)
        return np.zeros_like(dirs), dirs, channel
    device = robosense.MODELS[model.device]
    geometry = robosense.firing_geometry(
        device, model.rpm, np.asarray(device.example_vertical_deg), np.asarray(device.example_horizontal_deg)
    )
    firing = robosense.firing_of_sample(model.horizontal_samples, len(geometry.firing_az))
    # (F, L, 3) -> (L, H, 3): channel-major over the sampled firings
    origins = geometry.origin_m[firing].transpose(1, 0, 2).reshape(-1, 3)
    dirs = geometry.direction[firing].transpose(1, 0, 2).reshape(-1, 3)
    channel = np.repeat(np.arange(model.channels, dtype=np.int32), model.horizontal_samples)
    return origins, dirs, channel


def cast_rays(client: int, origin: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast segments origin -> ends (R, 3) in chunks (origin (3,) or one per ray (R, 3)); hit
    fraction (R,; inf = none), body id (R,)."""
    fraction = np.full(len(ends), np.inf)
    body = np.full(len(ends), NO_HIT_BODY, np.int64)
    origins = np.broadcast_to(origin, ends.shape)
    for i in range(0, len(ends), RAY_BATCH_SIZE):
        chunk = ends[i : i + RAY_BATCH_SIZE]
        starts = origins[i : i + RAY_BATCH_SIZE].tolist()
        results = pb.rayTestBatch(starts, chunk.tolist(), physicsClientId=client)
        ids = np.fromiter((r[0] for r in results), np.int64, len(results))
        frac = np.fromiter((r[2] for r in results), np.float64, len(results))
        hit = ids != NO_HIT_BODY
        body[i : i + len(chunk)] = ids
        fraction[i : i + len(chunk)] = np.where(hit, frac, np.inf)
    return fraction, body


def rays_hitting_boxes(
    origin: np.ndarray,
    dirs: np.ndarray,
    length_m: np.ndarray,
    centres: np.ndarray,
    rotations: np.ndarray,
    half_m: np.ndarray,
) -> np.ndarray:
    """(R,) mask of rays (origin + t * dirs, unit dirs, 0 <= t <= length_m) that touch any oriented box.

    centres (V, 3), rotations (V, 3, 3) box-to-world, half_m (3,) or (V, 3) half extents (one size for
    all boxes, or each its own). A bounding-sphere test over all (ray, box) pairs picks the few pairs
    that get the exact slab test."""
    mask = np.zeros(len(dirs), bool)
    if len(centres) == 0:
        return mask
    to_centre = centres - origin  # (V, 3)
    half_m = np.broadcast_to(np.asarray(half_m, float), centres.shape)
    radius = np.linalg.norm(half_m, axis=1)  # (V,)
    along = dirs @ to_centre.T  # (R, V): distance along the ray to the centre's foot
    off_axis_sq = np.sum(to_centre**2, axis=1) - along**2
    near = (off_axis_sq <= radius**2) & (along >= -radius) & (along <= length_m[:, None] + radius)
    ray, box = np.nonzero(near)
    if len(ray) == 0:
        return mask
    R_T = rotations[box].transpose(0, 2, 1)  # world -> box
    o_local = np.einsum("pij,pj->pi", R_T, -to_centre[box])
    d_local = np.einsum("pij,pj->pi", R_T, dirs[ray])
    d_local = np.where(np.abs(d_local) < MIN_DIRECTION, MIN_DIRECTION, d_local)
    t1 = (-half_m[box] - o_local) / d_local
    t2 = (half_m[box] - o_local) / d_local
    t_enter = np.minimum(t1, t2).max(axis=1)
    t_exit = np.maximum(t1, t2).min(axis=1)
    hit = (t_exit >= np.maximum(t_enter, 0.0)) & (t_enter <= length_m[ray])
    mask[ray[hit]] = True
    return mask


class LidarSimulator:
    """One lidar: cached static ranges + per-scan vehicle ray casts."""

    def __init__(
        self,
        scene: Scene,
        sensor_id: str,
        static: StaticWorld,
        vehicles: VehicleWorld,
        model: LidarModel | None = None,
    ) -> None:
        """`model` replaces the scene's lidar model (e.g. a run's own range noise)."""
        spec = scene.sensor(sensor_id)
        if spec.lidar is None:
            raise ValueError(f"sensor {sensor_id!r} is not a lidar")
        self.sensor_id = sensor_id
        self.model = model or spec.lidar
        self.vehicles = vehicles
        T = np.asarray(scene.T_world_from_sensor(sensor_id))
        self.origins_sensor, self.dirs_sensor, self.channel = ray_layout(self.model)
        self.origin = T[:3, 3].copy()
        self.origins_world = self.origins_sensor @ T[:3, :3].T + self.origin
        self.dirs_world = self.dirs_sensor @ T[:3, :3].T
        fraction, body = cast_rays(
            static.cid, self.origins_world, self.origins_world + self.dirs_world * self.model.max_range_m
        )
        self.static_range_m = fraction * self.model.max_range_m
        self.static_range_m.setflags(write=False)
        self.static_kind = np.array(
            [static.body_kind.get(int(b), "") if b != NO_HIT_BODY else "" for b in body]
        )
        self.static_intensity = np.array(
            [STATIC_INTENSITY.get(k, INTENSITY_OBJECT) for k in self.static_kind], np.float32
        )
        # Rays leave from up to the lens offset away from the sensor origin: the candidate test (rays
        # from the origin) sees boxes grown by that much.
        lens_m = float(np.max(np.linalg.norm(self.origins_sensor, axis=1)))
        margin_m = vehicles.settings.vehicle_ray_margin_m
        self._grow_m = margin_m + lens_m

    @property
    def num_rays(self) -> int:
        return len(self.dirs_sensor)

    def candidate_rays(self, poses: list[VehiclePose]) -> np.ndarray:
        """Indices of the rays whose segment (up to the static range) touches a vehicle's box."""
        if not poses:
            return np.zeros(0, np.int64)
        centres = np.array([p.center_m for p in poses], float)
        rotations = Rotation.from_euler("ZYX", [[p.yaw_rad, p.pitch_rad, 0.0] for p in poses]).as_matrix()
        half_m = np.array([self.vehicles.size_of(p) for p in poses], float) / 2 + self._grow_m
        length = np.minimum(self.static_range_m, self.model.max_range_m)
        mask = rays_hitting_boxes(self.origin, self.dirs_world, length, centres, rotations, half_m)
        return np.flatnonzero(mask)

    def cast(self, poses: list[VehiclePose]) -> RayHits:
        """Noise-free first hit of every ray with the vehicles at `poses` (already in the vehicle world)."""
        range_m = self.static_range_m.copy()
        vehicle = np.full(self.num_rays, -1, np.int64)
        rays = self.candidate_rays(poses)
        if len(rays):
            length = np.minimum(self.static_range_m[rays], self.model.max_range_m)
            starts = self.origins_world[rays]
            ends = starts + self.dirs_world[rays] * length[:, None]
            fraction, body = cast_rays(self.vehicles.cid, starts, ends)
            index = {p.vehicle_id: i for i, p in enumerate(poses)}
            hit_vehicle = np.array(
                [index.get(self.vehicles.body_vehicle.get(int(b), ""), -1) for b in body], np.int64
            )
            near = np.isfinite(fraction) & (hit_vehicle >= 0)
            range_m[rays[near]] = fraction[near] * length[near]
            vehicle[rays[near]] = hit_vehicle[near]
        return RayHits(range_m, vehicle)

    def scan(self, poses: list[VehiclePose], rng: np.random.Generator) -> LidarScan:
        """One revolution with the vehicles at `poses` (the caller has updated the vehicle world)."""
        hits = self.cast(poses)
        rays = np.flatnonzero(np.isfinite(hits.range_m))
        measured = hits.range_m[rays] + rng.normal(0.0, self.model.range_noise_std_m, len(rays))
        keep = (measured >= self.model.min_range_m) & (measured <= self.model.max_range_m)
        rays, measured = rays[keep], measured[keep]
        vehicle = hits.vehicle[rays]
        on_vehicle = vehicle >= 0
        ids = np.array([p.vehicle_id for p in poses] + [""])
        return LidarScan(
            sensor_id=self.sensor_id,
            points_m=(self.origins_sensor[rays] + self.dirs_sensor[rays] * measured[:, None]).astype(
                np.float32
            ),
            intensity=np.where(on_vehicle, np.float32(INTENSITY_VEHICLE), self.static_intensity[rays]),
            vehicle_ids=ids[vehicle],  # index -1 picks the trailing ""
            ray_index=rays.astype(np.int32),
            channel=self.channel[rays],
            range_m=measured.astype(np.float32),
        )


def to_point_cloud(scan: LidarScan, frame_id: str, stamp_ns: int) -> PointCloud:
    """foxglove.PointCloud of a scan (shared.perception.decode.point_cloud_message)."""
    return point_cloud_message(scan.points_m, scan.intensity, frame_id, stamp_ns)
