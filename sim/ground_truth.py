"""Ground-truth messages from the traffic state, and vehicle poses back from them (sensor side)."""

from __future__ import annotations

import math

from rmmdet.v1.perception_pb2 import ObjectClass
from rmmdet.v1.sim_pb2 import GroundTruth, JunctionFlow, SimClock, VehicleGroundTruth

from shared.scene.model import VehicleLabel
from shared.scene.scene import Scene
from sim.traffic import TrafficSim
from sim.world import VehiclePose

#: A vehicle class's ground-truth label (shared/scene/model.py VehicleLabel) as the message's enum.
OBJECT_CLASS: dict[VehicleLabel, int] = {
    "car": ObjectClass.OBJECT_CLASS_CAR,
    "truck": ObjectClass.OBJECT_CLASS_TRUCK,
    "bus": ObjectClass.OBJECT_CLASS_BUS,
}
RGBA_BITS = 8
RGBA_MAX = (1 << RGBA_BITS) - 1


def pack_rgba(rgba: tuple[float, float, float, float]) -> int:
    """RGBA in [0, 1] -> 0xRRGGBBAA."""
    out = 0
    for c in rgba:
        out = (out << RGBA_BITS) | round(min(max(c, 0.0), 1.0) * RGBA_MAX)
    return out


def unpack_rgba(value: int) -> tuple[float, float, float, float]:
    r, g, b, a = ((value >> shift) & RGBA_MAX for shift in (24, 16, 8, 0))
    return (r / RGBA_MAX, g / RGBA_MAX, b / RGBA_MAX, a / RGBA_MAX)


def ground_truth_message(traffic: TrafficSim, scene: Scene, seed: int, tick_hz: float) -> GroundTruth:
    """World state of the current tick (header left to the publisher)."""
    msg = GroundTruth(seed=seed, tick_hz=tick_hz)
    for v in traffic.vehicles:
        h = v.body.height_m
        gt = VehicleGroundTruth(
            vehicle_id=v.id,
            label=OBJECT_CLASS[v.body.label],
            vehicle_class=v.body.name,
            yaw_rate_radps=v.yaw_rate,
            lane_id=v.path.id,
            lane_progress_m=max(v.s, 0.0),
            area_id=scene.area_of(v.x, v.y, v.z) or "",
            destination_junction_id=v.destination,
            color_rgba=pack_rgba(v.rgba),
            connected=v.connected,
            pitch_rad=v.pitch,
            speed_mps=v.v,
        )
        c = gt.box.center_m
        # Box centre: half a body height above the road surface, along the body's up axis.
        c.x = v.x + math.sin(v.pitch) * math.cos(v.yaw) * h / 2
        c.y = v.y + math.sin(v.pitch) * math.sin(v.yaw) * h / 2
        c.z = v.z + math.cos(v.pitch) * h / 2
        gt.box.size_m.x, gt.box.size_m.y, gt.box.size_m.z = v.body.size_m
        gt.box.yaw_rad = v.yaw
        gt.velocity_mps.x, gt.velocity_mps.y, gt.velocity_mps.z = v.velocity_mps
        msg.vehicles.append(gt)
    for junction in scene.spec.junctions:
        msg.junction_flows.append(
            JunctionFlow(
                junction_id=junction.id, number=junction.number, arrivals=traffic.arrivals[junction.id]
            )
        )
    return msg


def sim_clock_message(
    traffic: TrafficSim, stamp_ns: int, real_time_factor: float, target_speed: float, paced_by: str
) -> SimClock:
    """The sim clock of the current tick: sim time `stamp_ns` (wall ns), the measured real-time factor,
    the target speed (0 = as fast as possible) and the consumer holding the sim ("" when none)."""
    clock = SimClock(
        tick=traffic.tick,
        step_s=traffic.dt,
        real_time_factor=real_time_factor,
        lock_step=False,
        target_speed=target_speed,
        paced_by=paced_by,
    )
    clock.sim_time.FromNanoseconds(stamp_ns)
    return clock


def _box_size(v: VehicleGroundTruth) -> tuple[float, float, float] | None:
    """The vehicle's own box size; None for a message that gives none (the scene's vehicle then)."""
    size = (v.box.size_m.x, v.box.size_m.y, v.box.size_m.z)
    return size if all(d > 0 for d in size) else None


def poses_from_ground_truth(msg: GroundTruth) -> list[VehiclePose]:
    return [
        VehiclePose(
            vehicle_id=v.vehicle_id,
            center_m=(v.box.center_m.x, v.box.center_m.y, v.box.center_m.z),
            yaw_rad=v.box.yaw_rad,
            pitch_rad=v.pitch_rad,
            rgba=unpack_rgba(v.color_rgba),
            size_m=_box_size(v),
        )
        for v in msg.vehicles
    ]
