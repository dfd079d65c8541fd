"""The flow experiment's perception stand-in, fitted to what the MEC chain actually publishes.

Measured (`ErrorObserver`, on closed-loop runs through rendered sensors and `MecCore`), per agent
output, each published object list (as the coordinator reads it, `agent_objects`) against the ground
truth of its capture instant, matched one-to-one (Hungarian on horizontal distance within
`gate_m`, same road level within `level_m`):

  recall by distance  per agent, matched / present vehicles in bins of horizontal distance from the
                      agent's sensors (their centroid): MECs see past their areas' borders, and not all
                      of them
  position error      per-axis standard deviation (x, y) of matched objects
  velocity error      per-axis standard deviation (vx, vy) of matched objects
  false positives     objects matching no vehicle, per agent and object list
  latency             age of the newest object list when a map update reads it (capture -> use)

`OracleAgents` reproduces that from ground truth: each agent reports a vehicle with its distance
bin's recall, where it was `latency_s` ago (constant-velocity back-projection), with Gaussian
position and velocity errors, plus Poisson false positives at rest on uniformly drawn points of the
lanes the agent covers. Draws are independent per map update. Units: metres, seconds, m/s.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import linear_sum_assignment

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.lanes import lane_agents
from shared.traffic.maps import AgentObjects

FloatArray = NDArray[np.float64]
UNMATCHED_COST = 1e6


class AgentErrors(BaseModel):
    model_config = ConfigDict(extra="forbid")

    recall_by_distance: list[float] = Field(description="recall per distance bin from the agent's sensors")
    present_by_distance: list[int] = Field(description="vehicle-frames behind each recall (its weight)")
    false_positives_per_list: float = Field(ge=0, description="objects matching no vehicle, per object list")
    object_lists: int = Field(ge=0, description="object lists measured")


class OracleErrorModel(BaseModel):
    """The fitted error model (`deploy/experiments/oracle_model.json`, written by the fit)."""

    model_config = ConfigDict(extra="forbid")

    distance_bin_m: float = Field(gt=0)
    agents: dict[str, AgentErrors]
    position_std_m: float = Field(ge=0, description="per axis (x, y), matched objects")
    velocity_std_mps: float = Field(ge=0, description="per axis (vx, vy), matched objects")
    latency_s: float = Field(ge=0, description="mean age of the newest object list at a map update")
    matched: int = Field(ge=0, description="matched object-vehicle pairs behind the error figures")
    fitted_on: dict[str, Any] = Field(default_factory=dict, description="seeds, fleets, duration, commit")

    @classmethod
    def load(cls, path: Path) -> OracleErrorModel:
        return cls.model_validate_json(path.read_text())

    def save(self, path: Path) -> None:
        path.write_text(self.model_dump_json(indent=2) + "\n")

    def recall(self, agent: str, distance_m: FloatArray) -> FloatArray:
        """Recall of `agent` at each distance (0 beyond the last bin)."""
        table = np.asarray([*self.agents[agent].recall_by_distance, 0.0])
        k = np.minimum((np.asarray(distance_m) / self.distance_bin_m).astype(np.int64), len(table) - 1)
        return table[k]


def agent_anchors_m(scene: Scene) -> dict[str, FloatArray]:
    """Agent id -> (2,) centroid of its sensors' positions (x, y)."""
    return {
        a: np.mean([scene.T_world_from_sensor(s.id)[:2, 3] for s in scene.sensors_of(a)], axis=0)
        for a in scene.agents
    }


def match(
    objects_m: FloatArray, truth_m: FloatArray, gate_m: float, level_m: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """One-to-one pairs (object row, truth row) of (N, 3) and (M, 3) road-contact points: the minimum
    total horizontal distance among pairs within `gate_m` and `level_m` in height."""
    if len(objects_m) == 0 or len(truth_m) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d = np.linalg.norm(objects_m[:, None, :2] - truth_m[None, :, :2], axis=2)
    ok = (d <= gate_m) & (np.abs(objects_m[:, None, 2] - truth_m[None, :, 2]) <= level_m)
    rows, cols = linear_sum_assignment(np.where(ok, d, UNMATCHED_COST))
    keep = ok[rows, cols]
    return rows[keep].astype(np.int64), cols[keep].astype(np.int64)


class ErrorObserver:
    """Accumulates the MEC chain's errors over runs (`objects`, `age`); `fit` turns them into a model.
    Picklable and mergeable (`merge`) so runs in worker processes can be pooled."""

    def __init__(self, scene: Scene, gate_m: float, level_m: float, bin_m: float, max_m: float) -> None:
        self.gate_m, self.level_m, self.bin_m = gate_m, level_m, bin_m
        self.bins = int(np.ceil(max_m / bin_m))
        self.anchors = agent_anchors_m(scene)
        self.present = {a: np.zeros(self.bins, np.int64) for a in scene.agents}
        self.hits = {a: np.zeros(self.bins, np.int64) for a in scene.agents}
        self.false_positives = dict.fromkeys(scene.agents, 0)
        self.lists = dict.fromkeys(scene.agents, 0)
        self.position_errors: list[FloatArray] = []  # (K, 2) per object list
        self.velocity_errors: list[FloatArray] = []
        self.ages_s: list[float] = []

    def objects(self, objects: AgentObjects, truth_m: FloatArray, truth_mps: FloatArray) -> None:
        """One object list against the (M, 3) road-contact points and (M, 2+) velocities of every
        vehicle at its capture instant."""
        agent = objects.agent_id
        rows, cols = match(objects.position_m, truth_m, self.gate_m, self.level_m)
        k = np.minimum(
            (np.linalg.norm(truth_m[:, :2] - self.anchors[agent], axis=1) / self.bin_m).astype(int),
            self.bins - 1,
        )
        np.add.at(self.present[agent], k, 1)
        np.add.at(self.hits[agent], k[cols], 1)
        self.false_positives[agent] += len(objects) - len(rows)
        self.lists[agent] += 1
        self.position_errors.append(objects.position_m[rows, :2] - truth_m[cols, :2])
        self.velocity_errors.append(objects.velocity_mps[rows, :2] - truth_mps[cols, :2])

    def age(self, age_s: float) -> None:
        """Age of the newest object list a map update reads."""
        self.ages_s.append(age_s)

    def merge(self, other: ErrorObserver) -> None:
        for a in self.present:
            self.present[a] += other.present[a]
            self.hits[a] += other.hits[a]
            self.false_positives[a] += other.false_positives[a]
            self.lists[a] += other.lists[a]
        self.position_errors += other.position_errors
        self.velocity_errors += other.velocity_errors
        self.ages_s += other.ages_s

    def fit(self, fitted_on: dict[str, Any] | None = None) -> OracleErrorModel:
        pos = np.concatenate(self.position_errors) if self.position_errors else np.zeros((0, 2))
        vel = np.concatenate(self.velocity_errors) if self.velocity_errors else np.zeros((0, 2))
        agents = {
            a: AgentErrors(
                recall_by_distance=np.round(self.hits[a] / np.maximum(self.present[a], 1), 4).tolist(),
                present_by_distance=self.present[a].tolist(),
                false_positives_per_list=round(self.false_positives[a] / max(self.lists[a], 1), 4),
                object_lists=self.lists[a],
            )
            for a in self.present
        }
        return OracleErrorModel(
            distance_bin_m=self.bin_m,
            agents=agents,
            # RMS about zero: a bias is an error too
            position_std_m=round(float(np.sqrt(np.mean(pos**2))) if len(pos) else 0.0, 5),
            velocity_std_mps=round(float(np.sqrt(np.mean(vel**2))) if len(vel) else 0.0, 5),
            latency_s=round(float(np.mean(self.ages_s)) if self.ages_s else 0.0, 4),
            matched=len(pos),
            fitted_on=fitted_on or {},
        )


class OracleAgents:
    """Per-agent object lists drawn from ground truth with `OracleErrorModel`'s errors."""

    def __init__(self, scene: Scene, network: RoadNetwork, model: OracleErrorModel, seed: int) -> None:
        self.model = model
        self.rng = np.random.default_rng(seed)
        self.anchors = agent_anchors_m(scene)
        covers = lane_agents(scene, network)
        # Points on the lanes each agent covers (false positives are drawn among them; spacing even).
        self.lane_points = {
            a: np.concatenate(
                [network.lanes[lane].points for lane in sorted(covers) if a in covers[lane]]
                or [np.zeros((0, 3))]
            )
            for a in scene.agents
        }

    def __call__(self, pos: FloatArray, vel: FloatArray) -> list[AgentObjects]:
        """Object lists of every agent for vehicles at (N, 3) road-contact points with (N, 3) velocities."""
        m = self.model
        seen_pos = pos - vel * m.latency_s
        var = max(m.position_std_m**2, 1e-6)
        out = []
        for agent, anchor in self.anchors.items():
            if agent not in m.agents:
                out.append(AgentObjects.empty(agent))
                continue
            recall = m.recall(agent, np.linalg.norm(seen_pos[:, :2] - anchor, axis=1))
            idx = np.flatnonzero(self.rng.uniform(size=len(pos)) < recall)
            p = seen_pos[idx].copy()
            v = vel[idx].copy()
            p[:, :2] += self.rng.normal(0.0, m.position_std_m, (len(idx), 2))
            v[:, :2] += self.rng.normal(0.0, m.velocity_std_mps, (len(idx), 2))
            points = self.lane_points[agent]
            n_fp = int(self.rng.poisson(m.agents[agent].false_positives_per_list)) if len(points) else 0
            fp = points[self.rng.integers(len(points), size=n_fp)] if n_fp else np.zeros((0, 3))
            out.append(
                AgentObjects(
                    agent,
                    np.concatenate([p, fp]),
                    np.concatenate([v, np.zeros((n_fp, 3))]),
                    np.full(len(idx) + n_fp, var),
                )
            )
        return out
