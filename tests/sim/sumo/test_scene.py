"""A SUMO network as a scene: ids kept (made scene ids), lanes scaled to table metres with their reverse
lanes, roadside agents at the chosen junctions, the lane graph SUMO's; the production coordinator plans
on it routes SUMO accepts."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import sumolib
from rmmdet.v1.planning_pb2 import RouteRequest

from shared.scene.road_network import RoadNetwork
from shared.traffic.config import load_coordinator_settings
from shared.traffic.core import CoordinatorCore
from sim.sumo import network
from sim.sumo.scene import (
    UNCOVERED_AREA,
    RoadsideLayout,
    coverage_layout,
    scene_from_sumo,
    scene_ids,
    sumo_ids,
)


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("grid") / "grid.net.xml"
    return network.grid_network(network.GridSpec(junctions_per_side=3, edge_length_m=180.0), out)


def test_scene_ids_are_valid_and_never_merge_two_sumo_ids() -> None:
    """Plain where that is safe; escaped where the plain form would merge two ids, start with `_` or
    `-` (OpenStreetMap's reverse edges) or leave no room for an agent's prefix (Hamburg's cluster ids of
    90 characters failed the scene's id pattern as `area_<id>`)."""
    from shared.bus.streams import validate_id

    assert scene_ids(["A0", "A0B1", "x/y"]) == {"A0": "a0", "A0B1": "a0b1", "x/y": "x_y"}
    merged = scene_ids(["A0", "a0", "35[1]", "35_1_"])
    assert len(set(merged.values())) == 4 and merged["35_1_"] == "35_1_" and merged["A0"] != "a0"
    cluster = "cluster_246_cluster_" + "_".join(str(540212376 + k) for k in range(8))
    osm = scene_ids(["-23975#1", "23975#1", cluster, cluster + "0"])
    assert osm["23975#1"] == "23975_1" and osm["-23975#1"][0] not in "_-"
    assert len(set(osm.values())) == 4
    for scene in osm.values():
        validate_id(f"lidar_{scene}", "id")


def test_lanes_junctions_and_agents_of_the_grid(grid: Path) -> None:
    net = sumolib.net.readNet(str(grid))
    scene, ids = scene_from_sumo(grid, RoadsideLayout(("B1", "C1"), range_sumo_m=54.0))
    assert len(scene.spec.junctions) == 9 and len(scene.spec.lanes) == len(net.getEdges()) == 24
    for edge in net.getEdges():
        lane = scene.lanes[ids[edge.getID()]]
        assert (lane.from_junction, lane.to_junction) == (
            ids[edge.getFromNode().getID()],
            ids[edge.getToNode().getID()],
        )
        assert scene.lane_length_m(lane.id) == pytest.approx(edge.getLength() / network.TABLE_SCALE, rel=0.02)
        assert lane.speed_limit_mps == pytest.approx(edge.getSpeed() / network.TABLE_SCALE)
        reverse = scene.lanes[lane.reverse_lane] if lane.reverse_lane else None
        assert reverse is not None and (reverse.from_junction, reverse.to_junction) == (
            lane.to_junction,
            lane.from_junction,
        )
        # A lane belongs to the agent at its end junction, else at its start, else to nobody.
        end, start = edge.getToNode().getID(), edge.getFromNode().getID()
        expected = next((f"area_{ids[j]}" for j in (end, start) if j in ("B1", "C1")), UNCOVERED_AREA)
        assert lane.area == expected
    assert sorted(scene.agents) == ["rsu_b1", "rsu_c1"]
    lidar = scene.sensors_of("rsu_b1")[0]
    centre = net.getNode("B1").getCoord()
    assert scene.T_world_from_sensor(lidar.id)[:2, 3] == pytest.approx(
        [c / network.TABLE_SCALE for c in centre]
    )
    # The lane graph is SUMO's: every connection, nothing else.
    graph = RoadNetwork(scene).successors
    sumo_graph = {(ids[e.getID()], ids[t.getID()]) for e in net.getEdges() for t in e.getOutgoing()}
    assert {(a, b) for a, succ in graph.items() for b in succ} == sumo_graph
    with pytest.raises(ValueError, match="junctions the network lacks"):
        scene_from_sumo(grid, RoadsideLayout(("Z9",)))


def test_coverage_layouts_pick_crossings_reproducibly(grid: Path) -> None:
    net = sumolib.net.readNet(str(grid))
    full = coverage_layout(net, 1.0, seed=0, range_sumo_m=50.0)
    assert full.junctions == ("A1", "B0", "B1", "B2", "C1")  # the crossings; corners have two roads
    half = coverage_layout(net, 0.5, seed=3, range_sumo_m=50.0)
    assert half == coverage_layout(net, 0.5, seed=3, range_sumo_m=50.0) and len(half.junctions) == 2
    assert set(half.junctions) <= set(full.junctions)


def test_the_coordinator_plans_routes_sumo_accepts(grid: Path) -> None:
    net = sumolib.net.readNet(str(grid))
    scene, ids = scene_from_sumo(grid, RoadsideLayout(("B1",)))
    core = CoordinatorCore(scene, load_coordinator_settings(), max_vehicles=16)
    request = RouteRequest(
        vehicle_id="v0", current_lane_id=ids["A0A1"], lane_progress_m=0.5, destination_junction_id=ids["C2"]
    )
    plan, _ = core.serve(request, now_s=0.0, wall_ns=0)
    edges = sumo_ids(ids, list(plan.lane_ids))
    assert edges[0] == "A0A1" and net.getEdge(edges[-1]).getToNode().getID() == "C2"
    assert all(net.getEdge(b) in net.getEdge(a).getOutgoing() for a, b in itertools.pairwise(edges))
