"""SUMO networks: the table exported with its ids and exactly its lane graph; generated grids and random
networks of the asked size; a failed SUMO command is a clear error."""

from __future__ import annotations

from pathlib import Path

import pytest
import sumolib

from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from sim.sumo import network, tools


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def test_table_network_keeps_ids_lane_graph_and_scaled_lengths(scene: Scene, tmp_path: Path) -> None:
    net = sumolib.net.readNet(str(network.table_network(scene, tmp_path / "table.net.xml")))
    assert {n.getID() for n in net.getNodes()} == {j.id for j in scene.spec.junctions}
    assert {e.getID() for e in net.getEdges()} == {lane.id for lane in scene.spec.lanes}
    for lane in scene.spec.lanes:
        edge = net.getEdge(lane.id)
        assert (edge.getFromNode().getID(), edge.getToNode().getID()) == (
            lane.from_junction,
            lane.to_junction,
        )
        assert edge.getLaneNumber() == 1
        assert edge.getSpeed() == pytest.approx(lane.speed_limit_mps * network.TABLE_SCALE, rel=1e-3)
        # SUMO trims a lane where it meets the junction's shape: at most a few metres of the full size.
        table_m = scene.lane_length_m(lane.id) * network.TABLE_SCALE
        assert table_m - 5.0 <= edge.getLength() <= table_m + 0.5, lane.id
    graph = RoadNetwork(scene).successors
    exported = {(e.getID(), to.getID()) for e in net.getEdges() for to in e.getOutgoing()}
    assert exported == {(a, b) for a, succ in graph.items() for b in succ}
    # No U-turn onto the same road's other lane, as on the table.
    assert not any(
        lane.reverse_lane and (lane.id, lane.reverse_lane) in exported for lane in scene.spec.lanes
    )


def test_grid_and_random_networks_have_the_asked_size(tmp_path: Path) -> None:
    spec = network.GridSpec(junctions_per_side=3, edge_length_m=150.0, lanes=2)
    grid = sumolib.net.readNet(str(network.grid_network(spec, tmp_path / "grid.net.xml")))
    assert len(grid.getNodes()) == 9
    assert len(grid.getEdges()) == 2 * 2 * 3 * 2  # 12 two-way roads of a 3 x 3 grid
    assert {e.getLaneNumber() for e in grid.getEdges()} == {2}
    # Junction to junction 150 m, less what the junctions' shapes take at both ends.
    assert all(120.0 <= e.getLength() <= 150.0 for e in grid.getEdges())
    rand = network.RandomSpec(iterations=40, seed=3)
    first = sumolib.net.readNet(str(network.random_network(rand, tmp_path / "r1.net.xml")))
    again = sumolib.net.readNet(str(network.random_network(rand, tmp_path / "r2.net.xml")))
    other = network.RandomSpec(iterations=40, seed=4)
    different = sumolib.net.readNet(str(network.random_network(other, tmp_path / "r3.net.xml")))

    def coords(net: sumolib.net.Net) -> list[tuple[float, float]]:
        return sorted(n.getCoord() for n in net.getNodes())

    assert len(first.getNodes()) > 10 and coords(first) == coords(again) != coords(different)


def test_a_failing_sumo_command_names_itself(tmp_path: Path) -> None:
    with pytest.raises(tools.SumoToolError, match="netconvert failed"):
        tools.run([tools.program("netconvert"), f"--node-files={tmp_path / 'missing.nod.xml'}"])
    with pytest.raises(tools.SumoToolError, match="not found"):
        tools.program("no-such-program")
