"""What coordinator shards send each other (issue 37): cliques and handed-over vehicles survive the wire
exactly; what does not fit is refused with its reason; a shard's view of its peers falls back to a
prior for a silent or gone region and refuses forged cliques (shared/traffic/peers.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from rmmdet.v1.planning_pb2 import AckStatus, PlanHandover, RouteRequest
from rmmdet.v1.traffic_pb2 import RegionClique

from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.traffic import messages
from shared.traffic.config import PlannerConfig
from shared.traffic.peers import RegionPeers, slowest_lane_times_s
from shared.traffic.plans import Ack
from shared.traffic.regions import Overlay, RegionMap, partition_junctions
from tests.shared.traffic.scenes import shard_cores

WALL0_NS = 1_800_000_000 * NS_PER_S


@pytest.fixture(scope="module")
def overlay() -> Overlay:
    net = RoadNetwork(Scene.load(DEFAULT_SCENE))
    return Overlay(net, RegionMap(partition_junctions(net, 2)))


def _wire(msg: RegionClique) -> RegionClique:
    out = RegionClique()
    out.ParseFromString(msg.SerializeToString())
    return out


def test_a_clique_crosses_the_wire_unchanged_no_way_included(overlay: Overlay) -> None:
    clique = overlay.clique(1, overlay.free_time_s * 2.0)
    assert np.isinf(clique.time_s).any()  # a U-turn pair has no way: it must survive as such
    msg = _wire(messages.clique_message(clique))
    assert messages.NO_WAY in msg.time_s and all(np.isfinite(msg.time_s))  # the codec refuses inf
    back = messages.clique_of(msg)
    np.testing.assert_array_equal(back.time_s, clique.time_s)
    np.testing.assert_array_equal(back.to_junction_s, clique.to_junction_s)
    assert (back.region, back.entering, back.leaving, back.junctions) == (
        clique.region, clique.entering, clique.leaving, clique.junctions)  # fmt: skip
    assert back.paths == clique.paths and back.junction_paths == clique.junction_paths
    assert overlay.clique_problem(back, overlay.free_time_s) is None


def test_a_malformed_clique_message_is_refused(overlay: Overlay) -> None:
    msg = messages.clique_message(overlay.clique(1, overlay.free_time_s))
    short = _wire(msg)
    del short.time_s[-1]
    with pytest.raises(ValueError, match="times for"):
        messages.clique_of(short)
    both = _wire(msg)
    both.paths[0].to_junction = "j1"
    both.paths[0].to_lane = "l0"
    with pytest.raises(ValueError, match="one of to_lane and to_junction"):
        messages.clique_of(both)
    negative = _wire(msg)
    negative.time_s[0] = -5.0  # not NO_WAY: stays negative, for clique_problem to refuse
    assert overlay.clique_problem(messages.clique_of(negative), overlay.free_time_s) == "clique_time"


def test_a_handed_over_vehicle_keeps_plan_version_and_ack_across_the_wire(overlay: Overlay) -> None:
    cores = shard_cores(overlay)
    net = overlay.net
    lane = next(lane for lane in overlay.lane_ids if cores[0].shard and cores[0].shard.owns(lane))
    far = next(j for j, r in sorted(overlay.regions.region_of_junction.items()) if r == 1)
    req = RouteRequest(vehicle_id="v01", current_lane_id=lane, destination_junction_id=far)
    plan, _ = cores[0].serve(req, 10.0, WALL0_NS)
    cores[0].on_ack("v01", plan.plan_id, plan.version, Ack.ACCEPTED, 10.5)
    released = cores[0].release("v01")
    assert released is not None
    wire = PlanHandover()
    wire.ParseFromString(messages.handover_message(released, 12.0).SerializeToString())
    assert wire.age_s == pytest.approx(2.0) and wire.ack == AckStatus.ACK_STATUS_ACCEPTED
    handover = messages.handover_of(wire, "v01", 100.0)  # the new shard's clock differs: age is kept
    assert handover.plan.issued_s == pytest.approx(98.0)
    assert (handover.plan.plan_id, handover.plan.version, handover.plan.ack) == (
        plan.plan_id, plan.version, Ack.ACCEPTED)  # fmt: skip
    assert handover.plan.route == released.plan.route
    assert handover.version == released.version
    assert handover.active.message == released.active.message
    assert handover.active.missing == released.active.missing
    assert handover.active.valid_until_ns == released.active.valid_until_ns
    cores[1].adopt(handover, 100.0, WALL0_NS + NS_PER_S)  # its versions; the route is planned afresh
    assert cores[1].owns_vehicle("v01") and not cores[0].owns_vehicle("v01")
    crossing = next(lane for lane in plan.lane_ids if overlay.regions.lane_region(net, lane) == 1)
    later, _ = cores[1].serve(
        RouteRequest(
            vehicle_id="v01",
            current_lane_id=crossing,
            destination_junction_id=far,
            current_plan_version=plan.version,
        ),
        101.0,
        WALL0_NS + NS_PER_S,
    )
    assert later.version > plan.version


def test_a_handover_that_does_not_fit_is_refused_with_its_reason(overlay: Overlay) -> None:
    cores = shard_cores(overlay)
    lane = next(lane for lane in overlay.lane_ids if cores[0].shard and cores[0].shard.owns(lane))
    far = next(j for j, r in sorted(overlay.regions.region_of_junction.items()) if r == 1)
    cores[0].serve(
        RouteRequest(vehicle_id="v01", current_lane_id=lane, destination_junction_id=far), 1.0, WALL0_NS
    )
    released = cores[0].release("v01")
    assert released is not None
    good = messages.handover_message(released, 1.0)

    def refused(change) -> str:
        msg = PlanHandover()
        msg.CopyFrom(good)
        change(msg)
        with pytest.raises(ValueError) as err:
            messages.handover_of(msg, "v01", 5.0)
        return str(err.value)

    assert "not held" in refused(lambda m: setattr(m, "held", False))
    assert "asked for" in refused(lambda m: setattr(m.plan, "vehicle_id", "v02"))
    assert "plan id" in refused(lambda m: setattr(m.plan, "plan_id", "x" * 32))
    assert "version" in refused(lambda m: setattr(m, "version_counter", m.plan.version - 1))
    assert "policy" in refused(lambda m: setattr(m.plan, "policy", 99))
    assert "junctions" in refused(lambda m: m.plan.junction_ids.append("j1"))
    assert "age" in refused(lambda m: setattr(m, "age_s", -1.0))


def test_peers_plan_on_fresh_cliques_and_fall_back_to_the_prior(overlay: Overlay) -> None:
    peers = RegionPeers(overlay, 0, stale_after_s=3.0)
    assert peers.on_prior(0.0) == [1]
    prior = peers.cliques(0.0)
    assert peers.cliques(0.5) is prior  # unchanged: the same object (the overlay caches per object)
    jammed = overlay.clique(1, overlay.free_time_s * 3.0)
    assert peers.receive(messages.clique_message(jammed), 1.0, 1.0) is None
    fresh = peers.cliques(1.0)
    assert fresh is not prior and peers.on_prior(1.0) == []
    np.testing.assert_array_equal(fresh[1].time_s, jammed.time_s)
    assert peers.on_prior(4.5) == [1]  # silent past stale_after_s
    np.testing.assert_array_equal(peers.cliques(4.5)[1].time_s, peers.priors[1].time_s)
    assert peers.receive(messages.clique_message(jammed), 5.0, 5.0) is None
    peers.gone(1)  # its shard's presence left: the prior at once
    assert peers.on_prior(5.0) == [1]


def test_peers_refuse_forged_and_own_cliques(overlay: Overlay) -> None:
    peers = RegionPeers(overlay, 0, stale_after_s=3.0)
    own = messages.clique_message(overlay.clique(0, overlay.free_time_s))
    assert peers.receive(own, 1.0, 1.0) == "clique_own_region"
    good = overlay.clique(1, overlay.free_time_s * 2.0)
    i, j = np.argwhere(np.isfinite(good.time_s))[0]
    fast = good.time_s.copy()
    fast[i, j] = 0.01  # a region faster than its speed limits, drawing traffic into it
    assert peers.receive(messages.clique_message(dataclasses.replace(good, time_s=fast)), 1.0, 1.0) == (
        "clique_too_fast"
    )
    broken = messages.clique_message(good)
    del broken.to_junction_s[0]
    assert peers.receive(broken, 1.0, 1.0) == "clique_shape"
    assert peers.on_prior(1.0) == [1]  # nothing usable arrived


def test_cliques_are_bounded_and_aged_by_their_stamp(overlay: Overlay) -> None:
    """Issue 52 item 3: a clique whose times were all infinite passed (the region shut to every other
    shard's traffic), times had no upper bound, and an old genuine clique replayed later was taken as
    fresh (freshness was its arrival)."""
    slowest = slowest_lane_times_s(overlay, PlannerConfig())
    peers = RegionPeers(overlay, 0, stale_after_s=3.0, slowest_time_s=slowest)
    good = overlay.clique(1, overlay.free_time_s * 2.0)
    shut = dataclasses.replace(
        good, time_s=np.full_like(good.time_s, np.inf), to_junction_s=np.full_like(good.to_junction_s, np.inf)
    )
    assert peers.receive(messages.clique_message(shut), 1.0, 1.0) == "clique_no_way"
    i, j = np.argwhere(np.isfinite(good.time_s))[0]
    slow = good.time_s.copy()
    slow[i, j] = 1e9  # pushing traffic out of the region: slower than any map the planner makes
    assert peers.receive(messages.clique_message(dataclasses.replace(good, time_s=slow)), 1.0, 1.0) == (
        "clique_too_slow"
    )
    jammed = overlay.clique(1, np.minimum(overlay.free_time_s * 50.0, slowest))  # slow, but genuine
    assert peers.receive(messages.clique_message(jammed), 1.0, 1.0) is None
    assert peers.on_prior(1.0) == []
    # The same genuine clique replayed: not newer than the one held, then older than stale_after_s.
    assert peers.receive(messages.clique_message(jammed), 2.0, 1.0) == "clique_old"
    assert peers.receive(messages.clique_message(good), 9.0, 1.5) == "clique_stale"
    assert peers.on_prior(4.5) == [1]  # its age is its stamp's: 3.5 s old, whatever arrived since


def test_a_shard_hands_over_only_to_the_region_of_the_lane_asked_from(overlay: Overlay) -> None:
    peers = RegionPeers(overlay, 0, stale_after_s=3.0)
    mine = next(lane for lane in overlay.lane_ids if overlay.lane_region[overlay.index[lane]] == 0)
    theirs = next(lane for lane in overlay.lane_ids if overlay.lane_region[overlay.index[lane]] == 1)
    assert peers.release_problem(theirs, 1) is None
    assert "region 0's" in (peers.release_problem(mine, 1) or "")  # forged: a vehicle on my lanes
    assert "asked by region 7" in (peers.release_problem(theirs, 7) or "")
    assert "unknown lane" in (peers.release_problem("no-such-lane", 1) or "")
