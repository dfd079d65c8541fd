"""Tests for the clustering lidar detector on ray-cast synthetic scenes (shared.detection.lidar.cluster)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from shared.detection.interface import DetectorInputError
from shared.detection.lidar.cluster import (
    ClusterLidarConfig,
    ClusterLidarDetector,
    bev_clusters,
    nearest_sensor,
    ring_radial_eps_per_m2,
)
from shared.detection.lidar.ground import Plane
from tests.shared.detection.lidar.raycast import Lidar, scan

L, W, H = 0.33, 0.22, 0.21
CAR_SIZE_M = (L, W, H)
DECK_TOP = 0.40
DECK_THICKNESS = 0.04
TABLE_CARS = np.array(
    [
        [1.2, 0.4, H / 2, L, W, H, 0.4],
        [-0.8, 1.3, H / 2, L, W, H, 1.9],
        [0.3, -1.8, H / 2, L, W, H, -0.3],
        [-2.5, -1.0, H / 2, L, W, H, 0.0],
    ]
)
DECK_CAR = np.array([[0.5, 2.4, DECK_TOP + H / 2, L, W, H, 0.02]])
DECK = np.array([[0.0, 2.4, DECK_TOP - DECK_THICKNESS / 2, 4.0, 0.36, DECK_THICKNESS, 0.0]])
PILLAR_H = DECK_TOP - DECK_THICKNESS
PILLARS = np.array([[x, 2.4, PILLAR_H / 2, 0.06, 0.06, PILLAR_H, 0.0] for x in (-1.0, 1.0)])
POLE = np.array([[1.5, -1.0, 0.21, 0.04, 0.04, 0.42, 0.0]])
BUILDING = np.array([[-2.0, -2.8, 0.3, 1.0, 0.7, 0.6, 0.2]])
CARS = np.vstack([TABLE_CARS, DECK_CAR])
STATIC = np.vstack([DECK, PILLARS, POLE, BUILDING])

# Agent3-like: one 32-line lidar hanging 0.62 m above the table. The simulator samples 250 azimuths;
# the accuracy test uses 720 so it measures the fit rather than the sampling.
HIGH_DENSE = Lidar(position=(0.0, 0.0, 0.62), samples=720)
HIGH_SIM = Lidar(position=(0.0, 0.0, 0.62), samples=250)


def yaw_error(a: float, b: float) -> float:
    """Absolute yaw difference modulo pi (front and back are the same box), radians."""
    return abs((a - b + math.pi / 2) % math.pi - math.pi / 2)


def match(dets: np.ndarray, cars: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Nearest detection (BEV) to each car."""
    assert dets.shape[0] > 0
    pairs = []
    for car in cars:
        k = int(np.argmin(np.hypot(dets[:, 0] - car[0], dets[:, 1] - car[1])))
        pairs.append((dets[k].astype(np.float64), car))
    return pairs


def detector(**settings: Any) -> ClusterLidarDetector:
    """The detector with the table car as its prior (the MEC sets the scene's)."""
    return ClusterLidarDetector(ClusterLidarConfig(vehicle_size_m=CAR_SIZE_M, **settings))


def test_refuses_to_run_without_the_scenes_vehicle() -> None:
    with pytest.raises(ValueError, match="vehicle_size_m"):
        ClusterLidarDetector(ClusterLidarConfig())


def scene(lidar: Lidar, seed: int = 0) -> np.ndarray:
    return scan(lidar, np.vstack([CARS, STATIC]), np.random.default_rng(seed))


def test_finds_every_vehicle_within_3cm_and_5deg() -> None:
    dets = detector().detect(scene(HIGH_DENSE))
    assert dets.shape == (len(CARS), 9) and dets.dtype == np.float32
    for det, car in match(dets, CARS):
        assert np.hypot(det[0] - car[0], det[1] - car[1]) < 0.03
        assert yaw_error(det[6], car[6]) < math.radians(5)
        assert det[2] == pytest.approx(car[2], abs=0.01)  # table: z = 0; deck car: on the peeled deck
        np.testing.assert_allclose(det[3:6], [L, W, H], atol=1e-6)
        assert 0.0 < det[7] < 1.0 and det[8] == 0.0
    assert np.all(np.diff(dets[:, 7]) <= 0.0)  # by descending score


def test_ignores_ground_deck_pillars_pole_and_building() -> None:
    dets = detector().detect(scan(HIGH_DENSE, STATIC, np.random.default_rng(1)))
    assert dets.shape == (0, 9)
    only_table = scan(HIGH_DENSE, np.zeros((0, 7)), np.random.default_rng(2))
    assert detector().detect(only_table).shape == (0, 9)


def test_simulator_density_still_finds_every_vehicle() -> None:
    # At the simulator's 32 x 250 rays a car 2.7 m away gets ~3 points per ring and face: looser bounds.
    dets = detector().detect(scene(HIGH_SIM))
    assert dets.shape[0] == len(CARS)
    for det, car in match(dets, CARS):
        assert np.hypot(det[0] - car[0], det[1] - car[1]) < 0.04
        assert yaw_error(det[6], car[6]) < math.radians(6)


def test_two_low_lidars_merged_cloud() -> None:
    # Agent1-like: two 16-line lidars 0.15 m high on opposite corners; the cloud is their union.
    sensors = ((-0.62, 0.62), (0.62, -0.62))
    rng = np.random.default_rng(3)
    cloud = np.vstack(
        [
            scan(
                Lidar(position=(x, y, 0.15), channels=16, samples=500, elevation_max=0.5353), TABLE_CARS, rng
            )
            for x, y in sensors
        ]
    )
    dets = detector(sensor_xy_m=sensors).detect(cloud)
    assert dets.shape[0] == len(TABLE_CARS)
    for det, car in match(dets, TABLE_CARS):
        assert np.hypot(det[0] - car[0], det[1] - car[1]) < 0.03
        assert yaw_error(det[6], car[6]) < math.radians(5)


def test_deterministic() -> None:
    cloud = scene(HIGH_SIM)
    np.testing.assert_array_equal(detector().detect(cloud), detector().detect(cloud))


def test_range_crop_and_min_points() -> None:
    cloud = scene(HIGH_DENSE)
    near = detector(max_range_m=2.0).detect(cloud)
    assert near.shape[0] == 3 and np.all(np.hypot(near[:, 0], near[:, 1]) < 2.0)
    assert detector(min_points=100_000).detect(cloud).shape == (0, 9)


def test_empty_and_invalid_input() -> None:
    det = detector()
    out = det.detect(np.zeros((0, 4), np.float32))
    assert out.shape == (0, 9) and out.dtype == np.float32
    cloud = scene(HIGH_SIM)
    cloud[10, 2] = np.nan
    with pytest.raises(DetectorInputError, match="not finite"):
        det.detect(cloud)
    with pytest.raises(DetectorInputError):
        det.detect(np.zeros((5, 3), np.float32))
    with pytest.raises(DetectorInputError):
        det.detect(np.zeros((5, 4), np.int32))
    assert det.name == "cluster"


def test_config_validation() -> None:
    with pytest.raises(ValidationError):
        ClusterLidarConfig(min_range_m=3.0, max_range_m=2.0)
    with pytest.raises(ValidationError):
        ClusterLidarConfig(z_min_m=1.0, z_max_m=0.5)
    with pytest.raises(ValidationError):
        ClusterLidarConfig(cluster_eps_min_m=0.2, cluster_eps_max_m=0.1)
    with pytest.raises(ValidationError):
        ClusterLidarConfig(vehicle_size_m=(0.33, 0.0, 0.21))
    with pytest.raises(ValidationError):
        ClusterLidarConfig(sensor_xy_m=())
    with pytest.raises(ValidationError):
        ClusterLidarConfig(typo=1)  # type: ignore[call-arg]


def test_nearest_sensor() -> None:
    sensors = np.array([[0.0, 0.0], [2.0, 0.0]])
    pos, dist = nearest_sensor(np.array([[0.5, 0.0], [1.5, 1.0]]), sensors)
    np.testing.assert_allclose(pos, [[0.0, 0.0], [2.0, 0.0]])
    np.testing.assert_allclose(dist, [0.5, math.hypot(0.5, 1.0)])


def test_bev_clusters_ellipse_along_line_of_sight() -> None:
    # Sensor at the origin, points 2 m away along +x. Radial (x) gaps of 0.2 m link (radial radius 0.25);
    # the same gap across the line of sight (y) does not (tangential radius 0.06).
    xy = np.array([[2.0, 0.0], [2.2, 0.0], [2.0, 0.2], [5.0, 5.0]])
    origin = np.zeros((4, 2))
    clusters = bev_clusters(xy, origin, np.full(4, 0.06), np.full(4, 0.25))
    assert sorted(c.tolist() for c in clusters) == [[0, 1], [2], [3]]
    assert bev_clusters(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0)) == []


def all_pairs_clusters(
    xy: np.ndarray, origin: np.ndarray, tangential: np.ndarray, radial: np.ndarray
) -> list[list[int]]:
    """The linking rule of `bev_clusters` on every pair (i < j), components by a plain flood fill."""
    n = len(xy)
    linked = np.zeros((n, n), bool)
    for i in range(n):
        sight = (xy[i] - origin[i]) / max(float(np.linalg.norm(xy[i] - origin[i])), 1e-6)
        for j in range(i + 1, n):
            d = xy[j] - xy[i]
            dr, dt = d @ sight, d[0] * sight[1] - d[1] * sight[0]
            et, er = max(tangential[i], tangential[j]), max(radial[i], radial[j])
            linked[i, j] = linked[j, i] = (dt / et) ** 2 + (dr / er) ** 2 <= 1.0
    label = -np.ones(n, int)
    for start in range(n):
        if label[start] < 0:
            label[start], stack = start, [start]
            while stack:
                for k in np.flatnonzero(linked[stack.pop()] & (label < 0)):
                    label[k] = start
                    stack.append(int(k))
    return sorted(np.flatnonzero(label == g).tolist() for g in np.unique(label))


def test_bev_clusters_with_per_point_reach_equal_every_pair() -> None:
    # Each point's neighbours are searched within its own reach: the components must be those of the
    # rule applied to every pair (so the table's `cluster` detector finds what it did).
    rng = np.random.default_rng(7)
    for _ in range(5):
        xy = rng.uniform(-3.0, 3.0, (300, 2))
        origin = np.zeros_like(xy)
        r = np.linalg.norm(xy, axis=1)
        tangential = np.clip(0.03 * r, 0.05, 0.12)
        radial = np.clip(0.06 * r**2, tangential, 0.25)
        got = sorted(c.tolist() for c in bev_clusters(xy, origin, tangential, radial))
        assert got == all_pairs_clusters(xy, origin, tangential, radial)
        assert 10 < len(got) < 300  # linked and unlinked pairs both occur


def test_the_cell_grid_links_a_dense_car_and_keeps_two_cars_apart() -> None:
    # Real size: a car 4.5 m long, dense as a 64-beam lidar's near car (~5 cm spacing), and a second
    # one 1.5 m behind it (a queue); the table's radii at 13.6x (the intersection's scale).
    size = (4.5, 1.8, 1.5)
    grid = np.stack(np.meshgrid(np.arange(0, 4.5, 0.05), np.arange(0, 1.8, 0.05)), -1).reshape(-1, 2)
    first = grid + np.array([10.0, -0.9])
    second = grid + np.array([10.0 + 4.5 + 1.5, -0.9])
    xy = np.vstack([first, second])
    xyz = np.column_stack([xy, np.full(len(xy), 1.5)])
    cfg = ClusterLidarConfig(
        vehicle_size_m=size,
        cluster_eps_min_m=0.68,
        cluster_eps_max_m=1.64,
        cluster_radial_eps_per_m2=0.0044,
        cluster_radial_eps_max_m=3.4,
    )
    exact = ClusterLidarDetector(cfg)._cluster(xyz, np.arange(len(xy)))
    cells = ClusterLidarDetector(cfg.model_copy(update={"cluster_grid": True}))._cluster(
        xyz, np.arange(len(xy))
    )
    split = [np.arange(len(first)), np.arange(len(first), len(xy))]
    for found in (exact, cells):
        assert [c.tolist() for c in found] == [s.tolist() for s in split]


def test_the_background_detector_links_cells_and_the_cluster_detector_every_pair() -> None:
    from shared.detection.registry import lidar_detector

    cfg = ClusterLidarConfig(vehicle_size_m=CAR_SIZE_M)
    assert lidar_detector("background", cluster=cfg).config.cluster_grid is True  # type: ignore[attr-defined]
    assert lidar_detector("cluster", cluster=cfg).config.cluster_grid is False  # type: ignore[attr-defined]
    off = cfg.model_copy(update={"cluster_grid": False})
    assert lidar_detector("background", cluster=off).config.cluster_grid is False  # type: ignore[attr-defined]


def test_heights_from_a_fitted_ground_on_a_sloped_offset_site() -> None:
    # The table scene tilted 0.08 rad about x and lowered 0.3 m: in the agent frame a sloped ground well
    # below z = 0, with the cars standing on it. Heights from the table's z = 0 lose the cars; from the
    # ground's plane they are found where they stand.
    tilt, drop = 0.08, -0.3
    R = np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(tilt), -math.sin(tilt)], [0.0, math.sin(tilt), math.cos(tilt)]]
    )
    cloud = scene(HIGH_DENSE)
    cloud[:, :3] = cloud[:, :3] @ R.T + [0.0, 0.0, drop]
    sensor = R @ np.array(HIGH_DENSE.position) + [0.0, 0.0, drop]
    cars = TABLE_CARS.copy()
    cars[:, :3] = cars[:, :3] @ R.T + [0.0, 0.0, drop]
    flat = detector(sensor_xy_m=((sensor[0], sensor[1]),))
    assert len(match_within(flat.detect(cloud), cars, 0.05)) < len(cars)
    sloped = detector(sensor_xy_m=((sensor[0], sensor[1]),))
    sloped.ground = Plane(normal=R @ np.array([0.0, 0.0, 1.0]), offset=-drop * math.cos(tilt))
    found = match_within(sloped.detect(cloud), cars, 0.05)
    assert len(found) == len(cars)
    for det, car in found:
        assert det[2] == pytest.approx(car[2], abs=0.02)  # the box stands on the sloped ground


def match_within(
    dets: np.ndarray, cars: np.ndarray, tolerance_m: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """(detection, car) of the cars with a detection centred within `tolerance_m` (BEV)."""
    out = []
    for car in cars:
        if dets.shape[0] == 0:
            continue
        d = np.hypot(dets[:, 0] - car[0], dets[:, 1] - car[1])
        if d.min() <= tolerance_m:
            out.append((dets[int(np.argmin(d))].astype(np.float64), car))
    return out


def test_ring_radius_from_the_lidars_channel_gaps() -> None:
    # Channels 0.01 rad apart 5 m above a roof: rings 0.01 * r^2 / 5 apart, linked up to 1.5 gaps.
    even = np.arange(32) * 0.01
    assert ring_radial_eps_per_m2([even], [5.0]) == pytest.approx(1.5 * 0.01 / 5.0)
    # A denser band (the median gap) sets it; of two lidars the wider spacing.
    banded = np.concatenate([np.arange(20) * 0.005, 0.2 + np.arange(5) * 0.05])
    assert ring_radial_eps_per_m2([banded], [5.0]) == pytest.approx(1.5 * 0.005 / 5.0)
    assert ring_radial_eps_per_m2([banded, even], [5.0, 2.5]) == pytest.approx(1.5 * 0.01 / 2.5)
    with pytest.raises(ValueError, match="height above the roof"):
        ring_radial_eps_per_m2([even], [0.0])


def box_surface(
    centre_xy: tuple[float, float], size: tuple[float, float, float], step_m: float
) -> np.ndarray:
    """Points on a box's roof and its four sides (axis-aligned), `step_m` apart, z from 0.5 m up."""
    (x, y), (length, width, height) = centre_xy, size
    gx, gy = np.meshgrid(np.arange(-length / 2, length / 2, step_m), np.arange(-width / 2, width / 2, step_m))
    roof = np.column_stack([gx.ravel() + x, gy.ravel() + y, np.full(gx.size, height)])
    sides = []
    for z in np.arange(0.5, height, step_m):
        for sx in (-length / 2, length / 2):
            ys = np.arange(-width / 2, width / 2, step_m)
            sides.append(np.column_stack([np.full(ys.size, x + sx), ys + y, np.full(ys.size, z)]))
        for sy in (-width / 2, width / 2):
            xs = np.arange(-length / 2, length / 2, step_m)
            sides.append(np.column_stack([xs + x, np.full(xs.size, y + sy), np.full(xs.size, z)]))
    return np.vstack([roof, *sides])


def test_a_car_queued_1m_behind_a_truck_is_split_and_each_boxed_with_its_class() -> None:
    # Real size, 28 m down the line of sight from the lidar: the radial radius there (1.1 m) links the
    # two; linked again at half the radii they part, the truck boxed with the truck class.
    car, truck = (4.5, 1.8, 1.5), (8.5, 2.5, 3.2)
    car_x = 28.0
    truck_x = car_x + car[0] / 2 + 1.0 + truck[0] / 2
    cloud = np.vstack([box_surface((car_x, 0.0), car, 0.25), box_surface((truck_x, 0.0), truck, 0.25)])
    points = np.column_stack([cloud, np.zeros(len(cloud))])
    cfg = ClusterLidarConfig(
        vehicle_size_m=car,
        vehicle_classes_m=((4.9, 1.9, 2.0), truck),
        max_range_m=80.0,
        z_max_m=13.6,
        cluster_eps_min_m=0.68,
        cluster_eps_max_m=1.64,
        cluster_radial_eps_per_m2=0.0014,
        cluster_radial_eps_max_m=3.4,
        max_length_m=6.14,
        max_width_m=4.36,
        min_height_m=0.68,
        max_height_m=4.09,
        ground_tolerance_m=0.27,
        size_tolerance_m=0.41,
        cluster_grid=True,
    )
    merged = ClusterLidarDetector(cfg.model_copy(update={"oversize_splits": 0})).detect(points)
    assert len(merged) == 0  # 15 m long: no vehicle
    found = ClusterLidarDetector(cfg.model_copy(update={"oversize_splits": 2})).detect(points)
    assert len(found) == 2
    by_x = found[np.argsort(found[:, 0])]
    np.testing.assert_allclose(by_x[:, 0], [car_x, truck_x], atol=0.3)
    np.testing.assert_allclose(by_x[0, 3:6], car, atol=0.05)
    np.testing.assert_allclose(by_x[1, 3:6], truck, atol=0.3)


def test_a_car_under_an_overhead_structure_is_boxed_without_it() -> None:
    """A signal head hanging over a car (its top 0.42 m up, above the car's 0.30 m height gate, 0.17 m
    over the roof): the cluster's points above the gap are the structure's; the car is boxed as it is
    without the head."""
    car = TABLE_CARS[:1]
    head = np.array([[car[0, 0], car[0, 1], 0.40, 0.05, 0.05, 0.04, 0.0]])
    cloud = scan(HIGH_DENSE, np.vstack([car, head]), np.random.default_rng(4))
    assert (cloud[:, 2] > 0.35).sum() > 3  # the head is seen
    dets = detector().detect(cloud)
    alone = detector().detect(scan(HIGH_DENSE, car, np.random.default_rng(4)))
    assert dets.shape == alone.shape == (1, 9)
    np.testing.assert_allclose(dets, alone, atol=0.01)  # as the car without the head over it
    assert detector(overhead_gap_m=1.0).detect(cloud).shape[0] == 0  # without: too tall for a car


def test_points_from_one_lidar_are_boxed_from_that_lidar() -> None:
    """Two lidars: a car nearer the first, seen (here) only by the second. Told where each point came
    from, the detector boxes it exactly as a detector with the second lidar alone; not told (or told
    with a length that does not match), from each cluster's nearest lidar. Told once: the next cloud
    is not."""
    near, far = (0.9, 0.9), (-1.5, -1.5)
    car = np.array([[1.2, 0.4, H / 2, L, W, H, 0.4]])
    cloud = scan(Lidar(position=(*far, 0.62), samples=720), car, np.random.default_rng(5))
    alone = detector(sensor_xy_m=(far,)).detect(cloud)
    both = detector(sensor_xy_m=(near, far))
    both.point_sensor = np.ones(len(cloud), np.int64)
    np.testing.assert_array_equal(both.detect(cloud), alone)
    assert both.point_sensor is None
    nearest = detector(sensor_xy_m=(near, far)).detect(cloud)
    both.point_sensor = np.ones(len(cloud) - 1, np.int64)  # not this cloud's: ignored
    np.testing.assert_array_equal(both.detect(cloud), nearest)


@pytest.mark.parametrize("grid", [True, False])
def test_no_points_left_after_a_slab_make_no_cluster(grid: bool) -> None:
    """A slab peeled off all of a cluster's points leaves nothing to recluster: no cluster, not an
    empty one (whose extent raised `zero-size array` in the intersection's tuning evaluation)."""
    xyz = np.array([[1.0, 0.0, 0.1], [1.1, 0.0, 0.1]])
    assert detector(cluster_grid=grid)._cluster(xyz, np.zeros(0, np.int64)) == []
