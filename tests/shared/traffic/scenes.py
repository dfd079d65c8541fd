"""Tiny synthetic scenes whose routes, lengths and cells can be checked by hand.

Lanes start and end exactly on their junctions' positions, so every junction connector has length 0
and a lane-graph edge weighs exactly the length of the lane it leads onto.
"""

from __future__ import annotations

from typing import Any

from shared.config import read_yaml
from shared.paths import DEFAULT_SCENE
from shared.scene.model import SceneSpec
from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings
from shared.traffic.core import CoordinatorCore
from shared.traffic.planner import ShardView
from shared.traffic.regions import Overlay

SPEED_MPS = 0.5


VEHICLE = read_yaml(DEFAULT_SCENE)["vehicle"]  # the sand table's car (the scene file is its home)
# Table-sized road geometry (no deck): these scenes' lanes and lengths are sized for the table's car.
ROAD = {"lane_width_m": 0.3, "corner_radius_m": 0.4, "sample_step_m": 0.02}


def _lane(lane_id: str, a: str, b: str, area: str, points: list[tuple[float, float]], **kw: Any) -> dict:
    return {
        "id": lane_id,
        "from_junction": a,
        "to_junction": b,
        "area": area,
        "points_m": [(x, y, 0.0) for x, y in points],
        "speed_limit_mps": SPEED_MPS,
        **kw,
    }


def _square(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float]]:
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


def planner_scene() -> Scene:
    """Two alternatives from junction ja to jb (speed limit 0.5 m/s everywhere):

        jz(-1,0) --in (1 m)--> ja(0,0) --ab (2 m, south)----------> jb(2,0) --bz (3 m)--> jz
                                  |                                   ^   \\
                                  +--ac (1.5 m, north)--> jc(0,1.5) --cb (2.5 m, north)   dead --> jd
        ba: jb -> ja, the opposite lane of ab (no U-turn between them); jx: a junction no lane reaches.

    short route in -> ab: 2 m (4 s); long route in -> ac -> cb: 4 m (8 s).
    """
    spec = {
        "scene_id": "planner_square",
        "vehicle": VEHICLE,
        "road": ROAD,
        "table": {"size_x_m": 8.0, "size_y_m": 8.0, "origin_m": (-4.0, -4.0)},
        "junctions": [
            {"id": "jz", "number": 1, "position_m": (-1.0, 0.0, 0.0)},
            {"id": "ja", "number": 2, "position_m": (0.0, 0.0, 0.0)},
            {"id": "jb", "number": 3, "position_m": (2.0, 0.0, 0.0)},
            {"id": "jc", "number": 4, "position_m": (0.0, 1.5, 0.0)},
            {"id": "jd", "number": 5, "position_m": (3.0, -1.0, 0.0)},
            {"id": "jx", "number": 6, "position_m": (3.0, 3.0, 0.0)},
        ],
        "lanes": [
            _lane("in", "jz", "ja", "south", [(-1.0, 0.0), (0.0, 0.0)]),
            _lane("ab", "ja", "jb", "south", [(0.0, 0.0), (2.0, 0.0)], reverse_lane="ba"),
            _lane("ac", "ja", "jc", "north", [(0.0, 0.0), (0.0, 1.5)]),
            _lane("cb", "jc", "jb", "north", [(0.0, 1.5), (2.0, 0.0)]),
            _lane("ba", "jb", "ja", "south", [(2.0, 0.0), (0.0, 0.0)], reverse_lane="ab"),
            _lane(
                "bz",
                "jb",
                "jz",
                "south",
                [(2.0, 0.0), (2.0, -1.0), (-1.0, -1.0), (-1.0, 0.0)],
                corner_radius_m=0.0,
            ),
            _lane("dead", "jb", "jd", "south", [(2.0, 0.0), (3.0, -1.0)]),
        ],
        "areas": [
            {"id": "south", "name": "south", "polygon_m": _square(-4.0, -4.0, 4.0, 0.5)},
            {"id": "north", "name": "north", "polygon_m": _square(-4.0, 0.5, 4.0, 4.0)},
        ],
        "agents": [{"id": "agent_s", "name": "S", "areas": ["south"]}],
    }
    return Scene(SceneSpec.model_validate(spec))


def map_scene() -> Scene:
    """Two straight one-way lanes on a 5 m x 3 m table with origin (-1, -1):

        hi: j3(3.5, 1.5) -> j4(0.5, 1.5), heading -x, in area north (seen by agent_n)
        lo: j1(0.5, 0.5) -> j2(3.5, 0.5), heading +x, in area south (seen by agent_s)

    Areas split at y = 1 (the boundary belongs to south, the first area in the file)."""
    spec = {
        "scene_id": "map_strip",
        "vehicle": VEHICLE,
        "road": ROAD,
        "table": {"size_x_m": 5.0, "size_y_m": 3.0, "origin_m": (-1.0, -1.0)},
        "junctions": [
            {"id": "j1", "number": 1, "position_m": (0.5, 0.5, 0.0)},
            {"id": "j2", "number": 2, "position_m": (3.5, 0.5, 0.0)},
            {"id": "j3", "number": 3, "position_m": (3.5, 1.5, 0.0)},
            {"id": "j4", "number": 4, "position_m": (0.5, 1.5, 0.0)},
        ],
        "lanes": [
            _lane("lo", "j1", "j2", "south", [(0.5, 0.5), (3.5, 0.5)]),
            _lane("hi", "j3", "j4", "north", [(3.5, 1.5), (0.5, 1.5)]),
        ],
        "areas": [
            {"id": "south", "name": "south", "polygon_m": _square(-1.0, -1.0, 4.0, 1.0)},
            {"id": "north", "name": "north", "polygon_m": _square(-1.0, 1.0, 4.0, 2.0)},
        ],
        "agents": [
            {"id": "agent_s", "name": "S", "areas": ["south"]},
            {"id": "agent_n", "name": "N", "areas": ["north"]},
        ],
    }
    return Scene(SceneSpec.model_validate(spec))


def shard_cores(overlay: Overlay, max_vehicles: int = 16) -> list[CoordinatorCore]:
    """One production core per region of `overlay` (no agents), each planning across the others with
    the cliques they publish on empty maps."""
    cores = [
        CoordinatorCore(
            overlay.net.scene,
            CoordinatorSettings(),
            max_vehicles,
            shard=ShardView(overlay, r),
            shard_agents=[],
        )
        for r in range(overlay.regions.regions)
    ]
    for r, core in enumerate(cores):
        assert core.shard is not None
        core.shard.cliques = {o: other.clique() for o, other in enumerate(cores) if o != r}
    return cores
