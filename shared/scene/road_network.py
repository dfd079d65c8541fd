"""Drivable road network of a scene: lane paths, junction connectors and the lane graph.

Lanes come from the scene file (rounded, resampled centrelines). Inside each junction's control zone
a vehicle drives a *connector*: a cubic Bezier from the end of its incoming lane to the start of the
chosen outgoing lane, tangent to both. Every (incoming, outgoing) pair is allowed except a U-turn onto
the same road's opposite lane. The lane graph (networkx) gives shortest routes to a junction.
Units: metres, radians.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import networkx as nx
import numpy as np

from shared.scene.lanes import arc_length, headings_rad, resample
from shared.scene.scene import Scene

FloatArray = np.ndarray

BEZIER_HANDLE_FRACTION = 0.45  # handle length as a fraction of the chord: close to a circular arc
BEZIER_SAMPLES = 64


@dataclass
class Path:
    """A drivable polyline: a lane or a junction connector."""

    id: str
    points: FloatArray  # (N, 3)
    lane_id: str | None = None  # set for lanes
    junction_id: str | None = None  # set for connectors
    from_lane: str | None = None
    to_lane: str | None = None
    s: FloatArray = field(init=False)
    heading: FloatArray = field(init=False)
    grade: FloatArray = field(init=False)  # dz/ds

    def __post_init__(self) -> None:
        self.s = arc_length(self.points)
        self.heading = headings_rad(self.points)
        dz = np.diff(self.points[:, 2])
        ds = np.maximum(np.diff(self.s), 1e-9)
        g = dz / ds
        self.grade = np.concatenate([g, g[-1:]])

    @property
    def length_m(self) -> float:
        return float(self.s[-1])

    def position(self, s_m: float) -> FloatArray:
        s_m = min(max(s_m, 0.0), self.length_m)
        return np.array([np.interp(s_m, self.s, self.points[:, k]) for k in range(3)])

    def heading_at(self, s_m: float) -> float:
        i = int(np.clip(np.searchsorted(self.s, s_m, side="right") - 1, 0, len(self.s) - 1))
        return float(self.heading[i])

    def grade_at(self, s_m: float) -> float:
        i = int(np.clip(np.searchsorted(self.s, s_m, side="right") - 1, 0, len(self.s) - 1))
        return float(self.grade[i])

    def project(self, xy: FloatArray, s_hint_m: float, window_m: float) -> float:
        """Arc length of the point of this path nearest to `xy`, searched near `s_hint_m`."""
        lo = int(np.searchsorted(self.s, s_hint_m - window_m))
        hi = int(np.searchsorted(self.s, s_hint_m + window_m)) + 1
        lo, hi = max(lo - 1, 0), min(hi, len(self.s))
        a = self.points[lo : hi - 1, :2]
        b = self.points[lo + 1 : hi, :2]
        if len(a) == 0:
            return float(np.clip(s_hint_m, 0.0, self.length_m))
        ab = b - a
        t = np.clip(
            np.einsum("ij,ij->i", xy - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12), 0, 1
        )
        nearest = a + ab * t[:, None]
        k = int(np.argmin(np.einsum("ij,ij->i", nearest - xy, nearest - xy)))
        return float(self.s[lo + k] + t[k] * (self.s[lo + k + 1] - self.s[lo + k]))


def bezier_connector(p0: FloatArray, h0: float, p3: FloatArray, h3: float, step_m: float) -> FloatArray:
    """Cubic Bezier from p0 (heading h0) to p3 (heading h3), resampled every `step_m` (z linear)."""
    chord = float(np.hypot(*(p3[:2] - p0[:2])))
    turn = abs(math.remainder(h3 - h0, 2 * math.pi))
    # Tighter turns need longer handles to stay round (hairpins at the viaduct exit).
    handle = chord * (BEZIER_HANDLE_FRACTION + 0.25 * turn / math.pi)
    c0 = p0[:2]
    c1 = p0[:2] + handle * np.array([math.cos(h0), math.sin(h0)])
    c2 = p3[:2] - handle * np.array([math.cos(h3), math.sin(h3)])
    c3 = p3[:2]
    t = np.linspace(0.0, 1.0, BEZIER_SAMPLES)[:, None]
    xy = (1 - t) ** 3 * c0 + 3 * (1 - t) ** 2 * t * c1 + 3 * (1 - t) * t**2 * c2 + t**3 * c3
    z = np.linspace(p0[2], p3[2], BEZIER_SAMPLES)
    return resample(np.column_stack([xy, z]), step_m)


def connector_id(junction_id: str, from_lane: str, to_lane: str) -> str:
    return f"{junction_id}:{from_lane}>{to_lane}"


class RoadNetwork:
    """Lanes, connectors and the lane graph of one scene."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        step = scene.road.sample_step_m
        self.lanes: dict[str, Path] = {
            lane.id: Path(lane.id, np.asarray(scene.lane_centreline(lane.id)), lane_id=lane.id)
            for lane in scene.spec.lanes
        }
        self.connectors: dict[str, Path] = {}
        self.successors: dict[str, list[str]] = {lane_id: [] for lane_id in self.lanes}
        for junction in scene.spec.junctions:
            incoming = [lane for lane in scene.spec.lanes if lane.to_junction == junction.id]
            outgoing = [lane for lane in scene.spec.lanes if lane.from_junction == junction.id]
            for lin in incoming:
                for lout in outgoing:
                    if lin.reverse_lane == lout.id:
                        continue  # no U-turns
                    if lin.next_lanes is not None and lout.id not in lin.next_lanes:
                        continue  # a turn this crossing forbids
                    a, b = self.lanes[lin.id], self.lanes[lout.id]
                    pts = bezier_connector(
                        a.points[-1], float(a.heading[-1]), b.points[0], float(b.heading[0]), step
                    )
                    cid = connector_id(junction.id, lin.id, lout.id)
                    self.connectors[cid] = Path(
                        cid, pts, junction_id=junction.id, from_lane=lin.id, to_lane=lout.id
                    )
                    self.successors[lin.id].append(lout.id)
        self.graph = nx.DiGraph()
        for lane_id, path in self.lanes.items():
            self.graph.add_node(lane_id, length_m=path.length_m)
        for cid, conn in self.connectors.items():
            assert conn.from_lane is not None and conn.to_lane is not None
            # Edge weight: the connector plus the lane it leads onto; turn: the heading change through
            # the connector, rad in [0, pi] (a planner may cost turns: vehicles slow down for them).
            weight = conn.length_m + self.lanes[conn.to_lane].length_m
            a, b = self.lanes[conn.from_lane], self.lanes[conn.to_lane]
            turn_rad = abs((float(b.heading[0]) - float(a.heading[-1]) + math.pi) % (2 * math.pi) - math.pi)
            self.graph.add_edge(conn.from_lane, conn.to_lane, weight=weight, connector=cid, turn_rad=turn_rad)
        self._to_junction = {lane.id: lane.to_junction for lane in scene.spec.lanes}
        self._from_junction = {lane.id: lane.from_junction for lane in scene.spec.lanes}
        self._route_cache: dict[tuple[str, str], list[str]] = {}

    def path(self, path_id: str) -> Path:
        return self.lanes[path_id] if path_id in self.lanes else self.connectors[path_id]

    def connector(self, junction_id: str, from_lane: str, to_lane: str) -> Path:
        return self.connectors[connector_id(junction_id, from_lane, to_lane)]

    def lane_end_junction(self, lane_id: str) -> str:
        return self._to_junction[lane_id]

    def lane_start_junction(self, lane_id: str) -> str:
        return self._from_junction[lane_id]

    def shortest_route(self, from_lane: str, destination_junction: str, weight: str = "weight") -> list[str]:
        """Lanes after `from_lane` up to one ending at `destination_junction` (shortest distance).

        Empty when `from_lane` itself ends there."""
        if self._to_junction[from_lane] == destination_junction:
            return []
        key = (from_lane, destination_junction)
        if weight == "weight" and key in self._route_cache:
            return list(self._route_cache[key])
        lengths, paths = nx.single_source_dijkstra(self.graph, from_lane, weight=weight)
        best: list[str] | None = None
        best_len = math.inf
        for lane_id, length in lengths.items():
            if (
                lane_id != from_lane
                and self._to_junction[lane_id] == destination_junction
                and length < best_len
            ):
                best, best_len = paths[lane_id], length
        if best is None:
            raise ValueError(f"junction {destination_junction} is unreachable from lane {from_lane}")
        route = best[1:]
        if weight == "weight":
            self._route_cache[key] = route
        return list(route)

    def route_length_m(self, lanes: list[str]) -> float:
        total = 0.0
        for a, b in itertools.pairwise(lanes):
            total += self.graph.edges[a, b]["weight"]
        return total

    def is_valid_route(self, from_lane: str, lanes: list[str]) -> bool:
        prev = from_lane
        for lane_id in lanes:
            if lane_id not in self.successors.get(prev, []):
                return False
            prev = lane_id
        return True
