"""Regions of a road network: balanced partitions pinned as configuration, crossing lanes, and overlay
routes across regions exactly as fast as the fastest route on the whole lane graph (CRP's promise)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra

from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import PlannerConfig
from shared.traffic.planner import LaneConditions, RoutePlanner, ShardView
from shared.traffic.regions import Overlay, RegionMap, partition_junctions
from sim.sumo import network as sumo_network
from sim.sumo.scene import RoadsideLayout, scene_from_sumo


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> RoadNetwork:
    net = sumo_network.grid_network(
        sumo_network.GridSpec(junctions_per_side=5), tmp_path_factory.mktemp("grid") / "g.net.xml"
    )
    scene, _ = scene_from_sumo(net, RoadsideLayout(()))
    return RoadNetwork(scene)


def test_partitions_are_balanced_reproducible_and_pinned(grid: RoadNetwork, tmp_path: Path) -> None:
    for k in (1, 2, 3, 4):
        regions = partition_junctions(grid, k, seed=0)
        sizes = np.bincount(list(regions.values()))
        assert len(regions) == 25 and len(sizes) == k and sizes.max() - sizes.min() <= 25 // k
        assert regions == partition_junctions(grid, k, seed=0)
    four = RegionMap(partition_junctions(grid, 4))
    crossing = four.crossing_lanes(grid)
    # A 5 x 5 grid (40 two-way roads) cut in 4: at best 10 roads; Kernighan-Lin's bisections within
    # 16 (seed 0 cuts 15), each road a lane each way.
    assert 0 < len(crossing) <= 32 and len(crossing) % 2 == 0
    four.save(tmp_path / "regions.json")
    assert RegionMap.load(tmp_path / "regions.json", grid) == four
    (tmp_path / "bad.json").write_text('{"regions": {"a0": 0}}')
    with pytest.raises(ValueError, match="junctions without a region"):
        RegionMap.load(tmp_path / "bad.json", grid)
    with pytest.raises(ValueError, match="regions must be within"):
        partition_junctions(grid, 26)


@pytest.mark.parametrize(("regions", "turn_penalty_s"), [(1, 0.0), (2, 0.0), (4, 0.0), (4, 3.0)])
def test_overlay_routes_are_as_fast_as_the_whole_graph(
    grid: RoadNetwork, regions: int, turn_penalty_s: float
) -> None:
    overlay = Overlay(grid, RegionMap(partition_junctions(grid, regions)), turn_penalty_s)
    rng = np.random.default_rng(regions)
    junctions = sorted(set(overlay.end_junction))
    for trial in range(40):
        lane_time_s = rng.uniform(5.0, 60.0, len(overlay.lane_ids))  # congestion anywhere
        cliques = {r: overlay.clique(r, lane_time_s) for r in range(regions)}
        start = overlay.lane_ids[rng.integers(len(overlay.lane_ids))]
        destination = junctions[rng.integers(len(junctions))]
        if grid.lane_end_junction(start) == destination:
            continue
        lanes = overlay.route(start, destination, lane_time_s, cliques)
        assert grid.is_valid_route(start, lanes) and grid.lane_end_junction(lanes[-1]) == destination
        dist = dijkstra(overlay._graph(lane_time_s, None), indices=overlay.index[start])
        ends = [k for k, j in enumerate(overlay.end_junction) if j == destination]
        best = min(dist[k] for k in ends)
        got = overlay.route_time_s(start, lanes, lane_time_s)
        assert got == pytest.approx(best, rel=1e-9), (trial, start, destination)


def test_the_sand_table_splits_too() -> None:
    net = RoadNetwork(Scene.load(DEFAULT_SCENE))
    regions = RegionMap(partition_junctions(net, 2))
    assert regions.regions == 2 and regions.crossing_lanes(net)
    overlay = Overlay(net, regions)
    times = np.full(len(overlay.lane_ids), 10.0)
    cliques = {r: overlay.clique(r, times) for r in range(2)}
    for lane in overlay.lane_ids:
        for junction in sorted(set(overlay.end_junction) - {net.lane_end_junction(lane)}):
            route = overlay.route(lane, junction, times, cliques)
            assert net.is_valid_route(lane, route) and net.lane_end_junction(route[-1]) == junction


def test_a_region_s_clique_steers_routes_and_a_prior_stands_in_for_a_lost_one(grid: RoadNetwork) -> None:
    regions = RegionMap(partition_junctions(grid, 2))
    overlay = Overlay(grid, regions)
    free = np.full(len(overlay.lane_ids), 10.0)
    jammed = free * 100.0
    start = next(lane for lane in overlay.lane_ids if overlay.lane_region[overlay.index[lane]] == 0)
    home = next(
        j
        for j, r in sorted(regions.region_of_junction.items())
        if r == 0 and j != grid.lane_end_junction(start)
    )
    away = next(j for j, r in sorted(regions.region_of_junction.items()) if r == 1)
    # Region 1 reports a jam: a trip inside region 0 does not cut through it.
    cliques = {0: overlay.clique(0, free), 1: overlay.clique(1, jammed)}
    route = overlay.route(start, home, free, cliques)
    assert all(regions.region_of_junction[grid.lane_end_junction(lane)] == 0 for lane in route)
    # Region 1's shard is gone: without its clique nothing in it is reachable; a free-flow prior stands in.
    with pytest.raises(ValueError, match="unreachable"):
        overlay.route(start, away, free, {0: cliques[0]})
    prior = overlay.route(start, away, free, {0: cliques[0], 1: overlay.clique(1, free)})
    assert grid.is_valid_route(start, prior) and grid.lane_end_junction(prior[-1]) == away


def test_a_forged_clique_is_refused_with_its_reason(grid: RoadNetwork) -> None:
    import dataclasses

    overlay = Overlay(grid, RegionMap(partition_junctions(grid, 2)))
    free = np.array(
        [grid.lanes[lane].length_m / grid.scene.lanes[lane].speed_limit_mps for lane in overlay.lane_ids]
    )
    np.testing.assert_allclose(overlay.free_time_s, free)  # the floor every shard checks cliques against
    jammed = free * 3.0
    good = overlay.clique(1, jammed)
    assert overlay.clique_problem(good, free) is None
    assert overlay.clique_problem(overlay.clique(0, free), free) is None  # free flow exactly: allowed
    i, j = np.argwhere(np.isfinite(good.time_s))[0]
    a, b = good.entering[i], good.leaving[j]

    def forged(**change: object) -> str | None:
        return overlay.clique_problem(dataclasses.replace(good, **change), free)

    def with_time(value: float) -> np.ndarray:
        t = good.time_s.copy()
        t[i, j] = value
        return t

    assert forged(region=7) == "clique_region"
    assert forged(entering=good.entering[1:]) == "clique_lanes"
    assert forged(time_s=good.time_s[:, 1:]) == "clique_shape"
    assert forged(time_s=with_time(-1.0)) == "clique_time"
    assert forged(time_s=with_time(float("nan"))) == "clique_time"
    assert forged(time_s=with_time(0.1)) == "clique_too_fast"  # a black hole drawing traffic in
    other_region = next(lane for lane in overlay.lane_ids if overlay.lane_region[overlay.index[lane]] == 0)
    assert forged(paths={**good.paths, (a, b): [other_region]}) == "clique_path"
    assert forged(paths={**good.paths, (a, b): ["no-such-lane"]}) == "clique_path"
    missing = {k: v for k, v in good.paths.items() if k != (a, b)}
    assert forged(paths=missing) == "clique_path"
    # No way where the region has one at free flow: refused (issue 52 item 3: a clique of all inf shut
    # the region; where it has none, a U-turn pair, inf needs no path: test_shard_messages.py).
    assert forged(time_s=with_time(float("inf")), paths=missing) == "clique_no_way"


def test_turns_are_measured_and_a_turn_penalty_takes_the_route_with_fewest_turns(grid: RoadNetwork) -> None:
    import itertools
    import math

    turns = {(a, b): d["turn_rad"] for a, b, d in grid.graph.edges(data=True)}
    # A grid's junctions: straight on (0), right and left (a right angle each); no U-turns.
    assert all(t < 0.05 or abs(t - math.pi / 2) < 0.05 for t in turns.values())
    assert sum(t < 0.05 for t in turns.values()) > 0 and sum(t > 1.5 for t in turns.values()) > 0

    def turn_count(lanes: list[str]) -> int:
        return sum(turns[(a, b)] > math.pi / 4 for a, b in itertools.pairwise(lanes))

    # From a lane leaving one corner to the opposite corner: many equally long staircase routes.
    corners = sorted({grid.lane_start_junction(lane) for lane in grid.lanes})
    start = next(lane for lane in sorted(grid.lanes) if grid.lane_start_junction(lane) == corners[0])
    origin = grid.lanes[start].points[0][:2]
    far = max(
        sorted({grid.lane_end_junction(lane) for lane in grid.lanes}),
        key=lambda j: max(
            float(np.hypot(*(grid.lanes[lane].points[-1][:2] - origin)))
            for lane in grid.lanes
            if grid.lane_end_junction(lane) == j
        ),
    )
    penalised = RoutePlanner(grid.scene, grid, PlannerConfig(policy="shortest", turn_penalty_s=3.0))
    route = penalised.plan("v1", start, far, LaneConditions())
    assert turn_count(route.lanes) <= 1  # an L, the fewest turns a corner-to-corner trip can take
    plain = RoutePlanner(grid.scene, grid, PlannerConfig(policy="shortest")).plan(
        "v1", start, far, LaneConditions()
    )
    # Without it, the shortest route zig-zags (a right turn's connector is the shortest way across a
    # junction) and is barely shorter: what made the city study's vehicles slower on coordinator routes.
    assert turn_count(plain.lanes) > turn_count(route.lanes)

    def length_m(lanes: list[str]) -> float:
        return sum(grid.lanes[lane].length_m for lane in lanes)

    assert length_m(route.lanes) == pytest.approx(length_m(plain.lanes), rel=0.02)


def test_a_shard_detours_only_for_a_clear_saving(grid: RoadNetwork) -> None:
    """`planner.detour_min_saving` on a shard: the free-flow shortest route (searched on free-flow
    cliques) is kept unless the fastest route on the published cliques saves more than that share."""
    overlay = Overlay(grid, RegionMap(partition_junctions(grid, 2)))
    start = overlay.lane_ids[0]
    destination = max(sorted(set(overlay.end_junction)), key=lambda j: len(grid.shortest_route(start, j)))
    shortest = RoutePlanner(grid.scene, grid, PlannerConfig(policy="shortest"))
    free = shortest.plan("v", start, destination, LaneConditions())
    jam = LaneConditions(count=dict.fromkeys(free.lanes[1:], 50.0))  # 50 s of queue on each of its lanes

    def shard_plan(min_saving: float) -> list[str]:
        cfg = PlannerConfig(detour_min_saving=min_saving)
        planners = [RoutePlanner(grid.scene, grid, cfg, ShardView(overlay, r)) for r in range(2)]
        cliques = {r: p.clique(jam) for r, p in enumerate(planners)}
        own = planners[int(overlay.lane_region[overlay.index[start]])]
        assert own.shard is not None
        own.shard.cliques = cliques
        return own.plan("v", start, destination, jam, "balanced").lanes

    assert shard_plan(0.0) != free.lanes  # the jam is worth a detour
    assert shard_plan(0.95) == free.lanes  # ... but not one saving 95 % of the jammed route's time


def test_a_real_city_splits_with_its_entry_junctions() -> None:
    """Bologna's Pasubio net has junctions where lanes only begin (`1-begin`): every shard of
    `make up WORLD=city SHARDS=2` crashed building the free-flow cliques (KeyError on such a junction)."""
    from shared.paths import REPO_ROOT
    from sim.sumo.scene import RoadsideLayout, scene_from_sumo

    net_path = REPO_ROOT / "tests/fixtures/real/sumo_scenarios/bologna_pasubio/pasubio_buslanes.net.xml"
    scene, _ = scene_from_sumo(net_path, RoadsideLayout(()))
    net = RoadNetwork(scene)
    starts_only = {net.lane_start_junction(lane) for lane in net.lanes} - {
        net.lane_end_junction(lane) for lane in net.lanes
    }
    assert starts_only
    overlay = Overlay(net, RegionMap(partition_junctions(net, 2)))
    cliques = overlay.free_flow_cliques()
    assert set(cliques) == {0, 1} and all(np.isfinite(c.time_s).any() for c in cliques.values())
