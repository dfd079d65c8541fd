"""The bus side of a coordinator shard (issue 37): one `CoordinatorCore` per region of a region map, each
in its own process with its own keys and presence token; Zenoh routers are the only middleware.

    cliques    after each map publication the shard puts its region's crossing times on
               `rmmdet/v1/cloud/regions/<region>/clique`; it takes the others' (checked: peers.py) and
               plans across their regions with them, across a silent or gone shard's on a free-flow prior
    requests   a vehicle asks every shard (target ALL, shared/vehicle/plan_client.py); the shard owning
               the lane it asks from answers, the others decline without a reply
    signatures every clique, release request and handover is signed by its shard's own key and checked
               by the others (shared/security/shard_auth.py)
    handover   a vehicle the owner does not hold yet may hold a plan from another shard: the owner asks
               the others (`rmmdet/v1/cloud/@rpc/release/<vehicle>`) and adopts its version counter
               (bounded by its own clock) before it answers, planning the request afresh (a handed-over
               route is never taken: nothing proves a shard made it); the releasing shard forgets the
               vehicle, so there is one owner at a time, and refuses a release asked from a lane off
               the plan the vehicle follows there. The request is answered later, not blocked on: a Zenoh
               thread must not wait for a reply that the same link delivers.

Names: shard k runs as instance `region<k>` of the coordinator service (its health and presence keys).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

import zenoh
from google.protobuf.message import DecodeError
from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse
from rmmdet.v1.planning_pb2 import PlanHandover, ReleaseRequest, RouteRequest
from rmmdet.v1.traffic_pb2 import RegionClique

from services.coordinator.newcomers import admit_newcomer, newcomer_admission
from shared.bus import names
from shared.bus.codec import MessageDecoder, encode
from shared.bus.health import DEGRADED
from shared.bus.node import Node
from shared.bus.rpc import RpcDeclined, RpcDeferred, RpcRejected, RpcServer
from shared.bus.streams import get_stream, limits, region_of_instance
from shared.config import ConfigError
from shared.scene.scene import Scene
from shared.security.shard_auth import ShardAuth
from shared.timebase import NS_PER_S, SimTime
from shared.traffic import messages
from shared.traffic.config import CoordinatorSettings
from shared.traffic.core import CoordinatorCore
from shared.traffic.lanes import lane_agents, lane_network
from shared.traffic.peers import RegionPeers, slowest_lane_times_s
from shared.traffic.planner import ShardView
from shared.traffic.regions import Clique, Overlay, RegionMap, agent_regions

log = logging.getLogger("services.coordinator.shard")

CLIQUES, RELEASE, ALIVE = get_stream("region_clique"), get_stream("release_rpc"), get_stream("alive")
INVALID = ErrorCode.ERROR_CODE_INVALID_REQUEST
MAX_PENDING = 4096  # vehicles between their release round and the answer that ends it


def shard_core(scene: Scene, settings: CoordinatorSettings, region: int) -> CoordinatorCore:
    """The core of region `region` of `settings.shards.regions`: fed by the agents that cover mostly
    its lanes, serving the vehicles on them. ConfigError for a region the map does not have."""
    if settings.shards.regions is None:
        raise ConfigError("--shard needs shards.regions (a region map) in the coordinator settings")
    net = lane_network(scene)
    try:
        regions = RegionMap.load(settings.shards.regions, net)
    except (OSError, ValueError, KeyError) as err:
        raise ConfigError(f"region map {settings.shards.regions}: {err}") from None
    if not 0 <= region < regions.regions:
        raise ConfigError(f"--shard {region}: {settings.shards.regions} has regions 0..{regions.regions - 1}")
    agents = [a for a, r in agent_regions(lane_agents(scene, net), net, regions).items() if r == region]
    view = ShardView(Overlay(net, regions, settings.planner.turn_penalty_s), region)
    return CoordinatorCore(scene, settings, settings.service.max_vehicles, shard=view, shard_agents=agents)


class ShardLink:
    """Region `core.shard.region`'s cliques, handovers and peers on `node` (see the module docstring).
    `poll` and `publish_clique` run on the service's main loop; `gate` and `on_release` on Zenoh threads."""

    def __init__(
        self,
        node: Node,
        core: CoordinatorCore,
        settings: CoordinatorSettings,
        clock: SimTime,
        auth: ShardAuth,
    ) -> None:
        assert core.shard is not None
        self.node, self.core, self.clock, self.auth = node, core, clock, auth
        self.newcomers = newcomer_admission(settings)
        self.view: ShardView = core.shard
        self.region = self.view.region
        self.counters = node.counters
        self.timeout_s = settings.shards.release_timeout_s
        self.peers = RegionPeers(
            self.view.overlay,
            self.region,
            settings.shards.clique_stale_after_s,
            slowest_lane_times_s(self.view.overlay, settings.planner),
        )
        self.on_prior: list[int] = self.peers.on_prior(clock.now_s())  # cached for the health callback
        self._own: Clique | None = None
        self._combined_of: tuple[object, object] = (None, None)
        self.clique_pub = node.publisher("region_clique", region=str(self.region))
        self.cliques_in = node.subscribe_stream(
            "region_clique", clock_s=clock.now_s, max_future_s=limits().max_clock_skew_s
        )
        self.shards_presence = node.presence(ALIVE.pattern(scope="cloud", service=names.COORDINATOR))
        self.release_server = RpcServer(
            node,
            "release_rpc",
            ReleaseRequest,
            self.on_release,
            stage="coordinator/release",
            served="handovers/answered",
            bind={"vehicle": "vehicle_id"},
        )
        node.queryable(self.release_server.key, self.release_server)
        self.handover_decoder = MessageDecoder(PlanHandover, node.counters)
        self._lock = threading.Lock()
        self._asked: set[str] = set()  # vehicles whose release round is over: served next, once
        # Releases are asked from this thread: never from a Zenoh callback (module docstring).
        self._todo: queue.SimpleQueue[tuple[RouteRequest, Callable[[], None]] | None] = queue.SimpleQueue()
        self._worker = threading.Thread(target=self._ask_loop, name="shard-release", daemon=True)
        self._worker.start()

    def close(self) -> None:
        self._todo.put(None)
        self._worker.join(timeout=2.0)

    # --- requests (Zenoh threads) ------------------------------------------------------------------

    def gate(self, request: RouteRequest) -> None:
        """Before the core serves `request`: declines a lane of another region; defers a vehicle this
        shard does not hold until the other shards were asked to hand it over."""
        lane = request.current_lane_id
        if lane not in self.view.overlay.index:
            return  # every shard refuses an unknown lane alike (core.serve)
        if not self.view.owns(lane):
            raise RpcDeclined("other_region")
        vid = request.vehicle_id
        with self._lock:
            if vid in self._asked:  # its release round is over (adopted, or nobody held it)
                self._asked.discard(vid)
                return
        if self.core.owns_vehicle(vid):
            return
        admit_newcomer(self.newcomers, vid)  # before a release round: a flood must not fan out
        raise RpcDeferred(lambda resume: self._todo.put((request, resume)))

    def _ask_loop(self) -> None:
        while (item := self._todo.get()) is not None:
            request, resume = item
            try:
                self._ask(request, resume)
            except Exception as err:  # the bus is closing: answer without a handover
                log.warning("release of %s not asked: %s", request.vehicle_id, err)
                self._asked_done(request.vehicle_id, resume)

    def _ask(self, request: RouteRequest, resume: Callable[[], None]) -> None:
        vid = request.vehicle_id
        ask = ReleaseRequest(vehicle_id=vid, lane_id=request.current_lane_id, region=self.region)
        ask.header.source_id = self.node.source_id
        ask_ns = time.time_ns()
        ask.header.stamp.FromNanoseconds(ask_ns)
        encoded = encode(self.auth.sign(ask, ask_ns))
        adopted = [False]

        def on_reply(reply: zenoh.Reply) -> None:
            try:
                if reply.ok is None:
                    self._refused(reply)
                    return
                sample = reply.ok
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                decoded = self.handover_decoder.decode(
                    sample.payload.to_bytes(), str(sample.encoding), attachment
                )
                if decoded is None:  # counted by the decoder
                    return
                msg = decoded.message
                assert isinstance(msg, PlanHandover)
                if not msg.held:
                    return
                if (problem := self.auth.problem(msg, ask_ns, None)) is not None:  # any other shard's
                    self.counters.inc(f"rejected/handover_{problem}")
                    return
                if adopted[0]:  # two shards held the vehicle: never expected; the first is kept
                    self.counters.inc("handovers/extra_holder")
                    log.warning("%s was held by more than one shard", vid)
                    return
                adopted[0] = self._adopt(msg, vid)
            except Exception:  # never raise into Zenoh
                log.exception("release reply for %s failed", vid)

        self.node.session.get(
            RELEASE.key(vehicle=vid),
            zenoh.handlers.Callback(on_reply, lambda: self._asked_done(vid, resume)),
            payload=encoded.payload,
            encoding=encoded.encoding,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.timeout_s,
            allowed_destination=zenoh.Locality.REMOTE,  # not this shard's own release queryable
            **RELEASE.qos.publisher_kwargs(),
        )
        self.counters.inc("handovers/asked")

    def _adopt(self, msg: PlanHandover, vid: str) -> bool:
        now_s = self.clock.now_s()
        try:
            handover = messages.handover_of(msg, vid, now_s)
            self.core.adopt(handover, now_s, time.time_ns())  # versions only: the route is planned afresh
        except ValueError as err:
            self.counters.inc("rejected/handover")
            log.warning("handover of %s refused: %s", vid, err)
            return False
        self.counters.inc("handovers/adopted")
        return True

    def _refused(self, reply: zenoh.Reply) -> None:
        error = ErrorResponse()
        try:
            error.ParseFromString(reply.err.payload.to_bytes() if reply.err is not None else b"")
        except DecodeError:
            self.counters.inc("handovers/transport_errors")
            return
        self.counters.inc("handovers/refused")

    def _asked_done(self, vid: str, resume: Callable[[], None]) -> None:
        with self._lock:
            if len(self._asked) >= MAX_PENDING:  # vehicles that never asked again (timed out): dropped
                self._asked.clear()
            self._asked.add(vid)
        resume()

    def on_release(self, request: ReleaseRequest, _start_ns: int) -> tuple[PlanHandover, int]:
        """Another shard asks for a vehicle now on a lane of its region: hand it over if held here
        (`RegionPeers.release_problem` refuses the rest)."""
        stamp_ns = request.header.stamp.ToNanoseconds()
        forged = self.auth.request_problem(request, stamp_ns, request.region, time.time_ns())
        if forged is not None:
            raise RpcRejected(f"release_{forged}", INVALID, f"not signed by region {request.region}'s shard")
        problem = self.peers.release_problem(request.lane_id, request.region)
        if problem is not None:
            raise RpcRejected("release_lane", INVALID, problem)
        refused = self.core.release_problem(request.vehicle_id, request.lane_id, time.time_ns())
        if refused is not None:
            detail = f"{request.vehicle_id} follows a plan here that does not take {request.lane_id!r}"
            raise RpcRejected(refused, INVALID, detail)
        handover = self.core.release(request.vehicle_id)
        if handover is None:
            return PlanHandover(held=False), 0
        self.counters.inc("handovers/released")
        return self.auth.sign(messages.handover_message(handover, self.clock.now_s()), stamp_ns), 0

    # --- peers (main loop) -------------------------------------------------------------------------

    def poll(self, now_s: float) -> None:
        """Take the other shards' cliques and presence; refresh what the planner crosses regions with."""
        for item in self.cliques_in.drain():
            region = CLIQUES.id_of(item.key, "region")
            if region == str(self.region):
                continue  # this shard's own, heard back
            msg = item.message
            assert isinstance(msg, RegionClique)
            if str(msg.region) != region:
                self.counters.inc("rejected/clique_key_mismatch")
                continue
            stamp_ns = item.header.stamp.ToNanoseconds()
            if (forged := self.auth.problem(msg, stamp_ns, msg.region)) is not None:
                self.counters.inc(f"rejected/clique_{forged}")
                continue
            problem = self.peers.receive(msg, now_s, stamp_ns / NS_PER_S)
            self.counters.inc(f"rejected/{problem}" if problem else "cliques/received")
        for key, alive in self.shards_presence.changes():
            gone = region_of_instance(ALIVE.id_of(key, "instance"))
            if gone is not None and not alive:
                self.peers.gone(gone)
                log.warning("shard of region %d left: its region is planned on a prior", gone)
        self._refresh(now_s)

    def _refresh(self, now_s: float) -> None:
        peers = self.peers.cliques(now_s)
        prior = self.peers.on_prior(now_s)
        if prior != self.on_prior:
            log.warning("regions on a prior: %s", prior or "none")
            self.on_prior = prior
        if self._combined_of[0] is not peers or self._combined_of[1] is not self._own:  # by identity
            self._combined_of = (peers, self._own)
            combined = dict(peers)
            if self._own is not None:
                combined[self.region] = self._own
            self.view.cliques = combined  # one assignment: the planner sees the old dict or the new

    def publish_clique(self, now_s: float) -> None:
        """After a map publication: this region's crossing times, for the others and for itself, stamped
        now on the clock of record (the others judge its age by it: `RegionPeers.receive`)."""
        self._own = self.core.clique()
        stamp_ns = round(now_s * NS_PER_S)
        signed = self.auth.sign(messages.clique_message(self._own), stamp_ns)
        self.clique_pub.put(signed, stamp_ns=stamp_ns, frame_id="world")
        self.counters.inc("cliques/published")
        self._refresh(now_s)

    def health(self) -> tuple[int, str] | None:
        """DEGRADED while another region is planned on a prior (cached: called on a Zenoh thread)."""
        if self.on_prior:
            return DEGRADED, f"regions {self.on_prior} planned on a prior (their shard silent)"
        return None
