"""Road networks for SUMO: generated grids and random networks (`netgenerate`), and the sand table's own
network exported with its junction and lane ids (plain XML -> `netconvert`).

The table is 1:18 (the paper's field of 8 m x 10 m as built): its network goes to SUMO at full size,
every length and speed times `TABLE_SCALE`, time unscaled, so SUMO's real-size vehicles drive it as
the model cars drive the table. Each table lane becomes a one-lane SUMO edge with the lane's id, each
junction a node with the junction's id, and the connections are exactly the table's lane graph
(`shared.scene.road_network.RoadNetwork`: every incoming-outgoing pair but the U-turn onto the same
road's opposite lane), so perception's lane keys and the coordinator's routes read the same in both.
Units: metres, m/s.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from sim.sumo import tools

#: SUMO metres per table metre (and SUMO m/s per table m/s): the sand table is a 1:18 model.
TABLE_SCALE = 18.0
#: Junction type of every generated or exported node. Priority (no signals) matches the table, whose
#: junctions have none, and keeps delays a matter of traffic, not of signal plans.
JUNCTION_TYPE = "priority"


@dataclass(frozen=True)
class GridSpec:
    """A `netgenerate --grid` network: `junctions_per_side`² junctions `edge_length_m` apart, every road
    two-way with `lanes` lanes per direction at `speed_mps`."""

    junctions_per_side: int = 10
    edge_length_m: float = 200.0
    lanes: int = 1
    speed_mps: float = 13.89


@dataclass(frozen=True)
class RandomSpec:
    """A `netgenerate --rand` network grown over `iterations` steps from `seed` (junctions
    `min_distance_m`..`max_distance_m` apart)."""

    iterations: int = 200
    seed: int = 0
    min_distance_m: float = 100.0
    max_distance_m: float = 250.0
    lanes: int = 1
    speed_mps: float = 13.89


def _netgenerate(kind: list[str], lanes: int, speed_mps: float, out: Path) -> Path:
    """Run netgenerate with the `kind` options and the settings every generated network shares."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tools.run(
        [
            tools.program("netgenerate"),
            *kind,
            f"--default.lanenumber={lanes}",
            f"--default.speed={speed_mps}",
            f"--default-junction-type={JUNCTION_TYPE}",
            "--no-turnarounds=true",  # as on the table: no U-turn onto the same road's other direction
            f"--output-file={out}",
        ]
    )
    return out


def grid_network(spec: GridSpec, out: Path) -> Path:
    """Write the grid network `out` (a .net.xml); its path."""
    kind = ["--grid", f"--grid.number={spec.junctions_per_side}", f"--grid.length={spec.edge_length_m}"]
    return _netgenerate(kind, spec.lanes, spec.speed_mps, out)


def random_network(spec: RandomSpec, out: Path) -> Path:
    """Write the random network `out` (a .net.xml); its path."""
    kind = [
        "--rand",
        f"--rand.iterations={spec.iterations}",
        f"--rand.min-distance={spec.min_distance_m}",
        f"--rand.max-distance={spec.max_distance_m}",
        f"--seed={spec.seed}",
    ]
    return _netgenerate(kind, spec.lanes, spec.speed_mps, out)


def _fmt(value: float) -> str:
    return f"{value:.3f}"


def table_plain_xml(scene: Scene, folder: Path) -> tuple[Path, Path, Path]:
    """The table's nodes, edges and connections as SUMO plain XML in `folder`, scaled by TABLE_SCALE;
    the three files (.nod.xml, .edg.xml, .con.xml)."""
    folder.mkdir(parents=True, exist_ok=True)
    nodes = ET.Element("nodes")
    for j in scene.spec.junctions:
        x, y, z = (c * TABLE_SCALE for c in j.position_m)
        ET.SubElement(nodes, "node", id=j.id, x=_fmt(x), y=_fmt(y), z=_fmt(z), type=JUNCTION_TYPE)
    edges = ET.Element("edges")
    for lane in scene.spec.lanes:
        # The lane's rounded centreline, so lengths match the table's; one SUMO lane on that line.
        line = scene.lane_centreline(lane.id) * TABLE_SCALE
        shape = " ".join(",".join(_fmt(c) for c in p) for p in line[:: max(1, len(line) // 64)])
        ET.SubElement(
            edges, "edge", id=lane.id, attrib={"from": lane.from_junction, "to": lane.to_junction},
            numLanes="1", speed=_fmt(lane.speed_limit_mps * TABLE_SCALE), shape=shape, spreadType="center",
        )  # fmt: skip
    connections = ET.Element("connections")
    network = RoadNetwork(scene)
    for from_lane, successors in network.successors.items():
        for to_lane in successors:
            ET.SubElement(connections, "connection", attrib={"from": from_lane, "to": to_lane})
    paths = (folder / "table.nod.xml", folder / "table.edg.xml", folder / "table.con.xml")
    for path, root in zip(paths, (nodes, edges, connections), strict=True):
        ET.indent(root)
        ET.ElementTree(root).write(path, encoding="unicode", xml_declaration=True)
    return paths


def table_network(scene: Scene, out: Path) -> Path:
    """Write the sand table's network `out` (a .net.xml, plain XML beside it); its path."""
    nod, edg, con = table_plain_xml(scene, out.parent)
    tools.run(
        [
            tools.program("netconvert"),
            f"--node-files={nod}",
            f"--edge-files={edg}",
            f"--connection-files={con}",
            "--no-turnarounds=true",
            "--geometry.remove=false",  # keep every lane as its own edge, ids unchanged
            f"--output-file={out}",
        ]
    )
    return out
