"""Sample traffic for recording tests: camera frames (header in attachment), radar scans and ground
truth (header in body), as the exact bytes a publisher puts on the bus."""

from __future__ import annotations

from dataclasses import dataclass

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.sensors_pb2 import RadarScan
from rmmdet.v1.sim_pb2 import GroundTruth

from shared.bus.codec import encode
from shared.bus.streams import get_stream

CAMERA_KEY = get_stream("camera_image").key(agent="agent1", sensor="cam_11")
RADAR_KEY = get_stream("radar_scan").key(agent="agent1", sensor="radar_1")
GROUND_TRUTH_KEY = get_stream("ground_truth").key()
#: Sim time of the first sample and the tick period, ns.
SIM_START_NS = 1_000_000_000
TICK_NS = 50_000_000


@dataclass(frozen=True)
class Sent:
    key: str
    encoding: str
    payload: bytes
    attachment: bytes | None
    message: Message
    header: Header

    @property
    def stamp_ns(self) -> int:
        return self.header.stamp.ToNanoseconds()


def _header(source: str, seq: int) -> Header:
    header = Header(source_id=source, seq=seq, frame_id="world", tick=seq)
    header.stamp.FromNanoseconds(SIM_START_NS + seq * TICK_NS)
    stage = header.processing.add(stage=f"{source}/publish")
    stage.start.FromNanoseconds(1_700_000_000_000_000_000 + seq)
    stage.end.FromNanoseconds(1_700_000_000_000_000_000 + seq)
    return header


def _sent(key: str, msg: Message, header: Header) -> Sent:
    encoded = encode(msg, header)
    return Sent(key, str(encoded.encoding), encoded.payload, encoded.attachment, msg, header)


def camera(seq: int) -> Sent:
    header = _header("agent1/cam_11", seq)
    img = CompressedImage(format="jpeg", frame_id="cam_11", data=bytes([0xFF, 0xD8, seq % 256]) * 100)
    img.timestamp.CopyFrom(header.stamp)
    return _sent(CAMERA_KEY, img, header)


def radar(seq: int) -> Sent:
    scan = RadarScan(sensor_id="radar_1")
    scan.targets.add(range_m=1.0 + seq, azimuth_rad=0.1, range_rate_mps=-0.2, rcs_dbsm=5.0, target_index=0)
    return _sent(RADAR_KEY, scan, _header("agent1/radar_1", seq))


def ground_truth(seq: int) -> Sent:
    gt = GroundTruth()
    vehicle = gt.vehicles.add(vehicle_id="veh1", lane_id="l1", lane_progress_m=0.1 * seq)
    vehicle.box.center_m.x = 0.01 * seq
    vehicle.velocity_mps.x = 0.2
    return _sent(GROUND_TRUTH_KEY, gt, _header("sim/world", seq))


def traffic(n_per_type: int) -> list[Sent]:
    """Interleaved camera, radar, ground truth samples, seq 1..n each."""
    out: list[Sent] = []
    for seq in range(1, n_per_type + 1):
        out += [camera(seq), radar(seq), ground_truth(seq)]
    return out
