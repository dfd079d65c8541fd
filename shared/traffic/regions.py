"""Regions of a road network, one coordinator shard each (issue 37), and routes across them.

Partition (`partition_junctions`): the junction graph (a node per junction, an edge per road, weighted
by its lanes) is cut by recursive Kernighan-Lin bisection (networkx), always the largest region next,
until there are `regions`: balanced halves with few roads cut. The result is configuration
(`RegionMap.save` / `load`), so a deployment pins its shard map.

A lane belongs to the region of its end junction: the vehicle on it decides there next, so that
region's shard owns it. Lanes whose two junctions are in different regions are *crossing lanes*; a
vehicle driving one is being handed over.

Routes across regions (`Overlay`, Customizable Route Planning on the lane graph: Delling et al. 2011,
`docs/references.md` \"SUMO\" (7)): each region publishes, for every crossing lane that enters it
and every one that leaves it, the fastest time between them inside the region (its *clique*) and the
lanes of that path. A route from a lane to a junction in another region is the fastest path over the
crossing lanes and the cliques, with the source region's own lanes at the start and the destination
region's at the end; turns are the lane graph's, so the overlay's times equal the whole graph's.
Times in seconds; `lane_time_s[k]` is the time to drive lane k (sorted lane ids) and its connector.
"""

from __future__ import annotations

import itertools
import json
import math
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from shared.scene.road_network import RoadNetwork

FloatArray = NDArray[np.float64]
#: The overlay's sink: "arrived at the destination junction" (next hop of a crossing lane's last leg).
SINK = -1
#: Cliques objects whose overlay searches are kept (least recently used dropped): a live shard has one
#: at a time, the lock-step study one per shard per step.
CLIQUE_CACHE = 32


def connector_times_s(
    network: RoadNetwork, edges: list[tuple[str, str]], turn_penalty_s: float = 0.0
) -> FloatArray:
    """Per lane-graph edge (a, b): the time to drive the junction's connector from a onto b at b's speed
    limit, plus `turn_penalty_s` per right angle of heading change (a vehicle slows down to turn: without
    it, routes through a grid zig-zag between equally long paths; one home for the planner and the
    overlay alike)."""
    out = np.empty(len(edges))
    for k, (a, b) in enumerate(edges):
        edge = network.graph.edges[a, b]
        connector_m = edge["weight"] - network.lanes[b].length_m
        out[k] = connector_m / network.scene.lanes[b].speed_limit_mps + turn_penalty_s * edge["turn_rad"] / (
            math.pi / 2
        )
    return out


def partition_junctions(network: RoadNetwork, regions: int, seed: int = 0) -> dict[str, int]:
    """Junction -> region 0..regions-1: recursive Kernighan-Lin bisection of the largest region."""
    junctions = sorted({network.lane_start_junction(lane) for lane in network.lanes} | {
        network.lane_end_junction(lane) for lane in network.lanes})  # fmt: skip
    if not 1 <= regions <= len(junctions):
        raise ValueError(f"regions must be within 1..{len(junctions)} junctions, got {regions}")
    graph = nx.Graph()
    graph.add_nodes_from(junctions)
    for lane in network.lanes:
        a, b = network.lane_start_junction(lane), network.lane_end_junction(lane)
        if a != b:
            weight = graph.get_edge_data(a, b, {"weight": 0})["weight"]
            graph.add_edge(a, b, weight=weight + 1)
    parts: list[set[str]] = [set(junctions)]
    while len(parts) < regions:
        largest = max(range(len(parts)), key=lambda k: (len(parts[k]), -k))
        part = parts.pop(largest)
        first, second = nx.community.kernighan_lin_bisection(graph.subgraph(part), weight="weight", seed=seed)
        parts[largest:largest] = [set(first), set(second)]
    # Regions numbered by their smallest junction id: the same cut always gets the same numbers.
    parts.sort(key=min)
    return {j: k for k, part in enumerate(parts) for j in part}


@dataclass(frozen=True)
class RegionMap:
    """Which shard owns what: junction -> region (lanes follow their end junction)."""

    region_of_junction: Mapping[str, int]

    @property
    def regions(self) -> int:
        return max(self.region_of_junction.values()) + 1

    def lane_region(self, network: RoadNetwork, lane: str) -> int:
        return self.region_of_junction[network.lane_end_junction(lane)]

    def crossing_lanes(self, network: RoadNetwork) -> list[str]:
        """Lanes from a junction of one region to a junction of another (sorted)."""
        r = self.region_of_junction
        return sorted(
            lane
            for lane in network.lanes
            if r[network.lane_start_junction(lane)] != r[network.lane_end_junction(lane)]
        )

    def save(self, path: Path) -> None:
        path.write_text(
            json.dumps({"regions": dict(sorted(self.region_of_junction.items()))}, indent=1) + "\n"
        )

    @classmethod
    def load(cls, path: Path, network: RoadNetwork | None = None) -> RegionMap:
        """The map of `path`; with `network`, every junction of it must have a region (ValueError)."""
        data = json.loads(path.read_text())
        regions = {str(j): int(k) for j, k in data["regions"].items()}
        if network is not None:
            junctions = {network.lane_end_junction(lane) for lane in network.lanes}
            missing = sorted(junctions - set(regions))
            if missing:
                raise ValueError(f"{path}: junctions without a region: {missing[:5]}")
        if sorted(set(regions.values())) != list(range(len(set(regions.values())))):
            raise ValueError(f"{path}: regions must be numbered 0..n-1")
        return cls(regions)


@dataclass(frozen=True)
class Clique:
    """One region's published crossing times, inside the region, inf where there is no way: `time_s[i,
    j]` from entering lane `entering[i]` (driven) to leaving lane `leaving[j]` (driven), `paths[(a, b)]`
    the lanes strictly between; `to_junction_s[i, k]` from `entering[i]` to a lane ending at junction
    `junctions[k]`, `junction_paths[(a, junction)]` the lanes after `a` up to that lane."""

    region: int
    entering: list[str]
    leaving: list[str]
    time_s: FloatArray
    paths: dict[tuple[str, str], list[str]]
    junctions: list[str]
    to_junction_s: FloatArray
    junction_paths: dict[tuple[str, str], list[str]]


class Overlay:
    """The lane graph split by a `RegionMap`; per-region searches and the overlay route across them."""

    def __init__(self, network: RoadNetwork, regions: RegionMap, turn_penalty_s: float = 0.0) -> None:
        """`turn_penalty_s`: the planner's (`PlannerConfig.turn_penalty_s`); every shard must use the same."""
        self.net = network
        self.regions = regions
        self.lane_ids = sorted(network.lanes)
        self.index = {lane: k for k, lane in enumerate(self.lane_ids)}
        self.lane_region = np.array([regions.lane_region(network, lane) for lane in self.lane_ids])
        self.start_region = np.array(
            [regions.region_of_junction[network.lane_start_junction(lane)] for lane in self.lane_ids]
        )
        self.crossing = regions.crossing_lanes(network)
        edges = list(network.graph.edges)
        self._src = np.array([self.index[a] for a, _ in edges], dtype=np.int64)
        self._dst = np.array([self.index[b] for _, b in edges], dtype=np.int64)
        free_mps = np.array([network.scene.lanes[lane].speed_limit_mps for lane in self.lane_ids])
        self.length_m = np.array([network.lanes[lane].length_m for lane in self.lane_ids])
        #: Each lane's time at its speed limit: the floor of a clique, and a silent region's prior.
        self.free_time_s = self.length_m / free_mps
        # Driving a junction's connector onto lane b, as the planner costs it.
        self._connector_s = connector_times_s(network, edges, turn_penalty_s)
        self._edge = {(a, b): k for k, (a, b) in enumerate(edges)}
        self._graphs: dict[int | None, tuple[csr_matrix, NDArray[np.int64]]] = {}
        self._free_cliques: dict[int, Clique] | None = None
        self.crossing_index = {c: k for k, c in enumerate(self.crossing)}
        self._leaving: dict[int, list[str]] = {r: [] for r in range(regions.regions)}
        for c in self.crossing:
            self._leaving[int(self.start_region[self.index[c]])].append(c)
        # Searches that depend only on the published cliques, per cliques object (one map update serves
        # many plans); the latest CLIQUE_CACHE objects are kept (shards sharing an overlay each have one).
        self._by_cliques: OrderedDict[int, _CliqueSearches] = OrderedDict()
        self.end_junction = [network.lane_end_junction(lane) for lane in self.lane_ids]
        self._ends: dict[str, list[int]] = {}
        for k, junction in enumerate(self.end_junction):
            self._ends.setdefault(junction, []).append(k)

    def _graph(self, lane_time_s: FloatArray, region: int | None) -> csr_matrix:
        """The lane graph with edge a->b costing its connector and lane b's time; only edges inside
        `region` (both lanes owned by it, or a crossing lane leaving it as the last step) when given.
        Each region's matrix is built once; its costs are rewritten in place per call."""
        if region not in self._graphs:
            keep = np.flatnonzero(
                np.ones(len(self._src), bool)
                if region is None
                else (self.lane_region[self._src] == region)
                & ((self.lane_region[self._dst] == region) | (self.start_region[self._dst] == region))
            )
            n = len(self.lane_ids)
            # Data = edge number + 1 while building, so each stored slot maps back to its edge.
            graph = csr_matrix((keep + 1.0, (self._src[keep], self._dst[keep])), shape=(n, n))
            self._graphs[region] = (graph, graph.data.astype(np.int64) - 1)
        graph, edge = self._graphs[region]
        # A zero cost would vanish from the sparse matrix: lanes take at least a microsecond.
        graph.data[:] = np.maximum(self._connector_s[edge] + lane_time_s[self._dst[edge]], 1e-6)
        return graph

    def clique_problem(
        self,
        clique: Clique,
        free_time_s: FloatArray,
        slack: float = 0.99,
        slowest_time_s: FloatArray | None = None,
    ) -> str | None:
        """Why a clique received from another shard cannot be used (a counter name), or None. Its region
        must exist; its lanes, junctions and matrix shapes must be the region's; every time a number
        >= 0 (inf: no way); every finite time needs a path of the region's own lanes that the lane graph
        connects, to the right lane or junction, and no faster than that path at free flow (`slack` of
        it, for rounding): a forged clique can neither route through lanes that do not join nor
        promise a region faster than its speed limits to draw traffic into it. No way (inf) exactly where
        the region has none at free flow (a region's lanes are never closed on the maps: a clique of all
        inf would shut it); with `slowest_time_s` (each lane's slowest time a genuine map can give), no
        finite time slower than its path at those times (`clique_too_slow`: pushing traffic out)."""
        r = clique.region
        if not 0 <= r < self.regions.regions:
            return "clique_region"
        junctions = sorted(j for j, k in self.regions.region_of_junction.items() if k == r)
        entering = [c for c in self.crossing if self.lane_region[self.index[c]] == r]
        if clique.entering != entering or clique.leaving != self._leaving[r] or clique.junctions != junctions:
            return "clique_lanes"
        if clique.time_s.shape != (len(entering), len(clique.leaving)) or clique.to_junction_s.shape != (
            len(entering),
            len(junctions),
        ):
            return "clique_shape"
        for times in (clique.time_s, clique.to_junction_s):
            if np.isnan(times).any() or (times < 0).any():
                return "clique_time"
        prior = self.free_flow_cliques()[r]
        if (np.isinf(clique.time_s) != np.isinf(prior.time_s)).any() or (
            np.isinf(clique.to_junction_s) != np.isinf(prior.to_junction_s)
        ).any():
            return "clique_no_way"
        for i, a in enumerate(entering):
            for j, b in enumerate(clique.leaving):
                if np.isfinite(clique.time_s[i, j]):
                    problem = self._path_problem(a, clique.paths.get((a, b)), b, None, r)
                    if problem is None:
                        problem = self._time_problem(
                            clique.time_s[i, j],
                            a,
                            [*clique.paths[(a, b)], b],
                            free_time_s,
                            slowest_time_s,
                            slack,
                        )
                    if problem:
                        return problem
            for k, junction in enumerate(junctions):
                if np.isfinite(clique.to_junction_s[i, k]):
                    path = clique.junction_paths.get((a, junction))
                    problem = self._path_problem(a, path, None, junction, r)
                    if problem is None and path:
                        problem = self._time_problem(
                            clique.to_junction_s[i, k], a, path, free_time_s, slowest_time_s, slack
                        )
                    if problem:
                        return problem
        return None

    def _time_problem(
        self,
        time_s: float,
        start: str,
        path: list[str],
        free_time_s: FloatArray,
        slowest_time_s: FloatArray | None,
        slack: float,
    ) -> str | None:
        if time_s < slack * self.route_time_s(start, path, free_time_s):
            return "clique_too_fast"
        if slowest_time_s is not None and time_s * slack > self.route_time_s(start, path, slowest_time_s):
            return "clique_too_slow"
        return None

    def _path_problem(
        self, start: str, path: list[str] | None, last: str | None, junction: str | None, region: int
    ) -> str | None:
        """`start`, `path`, then `last` (a lane) must be connected lanes, the path's own lanes in `region`;
        with `junction`, the route must end at it."""
        if path is None:
            return "clique_path"
        lanes = [*path, last] if last is not None else list(path)
        if any(lane not in self.index for lane in lanes):
            return "clique_path"
        if any(self.lane_region[self.index[lane]] != region for lane in path):
            return "clique_path"
        if not self.net.is_valid_route(start, lanes):
            return "clique_path"
        end = lanes[-1] if lanes else start
        if junction is not None and self.net.lane_end_junction(end) != junction:
            return "clique_path"
        return None

    def route_time_s(self, from_lane: str, lanes: list[str], lane_time_s: FloatArray) -> float:
        """Time of `lanes` after `from_lane`: each connector and lane, as the overlay costs them."""
        total = 0.0
        for a, b in itertools.pairwise([from_lane, *lanes]):
            total += self._connector_s[self._edge[(a, b)]] + lane_time_s[self.index[b]]
        return float(total)

    def free_flow_cliques(self) -> dict[int, Clique]:
        """Every region's clique at free flow (a silent region's prior, the free-flow shortest routes'
        overlay), made once. The same object on every call, so the searches cached per cliques object are
        shared: do not modify it."""
        if self._free_cliques is None:
            self._free_cliques = {r: self.clique(r, self.free_time_s) for r in range(self.regions.regions)}
        return self._free_cliques

    def clique(self, region: int, lane_time_s: FloatArray) -> Clique:
        """Region `region`'s crossing times on `lane_time_s` (what its shard publishes)."""
        entering = [c for c in self.crossing if self.lane_region[self.index[c]] == region]
        leaving = [c for c in self.crossing if self.start_region[self.index[c]] == region]
        junctions = sorted(j for j, r in self.regions.region_of_junction.items() if r == region)
        times = np.full((len(entering), len(leaving)), np.inf)
        to_junction = np.full((len(entering), len(junctions)), np.inf)
        paths: dict[tuple[str, str], list[str]] = {}
        junction_paths: dict[tuple[str, str], list[str]] = {}
        if entering:
            graph = self._graph(lane_time_s, region)
            dist, pred = dijkstra(graph, indices=[self.index[c] for c in entering], return_predecessors=True)
            for i, a in enumerate(entering):
                for j, b in enumerate(leaving):
                    t = dist[i, self.index[b]]
                    if np.isfinite(t) and a != b:
                        times[i, j] = t
                        paths[(a, b)] = self._walk(pred[i], self.index[a], self.index[b])[1:-1]
                for k, junction in enumerate(junctions):
                    leg = self._to_junction(dist[i], pred[i], self.index[a], junction)
                    if leg is not None:
                        to_junction[i, k], junction_paths[(a, junction)] = leg
        return Clique(region, entering, leaving, times, paths, junctions, to_junction, junction_paths)

    def _to_junction(
        self, dist: FloatArray, pred: NDArray[np.int64], source: int, junction: str
    ) -> tuple[float, list[str]] | None:
        """From lane `source` (searched: `dist`, `pred`) to the nearest lane ending at `junction`: its
        time and the lanes after `source` (none when `source` itself ends there); None if unreachable."""
        if self.end_junction[source] == junction:
            return 0.0, []
        # A junction where lanes only begin (a real net's entry, Pasubio's `1-begin`) ends none.
        ends = [k for k in self._ends.get(junction, ()) if k != source and np.isfinite(dist[k])]
        if not ends:
            return None
        best = min(ends, key=lambda k: dist[k])
        return float(dist[best]), self._walk(pred, source, best)[1:]

    def _walk(self, pred: NDArray[np.int64], source: int, target: int) -> list[str]:
        out = [target]
        while out[-1] != source:
            out.append(int(pred[out[-1]]))
        return [self.lane_ids[k] for k in reversed(out)]

    def route(
        self, from_lane: str, destination: str, lane_time_s: FloatArray, cliques: Mapping[int, Clique]
    ) -> list[str]:
        """Lanes after `from_lane` to one ending at junction `destination`, fastest over the overlay:
        the source region's lanes (timed by `lane_time_s`: a shard knows its own lanes) to a leaving
        crossing lane, then every region's clique (`cliques`, the source region's own included): its
        crossing times and, in the destination's region, its times to the destination. A region
        without a clique is not crossed. ValueError when unreachable. The overlay's times to each
        destination are computed once per `cliques` object (one map update serves many plans)."""
        src_region = int(self.lane_region[self.index[from_lane]])
        source = self.index[from_lane]
        dist, pred = dijkstra(self._graph(lane_time_s, src_region), indices=source, return_predecessors=True)
        best_s, best_leg, best_node = math.inf, None, -1
        if self.regions.region_of_junction[destination] == src_region:  # it may stay inside
            inside = self._to_junction(dist, pred, source, destination)
            if inside is not None and inside[1]:
                best_s, best_leg = inside
        to_sink, next_hop, last_legs = self._to_destination(destination, cliques)
        for c in self._leaving[src_region]:
            k = self.crossing_index[c]
            t = dist[self.index[c]] + to_sink[k]
            if t < best_s:
                best_s, best_node = t, k
        if not np.isfinite(best_s):
            raise ValueError(f"junction {destination} is unreachable from lane {from_lane}")
        if best_node < 0:
            assert best_leg is not None
            return best_leg
        lanes = self._walk(pred, source, self.index[self.crossing[best_node]])[1:]
        k, crossing_legs = best_node, self._searches(cliques).legs
        while k != SINK:
            nxt = int(next_hop[k])
            lanes += (last_legs if nxt == SINK else crossing_legs)[(k, nxt)]
            k = nxt
        return lanes

    def _to_destination(
        self, destination: str, cliques: Mapping[int, Clique]
    ) -> tuple[FloatArray, NDArray[np.int64], dict[tuple[int, int], list[str]]]:
        """Over the cliques: from each crossing lane (driven) to a lane ending at `destination`, the
        time, the next overlay node (a crossing lane's index, or SINK) and the last legs' lanes (the
        others are the searches' `legs`)."""
        searches = self._searches(cliques)
        if destination in searches.to_sink:
            return searches.to_sink[destination]
        n = len(self.crossing)
        rows, cols, cost = [searches.rows], [searches.cols], [searches.cost]
        legs: dict[tuple[int, int], list[str]] = {}  # the last legs, into the sink
        end = cliques.get(self.regions.region_of_junction[destination])
        if end is not None and destination in end.junctions:
            j = end.junctions.index(destination)
            finite = [i for i in range(len(end.entering)) if np.isfinite(end.to_junction_s[i, j])]
            rows.append(np.array([self.crossing_index[end.entering[i]] for i in finite], dtype=np.int64))
            cols.append(np.full(len(finite), n, dtype=np.int64))
            cost.append(np.maximum(end.to_junction_s[finite, j], 1e-6))
            for i in finite:
                legs[(self.crossing_index[end.entering[i]], SINK)] = end.junction_paths[
                    (end.entering[i], destination)
                ]
        # Backwards from the sink (node n): each node's time to it and its next hop toward it.
        reverse = csr_matrix(
            (np.concatenate(cost), (np.concatenate(cols), np.concatenate(rows))), shape=(n + 1, n + 1)
        )
        to_sink, pred = dijkstra(reverse, indices=n, return_predecessors=True)
        next_hop = np.where(pred == n, SINK, pred).astype(np.int64)
        result = (to_sink[:n], next_hop[:n], legs)
        searches.to_sink[destination] = result
        return result

    def _searches(self, cliques: Mapping[int, Clique]) -> _CliqueSearches:
        """The overlay's edges between crossing lanes from `cliques`, and the sink searches made on them
        (cached per cliques object)."""
        found = self._by_cliques.get(id(cliques))
        if found is not None and found.cliques is cliques:
            self._by_cliques.move_to_end(id(cliques))
            return found
        rows: list[int] = []
        cols: list[int] = []
        cost: list[float] = []
        legs: dict[tuple[int, int], list[str]] = {}
        for clique in cliques.values():
            for i, j in zip(*np.nonzero(np.isfinite(clique.time_s)), strict=True):
                a, b = clique.entering[i], clique.leaving[j]
                ka, kb = self.crossing_index[a], self.crossing_index[b]
                rows.append(ka)
                cols.append(kb)
                cost.append(max(float(clique.time_s[i, j]), 1e-6))  # a zero would vanish
                legs[(ka, kb)] = [*clique.paths[(a, b)], b]
        searches = _CliqueSearches(
            cliques,
            np.array(rows, dtype=np.int64),
            np.array(cols, dtype=np.int64),
            np.array(cost, dtype=float),
            legs,
        )
        self._by_cliques[id(cliques)] = searches
        while len(self._by_cliques) > CLIQUE_CACHE:
            self._by_cliques.popitem(last=False)
        return searches


@dataclass
class _CliqueSearches:
    """What `Overlay` derives from one cliques object: the crossing-lane edges (node indices, seconds,
    the legs' lanes) and each destination's sink search. Holds `cliques` so its id stays unique."""

    cliques: Mapping[int, Clique]
    rows: NDArray[np.int64]
    cols: NDArray[np.int64]
    cost: FloatArray
    legs: dict[tuple[int, int], list[str]]
    to_sink: dict[str, tuple[FloatArray, NDArray[np.int64], dict[tuple[int, int], list[str]]]] = field(
        default_factory=dict
    )


def agent_regions(
    agents: Mapping[str, list[str]], network: RoadNetwork, regions: RegionMap
) -> dict[str, int]:
    """Agent -> the region owning most of the lanes it covers (`agents`: lane -> its agents, as
    `shared.traffic.lanes.lane_agents` gives), ties to the lower region; an agent covering no lane is
    left out."""
    votes: dict[str, list[int]] = {}
    for lane, lane_agents in agents.items():
        for agent in lane_agents:
            votes.setdefault(agent, []).append(regions.lane_region(network, lane))
    return {a: int(np.bincount(v).argmax()) for a, v in votes.items()}
