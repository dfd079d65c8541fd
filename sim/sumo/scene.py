"""A SUMO network as a project scene, so the production coordinator plans on it unchanged.

The coordinator, its maps and the fitted perception model (studies/experiments/oracle.py) are in table
metres (the 1:18 sand table). A SUMO district goes the other way from `network.table_network`: every
length and speed divided by `TABLE_SCALE`, times unscaled, so a 2 km grid is a 111 m "table" whose
lanes, vehicle spacing and perception errors are at the scale every setting was chosen on.

- junctions: the network's nodes (ids made scene ids, `scene_ids`), numbered in id order;
- lanes: one per SUMO edge cars may use (one direction of a road; a multi-lane edge by its middle
  lane's line), its shape as is (no corner rounding), the opposite edge between the same nodes as its
  reverse, the edges SUMO connects it to (for that vehicle class) as its next lanes: a crossing's turn
  restrictions hold in plans;
- roadside agents at the chosen junctions (`RoadsideLayout`): each has a square area of `range_sumo_m`
  half-width about its junction and one pole lidar there (its anchor for the perception model's recall
  by distance). A lane belongs to the agent at its end junction (its approach, where queues form), else
  to the one at its start, else to the uncovered area: the maps count it when that agent is LIVE.
Units: table metres unless a name says SUMO metres (`_sumo_m`).
"""

from __future__ import annotations

import re
from collections import Counter
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
from sim.sumo.ids import MAX_ID_CHARS, bus_id
from sim.sumo.network import TABLE_SCALE

#: The area of the lanes no roadside agent covers (lowest priority: it spans the whole table).
UNCOVERED_AREA = "uncovered"
#: Pole height of an agent's lidar above the road, table metres (the table's lidars: 0.15-0.6 m).
POLE_HEIGHT_M = 0.5
#: Margin of the table around the network, table metres.
TABLE_MARGIN_M = 1.0
_ID_OK = re.compile(r"[^a-z0-9_\-]")
#: A junction's scene id leaves room for the prefixes of its agent's ids (`lidar_`, `area_`, `rsu_`).
SCENE_ID_CHARS = MAX_ID_CHARS - len("lidar_")


@dataclass(frozen=True)
class RoadsideLayout:
    """Roadside agents at `junctions` (SUMO node ids), each seeing `range_sumo_m` about its junction."""

    junctions: tuple[str, ...]
    range_sumo_m: float = 60.0


def scene_ids(sumo_ids: Iterable[str]) -> dict[str, str]:
    """SUMO id -> scene id: lower case with `_` for characters a scene id may not hold where that is a
    valid id of at most SCENE_ID_CHARS that no other SUMO id of the net shares (`A0` -> `a0`), else the
    injective escape of `sim.sumo.ids` (OpenStreetMap's `-23975#1`, Hamburg's 90-character cluster ids);
    ValueError when two SUMO ids would still become one."""
    unique = list(dict.fromkeys(sumo_ids))
    plain = {s: _ID_OK.sub("_", s.lower()) for s in unique}
    shared = Counter(plain.values())
    out = {
        s: p
        if p and p[0] not in "_-" and len(p) <= SCENE_ID_CHARS and shared[p] == 1
        else bus_id(s, max_chars=SCENE_ID_CHARS)
        for s, p in plain.items()
    }
    seen: dict[str, str] = {}
    for sumo, scene in out.items():
        if scene in seen:
            raise ValueError(f"SUMO ids {seen[scene]!r} and {sumo!r} both become scene id {scene!r}")
        seen[scene] = sumo
    return out


def coverage_layout(net: sumolib.net.Net, fraction: float, seed: int, range_sumo_m: float) -> RoadsideLayout:
    """Agents at `fraction` of the network's crossings (junctions of at least three roads, not bends),
    signalised ones first (where a city would mount them: poles and power are there), drawn with
    `seed` within each group."""
    crossings = sorted(n.getID() for n in _nodes(net) if len(n.getNeighboringNodes()) >= 3)
    k = round(fraction * len(crossings))
    signalised = [c for c in crossings if net.getNode(c).getType().startswith("traffic_light")]
    others = [c for c in crossings if c not in set(signalised)]
    rng = np.random.default_rng(seed)
    chosen = [signalised[i] for i in rng.choice(len(signalised), size=min(k, len(signalised)), replace=False)]
    chosen += [others[i] for i in rng.choice(len(others), size=k - len(chosen), replace=False)]
    return RoadsideLayout(tuple(sorted(chosen)), range_sumo_m)


def _nodes(net: sumolib.net.Net) -> list[sumolib.net.node.Node]:
    return [n for n in net.getNodes() if n.getType() != "internal"]


def _square(centre: np.ndarray, half: float) -> list[tuple[float, float]]:
    x, y = float(centre[0]), float(centre[1])
    return [(x - half, y - half), (x + half, y - half), (x + half, y + half), (x - half, y + half)]


def scene_from_sumo(
    net_path: Path, layout: RoadsideLayout, scene_id: str = "sumo", vehicle_class: str = "passenger"
) -> tuple[Scene, dict[str, str]]:
    """The scene of the SUMO network `net_path` with `layout`'s roadside agents, and the SUMO id -> scene
    id map of its junctions and lanes: the edges `vehicle_class` may drive on (a real city's bus lanes,
    tram tracks and footways are no lanes for the plans of cars)."""
    net = sumolib.net.readNet(str(net_path))
    nodes = sorted(_nodes(net), key=lambda n: n.getID())
    edges = sorted(
        (e for e in net.getEdges() if e.getFunction() != "internal" and e.allows(vehicle_class)),
        key=lambda e: e.getID(),
    )
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
    kept = {e.getID() for e in edges}
    lanes = []
    for e in edges:
        line = np.asarray(e.getLanes()[e.getLaneNumber() // 2].getShape(), float)[:, :2] * scale
        ends = (e.getToNode().getID(), e.getFromNode().getID())
        area = next((f"area_{ids[j]}" for j in ends if j in agent_of), UNCOVERED_AREA)
        reverse = pairs.get((e.getToNode().getID(), e.getFromNode().getID()))
        turns = sorted(
            ids[after.getID()]
            for after, links in e.getOutgoing().items()
            if after.getID() in kept and any(_links_class(c, vehicle_class) for c in links)
        )
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
                next_lanes=turns,
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


def _links_class(connection: sumolib.net.connection.Connection, vehicle_class: str) -> bool:
    """True if the connection joins two lanes `vehicle_class` may use."""
    return bool(
        connection.getFromLane().allows(vehicle_class) and connection.getToLane().allows(vehicle_class)
    )


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
