"""Vehicle classes in the sim: the mix spawns deterministically per seed, each vehicle's PyBullet body,
ground truth and sensor footprint have its own class's size, traffic keeps each vehicle's own length
apart; the crossing's signal heads are static bodies. The sand table (one class) is checked unchanged
by the rest of tests/sim."""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Iterator

import numpy as np
import pybullet as pb
import pytest
from rmmdet.v1.perception_pb2 import ObjectClass

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from sim.config import TrafficSettings
from sim.ground_truth import ground_truth_message, poses_from_ground_truth
from sim.sensors.camera import vehicles_box_corners
from sim.sensors.lidar import LidarSimulator
from sim.traffic import TrafficSim, fleet_classes
from sim.world import StaticWorld, VehiclePose, VehicleWorld

TICK_HZ = 30.0


def _scene_with_mix(scene: Scene, mix: dict[str, float]) -> Scene:
    return Scene(scene.spec.model_copy(update={"traffic_mix": mix}))


@pytest.fixture(scope="module")
def static(full_scene: Scene) -> Iterator[StaticWorld]:
    world = StaticWorld(full_scene)
    yield world
    world.close()


@pytest.fixture(scope="module")
def vehicles(full_scene: Scene, static: StaticWorld) -> Iterator[VehicleWorld]:
    world = VehicleWorld(full_scene, settings=static.settings)
    yield world
    world.close()


def test_the_mix_is_spawned_in_exact_shares_and_the_same_order_per_seed(full_scene: Scene) -> None:
    mix = full_scene.spec.fleet_mix
    names = [[c.name for c in fleet_classes(mix, 10, seed)] for seed in range(6)]
    assert all(Counter(n) == {"car": 7, "van": 2, "truck": 1} for n in names)
    assert names[0] == [c.name for c in fleet_classes(mix, 10, 0)]  # deterministic
    assert len({tuple(n) for n in names}) > 1  # and shuffled by the seed
    # Shares that do not divide: the leftovers to the largest remainders (12 x: 8.4, 2.4, 1.2).
    assert Counter(c.name for c in fleet_classes(mix, 12, 0)) == {"car": 9, "van": 2, "truck": 1}
    # The same fleet in the traffic sim.
    sim = TrafficSim(
        full_scene, RoadNetwork(full_scene), TrafficSettings(vehicles=10), seed=3, tick_hz=TICK_HZ
    )
    assert [v.body.name for v in sim.vehicles] == [c.name for c in fleet_classes(mix, 10, 3)]


def test_ground_truth_and_bodies_have_each_class_size(full_scene: Scene, vehicles: VehicleWorld) -> None:
    sim = TrafficSim(
        full_scene, RoadNetwork(full_scene), TrafficSettings(vehicles=10), seed=3, tick_hz=TICK_HZ
    )
    gt = ground_truth_message(sim, full_scene, seed=3, tick_hz=TICK_HZ)
    by_class = {v.vehicle_class: v for v in gt.vehicles}
    assert set(by_class) == {"car", "van", "truck"}
    for name, v in by_class.items():
        body = full_scene.spec.vehicle_class(name)
        assert (v.box.size_m.x, v.box.size_m.y, v.box.size_m.z) == body.size_m
        assert v.box.center_m.z == pytest.approx(body.height_m / 2)  # standing on the flat road
    assert by_class["truck"].label == ObjectClass.OBJECT_CLASS_TRUCK
    assert by_class["van"].label == by_class["car"].label == ObjectClass.OBJECT_CLASS_CAR

    # Each PyBullet body is the car model at its class's size: its collision box (chassis from 15 % of
    # the height up, 92 % of the width; the shell on top) at yaw 0 spans exactly that much.
    poses = [
        VehiclePose(p.vehicle_id, (20.0 * k, 30.0, p.center_m[2]), 0.0, rgba=p.rgba, size_m=p.size_m)
        for k, p in enumerate(poses_from_ground_truth(gt))
    ]
    vehicles.update(poses)
    for pose in poses:
        lo, hi = pb.getAABB(vehicles.bodies[pose.vehicle_id], physicsClientId=vehicles.cid)
        extent = np.subtract(hi, lo)
        length, width, height = pose.size_m or ()
        assert extent == pytest.approx([length, 0.92 * width, 0.85 * height], abs=0.05)
    # Resized in place when a vehicle's size changes (a pose without one: the reference car).
    truck = next(p for p in poses if p.size_m == full_scene.spec.vehicle_class("truck").size_m)
    vehicles.update([VehiclePose(truck.vehicle_id, truck.center_m, 0.0, rgba=truck.rgba)])
    lo, hi = pb.getAABB(vehicles.bodies[truck.vehicle_id], physicsClientId=vehicles.cid)
    assert hi[0] - lo[0] == pytest.approx(full_scene.spec.vehicle.length_m, abs=0.05)


def test_a_trucks_box_corners_and_lidar_returns_span_its_own_length(
    full_scene: Scene, static: StaticWorld, vehicles: VehicleWorld
) -> None:
    truck = full_scene.spec.vehicle_class("truck")
    pose = VehiclePose("v_truck", (0.0, 0.0, truck.height_m / 2), 0.0, size_m=truck.size_m)
    corners = vehicles_box_corners([pose], full_scene.spec.vehicle.size_m)[0]
    assert np.ptp(corners, axis=0) == pytest.approx(truck.size_m)
    vehicles.update([pose])
    lidar = LidarSimulator(full_scene, "lidar_11", static, vehicles)
    hits = lidar.cast([pose])
    on_truck = np.flatnonzero(hits.vehicle == 0)
    points = lidar.origins_world[on_truck] + lidar.dirs_world[on_truck] * hits.range_m[on_truck, None]
    # Beyond what a car-sized candidate box (4.5 m) would let through, within the truck's 8.5 m.
    assert 7.0 < np.ptp(points[:, 0]) <= truck.length_m + 0.05
    assert points[:, 2].max() > 0.9 * truck.height_m


def test_traffic_keeps_each_vehicles_own_length_apart(full_scene: Scene) -> None:
    scene = _scene_with_mix(full_scene, {"car": 0.5, "van": 0.1, "truck": 0.4})
    sim = TrafficSim(scene, RoadNetwork(scene), TrafficSettings(vehicles=24), seed=5, tick_hz=TICK_HZ)
    assert Counter(v.body.name for v in sim.vehicles)["truck"] == 10
    behind_truck = 0
    for tick in range(round(90 * TICK_HZ)):
        sim.step()
        if tick % 10:
            continue
        assert sim.overlapping_pairs() == []
        on_path: dict[str, list] = {}
        for v in sim.vehicles:
            on_path.setdefault(v.path.id, []).append(v)
        for queue in on_path.values():
            queue.sort(key=lambda v: v.s)
            for rear, front in itertools.pairwise(queue):
                gap_m = front.s - rear.s - (front.body.length_m + rear.body.length_m) / 2
                assert gap_m > 0.0, (rear.id, front.id, gap_m)
                behind_truck += front.body.name == "truck" and gap_m < 10.0
    assert behind_truck > 0  # vehicles did queue close behind trucks
    assert sum(sim.arrivals.values()) >= 20  # and the mix kept moving


def test_signal_heads_are_static_bodies_over_the_approaches(full_scene: Scene, static: StaticWorld) -> None:
    heads = [o for o in full_scene.spec.static_objects if o.kind == "signal_head"]
    assert {o.id for o in heads} == {f"signal_{a}_head" for a in "nesw"}
    for head in heads:
        bodies = [b for b, kind in static.body_kind.items() if kind == head.id]
        assert len(bodies) == 4  # housing and three lamp faces
        boxes = np.array([pb.getAABB(b, physicsClientId=static.cid) for b in bodies])
        lo, hi = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
        assert lo[2] == pytest.approx(4.6, abs=0.05) and hi[2] == pytest.approx(5.7, abs=0.05)
        # A ray down the approach toward the head, at lamp height, hits the head's lens side first.
        facing = np.array([np.cos(head.yaw_rad), np.sin(head.yaw_rad), 0.0])
        centre = np.array(head.position_m) + np.array([0.0, 0.0, 0.55])  # mid-height
        start = centre + 30.0 * facing
        hit = pb.rayTest(start.tolist(), centre.tolist(), physicsClientId=static.cid)[0]
        assert static.body_kind.get(hit[0]) == head.id
        assert np.linalg.norm(np.subtract(hit[3], centre)) < 0.2  # the lamp face, 0.15 m + lens
