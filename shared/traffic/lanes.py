"""Which lane a vehicle is on, and which agents can see each lane.

A vehicle is matched to the nearest lane centreline sample, with height weighted up so a car on the
viaduct deck never matches the road underneath, and, when it moves, only among lanes whose direction
agrees with its velocity (the two lanes of a road lie one lane width apart). Units: metres, radians.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from shared.config import ConfigError
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import MapConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

OFF_LANE = -1
MAX_LANES_IN_REACH = 6  # lanes that can pass within lane_match_max_m of one point (junction mouths)


def lane_network(scene: Scene) -> RoadNetwork:
    """The road network the coordinator maps and plans on. A scene without a lane map (a site that runs
    perception only) has nothing to map or plan on: a ConfigError naming the scene, not an error from
    deep inside the network or the lane index."""
    if not scene.spec.lanes or scene.spec.road is None:
        where = f" ({scene.source})" if scene.source is not None else ""
        raise ConfigError(
            f"scene {scene.scene_id}{where} has no lane map: the coordinator needs one (lanes, junctions and "
            "a road block) for its per-lane traffic maps and its routes"
        )
    return RoadNetwork(scene)


class LaneLocator:
    """Lane index (into `lane_ids`) of world positions; `OFF_LANE` when no lane is near enough."""

    def __init__(self, network: RoadNetwork, cfg: MapConfig) -> None:
        self.cfg = cfg
        self.lane_ids: list[str] = sorted(network.lanes)
        points, owner, heading = [], [], []
        for k, lane_id in enumerate(self.lane_ids):
            path = network.lanes[lane_id]
            points.append(path.points)
            owner.append(np.full(len(path.points), k))
            heading.append(path.heading)
        self._points = np.concatenate(points)
        self._owner = np.concatenate(owner)
        self._heading = np.concatenate(heading)
        self._scale = np.array([1.0, 1.0, cfg.lane_level_weight])
        self._tree = cKDTree(self._points * self._scale)
        # Candidates per query: every sample within reach of up to MAX_LANES_IN_REACH lanes (a lane
        # passes about 2 * reach / step samples), so the farther lane of a two-lane road is among them.
        step_m = float(
            np.median(np.linalg.norm(np.diff(network.lanes[self.lane_ids[0]].points, axis=0), axis=1))
        )
        per_lane = int(np.ceil(2 * cfg.lane_match_max_m / step_m)) + 1
        self._k = min(len(self._points), MAX_LANES_IN_REACH * per_lane)
        self.lengths_m = np.array([network.lanes[lane].length_m for lane in self.lane_ids])

    def locate(self, position_m: FloatArray, velocity_mps: FloatArray) -> IntArray:
        """(N,) lane indices for (N, 3) positions and (N, 2+) velocities."""
        n = len(position_m)
        out = np.full(n, OFF_LANE, dtype=np.int64)
        if n == 0:
            return out
        scaled = np.asarray(position_m, float) * self._scale
        dist, idx = self._tree.query(scaled, k=self._k, distance_upper_bound=self.cfg.lane_match_max_m)
        dist, idx = dist.reshape(n, self._k), idx.reshape(n, self._k)
        ok = np.isfinite(dist)  # misses come back as inf with index == number of samples
        idx = np.where(ok, idx, 0)
        speed = np.hypot(velocity_mps[:, 0], velocity_mps[:, 1])
        course = np.arctan2(velocity_mps[:, 1], velocity_mps[:, 0])
        moving = speed >= self.cfg.min_speed_for_heading_mps
        delta = np.abs(np.remainder(self._heading[idx] - course[:, None] + np.pi, 2 * np.pi) - np.pi)
        ok &= ~moving[:, None] | (delta <= self.cfg.heading_gate_rad)
        first = np.argmax(ok, axis=1)  # results are sorted by distance: the nearest agreeing sample
        found = ok[np.arange(n), first]
        out[found] = self._owner[idx[found, first[found]]]
        return out


def lane_agents(scene: Scene, network: RoadNetwork, min_fraction: float = 0.0) -> dict[str, list[str]]:
    """Agents whose areas hold more than `min_fraction` of each lane's centreline samples."""
    area_agent: dict[str, list[str]] = defaultdict(list)
    for agent in scene.spec.agents:
        for area in agent.areas:
            area_agent[area].append(agent.id)
    lane_ids = list(network.lanes)
    sizes = [len(network.lanes[lane].points) for lane in lane_ids]
    # Every lane's samples at once (one vectorised lookup per area, not one per point).
    area_index = scene.area_indices(np.concatenate([network.lanes[lane].points for lane in lane_ids]))
    out: dict[str, list[str]] = {}
    for lane_id, n, idx in zip(lane_ids, sizes, np.split(area_index, np.cumsum(sizes)[:-1]), strict=True):
        counts: dict[str, int] = defaultdict(int)
        areas, hits = np.unique(idx[idx >= 0], return_counts=True)
        for k, c in zip(areas, hits, strict=True):
            for agent_id in area_agent.get(scene.spec.areas[k].id, []):
                counts[agent_id] += int(c)
        out[lane_id] = sorted(a for a, c in counts.items() if c > min_fraction * n)
    return out
