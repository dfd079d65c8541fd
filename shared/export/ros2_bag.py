"""A run's object lists and plans as ROS 2 messages (CDR through the rosbags typestore), for a ROS 2
bag: each agent's object list as vision_msgs/msg/Detection3DArray (`/rmmdet/<agent>/objects`) and as
visualization_msgs/msg/MarkerArray (`/rmmdet/<agent>/markers`: a cube per object, its track id as the
marker id), each plan as nav_msgs/msg/Path (`/rmmdet/plans/<vehicle>`, shared/vehicle/ros2.py).

vision_msgs is not one of rosbags' built-in stores: its 4.x (Humble) definitions are registered from
the .msg files in shared/export/msg/. Boxes are in the scene's `world` frame; a Detection3D's id is
the track id and its one hypothesis the object's best class (the project's class name) and existence
probability.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rmmdet.v1.perception_pb2 import ObjectClass, TrackedObjects
from rosbags.typesys import get_types_from_msg

from shared.timebase import NS_PER_S
from shared.vehicle import ros2 as vehicle_ros2
from shared.vehicle.ros2 import ros_header, ros_pose

MSG_DIR = Path(__file__).parent / "msg"
DETECTIONS_TYPE = "vision_msgs/msg/Detection3DArray"
MARKERS_TYPE = "visualization_msgs/msg/MarkerArray"
MARKER_LIFETIME_S = 0.2  # two object-list periods: a marker not renewed disappears
CLASS_NAMES = {v: ObjectClass.Name(v).removeprefix("OBJECT_CLASS_").lower() for v in ObjectClass.values()}


def typestore() -> Any:
    """The vehicle's ROS 2 store (Humble + rmmdet_msgs) with vision_msgs registered."""
    store = vehicle_ros2.typestore()
    types: dict[str, Any] = {}
    for path in sorted((MSG_DIR / "vision_msgs").glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"vision_msgs/msg/{path.stem}"))
    store.register(types)
    return store


def detections_cdr(objects: TrackedObjects, store: Any) -> bytes:
    """An object list as a CDR vision_msgs/msg/Detection3DArray."""
    types = store.types
    header = ros_header(store, objects.header.stamp.ToNanoseconds())
    detections = []
    for obj in objects.objects:
        box = obj.box
        pose = ros_pose(store, box.center_m.x, box.center_m.y, box.center_m.z, box.yaw_rad)
        best = max(obj.classification, key=lambda h: h.probability, default=None)
        hypothesis = types["vision_msgs/msg/ObjectHypothesis"](
            class_id=CLASS_NAMES.get(best.label, "unknown") if best is not None else "unknown",
            score=float(obj.existence_probability),
        )
        covariance = types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_covariance(obj))
        detections.append(
            types["vision_msgs/msg/Detection3D"](
                header=header,
                results=[
                    types["vision_msgs/msg/ObjectHypothesisWithPose"](hypothesis=hypothesis, pose=covariance)
                ],
                bbox=types["vision_msgs/msg/BoundingBox3D"](
                    center=pose,
                    size=types["geometry_msgs/msg/Vector3"](x=box.size_m.x, y=box.size_m.y, z=box.size_m.z),
                ),
                id=str(obj.track_id),
            )
        )
    msg = types[DETECTIONS_TYPE](header=header, detections=detections)
    return bytes(store.serialize_cdr(msg, DETECTIONS_TYPE))


def _covariance(obj: Any) -> Any:
    """ROS's 6x6 pose covariance (x y z roll pitch yaw) from the track's 3x3 position covariance and
    yaw variance; unknown entries 0."""
    cov = np.zeros((6, 6))
    if len(obj.position_covariance_m2) == 9:
        cov[:3, :3] = np.reshape(obj.position_covariance_m2, (3, 3))
    cov[5, 5] = obj.yaw_variance_rad2
    return cov.reshape(36)


def markers_cdr(objects: TrackedObjects, store: Any) -> bytes:
    """An object list as a CDR visualization_msgs/msg/MarkerArray of cubes (ADD, short lifetime)."""
    types = store.types
    header = ros_header(store, objects.header.stamp.ToNanoseconds())
    marker_cls = types["visualization_msgs/msg/Marker"]
    lifetime = types["builtin_interfaces/msg/Duration"](sec=0, nanosec=int(MARKER_LIFETIME_S * NS_PER_S))
    markers = []
    for obj in objects.objects:
        box = obj.box
        markers.append(
            marker_cls(
                header=header,
                ns=objects.agent_id,
                id=int(obj.track_id) % 2**31,
                type=marker_cls.CUBE,
                action=marker_cls.ADD,
                pose=ros_pose(store, box.center_m.x, box.center_m.y, box.center_m.z, box.yaw_rad),
                scale=types["geometry_msgs/msg/Vector3"](x=box.size_m.x, y=box.size_m.y, z=box.size_m.z),
                color=types["std_msgs/msg/ColorRGBA"](r=0.1, g=0.6, b=1.0, a=0.6),
                lifetime=lifetime,
                frame_locked=False,
                points=[],
                colors=[],
                texture_resource="",
                texture=types["sensor_msgs/msg/CompressedImage"](
                    header=header, format="", data=np.zeros(0, np.uint8)
                ),
                uv_coordinates=[],
                text="",
                mesh_resource="",
                mesh_file=types["visualization_msgs/msg/MeshFile"](filename="", data=np.zeros(0, np.uint8)),
                mesh_use_embedded_materials=False,
            )
        )
    return bytes(store.serialize_cdr(types[MARKERS_TYPE](markers=markers), MARKERS_TYPE))
