"""The city study's arms on a 3 x 3 grid: every arm drives all vehicles home; the coordinator arm serves
plans from the production core that the vehicles' plan clients accept and SUMO drives."""

from __future__ import annotations

from pathlib import Path

import pytest
import sumolib

from shared.paths import REPO_ROOT
from shared.traffic.config import load_coordinator_settings
from sim.sumo import demand, network
from sim.sumo.scene import coverage_layout
from studies.city.run import ARMS, CityRun, roadside_model, run_arm
from studies.experiments.oracle import OracleErrorModel

ORACLE_MODEL = REPO_ROOT / "deploy" / "experiments" / "oracle_model.json"


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> CityRun:
    folder = tmp_path_factory.mktemp("city")
    net = network.grid_network(network.GridSpec(junctions_per_side=3), folder / "grid.net.xml")
    routes = demand.routed_demand(
        net, demand.DemandSpec(vehicles=40, end_s=60.0, min_distance_m=100.0), 1, folder / "s1.rou.xml"
    )
    layout = coverage_layout(sumolib.net.readNet(str(net)), 1.0, seed=1, range_sumo_m=60.0)
    return CityRun(net, routes, layout, seed=1, duration_s=600.0, reroute_period_s=20.0)


@pytest.mark.parametrize("arm", ARMS)
def test_every_arm_brings_every_vehicle_home(run: CityRun, arm: str, tmp_path: Path) -> None:
    model = OracleErrorModel.load(ORACLE_MODEL)
    result = run_arm(run, arm, load_coordinator_settings(), model, tmp_path)
    trips = result["trips"]
    assert trips["trips"] == 40 and trips["unfinished"] == 0 and trips["travel_time_mean_s"] > 0
    counts = result["counts"]
    assert counts["arrived"] == 40 and counts.get("route_refused", 0) == 0
    if arm == "sumo_covered":
        assert counts["reroute_rounds"] >= 1 and counts["rerouted"] > 0
    if arm == "rmmdet":
        served = counts["plans/served"]
        assert served > 20 and counts["clients/requests"] >= served
        assert counts["clients/answer/accepted"] == served + counts.get("plans/pushed", 0)
        assert counts["route_set"] == counts["clients/answer/accepted"]
        assert result["driver_ms"]["p95"] is not None


def test_roadside_agents_take_the_profile_s_errors() -> None:
    model = OracleErrorModel.load(ORACLE_MODEL)
    roadside = roadside_model(model, ["rsu_a", "rsu_b"], "agent1")
    assert sorted(roadside.agents) == ["rsu_a", "rsu_b"]
    assert (
        roadside.agents["rsu_a"] == model.agents["agent1"] and roadside.position_std_m == model.position_std_m
    )
    with pytest.raises(ValueError, match="not fitted"):
        roadside_model(model, ["rsu_a"], "agent9")


def test_vehicles_with_ids_as_real_scenarios_write_them_are_served(run: CityRun, tmp_path: Path) -> None:
    """Issue 53: a real city's ids (`Audinot_7_0`: capitals; dots, `#`) failed the bus's id
    pattern, so every route request was refused (`plans/vehicle_id`) and the rmmdet arm drove the
    scenario's own routes. Mapped onto the pattern and back (`sim.sumo.ids`), they are served."""
    import xml.etree.ElementTree as ET

    tree = ET.parse(run.routes)
    for k, vehicle in enumerate(tree.getroot().iter("vehicle")):
        vehicle.set("id", f"Audinot_{k}.Car#{vehicle.get('id')}")
    routes = tmp_path / "world_ids.rou.xml"
    tree.write(routes)
    world_run = CityRun(run.net, routes, run.layout, seed=1, duration_s=600.0, reroute_period_s=20.0)
    result = run_arm(
        world_run, "rmmdet", load_coordinator_settings(), OracleErrorModel.load(ORACLE_MODEL), tmp_path
    )
    counts = result["counts"]
    assert counts.get("plans/vehicle_id", 0) == 0 and counts["arrived"] == 40
    assert counts["plans/served"] > 20 and counts["clients/answer/accepted"] >= counts["plans/served"]
