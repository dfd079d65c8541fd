"""PyBullet sand table built from the scene file: table with a painted road texture, viaduct deck and
pillars, buildings, poles and signal heads, and vehicles (each class the same body model at its own size).

Two kinds of PyBullet clients are built from the same scene (each its own DIRECT connection):
- `StaticWorld`: everything that never moves. Sensors render / ray-cast it once per sensor and keep
  the result (background image and depth, per-ray ranges).
- `VehicleWorld`: only the vehicles, moved to each tick's ground-truth poses. Sensors render and
  ray-cast it per frame and combine with the static result by depth (correct occlusion both ways).
A full world (static + vehicles in one client) serves whole-scene renders and checks.
What the scene does not size (table slab, texture resolution, markings, deck pieces, ray tolerances) is
`WorldSettings` (sim/config.py), scaled to the scene here. Units: metres, radians; colours RGBA in [0, 1].
"""

from __future__ import annotations

import itertools
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pybullet as pb
from scipy.spatial.transform import Rotation

from shared.scene.scale import SiteScale, at_scale
from shared.scene.scene import Scene
from sim.config import WorldSettings

TABLE_RGB = (92, 140, 84)  # lawn
ROAD_RGB = (70, 70, 74)
MARKING_RGB = (235, 235, 235)
JUNCTION_RGB = (80, 80, 86)
DECK_RGBA = (0.62, 0.62, 0.6, 1.0)
PILLAR_RGBA = (0.55, 0.55, 0.53, 1.0)
TYRE_RGBA = (0.08, 0.08, 0.08, 1.0)

# Vehicle body parts (fractions of the scene's vehicle box), all inside the ground-truth box so that
# lidar returns on a vehicle lie on or inside its box.
CHASSIS_Z_FRACTION = (0.15, 0.55)  # bottom, top of the chassis as fractions of height
SHELL_FRACTION = (0.7, 0.82, 0.45)  # length, width, height of the top shell
WHEEL_RADIUS_FRACTION = 0.15  # of the body height: 0.0315 m for the Deepracer

# Signal heads: unlit lenses (no phases are simulated), as dark tints of red, amber and green, top down.
SIGNAL_LAMP_RGBA = ((0.45, 0.05, 0.05, 1.0), (0.5, 0.33, 0.02, 1.0), (0.05, 0.35, 0.12, 1.0))
SIGNAL_LAMP_FILL = 0.85  # lens diameter / the housing's width (a 300 mm lens in a 350 mm wide head)
SIGNAL_LAMP_DEPTH_FRACTION = 0.07  # lens protrusion / the housing's depth (~2 cm on a 0.3 m deep head)


@dataclass(frozen=True)
class VehiclePose:
    """A vehicle box pose: centre of the box, yaw and pitch (URDF sign)."""

    vehicle_id: str
    center_m: tuple[float, float, float]
    yaw_rad: float
    pitch_rad: float = 0.0
    rgba: tuple[float, float, float, float] = (0.8, 0.1, 0.1, 1.0)
    size_m: tuple[float, float, float] | None = None  # length, width, height; None: the scene's vehicle


def quat_from_rpy(roll: float, pitch: float, yaw: float) -> list[float]:
    return [float(q) for q in Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()]


def world_settings(scene: Scene, settings: WorldSettings | None = None) -> WorldSettings:
    """`settings` (default: the defaults) at `scene`'s scale (idempotent: scaled settings stay so)."""
    return at_scale(settings or WorldSettings(), SiteScale.of(scene.spec))


def road_texture(
    scene: Scene, settings: WorldSettings | None = None, px_per_m: float | None = None
) -> np.ndarray:
    """Top-down RGB image of the table: lawn, road surface, junction pads, lane markings, at `px_per_m`
    (default: the world's texture resolution).

    Row 0 is the table's max-y edge (image v grows toward -y), column 0 its min-x edge."""
    world = world_settings(scene, settings)
    px_per_m = world.texture_px_per_m if px_per_m is None else px_per_m
    table = scene.spec.table
    w = round(table.size_x_m * px_per_m)
    h = round(table.size_y_m * px_per_m)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = TABLE_RGB
    x0, y0 = table.origin_m

    def px(xy: np.ndarray) -> np.ndarray:
        cols = (xy[:, 0] - x0) * px_per_m
        rows = (y0 + table.size_y_m - xy[:, 1]) * px_per_m
        return np.round(np.column_stack([cols, rows]) * 4).astype(np.int32)  # 2 fractional bits

    road = scene.spec.road
    if road is None:  # a site without a lane map: bare ground
        return img
    width_px = max(1, round(road.lane_width_m * px_per_m))
    for lane in scene.spec.lanes:
        pts = np.asarray(scene.lane_centreline(lane.id))
        ground = pts[pts[:, 2] <= road.elevated_min_z_m]
        if len(ground) >= 2:
            cv2.polylines(img, [px(ground[:, :2])], False, ROAD_RGB, width_px + 2, cv2.LINE_AA, shift=2)
    for j in scene.spec.junctions:
        centre = px(np.array([j.position_m[:2]]))[0]
        cv2.circle(
            img,
            tuple(int(c) for c in centre),
            round(j.radius_m * px_per_m * 4),
            JUNCTION_RGB,
            -1,
            cv2.LINE_AA,
            2,
        )
    # Lane edge markings: dashed lines at both edges of every ground lane.
    mark_px = max(1, round(world.marking_width_m * px_per_m))
    for lane in scene.spec.lanes:
        pts = np.asarray(scene.lane_centreline(lane.id))
        d = np.gradient(pts[:, :2], axis=0)
        n = np.column_stack([-d[:, 1], d[:, 0]]) / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        on = (np.floor(s / world.marking_dash_m) % 2 == 0) & (pts[:, 2] <= road.elevated_min_z_m)
        for side in (-1, 1):
            edge = pts[:, :2] + side * n * road.lane_width_m / 2
            start = None
            for i, flag in enumerate(on):
                if flag and start is None:
                    start = i
                if (not flag or i == len(on) - 1) and start is not None:
                    if i - start >= 1:
                        cv2.polylines(
                            img, [px(edge[start : i + 1])], False, MARKING_RGB, mark_px, cv2.LINE_AA, 2
                        )
                    start = None
    return img


def _load_texture(img: np.ndarray, cid: int) -> int:
    """A PyBullet texture of `img` (RGB). PyBullet loads textures from files only: the image is written
    to a directory of this process's own (mkdtemp: created 0700 with a name no one can predict) and
    removed once loaded. A shared cache at a predictable /tmp name let another local user plant the
    texture, or a symlink the write followed."""
    with tempfile.TemporaryDirectory(prefix="rmmdet_texture_") as folder:
        path = Path(folder) / "texture.png"
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        return int(pb.loadTexture(str(path), physicsClientId=cid))


class _Client:
    def __init__(self) -> None:
        self.cid = pb.connect(pb.DIRECT)

    def close(self) -> None:
        if self.cid >= 0 and pb.isConnected(self.cid):
            pb.disconnect(self.cid)
        self.cid = -1

    def __enter__(self) -> _Client:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def _box(
    cid: int, centre: list[float], half: list[float], quat: list[float], rgba: tuple, collision: bool = True
) -> int:
    vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=list(rgba), physicsClientId=cid)
    col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half, physicsClientId=cid) if collision else -1
    return pb.createMultiBody(0, col, vis, centre, quat, physicsClientId=cid)


def _cylinder(
    cid: int, base: list[float], radius: float, height: float, rgba: tuple, collision: bool = True
) -> int:
    vis = pb.createVisualShape(
        pb.GEOM_CYLINDER, radius=radius, length=height, rgbaColor=list(rgba), physicsClientId=cid
    )
    col = (
        pb.createCollisionShape(pb.GEOM_CYLINDER, radius=radius, height=height, physicsClientId=cid)
        if collision
        else -1
    )
    return pb.createMultiBody(0, col, vis, [base[0], base[1], base[2] + height / 2], physicsClientId=cid)


def _signal_lamps(
    cid: int,
    base: tuple[float, float, float],
    size_m: tuple[float, float, float],
    yaw: float,
    collision: bool,
) -> list[int]:
    """The three lamp faces of a signal head (red over amber over green) on its +x face: each a thin
    upright disc a third of the housing high, filling `SIGNAL_LAMP_FILL` of its width or height."""
    depth, width, height = size_m
    radius = SIGNAL_LAMP_FILL * min(width, height / 3) / 2
    lens_m = SIGNAL_LAMP_DEPTH_FRACTION * depth
    # A cylinder's axis is its z: tilt it onto the facing direction (pitch 90 deg, then the head's yaw).
    quat = quat_from_rpy(0.0, math.pi / 2, yaw)
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    bodies = []
    for k, rgba in enumerate(SIGNAL_LAMP_RGBA):
        centre = np.array(base) + forward * (depth / 2 + lens_m / 2)
        centre[2] += height * (5 - 2 * k) / 6  # the centres of the upper, middle and lower thirds
        vis = pb.createVisualShape(
            pb.GEOM_CYLINDER, radius=radius, length=lens_m, rgbaColor=list(rgba), physicsClientId=cid
        )
        col = (
            pb.createCollisionShape(pb.GEOM_CYLINDER, radius=radius, height=lens_m, physicsClientId=cid)
            if collision
            else -1
        )
        bodies.append(pb.createMultiBody(0, col, vis, centre.tolist(), quat, physicsClientId=cid))
    return bodies


class StaticWorld(_Client):
    """Table, road texture, viaduct, static objects. `body_kind[body_id]` names what each body is;
    `settings` are the world's at the scene's scale."""

    def __init__(self, scene: Scene, settings: WorldSettings | None = None) -> None:
        super().__init__()
        self.scene = scene
        self.settings = world_settings(scene, settings)
        self.body_kind: dict[int, str] = {}
        self._build_table()
        self._build_viaduct()
        self._build_static_objects()

    def _build_table(self) -> None:
        cid, table, world = self.cid, self.scene.spec.table, self.settings
        x0, y0 = table.origin_m
        x1, y1 = x0 + table.size_x_m, y0 + table.size_y_m
        # Textured top: square tiles, each a two-triangle mesh with its own crop of the road texture.
        # Small triangles keep TinyRenderer's interpolation stable at grazing view angles.
        texture = road_texture(self.scene, world)
        px_per_m = texture.shape[1] / table.size_x_m
        tile_m = world.table_tile_m
        nx_tiles = max(1, math.ceil(table.size_x_m / tile_m))
        ny_tiles = max(1, math.ceil(table.size_y_m / tile_m))
        for j in range(ny_tiles):
            for i in range(nx_tiles):
                tx0, ty0 = x0 + i * tile_m, y0 + j * tile_m
                tx1, ty1 = min(tx0 + tile_m, x1), min(ty0 + tile_m, y1)
                c0, c1 = round((tx0 - x0) * px_per_m), round((tx1 - x0) * px_per_m)
                r0, r1 = round((y1 - ty1) * px_per_m), round((y1 - ty0) * px_per_m)
                hx, hy = (tx1 - tx0) / 2, (ty1 - ty0) / 2
                # Vertices are local to the body (TinyRenderer culls by the body's own bounds).
                vis = pb.createVisualShape(
                    pb.GEOM_MESH,
                    vertices=[[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]],
                    indices=[0, 1, 2, 0, 2, 3],
                    uvs=[[0, 1], [1, 1], [1, 0], [0, 0]],
                    normals=[[0, 0, 1]] * 4,
                    physicsClientId=cid,
                )
                body = pb.createMultiBody(0, -1, vis, [tx0 + hx, ty0 + hy, 0.0], physicsClientId=cid)
                tile = np.ascontiguousarray(texture[r0:r1, c0:c1])
                tex = _load_texture(tile, cid)
                pb.changeVisualShape(
                    body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=cid
                )
                self.body_kind[body] = "table"
        col = pb.createCollisionShape(
            pb.GEOM_BOX,
            halfExtents=[table.size_x_m / 2, table.size_y_m / 2, world.table_thickness_m / 2],
            physicsClientId=cid,
        )
        # The slab needs a visual of its own: PyBullet draws a body without one as a white box, which
        # would z-fight with the tiles. Its top sits just below them.
        slab_vis = pb.createVisualShape(
            pb.GEOM_BOX,
            halfExtents=[table.size_x_m / 2, table.size_y_m / 2, world.table_thickness_m / 2],
            rgbaColor=[c / 255 for c in TABLE_RGB] + [1.0],
            physicsClientId=cid,
        )
        slab = pb.createMultiBody(
            0,
            col,
            slab_vis,
            [(x0 + x1) / 2, (y0 + y1) / 2, -world.table_thickness_m / 2 - world.table_slab_drop_m],
            physicsClientId=cid,
        )
        self.body_kind[slab] = "table"

    def _build_viaduct(self) -> None:
        road = self.scene.spec.road
        if road is None or road.deck is None:
            return
        deck = road.deck
        for lane in self.scene.spec.lanes:
            pts = np.asarray(self.scene.lane_centreline(lane.id))
            elevated = pts[:, 2] > road.elevated_min_z_m
            if not elevated.any():
                continue
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
            idx = np.nonzero(elevated)[0]
            first, last = max(idx[0] - 1, 0), min(idx[-1] + 1, len(pts) - 1)
            marks = np.arange(s[first], s[last], self.settings.deck_piece_m)
            marks = np.append(marks, s[last])
            for a, b in itertools.pairwise(marks):
                pa = np.array([np.interp(a, s, pts[:, k]) for k in range(3)])
                pb_ = np.array([np.interp(b, s, pts[:, k]) for k in range(3)])
                d = pb_ - pa
                length = float(np.linalg.norm(d))
                yaw = math.atan2(d[1], d[0])
                pitch = -math.atan2(d[2], math.hypot(d[0], d[1]))
                quat = quat_from_rpy(0.0, pitch, yaw)
                rot = Rotation.from_quat(quat)
                # The deck's top face is the road surface: centre sits half a thickness below it.
                centre = (pa + pb_) / 2 + rot.apply([0, 0, -deck.thickness_m / 2])
                half = [
                    length / 2 + self.settings.deck_piece_overlap_m,
                    deck.width_m / 2,
                    deck.thickness_m / 2,
                ]
                self.body_kind[_box(self.cid, centre.tolist(), half, quat, DECK_RGBA)] = "viaduct"
            pillar_marks = np.arange(s[first] + deck.pillar_spacing_m / 2, s[last], deck.pillar_spacing_m)
            for m in pillar_marks:
                p = np.array([np.interp(m, s, pts[:, k]) for k in range(3)])
                if p[2] < self.settings.pillar_min_z_m:
                    continue
                height = p[2] - deck.thickness_m
                self.body_kind[
                    _cylinder(self.cid, [p[0], p[1], 0.0], deck.pillar_radius_m, height, PILLAR_RGBA)
                ] = "pillar"

    def _build_static_objects(self) -> None:
        for obj in self.scene.spec.static_objects:
            x, y, z = obj.position_m
            sx, sy, sz = obj.size_m
            if obj.kind == "cylinder":
                body = _cylinder(self.cid, [x, y, z], sx / 2, sz, obj.rgba, obj.collision)
            else:
                body = _box(
                    self.cid,
                    [x, y, z + sz / 2],
                    [sx / 2, sy / 2, sz / 2],
                    quat_from_rpy(0, 0, obj.yaw_rad),
                    obj.rgba,
                    obj.collision,
                )
            self.body_kind[body] = obj.id
            if obj.kind == "signal_head":
                for lamp in _signal_lamps(self.cid, obj.position_m, obj.size_m, obj.yaw_rad, obj.collision):
                    self.body_kind[lamp] = obj.id


class VehicleWorld(_Client):
    """Vehicle bodies only; `update()` moves them to a set of poses (extra bodies are parked away)."""

    def __init__(
        self, scene: Scene, client: int | None = None, settings: WorldSettings | None = None
    ) -> None:
        if client is None:
            super().__init__()
        else:
            self.cid = client
        self.settings = world_settings(scene, settings)
        # The reference class's size: the body of a pose that gives none of its own.
        self.size_m = scene.spec.vehicle.size_m
        self.bodies: dict[str, int] = {}
        self.body_vehicle: dict[int, str] = {}
        self._looks: dict[str, tuple[tuple[float, float, float, float], tuple[float, float, float]]] = {}

    def size_of(self, pose: VehiclePose) -> tuple[float, float, float]:
        """The body size of the vehicle at `pose`: its own, else the scene's vehicle's."""
        return self.size_m if pose.size_m is None else pose.size_m

    def _create(
        self, vehicle_id: str, rgba: tuple[float, float, float, float], size_m: tuple[float, float, float]
    ) -> int:
        # Every class is the same body model scaled to its own box (no class-specific geometry).
        length, width, height = size_m
        z0 = -height / 2  # box centre frame
        c_lo, c_hi = CHASSIS_Z_FRACTION
        wheel_r = WHEEL_RADIUS_FRACTION * height
        chassis_half = [length / 2, width / 2 * 0.92, (c_hi - c_lo) * height / 2]
        chassis_pos = [0.0, 0.0, z0 + (c_lo + c_hi) / 2 * height]
        shell_half = [
            SHELL_FRACTION[0] * length / 2,
            SHELL_FRACTION[1] * width / 2,
            SHELL_FRACTION[2] * height / 2,
        ]
        shell_pos = [-0.05 * length, 0.0, z0 + c_hi * height + shell_half[2]]
        shapes = [pb.GEOM_BOX, pb.GEOM_BOX]
        halves = [chassis_half, shell_half]
        positions = [chassis_pos, shell_pos]
        colours = [list(rgba), [0.12, 0.12, 0.14, 1.0]]
        wheel_x = length / 2 - wheel_r * 1.4
        wheel_y = width / 2 - wheel_r * 0.6
        # Wheels are boxes: TinyRenderer draws every triangle of the world per render call, and four
        # tessellated cylinders per vehicle tripled the per-call cost of the camera ROI renders.
        wheel_half = [wheel_r, wheel_r * 0.55, wheel_r]
        vis = pb.createVisualShapeArray(
            shapeTypes=[*shapes, *[pb.GEOM_BOX] * 4],
            halfExtents=[*halves, *[wheel_half] * 4],
            rgbaColors=[*colours, *[list(TYRE_RGBA)] * 4],
            visualFramePositions=[
                *positions,
                *[[sx * wheel_x, sy * wheel_y, z0 + wheel_r] for sx in (1, -1) for sy in (1, -1)],
            ],
            physicsClientId=self.cid,
        )
        col = pb.createCollisionShapeArray(
            shapeTypes=shapes,
            halfExtents=halves,
            collisionFramePositions=positions,
            physicsClientId=self.cid,
        )
        body = pb.createMultiBody(0, col, vis, [0, 0, self.settings.parked_z_m], physicsClientId=self.cid)
        self.bodies[vehicle_id] = body
        self.body_vehicle[body] = vehicle_id
        self._looks[vehicle_id] = (rgba, size_m)
        return body

    def update(self, poses: list[VehiclePose]) -> None:
        seen = set()
        for pose in poses:
            body = self.bodies.get(pose.vehicle_id)
            looks = (pose.rgba, self.size_of(pose))
            if body is None:
                body = self._create(pose.vehicle_id, *looks)
            elif self._looks[pose.vehicle_id] != looks:  # repainted or resized: rebuild the body
                pb.removeBody(body, physicsClientId=self.cid)
                del self.body_vehicle[body]
                body = self._create(pose.vehicle_id, *looks)
            pb.resetBasePositionAndOrientation(
                body,
                list(pose.center_m),
                quat_from_rpy(0.0, pose.pitch_rad, pose.yaw_rad),
                physicsClientId=self.cid,
            )
            seen.add(pose.vehicle_id)
        for vid, body in self.bodies.items():
            if vid not in seen:
                pb.resetBasePositionAndOrientation(
                    body, [0, 0, self.settings.parked_z_m], [0, 0, 0, 1], physicsClientId=self.cid
                )


class FullWorld(StaticWorld):
    """Static scene and vehicles in one client (whole-scene renders, collision checks)."""

    def __init__(self, scene: Scene, settings: WorldSettings | None = None) -> None:
        super().__init__(scene, settings)
        self.vehicles = VehicleWorld(scene, client=self.cid, settings=self.settings)

    def update(self, poses: list[VehiclePose]) -> None:
        self.vehicles.update(poses)
