"""Coordinator core (no bus): coverage-filtered maps, served plans and rejections, pushed replans and
their delivery, acknowledgements, and the loop's cadence (`tick`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from rmmdet.v1.common_pb2 import ErrorCode
from rmmdet.v1.planning_pb2 import RouteAck, RouteRequest
from rmmdet.v1.traffic_pb2 import AgentState as PbState

from shared.bus.health import DEGRADED, NOMINAL
from shared.bus.streams import limits
from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.traffic.config import CoordinatorSettings
from shared.traffic.core import CoordinatorCore, RequestRejected, Tick
from shared.traffic.coverage import AgentState
from shared.traffic.messages import agent_objects
from shared.traffic.planner import Route
from shared.traffic.plans import Ack, version_of
from tests.integration.fake_mec import AgentCars
from tests.shared.traffic.scenes import planner_scene

WALL0_NS = 1_700_000_000 * NS_PER_S
CARS = 3


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


@pytest.fixture(scope="module")
def cars(scene: Scene) -> dict[str, AgentCars]:
    net = RoadNetwork(scene)
    return {a: AgentCars(scene, net, a, CARS) for a in scene.agents}


def make_core(scene: Scene, max_vehicles: int = 16) -> CoordinatorCore:
    return CoordinatorCore(scene, CoordinatorSettings(), max_vehicles)


def feed(core: CoordinatorCore, cars: dict[str, AgentCars], now_s: float, agents=None) -> None:
    for agent in agents or core.agents:
        msg = cars[agent].message(now_s)
        core.on_objects(agent, agent_objects(agent, msg), WALL0_NS + round(now_s * NS_PER_S), now_s)


def request(vid: str = "v01", lane: str = "l0", dest: str = "j3", version: int = 0) -> RouteRequest:
    return RouteRequest(
        vehicle_id=vid, current_lane_id=lane, destination_junction_id=dest, current_plan_version=version
    )


def test_maps_hold_only_live_agents(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    feed(core, cars, 1.0)
    snap = core.update_map(1.0)
    assert snap.lane_count.sum() == len(core.agents) * CARS
    only_agent1 = [i for i, lane in enumerate(snap.lane_ids) if core.builder.lane_agents[lane] == ["agent1"]]
    assert only_agent1 and snap.lane_observed[only_agent1].all()
    # agent1's MEC dies (presence gone): its cars leave the maps at once, its lanes turn unobserved.
    core.on_presence("agent1", False)
    feed(core, cars, 1.2, agents=["agent2", "agent3"])
    snap = core.update_map(1.2)
    assert snap.lane_count.sum() == 2 * CARS
    assert not snap.lane_observed[only_agent1].any()
    states = core.states(1.2)
    assert states["agent1"] is AgentState.STALE and states["agent2"] is AgentState.LIVE
    msg, stamp_ns = core.map_message(1.2)
    coverage = {c.agent_id: c.state for c in msg.coverage}
    live, stale = PbState.AGENT_STATE_LIVE, PbState.AGENT_STATE_STALE
    assert coverage == {"agent1": stale, "agent2": live, "agent3": live}
    assert stamp_ns == WALL0_NS + round(1.2 * NS_PER_S)
    # Back, but its data is old: data age alone keeps it STALE (a hung MEC keeps its token) ...
    core.on_presence("agent1", True)
    assert core.states(2.0)["agent1"] is AgentState.STALE
    # ... and LOST after lost_after_s; its first new list makes it LIVE again.
    lost_s = 1.0 + core.settings.coverage.lost_after_s + 0.1
    assert core.states(lost_s)["agent1"] is AgentState.LOST
    feed(core, cars, lost_s, agents=["agent1"])
    assert core.states(lost_s)["agent1"] is AgentState.LIVE


def test_unknown_agent_and_reordered_lists(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    msg = cars["agent1"].message(0.0)
    assert not core.on_objects("agent9", agent_objects("agent9", msg), WALL0_NS, 0.0)
    assert not core.on_presence("agent9", True)
    assert core.on_objects("agent1", agent_objects("agent1", msg), WALL0_NS + NS_PER_S, 0.0)
    empty = agent_objects("agent1", cars["agent1"].message(0.0).__class__())
    assert core.on_objects("agent1", empty, WALL0_NS, 0.1)  # older stamp: ignored, newer list kept
    assert core.update_map(0.1).lane_count.sum() == CARS


def test_serve_plans_with_coverage_and_versions(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    feed(core, cars, 1.0, agents=["agent1", "agent3"])
    core.update_map(1.0)
    plan, stamp_ns = core.serve(request(), 1.0, WALL0_NS)
    assert plan.lane_ids[0] == "l0" and plan.plan_id
    assert core.net.lane_end_junction(plan.lane_ids[-1]) == "j3"
    assert list(plan.coverage.missing_agents) == ["agent2"]
    assert sorted(plan.coverage.live_agents) == ["agent1", "agent3"]
    assert plan.valid_until.ToNanoseconds() == WALL0_NS + round(core.settings.planner.plan_ttl_s * NS_PER_S)
    assert stamp_ns == WALL0_NS + NS_PER_S
    # Versions are issue times (µs); one above the last within a microsecond.
    assert plan.version == version_of(WALL0_NS)
    core.on_ack("v01", plan.plan_id, plan.version, Ack.REJECTED_STALE, 1.0)  # (the vehicle had newer)
    assert core.serve(request(), 1.1, WALL0_NS)[0].version == version_of(WALL0_NS) + 1
    # The version a request claims is not trusted: it never moves the vehicle's versions.
    claimed = limits().max_claimed_plan_version
    assert core.serve(request("v02", version=claimed), 1.2, WALL0_NS + 5000)[0].version == version_of(
        WALL0_NS + 5000
    )


def test_serve_uses_lists_that_arrived_after_the_last_map(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    core.update_map(0.0)
    feed(core, cars, 0.5)
    assert core.dirty
    plan, stamp_ns = core.serve(request(), 0.5, WALL0_NS)
    assert stamp_ns == WALL0_NS + round(0.5 * NS_PER_S) and not core.dirty
    assert list(plan.coverage.missing_agents) == []


@pytest.mark.parametrize(
    ("req", "reason", "code"),
    [
        (request(vid="V 1"), "vehicle_id", ErrorCode.ERROR_CODE_INVALID_REQUEST),
        (request(lane="l99"), "unknown_lane", ErrorCode.ERROR_CODE_NOT_FOUND),
        (request(dest="j99"), "unknown_junction", ErrorCode.ERROR_CODE_NOT_FOUND),
    ],
)
def test_serve_rejects_bad_requests(scene: Scene, req: RouteRequest, reason: str, code: int) -> None:
    core = make_core(scene)
    core.update_map(0.0)
    with pytest.raises(RequestRejected) as err:
        core.serve(req, 0.0, WALL0_NS)
    assert err.value.reason == reason and err.value.code == code


def test_a_full_plan_book_evicts_the_longest_idle_vehicle_and_serves_the_new_one(scene: Scene) -> None:
    core = make_core(scene, max_vehicles=2)
    core.update_map(0.0)
    core.serve(request("v01"), 0.0, WALL0_NS)
    core.serve(request("v02"), 0.1, WALL0_NS)
    core.serve(request("v01"), 0.2, WALL0_NS)  # v02 is now the longest idle
    plan, _ = core.serve(request("v03"), 0.3, WALL0_NS)  # a new vehicle is served, never locked out
    assert plan.vehicle_id == "v03" and core.vehicles_evicted == 1
    again, _ = core.serve(request("v02"), 0.4, WALL0_NS)  # the evicted one starts afresh when it asks
    assert again.version == version_of(WALL0_NS) and core.vehicles_evicted == 2


def test_ten_thousand_made_up_ids_evict_no_vehicle_that_follows_a_plan(scene: Scene) -> None:
    """Issue 52 item 10: a full book evicted the longest idle vehicle whatever it was, so 10,000
    made-up ids (asking, never acknowledging) evicted every real vehicle's plan and version counter.
    Now strangers go first; the book stays at its bound, and the real vehicles keep their plans."""
    core = make_core(scene, max_vehicles=64)
    core.update_map(0.0)
    real = {}
    for k in range(32):
        plan, _ = core.serve(request(f"real{k:02d}"), 0.0, WALL0_NS)
        core.on_ack(plan.vehicle_id, plan.plan_id, plan.version, Ack.ACCEPTED, 0.0)
        real[plan.vehicle_id] = plan
    for k in range(10_000):
        core.serve(request(f"fake{k:05d}"), 1.0 + k * 1e-4, WALL0_NS)
    assert len(core.book.vehicles()) == 64 and core.vehicles_evicted == 10_000 - 32
    assert all(core.owns_vehicle(v) for v in real)
    again, _ = core.serve(request("real00", version=real["real00"].version), 3.0, WALL0_NS)
    # Its version counter was kept (an evicted vehicle starts again at the issue time's version).
    assert again.plan_id == real["real00"].plan_id or again.version == real["real00"].version + 1


def test_vehicles_idle_past_the_limit_are_forgotten(scene: Scene) -> None:
    core = make_core(scene)
    idle_s = core.settings.delivery.vehicle_idle_s
    core.update_map(0.0)
    core.serve(request("v01"), 0.0, WALL0_NS)
    core.serve(request("v02"), idle_s + 1.0, WALL0_NS)
    assert core.vehicles_evicted == 1


def test_coverage_change_pushes_plan_until_acknowledged(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    delivery = core.settings.delivery
    core.update_map(0.0)  # nothing LIVE yet
    first, _ = core.serve(request(), 0.0, WALL0_NS)
    core.on_ack("v01", first.plan_id, first.version, Ack.ACCEPTED, 0.0)
    assert core.replan(0.5, WALL0_NS) == 0  # same coverage, same (empty) maps: nothing to push
    feed(core, cars, 1.0)
    core.update_map(1.0)  # every agent LIVE now: the plan was made without them
    assert core.replan(1.0, WALL0_NS) == 1
    due = core.due(1.0)
    assert len(due) == 1
    pushed, _, first_send = due[0]
    assert first_send and pushed.version == first.version + 1 and list(pushed.coverage.missing_agents) == []
    assert list(pushed.lane_ids[:2]) == list(first.lane_ids[:2])  # the first turn is kept
    assert core.replan(1.1, WALL0_NS) == 0  # still being delivered: not replanned again
    assert core.due(1.0 + delivery.ack_timeout_s / 2) == []
    resent = core.due(1.0 + delivery.ack_timeout_s)
    assert [(p.plan_id, first_send) for p, _, first_send in resent] == [(pushed.plan_id, False)]
    assert not core.on_ack("v01", first.plan_id, first.version, Ack.ACCEPTED, 1.0)  # not the latest
    assert core.on_ack("v01", pushed.plan_id, pushed.version, Ack.ACCEPTED, 1.0)
    assert core.due(5.0) == []
    assert core.active_plans(5.0) == 1


def test_pushed_plan_given_up_after_max_sends(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    core.update_map(0.0)
    core.serve(request(), 0.0, WALL0_NS)
    feed(core, cars, 1.0)
    core.update_map(1.0)
    assert core.replan(1.0, WALL0_NS) == 1
    delivery = core.settings.delivery
    sent_at = [t for t in np.arange(1.0, 30.0, 0.05) for _ in core.due(float(t))]
    waits = np.diff(sent_at)
    assert len(sent_at) == delivery.max_sends and core.plans_given_up == 1
    assert np.allclose(waits, [delivery.ack_wait_s(k) for k in range(1, delivery.max_sends)], atol=0.051)
    assert core.active_plans(30.0) == 0


def test_ended_plans_are_not_replanned(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    core.update_map(0.0)
    plan, _ = core.serve(request(), 0.0, WALL0_NS)
    assert core.on_ack("v01", plan.plan_id, plan.version, Ack.REJECTED_INVALID, 0.0)
    assert core.planner.planned_load() == {}  # its lanes are no longer load for others
    feed(core, cars, 1.0)
    core.update_map(1.0)
    assert core.replan(1.0, WALL0_NS) == 0


def test_tick_rebuilds_publishes_and_flags_coverage_changes(scene: Scene, cars: dict[str, AgentCars]) -> None:
    """Known answer with map_publish_hz = 2 and map_update_max_hz = 20: the first tick publishes; the
    first lists make every agent LIVE (no presence token seen yet counts as present), which publishes at
    once and restarts the 0.5 s period; lists arriving between publications rebuild the maps at most
    every 0.05 s without publishing."""
    core = make_core(scene)
    assert core.tick(0.0, WALL0_NS) == Tick(coverage=None, publish_map=True, replanned=None)  # all LOST
    feed(core, cars, 0.1)
    t = core.tick(0.1, WALL0_NS)
    assert t.publish_map and t.coverage == dict.fromkeys(core.agents, AgentState.LIVE) and not core.dirty
    feed(core, cars, 0.12)
    assert not core.tick(0.12, WALL0_NS).publish_map and core.dirty  # rebuilt 0.02 s ago: not yet
    assert not core.tick(0.16, WALL0_NS).publish_map and not core.dirty
    assert not core.tick(0.59, WALL0_NS).publish_map
    assert core.tick(0.6, WALL0_NS).publish_map
    assert core.tick(2.1, WALL0_NS).replanned == 0  # first re-plan one interval (2 s) after the first tick


def test_tick_publishes_at_once_on_a_coverage_change(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    for agent in core.agents:
        core.on_presence(agent, True)
    feed(core, cars, 0.0)
    t = core.tick(0.0, WALL0_NS)
    assert t.publish_map and t.coverage == dict.fromkeys(core.agents, AgentState.LIVE)
    assert core.health() == (NOMINAL, "3/3 agents LIVE, 0 active plans")
    assert core.tick(0.2, WALL0_NS).coverage is None
    core.on_presence("agent2", False)
    t = core.tick(0.3, WALL0_NS)  # before the 0.5 s period is over
    assert t.publish_map and t.coverage is not None and t.coverage["agent2"] is AgentState.STALE
    assert core.next_map_s == pytest.approx(0.8)
    assert core.health() == (DEGRADED, "2/3 agents LIVE, 0 active plans; missing: agent2 STALE")


def test_receive_ack_counts_and_rejects(scene: Scene, cars: dict[str, AgentCars]) -> None:
    core = make_core(scene)
    feed(core, cars, 0.0)
    plan, _ = core.serve(request(), 0.0, WALL0_NS)
    ok = RouteAck(vehicle_id="v01", plan_id=plan.plan_id, version=plan.version, status=Ack.ACCEPTED.value)
    assert core.receive_ack("v01", ok, 0.0) == ["acks/accepted"]
    assert core.receive_ack("v02", ok, 0.0) == ["rejected/ack_vehicle_mismatch"]  # key: another vehicle
    bad_status = RouteAck(vehicle_id="v01", plan_id=plan.plan_id, version=plan.version, status=99)
    assert core.receive_ack("v01", bad_status, 0.0) == ["rejected/ack_status"]
    old = RouteAck(vehicle_id="v01", plan_id="p-old", version=plan.version, status=Ack.COMPLETED.value)
    assert core.receive_ack("v01", old, 0.0) == ["acks/completed", "acks/not_latest"]


def test_replanning_runs_at_its_interval_of_the_clock_of_record(scene: Scene) -> None:
    """Known answer: with replan_interval_s = 2, calls at 10.0, 11.0, 12.0, 12.5, 14.3, 20.0 s replan at
    12.0 (one interval after the first call), 14.3 (due since 14.0) and 20.0 (late: the next is then
    from 20.0, not a burst of the missed ones)."""
    core = make_core(scene)
    assert core.settings.replan_interval_s == 2.0
    ran = [t for t in (10.0, 11.0, 12.0, 12.5, 14.3, 20.0, 21.0) if core.replan_if_due(t, 0) is not None]
    assert ran == [12.0, 14.3, 20.0]
    assert core.next_replan_s == 22.0


def test_a_repeated_request_gets_the_same_plan_until_its_reply_is_acknowledged(scene: Scene) -> None:
    """A reply lost in a router restart: the vehicle asks again from the same lane for the same
    destination and is answered with the same plan (idempotent), not a new version of it."""
    core = make_core(scene)
    core.update_map(0.0)
    first, _ = core.serve(request(), 0.0, WALL0_NS)
    again, _ = core.serve(request(), 1.0, WALL0_NS + NS_PER_S)
    assert (again.plan_id, again.version, again.valid_until) == (
        first.plan_id,
        first.version,
        first.valid_until,
    )
    assert core.repeats == 1
    other, _ = core.serve(request(dest="j1"), 1.5, WALL0_NS + NS_PER_S)  # another request: a new plan
    assert other.plan_id != first.plan_id and other.version > first.version
    core.on_ack("v01", other.plan_id, other.version, Ack.ACCEPTED, 2.0)
    followed, _ = core.serve(request(dest="j1"), 2.0, WALL0_NS + 2 * NS_PER_S)  # acknowledged: planned anew
    assert followed.plan_id != other.plan_id and core.repeats == 1


def test_claims_against_the_followed_plan_are_refused_and_leave_it_unchanged(scene: Scene) -> None:
    """While a vehicle follows its plan (ACCEPTED, within its TTL) a request for it can only come from
    one of the plan's lanes and for its destination (on its last lane, the next trip's): a forged one
    asking from elsewhere or for another destination is refused, and the coordinator's record of the
    vehicle (its plan, its load on the lanes) stays as it was."""
    core = make_core(scene)
    core.update_map(0.0)
    plan, _ = core.serve(request(), 0.0, WALL0_NS)
    lanes = list(plan.lane_ids)
    assert len(lanes) >= 2
    core.on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 0.0)
    latest = core.book.latest("v01")
    off_plan = next(lane for lane in core.net.lanes if lane not in lanes)
    other_dest = next(j for j in core.planner.junctions if j != "j3")
    for req, reason in (
        (request(lane=off_plan), "claim_lane"),
        (request(lane=lanes[0], dest=other_dest), "claim_destination"),
    ):
        with pytest.raises(RequestRejected) as err:
            core.serve(req, 1.0, WALL0_NS + NS_PER_S)
        assert err.value.reason == reason and err.value.code == ErrorCode.ERROR_CODE_INVALID_REQUEST
    assert core.book.latest("v01") is latest
    # The vehicle itself, further along its plan: served. On the plan's last lane the next trip's
    # destination may be asked for.
    onward, _ = core.serve(request(lane=lanes[1]), 2.0, WALL0_NS + 2 * NS_PER_S)
    assert onward.lane_ids[0] == lanes[1]
    core.on_ack("v01", onward.plan_id, onward.version, Ack.ACCEPTED, 2.0)
    last = list(onward.lane_ids)[-1]
    next_trip, _ = core.serve(request(lane=last, dest=other_dest), 3.0, WALL0_NS + 3 * NS_PER_S)
    assert next_trip.destination_junction_id == other_dest
    # Committed at the destination junction to a lane beyond it: the next trip, from that lane.
    core.on_ack("v01", next_trip.plan_id, next_trip.version, Ack.ACCEPTED, 3.0)
    beyond = next(lane for lane in core.net.lanes if core.net.lane_start_junction(lane) == other_dest)
    third = next(j for j in core.planner.junctions if j not in ("j3", other_dest))
    assert core.serve(request(lane=beyond, dest=third), 4.0, WALL0_NS + 4 * NS_PER_S)[0].lane_ids[0] == beyond


def test_a_request_that_overtook_its_plan_end_ack_is_served(scene: Scene) -> None:
    """A vehicle left its plan by a detour and asks from the lane it took; its REJECTED_INVALID ack (by
    pub/sub) has not arrived yet, as after a router restart. The request repeats the end (`ended_plan_id`,
    `ended_status`): the plan ends as the ack would have ended it and the request is served. Naming
    another plan, or a status that is no end, changes nothing: claim_lane as before."""
    core = make_core(scene)
    core.update_map(0.0)
    plan, _ = core.serve(request(), 0.0, WALL0_NS)
    core.on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 0.0)
    off_plan = next(lane for lane in core.net.lanes if lane not in plan.lane_ids)
    for ended_id, status in (("f" * 32, Ack.REJECTED_INVALID), (plan.plan_id, Ack.ACCEPTED)):
        req = request(lane=off_plan)
        req.ended_plan_id, req.ended_status = ended_id, status.value
        with pytest.raises(RequestRejected, match="follows a plan"):
            core.serve(req, 1.0, WALL0_NS + NS_PER_S)
    assert core.ended_by_request == 0
    req = request(lane=off_plan)
    req.ended_plan_id, req.ended_status = plan.plan_id, Ack.REJECTED_INVALID.value
    served, _ = core.serve(req, 1.0, WALL0_NS + NS_PER_S)
    assert served.lane_ids[0] == off_plan and core.ended_by_request == 1
    # The ack arriving afterwards is for a plan no longer the latest: ignored, nothing undone.
    assert not core.on_ack("v01", plan.plan_id, plan.version, Ack.REJECTED_INVALID, 1.5)


def test_claims_are_free_once_the_plan_lapsed_or_the_vehicles_left(scene: Scene) -> None:
    core = make_core(scene)
    core.update_map(0.0)
    plan, _ = core.serve(request(), 0.0, WALL0_NS)
    core.on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 0.0)
    off_plan = next(lane for lane in core.net.lanes if lane not in plan.lane_ids)
    expired_ns = plan.valid_until.ToNanoseconds()  # the vehicle dropped it then, on the wall clock
    assert core.serve(request(lane=off_plan), 1.0, expired_ns)[0].lane_ids[0] == off_plan
    again, _ = core.serve(request(), 2.0, expired_ns + NS_PER_S)
    core.on_ack("v01", again.plan_id, again.version, Ack.ACCEPTED, 2.0)
    assert core.vehicles_left() == 1  # the sim left: its vehicles' plans end with it
    assert core.book.latest("v01") is None
    assert core.serve(request(lane=off_plan), 3.0, expired_ns + 2 * NS_PER_S)[0].lane_ids[0] == off_plan


def test_a_repeated_request_is_planned_anew_once_the_coverage_changed(
    scene: Scene, cars: dict[str, AgentCars]
) -> None:
    core = make_core(scene)
    core.update_map(0.0)  # nothing LIVE
    first, _ = core.serve(request(), 0.0, WALL0_NS)
    feed(core, cars, 1.0)
    core.update_map(1.0)  # every agent LIVE now
    again, _ = core.serve(request(), 1.0, WALL0_NS + NS_PER_S)
    assert again.plan_id != first.plan_id and list(again.coverage.missing_agents) == []
    assert core.repeats == 0


def test_shards_serve_only_their_lanes_and_hand_a_vehicle_over_with_its_versions(scene: Scene) -> None:
    from shared.traffic.regions import Overlay, RegionMap, partition_junctions
    from tests.shared.traffic.scenes import shard_cores

    net = RoadNetwork(scene)
    regions = RegionMap(partition_junctions(net, 2))
    cores = shard_cores(Overlay(net, regions))
    lane = next(lane for lane in sorted(net.lanes) if regions.lane_region(net, lane) == 0)
    far = next(j for j, r in sorted(regions.region_of_junction.items()) if r == 1)
    with pytest.raises(RequestRejected) as refused:
        cores[1].serve(request("v01", lane, far), 1.0, WALL0_NS)
    assert refused.value.reason == "not_owner"
    plan, _ = cores[0].serve(request("v01", lane, far), 1.0, WALL0_NS)
    assert (
        net.is_valid_route(lane, list(plan.lane_ids[1:])) and net.lane_end_junction(plan.lane_ids[-1]) == far
    )
    cores[0].on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 1.0)
    # The vehicle reaches region 1: it moves there, and only there.
    assert cores[1].release("v01") is None  # region 1 never held it
    crossing = next(lane for lane in plan.lane_ids if regions.lane_region(net, lane) == 1)
    assert cores[0].release_problem("v01", crossing, WALL0_NS + NS_PER_S) is None  # on its plan
    handover = cores[0].release("v01")
    assert handover is not None and not cores[0].owns_vehicle("v01")
    cores[1].adopt(handover, 2.0, WALL0_NS + NS_PER_S)
    assert cores[1].owns_vehicle("v01") and cores[1].book.latest("v01") is None  # its version, no route
    later, _ = cores[1].serve(request("v01", crossing, far, plan.version), 2.0, WALL0_NS + NS_PER_S)
    assert later.version > plan.version and later.plan_id != plan.plan_id  # planned here, versions on
    assert cores[1].release("v01") is not None and not cores[1].owns_vehicle("v01")


def test_a_forged_handover_neither_takes_a_vehicle_nor_gives_it_a_route(scene: Scene) -> None:
    """Issue 52 item 1: a forger asked shard 0 to release a vehicle that followed shard 0's plan on shard
    0's lanes (claiming a lane of region 1 the plan never takes), then answered shard 0's release query
    with a detour, TTL + 100 s and version 2^53 - 2: the shard signed and served that plan, and the
    vehicle refused every later one as from the future."""
    from shared.traffic.plans import Route
    from shared.traffic.regions import Overlay, RegionMap, partition_junctions
    from tests.shared.traffic.scenes import shard_cores

    net = RoadNetwork(scene)
    regions = RegionMap(partition_junctions(net, 2))
    cores = shard_cores(Overlay(net, regions))
    lane = next(lane for lane in sorted(net.lanes) if regions.lane_region(net, lane) == 0)
    near = net.lane_end_junction(lane)
    plan, _ = cores[0].serve(request("v01", lane, near), 1.0, WALL0_NS)
    cores[0].on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 1.0)
    off_plan = next(
        x
        for x in sorted(net.lanes)
        if regions.lane_region(net, x) == 1
        and x not in plan.lane_ids
        and net.lane_start_junction(x) != near  # (a lane leaving the destination starts the next trip)
    )
    assert cores[0].release_problem("v01", off_plan, WALL0_NS + NS_PER_S) == "release_claim_lane"
    assert cores[0].owns_vehicle("v01")
    # The forged reply to a release query: its own route and a version far ahead of any clock.
    forged = cores[0].release("v01")
    assert forged is not None
    detour = Route([lane], [], 1e6, 1e6, "balanced")
    forged = dataclasses.replace(
        forged, plan=dataclasses.replace(forged.plan, route=detour, version=2**53 - 2), version=2**53 - 2
    )
    with pytest.raises(ValueError, match="ahead of this shard's clock"):
        cores[0].adopt(forged, 2.0, WALL0_NS + NS_PER_S)
    assert not cores[0].owns_vehicle("v01")
    # Within the clock: only the version counter is taken; the request is planned afresh.
    fair = dataclasses.replace(
        forged, plan=dataclasses.replace(forged.plan, version=plan.version), version=plan.version
    )
    cores[0].adopt(fair, 2.0, WALL0_NS + NS_PER_S)
    again, _ = cores[0].serve(request("v01", lane, near), 2.0, WALL0_NS + NS_PER_S)
    assert list(again.lane_ids) != [lane] or again.expected_travel_time_s < 1e6
    assert again.version > plan.version and again.plan_id not in (plan.plan_id, forged.plan.plan_id)


@pytest.mark.parametrize(
    ("request_replan", "others_on_ab", "lanes"),
    [
        ("on_gain", 3, ["in", "ab"]),  # ab 4 s + 3 x 2 s = 10 s; ac + cb 8 s saves 20 %: not more, kept
        ("on_gain", 5, ["in", "ac", "cb"]),  # ab 14 s: the detour saves 43 %
        ("always", 3, ["in", "ac", "cb"]),  # planned afresh: the faster route whatever it saves
    ],
)
def test_a_request_on_the_followed_plan_keeps_it_unless_a_new_route_saves_the_replan_gain(
    request_replan: str, others_on_ab: int, lanes: list[str]
) -> None:
    """planner_scene from lane `in` to jb: ab 4 s, or ac + cb 8 s; each vehicle planned onto ab adds
    2 s (junction service 1 s x load weight 2). A vehicle following [in, ab] asks again from `in` after
    others were planned onto ab: with `request_replan: on_gain` it keeps its plan unless the new route
    saves more than `replan_gain` (0.2) of the kept one's time, like a pushed re-plan."""
    settings = CoordinatorSettings.model_validate({"request_replan": request_replan})
    core = CoordinatorCore(planner_scene(), settings, 16)
    core.update_map(0.0)
    plan, _ = core.serve(request(lane="in", dest="jb"), 0.0, WALL0_NS)
    assert list(plan.lane_ids) == ["in", "ab"]
    core.on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 0.0)
    for k in range(others_on_ab):
        core.planner.commit(f"o{k}", Route(["in", "ab"], ["ja"], 0.0, 3.0, "balanced"))
    again, _ = core.serve(request(lane="in", dest="jb"), 1.0, WALL0_NS + NS_PER_S)
    assert list(again.lane_ids) == lanes
    assert again.version > plan.version  # a plan issued now either way (its TTL from now)
    assert core.plans_kept == (1 if lanes == ["in", "ab"] else 0)
