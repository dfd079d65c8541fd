"""A SUMO network as a project scene, so the production coordinator plans on it unchanged.

The coordinator, its maps and the fitted perception model (studies/experiments/oracle.py) are in table
metres (the 1:18 sand table). A SUMO district goes the other way from `network.table_network`: every
length and speed divided by `TABLE_SCALE`, times unscaled, so a 2 km grid is a 111 m "table" whose
lanes, vehicle spacing and perception errors are at the scale every setting was chosen on.

- junctions: the network's nodes (ids made scene ids, `scene_ids`), numbered in id order;
- lanes: one per SUMO edge (one direction of a road; a multi-lane edge by its middle lane's line), its
  shape as is (no corner rounding), the opposite edge between the same nodes as its reverse;
- roadside agents at the chosen junctions (`RoadsideLayout`): each has a square area of `range_sumo_m`
  half-width about its junction and one pole lidar there (its anchor for the perception model's recall
  by distance). A lane belongs to the agent at its end junction (its approach, where queues form), else
  to the one at its start, else to the uncovered area: the maps count it when that agent is LIVE.
Units: table metres unless a name says SUMO metres (`_sumo_m`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sumolib

from shared.paths import DEFAULT_SCENE
from shared.scene.model import (
    AgentSpec,
    AreaSpec,
    JunctionSpec,
    LaneSpec,
    LidarModel,
    PoseSpec,
    SceneSpec,
    SensorSpec,
    TableSpec,
)
from shared.scene.scene import Scene
from sim.sumo.network import TABLE_SCALE

#: The area of the lanes no roadside agent covers (lowest priority: it spans the whole table).
UNCOVERED_AREA = "uncovered"
#: Pole height of an agent's lidar above the road, table metres (the table's lidars: 0.15-0.6 m).
POLE_HEIGHT_M = 0.5
#: Margin of the table around the network, table metres.
TABLE_MARGIN_M = 1.0
_ID_OK = re.compile(r"[^a-z0-9_\-]")


@dataclass(frozen=True)
class RoadsideLayout:
    """Roadside agents at `junctions` (SUMO node ids), each seeing `range_sumo_m` about its junction."""

    junctions: tuple[str, ...]
    range_sumo_m: float = 60.0


def scene_ids(sumo_ids: Iterable[str]) -> dict[str, str]:
    """SUMO id -> scene id (lower case, characters a scene id may not hold as "_"); ValueError when two
    SUMO ids would become one."""
    out = {s: _ID_OK.sub("_", s.lower())[:64] or "_" for s in sumo_ids}
    seen: dict[str, str] = {}
    for sumo, scene in out.items():
        if scene in seen:
            raise ValueError(f"SUMO ids {seen[scene]!r} and {sumo!r} both become scene id {scene!r}")
        seen[scene] = sumo
    return out


def coverage_layout(net: sumolib.net.Net, fraction: float, seed: int, range_sumo_m: float) -> RoadsideLayout:
    """Agents at `fraction` of the network's junctions (with at least three roads: crossings, not bends),
    drawn with `seed`."""
    crossings = sorted(n.getID() for n in _nodes(net) if len(n.getNeighboringNodes()) >= 3)
    k = round(fraction * len(crossings))
    chosen = np.random.default_rng(seed).choice(len(crossings), size=k, replace=False)
    return RoadsideLayout(tuple(sorted(crossings[i] for i in chosen)), range_sumo_m)


def _nodes(net: sumolib.net.Net) -> list[sumolib.net.node.Node]:
    return [n for n in net.getNodes() if n.getType() != "internal"]


def _square(centre: np.ndarray, half: float) -> list[tuple[float, float]]:
    x, y = float(centre[0]), float(centre[1])
    return [(x - half, y - half), (x + half, y - half), (x + half, y + half), (x - half, y + half)]


def scene_from_sumo(
    net_path: Path, layout: RoadsideLayout, scene_id: str = "sumo"
) -> tuple[Scene, dict[str, str]]:
    """The scene of the SUMO network `net_path` with `layout`'s roadside agents, and the SUMO id -> scene
    id map of its junctions and lanes (edges)."""
    net = sumolib.net.readNet(str(net_path))
    nodes = sorted(_nodes(net), key=lambda n: n.getID())
    edges = sorted((e for e in net.getEdges() if e.getFunction() != "internal"), key=lambda e: e.getID())
    ids = scene_ids([n.getID() for n in nodes] + [e.getID() for e in edges])
    unknown = sorted(set(layout.junctions) - {n.getID() for n in nodes})
    if unknown:
        raise ValueError(f"roadside agents at junctions the network lacks: {unknown}")
    scale = 1.0 / TABLE_SCALE
    xy = {n.getID(): np.asarray(n.getCoord()[:2], float) * scale for n in nodes}
    half = layout.range_sumo_m * scale
    agent_of = {j: f"rsu_{ids[j]}" for j in layout.junctions}
    areas = [
        AreaSpec(id=f"area_{ids[j]}", name=f"roadside {j}", polygon_m=_square(xy[j], half))
        for j in layout.junctions
    ]
    lo = np.min(list(xy.values()), axis=0) - TABLE_MARGIN_M
    hi = np.max(list(xy.values()), axis=0) + TABLE_MARGIN_M
    areas.append(
        AreaSpec(
            id=UNCOVERED_AREA,
            name="not covered",
            polygon_m=[(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])],
        )
    )
    junctions = [
        JunctionSpec(
            id=ids[n.getID()],
            number=k + 1,
            position_m=(*map(float, xy[n.getID()]), 0.0),
            radius_m=_radius_m(n, scale),
        )
        for k, n in enumerate(nodes)
    ]
    pairs = {(e.getFromNode().getID(), e.getToNode().getID()): e.getID() for e in edges}
    lanes = []
    for e in edges:
        line = np.asarray(e.getLanes()[e.getLaneNumber() // 2].getShape(), float)[:, :2] * scale
        ends = (e.getToNode().getID(), e.getFromNode().getID())
        area = next((f"area_{ids[j]}" for j in ends if j in agent_of), UNCOVERED_AREA)
        reverse = pairs.get((e.getToNode().getID(), e.getFromNode().getID()))
        lanes.append(
            LaneSpec(
                id=ids[e.getID()],
                from_junction=ids[e.getFromNode().getID()],
                to_junction=ids[e.getToNode().getID()],
                area=area,
                points_m=[(float(x), float(y), 0.0) for x, y in line],
                speed_limit_mps=e.getSpeed() * scale,
                corner_radius_m=0.0,
                reverse_lane=ids[reverse] if reverse else None,
            )
        )
    agents = [
        AgentSpec(id=agent_of[j], name=f"roadside agent at {j}", areas=[f"area_{ids[j]}"])
        for j in layout.junctions
    ]
    sensors = [
        SensorSpec(
            id=f"lidar_{ids[j]}",
            agent=agent_of[j],
            kind="lidar",
            rate_hz=10.0,
            pose=PoseSpec(position_m=(*map(float, xy[j]), POLE_HEIGHT_M), rpy_rad=(0.0, 0.0, 0.0)),
            lidar=LidarModel(
                channels=16,
                horizontal_samples=500,
                vertical_min_rad=-0.5353,
                vertical_max_rad=0.5353,
                min_range_m=0.1,
                max_range_m=half * np.sqrt(2),
            ),
        )
        for j in layout.junctions
    ]
    table = Scene.load(DEFAULT_SCENE).spec  # the model car and road settings of the sand table
    spec = SceneSpec(
        scene_id=scene_id,
        description=f"SUMO network {net_path.name} at 1:{TABLE_SCALE:g}",
        table=TableSpec(
            size_x_m=float(hi[0] - lo[0]),
            size_y_m=float(hi[1] - lo[1]),
            origin_m=(float(lo[0]), float(lo[1])),
        ),
        road=table.road,
        vehicle=table.vehicle,
        junctions=junctions,
        lanes=lanes,
        areas=areas,
        agents=agents,
        sensors=sensors,
    )
    return Scene(spec), ids


def _radius_m(node: sumolib.net.node.Node, scale: float) -> float:
    """The node's control zone: the farthest point of its shape from its centre (lanes end there), table
    metres; a node without a shape gets a car length (0.33 m, the table's)."""
    shape = node.getShape()
    if not shape:
        return 0.33
    centre = np.asarray(node.getCoord()[:2], float)
    return float(max(np.linalg.norm(np.asarray(shape, float)[:, :2] - centre, axis=1))) * scale


def sumo_ids(ids: dict[str, str], scene: Sequence[str]) -> list[str]:
    """Scene ids (lanes of a plan) back to SUMO edge ids."""
    back = {v: k for k, v in ids.items()}
    return [back[s] for s in scene]
