"""`rmmdet import`: ROS 1 and ROS 2 bags (sqlite3 or mcap storage) into the project's recording, so
`rmmdet replay` drives the MECs from data recorded elsewhere.

Bags are read with rosbags' AnyReader (type definitions stored in the bag are used; a bag without them
falls back on the ROS 2 Humble / ROS 1 Noetic stores; types neither knows, e.g. radar_msgs, come from
`.msg` files given with `--msg DIR`: `DIR/<package>/msg/<Name>.msg`). Each topic is bound to one of
the scene's sensors: by the mapping file (`topics: {<topic>: <sensor id>}`), or, without one, by the
scene sensor id its name or its first message's frame id contains (the longest). Converted:
- sensor_msgs/Image and CompressedImage -> the camera's foxglove.CompressedImage (a JPEG or PNG kept
  as it is, anything else encoded as PNG: lossless, so the MEC sees the bag's own pixels);
- sensor_msgs/PointCloud2 of any field layout and byte order -> the lidar's foxglove.PointCloud (x, y,
  z and intensity; intensity scaled to [0, 1] when it is given in 0..255; points without a finite x, y,
  z dropped); a cloud without x, y or z is an error;
- radar_msgs/RadarScan (returns: range, azimuth, elevation, doppler_velocity, amplitude) -> RadarScan;
- raw Robosense packets -> the lidar's clouds through the project's RS-LiDAR decoder
  (shared/devices/robosense.py: DIFOP angle tables, frames split at the azimuth wrap, first returns):
  ROS 2 rslidar_msg/RslidarPacket (`is_difop`, `data`), one packet a message, and ROS 1
  rslidar_msgs/rslidarScan (`packets[].data`, a DIFOP topic's name containing "difop"); the unit's
  model is the mapping's (`{<topic>: {sensor: lidar_11, device: rs16}}`: the scene's generic lidars
  name none), each frame stamped with its last packet's message stamp (receive time) less one packet.
Each message keeps its header stamp (or, with `rebase_to_ns`, every stamp moves by one offset so the
first lands there: a live MEC judges freshness on its clock). Out of order stamps on a topic, a mapping
that names an unknown sensor or binds a topic of a type that cannot be converted, a corrupt or cut-off
bag: `BagImportError` naming the topic and message index; the output is written to `<out>.partial`
and renamed only when everything was read.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.sensors_pb2 import RadarScan, RadarTarget
from rosbags.highlevel import AnyReader
from rosbags.image import message_to_cvimage
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from shared.bus.codec import encode
from shared.bus.node import make_header
from shared.bus.streams import SENSOR_STREAM, get_stream, sensor_group_source
from shared.devices import robosense
from shared.devices.robosense import MODELS
from shared.devices.sources import lidar_frame_message
from shared.perception.decode import encoded_format, point_cloud_message, unit_intensity
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S

POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
RADAR_TYPE = "radar_msgs/msg/RadarScan"
PACKET_TYPES = (
    "rslidar_msg/msg/RslidarPacket",
    "rslidar_msgs/msg/rslidarScan",
    "rslidar_msgs/msg/rslidarPacket",
)
KIND_OF_TYPE = {
    **dict.fromkeys(IMAGE_TYPES, "camera"),
    CLOUD_TYPE: "lidar",
    RADAR_TYPE: "radar",
    **dict.fromkeys(PACKET_TYPES, "lidar"),
}


class BagImportError(Exception):
    """The import stopped; nothing was written."""


@dataclass
class ImportReport:
    mapped: dict[str, str] = field(default_factory=dict)  # topic -> sensor id
    skipped: dict[str, str] = field(default_factory=dict)  # topic -> why
    messages: dict[str, int] = field(default_factory=dict)  # sensor id -> messages written
    first_stamp_ns: int | None = None
    packet_counters: dict[str, dict[str, int]] = field(default_factory=dict)  # sensor -> the decoder's counts
    out: Path | None = None


def register_msg_dir(store: Any, msg_dir: Path) -> list[str]:
    """Register every `<pkg>/msg/<Name>.msg` under `msg_dir`; the type names."""
    types: dict[str, Any] = {}
    for path in sorted(msg_dir.glob("*/msg/*.msg")):
        name = f"{path.parent.parent.name}/msg/{path.stem}"
        try:
            types.update(get_types_from_msg(path.read_text(), name))
        except Exception as exc:
            raise BagImportError(f"{path}: not a message definition ({exc})") from None
    store.register(types)
    return sorted(types)


def pointcloud2_points(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 x, y, z and (N,) intensity in [0, 1] of a sensor_msgs/PointCloud2 of any field
    layout and byte order; ValueError for a cloud without x/y/z or whose data does not fit its shape."""
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in ("x", "y", "z") if name not in fields]
    if missing:
        raise ValueError(f"PointCloud2 without {'/'.join(missing)} (fields: {sorted(fields)})")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z", "intensity"):
        f = fields.get(name)
        if f is None:
            continue
        if f.datatype not in POINTFIELD_DTYPES:
            raise ValueError(f"PointCloud2 field {name} has datatype {f.datatype}")
        names.append(name)
        formats.append(order + POINTFIELD_DTYPES[f.datatype])
        offsets.append(f.offset)
    step = int(msg.point_step)
    if step <= 0 or any(o + np.dtype(fmt).itemsize > step for o, fmt in zip(offsets, formats, strict=True)):
        raise ValueError(f"PointCloud2 fields do not fit its point_step {step}")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    height, width, row_step = int(msg.height), int(msg.width), int(msg.row_step)
    data = bytes(msg.data)
    if row_step < width * step or len(data) < height * row_step:
        raise ValueError(f"PointCloud2 data of {len(data)} B is short of {height} rows of {row_step} B")
    rows = [np.frombuffer(data, dtype, count=width, offset=r * row_step) for r in range(height)]
    points = np.concatenate(rows) if rows else np.zeros(0, dtype)
    xyz = np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float64)
    intensity = points["intensity"].astype(np.float64) if "intensity" in names else np.zeros(len(points))
    keep = np.isfinite(xyz).all(axis=1)
    return xyz[keep], unit_intensity(intensity[keep])


def image_data(msg: Any, msgtype: str) -> tuple[str, bytes]:
    """A sensor_msgs Image or CompressedImage as the camera message's (format, bytes): a JPEG or PNG
    kept byte for byte, anything else encoded as PNG (lossless: the MEC sees the bag's pixels)."""
    if msgtype.endswith("CompressedImage"):
        data = bytes(msg.data)
        fmt = encoded_format(data)
        if fmt is not None:
            return fmt, data
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if decoded is None:
            raise ValueError(f"CompressedImage of format {msg.format!r} does not decode")
        image = decoded
    else:
        try:
            image = message_to_cvimage(msg, "bgr8")
        except Exception as exc:  # rosbags-image raises on encodings and sizes it cannot take
            raise ValueError(f"Image ({msg.encoding}, {msg.width}x{msg.height}): {exc}") from None
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("the image does not encode as PNG")
    return "png", bytes(buf.tobytes())


def radar_targets(msg: Any) -> list[RadarTarget]:
    """radar_msgs/RadarScan returns as RadarTargets (amplitude taken as the RCS, dBsm)."""
    return [
        RadarTarget(
            range_m=float(r.range),
            azimuth_rad=float(r.azimuth),
            elevation_rad=float(r.elevation),
            range_rate_mps=float(r.doppler_velocity),
            rcs_dbsm=float(r.amplitude),
            target_index=i,
        )
        for i, r in enumerate(msg.returns)
    ]


def auto_sensor(topic: str, frame_id: str, sensor_ids: Sequence[str]) -> str | None:
    """The scene sensor whose id the topic name or the frame id contains (the longest), or None."""
    found = [
        s
        for s in sensor_ids
        if re.search(rf"(^|[^a-z0-9]){re.escape(s)}($|[^a-z0-9])", f"{topic} {frame_id}")
    ]
    return max(found, key=len) if found else None


@dataclass(frozen=True)
class Binding:
    """What a topic feeds: a scene sensor, and for raw Robosense packets the unit's model."""

    sensor: str
    device: str | None = None


def load_mapping(path: Path | None, scene: Scene) -> dict[str, Binding] | None:
    """`topics: {<topic>: <sensor id> | {sensor: <id>, device: rs16 | rs32}}`, checked against the scene."""
    if path is None:
        return None
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise BagImportError(f"{path}: {exc}") from None
    topics = data.get("topics") if isinstance(data, dict) else None
    if not isinstance(topics, dict):
        raise BagImportError(f"{path}: expected `topics: {{<topic>: <sensor id>}}`")
    out: dict[str, Binding] = {}
    for topic, value in topics.items():
        if isinstance(value, str):
            out[str(topic)] = Binding(value)
            continue
        if not (
            isinstance(value, dict)
            and isinstance(value.get("sensor"), str)
            and set(value) <= {"sensor", "device"}
        ):
            raise BagImportError(f"{path}: topic {topic}: expected a sensor id or {{sensor, device}}")
        device = value.get("device")
        if device is not None and device not in MODELS:
            raise BagImportError(f"{path}: topic {topic}: device {device!r} is none of {sorted(MODELS)}")
        out[str(topic)] = Binding(value["sensor"], device)
    unknown = sorted({b.sensor for b in out.values() if b.sensor not in scene.sensors})
    if unknown:
        raise BagImportError(f"{path}: sensor(s) {unknown} are not in scene {scene.scene_id}")
    return out


def _typestore(bags: Sequence[Path]) -> Any:
    ros1 = any(p.suffix == ".bag" for p in bags)
    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def import_bags(
    bags: Sequence[Path],
    out: Path,
    scene: Scene,
    mapping: dict[str, Binding] | None = None,
    msg_dir: Path | None = None,
    rebase_to_ns: int | None = None,
) -> ImportReport:
    """Import `bags` into the recording `out` (module docstring)."""
    from shared.recording.writer import RecordingWriter  # local: the writer pulls in mcap's protobuf support

    report = ImportReport()
    store = _typestore(bags)
    if msg_dir is not None:
        register_msg_dir(store, msg_dir)
    partial = out.with_name(out.name + ".partial")
    partial.unlink(missing_ok=True)
    try:
        with AnyReader(list(bags), default_typestore=store) as reader, RecordingWriter(partial) as writer:
            bound = _bind(reader, scene, mapping, report)
            _copy(reader, writer, bound, scene, report, rebase_to_ns)
    except BagImportError:
        partial.unlink(missing_ok=True)
        raise
    except Exception as exc:  # rosbags' and mcap's own errors on corrupt or cut-off input
        partial.unlink(missing_ok=True)
        raise BagImportError(f"{', '.join(map(str, bags))}: {type(exc).__name__}: {exc}") from None
    partial.replace(out)
    report.out = out
    return report


@dataclass(frozen=True)
class _Bound:
    binding: Binding
    msgtype: str


def _bind(
    reader: Any, scene: Scene, mapping: dict[str, Binding] | None, report: ImportReport
) -> dict[str, _Bound]:
    """topic -> what it feeds, for the topics imported; the rest go to `report.skipped` with why."""
    bound: dict[str, _Bound] = {}
    for topic, info in sorted(reader.topics.items()):
        msgtype = info.msgtype or ""
        if mapping is not None:
            binding = mapping.get(topic)
            if binding is None:
                report.skipped[topic] = "not in the mapping"
                continue
        else:
            found = auto_sensor(topic, _first_frame_id(reader, topic), list(scene.sensors))
            if found is None:
                report.skipped[topic] = "names no scene sensor"
                continue
            binding = Binding(found)
        sensor = binding.sensor
        kind = KIND_OF_TYPE.get(msgtype)
        if kind is None:
            if mapping is not None:
                raise BagImportError(f"topic {topic}: type {msgtype} cannot be imported (mapped to {sensor})")
            report.skipped[topic] = f"type {msgtype} is not imported"
            continue
        if scene.sensor(sensor).kind != kind:
            raise BagImportError(
                f"topic {topic}: a {msgtype} cannot feed {sensor}, a {scene.sensor(sensor).kind}"
            )
        if msgtype in PACKET_TYPES and binding.device is None:
            raise BagImportError(
                f"topic {topic}: Robosense packets need the unit's model: map it as "
                f"{{sensor: {sensor}, device: rs16 | rs32}}"
            )
        bound[topic] = _Bound(binding, msgtype)
        report.mapped[topic] = sensor
    return bound


def _first_frame_id(reader: Any, topic: str) -> str:
    connections = [c for c in reader.connections if c.topic == topic]
    for connection, _, raw in reader.messages(connections=connections):
        try:
            return str(reader.deserialize(raw, connection.msgtype).header.frame_id)
        except Exception:
            return ""
    return ""


def _stamp_ns(msg: Any, bag_time_ns: int) -> int:
    """A message's header stamp (a packet's own `stamp` where it has no header), else its bag time."""
    stamp = msg.header.stamp if hasattr(msg, "header") else getattr(msg, "stamp", None)
    value = int(stamp.sec) * NS_PER_S + int(stamp.nanosec) if stamp is not None else 0
    return value or int(bag_time_ns)


def _copy(
    reader: Any,
    writer: Any,
    bound: dict[str, _Bound],
    scene: Scene,
    report: ImportReport,
    rebase_to_ns: int | None,
) -> None:
    connections = [c for c in reader.connections if c.topic in bound]
    index: dict[str, int] = {}
    last_stamp: dict[str, int] = {}
    offset_ns: int | None = None
    seq: dict[str, int] = {}
    streams: dict[str, robosense.LidarStream] = {}

    def write(sensor: str, message: Message, stamp_ns: int) -> None:
        spec = scene.sensor(sensor)
        seq[sensor] = seq.get(sensor, 0) + 1
        source = sensor_group_source(spec.agent, spec.kind)
        encoded = encode(message, make_header(source, seq[sensor], stamp_ns=stamp_ns, frame_id=sensor))
        key = get_stream(SENSOR_STREAM[spec.kind]).key(agent=spec.agent, sensor=sensor)
        writer.write(key, str(encoded.encoding), encoded.payload, encoded.attachment, stamp_ns, stamp_ns)
        report.messages[sensor] = report.messages.get(sensor, 0) + 1

    for connection, bag_time_ns, raw in reader.messages(connections=connections):
        topic = connection.topic
        i = index[topic] = index.get(topic, -1) + 1
        target = bound[topic]
        sensor = target.binding.sensor
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except Exception as exc:
            raise BagImportError(f"topic {topic} message {i}: does not deserialize ({exc})") from None
        stamp_ns = _stamp_ns(msg, bag_time_ns)
        if stamp_ns < last_stamp.get(topic, stamp_ns):
            raise BagImportError(
                f"topic {topic} message {i}: stamp {stamp_ns} before the previous {last_stamp[topic]}"
            )
        last_stamp[topic] = stamp_ns
        if offset_ns is None:
            report.first_stamp_ns = stamp_ns
            offset_ns = 0 if rebase_to_ns is None else rebase_to_ns - stamp_ns
        stamp_ns += offset_ns
        if target.msgtype in PACKET_TYPES:
            device = target.binding.device
            assert device is not None  # _bind insists
            stream = streams.setdefault(sensor, robosense.LidarStream(MODELS[device]))
            for frame in _packets(stream, topic, msg, stamp_ns):
                write(sensor, lidar_frame_message(frame, sensor), frame.stamp_ns)
            continue
        try:
            message = _convert(msg, target.msgtype, sensor, stamp_ns)
        except ValueError as exc:
            raise BagImportError(f"topic {topic} message {i}: {exc}") from None
        write(sensor, message, stamp_ns)
    for sensor, stream in streams.items():
        report.packet_counters[sensor] = dict(stream.counters)


def _packets(stream: robosense.LidarStream, topic: str, msg: Any, stamp_ns: int) -> list[robosense.Frame]:
    """The frames a packet message completed (bad packets are counted by the stream, as live)."""
    frames: list[robosense.Frame] = []
    if hasattr(msg, "packets"):  # ROS 1 rslidarScan: MSOP packets (or DIFOP ones on a difop topic)
        payloads = [(bytes(p.data), "difop" in topic) for p in msg.packets]
    else:  # one packet a message
        payloads = [(bytes(msg.data), bool(getattr(msg, "is_difop", 0)) or "difop" in topic)]
    for data, difop in payloads:
        if difop:
            stream.on_difop(data)
        else:
            frames += stream.on_msop(data, stamp_ns)
    return frames


def _convert(msg: Any, msgtype: str, sensor: str, stamp_ns: int) -> Message:
    if msgtype in IMAGE_TYPES:
        fmt, data = image_data(msg, msgtype)
        image = CompressedImage(frame_id=sensor, format=fmt, data=data)
        image.timestamp.FromNanoseconds(stamp_ns)
        return image
    if msgtype == CLOUD_TYPE:
        xyz, intensity = pointcloud2_points(msg)
        return point_cloud_message(xyz, intensity, sensor, stamp_ns)
    return RadarScan(sensor_id=sensor, targets=radar_targets(msg))
