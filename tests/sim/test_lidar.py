"""Lidar model on the real sand table: cached static casts + per-scan vehicle casts agree with casting
the whole world, returns lie on the vehicles, occlusion, determinism, point-cloud encoding."""

from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from shared.perception.decode import point_cloud_to_array as from_point_cloud
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from sim.config import TrafficSettings
from sim.sensors.lidar import (
    INTENSITY_VEHICLE,
    RAY_BATCH_SIZE,
    LidarScan,
    LidarSimulator,
    cast_rays,
    ray_directions,
    rays_hitting_boxes,
    to_point_cloud,
)
from sim.traffic import TrafficSim
from sim.world import FullWorld, StaticWorld, VehiclePose, VehicleWorld

LIDAR = "lidar_11"  # at (-0.62, 2.12, 0.15), agent1's intersection
RANGE_TOL_M = 1e-4  # PyBullet casts of the same segment agree to float precision
SURFACE_TOL_M = 0.003
CONVEX_CAST_TOL_M = 0.001  # Bullet's ray vs box cast overshoots edges by a fraction of a mm


def _zero_noise(scene: Scene, sensor_id: str) -> Scene:
    spec = scene.spec
    sensors = [
        s.model_copy(update={"lidar": s.lidar.model_copy(update={"range_noise_std_m": 0.0})})
        if s.id == sensor_id and s.lidar is not None
        else s
        for s in spec.sensors
    ]
    return Scene(spec.model_copy(update={"sensors": sensors}))


@pytest.fixture(scope="module")
def lidar(scene: Scene, static: StaticWorld, vehicles: VehicleWorld) -> LidarSimulator:
    return LidarSimulator(scene, LIDAR, static, vehicles)


@pytest.fixture(scope="module")
def exact(scene: Scene, static: StaticWorld, vehicles: VehicleWorld) -> LidarSimulator:
    """The same lidar without range noise."""
    return LidarSimulator(_zero_noise(scene, LIDAR), LIDAR, static, vehicles)


def _pose(scene: Scene, vid: str, x: float, y: float, yaw: float) -> VehiclePose:
    return VehiclePose(vid, (x, y, scene.spec.vehicle.height_m / 2), yaw)


def _near_poses(scene: Scene) -> list[VehiclePose]:
    """Vehicles on the lanes around lidar_11: west arm (both ways) and north arm."""
    return [
        _pose(scene, "west_out", -1.2, 1.65, math.pi),
        _pose(scene, "west_in", -0.9, 1.35, 0.0),
        _pose(scene, "north_in", -0.15, 2.6, -math.pi / 2),
    ]


def _traffic_poses(scene: Scene, steps: int) -> list[VehiclePose]:
    traffic = TrafficSim(scene, RoadNetwork(scene), TrafficSettings(vehicles=10), seed=1, tick_hz=60)
    for _ in range(steps):
        traffic.step()
    h = scene.spec.vehicle.height_m
    return [VehiclePose(v.id, (v.x, v.y, v.z + h / 2), v.yaw, v.pitch, v.rgba) for v in traffic.vehicles]


def _box_local(points_world: np.ndarray, pose: VehiclePose) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("ZYX", [pose.yaw_rad, pose.pitch_rad, 0.0])
    return rot.inv().apply(points_world - np.asarray(pose.center_m))


def _to_world(lidar: LidarSimulator, scene: Scene, points: np.ndarray) -> np.ndarray:
    T = np.asarray(scene.T_world_from_sensor(lidar.sensor_id))
    return points.astype(float) @ T[:3, :3].T + T[:3, 3]


def test_ray_directions_layout(scene: Scene) -> None:
    model = scene.sensor(LIDAR).lidar
    assert model is not None
    dirs, channel = ray_directions(model)
    n = model.horizontal_samples
    assert dirs.shape == (model.channels * n, 3)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    elevation = np.arcsin(dirs[:, 2])
    assert elevation[0] == pytest.approx(model.vertical_min_rad)
    assert elevation[-1] == pytest.approx(model.vertical_max_rad)
    assert np.all(channel == np.arange(len(dirs)) // n)
    azimuth = np.arctan2(dirs[:n, 1], dirs[:n, 0])
    assert azimuth[0] == pytest.approx(0.0)  # sensor +x
    assert azimuth[1] == pytest.approx(2 * math.pi / n)  # counter-clockwise


def test_cast_rays_chunks_large_batches(static: StaticWorld) -> None:
    count = 2 * RAY_BATCH_SIZE + 5
    rng = np.random.default_rng(0)
    height_m, drop_m = 0.5, 1.0
    xy = rng.uniform(-0.5, 0.5, (count, 2))
    origin = np.array([0.05, 0.05, height_m])  # above the central intersection: only the table below
    ends = np.column_stack([xy, np.full(count, height_m - drop_m)])
    fraction, body = cast_rays(static.cid, origin, ends)
    assert np.all(body >= 0)
    # The slab's top is the only collision surface.
    expected = (height_m + static.settings.table_slab_drop_m) / drop_m
    np.testing.assert_allclose(fraction, expected, atol=RANGE_TOL_M)


def test_static_and_vehicle_returns_match_full_world_casts(
    scene: Scene, exact: LidarSimulator, vehicles: VehicleWorld, full: FullWorld
) -> None:
    poses = _near_poses(scene) + _traffic_poses(scene, steps=30)
    vehicles.update(poses)
    full.update(poses)
    hits = exact.cast(poses)

    max_range = exact.model.max_range_m
    fraction, body = cast_rays(full.cid, exact.origin, exact.origin + exact.dirs_world * max_range)
    ref_range = fraction * max_range
    ref_vehicle = np.array([full.vehicles.body_vehicle.get(int(b), "") for b in body])
    ids = np.array([p.vehicle_id for p in poses] + [""])

    np.testing.assert_array_equal(np.isfinite(hits.range_m), np.isfinite(ref_range))
    finite = np.isfinite(ref_range)
    np.testing.assert_allclose(hits.range_m[finite], ref_range[finite], atol=RANGE_TOL_M)
    np.testing.assert_array_equal(ids[hits.vehicle], ref_vehicle)
    # Vehicles occlude the static scene: those rays are shorter than their cached static range.
    on_vehicle = hits.vehicle >= 0
    assert on_vehicle.sum() > 50
    assert np.all(hits.range_m[on_vehicle] < exact.static_range_m[on_vehicle])
    assert {"west_out", "west_in", "north_in"} <= set(ids[hits.vehicle])

    # With zero noise the scan is exactly those returns, in the sensor frame.
    scan = exact.scan(poses, np.random.default_rng(0))
    model = exact.model
    valid = finite & (ref_range >= model.min_range_m) & (ref_range <= model.max_range_m)
    np.testing.assert_array_equal(scan.ray_index, np.flatnonzero(valid))
    expected = exact.dirs_sensor[scan.ray_index] * ref_range[scan.ray_index, None]
    np.testing.assert_allclose(scan.points_m, expected, atol=RANGE_TOL_M)
    np.testing.assert_array_equal(scan.vehicle_ids, ref_vehicle[scan.ray_index])


def test_vehicle_returns_lie_on_its_box(scene: Scene, lidar: LidarSimulator, vehicles: VehicleWorld) -> None:
    poses = _near_poses(scene)
    vehicles.update(poses)
    scan = lidar.scan(poses, np.random.default_rng(3))
    assert scan.points_m.dtype == np.float32 and scan.intensity.dtype == np.float32
    half = np.asarray(vehicles.size_m) / 2
    slack = 3 * lidar.model.range_noise_std_m
    world = _to_world(lidar, scene, scan.points_m)
    for pose in poses:
        mine = scan.vehicle_ids == pose.vehicle_id
        assert mine.sum() >= 10, pose.vehicle_id
        local = _box_local(world[mine], pose)
        assert np.all(np.abs(local) <= half + slack), pose.vehicle_id
        assert np.all(scan.intensity[mine] == np.float32(INTENSITY_VEHICLE))
    # Unlabelled returns (static scene) are never deep inside a vehicle box.
    others = scan.vehicle_ids == ""
    for pose in poses:
        local = _box_local(world[others], pose)
        assert not np.any(np.all(np.abs(local) < half - slack, axis=1))
    assert np.all(scan.intensity[others] < INTENSITY_VEHICLE)


def test_some_vehicle_returns_are_on_the_box_surface(
    scene: Scene, exact: LidarSimulator, vehicles: VehicleWorld
) -> None:
    poses = _near_poses(scene)
    vehicles.update(poses)
    scan = exact.scan(poses, np.random.default_rng(0))
    half = np.asarray(vehicles.size_m) / 2
    world = _to_world(exact, scene, scan.points_m)
    for pose in poses:
        local = _box_local(world[scan.vehicle_ids == pose.vehicle_id], pose)
        depth_inside = np.min(half - np.abs(local), axis=1)  # 0 on the surface
        assert np.all(depth_inside >= -CONVEX_CAST_TOL_M)
        assert np.sum(depth_inside < SURFACE_TOL_M) >= 3, pose.vehicle_id


def test_vehicle_behind_building_gets_no_returns(
    scene: Scene, lidar: LidarSimulator, vehicles: VehicleWorld
) -> None:
    # On lane l3 behind building_nw as seen from lidar_11 (the lidar is lower than the building).
    hidden = _pose(scene, "hidden", -3.05, 2.45, math.pi / 2)
    poses = [hidden, *_near_poses(scene)]
    vehicles.update(poses)
    # It is in the lidar's field and range: without the static scene, rays would reach it.
    half = np.asarray(vehicles.size_m) / 2
    unobstructed = np.full(lidar.num_rays, lidar.model.max_range_m)
    centre = np.asarray([hidden.center_m])
    rotation = np.array([[[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]])  # yaw 90 deg
    assert rays_hitting_boxes(lidar.origin, lidar.dirs_world, unobstructed, centre, rotation, half).sum() > 5
    scan = lidar.scan(poses, np.random.default_rng(0))
    assert "hidden" not in set(scan.vehicle_ids)
    assert "west_out" in set(scan.vehicle_ids)


def test_returns_are_never_behind_static_obstacles(
    scene: Scene, lidar: LidarSimulator, vehicles: VehicleWorld
) -> None:
    poses = _traffic_poses(scene, steps=120)
    vehicles.update(poses)
    hits = lidar.cast(poses)
    on_vehicle = hits.vehicle >= 0
    assert np.all(hits.range_m[on_vehicle] <= lidar.static_range_m[on_vehicle])
    assert np.all(hits.range_m <= lidar.static_range_m)


def test_same_seed_same_points_other_seed_other_noise(
    scene: Scene, lidar: LidarSimulator, vehicles: VehicleWorld
) -> None:
    poses = _near_poses(scene)
    vehicles.update(poses)
    a = lidar.scan(poses, np.random.default_rng(7))
    b = lidar.scan(poses, np.random.default_rng(7))
    c = lidar.scan(poses, np.random.default_rng(8))
    np.testing.assert_array_equal(a.points_m, b.points_m)
    np.testing.assert_array_equal(a.ray_index, b.ray_index)
    np.testing.assert_array_equal(a.vehicle_ids, b.vehicle_ids)
    common, ia, ic = np.intersect1d(a.ray_index, c.ray_index, return_indices=True)
    assert len(common) > 1000
    diff = a.range_m[ia] - c.range_m[ic]
    assert np.mean(diff != 0) > 0.99
    # The noise has the model's spread (difference of two draws: sqrt(2) sigma).
    sigma = lidar.model.range_noise_std_m
    assert np.std(diff) == pytest.approx(math.sqrt(2) * sigma, rel=0.1)


def test_point_cloud_round_trip(scene: Scene, lidar: LidarSimulator, vehicles: VehicleWorld) -> None:
    poses = _near_poses(scene)
    vehicles.update(poses)
    scan = lidar.scan(poses, np.random.default_rng(1))
    stamp_ns = 1_234_567_890_123
    msg = to_point_cloud(scan, LIDAR, stamp_ns)
    assert msg.frame_id == LIDAR
    assert msg.timestamp.ToNanoseconds() == stamp_ns
    assert msg.point_stride == 16
    assert [f.name for f in msg.fields] == ["x", "y", "z", "intensity"]
    assert msg.pose.orientation.w == 1.0 and msg.pose.position.x == 0.0
    assert len(msg.data) == len(scan) * 16
    decoded = from_point_cloud(type(msg).FromString(msg.SerializeToString()))
    assert decoded.dtype == np.float32
    np.testing.assert_array_equal(decoded, np.column_stack([scan.points_m, scan.intensity]))


def test_empty_point_cloud_round_trip() -> None:
    empty = LidarScan(
        sensor_id=LIDAR,
        points_m=np.zeros((0, 3), np.float32),
        intensity=np.zeros(0, np.float32),
        vehicle_ids=np.zeros(0, str),
        ray_index=np.zeros(0, np.int32),
        channel=np.zeros(0, np.int32),
        range_m=np.zeros(0, np.float32),
    )
    assert from_point_cloud(to_point_cloud(empty, LIDAR, 0)).shape == (0, 4)


def test_rejects_non_lidar_sensor(scene: Scene, static: StaticWorld, vehicles: VehicleWorld) -> None:
    camera = next(s.id for s in scene.spec.sensors if s.lidar is None)
    with pytest.raises(ValueError, match="not a lidar"):
        LidarSimulator(scene, camera, static, vehicles)


def test_pybullet_batch_limit_respected() -> None:
    assert RAY_BATCH_SIZE < pb.MAX_RAY_INTERSECTION_BATCH_SIZE
