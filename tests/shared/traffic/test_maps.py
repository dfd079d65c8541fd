"""merge_agents, TrafficMapBuilder (counts, smoothing, speeds, observation), area ranks and grid cells.

The map scene (scenes.map_scene): lane `lo` at y = 0.5 heading +x (area south, agent_s), lane `hi` at
y = 1.5 heading -x (area north, agent_n), both 3 m long; table 5 m x 3 m from (-1, -1); cells 0.5 m."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.scene.road_network import RoadNetwork
from shared.traffic.config import MapConfig
from shared.traffic.lanes import OFF_LANE, lane_agents
from shared.traffic.maps import AgentObjects, TrafficMapBuilder, Vehicles, area_ranks, merge_agents
from shared.traffic.planner import LaneConditions
from tests.shared.traffic.scenes import map_scene, planner_scene

GATE_M = 0.3
LEVEL_M = 0.1
TAU_S = 5.0
GAIN_1S = 1.0 - math.exp(-1.0 / TAU_S)  # 0.18126924692...
HI, LO = 0, 1  # lane_ids are sorted
SOUTH, NORTH = 0, 1  # area_ids follow the file


def objects(agent: str, pos: list[tuple[float, float, float]], var: list[float], vel=None) -> AgentObjects:
    p = np.array(pos, float).reshape(-1, 3)
    v = np.zeros_like(p) if vel is None else np.array(vel, float).reshape(-1, 3)
    return AgentObjects(agent, p, v, np.array(var, float))


def vehicles(rows: list[tuple[tuple[float, float, float], tuple[float, float]]]) -> Vehicles:
    """(position, planar velocity) rows as merged vehicles."""
    pos = np.array([p for p, _ in rows], float).reshape(-1, 3)
    vel = np.array([(vx, vy, 0.0) for _, (vx, vy) in rows], float).reshape(-1, 3)
    return Vehicles(pos, vel, np.full(len(rows), 0.01), [("a",)] * len(rows))


# --- merge_agents ---------------------------------------------------------------------------------


def test_two_agents_seeing_one_car_fuse_by_inverse_variance() -> None:
    a = objects("a", [(1.0, 0.0, 0.0)], [0.01], vel=[(0.2, 0.0, 0.0)])
    b = objects("b", [(1.1, 0.0, 0.0)], [0.03], vel=[(0.4, 0.0, 0.0)])
    merged = merge_agents([a, b], GATE_M, LEVEL_M)
    # weights 100 and 33.3: a counts 3/4, b 1/4
    assert len(merged) == 1
    np.testing.assert_allclose(merged.position_m, [[1.025, 0.0, 0.0]])
    np.testing.assert_allclose(merged.velocity_mps, [[0.25, 0.0, 0.0]])
    np.testing.assert_allclose(merged.position_var_m2, [0.0075])
    assert merged.agents == [("a", "b")]


def test_third_agent_folds_into_the_fused_vehicle() -> None:
    a = objects("a", [(0.0, 0.0, 0.0)], [0.02])
    b = objects("b", [(0.1, 0.0, 0.0)], [0.02])
    c = objects("c", [(0.2, 0.0, 0.0)], [0.01])
    merged = merge_agents([a, b, c], GATE_M, LEVEL_M)
    # a+b: x = 0.05, var 0.01; then with c (var 0.01): x = 0.125, var 0.005
    np.testing.assert_allclose(merged.position_m, [[0.125, 0.0, 0.0]])
    np.testing.assert_allclose(merged.position_var_m2, [0.005])
    assert merged.agents == [("a", "b", "c")]


@pytest.mark.parametrize(
    "other",
    [
        (1.4, 0.0, 0.0),  # 0.4 m apart in xy: beyond the gate
        (1.0, 0.0, 0.4),  # same xy, 0.4 m higher: deck above the road
        (1.0, 0.25, 0.15),  # inside the gate in xy, but a level apart
    ],
)
def test_objects_beyond_the_gate_or_level_stay_apart(other: tuple[float, float, float]) -> None:
    merged = merge_agents(
        [objects("a", [(1.0, 0.0, 0.0)], [0.01]), objects("b", [other], [0.01])], GATE_M, LEVEL_M
    )
    assert len(merged) == 2
    np.testing.assert_allclose(merged.position_m, [(1.0, 0.0, 0.0), other])
    assert merged.agents == [("a",), ("b",)]


def test_one_agents_close_objects_are_never_merged() -> None:
    a = objects("a", [(1.0, 0.0, 0.0), (1.05, 0.0, 0.0)], [0.01, 0.01])
    assert len(merge_agents([a], GATE_M, LEVEL_M)) == 2
    b = objects("b", [(1.0, 0.0, 0.0)], [0.01])
    merged = merge_agents([a, b], GATE_M, LEVEL_M)
    assert len(merged) == 2
    assert merged.agents == [("a", "b"), ("a",)]
    np.testing.assert_allclose(merged.position_m, [(1.0, 0.0, 0.0), (1.05, 0.0, 0.0)])


def test_assignment_is_global_not_greedy() -> None:
    # Greedy nearest pairing would take b@0.2 for a@0.25 (0.05 m) and leave b@0.45 alone (0.45 m from a@0);
    # the optimal assignment pairs a@0 with b@0.2 and a@0.25 with b@0.45 (0.2 m each).
    a = objects("a", [(0.0, 0.0, 0.0), (0.25, 0.0, 0.0)], [0.01, 0.01])
    b = objects("b", [(0.2, 0.0, 0.0), (0.45, 0.0, 0.0)], [0.01, 0.01])
    merged = merge_agents([a, b], GATE_M, LEVEL_M)
    assert len(merged) == 2
    np.testing.assert_allclose(merged.position_m[:, 0], [0.1, 0.35])
    assert merged.agents == [("a", "b"), ("a", "b")]


def test_empty_object_lists() -> None:
    assert len(merge_agents([], GATE_M, LEVEL_M)) == 0
    b = objects("b", [(1.0, 0.0, 0.0)], [0.01])
    merged = merge_agents([AgentObjects.empty("a"), b, AgentObjects.empty("c")], GATE_M, LEVEL_M)
    assert merged.agents == [("b",)]
    np.testing.assert_allclose(merged.position_m, [(1.0, 0.0, 0.0)])


def test_merge_does_not_modify_its_inputs() -> None:
    a = objects("a", [(1.0, 0.0, 0.0)], [0.01])
    b = objects("b", [(1.1, 0.0, 0.0)], [0.03])
    merge_agents([a, b], GATE_M, LEVEL_M)
    np.testing.assert_array_equal(a.position_m, [(1.0, 0.0, 0.0)])
    np.testing.assert_array_equal(a.position_var_m2, [0.01])


# --- area ranks and lane agents -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("counts", "ranks"),
    [
        ([3.0, 1.0, 1.0, 0.0], [3, 1, 2, 0]),
        ([0.0, 0.0, 0.0], [0, 1, 2]),
        ([2.0, 5.0], [0, 1]),
        ([], []),
    ],
)
def test_area_ranks_emptiest_first_ties_in_file_order(counts: list[float], ranks: list[int]) -> None:
    assert area_ranks(np.array(counts, float)).tolist() == ranks


def test_lane_agents_by_covered_share() -> None:
    scene = planner_scene()
    network = RoadNetwork(scene)
    # lane ac runs from y = 0 to 1.5; agent_s covers y <= 0.5: about a third of its samples
    assert lane_agents(scene, network)["ac"] == ["agent_s"]
    assert lane_agents(scene, network, min_fraction=0.3)["ac"] == ["agent_s"]
    assert lane_agents(scene, network, min_fraction=0.4)["ac"] == []
    assert lane_agents(scene, network)["cb"] == ["agent_s"]  # ends at y = 0
    assert lane_agents(scene, network)["ab"] == ["agent_s"]


# --- TrafficMapBuilder ----------------------------------------------------------------------------


@pytest.fixture
def builder() -> TrafficMapBuilder:
    scene = map_scene()
    cfg = MapConfig(smoothing_time_constant_s=TAU_S, speed_valid_s=3.0, grid_cell_m=0.5)
    return TrafficMapBuilder(scene, RoadNetwork(scene), cfg)


FIRST = vehicles(
    [
        ((1.0, 0.5, 0.0), (0.2, 0.0)),  # lo
        ((2.0, 0.5, 0.0), (0.4, 0.0)),  # lo
        ((1.0, 1.5, 0.0), (-0.3, 0.0)),  # hi
        ((3.0, 1.0, 0.0), (0.0, 0.0)),  # between the lanes (0.5 m from each): off-lane, area south
    ]
)


def test_builder_layout(builder: TrafficMapBuilder) -> None:
    assert builder.lane_ids == ["hi", "lo"]
    assert builder.area_ids == ["south", "north"]
    assert builder.lane_agents == {"lo": ["agent_s"], "hi": ["agent_n"]}
    assert builder.grid_origin_m == (-1.0, -1.0)
    assert builder.grid_shape == (6, 10)  # rows (y: 3 m), columns (x: 5 m)


def test_first_update_counts_lanes_areas_and_cells(builder: TrafficMapBuilder) -> None:
    snap = builder.update(FIRST, 0.0, None)
    assert snap.vehicle_lane.tolist() == [LO, LO, HI, OFF_LANE]
    np.testing.assert_array_equal(snap.lane_count, [1.0, 2.0])
    np.testing.assert_array_equal(snap.lane_count_smoothed, [1.0, 2.0])  # first update: gain 1
    np.testing.assert_allclose(snap.lane_speed_mps, [0.3, 0.3])  # hi: 0.3; lo: (0.2 + 0.4) / 2
    assert snap.lane_speed_valid.tolist() == [True, True]
    assert snap.lane_observed.tolist() == [True, True]
    np.testing.assert_allclose(snap.lane_length_m, [3.0, 3.0])
    np.testing.assert_array_equal(snap.area_count, [3.0, 1.0])
    np.testing.assert_allclose(snap.area_speed_mps, [0.2, 0.3])  # south: (0.2 + 0.4 + 0) / 3
    assert snap.area_rank.tolist() == [1, 0]  # north is emptier
    # cells: col = floor((x + 1) / 0.5), row = floor((y + 1) / 0.5)
    expected = np.zeros((6, 10))
    expected[3, 4] = expected[3, 6] = expected[5, 4] = expected[4, 8] = 1.0
    np.testing.assert_array_equal(snap.grid_count, expected)
    np.testing.assert_array_equal(snap.grid_samples, expected.astype(np.int64))
    assert snap.grid_speed_mps[3, 4] == pytest.approx(0.2)
    assert snap.grid_speed_mps[5, 4] == pytest.approx(0.3)
    assert snap.grid_speed_mps[0, 0] == 0.0
    assert snap.lane_index("lo") == LO


def test_exponential_smoothing_gain(builder: TrafficMapBuilder) -> None:
    builder.update(FIRST, 0.0, None)
    one_on_lo = vehicles([((1.5, 0.5, 0.0), (0.5, 0.0))])
    snap = builder.update(one_on_lo, 1.0, None)
    np.testing.assert_array_equal(snap.lane_count, [0.0, 1.0])
    np.testing.assert_allclose(snap.lane_count_smoothed, [1.0 - GAIN_1S, 2.0 - GAIN_1S])
    np.testing.assert_allclose(snap.lane_count_smoothed, [0.8187307531, 1.8187307531])
    # lo speed: 0.3 + gain (0.5 - 0.3); hi had no sample: keeps 0.3, not 0
    np.testing.assert_allclose(snap.lane_speed_mps, [0.3, 0.3 + GAIN_1S * 0.2])
    assert snap.lane_speed_valid.tolist() == [True, True]
    # areas and cells smooth the same way
    np.testing.assert_allclose(snap.area_count_smoothed, [3.0 + GAIN_1S * (1.0 - 3.0), 1.0 - GAIN_1S])
    # a second update at the same instant changes nothing (dt = 0: gain 0); so does one back in time
    again = builder.update(vehicles([]), 1.0, None)
    np.testing.assert_allclose(again.lane_count_smoothed, snap.lane_count_smoothed)
    back = builder.update(vehicles([]), 0.5, None)
    np.testing.assert_allclose(back.lane_count_smoothed, snap.lane_count_smoothed)


def test_smoothing_halves_in_tau_ln2_whatever_the_step(builder: TrafficMapBuilder) -> None:
    builder.update(vehicles([((1.0, 0.5, 0.0), (0.2, 0.0))] * 2), 0.0, None)
    half_life = TAU_S * math.log(2.0)
    snap = builder.update(vehicles([]), half_life, None)
    assert snap.lane_count_smoothed[LO] == pytest.approx(1.0)
    # ten small steps over another half-life give the same result as one step
    for k in range(1, 11):
        snap = builder.update(vehicles([]), half_life * (1 + k / 10), None)
    assert snap.lane_count_smoothed[LO] == pytest.approx(0.5)


def test_speed_turns_invalid_after_speed_valid_s(builder: TrafficMapBuilder) -> None:
    builder.update(FIRST, 0.0, None)  # both lanes sampled at t = 0
    builder.update(vehicles([((1.5, 0.5, 0.0), (0.5, 0.0))]), 1.0, None)  # lo sampled at t = 1
    snap = builder.update(vehicles([]), 4.0, None)  # hi 4 s old, lo 3 s old (valid for 3 s)
    assert snap.lane_speed_valid.tolist() == [False, True]
    assert snap.area_speed_valid.tolist() == [True, False]  # south sampled at t = 1, north at t = 0
    snap = builder.update(vehicles([]), 4.5, None)
    assert snap.lane_speed_valid.tolist() == [False, False]
    # the stale value is kept (not zeroed); consumers look at the flag
    assert snap.lane_speed_mps[LO] == pytest.approx(0.3 + GAIN_1S * 0.2)


def test_lane_never_sampled_has_no_speed(builder: TrafficMapBuilder) -> None:
    snap = builder.update(vehicles([((1.0, 0.5, 0.0), (0.2, 0.0))]), 0.0, None)
    assert snap.lane_speed_valid.tolist() == [False, True]
    assert snap.lane_speed_mps[HI] == 0.0
    # a stopped vehicle is a sample of speed 0
    snap = builder.update(vehicles([((1.0, 1.5, 0.0), (0.0, 0.0))]), 1.0, None)
    assert snap.lane_speed_valid.tolist() == [True, True]
    assert snap.lane_speed_mps[HI] == 0.0


def test_unobserved_lane_keeps_its_smoothed_count(builder: TrafficMapBuilder) -> None:
    builder.update(FIRST, 0.0, None)
    snap = builder.update(vehicles([]), 1.0, {"agent_s"})  # agent_n is down: hi unobserved
    assert snap.lane_observed.tolist() == [False, True]
    assert snap.lane_count_smoothed[HI] == pytest.approx(1.0)
    assert snap.lane_count_smoothed[LO] == pytest.approx(2.0 * (1.0 - GAIN_1S))
    cond = LaneConditions.from_snapshot(snap)
    assert cond.count == {"lo": 0.0, "hi": 0.0}  # unobserved hi: the prior (lo's density now: none)
    assert cond.speed_mps == pytest.approx({"hi": 0.3, "lo": 0.3})
    assert cond.area_rank == {"south": 0, "north": 1}  # equal counts (0): file order
    # nobody live: nothing observed, nothing decays
    snap = builder.update(vehicles([]), 2.0, [])
    assert snap.lane_observed.tolist() == [False, False]
    assert snap.lane_count_smoothed[LO] == pytest.approx(2.0 * (1.0 - GAIN_1S))
    # agent_n back: hi decays by one step of gain from where it was held
    snap = builder.update(vehicles([]), 3.0, ["agent_s", "agent_n"])
    assert snap.lane_observed.tolist() == [True, True]
    assert snap.lane_count_smoothed[HI] == pytest.approx(1.0 - GAIN_1S)


def test_unobserved_lanes_and_areas_take_the_observed_density(builder: TrafficMapBuilder) -> None:
    snap = builder.update(FIRST, 0.0, {"agent_s"})  # agent_n down: hi and the north area unobserved
    assert snap.prior_density_per_m == pytest.approx(2.0 / 3.0)  # lo: 2 cars on 3 m
    np.testing.assert_allclose(snap.lane_count_expected, [2.0, 2.0])  # hi: 2/3 per m x 3 m; lo counted
    assert LaneConditions.from_snapshot(snap).count == pytest.approx({"hi": 2.0, "lo": 2.0})
    assert snap.area_observed.tolist() == [True, False]
    # south counts 3 (one off-lane), north is ranked by its prior, 2 (not 0): north the emptier
    assert snap.area_rank.tolist() == [1, 0]
    # nobody live: the last observed density is kept (history), every lane at the prior
    snap = builder.update(vehicles([]), 1.0, [])
    assert snap.prior_density_per_m == pytest.approx(2.0 / 3.0)
    np.testing.assert_allclose(snap.lane_count_expected, [2.0, 2.0])
    # ground truth observes everything: the counts themselves
    snap = builder.update(FIRST, 2.0, None)
    np.testing.assert_array_equal(snap.lane_count_expected, snap.lane_count)
    assert snap.area_observed.tolist() == [True, True]


def test_live_agents_none_observes_everything(builder: TrafficMapBuilder) -> None:
    assert builder.lane_observed(None).tolist() == [True, True]
    assert builder.lane_observed({"agent_n"}).tolist() == [True, False]
    assert builder.lane_observed({"someone-else"}).tolist() == [False, False]


@pytest.mark.parametrize(
    ("x", "y", "cell"),
    [
        (-1.0, -1.0, 0),  # the table's corner
        (-0.5, -1.0, 1),  # a cell edge belongs to the next cell
        (-0.5001, -1.0, 0),
        (-1.0, -0.5, 10),  # one row up: + columns
        (1.0, 0.5, 3 * 10 + 4),
        (3.999, 1.999, 5 * 10 + 9),  # last cell
        (4.0, 0.0, -1),  # the far x edge is outside
        (0.0, 2.0, -1),  # the far y edge is outside
        (-1.0001, 0.0, -1),
        (0.0, -1.0001, -1),
        (40.0, 40.0, -1),
    ],
)
def test_grid_cells(builder: TrafficMapBuilder, x: float, y: float, cell: int) -> None:
    assert builder.cells(np.array([[x, y, 0.0]])).tolist() == [cell]


def test_vehicle_outside_the_table_counts_nowhere(builder: TrafficMapBuilder) -> None:
    snap = builder.update(vehicles([((10.0, 10.0, 0.0), (0.3, 0.0))]), 0.0, None)
    assert snap.vehicle_lane.tolist() == [OFF_LANE]
    assert snap.lane_count.sum() == 0
    assert snap.area_count.sum() == 0
    assert snap.grid_count.sum() == 0


def test_empty_update(builder: TrafficMapBuilder) -> None:
    snap = builder.update(vehicles([]), 0.0, None)
    assert snap.vehicle_lane.shape == (0,)
    np.testing.assert_array_equal(snap.lane_count, [0.0, 0.0])
    assert snap.area_rank.tolist() == [0, 1]
    assert snap.grid_count.shape == (6, 10)
