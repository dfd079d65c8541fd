"""A ROS 2 vehicle's side of its plans: the plan as nav_msgs/msg/Path and the car's answer as
rmmdet_msgs/msg/PlanAck, both CDR (the rosbags typestore), on the Zenoh keys `zenoh-bridge-ros2dds`
maps the car's topics to.

The bridge sees a ROS 2 topic `/rmmdet/plan` of a car whose bridge runs with `namespace: "/<id>"` as
the Zenoh key `<id>/rmmdet/plan` (the namespace is added to every interface routed to Zenoh, the
leading slash dropped; zenoh-plugin-ros2dds DEFAULT_CONFIG.json5), and carries CDR payloads as they
are. So the vehicle client puts a Path's CDR on `<id>/rmmdet/plan` (the car subscribes to
`/rmmdet/plan`) and hears the car's PlanAck on `<id>/rmmdet/plan_ack` (the car publishes
`/rmmdet/plan_ack`). Bridge configuration: deploy/ros2/.

The Path is in the scene's `world` frame: the points of every lane of the plan in order (a lane's
first point dropped where it repeats the previous lane's last), each pose facing along its lane. Its
header stamp is the plan's issue time (its version, µs), unique per plan: the car's PlanAck echoes it
as `path_stamp`, which is how the client knows which plan an answer is for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from rmmdet.v1.planning_pb2 import RoutePlan
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from shared.paths import DEPLOY_DIR
from shared.scene.road_network import RoadNetwork
from shared.timebase import NS_PER_S
from shared.traffic.plans import Ack

PATH_TYPE = "nav_msgs/msg/Path"
PLAN_ACK_TYPE = "rmmdet_msgs/msg/PlanAck"
PLAN_ACK_MSG = DEPLOY_DIR / "ros2" / "rmmdet_msgs" / "msg" / "PlanAck.msg"
PLAN_TOPIC = "rmmdet/plan"
PLAN_ACK_TOPIC = "rmmdet/plan_ack"
FRAME_ID = "world"
MAX_PLAN_ACK_BYTES = 4096  # a PlanAck is a stamp, a byte and a short reason


def typestore() -> Any:
    """ROS 2 Humble's types and rmmdet_msgs/msg/PlanAck (from its .msg file in deploy/ros2)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(PLAN_ACK_MSG.read_text(), PLAN_ACK_TYPE))
    return store


def bridge_key(namespace: str, topic: str) -> str:
    """The Zenoh key zenoh-bridge-ros2dds routes `topic` of a bridge running with `namespace` on.

    >>> bridge_key("/v03", "/rmmdet/plan")
    'v03/rmmdet/plan'
    """
    parts = [p for p in (namespace.strip("/"), topic.strip("/")) if p]
    return "/".join(parts)


def path_stamp_ns(version: int) -> int:
    """The stamp of a plan's Path: its version (issue time, µs) in ns."""
    return version * 1000


def plan_poses(plan: RoutePlan, network: RoadNetwork) -> np.ndarray:
    """(N, 4) x, y, z, heading of the plan's lanes in order; ValueError naming an unknown lane."""
    rows: list[np.ndarray] = []
    for lane_id in plan.lane_ids:
        lane = network.lanes.get(lane_id)
        if lane is None:
            raise ValueError(f"plan {plan.plan_id}: lane {lane_id!r} is not in the road network")
        points = np.column_stack([lane.points, lane.heading])
        if rows and np.allclose(rows[-1][-1, :3], points[0, :3]):
            points = points[1:]
        rows.append(points)
    return np.concatenate(rows) if rows else np.zeros((0, 4))


def ros_header(store: Any, stamp_ns: int, frame_id: str = FRAME_ID) -> Any:
    """A std_msgs/msg/Header at `stamp_ns` (ROS 1's, which also numbers messages, with seq 0)."""
    sec, nanosec = divmod(stamp_ns, NS_PER_S)
    time_cls, header_cls = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    seq = {"seq": 0} if "seq" in header_cls.__dataclass_fields__ else {}
    return header_cls(**seq, stamp=time_cls(sec=sec, nanosec=nanosec), frame_id=frame_id)


def ros_pose(store: Any, x: float, y: float, z: float, yaw_rad: float) -> Any:
    """A geometry_msgs/msg/Pose at (x, y, z), m, turned `yaw_rad` about z."""
    types = store.types
    quat = types["geometry_msgs/msg/Quaternion"]
    return types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
        orientation=quat(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2)),
    )


def plan_path_cdr(plan: RoutePlan, network: RoadNetwork, store: Any) -> bytes:
    """The plan as a CDR nav_msgs/msg/Path (module docstring)."""
    header = ros_header(store, path_stamp_ns(int(plan.version)))
    stamped = store.types["geometry_msgs/msg/PoseStamped"]
    poses = [
        stamped(header=header, pose=ros_pose(store, x, y, z, h)) for x, y, z, h in plan_poses(plan, network)
    ]
    return bytes(store.serialize_cdr(store.types[PATH_TYPE](header=header, poses=poses), PATH_TYPE))


@dataclass(frozen=True)
class CarAnswer:
    """A car's PlanAck: which plan (by the Path's stamp, ns) and its decision."""

    path_stamp_ns: int
    status: Ack
    reason: str


def parse_plan_ack(cdr: bytes, store: Any) -> CarAnswer:
    """A CDR rmmdet_msgs/msg/PlanAck; ValueError saying why it is not one."""
    if len(cdr) > MAX_PLAN_ACK_BYTES:
        raise ValueError(f"PlanAck of {len(cdr)} B > {MAX_PLAN_ACK_BYTES} B")
    try:
        msg = store.deserialize_cdr(cdr, PLAN_ACK_TYPE)
    except Exception as exc:  # rosbags raises assorted errors on truncated or foreign bytes
        raise ValueError(f"not a CDR {PLAN_ACK_TYPE}: {type(exc).__name__}: {exc}") from None
    try:
        status = Ack(msg.status)
    except ValueError:
        raise ValueError(f"PlanAck status {msg.status} is none of {[a.value for a in Ack]}") from None
    return CarAnswer(msg.path_stamp.sec * NS_PER_S + msg.path_stamp.nanosec, status, msg.reason)


def plan_ack_cdr(path_stamp_ns: int, status: Ack, reason: str, store: Any) -> bytes:
    """A CDR PlanAck, as a ROS 2 car would publish it (tests and tools)."""
    types = store.types
    stamp = types["builtin_interfaces/msg/Time"](
        sec=path_stamp_ns // NS_PER_S, nanosec=path_stamp_ns % NS_PER_S
    )
    msg = types[PLAN_ACK_TYPE](path_stamp=stamp, status=status.value, reason=reason)
    return bytes(store.serialize_cdr(msg, PLAN_ACK_TYPE))
