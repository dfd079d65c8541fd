"""Merged vehicle density and speed maps from the agents' object lists.

    agents' objects (world frame) --merge_agents--> one list of vehicles (cross-agent duplicates fused)
      --TrafficMapBuilder.update--> per-lane / per-area / per-cell counts and speeds, smoothed in time

Smoothing is exponential with time constant tau: x += (1 - exp(-dt / tau)) (sample - x), so the result
does not depend on the update rate. A speed is averaged only from samples (an empty lane has no speed,
not speed 0) and turns invalid when no sample came for `speed_valid_s`. Lanes seen by no live agent are
marked unobserved: their count is unknown, not zero. Planners read an unobserved lane's count from a
prior (`TrafficSnapshot.lane_count_expected`): the observed lanes' mean density (vehicles per metre,
the last one seen when nothing is observed) times its length; an area no live agent covers is ranked
by the same prior. Units: metres, seconds, m/s.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import MapConfig
from shared.traffic.lanes import OFF_LANE, LaneLocator, lane_agents

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

UNMATCHED_COST = 1e6  # assignment cost of pairs outside the gate (never accepted)


@dataclass
class AgentObjects:
    """One agent's latest objects in the world frame."""

    agent_id: str
    position_m: FloatArray  # (N, 3) road-contact point (box bottom centre): lanes lie on the road
    velocity_mps: FloatArray  # (N, 3)
    position_var_m2: FloatArray  # (N,) mean per-axis position variance (weights the merge)

    @classmethod
    def empty(cls, agent_id: str) -> AgentObjects:
        return cls(agent_id, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.position_m)


@dataclass
class Vehicles:
    """Merged vehicles: one row per physical vehicle, with the agents that saw it."""

    position_m: FloatArray
    velocity_mps: FloatArray
    position_var_m2: FloatArray
    agents: list[tuple[str, ...]] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.position_m)


def merge_agents(objects: Sequence[AgentObjects], gate_m: float, level_m: float) -> Vehicles:
    """Fuse objects that two agents both report (overlapping coverage) into one vehicle.

    Agents are folded in one at a time: Hungarian assignment on xy distance between the vehicles so
    far and the next agent's objects, pairs within `gate_m` (and `level_m` in z) fused by inverse
    variance, the rest appended. Objects of one agent are never merged with each other (its tracker
    already keeps them apart)."""
    pos = np.zeros((0, 3))
    vel = np.zeros((0, 3))
    var = np.zeros(0)
    agents: list[tuple[str, ...]] = []
    for obj in objects:
        if len(obj) == 0:
            continue
        if len(pos) == 0:
            pos, vel, var = obj.position_m.copy(), obj.velocity_mps.copy(), obj.position_var_m2.copy()
            agents = [(obj.agent_id,)] * len(obj)
            continue
        dxy = np.linalg.norm(pos[:, None, :2] - obj.position_m[None, :, :2], axis=2)
        dz = np.abs(pos[:, None, 2] - obj.position_m[None, :, 2])
        ok = (dxy <= gate_m) & (dz <= level_m)
        rows, cols = linear_sum_assignment(np.where(ok, dxy, UNMATCHED_COST))
        keep = ok[rows, cols]
        rows, cols = rows[keep], cols[keep]
        w_old = 1.0 / np.maximum(var[rows], 1e-12)
        w_new = 1.0 / np.maximum(obj.position_var_m2[cols], 1e-12)
        total = w_old + w_new
        pos[rows] = (pos[rows] * w_old[:, None] + obj.position_m[cols] * w_new[:, None]) / total[:, None]
        vel[rows] = (vel[rows] * w_old[:, None] + obj.velocity_mps[cols] * w_new[:, None]) / total[:, None]
        var[rows] = 1.0 / total
        for r in rows:
            agents[r] = (*agents[r], obj.agent_id)
        new = np.setdiff1d(np.arange(len(obj)), cols)
        pos = np.vstack([pos, obj.position_m[new]])
        vel = np.vstack([vel, obj.velocity_mps[new]])
        var = np.concatenate([var, obj.position_var_m2[new]])
        agents += [(obj.agent_id,)] * len(new)
    return Vehicles(pos, vel, var, agents)


class _Smoothed:
    """Exponentially smoothed counts (always sampled) and speeds (sampled where vehicles are)."""

    def __init__(self, size: int) -> None:
        self.count = np.zeros(size)
        self.speed = np.zeros(size)
        self.speed_seen_s = np.full(size, -math.inf)
        self.samples = np.zeros(size, dtype=np.int64)

    def update(self, gain: float, count: NDArray[Any], speed_sum: NDArray[Any], t_s: float) -> None:
        count = np.asarray(count, float)
        speed_sum = np.asarray(speed_sum, float)
        self.count += gain * (count - self.count)
        has = count > 0
        mean = np.divide(speed_sum, count, out=np.zeros_like(speed_sum), where=has)
        fresh = has & ~np.isfinite(self.speed_seen_s)
        self.speed[fresh] = mean[fresh]  # first sample: no prior to smooth against
        upd = has & ~fresh
        self.speed[upd] += gain * (mean[upd] - self.speed[upd])
        self.speed_seen_s[has] = t_s
        self.samples += count.astype(np.int64)

    def valid(self, t_s: float, valid_s: float) -> BoolArray:
        return np.asarray(t_s - self.speed_seen_s <= valid_s)


@dataclass(frozen=True)
class TrafficSnapshot:
    """The maps at one instant. Lane arrays follow `lane_ids`, area arrays `area_ids`."""

    t_s: float
    lane_ids: list[str]
    lane_count: FloatArray  # vehicles on the lane now (unobserved lanes: 0, see lane_observed)
    lane_count_smoothed: FloatArray
    lane_length_m: FloatArray
    lane_speed_mps: FloatArray
    lane_speed_valid: BoolArray
    lane_observed: BoolArray  # covered by at least one live agent
    prior_density_per_m: float  # vehicles per metre of observed lane (the prior of unobserved ones)
    area_ids: list[str]
    area_count: FloatArray
    area_count_smoothed: FloatArray
    area_speed_mps: FloatArray
    area_speed_valid: BoolArray
    area_observed: BoolArray  # one of a live agent's areas
    area_rank: NDArray[np.int64]  # 0 = least crowded (the paper's rank; unobserved areas at the prior)
    grid_origin_m: tuple[float, float]
    grid_cell_m: float
    grid_shape: tuple[int, int]  # rows (y), columns (x)
    grid_count: FloatArray  # (rows, cols) smoothed
    grid_speed_mps: FloatArray  # (rows, cols) smoothed, 0 where never sampled
    grid_samples: NDArray[np.int64]
    vehicle_lane: NDArray[np.int64]  # lane index per merged vehicle (OFF_LANE if none)

    def lane_index(self, lane_id: str) -> int:
        return self.lane_ids.index(lane_id)

    @property
    def lane_count_expected(self) -> FloatArray:
        """(L,) vehicles per lane: counted where observed, the density prior elsewhere."""
        return np.where(self.lane_observed, self.lane_count, self.prior_density_per_m * self.lane_length_m)


def area_ranks(counts: FloatArray) -> NDArray[np.int64]:
    """Rank of each area by count, 0 = emptiest; equal counts keep file order (stable sort)."""
    order = np.argsort(counts, kind="stable")
    ranks = np.empty(len(counts), dtype=np.int64)
    ranks[order] = np.arange(len(counts))
    return ranks


class TrafficMapBuilder:
    """Keeps the smoothed maps; `update()` folds in one merged vehicle list."""

    def __init__(self, scene: Scene, network: RoadNetwork, cfg: MapConfig) -> None:
        self.scene = scene
        self.cfg = cfg
        self.locator = LaneLocator(network, cfg)
        self.lane_ids = self.locator.lane_ids
        self.lane_agents = lane_agents(scene, network)
        self.area_ids = [a.id for a in scene.spec.areas]
        self.area_lane_length_m = np.array(
            [
                sum(
                    float(ln)
                    for ln, lane in zip(self.locator.lengths_m, self.lane_ids, strict=True)
                    if scene.lanes[lane].area == area
                )
                for area in self.area_ids
            ]
        )
        self._density_per_m = 0.0  # the prior: last observed mean density
        self.grid = scene.table_grid(cfg.grid_cell_m)
        self.grid_origin_m, self.grid_shape = self.grid.origin_m, self.grid.shape
        self._lanes = _Smoothed(len(self.lane_ids))
        self._areas = _Smoothed(len(self.area_ids))
        self._grid = _Smoothed(self.grid.size)
        self._last_t_s: float | None = None

    def lane_observed(self, live_agents: Collection[str] | None) -> BoolArray:
        """Lanes some live agent covers; `None` means everything is observed (ground truth)."""
        if live_agents is None:
            return np.ones(len(self.lane_ids), dtype=bool)
        return np.array([any(a in live_agents for a in self.lane_agents[lane]) for lane in self.lane_ids])

    def area_observed(self, live_agents: Collection[str] | None) -> BoolArray:
        """Areas one of whose agents is live; `None`: all (ground truth)."""
        if live_agents is None:
            return np.ones(len(self.area_ids), dtype=bool)
        covered = {area for a in live_agents if a in self.scene.agents for area in self.scene.agents[a].areas}
        return np.array([area in covered for area in self.area_ids])

    def cells(self, position_m: FloatArray) -> NDArray[np.int64]:
        """Flat grid index per position; -1 outside the table."""
        return self.grid.cells(position_m)

    def update(self, vehicles: Vehicles, t_s: float, live_agents: Collection[str] | None) -> TrafficSnapshot:
        """Fold in the merged vehicles of time `t_s`; `live_agents` decide which lanes are observed."""
        gain = (
            1.0
            if self._last_t_s is None
            else 1.0 - math.exp(-max(t_s - self._last_t_s, 0.0) / self.cfg.smoothing_time_constant_s)
        )
        self._last_t_s = t_s
        speed = np.hypot(vehicles.velocity_mps[:, 0], vehicles.velocity_mps[:, 1])
        lane = self.locator.locate(vehicles.position_m, vehicles.velocity_mps)
        on = lane != OFF_LANE
        lane_count = np.bincount(lane[on], minlength=len(self.lane_ids)).astype(float)
        lane_speed = np.bincount(lane[on], weights=speed[on], minlength=len(self.lane_ids))
        observed = self.lane_observed(live_agents)
        # An unobserved lane keeps its last smoothed state instead of decaying toward a false zero.
        prev_count = self._lanes.count.copy()
        self._lanes.update(gain, lane_count, lane_speed, t_s)
        self._lanes.count[~observed] = prev_count[~observed]

        area_idx = self.scene.area_indices(vehicles.position_m)
        has_area = area_idx >= 0
        area_count = np.bincount(area_idx[has_area], minlength=len(self.area_ids)).astype(float)
        area_speed = np.bincount(area_idx[has_area], weights=speed[has_area], minlength=len(self.area_ids))
        self._areas.update(gain, area_count, area_speed, t_s)
        observed_m = float(self.locator.lengths_m[observed].sum())
        if observed_m > 0:
            self._density_per_m = float(lane_count[observed].sum()) / observed_m
        area_observed = self.area_observed(live_agents)
        area_expected = np.where(area_observed, area_count, self._density_per_m * self.area_lane_length_m)

        cell = self.cells(vehicles.position_m)
        inside = cell >= 0
        n_cells = self.grid.size
        grid_count = np.bincount(cell[inside], minlength=n_cells).astype(float)
        grid_speed = np.bincount(cell[inside], weights=speed[inside], minlength=n_cells)
        self._grid.update(gain, grid_count, grid_speed, t_s)

        valid_s = self.cfg.speed_valid_s
        return TrafficSnapshot(
            t_s=t_s,
            lane_ids=self.lane_ids,
            lane_count=lane_count,
            lane_count_smoothed=self._lanes.count.copy(),
            lane_length_m=self.locator.lengths_m,
            lane_speed_mps=self._lanes.speed.copy(),
            lane_speed_valid=self._lanes.valid(t_s, valid_s),
            lane_observed=observed,
            prior_density_per_m=self._density_per_m,
            area_ids=self.area_ids,
            area_count=area_count,
            area_count_smoothed=self._areas.count.copy(),
            area_speed_mps=self._areas.speed.copy(),
            area_speed_valid=self._areas.valid(t_s, valid_s),
            area_observed=area_observed,
            area_rank=area_ranks(area_expected),
            grid_origin_m=self.grid_origin_m,
            grid_cell_m=self.cfg.grid_cell_m,
            grid_shape=self.grid_shape,
            grid_count=self._grid.count.reshape(self.grid_shape).copy(),
            grid_speed_mps=self._grid.speed.reshape(self.grid_shape).copy(),
            grid_samples=self._grid.samples.reshape(self.grid_shape).copy(),
            vehicle_lane=lane,
        )
