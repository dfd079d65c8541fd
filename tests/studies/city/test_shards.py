"""The coordinator in two region shards on a 3 x 3 SUMO grid (the issue's make-test case): every request
served, vehicles handed over between shards with their plans, never two owners; a shard killed mid-run
leaves the other's vehicles served and the killed region's vehicles on their plans, then a restarted
shard serves its region again."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import sumolib

from shared.paths import REPO_ROOT
from shared.scene.road_network import RoadNetwork
from shared.traffic.config import load_coordinator_settings
from shared.traffic.maps import AgentObjects
from shared.traffic.regions import RegionMap, partition_junctions
from sim.sumo import demand, network
from sim.sumo.scene import coverage_layout, scene_from_sumo
from studies.city.run import CityRun, run_arm
from studies.city.shards import ShardedCoordinator
from studies.experiments.oracle import OracleErrorModel

ORACLE_MODEL = REPO_ROOT / "deploy" / "experiments" / "oracle_model.json"


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> CityRun:
    folder = tmp_path_factory.mktemp("shards")
    net = network.grid_network(network.GridSpec(junctions_per_side=3), folder / "grid.net.xml")
    spec = demand.DemandSpec(vehicles=50, end_s=60.0, min_distance_m=100.0)
    routes = demand.routed_demand(net, spec, 2, folder / "s2.rou.xml")
    layout = coverage_layout(sumolib.net.readNet(str(net)), 1.0, seed=2, range_sumo_m=60.0)
    return CityRun(net, routes, layout, seed=2, duration_s=600.0, shards=2)


def _run(run: CityRun, tmp_path: Path) -> dict[str, int]:
    result = run_arm(
        run, "rmmdet", load_coordinator_settings(), OracleErrorModel.load(ORACLE_MODEL), tmp_path
    )
    assert result["trips"]["trips"] == 50 and result["trips"]["unfinished"] == 0  # everyone home
    counts: dict[str, int] = result["counts"]
    assert counts["shards/max_owners"] == 1  # never two owners (checked after every step)
    assert set(result["shard_ms"]) == {"0", "1"} and all(s["p95_ms"] > 0 for s in result["shard_ms"].values())
    return counts


def test_two_shards_serve_every_request_and_hand_vehicles_over(run: CityRun, tmp_path: Path) -> None:
    counts = _run(run, tmp_path)
    assert counts["plans/served"] == counts["clients/requests"] > 20  # no request refused
    assert counts["shards/served/0"] > 0 and counts["shards/served/1"] > 0
    assert counts["shards/handovers"] > 0
    assert counts["clients/answer/accepted"] == counts["plans/served"] + counts.get("plans/pushed", 0)


def test_a_killed_shard_leaves_the_other_serving_and_a_restarted_one_serves_again(
    run: CityRun, tmp_path: Path
) -> None:
    faulty = dataclasses.replace(run, kill_shard=1, kill_at_s=15.0, restart_after_s=30.0)
    counts = _run(faulty, tmp_path)
    assert counts["shards/killed"] == 1 and counts["shards/restarted"] == 1
    assert counts["plans/no_shard"] > 0  # region 1's requests while it was down
    assert counts["shards/served_since_killed/0"] > 0  # region 0 kept serving
    assert counts["shards/served_since_restarted/1"] > 0  # region 1 serves again after its restart
    refused = {k for k in counts if k.startswith("plans/") and k not in ("plans/served", "plans/pushed")}
    assert refused == {"plans/no_shard"}  # nothing else was refused


def test_a_shard_publishing_a_forged_clique_is_refused_and_its_prior_used(run: CityRun) -> None:
    scene, _ = scene_from_sumo(run.net, run.layout)
    regions = RegionMap(partition_junctions(RoadNetwork(scene), 2))
    sharded = ShardedCoordinator(scene, load_coordinator_settings(), regions, 64)
    rogue = sharded.shards[1]
    assert rogue is not None
    honest = rogue.clique
    rogue.clique = lambda: dataclasses.replace(honest(), time_s=np.zeros_like(honest().time_s))  # type: ignore[method-assign]
    sharded.update([AgentObjects.empty(a) for a in scene.agents], 1.0, 10**9)
    assert sharded.counts["rejected/clique_too_fast"] == 1
    own = sharded.shards[0]
    assert own is not None and own.shard is not None
    assert own.shard.cliques[1] is sharded.priors[1]  # region 1 planned on its prior, not the forgery
