"""A coordinator shard's view of the other regions (issue 37): the latest clique each one's shard
published, checked before use, and a free-flow prior for a region whose shard is silent or gone.

The other shards' cliques come over the bus (`region_clique`); one that does not decode into its
region's shape or fails `Overlay.clique_problem` (lanes that do not join, a region faster than its speed
limits) is refused and counted, never planned with: a forged clique must not draw traffic into a region.
A region heard from within `stale_after_s` is planned on its clique; otherwise, or once its shard's
presence is gone, on the prior (every lane at its speed limit) and named in `on_prior` so the shard's
health says that part of its plans is blind. A clique's age is its stamp's (a replayed one is old), and
its times are held between free flow and the slowest a genuine map gives (`slowest_lane_times_s`).
Times: seconds on the shard's clock of record.
"""

from __future__ import annotations

from rmmdet.v1.traffic_pb2 import RegionClique

from shared.bus.streams import limits
from shared.traffic import messages
from shared.traffic.config import PlannerConfig
from shared.traffic.regions import Clique, FloatArray, Overlay


def slowest_lane_times_s(overlay: Overlay, planner: PlannerConfig) -> FloatArray:
    """(L,) each lane's slowest time a genuine shard's maps can give it, the bound a clique's times are
    held to: the planner floors perceived speeds at `min_speed_mps` and adds a junction service per car
    on the lane and `load_weight` per vehicle planned onto it, each count at most what one object list
    may carry (the bus's `max_list_length`)."""
    services = planner.junction_service_s * (1.0 + planner.load_weight) * limits().max_list_length
    return overlay.length_m / planner.min_speed_mps + services


class RegionPeers:
    """Region `region`'s view of the others on `overlay`; `slowest_time_s`: `slowest_lane_times_s`."""

    def __init__(
        self, overlay: Overlay, region: int, stale_after_s: float, slowest_time_s: FloatArray | None = None
    ) -> None:
        self.overlay = overlay
        self.region = region
        self.stale_after_s = stale_after_s
        self.slowest_time_s = slowest_time_s
        self.priors = {r: c for r, c in overlay.free_flow_cliques().items() if r != region}
        self._latest: dict[int, tuple[Clique, float]] = {}  # region -> its newest clique, its stamp (s)
        self._view: dict[int, Clique] = dict(self.priors)
        self._fresh: frozenset[int] = frozenset()

    def receive(self, msg: RegionClique, now_s: float, stamp_s: float) -> str | None:
        """Take another shard's clique, stamped `stamp_s` by its shard (the clock of record, as `now_s`);
        returns why it was refused (a counter name) or None. Its freshness is its stamp's, not its
        arrival's: a clique replayed later is as old as when it was made (`clique_stale` once older than
        `stale_after_s`, `clique_old` when not newer than the region's clique held)."""
        if msg.region == self.region:
            return "clique_own_region"
        if now_s - stamp_s > self.stale_after_s:
            return "clique_stale"
        held = self._latest.get(msg.region)
        if held is not None and stamp_s <= held[1]:
            return "clique_old"
        try:
            clique = messages.clique_of(msg)
        except ValueError:
            return "clique_shape"
        problem = self.overlay.clique_problem(
            clique, self.overlay.free_time_s, slowest_time_s=self.slowest_time_s
        )
        if problem is None:
            self._latest[clique.region] = (clique, stamp_s)
            self._view = {}  # rebuilt by `cliques`: a new object, so the overlay's caches refresh
        return problem

    def release_problem(self, lane: str, asking_region: int) -> str | None:
        """Why this shard must not hand over a vehicle that another shard says now asks from `lane`
        (a message), or None. The lane must exist and belong to the asking region, not to this one: a
        shard never gives away a vehicle on its own lanes, whoever asks."""
        overlay = self.overlay
        if lane not in overlay.index:
            return f"unknown lane {lane[:80]!r}"
        owner = int(overlay.lane_region[overlay.index[lane]])
        if owner == self.region or owner != asking_region:
            return f"lane {lane!r} is region {owner}'s, asked by region {asking_region}"
        return None

    def gone(self, region: int) -> None:
        """Region `region`'s shard left the bus: its region is planned on the prior from now."""
        if self._latest.pop(region, None) is not None:
            self._view = {}

    def cliques(self, now_s: float) -> dict[int, Clique]:
        """Every other region's clique: the latest fresh one, else the prior. The same object while
        nothing changed (the overlay caches its searches per cliques object)."""
        fresh = frozenset(r for r, (_, at_s) in self._latest.items() if now_s - at_s <= self.stale_after_s)
        if fresh != self._fresh or not self._view:
            self._fresh = fresh
            self._view = {r: self._latest[r][0] if r in fresh else prior for r, prior in self.priors.items()}
        return self._view

    def on_prior(self, now_s: float) -> list[int]:
        """Regions planned on the prior at `now_s` (sorted)."""
        self.cliques(now_s)
        return sorted(set(self.priors) - self._fresh)
