"""The browser dashboard's state (issue 18): what the page shows, gathered from the bus messages and
`rmmdet health`'s verdict, as one JSON-able snapshot. No bus, no server: the viewer service feeds it
and serves `snapshot()`.

Shown: each agent's coverage in the coordinator's maps (LIVE / STALE / LOST, data age, objects) with
the rate of its object lists over the last RATE_WINDOW_S and their processing latency (the MEC's own
stage latencies, summed); the paper's Table II live: each junction's vehicle count since the sim
started; route plans pushed and served (asked for) and acknowledgements by status; the traffic grid
(vehicles and mean speed per cell) for the heat map; the alarms (`rmmdet health`'s problems). Times:
`now_s` monotonic s.
"""

from __future__ import annotations

from collections import Counter, deque
from typing import Any

import numpy as np
from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import AckStatus, RouteAck, RoutePlan
from rmmdet.v1.sim_pb2 import GroundTruth
from rmmdet.v1.traffic_pb2 import AgentState, TrafficGrid, TrafficMap

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene

RATE_WINDOW_S = 5.0
STATE = {AgentState.AGENT_STATE_LIVE: "LIVE", AgentState.AGENT_STATE_STALE: "STALE"}
STATE[AgentState.AGENT_STATE_LOST] = "LOST"


class DashboardState:
    def __init__(self, agents: list[str]) -> None:
        self.agents = list(agents)
        self._arrivals: dict[str, deque[float]] = {a: deque() for a in agents}
        self._latency_s: dict[str, float] = {}
        self._coverage: dict[str, dict[str, Any]] = {}
        self._junctions: dict[str, dict[str, Any]] = {}
        self._grid: dict[str, Any] | None = None  # _grid_msg as JSON, made on the first snapshot after it
        self._grid_msg: TrafficGrid | None = None
        self.plans_pushed = 0
        self.plans_served = 0
        self.acks: Counter[str] = Counter()
        self._health: dict[str, Any] = {"loop_ok": None, "summary": "no health probe yet", "alarms": []}

    def on_objects(self, agent: str, msg: TrackedObjects, now_s: float) -> None:
        if agent not in self._arrivals:
            return
        arrivals = self._arrivals[agent]
        arrivals.append(now_s)
        while now_s - arrivals[0] > RATE_WINDOW_S:  # bounded even when no snapshot is ever taken
            arrivals.popleft()
        self._latency_s[agent] = sum(s.duration_s for s in msg.stage_latencies)

    def on_traffic_map(self, msg: TrafficMap) -> None:
        self._coverage = {
            c.agent_id: {"state": STATE.get(c.state, "?"), "age_s": c.data_age_s, "objects": c.object_count}
            for c in msg.coverage
        }
        # The grid (thousands of cells) is turned into JSON only when a snapshot is taken: maps come
        # faster than snapshots while nobody watches, and converting each was the viewer's top cost.
        self._grid_msg, self._grid = msg.grid, None

    def on_ground_truth(self, msg: GroundTruth) -> None:
        for flow in msg.junction_flows:
            self._junctions[flow.junction_id] = {"number": flow.number, "vehicles": flow.arrivals}

    def on_plan(self, msg: RoutePlan, served: bool = False) -> None:
        """A plan the coordinator pushed, or (`served`) one a vehicle asked for over the route RPC."""
        if served:
            self.plans_served += 1
        else:
            self.plans_pushed += 1

    def on_ack(self, msg: RouteAck) -> None:
        self.acks[AckStatus.Name(msg.status).removeprefix("ACK_STATUS_")] += 1

    def on_health(self, loop_ok: bool, summary: str, alarms: list[str]) -> None:
        self._health = {"loop_ok": loop_ok, "summary": summary, "alarms": list(alarms)}

    def rate_hz(self, agent: str, now_s: float) -> float:
        arrivals = self._arrivals[agent]
        while arrivals and now_s - arrivals[0] > RATE_WINDOW_S:
            arrivals.popleft()
        return len(arrivals) / RATE_WINDOW_S

    def grid(self) -> dict[str, Any] | None:
        """The newest traffic grid as the page draws it (cells row-major, 3 decimals)."""
        g = self._grid_msg
        if self._grid is None and g is not None:
            self._grid = {
                "origin_m": [g.origin_m.x_m, g.origin_m.y_m],
                "cell_m": g.cell_size_m,
                "columns": g.column_count,
                "rows": g.row_count,
                "vehicles": np.round(np.asarray(g.vehicle_count, float), 3).tolist(),
                "mean_speed_mps": np.round(np.asarray(g.mean_speed_mps, float), 3).tolist(),
            }
        return self._grid

    def snapshot(self, now_s: float) -> dict[str, Any]:
        return {
            "agents": [
                {
                    "agent": a,
                    **self._coverage.get(a, {"state": "?", "age_s": None, "objects": 0}),
                    "rate_hz": round(self.rate_hz(a, now_s), 2),
                    "latency_ms": None if a not in self._latency_s else round(self._latency_s[a] * 1e3, 1),
                }
                for a in self.agents
            ],
            "junctions": sorted(self._junctions.values(), key=lambda j: j["number"]),
            "plans": {
                "pushed": self.plans_pushed,
                "served": self.plans_served,
                "acknowledged": dict(self.acks),
            },
            "grid": self.grid(),
            "health": self._health,
        }


def map_of(scene: Scene, network: RoadNetwork) -> dict[str, Any]:
    """The dashboard's static map: every lane's centreline (x, y) and every junction's number."""
    return {
        "lanes": [
            {"id": lane_id, "points": [[round(float(p[0]), 3), round(float(p[1]), 3)] for p in path.points]}
            for lane_id, path in network.lanes.items()
        ],
        "junctions": [
            {"id": j.id, "number": j.number, "x": j.position_m[0], "y": j.position_m[1]}
            for j in scene.spec.junctions
        ],
    }
