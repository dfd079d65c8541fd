"""SumoWorld (libsumo in lock step): vehicles' states in the project's frame, routes given and refused,
SUMO's router fed chosen travel times, one world per process, the trips summarised from tripinfo."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import sumolib

from sim.sumo import demand, network, trips
from sim.sumo.world import Rerouting, SumoWorld, yaw_from_sumo_angle


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("grid")
    net = network.grid_network(network.GridSpec(junctions_per_side=3), folder / "grid.net.xml")
    spec = demand.DemandSpec(vehicles=20, end_s=40.0, min_distance_m=100.0)
    return net, demand.routed_demand(net, spec, 1, folder / "s1.rou.xml")


def test_sumo_heading_becomes_yaw() -> None:
    assert yaw_from_sumo_angle(90.0) == pytest.approx(0.0)  # east
    assert yaw_from_sumo_angle(0.0) == pytest.approx(math.pi / 2)  # north
    assert yaw_from_sumo_angle(180.0) == pytest.approx(-math.pi / 2)  # south
    assert abs(yaw_from_sumo_angle(270.0)) == pytest.approx(math.pi)  # west


def test_every_vehicle_arrives_and_states_follow_their_edges(grid: tuple[Path, Path], tmp_path: Path) -> None:
    net_path, routes = grid
    net = sumolib.net.readNet(str(net_path))
    tripinfo = tmp_path / "tripinfo.xml"
    seen = 0
    with SumoWorld(net_path, routes, seed=1, tripinfo=tripinfo) as world:
        while world.expected_vehicles() > 0 and world.time_s < 900:
            world.step()
            states = world.vehicles()
            for i, edge_id in enumerate(states.edge):
                if edge_id.startswith(":"):
                    continue  # inside a junction
                edge = net.getEdge(edge_id)
                (x0, y0), (x1, y1) = edge.getFromNode().getCoord(), edge.getToNode().getCoord()
                if min(math.dist(states.position_m[i], p) for p in ((x0, y0), (x1, y1))) < 40.0:
                    continue  # near a junction: may still be turning
                assert math.cos(states.yaw_rad[i] - math.atan2(y1 - y0, x1 - x0)) > 0.99  # along its edge
                seen += 1
        arrived = world.counts["arrived"]
        end_s = world.time_s
    summary = trips.summarise(tripinfo, 0.0, end_s)
    assert seen > 0 and summary.trips == arrived == 20 and summary.unfinished == 0
    assert summary.travel_time_mean_s > 0 and summary.trips_per_hour == pytest.approx(20 * 3600 / end_s)


def test_routes_are_given_refused_and_rerouted(grid: tuple[Path, Path]) -> None:
    net_path, routes = grid
    net = sumolib.net.readNet(str(net_path))
    with SumoWorld(net_path, routes, seed=1) as world:
        with pytest.raises(RuntimeError, match="one simulation per process"):
            SumoWorld(net_path, routes, seed=2)

        def choice(e: str) -> bool:  # on an edge with a choice of turns at its end
            return not e.startswith(":") and len(net.getEdge(e).getOutgoing()) >= 2

        while not any(choice(e) for e in world.vehicles().edge) or world.time_s < 5:
            world.step()  # a few seconds: SUMO lets a car that is only just inserted take any route
        states = world.vehicles()
        i = next(k for k, e in enumerate(states.edge) if choice(e))
        vid, here = states.ids[i], states.edge[i]
        route = world.route(vid)[world.route(vid).index(here) :]
        elsewhere = next(e.getID() for e in net.getEdges() if e.getID() not in route)
        assert not world.set_route(vid, [elsewhere])  # must start on the vehicle's current edge
        assert world.counts["route_refused"] == 1
        turns = [e.getID() for e in net.getEdge(here).getOutgoing()]
        other = next(e for e in turns if len(route) < 2 or e != route[1])
        assert world.set_route(vid, [here, other]) and world.route(vid)[-2:] == [here, other]
        # Tell the router that edge is very slow: rerouted to the old destination, another way.
        world.set_route(vid, route)
        world.adapt_travel_times({other: 1e6})
        world.reroute(vid)
        assert world.route(vid)[-1] == route[-1] and other not in world.route(vid)


def test_the_rerouting_device_options_are_pinned() -> None:
    options = Rerouting(period_s=30.0).options()
    assert "--device.rerouting.period=30.0" in options
    assert (
        "--device.rerouting.probability=1.0" in options
        and "--device.rerouting.adaptation-steps=180" in options
    )
    assert not any("adaptation-weight" in o for o in options)  # SUMO takes steps or weight, not both
