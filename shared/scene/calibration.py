"""Scene sensors as rmmdet.v1 calibration messages (what MECs and tools receive over the bus)."""

from __future__ import annotations

from rmmdet.v1.geometry_pb2 import Pose
from rmmdet.v1.sensors_pb2 import (
    CalibrationSet,
    CameraIntrinsics,
    LidarSpec,
    RadarSpec,
    SensorCalibration,
    SensorKind,
)

from shared.geometry.transforms import pose_from_matrix
from shared.scene.scene import Scene

_KIND = {
    "camera": SensorKind.SENSOR_KIND_CAMERA,
    "lidar": SensorKind.SENSOR_KIND_LIDAR,
    "radar": SensorKind.SENSOR_KIND_RADAR,
}


def _proto_fields(
    msg_type: type[LidarSpec] | type[RadarSpec], values: dict[str, object]
) -> dict[str, object]:
    """The scene model also holds simulation-only parameters (noise, clutter): keep the contract's."""
    names = set(msg_type.DESCRIPTOR.fields_by_name)
    return {k: v for k, v in values.items() if k in names}


def sensor_calibration(scene: Scene, sensor_id: str) -> SensorCalibration:
    s = scene.sensor(sensor_id)
    position, quat = pose_from_matrix(scene.T_world_from_sensor(sensor_id))
    pose = Pose()
    pose.position_m.x, pose.position_m.y, pose.position_m.z = (float(v) for v in position)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in quat)
    msg = SensorCalibration(
        sensor_id=s.id, agent_id=s.agent, kind=_KIND[s.kind], world_from_sensor=pose, rate_hz=s.rate_hz
    )
    if s.camera is not None:
        K = scene.K(s.id)
        msg.camera.CopyFrom(
            CameraIntrinsics(
                width_px=s.camera.width_px,
                height_px=s.camera.height_px,
                fx_px=float(K[0, 0]),
                fy_px=float(K[1, 1]),
                cx_px=float(K[0, 2]),
                cy_px=float(K[1, 2]),
                hfov_rad=s.camera.hfov_rad,
                distortion_model="plumb_bob" if s.camera.distortion else "",
                distortion=s.camera.distortion,
            )
        )
    elif s.lidar is not None:
        values = s.lidar.model_dump()
        values["vertical_min_rad"], values["vertical_max_rad"] = s.lidar.vertical_range_rad
        msg.lidar.CopyFrom(LidarSpec(**_proto_fields(LidarSpec, values)))
    elif s.radar is not None:
        msg.radar.CopyFrom(RadarSpec(**_proto_fields(RadarSpec, s.radar.model_dump())))
        msg.paired_camera_id = s.paired_camera or ""
    return msg


def calibration_set(scene: Scene, agent_id: str | None = None) -> CalibrationSet:
    """All sensors of one agent (or of the whole scene when `agent_id` is None)."""
    return CalibrationSet(
        scene_id=scene.scene_id,
        sensors=[sensor_calibration(scene, s.id) for s in scene.sensors_of(agent_id)],
    )
