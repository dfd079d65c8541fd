"""The 3D view's Foxglove messages, known answers: the table's entities, a track's box, colour, id and
velocity arrow, a plan's line strip."""

from __future__ import annotations

import math

import numpy as np
import pytest
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from rmmdet.v1 import perception_pb2 as pb
from rmmdet.v1.planning_pb2 import RoutePlan
from rmmdet.v1.sensors_pb2 import RadarScan
from rmmdet.v1.sim_pb2 import GroundTruth
from rmmdet.v1.traffic_pb2 import TrafficMap

from shared.perception.output import detections_2d_message
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.viewer import scene as view
from shared.viewer.core import FRAMES, PLANS, TABLE, ViewerCore

STAMP_NS = 1_700_000_000_123_456_789


@pytest.fixture(scope="module")
def network(test_scene: Scene) -> RoadNetwork:
    return RoadNetwork(test_scene)


def roundtrip(update: SceneUpdate) -> SceneUpdate:
    out = SceneUpdate()
    out.ParseFromString(update.SerializeToString())
    return out


def test_the_table_has_every_lane_junction_and_sensor(test_scene: Scene, network: RoadNetwork) -> None:
    update = roundtrip(view.table(test_scene, network, STAMP_NS))
    by_id = {e.id: e for e in update.entities}
    assert {f"lane/{lane}" for lane in network.lanes} <= by_id.keys()
    for j in test_scene.spec.junctions:
        assert by_id[f"junction/{j.id}"].texts[0].text == str(j.number)
    assert {f"sensor/{s.id}" for s in test_scene.spec.sensors} <= by_id.keys()
    lane_id, path = next(iter(network.lanes.items()))
    line = by_id[f"lane/{lane_id}"].lines[0]
    got = np.array([(p.x, p.y) for p in line.points])
    np.testing.assert_allclose(got, np.asarray(path.points)[:, :2])
    assert all(e.frame_id == "world" and e.timestamp.ToNanoseconds() == STAMP_NS for e in update.entities)
    assert not any(e.HasField("lifetime") for e in update.entities)  # static


def test_a_sensor_wedge_spans_its_field_of_view_at_its_range(test_scene: Scene) -> None:
    spec = next(s for s in test_scene.spec.sensors if s.kind == "radar")
    assert spec.radar is not None
    wedge = np.array(view.fov_wedge(spec))
    x, y, z = spec.pose.position_m
    assert wedge[0] == pytest.approx((x, y, z)) and wedge[-1] == pytest.approx((x, y, z))
    reach = np.hypot(wedge[1:-1, 0] - x, wedge[1:-1, 1] - y)
    assert reach == pytest.approx(spec.radar.max_range_m)
    hfov = spec.radar.hfov_rad
    start = math.atan2(wedge[1, 1] - y, wedge[1, 0] - x)
    assert math.remainder(start - (view.sensor_yaw(spec) - hfov / 2), 2 * math.pi) == pytest.approx(
        0.0, abs=1e-9
    )


def track(track_id: int, modalities: list[int], state: int, v: tuple[float, float]) -> pb.TrackedObject:
    obj = pb.TrackedObject(track_id=track_id, state=state, modalities=modalities)
    obj.box.center_m.x, obj.box.center_m.y, obj.box.center_m.z = 1.0, 2.0, 0.05
    obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = 0.25, 0.1, 0.1
    obj.box.yaw_rad = math.pi / 2
    obj.velocity_mps.x, obj.velocity_mps.y = v
    return obj


def test_a_track_is_a_box_coloured_by_modality_with_its_id_and_velocity() -> None:
    msg = pb.TrackedObjects(agent_id="agent3")
    msg.objects.append(
        track(7, [pb.MODALITY_LIDAR, pb.MODALITY_CAMERA], pb.TRACK_STATE_CONFIRMED, (0.0, 0.3))
    )
    msg.objects.append(track(8, [], pb.TRACK_STATE_COASTING, (0.0, 0.0)))
    fused, coasting = roundtrip(view.tracked_objects("agent3", msg, STAMP_NS)).entities
    assert fused.id == "agent3/track/7" and fused.lifetime.ToNanoseconds() == 500_000_000
    cube = fused.cubes[0]
    assert (cube.pose.position.x, cube.pose.position.y, cube.pose.position.z) == pytest.approx(
        (1.0, 2.0, 0.05)
    )
    assert (cube.size.x, cube.size.y, cube.size.z) == pytest.approx((0.25, 0.1, 0.1))
    q = cube.pose.orientation
    assert (q.z, q.w) == pytest.approx((math.sin(math.pi / 4), math.cos(math.pi / 4)))
    assert (cube.color.r, cube.color.g, cube.color.b) == pytest.approx((0.2, 0.85, 0.3))  # lidar + camera
    assert fused.texts[0].text == "agent3:7"
    arrow = fused.arrows[0]
    assert arrow.shaft_length == pytest.approx(0.3)  # 1 s of travel
    assert arrow.pose.orientation.z == pytest.approx(math.sin(math.pi / 4))  # heading +y
    assert coasting.arrows == [] and coasting.cubes[0].color.a == pytest.approx(0.35)


def test_a_plan_is_a_line_along_its_lanes(network: RoadNetwork) -> None:
    lanes = list(network.lanes)[:2]
    plan = RoutePlan(vehicle_id="v03", plan_id="a" * 32, version=4, lane_ids=[*lanes, "no_such_lane"])
    (entity,) = roundtrip(view.route_plan(plan, network, STAMP_NS)).entities
    expected = [p for lane in lanes for p in network.lanes[lane].points]
    points = entity.lines[0].points
    assert len(points) == len(expected)
    assert (points[0].x, points[0].y) == pytest.approx(tuple(map(float, expected[0][:2])))
    assert entity.id == "plan/v03" and entity.texts[0].text == "v03 v4"
    empty = RoutePlan(vehicle_id="v03", plan_id="b" * 32, version=5, lane_ids=["no_such_lane"])
    assert not view.route_plan(empty, network, STAMP_NS).entities


def test_ground_truth_vehicles_are_their_own_layer() -> None:
    gt = GroundTruth()
    v = gt.vehicles.add(vehicle_id="v01")
    v.box.center_m.x, v.box.size_m.x = 0.5, 0.25
    (entity,) = view.ground_truth(gt, STAMP_NS).entities
    assert entity.id == "gt/v01" and entity.cubes[0].pose.position.x == pytest.approx(0.5)
    assert entity.lifetime.ToNanoseconds() > 0


def test_the_traffic_grid_packs_density_and_speed_per_cell() -> None:
    tm = TrafficMap()
    g = tm.grid
    g.origin_m.x_m, g.origin_m.y_m, g.cell_size_m = -1.0, -2.0, 0.5
    g.column_count, g.row_count = 3, 2
    g.vehicle_count.extend([0, 1, 2, 3, 4, 5])
    g.mean_speed_mps.extend([0, 0.1, 0.2, 0.3, 0.4, 0.5])
    grid = view.traffic_grid(tm, STAMP_NS)
    assert grid.column_count == 3 and grid.cell_size.x == pytest.approx(0.5)
    assert (grid.pose.position.x, grid.pose.position.y) == pytest.approx((-1.0, -2.0))
    cells = np.frombuffer(grid.data, dtype="<f4").reshape(2, 3, 2)  # rows, columns, fields
    assert cells[1, 2, 0] == pytest.approx(5.0) and cells[1, 2, 1] == pytest.approx(0.5)
    assert [f.name for f in grid.fields] == ["vehicles", "mean_speed_mps"]
    assert grid.row_stride == 3 * grid.cell_stride == 24


# --- the viewer's decision loop (shared/viewer/core.py) -------------------------------------------


def test_the_core_draws_the_table_and_plans_on_their_cadences(
    test_scene: Scene, network: RoadNetwork
) -> None:
    core = ViewerCore(test_scene, network)
    topics = [d.topic for d in core.draw(0.0, STAMP_NS)]
    assert topics == [TABLE, FRAMES]  # no plans yet
    assert core.draw(1.0, STAMP_NS) == []  # nothing new, no cadence due
    lane = next(iter(network.lanes))
    plan = RoutePlan(vehicle_id="v01", plan_id="a" * 32, version=1, lane_ids=[lane])
    plan.valid_until.FromNanoseconds(STAMP_NS + 10 * 10**9)
    core.on_plan(plan, now_s=1.1)
    core.on_tracks("agent1", pb.TrackedObjects(agent_id="agent1"), STAMP_NS)
    draws = {d.topic: d for d in core.draw(1.1, STAMP_NS)}
    assert set(draws) == {"/agents/agent1/tracks", PLANS}  # a changed plan at once
    assert [e.id for e in draws[PLANS].draw().entities] == ["plan/v01"]
    assert [d.topic for d in core.draw(2.0, STAMP_NS)] == [TABLE, FRAMES]  # table every 2 s
    (redraw,) = core.draw(2.2, STAMP_NS + 10**9)
    assert redraw.topic == PLANS  # plans every 1 s: as drawn before, stamped now (lifetime from now)
    (entity,) = redraw.draw().entities
    assert entity.timestamp.ToNanoseconds() == STAMP_NS + 10**9 and "v1" in entity.texts[0].text
    newer = RoutePlan(vehicle_id="v01", plan_id="b" * 32, version=2, lane_ids=[lane])
    newer.valid_until.CopyFrom(plan.valid_until)
    core.on_plan(newer, now_s=2.3)
    (entity,) = core.draw(2.3, STAMP_NS)[0].draw().entities
    assert "v2" in entity.texts[0].text  # a new plan is drawn anew
    assert core.draw(3.3, STAMP_NS + 11 * 10**9) == []  # its plan expired: dropped, nothing drawn
    assert core.plans == {}


def test_detections_become_image_annotations() -> None:
    rows = np.array([[10, 20, 50, 40, 0.75, 0]], np.float32)
    ann = view.image_annotations(detections_2d_message("cam_2", rows, 448, 336), STAMP_NS)
    (box,) = ann.points
    assert box.type == PointsAnnotation.LINE_LOOP
    assert [(p.x, p.y) for p in box.points] == [(10, 20), (50, 20), (50, 40), (10, 40)]
    assert box.timestamp.ToNanoseconds() == STAMP_NS
    (text,) = ann.texts
    assert text.text == "car 0.75"
    assert (text.position.x, text.position.y) == (10, 6)
    empty = view.image_annotations(pb.Detection2DArray(sensor_id="cam_2"), STAMP_NS)
    assert len(empty.points) == 0 and len(empty.texts) == 0


def test_lidar_and_radar_frames_are_placed_on_the_table(test_scene: Scene) -> None:
    frames = view.sensor_frames(test_scene, STAMP_NS)
    placed = {tf.child_frame_id: tf for tf in frames.transforms}
    expected = {s.id for s in test_scene.spec.sensors if s.kind in ("lidar", "radar")}
    assert set(placed) == expected and expected
    for sensor_id, tf in placed.items():
        T = np.asarray(test_scene.T_world_from_sensor(sensor_id))
        assert tf.parent_frame_id == "world"
        assert [tf.translation.x, tf.translation.y, tf.translation.z] == pytest.approx(T[:3, 3].tolist())
        q = tf.rotation  # the rotation of the quaternion applied to +x is the matrix's first column
        x_axis = [1 - 2 * (q.y**2 + q.z**2), 2 * (q.x * q.y + q.w * q.z), 2 * (q.x * q.z - q.w * q.y)]
        assert x_axis == pytest.approx(T[:3, 0].tolist(), abs=1e-9)


def test_radar_targets_are_spheres_in_the_radar_frame() -> None:
    scan = RadarScan(sensor_id="radar_2")
    scan.targets.add(range_m=2.0, azimuth_rad=math.pi / 2, elevation_rad=0.0, range_rate_mps=-0.5)
    scan.targets.add(range_m=1.0, azimuth_rad=0.0, elevation_rad=math.pi / 6, range_rate_mps=0.25)
    (entity,) = view.radar_targets(scan, STAMP_NS).entities
    assert entity.frame_id == "radar_2" and entity.lifetime.ToNanoseconds() > 0
    first, second = entity.spheres
    assert (first.pose.position.x, first.pose.position.y) == pytest.approx((0.0, 2.0), abs=1e-12)
    assert first.color == view.RADAR_APPROACHING and second.color == view.RADAR_RECEDING
    assert second.pose.position.z == pytest.approx(0.5)
    assert [t.text for t in entity.texts] == ["-0.50 m/s", "+0.25 m/s"]


def test_every_topic_the_core_draws_is_known_before_it_draws(test_scene: Scene, network: RoadNetwork) -> None:
    """The service advertises `topics()` at start: every draw of every input names one of them, with
    its type."""
    core = ViewerCore(test_scene, network)
    lane = next(iter(network.lanes))
    plan = RoutePlan(vehicle_id="v01", plan_id="a" * 32, version=1, lane_ids=[lane])
    plan.valid_until.FromNanoseconds(STAMP_NS + 10**10)
    core.on_plan(plan, now_s=0.0)
    for agent in test_scene.agents:
        core.on_tracks(agent, pb.TrackedObjects(agent_id=agent), STAMP_NS)
    core.on_ground_truth(GroundTruth(), STAMP_NS)
    core.on_traffic_map(TrafficMap(), STAMP_NS)
    drawn = {d.topic: d.message_type for d in core.draw(0.0, STAMP_NS)}
    assert drawn == core.topics()


def test_an_older_plan_does_not_replace_a_newer_one(test_scene: Scene, network: RoadNetwork) -> None:
    """A served copy (low priority) may arrive after a newer push: the newer stays drawn."""
    core = ViewerCore(test_scene, network)
    lane = next(iter(network.lanes))
    newer = RoutePlan(vehicle_id="v01", plan_id="b" * 32, version=6, lane_ids=[lane])
    older = RoutePlan(vehicle_id="v01", plan_id="a" * 32, version=5, lane_ids=[lane])
    for plan in (newer, older):
        plan.valid_until.FromNanoseconds(STAMP_NS + 10**10)
        core.on_plan(plan, now_s=0.0)
    assert core.plans["v01"].version == 6


def test_plans_beyond_the_cap_drop_their_drawings(
    test_scene: Scene, network: RoadNetwork, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("shared.viewer.core.MAX_PLANS", 2)
    core = ViewerCore(test_scene, network)
    lane = next(iter(network.lanes))
    for i in range(3):
        plan = RoutePlan(vehicle_id=f"v{i}", plan_id="a" * 32, version=1, lane_ids=[lane])
        plan.valid_until.FromNanoseconds(STAMP_NS + 10**10)
        core.on_plan(plan, now_s=float(i))
        for d in core.draw(float(i), STAMP_NS):
            d.draw()
    assert set(core.plans) == {"v1", "v2"}
    assert set(core._plan_entities) == {"v1", "v2"}  # the evicted vehicle's cached drawing is gone
