"""Flow experiment: runs drive planned routes, count flow and trips, and the statistics are right."""

from __future__ import annotations

import numpy as np
import pytest

from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings
from shared.traffic.maps import AgentObjects
from sim.config import load_sim_settings
from sim.traffic import TrafficSim
from studies.experiments import report
from studies.experiments.config import FlowExperimentSettings, parse_arm
from studies.experiments.flow import RunResult, Scheduler, run_flow, traffic_settings, vehicle_state
from studies.experiments.oracle import AgentErrors, ErrorObserver, OracleAgents, OracleErrorModel, match

DURATION_S = 20.0


@pytest.fixture(scope="module")
def setup() -> tuple[Scene, object, CoordinatorSettings, FlowExperimentSettings]:
    sim = load_sim_settings()
    return Scene.load(sim.scene), sim, CoordinatorSettings(), FlowExperimentSettings(duration_s=DURATION_S)


@pytest.mark.parametrize(
    "policy",
    ["random", "paper_rule", "paper_rule@ground_truth", "shortest", "dynamic_ground_truth", "balanced"],
)
def test_every_policy_plans_and_moves_traffic(setup, policy) -> None:  # type: ignore[no-untyped-def]
    scene, sim, coord, exp = setup
    result = run_flow(scene, sim, coord, exp, policy, vehicles=8, seed=7)
    counts = result.extra["plan_counts"]
    # Every request is served and every plan applied: the vehicles acknowledge each one as accepted.
    assert not [k for k in counts if k.startswith(("plans/", "rejected/"))], counts
    assert counts.get("acks/accepted", 0) == result.plans >= 8
    if policy.startswith(("random", "shortest", "paper_rule")):
        assert result.extra["plans_pushed"] == 0  # one-junction or map-free policies are never re-planned
    assert result.total_flow > 0
    assert set(result.arrivals) == {j.number for j in scene.spec.junctions}
    assert 0.0 < result.mean_speed_mps <= sim.traffic.max_speed_mps + 1e-9
    assert result.speed_samples.sum() > 0
    if policy != "random" and policy != "shortest":
        assert result.extra["map_updates"] == round(DURATION_S / exp.map_period_s)
    if policy.endswith("ground_truth"):  # maps of exact positions on every lane: no count error
        assert result.extra["lane_count_abs_error_per_update"] == 0.0


def test_vehicles_follow_their_plans(setup) -> None:  # type: ignore[no-untyped-def]
    """Every lane a vehicle enters is the one its latest plan named (shortest: whole routes)."""
    scene, sim, coord, _exp = setup
    traffic = TrafficSim(scene, _net(scene), traffic_settings(sim, 6), 3, sim.tick_hz)
    scheduler = Scheduler(scene, coord, "shortest", 3, None, len(traffic.vehicles))
    expected: dict[str, str] = {}
    version = {v.id: v.plan_version for v in traffic.vehicles}
    entered = followed = 0
    for _ in range(round(30 * sim.tick_hz)):
        scheduler.serve(traffic)
        for v in traffic.vehicles:
            if v.plan_version != version[v.id]:  # a new plan: its first lane is the next one
                version[v.id] = v.plan_version
                expected[v.id] = v.plan[0]
        before = {v.id: v.lane_id for v in traffic.vehicles}
        traffic.step()
        for v in traffic.vehicles:
            if v.lane_id != before[v.id] and v.id in expected:
                entered += 1
                followed += v.lane_id == expected[v.id]
    assert entered > 5
    assert followed == entered


@pytest.mark.parametrize(
    ("arm", "parsed"),
    [
        ("random", ("random", None)),
        ("balanced", ("balanced", "perceived")),
        ("paper_rule@ground_truth", ("paper_rule", "ground_truth")),
        ("dynamic_ground_truth", ("dynamic_ground_truth", "ground_truth")),
    ],
)
def test_parse_arm(arm: str, parsed: tuple[str, str | None]) -> None:
    assert parse_arm(arm) == parsed


@pytest.mark.parametrize("arm", ["fastest", "shortest@ground_truth", "balanced@psychic", "random@perceived"])
def test_parse_arm_rejects(arm: str) -> None:
    with pytest.raises(ValueError, match=arm.partition("@")[0]):
        parse_arm(arm)
    with pytest.raises(ValueError):
        FlowExperimentSettings(policies=[arm])


def _model(scene: Scene, recall: list[float], **kw: float) -> OracleErrorModel:
    errors = AgentErrors(
        recall_by_distance=recall,
        present_by_distance=[1] * len(recall),
        false_positives_per_list=kw.pop("fp", 0.0),
        object_lists=1,
    )
    defaults = {"position_std_m": 0.0, "velocity_std_mps": 0.0, "latency_s": 0.0, "matched": 1}
    return OracleErrorModel(distance_bin_m=1.0, agents=dict.fromkeys(scene.agents, errors), **defaults | kw)


def test_oracle_agents_follow_their_model(setup) -> None:  # type: ignore[no-untyped-def]
    scene, sim, _coord, _exp = setup
    traffic = TrafficSim(scene, _net(scene), traffic_settings(sim, 20), 5, sim.tick_hz)
    pos, vel = vehicle_state(traffic)
    # Recall 1 out to 100 m, no noise: every agent reports every vehicle, where it was 0.5 s ago.
    sees_all = OracleAgents(scene, _net(scene), _model(scene, [1.0] * 100, latency_s=0.5), 0)
    for obj in sees_all(pos, vel):
        np.testing.assert_allclose(obj.position_m, pos - 0.5 * vel)
        np.testing.assert_allclose(obj.velocity_mps, vel)
    # Recall 0: nothing but the false positives, at rest on the agent's lanes (2 per list on average).
    blind = OracleAgents(scene, _net(scene), _model(scene, [0.0], fp=2.0), 0)
    lists = [blind(pos, vel) for _ in range(200)]
    per_list = np.mean([len(o) for batch in lists for o in batch])
    assert per_list == pytest.approx(2.0, abs=0.2)
    assert all(not o.velocity_mps.any() for batch in lists for o in batch)


def test_model_recall_by_distance_known_answer(setup) -> None:  # type: ignore[no-untyped-def]
    scene = setup[0]
    model = _model(scene, [0.9, 0.5])
    agent = next(iter(scene.agents))
    assert model.recall(agent, np.array([0.0, 0.99, 1.0, 1.99, 2.0, 50.0])).tolist() == [
        0.9,
        0.9,
        0.5,
        0.5,
        0,
        0,
    ]


def test_match_is_one_to_one_within_gate_and_level() -> None:
    objects = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.05, 0.2]])
    truth = np.array([[0.05, 0.0, 0.0], [0.9, 0.0, 0.0], [0.0, 0.0, 0.2]])
    rows, cols = match(objects, truth, gate_m=0.3, level_m=0.05)
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(0, 0), (1, 1), (3, 2)]


def test_error_observer_fit_known_answer(setup) -> None:  # type: ignore[no-untyped-def]
    """Two lists of one agent: errors +-0.03 m / +-0.04 m/s, one vehicle missed, one false positive."""
    scene = setup[0]
    agent = next(iter(scene.agents))
    observer = ErrorObserver(scene, gate_m=0.3, level_m=0.05, bin_m=100.0, max_m=100.0)
    truth = np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0], [3.0, 1.0, 0.0]])
    truth_v = np.array([[0.2, 0.0], [0.2, 0.0], [0.2, 0.0]])
    seen = AgentObjects(
        agent,
        truth[:2] + np.array([[0.03, 0.03, 0.0], [-0.03, -0.03, 0.0]]),
        np.array([[0.24, 0.04, 0.0], [0.16, -0.04, 0.0]]),
        np.ones(2),
    )
    observer.objects(seen, truth, truth_v)
    ghost = AgentObjects(agent, np.array([[9.0, 9.0, 0.0]]), np.zeros((1, 3)), np.ones(1))
    other = ErrorObserver(scene, gate_m=0.3, level_m=0.05, bin_m=100.0, max_m=100.0)
    other.objects(ghost, truth, truth_v)
    other.age(0.1)
    observer.age(0.3)
    observer.merge(other)
    model = observer.fit()
    assert model.position_std_m == pytest.approx(0.03)
    assert model.velocity_std_mps == pytest.approx(0.04)
    assert model.agents[agent].recall_by_distance == [pytest.approx(2 / 6, abs=1e-4)]
    assert model.agents[agent].false_positives_per_list == 0.5
    assert model.latency_s == pytest.approx(0.2)
    assert model.matched == 2


def _result(policy: str, vehicles: int, seed: int, flow: int, trip_s: float) -> RunResult:
    return RunResult(
        policy, vehicles, seed, 10.0, {1: flow, 2: 0}, [trip_s], 0.3, 0, 1, np.zeros((1, 1)), np.zeros((1, 1))
    )


def test_aggregate_and_acceptance() -> None:
    runs = [
        _result("random", 10, 1, 100, 50.0),
        _result("random", 10, 2, 120, 50.0),
        _result("balanced", 10, 1, 130, 20.0),
        _result("balanced", 10, 2, 134, 20.0),
        _result("balanced", 20, 1, 200, 30.0),
        _result("balanced", 20, 2, 200, 32.0),
        _result("shortest", 20, 1, 190, 35.0),
        _result("shortest", 20, 2, 190, 37.0),
    ]
    agg = report.aggregate(runs)
    assert agg["10"]["random"]["total_flow"]["mean"] == pytest.approx(110.0)
    assert agg["10"]["balanced"]["flow_per_junction"] == {"1": 132.0, "2": 0.0}
    checks = report.acceptance(agg)
    assert checks["flow_gain_vs_random_10_vehicles"] == pytest.approx(132 / 110 - 1)
    assert checks["travel_time_20_vehicles_balanced_minus_shortest_s"] == pytest.approx(-5.0)
    text = report.markdown(agg, [1, 2], None)
    assert "| balanced | 132 | 0 | 132 |" in text  # the per-junction table


def _net(scene: Scene):  # type: ignore[no-untyped-def]
    from shared.scene.road_network import RoadNetwork

    return RoadNetwork(scene)


def test_readme_section_reports_every_row_and_the_checks() -> None:
    ci = {"mean": 10.0, "ci95": 1.0}
    row = {m: ci for m in report.METRICS} | {"flow_per_junction": {"1": 4.0, "2": 6.0}}
    agg = {
        "10": {"random": row, "balanced": row | {"total_flow": {"mean": 12.0, "ci95": 0.5}}},
        "20": {"balanced": row},
    }
    results = {
        "aggregate": agg,
        "acceptance": report.acceptance(agg),
        "settings": {"seeds": [1, 2], "duration_s": 30.0, "workers": 2, "policies": ["random", "balanced"]},
        "wall_s": 5.0,
        "commit": "abc",
    }
    text = report.readme_section(results, [1, 2])
    balanced_10 = next(line for line in text.splitlines() if line.startswith("| 10 | **`balanced`** |"))
    assert balanced_10.endswith("| 12 ± 0 |") and "| 20 | **`balanced`** |" in text  # flow: last column
    assert "| random (before) | 4 | 6 | 10 |" in text
    assert "10 vehicles: `balanced` flow against random turns +20.0 %" in text
    assert text.index("| 10 | `random`") < text.index("| 10 | **`balanced`**")  # configured order


def _trips_run(policy: str, seed: int, trips: list[tuple[str, int, float, float | None]]) -> RunResult:
    run = _result(policy, 20, seed, 100, 0.0)
    run.trip_times_s = [t for _, _, t, _ in trips]
    run.trips = trips
    run.duration_s = 360.0
    return run


def test_paired_differences_match_trips_and_pair_by_seed() -> None:
    """Known answer: per seed, balanced minus shortest over the trips both completed."""
    runs = [
        _trips_run("shortest", 1, [("v0", 1, 30.0, 10.0), ("v1", 1, 40.0, 10.0)]),
        _trips_run("balanced", 1, [("v0", 1, 25.0, 10.0), ("v1", 1, 38.0, 10.0), ("v1", 2, 50.0, 10.0)]),
        _trips_run("shortest", 2, [("v0", 1, 30.0, 10.0)]),
        _trips_run("balanced", 2, [("v0", 1, 26.0, 10.0), ("v2", 1, 9.0, 10.0)]),
    ]
    paired = report.paired_differences(runs)["20"]["balanced"]
    # Matched trips: seed 1 (-5 - 2) / 2 = -3.5, seed 2: -4 (v2's trip has no partner).
    assert paired["matched_travel_time_s"]["mean"] == pytest.approx(-3.75)
    assert paired["matched_travel_time_s"]["n"] == 2
    # Trips per hour over 360 s: seed 1 +1 trip = +10 / h, seed 2 +1 trip = +10 / h.
    assert paired["trips_per_hour"]["mean"] == pytest.approx(10.0)
    assert paired["trips_per_hour"]["ci95"] == pytest.approx(0.0)
    assert "shortest" not in report.paired_differences(runs)["20"]  # no row for the baseline itself


def test_the_grid_hands_its_workers_only_the_settings_that_were_set(monkeypatch: pytest.MonkeyPatch) -> None:
    # A dumped default comes back explicit in the worker and no longer scales with the scene: at the
    # sand table the same numbers, on a real-size scene the table's.
    from shared.traffic.config import load_coordinator_settings
    from studies.experiments.config import load_flow_settings

    jobs: list[tuple[str, ...]] = []
    monkeypatch.setattr(report, "run_jobs", lambda _fn, given, _workers, *_rest: jobs.extend(given) or [])
    exp = load_flow_settings()
    report.run_grid(exp, load_sim_settings(exp.sim_config), load_coordinator_settings(exp.coordinator_config))
    _policy, _vehicles, _seed, _exp_json, sim_json, coord_json = jobs[0]
    coordinator = CoordinatorSettings.model_validate_json(coord_json)
    assert "dedup_gate_m" not in coordinator.maps.model_fields_set  # the base file leaves it to the scene
    assert '"horizon_m"' not in sim_json
