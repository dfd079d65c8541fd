"""The bus streams the viewer draws, and how each draw takes them into the view and the dashboard.

Object lists are all counted for the dashboard's rates and only the newest per agent drawn; ground
truth and the traffic map are latest-wins; pushed and served plans and acknowledgements are kept (a
bounded queue each); a sharded coordinator's region maps are merged into one map (`make up SHARDS=2`).
Stamps ahead of the clock of record are refused (`rejected/future`).
"""

from __future__ import annotations

from typing import Any

from shared.bus.node import Node, Received, Subscription
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import limits
from shared.scene.scene import Scene
from shared.timebase import SimTime
from shared.traffic.messages import LatestRegionMaps
from shared.viewer.core import ViewerCore
from shared.viewer.dashboard import DashboardState

PLAN_QUEUE = 256  # pushed plans (or acks) between two draws (one per vehicle at most, normally)
OBJECT_QUEUE = 8  # object lists of one agent between two draws (all counted for its rate, the newest drawn)
REGION_MAP_QUEUE = 16  # region maps of a sharded coordinator between two draws (the newest per region kept)


class ViewerInputs:
    """The viewer's subscriptions on `node` for `scene`'s agents."""

    def __init__(self, node: Node, scene: Scene) -> None:
        clock = SimTime()
        node.follow_sim_time(clock)
        skew_s = limits().max_clock_skew_s

        def subscribe(name: str, queue: BoundedQueue[Received] | None = None, **kw: Any) -> Subscription:
            return node.subscribe_stream(name, queue=queue, clock_s=clock.now_s, max_future_s=skew_s, **kw)

        self.objects = {a: subscribe("objects", agent=a, maxsize=OBJECT_QUEUE) for a in scene.agents}
        self.acks = subscribe("route_ack", maxsize=PLAN_QUEUE)
        self.ground_truth = subscribe("ground_truth", maxsize=1)
        self.traffic = subscribe("traffic_map", maxsize=1)
        self.region_maps = subscribe("region_map", maxsize=REGION_MAP_QUEUE)
        self.regions = LatestRegionMaps()
        self.plans = subscribe(
            "route_plan", BoundedQueue(PLAN_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/plans")
        )
        self.served = subscribe(  # plans vehicles asked for (the coordinator copies them)
            "route_plan_served",
            BoundedQueue(PLAN_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/served_plans"),
        )

    def take(self, core: ViewerCore, board: DashboardState, now_s: float) -> None:
        """Everything that arrived since the last call, into the view core and the dashboard's state
        (`now_s`: monotonic seconds of this draw)."""
        for agent, sub in self.objects.items():
            items = sub.drain()
            for item in items:
                board.on_objects(agent, item.message, now_s)
            for item in items[-1:]:
                core.on_tracks(agent, item.message, item.header.stamp.ToNanoseconds())
        for item in self.ground_truth.drain()[-1:]:
            core.on_ground_truth(item.message, item.header.stamp.ToNanoseconds())
            board.on_ground_truth(item.message)
        for item in self.plans.drain():
            core.on_plan(item.message, now_s)
            board.on_plan(item.message)
        for item in self.served.drain():
            core.on_plan(item.message, now_s)
            board.on_plan(item.message, served=True)
        for item in self.acks.drain():
            board.on_ack(item.message)
        for item in self.traffic.drain()[-1:]:
            core.on_traffic_map(item.message, item.header.stamp.ToNanoseconds())
            board.on_traffic_map(item.message)
        arrived = self.region_maps.drain()
        for item in arrived:
            self.regions.put(item.key, item.message, item.header.stamp.ToNanoseconds(), now_s)
        if arrived and (merged := self.regions.merged(now_s)) is not None:
            core.on_traffic_map(*merged)
            board.on_traffic_map(merged[0])
