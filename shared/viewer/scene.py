"""The live 3D view as Foxglove messages: pure functions from the scene and bus messages to Foxglove's
protobuf schemas (`foxglove_schemas_protobuf`, the types the bus already uses for images and clouds;
no bus, no server: the viewer service and MCAP export call them alike).

Everything is drawn in the `world` frame of the table (metres, z up), except what a lidar or radar
sees: that stays in the sensor's own frame, placed by `sensor_frames` (world -> sensor). Entity ids
are stable per thing (`lane/<id>`, `<agent>/track/<id>`, `plan/<vehicle>`, ...) so an update replaces
what it drew before, and every dynamic entity carries a `lifetime` so that what stops being published
(a track dropped, an agent gone) disappears on its own instead of freezing in the view.

Tracked boxes are coloured by the modalities that updated them in the latest frame (the paper's fusion
branches): lidar + camera green, radar + camera orange, lidar alone blue, radar alone purple, camera
alone yellow, none (coasting) grey; a coasting track is drawn translucent. Ids are text above the box,
velocities arrows from its centre (length = 1 s of travel).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from foxglove_schemas_protobuf.ArrowPrimitive_pb2 import ArrowPrimitive
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Grid_pb2 import Grid
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.Vector2_pb2 import Vector2
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.duration_pb2 import Duration
from google.protobuf.timestamp_pb2 import Timestamp
from rmmdet.v1 import perception_pb2 as pb
from rmmdet.v1.geometry_pb2 import Box3D
from rmmdet.v1.planning_pb2 import RoutePlan
from rmmdet.v1.sensors_pb2 import RadarScan
from rmmdet.v1.sim_pb2 import GroundTruth
from rmmdet.v1.traffic_pb2 import TrafficMap
from scipy.spatial.transform import Rotation

from shared.geometry.transforms import polar_to_cartesian
from shared.scene.model import SensorSpec
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S

FRAME = "world"
DYNAMIC_LIFETIME_S = 0.5  # a track or vehicle not redrawn for this long disappears
PLAN_LIFETIME_S = 5.0
PLAN_LIFT_M = 0.02  # plans are drawn this far above the lanes they follow
LANE_COLOR = Color(r=0.55, g=0.55, b=0.6, a=1.0)
JUNCTION_COLOR = Color(r=1.0, g=1.0, b=1.0, a=1.0)
FOV_COLOR = {"camera": Color(r=1.0, g=0.9, b=0.2, a=0.6), "lidar": Color(r=0.2, g=0.6, b=1.0, a=0.6)}
FOV_COLOR["radar"] = Color(r=0.8, g=0.3, b=1.0, a=0.6)
GROUND_TRUTH_COLOR = Color(r=0.85, g=0.85, b=0.85, a=0.35)
PLAN_COLOR = Color(r=0.1, g=0.9, b=0.9, a=0.9)
CAMERA_RANGE_M = 2.0  # cameras have no range: their field of view is drawn this long
MODALITY_COLORS: dict[frozenset[int], Color] = {
    frozenset({pb.MODALITY_LIDAR, pb.MODALITY_CAMERA}): Color(r=0.2, g=0.85, b=0.3, a=0.8),
    frozenset({pb.MODALITY_RADAR, pb.MODALITY_CAMERA}): Color(r=1.0, g=0.55, b=0.1, a=0.8),
    frozenset({pb.MODALITY_LIDAR}): Color(r=0.2, g=0.5, b=1.0, a=0.8),
    frozenset({pb.MODALITY_RADAR}): Color(r=0.6, g=0.3, b=0.9, a=0.8),
    frozenset({pb.MODALITY_CAMERA}): Color(r=1.0, g=0.9, b=0.2, a=0.8),
}
COASTING_COLOR = Color(r=0.6, g=0.6, b=0.6, a=0.35)


def timestamp(stamp_ns: int) -> Timestamp:
    t = Timestamp()
    t.FromNanoseconds(stamp_ns)
    return t


def duration(seconds: float) -> Duration:
    d = Duration()
    d.FromNanoseconds(round(seconds * NS_PER_S))
    return d


def yaw_quaternion(yaw_rad: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


def pose(x: float, y: float, z: float, yaw_rad: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=yaw_quaternion(yaw_rad))


def line_strip(points: Iterable[Sequence[float]], color: Color, thickness_m: float) -> LinePrimitive:
    return LinePrimitive(
        type=LinePrimitive.LINE_STRIP,
        pose=pose(0.0, 0.0, 0.0),
        thickness=thickness_m,
        points=[Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]) if len(p) > 2 else 0.0) for p in points],
        color=color,
    )


def label(x: float, y: float, z: float, text: str, color: Color, font_size: float) -> TextPrimitive:
    """Text at (x, y, z) that always faces the viewer."""
    return TextPrimitive(pose=pose(x, y, z), billboard=True, font_size=font_size, color=color, text=text)


def modality_color(modalities: Iterable[int], coasting: bool) -> Color:
    """The colour of a track from the modalities that updated it (see the module doc)."""
    if coasting:
        return COASTING_COLOR
    return MODALITY_COLORS.get(frozenset(modalities), COASTING_COLOR)


# --- the table (static) -------------------------------------------------------------------------


def table(scene: Scene, network: RoadNetwork, stamp_ns: int) -> SceneUpdate:
    """Lanes (centrelines), junctions with their flow-count numbers, and every sensor with its field
    of view (a wedge at its mounting height, as long as its range). Static: no lifetime."""
    entities = []
    for lane_id, path in network.lanes.items():
        entities.append(
            SceneEntity(
                timestamp=timestamp(stamp_ns),
                frame_id=FRAME,
                id=f"lane/{lane_id}",
                lines=[line_strip(path.points, LANE_COLOR, 0.01)],
            )
        )
    for junction in scene.spec.junctions:
        x, y, z = junction.position_m
        entities.append(
            SceneEntity(
                timestamp=timestamp(stamp_ns),
                frame_id=FRAME,
                id=f"junction/{junction.id}",
                texts=[label(x, y, z + 0.1, str(junction.number), JUNCTION_COLOR, 0.15)],
            )
        )
    for spec in scene.spec.sensors:
        entities.append(
            SceneEntity(
                timestamp=timestamp(stamp_ns),
                frame_id=FRAME,
                id=f"sensor/{spec.id}",
                lines=[line_strip(fov_wedge(spec), FOV_COLOR[spec.kind], 0.005)],
                texts=[label(*spec.pose.position_m, spec.id, FOV_COLOR[spec.kind], 0.06)],
            )
        )
    return SceneUpdate(entities=entities)


def fov_wedge(spec: SensorSpec, steps: int = 12) -> list[tuple[float, float, float]]:
    """The horizontal field of view of a sensor as a closed outline: apex at the sensor, an arc at its
    range (cameras: CAMERA_RANGE_M; a spinning lidar: the whole circle), at the sensor's height."""
    x, y, z = spec.pose.position_m
    yaw = sensor_yaw(spec)
    if spec.lidar is not None:
        hfov, reach = 2 * math.pi, spec.lidar.max_range_m
    elif spec.radar is not None:
        hfov, reach = spec.radar.hfov_rad, spec.radar.max_range_m
    else:
        assert spec.camera is not None  # SensorSpec validates that its kind's model is given
        hfov, reach = spec.camera.hfov_rad, CAMERA_RANGE_M
    arc = [
        (x + reach * math.cos(a), y + reach * math.sin(a), z)
        for a in (yaw - hfov / 2 + hfov * k / steps for k in range(steps + 1))
    ]
    return [(x, y, z), *arc, (x, y, z)]


def sensor_yaw(spec: SensorSpec) -> float:
    """Heading of a sensor's +x axis in the table plane, rad."""
    if spec.pose.rpy_rad is not None:
        return float(spec.pose.rpy_rad[2])
    assert spec.pose.quat_xyzw is not None  # PoseSpec holds exactly one of the two
    qx, qy, qz, qw = spec.pose.quat_xyzw
    return math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


# --- dynamic layers -----------------------------------------------------------------------------


def box_entity(
    entity_id: str,
    box: Box3D,
    color: Color,
    text: str,
    label_z_m: float,
    stamp_ns: int,
    arrows: Sequence[ArrowPrimitive] = (),
) -> SceneEntity:
    """A box (its yaw about z) with a label above or below it, living DYNAMIC_LIFETIME_S."""
    c, size = box.center_m, box.size_m
    return SceneEntity(
        timestamp=timestamp(stamp_ns),
        frame_id=FRAME,
        id=entity_id,
        lifetime=duration(DYNAMIC_LIFETIME_S),
        cubes=[
            CubePrimitive(
                pose=pose(c.x, c.y, c.z, box.yaw_rad), size=Vector3(x=size.x, y=size.y, z=size.z), color=color
            )
        ],
        texts=[label(c.x, c.y, label_z_m, text, color, 0.05)],
        arrows=list(arrows),
    )


def tracked_objects(agent_id: str, msg: pb.TrackedObjects, stamp_ns: int) -> SceneUpdate:
    """One agent's tracks: boxes coloured by modality and state, ids, velocity arrows."""
    entities = []
    for obj in msg.objects:
        b = obj.box
        coasting = obj.state == pb.TRACK_STATE_COASTING
        color = modality_color(obj.modalities, coasting)
        vx, vy = obj.velocity_mps.x, obj.velocity_mps.y
        speed = math.hypot(vx, vy)
        top = b.center_m.z + b.size_m.z / 2
        arrows = []
        if speed > 1e-3:
            arrows.append(
                ArrowPrimitive(
                    pose=pose(b.center_m.x, b.center_m.y, top, math.atan2(vy, vx)),
                    shaft_length=speed,
                    shaft_diameter=0.01,
                    head_length=0.04,
                    head_diameter=0.03,
                    color=color,
                )
            )
        entities.append(
            box_entity(
                f"{agent_id}/track/{obj.track_id}",
                b,
                color,
                f"{agent_id}:{obj.track_id}",
                top + 0.05,
                stamp_ns,
                arrows,
            )
        )
    return SceneUpdate(entities=entities)


def route_plan(msg: RoutePlan, network: RoadNetwork, stamp_ns: int) -> SceneUpdate:
    """A vehicle's planned lanes as one line strip, labelled with the vehicle id and plan version."""
    points = [
        (float(p[0]), float(p[1]), (float(p[2]) if len(p) > 2 else 0.0) + PLAN_LIFT_M)
        for lane in msg.lane_ids
        if lane in network.lanes
        for p in network.lanes[lane].points
    ]
    if not points:
        return SceneUpdate()
    x, y, z = points[0]
    return SceneUpdate(
        entities=[
            SceneEntity(
                timestamp=timestamp(stamp_ns),
                frame_id=FRAME,
                id=f"plan/{msg.vehicle_id}",
                lifetime=duration(PLAN_LIFETIME_S),
                lines=[line_strip(points, PLAN_COLOR, 0.015)],
                texts=[label(x, y, z + 0.1, f"{msg.vehicle_id} v{msg.version}", PLAN_COLOR, 0.05)],
            )
        ]
    )


def ground_truth(msg: GroundTruth, stamp_ns: int) -> SceneUpdate:
    """The simulated vehicles as they are (a layer of its own, to hide): translucent boxes with ids."""
    entities = []
    for v in msg.vehicles:
        b = v.box
        below = b.center_m.z - b.size_m.z / 2 - 0.03
        entities.append(
            box_entity(f"gt/{v.vehicle_id}", b, GROUND_TRUTH_COLOR, v.vehicle_id, below, stamp_ns)
        )
    return SceneUpdate(entities=entities)


#: Cell layout of the traffic grid: smoothed vehicles per cell, then their mean speed (float32 each).
GRID_FIELDS = (("vehicles", 0), ("mean_speed_mps", 4))
GRID_CELL_BYTES = 8


def traffic_grid(msg: TrafficMap, stamp_ns: int) -> Grid:
    """The coordinator's density / speed grid as a Foxglove Grid (colour it by either field)."""
    g = msg.grid
    cols, rows = int(g.column_count), int(g.row_count)
    cells = np.zeros((rows * cols, 2), dtype="<f4")
    if len(g.vehicle_count) == rows * cols:
        cells[:, 0] = g.vehicle_count
    if len(g.mean_speed_mps) == rows * cols:
        cells[:, 1] = g.mean_speed_mps
    return Grid(
        timestamp=timestamp(stamp_ns),
        frame_id=FRAME,
        pose=pose(g.origin_m.x_m, g.origin_m.y_m, 0.0),
        column_count=cols,
        cell_size=Vector2(x=g.cell_size_m, y=g.cell_size_m),
        row_stride=cols * GRID_CELL_BYTES,
        cell_stride=GRID_CELL_BYTES,
        fields=[
            PackedElementField(name=n, offset=o, type=PackedElementField.FLOAT32) for n, o in GRID_FIELDS
        ],
        data=cells.tobytes(),
    )


DETECTION_COLOR = Color(r=0.2, g=1.0, b=0.3, a=1.0)
DETECTION_TEXT_BACKGROUND = Color(r=0.0, g=0.0, b=0.0, a=0.6)


def image_annotations(msg: pb.Detection2DArray, stamp_ns: int) -> ImageAnnotations:
    """A camera's 2D detections as annotations over its image: each box an outline, its score above
    it. Stamped with the image's own stamp so a viewer pairs them with the frame they were found in."""
    out = ImageAnnotations()
    for d in msg.detections:
        b = d.box
        u0, v0 = b.center_u_px - b.width_px / 2, b.center_v_px - b.height_px / 2
        u1, v1 = u0 + b.width_px, v0 + b.height_px
        box = out.points.add(type=PointsAnnotation.LINE_LOOP, outline_color=DETECTION_COLOR, thickness=2.0)
        box.timestamp.CopyFrom(timestamp(stamp_ns))
        box.points.extend(Point2(x=u, y=v) for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1)))
        name = pb.ObjectClass.Name(d.classification[0].label) if d.classification else "OBJECT_CLASS_UNKNOWN"
        text = out.texts.add(
            text=f"{name.removeprefix('OBJECT_CLASS_').lower()} {d.score:.2f}",
            font_size=12.0,
            text_color=DETECTION_COLOR,
            background_color=DETECTION_TEXT_BACKGROUND,
        )
        text.timestamp.CopyFrom(timestamp(stamp_ns))
        text.position.CopyFrom(Point2(x=u0, y=max(0.0, v0 - 14.0)))
    return out


SENSOR_FRAME_KINDS = ("lidar", "radar")  # whose data is drawn in 3D in its own frame
RADAR_APPROACHING = Color(r=1.0, g=0.35, b=0.2, a=0.9)  # range rate < 0
RADAR_RECEDING = Color(r=0.3, g=0.6, b=1.0, a=0.9)
RADAR_TARGET_SIZE_M = 0.06


def sensor_frames(scene: Scene, stamp_ns: int) -> FrameTransforms:
    """`world` -> each lidar's and radar's body frame (+x forward, +y left, +z up), so a viewer places
    their clouds and targets (which come in those frames) on the table."""
    out = FrameTransforms()
    for spec in scene.spec.sensors:
        if spec.kind not in SENSOR_FRAME_KINDS:
            continue
        T = np.asarray(scene.T_world_from_sensor(spec.id), float)
        qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
        tf = out.transforms.add(parent_frame_id=FRAME, child_frame_id=spec.id)
        tf.timestamp.CopyFrom(timestamp(stamp_ns))
        tf.translation.CopyFrom(Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]))
        tf.rotation.CopyFrom(Quaternion(x=qx, y=qy, z=qz, w=qw))
    return out


def radar_targets(msg: RadarScan, stamp_ns: int) -> SceneUpdate:
    """A radar's targets in its own frame: a sphere each, red approaching, blue receding, its range
    rate beside it."""
    spheres, texts = [], []
    polar = np.array([[t.range_m, t.azimuth_rad, t.elevation_rad] for t in msg.targets]).reshape(-1, 3)
    points = polar_to_cartesian(polar[:, 0], polar[:, 1], polar[:, 2])
    for t, (x, y, z) in zip(msg.targets, points.tolist(), strict=True):
        color = RADAR_APPROACHING if t.range_rate_mps < 0 else RADAR_RECEDING
        size = Vector3(x=RADAR_TARGET_SIZE_M, y=RADAR_TARGET_SIZE_M, z=RADAR_TARGET_SIZE_M)
        spheres.append(SpherePrimitive(pose=pose(x, y, z), size=size, color=color))
        texts.append(label(x, y, z + RADAR_TARGET_SIZE_M, f"{t.range_rate_mps:+.2f} m/s", color, 0.04))
    entity = SceneEntity(
        timestamp=timestamp(stamp_ns),
        frame_id=msg.sensor_id,
        id=f"radar/{msg.sensor_id}",
        lifetime=duration(DYNAMIC_LIFETIME_S),
        spheres=spheres,
        texts=texts,
    )
    return SceneUpdate(entities=[entity])
