"""The city study on public real-city SUMO scenarios (tests/fixtures/real/sumo_scenarios: Bologna's
Andrea Costa and Pasubio districts, the Hamburg test field), each as SUMO reads its configuration, for a
few simulated minutes (issue 53 item 1).

What each first broke: Bologna's configuration root `<sumoConfiguration>` was refused; its edge and node
ids (`35[1][1]`, node and edge both `104`) made lanes of bus-only edges and of junctions; 15 % of the
coordinator's plans took turns the crossings forbid (SUMO refused them); its `ignoring` cars end trips on
bus lanes no car plan reaches (5 % `no_route`); Hamburg's 90-character cluster ids failed the scene's
id pattern; the detectors' outputs were written into the vendored folder."""

from __future__ import annotations

from pathlib import Path

import pytest
import sumolib

from shared.paths import REPO_ROOT
from shared.traffic.config import load_coordinator_settings
from sim.sumo.scenario import load_scenario, stage
from sim.sumo.scene import coverage_layout
from studies.city.config import CityStudySettings
from studies.city.run import CityRun, run_arm
from studies.city.study import markdown_table, run_study
from studies.experiments.oracle import OracleErrorModel

SCENARIOS = REPO_ROOT / "tests" / "fixtures" / "real" / "sumo_scenarios"
ORACLE_MODEL = REPO_ROOT / "deploy" / "experiments" / "oracle_model.json"
CONFIGS = {
    "bologna_acosta": "run.sumocfg",
    "bologna_pasubio": "run.sumocfg",
    "hamburg_tavf": "run_simulation.sumocfg",
}


def _run(name: str, work: Path, duration_s: float, coverage: float = 0.5) -> CityRun:
    scn = stage(load_scenario(SCENARIOS / name / CONFIGS[name]), work / "inputs")
    layout = coverage_layout(sumolib.net.readNet(str(scn.net)), coverage, 1, 60.0)
    return CityRun(
        scn.net, scn.routes, layout, 1, duration_s, additional=scn.additional, begin_s=scn.begin_s,
        reroute_period_s=60.0,
    )  # fmt: skip


def _reroutes(tripinfo: Path, kept: bool, kept_ids: set[str]) -> list[int]:
    return [
        int(t.rerouteNo) for t in sumolib.xml.parse(str(tripinfo), "tripinfo") if (t.id in kept_ids) == kept
    ]


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_the_coordinator_serves_a_real_city_s_cars_and_leaves_its_buses_alone(
    name: str, tmp_path: Path
) -> None:
    """Every request answered, none refused for its id; buses (and Bologna's bus-lane cars, Hamburg's
    trucks) keep their routes; SUMO takes nearly every plan; the vendored folder gains no file."""
    before = sorted(p.name for p in (SCENARIOS / name).iterdir())
    model = OracleErrorModel.load(ORACLE_MODEL)
    result = run_arm(_run(name, tmp_path, 150.0), "rmmdet", load_coordinator_settings(), model, tmp_path)
    counts = result["counts"]
    print(name, {k: v for k, v in counts.items() if not k.startswith("shards/")})
    assert sorted(p.name for p in (SCENARIOS / name).iterdir()) == before
    assert counts["plans/served"] > 100
    refused = {
        k: v
        for k, v in counts.items()
        if k.startswith("plans/") and k not in ("plans/served", "plans/pushed")
    }
    assert refused == {}, refused  # no vehicle_id, unknown_lane or no_route
    assert counts.get("route_refused", 0) <= 0.01 * counts["route_set"]
    assert counts.get("kept/class_bus", 0) > 0 and counts.get("kept/route_refused", 0) == 0
    assert result["trips"]["trips"] > 0


def test_sumo_s_rerouting_device_leaves_the_kept_vehicles_alone(tmp_path: Path) -> None:
    """The oracle arm (SUMO's device on every vehicle) reroutes cars but no bus: the device is switched
    off per kept vehicle as SUMO loads it (5 of 35 Pasubio buses were rerouted before)."""
    from sim.sumo.world import KeptVehicles, Rerouting, SumoWorld

    run = _run("bologna_pasubio", tmp_path, 600.0)
    tripinfo = tmp_path / "oracle.tripinfo.xml"
    with SumoWorld(
        run.net, run.routes, 1, rerouting=Rerouting(period_s=30.0, pre_period_s=30.0), tripinfo=tripinfo,
        additional=run.additional, keep=KeptVehicles(),
    ) as world:  # fmt: skip
        while world.time_s < 600.0:
            world.step()
        kept = set(world.kept)
    assert kept and max(_reroutes(tripinfo, True, kept)) == 0
    assert sum(_reroutes(tripinfo, False, kept)) > 50


def test_a_study_of_a_scenario_compares_every_arm(tmp_path: Path) -> None:
    """`scenario:` in the settings: the scenario's demand (scaled) under every arm, compared per level."""
    s = CityStudySettings(
        scenario=SCENARIOS / "bologna_pasubio" / "run.sumocfg", scale=[1.0], duration_s=120.0, seeds=[1, 2],
        coverage=[0.5], reroute_period_s=30.0, workers=1,
    )  # fmt: skip
    results = run_study(s, tmp_path / "work", tmp_path / "out")
    assert len(results["runs"]) == 2 * 5
    row = results["comparisons"]["x1@0.5"]
    assert set(row) == {"as_given", "shortest", "sumo_oracle", "sumo_covered"}
    assert all(v["travel_time_mean_s"]["n"] == 2 for v in row.values())
    assert "SUMO scenario bologna_pasubio/run.sumocfg" in markdown_table(results)
    assert not any(p.name.startswith("e1_output") for p in (SCENARIOS / "bologna_pasubio").iterdir())


def test_real_cities_are_tuned_on_one_scenario_and_scored_on_the_others(tmp_path: Path) -> None:
    """`rmmdet experiments cities`: the setting chosen on the tuning scenario's tuning seeds, then every
    other scenario scored on the held-out seeds with it; the tuning scenario is not in the table."""
    from studies.city.real import RealCitiesSettings, markdown_table, run_cities

    s = RealCitiesSettings(
        scenarios={n: SCENARIOS / n / CONFIGS[n] for n in ("bologna_acosta", "bologna_pasubio")},
        tuning="bologna_acosta", candidates=["table", "district"],
        study={"seeds": [1, 2], "coverage": [0.5], "duration_s": 60.0, "workers": 1},
    )  # fmt: skip
    results = run_cities(s, tmp_path / "work", tmp_path / "out")
    tuning = results["tuning"]
    assert set(tuning["mean_travel_time_s"]) == {"table", "district"}
    assert tuning["chosen"] == min(tuning["mean_travel_time_s"], key=tuning["mean_travel_time_s"].get)
    assert list(results["held_out"]) == ["bologna_pasubio"]
    table = markdown_table(results)
    assert "| bologna_pasubio | x1@0.5 |" in table and "| bologna_acosta |" not in table
    assert (tmp_path / "out" / "results.json").is_file()
