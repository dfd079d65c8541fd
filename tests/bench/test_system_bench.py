"""The system bench's analysis on a synthetic tap: rates, FULL share, latencies in sim time, plans."""

from __future__ import annotations

from rmmdet.v1.perception_pb2 import PerceptionStatus
from rmmdet.v1.traffic_pb2 import AgentState

from shared.timebase import NS_PER_S as NS
from tests.bench.system_bench import Tap, analyse, plan_latency

MS = 1_000_000
FULL = PerceptionStatus.PERCEPTION_STATUS_FULL
DEGRADED = PerceptionStatus.PERCEPTION_STATUS_DEGRADED
LIVE = AgentState.AGENT_STATE_LIVE


def tap_at_half_speed() -> Tap:
    """10 wall seconds of a sim at real-time factor 0.5: sim ns = wall ns / 2 (both from 0)."""
    tap = Tap()
    tap.clock = [(w * 100 * MS, w * 50 * MS, 0.5) for w in range(101)]
    for k in range(50):  # objects at 10 Hz of sim time (5 s of sim), 40 ms of sim after their stamp
        stamp = k * 100 * MS
        tap.objects["agent1"].append((2 * (stamp + 40 * MS), stamp, k, DEGRADED if k < 5 else FULL))
    tap.maps = [(2 * (k * 500 * MS + 60 * MS), k * 500 * MS, {"agent1": LIVE}) for k in range(10)]
    tap.acks = [
        (
            2 * (k * NS + 200 * MS),
            k * NS,
        )
        for k in range(1, 5)
    ]
    return tap


def test_analysis_maps_arrivals_to_sim_time() -> None:
    out = analyse(tap_at_half_speed(), 0, 10 * NS)
    assert abs(out["sim"]["real_time_factor"] - 0.5) < 1e-9
    agent = out["agents"]["agent1"]
    assert agent["messages"] == 50 and abs(agent["rate_hz_sim"] - 10.0) < 1e-9
    assert agent["fraction_full"] == 0.9
    lat = agent["sensor_to_objects"]
    assert abs(lat["sim_p50_ms"] - 40.0) < 1e-6 and abs(lat["sim_p95_ms"] - 40.0) < 1e-6
    coord = out["coordinator"]
    assert coord["fraction_all_live"] == 1.0 and abs(coord["objects_to_map"]["sim_p95_ms"] - 60.0) < 1e-6
    # Plans applied by vehicles (acks keep the plan's stamp): 200 ms of sim time after the objects.
    assert (
        coord["objects_to_plan"]["count"] == 4 and abs(coord["objects_to_plan"]["sim_p95_ms"] - 200.0) < 1e-6
    )
    assert coord["objects_to_pushed_plan"] == {"count": 0}
    assert plan_latency(coord) is coord["objects_to_plan"]


def test_runs_without_acks_fall_back_to_pushed_plans() -> None:
    pushed = {"count": 2, "sim_p95_ms": 170.0}
    assert plan_latency({"objects_to_pushed_plan": pushed}) is pushed
    assert plan_latency({"objects_to_plan": {"count": 0}, "objects_to_pushed_plan": pushed}) is pushed


def test_drift_known_answer() -> None:
    from tests.bench.system_bench import drift

    # 10 MB over half an hour: a slope of 20 MB/h; threads 5-7, fds constant.
    samples = [
        {"t_s": 1800.0 * i / 10, "rss_mb": 100.0 + i, "threads": 5 + (i % 3), "fds": 40} for i in range(11)
    ]
    assert drift(samples) == {"rss_slope_mb_per_h": 20.0, "threads_spread": 2, "fds_spread": 0}
    assert drift(samples[:1]) == {"rss_slope_mb_per_h": 0.0, "threads_spread": 0, "fds_spread": 0}


def test_rss_series_is_thinned_to_minutes_and_mb() -> None:
    from tests.bench.system_bench import rss_series

    samples = [{"t_s": 1000.0 + 30.0 * i, "rss_mb": 100.0 + 0.25 * i} for i in range(240)]
    series = rss_series(samples, points=60)
    assert len(series) == 60
    assert series[0] == [0.0, 100.0] and series[1] == [2.0, 101.0]
    assert rss_series([]) == []
    assert len(rss_series(samples[:119], points=60)) <= 60  # not a multiple: still at most `points`


def test_the_view_client_watches_what_the_layout_shows() -> None:
    import json

    from tests.bench.view_client import LAYOUT, layout_topics

    topics = layout_topics(json.loads(LAYOUT.read_text()))
    assert {"/table", "/plans", "/health", "/agents/agent1/tracks"} <= topics
    assert {"/agents/agent2/camera/cam_2", "/agents/agent2/camera/cam_2/detections"} <= topics
    assert "/ground_truth" not in topics  # a hidden layer is not watched
