"""RoutePlanner on a hand-checkable square (see scenes.planner_scene): every lane 0.5 m/s, connectors 0 m.

From lane `in` to junction jb: short route ab = 2 m (4 s), long route ac + cb = 1.5 m + 2.5 m (8 s)."""

from __future__ import annotations

import math
from collections import Counter

import pytest

from shared.scene.road_network import RoadNetwork
from shared.traffic.config import PlannerConfig
from shared.traffic.planner import LaneConditions, NoRouteError, Route, RoutePlanner
from tests.shared.traffic.scenes import planner_scene

SHORT = ["in", "ab"]
LONG = ["in", "ac", "cb"]


@pytest.fixture(scope="module")
def network() -> RoadNetwork:
    return RoadNetwork(planner_scene())


def make_planner(network: RoadNetwork, **cfg: object) -> RoutePlanner:
    settings = {"junction_service_s": 1.0, "load_weight": 2.0, "load_horizon_lanes": 3, "min_speed_mps": 0.05}
    settings.update(cfg)
    return RoutePlanner(network.scene, network, PlannerConfig(**settings))


def test_lane_graph_of_the_square(network: RoadNetwork) -> None:
    assert {lane: round(path.length_m, 9) for lane, path in network.lanes.items()} == {
        "in": 1.0,
        "ab": 2.0,
        "ac": 1.5,
        "cb": 2.5,
        "ba": 2.0,
        "bz": 5.0,
        "dead": round(math.sqrt(2.0), 9),
    }
    # No U-turn onto the same road's opposite lane: ab -/-> ba at jb, ba -/-> ab at ja.
    assert network.successors == {
        "in": ["ab", "ac"],
        "ab": ["bz", "dead"],
        "ac": ["cb"],
        "cb": ["ba", "bz", "dead"],
        "ba": ["ac"],
        "bz": ["in"],
        "dead": [],
    }
    # Coincident lane ends: an edge weighs exactly the lane it leads onto.
    for a, b in network.graph.edges:
        assert network.graph.edges[a, b]["weight"] == pytest.approx(network.lanes[b].length_m, abs=1e-9)


def test_shortest_picks_the_short_route_whatever_the_traffic(network: RoadNetwork) -> None:
    planner = make_planner(network)
    route = planner.plan("v1", "in", "jb", LaneConditions(), "shortest")
    assert route == Route(SHORT, ["ja"], pytest.approx(4.0), pytest.approx(3.0), "shortest")
    jammed = LaneConditions(count={"ab": 50.0}, speed_mps={"ab": 0.01})
    assert planner.plan("v1", "in", "jb", jammed, "shortest").lanes == SHORT
    assert planner.plan("v1", "in", "jb", jammed, "shortest").expected_travel_time_s == pytest.approx(4.0)


def test_shortest_never_u_turns(network: RoadNetwork) -> None:
    # ab -> ba would be 2 m, but it is a U-turn: the way back to ja is bz (5 m) then in (1 m).
    route = make_planner(network).plan("v1", "ab", "ja", LaneConditions(), "shortest")
    assert route.lanes == ["ab", "bz", "in"]
    assert route.junctions == ["jb", "jz"]
    assert route.length_m == pytest.approx(2.0 + 5.0 + 1.0)
    assert route.expected_travel_time_s == pytest.approx(6.0 / 0.5)


def test_default_policy_comes_from_the_config(network: RoadNetwork) -> None:
    planner = make_planner(network, policy="shortest")
    assert planner.plan("v1", "in", "jb", LaneConditions()).policy == "shortest"


# Break-even: the short lane (2 m) at speed v takes 2 / v; the long route takes 1.5/0.5 + 2.5/0.5 = 8 s,
# so the planner switches when 2 / v > 8, i.e. v < 0.25 m/s.
@pytest.mark.parametrize(
    ("speed_ab", "lanes", "time_s"),
    [
        (0.5, SHORT, 4.0),
        (0.3, SHORT, 2.0 / 0.3),
        (0.26, SHORT, 2.0 / 0.26),
        (0.24, LONG, 8.0),
        (0.2, LONG, 8.0),
        (5.0, SHORT, 4.0),  # measured speeds are capped at the speed limit
    ],
)
def test_dynamic_ground_truth_switches_below_the_break_even_speed(
    network: RoadNetwork, speed_ab: float, lanes: list[str], time_s: float
) -> None:
    cond = LaneConditions(speed_mps={"ab": speed_ab}, count={"ab": 30.0})  # counts do not matter here
    route = make_planner(network).plan("v1", "in", "jb", cond, "dynamic_ground_truth")
    assert route.lanes == lanes
    assert route.expected_travel_time_s == pytest.approx(time_s)
    assert route.length_m == pytest.approx(1.0 + (2.0 if lanes == SHORT else 4.0))
    assert route.junctions == (["ja"] if lanes == SHORT else ["ja", "jc"])


def test_stopped_lane_is_slow_not_closed(network: RoadNetwork) -> None:
    planner = make_planner(network)
    cond = LaneConditions(speed_mps={"ab": 0.0})
    assert planner.lane_time_s("ab", cond, "dynamic_ground_truth") == pytest.approx(2.0 / 0.05)
    assert planner.plan("v1", "in", "jb", cond, "dynamic_ground_truth").lanes == LONG


def test_balanced_lane_time_includes_queue_and_load(network: RoadNetwork) -> None:
    planner = make_planner(network, junction_service_s=2.0, load_weight=0.5)
    cond = LaneConditions(count={"ab": 1.0}, speed_mps={"ab": 0.25})
    # 2 m / 0.25 m/s + 2 s x (1 car + 0.5 x 3 planned)
    assert planner.lane_time_s("ab", cond, "balanced", Counter({"ab": 3})) == pytest.approx(8.0 + 5.0)
    assert planner.lane_time_s("ab", cond, "balanced") == pytest.approx(8.0 + 2.0)
    # the queue term is balanced's only
    assert planner.lane_time_s("ab", cond, "dynamic_ground_truth", Counter({"ab": 3})) == pytest.approx(8.0)


def test_balanced_on_free_speed_charges_the_queue_not_its_speed(network: RoadNetwork) -> None:
    """`speed_source: free`: a lane whose seen cars stand at a red light costs its free time plus the
    junction service per car, however slow they are; the other policies still read the speed."""
    planner = make_planner(network, junction_service_s=2.0, speed_source="free")
    cond = LaneConditions(count={"ab": 1.0}, speed_mps={"ab": 0.05})
    assert planner.lane_time_s("ab", cond, "balanced") == pytest.approx(4.0 + 2.0)  # 2 m / 0.5 m/s + 2 s
    assert planner.plan("v1", "in", "jb", cond, "balanced").lanes == SHORT
    assert planner.lane_time_s("ab", cond, "dynamic_ground_truth") == pytest.approx(2.0 / 0.05)
    perceived = make_planner(network, junction_service_s=2.0)
    assert perceived.plan("v1", "in", "jb", cond, "balanced").lanes == LONG  # 40 s + 2 s on ab


@pytest.mark.parametrize(
    ("cars_on_ab", "min_saving", "lanes"),
    [
        (5, 0.0, LONG),  # ab 4 + 5 = 9 s, the detour 8 s: the fastest, whatever it saves
        (5, 0.2, SHORT),  # saves 1 s of 9 (11 %): not worth a detour
        (5, 0.1, LONG),
        (7, 0.2, LONG),  # ab 11 s: the detour saves 27 %
    ],
)
def test_balanced_detours_only_for_a_clear_saving(
    network: RoadNetwork, cars_on_ab: int, min_saving: float, lanes: list[str]
) -> None:
    """`detour_min_saving`: the free-flow shortest route is kept unless the fastest route on the maps
    saves more than that share of its time (queue delay 1 s per car)."""
    planner = make_planner(network, detour_min_saving=min_saving)
    route = planner.plan("v1", "in", "jb", LaneConditions(count={"ab": float(cars_on_ab)}), "balanced")
    assert route.lanes == lanes
    assert route.expected_travel_time_s == pytest.approx(8.0 if lanes == LONG else 4.0 + cars_on_ab)


def test_balanced_spreads_successive_vehicles(network: RoadNetwork) -> None:
    planner = make_planner(network)  # junction service 1 s, load weight 2
    cond = LaneConditions(count={"ab": 1.0})  # one car on the short lane already
    # v1: short = 4 + 1 x (1 + 0) = 5 < long 8
    r1 = planner.plan("v1", "in", "jb", cond, "balanced")
    assert (r1.lanes, r1.expected_travel_time_s) == (SHORT, pytest.approx(5.0))
    planner.commit("v1", r1)
    # v2: short = 4 + 1 x (1 + 2 x 1) = 7 < 8
    r2 = planner.plan("v2", "in", "jb", cond, "balanced")
    assert (r2.lanes, r2.expected_travel_time_s) == (SHORT, pytest.approx(7.0))
    planner.commit("v2", r2)
    # v3: short = 4 + 1 x (1 + 2 x 2) = 9 > long 8
    r3 = planner.plan("v3", "in", "jb", cond, "balanced")
    assert (r3.lanes, r3.junctions, r3.expected_travel_time_s) == (LONG, ["ja", "jc"], pytest.approx(8.0))
    planner.commit("v3", r3)
    assert planner.planned_load() == Counter({"ab": 2, "ac": 1, "cb": 1})
    assert planner.planned_load(exclude="v1") == Counter({"ab": 1, "ac": 1, "cb": 1})
    # v4: short 9 vs long (3 + 2) + (5 + 2) = 12
    assert planner.route_time_s(LONG, cond, "balanced", exclude="v4") == pytest.approx(12.0)
    r4 = planner.plan("v4", "in", "jb", cond, "balanced")
    assert (r4.lanes, r4.expected_travel_time_s) == (SHORT, pytest.approx(9.0))
    # a vehicle's own committed load does not count against it: v1 sees 4 + 1 + 2 x 1 = 7
    assert planner.plan("v1", "in", "jb", cond, "balanced").expected_travel_time_s == pytest.approx(7.0)
    # forgetting v1 and v2 clears the short lane again
    planner.forget("v1")
    planner.forget("v2")
    planner.forget("never-planned")
    assert planner.planned_load() == Counter({"ac": 1, "cb": 1})
    r5 = planner.plan("v5", "in", "jb", cond, "balanced")
    assert (r5.lanes, r5.expected_travel_time_s) == (SHORT, pytest.approx(5.0))


def test_commit_counts_only_the_load_horizon(network: RoadNetwork) -> None:
    planner = make_planner(network, load_horizon_lanes=1)
    planner.commit("v1", Route(LONG, ["ja", "jc"], 8.0, 5.0, "balanced"))
    assert planner.planned_load() == Counter({"ac": 1})  # current lane excluded, cb beyond the horizon
    planner.commit("v1", Route(SHORT, ["ja"], 4.0, 3.0, "balanced"))  # a new plan replaces the old
    assert planner.planned_load() == Counter({"ab": 1})


@pytest.mark.parametrize(
    ("count", "rank", "expected"),
    [
        ({}, {"south": 0, "north": 1}, "ab"),  # (0+1)(0+1)=1 < (0+1)(1+1)=2
        ({"ab": 1.0}, {"south": 0, "north": 1}, "ab"),  # 2 = 2: tie -> first successor
        ({"ab": 2.0}, {"south": 0, "north": 1}, "ac"),  # 3 > 2
        ({}, {"south": 1, "north": 0}, "ac"),  # 2 > 1
        ({"ac": 3.0}, {"south": 1, "north": 0}, "ab"),  # 2 < 4
        ({}, {}, "ab"),  # nothing known: all scores 1, first successor
    ],
)
def test_paper_rule_minimises_count_times_rank(
    network: RoadNetwork, count: dict[str, float], rank: dict[str, int], expected: str
) -> None:
    route = make_planner(network).plan(
        "v1", "in", "jb", LaneConditions(count=count, area_rank=rank), "paper_rule"
    )
    assert route.lanes == ["in", expected]  # one junction at a time, whatever the destination
    assert route.junctions == ["ja"]
    assert route.policy == "paper_rule"
    assert route.expected_travel_time_s == pytest.approx(network.lanes[expected].length_m / 0.5)


def test_random_returns_only_successors_and_is_seeded(network: RoadNetwork) -> None:
    a = make_planner(network, seed=3)
    b = make_planner(network, seed=3)
    picks = [a.plan("v1", "ab", "ja", LaneConditions(), "random").lanes for _ in range(60)]
    assert all(p[0] == "ab" and len(p) == 2 for p in picks)
    assert {p[1] for p in picks} == {"bz", "dead"}  # never the U-turn ba
    assert picks == [b.plan("v1", "ab", "ja", LaneConditions(), "random").lanes for _ in range(60)]


@pytest.mark.parametrize("policy", ["random", "paper_rule", "shortest", "dynamic_ground_truth", "balanced"])
@pytest.mark.parametrize(
    ("lane", "destination"),
    [("nope", "jb"), ("in", "nope"), ("dead", "jb")],
)
def test_unknown_ids_and_dead_ends_raise(
    network: RoadNetwork, policy: str, lane: str, destination: str
) -> None:
    with pytest.raises(NoRouteError):
        make_planner(network).plan("v1", lane, destination, LaneConditions(), policy)  # type: ignore[arg-type]


@pytest.mark.parametrize("policy", ["shortest", "dynamic_ground_truth", "balanced"])
def test_unreachable_destination_raises(network: RoadNetwork, policy: str) -> None:
    with pytest.raises(NoRouteError, match="unreachable"):
        make_planner(network).plan("v1", "in", "jx", LaneConditions(), policy)  # type: ignore[arg-type]
    assert issubclass(NoRouteError, ValueError)


@pytest.mark.parametrize("policy", ["shortest", "dynamic_ground_truth", "balanced"])
def test_lane_ending_at_the_destination_is_the_whole_route(network: RoadNetwork, policy: str) -> None:
    route = make_planner(network).plan("v1", "in", "ja", LaneConditions(count={"in": 9.0}), policy)  # type: ignore[arg-type]
    assert route.lanes == ["in"]
    assert route.junctions == []
    assert route.expected_travel_time_s == 0.0
    assert route.length_m == pytest.approx(1.0)
