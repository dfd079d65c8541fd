"""The dashboard's state, known answers: coverage and rates per agent, junction counters, plans and
acknowledgements, the heat-map grid, alarms."""

from __future__ import annotations

import json

import pytest
from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import AckStatus, RouteAck, RoutePlan
from rmmdet.v1.sim_pb2 import GroundTruth
from rmmdet.v1.traffic_pb2 import AgentState, TrafficMap

from shared.viewer.dashboard import RATE_WINDOW_S, DashboardState


def test_the_snapshot_gathers_every_panel() -> None:
    d = DashboardState(["agent1", "agent2"])
    objects = TrackedObjects(agent_id="agent1")
    objects.stage_latencies.add(stage="detect", duration_s=0.02)
    objects.stage_latencies.add(stage="track", duration_s=0.005)
    for k in range(50):  # 10 Hz for 5 s
        d.on_objects("agent1", objects, now_s=k * 0.1)
    d.on_objects("agent9", objects, now_s=0.0)  # not an agent of the scene: ignored
    tm = TrafficMap()
    tm.coverage.add(agent_id="agent1", state=AgentState.AGENT_STATE_LIVE, data_age_s=0.05, object_count=4)
    tm.coverage.add(agent_id="agent2", state=AgentState.AGENT_STATE_STALE, data_age_s=1.2, object_count=0)
    tm.grid.column_count, tm.grid.row_count, tm.grid.cell_size_m = 2, 1, 0.5
    tm.grid.vehicle_count.extend([1.0, 0.5])
    tm.grid.mean_speed_mps.extend([0.2, 0.0])
    d.on_traffic_map(tm)
    gt = GroundTruth()
    gt.junction_flows.add(junction_id="j2", number=2, arrivals=7)
    gt.junction_flows.add(junction_id="j1", number=1, arrivals=3)
    d.on_ground_truth(gt)
    d.on_plan(RoutePlan(vehicle_id="v1"))
    d.on_ack(RouteAck(status=AckStatus.ACK_STATUS_ACCEPTED))
    d.on_ack(RouteAck(status=AckStatus.ACK_STATUS_DUPLICATE))
    d.on_health(False, "loop NOT OK: agent2 STALE", ["agent2 STALE"])
    snap = d.snapshot(now_s=4.95)
    json.dumps(snap)  # JSON-able as it is
    a1, a2 = snap["agents"]
    assert a1 == {
        "agent": "agent1",
        "state": "LIVE",
        "age_s": 0.05,
        "objects": 4,
        "rate_hz": 10.0,
        "latency_ms": 25.0,
    }
    assert a2["state"] == "STALE" and a2["rate_hz"] == 0.0 and a2["latency_ms"] is None
    assert [j["number"] for j in snap["junctions"]] == [1, 2] and snap["junctions"][1]["vehicles"] == 7
    assert snap["plans"] == {"pushed": 1, "served": 0, "acknowledged": {"ACCEPTED": 1, "DUPLICATE": 1}}
    assert snap["grid"]["vehicles"] == [1.0, 0.5] and snap["grid"]["columns"] == 2
    assert snap["health"]["alarms"] == ["agent2 STALE"]
    assert d.rate_hz("agent1", 4.9 + RATE_WINDOW_S + 0.01) == pytest.approx(0.0)  # gone quiet


def test_served_plans_are_counted_apart_from_pushed_ones() -> None:
    board = DashboardState(["agent1"])
    board.on_plan(RoutePlan(vehicle_id="v1", version=1))
    board.on_plan(RoutePlan(vehicle_id="v2", version=1), served=True)
    board.on_plan(RoutePlan(vehicle_id="v3", version=1), served=True)
    assert board.snapshot(0.0)["plans"] == {"pushed": 1, "served": 2, "acknowledged": {}}


def test_arrivals_are_bounded_without_snapshots() -> None:
    """With no dashboard (no snapshots taken) the rate window must not grow with every list."""
    board = DashboardState(["agent1"])
    msg = TrackedObjects(agent_id="agent1")
    for i in range(1000):
        board.on_objects("agent1", msg, now_s=i * 0.1)
    assert len(board._arrivals["agent1"]) <= RATE_WINDOW_S / 0.1 + 1
