"""Pipeline result -> `rmmdet.v1.TrackedObjects` (the MEC's output message, without its header), and a
camera's 2D detections -> `rmmdet.v1.Detection2DArray` (for the live view)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from rmmdet.v1 import perception_pb2 as pb

from shared.detection.interface import CAMERA_COLUMNS
from shared.perception.inputs import InputReport, InputState, Status
from shared.perception.pipeline import AgentResult
from shared.tracking.track_table import Track, TrackState

MODALITY = {"camera": pb.MODALITY_CAMERA, "lidar": pb.MODALITY_LIDAR, "radar": pb.MODALITY_RADAR}
STATUS = {
    Status.FULL: pb.PERCEPTION_STATUS_FULL,
    Status.DEGRADED: pb.PERCEPTION_STATUS_DEGRADED,
    Status.UNAVAILABLE: pb.PERCEPTION_STATUS_UNAVAILABLE,
}
INPUT_STATE = {
    InputState.OK: pb.INPUT_STATE_OK,
    InputState.STALE: pb.INPUT_STATE_STALE,
    InputState.MISSING: pb.INPUT_STATE_MISSING,
}
TRACK_STATE = {
    TrackState.TENTATIVE: pb.TRACK_STATE_TENTATIVE,
    TrackState.CONFIRMED: pb.TRACK_STATE_CONFIRMED,
    TrackState.COASTING: pb.TRACK_STATE_COASTING,
}
# Yaw variance reported when the heading is unknown (uniform over a half turn), rad^2.
UNKNOWN_YAW_VARIANCE_RAD2 = (np.pi**2) / 12


def track_to_message(track: Track, out: pb.TrackedObject, default_size_m: tuple[float, float, float]) -> None:
    """`track` into `out`; a track no sensor has sized (radar only) gets `default_size_m` (the scene's
    car: length, width, height, m)."""
    out.track_id = track.track_id
    out.existence_probability = float(np.clip(track.existence_probability, 0.0, 1.0))
    out.classification.add(label=pb.OBJECT_CLASS_CAR, probability=1.0)
    pos = track.position_m
    out.box.center_m.x, out.box.center_m.y, out.box.center_m.z = float(pos[0]), float(pos[1]), track.z_m
    size = track.size_m if track.size_m is not None else default_size_m
    out.box.size_m.x, out.box.size_m.y, out.box.size_m.z = (float(v) for v in size)
    if track.yaw_rad is None:
        out.orientation_availability = pb.ORIENTATION_AVAILABILITY_UNAVAILABLE
        out.yaw_variance_rad2 = UNKNOWN_YAW_VARIANCE_RAD2
    else:
        out.box.yaw_rad = float(track.yaw_rad)
        out.orientation_availability = (
            pb.ORIENTATION_AVAILABILITY_AVAILABLE
            if track.heading_sign_known
            else pb.ORIENTATION_AVAILABILITY_SIGN_UNKNOWN
        )
    vel = track.velocity_mps
    out.velocity_mps.x, out.velocity_mps.y = float(vel[0]), float(vel[1])
    cov = np.zeros((3, 3))
    cov[:2, :2] = track.position_cov_m2
    out.position_covariance_m2.extend(cov.ravel().tolist())
    vcov = np.zeros((3, 3))
    vcov[:2, :2] = track.velocity_cov_m2ps2
    out.velocity_covariance_m2ps2.extend(vcov.ravel().tolist())
    out.modalities.extend(MODALITY[m] for m in sorted(track.modalities))
    out.state = TRACK_STATE[track.state]
    out.age_frames = track.age_frames
    out.consecutive_misses = track.consecutive_misses


def tracked_objects_message(
    result: AgentResult,
    agent_id: str,
    status: Status,
    inputs: Sequence[InputReport],
    kinds: Mapping[str, str],
    default_size_m: tuple[float, float, float],
) -> pb.TrackedObjects:
    msg = pb.TrackedObjects(agent_id=agent_id, status=STATUS[status])
    for r in inputs:
        msg.inputs.add(
            sensor_id=r.sensor_id,
            modality=MODALITY[kinds[r.sensor_id]],
            state=INPUT_STATE[r.state],
            age_s=r.age_s,
        )
    for stage, seconds in result.latencies_s.items():
        msg.stage_latencies.add(stage=stage, duration_s=seconds)
    for track in result.tracks:
        track_to_message(track, msg.objects.add(), default_size_m)
    return msg


_X0, _Y0, _X1, _Y1, _SCORE = (CAMERA_COLUMNS.index(c) for c in ("x0", "y0", "x1", "y1", "score"))


def detections_2d_message(
    sensor_id: str, boxes: np.ndarray, width_px: int, height_px: int
) -> pb.Detection2DArray:
    """One camera's detections (the detector's (N, 6) rows, pixels of the image it saw) as a
    Detection2DArray: centre and size in pixels, the score, class car (the table's only class)."""
    msg = pb.Detection2DArray(sensor_id=sensor_id, image_width_px=width_px, image_height_px=height_px)
    for row in np.asarray(boxes, float):
        d = msg.detections.add(score=float(row[_SCORE]))
        d.box.center_u_px = (row[_X0] + row[_X1]) / 2
        d.box.center_v_px = (row[_Y0] + row[_Y1]) / 2
        d.box.width_px = row[_X1] - row[_X0]
        d.box.height_px = row[_Y1] - row[_Y0]
        d.classification.add(label=pb.OBJECT_CLASS_CAR, probability=float(row[_SCORE]))
    return msg
