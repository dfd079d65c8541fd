"""ROS 1 and ROS 2 bags (sqlite3 or mcap storage) -> scene-sensor messages, for `rmmdet import`
(shared/captures/importer.py writes them; `rmmdet replay` drives the MECs from the recording).

Bags are read with rosbags' AnyReader (type definitions stored in the bag are used; a bag without them
falls back on the ROS 2 Humble / ROS 1 Noetic stores, then on the device drivers' message definitions
shipped in `shared/captures/msg/` (rslidar_sdk's rslidar_msg, ros_rslidar's rslidar_msgs,
velodyne_msgs, nebula_msgs, can_msgs), then on `.msg` files given with `--msg DIR`
(`DIR/<package>/msg/<Name>.msg`). rslidar_sdk changed `rslidar_msg/RslidarPacket` in place: its
2022 layout (`stamp`, `uint8[1248] data`, in `RslidarScan` arrays) is `msg_legacy/`, taken for a bag
that holds `RslidarScan` or whose packets do not read the current way (`header`, `is_difop`,
`is_frame_begin`, `data`).

Each topic is bound to a scene sensor by the mapping's `topics:` (shared/captures/mapping.py), or,
without a mapping, to the sensor whose id its name or its first message's frame id contains (the
longest). Converted:
- sensor_msgs/Image and CompressedImage -> the camera's foxglove.CompressedImage (a JPEG or PNG kept
  as it is, anything else encoded as PNG: lossless, so the MEC sees the bag's own pixels);
- sensor_msgs/PointCloud2 of any field layout and byte order -> the lidar's foxglove.PointCloud (x, y,
  z and intensity; intensity scaled to [0, 1] when it is given in 0..255; points without a finite x, y,
  z dropped); a cloud without x, y or z is an error;
- radar_msgs/RadarScan (returns: range, azimuth, elevation, doppler_velocity, amplitude) -> RadarScan;
- raw lidar packets (Robosense MSOP / DIFOP, Velodyne data) in any of the drivers' messages, one packet
  or an array of them a message -> the lidar's clouds through the live adapters' decoders
  (shared/captures/units.py); the unit's model from its bytes (DIFOP tables, Velodyne factory byte),
  else the mapping's `device:`; a packet is stamped with its own stamp, else its message's;
- can_msgs/Frame carrying an ARS 408's frames -> its detection lists (the mapping's `can_id` picks
  the radar; the lists' layout from the radar's own RadarState frames).
Each message keeps its header stamp (the importer can move every stamp by one offset). Out of order
stamps on a topic, a mapping that names an unknown sensor or binds a topic of a type that cannot be
converted, a corrupt or cut-off bag: `BagImportError` naming the topic and message index.
"""

from __future__ import annotations

import bz2
import functools
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import lz4.frame
import numpy as np
import zstandard
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.sensors_pb2 import RadarScan, RadarTarget
from rosbags import rosbag1
from rosbags.highlevel import AnyReader
from rosbags.image import message_to_cvimage
from rosbags.rosbag2 import storage_mcap
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from shared.bus.codec import DEFAULT_MAX_PAYLOAD_BYTES
from shared.captures import identify
from shared.captures.errors import CaptureError
from shared.captures.mapping import Binding, Mapping
from shared.captures.report import ImportReport, Item
from shared.captures.units import RadarUnit, RobosenseUnit, VelodyneUnit, lidar_unit
from shared.devices import ars408, robosense
from shared.perception.decode import (
    FLOAT32_BYTES,
    MAX_IMAGE_PIXELS,
    POINT_FIELDS,
    encoded_format,
    image_size,
    point_cloud_message,
    unit_intensity,
)
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S

POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
RADAR_TYPE = "radar_msgs/msg/RadarScan"
CAN_TYPE = "can_msgs/msg/Frame"
# Lidar packet messages: one packet (`data`) or an array of them (`packets[].data`) a message.
PACKET_TYPES = (
    "rslidar_msg/msg/RslidarPacket",
    "rslidar_msg/msg/RslidarScan",
    "rslidar_msgs/msg/rslidarScan",
    "rslidar_msgs/msg/rslidarPacket",
    "velodyne_msgs/msg/VelodyneScan",
    "velodyne_msgs/msg/VelodynePacket",
    "nebula_msgs/msg/NebulaPackets",
    "nebula_msgs/msg/NebulaPacket",
)
KIND_OF_TYPE = {
    **dict.fromkeys(IMAGE_TYPES, "camera"),
    CLOUD_TYPE: "lidar",
    RADAR_TYPE: "radar",
    CAN_TYPE: "radar",
    **dict.fromkeys(PACKET_TYPES, "lidar"),
}
MSG_DIR = Path(__file__).with_name("msg")
LEGACY_MSG_DIR = Path(__file__).with_name("msg_legacy")
LEGACY_MARKER = "rslidar_msg/msg/RslidarScan"  # only rslidar_sdk's 2022 layout has it


#: Caps checked against what a bag declares before anything is read or allocated (a message or chunk
#: that declares more is refused by name). A cloud: what one point-cloud message may carry over the bus
#: (x, y, z, intensity float32: 16 bytes a point). An image: the MEC's MAX_IMAGE_PIXELS. A chunk:
#: ROS 1 and rosbag2 write chunks of under a megabyte by default.
MAX_CLOUD_POINTS = DEFAULT_MAX_PAYLOAD_BYTES // (FLOAT32_BYTES * len(POINT_FIELDS))
MAX_CHUNK_BYTES = 256 * 1024 * 1024


class BagImportError(CaptureError):
    """The import stopped; nothing was written."""


def _inflate(compression: str, data: bytes, size: int) -> bytes:
    """A bag chunk's bytes, inflated to at most its declared `size` (and `size` at most MAX_CHUNK_BYTES):
    a chunk whose data would inflate past what it declares is refused before it is allocated."""
    if size > MAX_CHUNK_BYTES:
        raise BagImportError(
            f"a chunk declares {size} bytes, more than the {MAX_CHUNK_BYTES} a chunk may hold"
        )
    if compression in ("", "none"):
        return data
    if compression == "zstd":
        declared = zstandard.frame_content_size(data)  # -1: not in the frame header
        if declared > size:
            raise BagImportError(f"a zstd chunk inflates to {declared} bytes, past the {size} it declares")
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        inflater: Any = lz4.frame.LZ4FrameDecompressor()
    elif compression == "bz2":
        inflater = bz2.BZ2Decompressor()
    else:
        raise BagImportError(f"chunk compression {compression!r} is none of zstd, lz4, bz2")
    raw = inflater.decompress(data, max_length=size + 1)
    if len(raw) > size:
        raise BagImportError(f"a {compression} chunk inflates past the {size} bytes it declares")
    return raw


# rosbags hands an MCAP chunk's declared uncompressed size to its decompressors and inflates without
# bound itself: every one it knows is replaced by the bounded one (the same bytes for any honest chunk).
for _name in list(storage_mcap.DECOMPRESSORS):
    storage_mcap.DECOMPRESSORS[_name] = functools.partial(_inflate, _name)


def _bound_ros1_chunks(reader: Any) -> None:
    """The ROS 1 bags' chunks inflated by `_inflate`, to the uncompressed size each chunk's header
    declares (rosbags keeps only the compressed size)."""
    for bag in getattr(reader, "readers", []):
        if not isinstance(bag, rosbag1.Reader) or bag.bio is None:
            continue
        for pos, chunk in list(bag.chunks.items()):
            bag.bio.seek(pos)
            header = rosbag1.reader.Header.read(bag.bio, rosbag1.reader.RecordType.CHUNK)
            compression, size = header.get_string("compression"), header.get_uint32("size")
            bag.chunks[pos] = chunk._replace(decompressor=functools.partial(_inflate, compression, size=size))


def register_msg_dir(store: Any, msg_dir: Path, only_new: bool = False) -> list[str]:
    """Register every `<pkg>/msg/<Name>.msg` under `msg_dir` (with `only_new`, those the store does not
    know yet); the type names registered."""
    types: dict[str, Any] = {}
    for path in sorted(msg_dir.glob("*/msg/*.msg")):
        name = f"{path.parent.parent.name}/msg/{path.stem}"
        if only_new and name in store.types:
            continue
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
    if height * width > MAX_CLOUD_POINTS or (width == 0 and height > MAX_CLOUD_POINTS):
        raise ValueError(
            f"PointCloud2 of {height} x {width} points: over the {MAX_CLOUD_POINTS} a cloud message carries"
        )
    data = bytes(msg.data)
    if row_step < width * step or len(data) < height * row_step:
        raise ValueError(f"PointCloud2 data of {len(data)} B is short of {height} rows of {row_step} B")
    if width == 0 or height == 0:
        points = np.zeros(0, dtype)
    else:  # the rows' points, read through a strided view (one copy, however many rows)
        raw = np.frombuffer(data, np.uint8, count=(height - 1) * row_step + width * step)
        cells = np.lib.stride_tricks.as_strided(raw, (height, width, step), (row_step, step, 1))
        points = np.ascontiguousarray(cells).reshape(-1).view(dtype)
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
        width, height = image_size(data)  # the header's size, nothing decoded: a bomb is refused unread
        if width * height > MAX_IMAGE_PIXELS:
            raise ValueError(f"CompressedImage of {width}x{height} px: over the {MAX_IMAGE_PIXELS} px cap")
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if decoded is None:
            raise ValueError(f"CompressedImage of format {msg.format!r} does not decode")
        image = decoded
    else:
        if int(msg.width) * int(msg.height) > MAX_IMAGE_PIXELS:
            raise ValueError(f"Image of {msg.width}x{msg.height} px: over the {MAX_IMAGE_PIXELS} px cap")
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


def _typestore(bags: Sequence[Path], legacy: bool, msg_dir: Path | None) -> Any:
    ros1 = any(p.suffix == ".bag" for p in bags)
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    for folder in (msg_dir, LEGACY_MSG_DIR if legacy else None, MSG_DIR):  # the first to define a type wins
        if folder is not None:
            register_msg_dir(store, folder, only_new=True)
    return store


def _bag_types(bags: Sequence[Path]) -> set[str]:
    with AnyReader(list(bags), default_typestore=_typestore(bags, False, None)) as reader:
        return {c.msgtype for c in reader.connections}


@dataclass(frozen=True)
class _Bound:
    bindings: tuple[Binding, ...]
    msgtype: str

    @property
    def sensor(self) -> str:
        return self.bindings[0].sensor


def bag_items(
    bags: Sequence[Path],
    scene: Scene,
    mapping: Mapping | None,
    msg_dir: Path | None,
    report: ImportReport,
) -> Iterator[Item]:
    """The scene-sensor messages of `bags` (module docstring), in the bags' time order."""
    try:
        types = _bag_types(bags)
        legacy = _legacy_layout(bags, types, msg_dir)
    except CaptureError:
        raise
    except Exception as exc:  # rosbags' own errors on a corrupt, foreign or cut-off bag
        raise BagImportError(f"{', '.join(map(str, bags))}: {type(exc).__name__}: {exc}") from None
    yield from _bag_items(bags, scene, mapping, _typestore(bags, legacy, msg_dir), report)


def _legacy_layout(bags: Sequence[Path], types: set[str], msg_dir: Path | None) -> bool:
    """Whether the bag's rslidar_msg packets are rslidar_sdk's 2022 layout: it has `RslidarScan`, or its
    first `RslidarPacket` reads as a 1248-byte packet only that way. Decided once, before anything is
    imported: a later packet of the wrong length is the decoder's to count, not a reason to switch."""
    if LEGACY_MARKER in types:
        return True
    if "rslidar_msg/msg/RslidarPacket" not in types:
        return False
    for legacy in (False, True):
        with AnyReader(list(bags), default_typestore=_typestore(bags, legacy, msg_dir)) as reader:
            _bound_ros1_chunks(reader)
            connections = [c for c in reader.connections if c.msgtype == "rslidar_msg/msg/RslidarPacket"]
            first = next(iter(reader.messages(connections=connections)), None)
            if first is None:
                return False
            try:
                msg = reader.deserialize(first[2], first[0].msgtype)
            except Exception:  # rosbags' own error: the bytes are not this layout
                continue
            if len(bytes(getattr(msg, "data", b""))) == robosense.PACKET_BYTES:
                return legacy
    raise BagImportError(f"{', '.join(map(str, bags))}: rslidar_msg packets read in neither layout")


def _bag_items(
    bags: Sequence[Path], scene: Scene, mapping: Mapping | None, store: Any, report: ImportReport
) -> Iterator[Item]:
    try:
        reader_cm = AnyReader(list(bags), default_typestore=store)
        reader = reader_cm.__enter__()
    except Exception as exc:
        raise BagImportError(f"{', '.join(map(str, bags))}: {type(exc).__name__}: {exc}") from None
    try:
        _bound_ros1_chunks(reader)
        bound = _bind(reader, scene, mapping, report)
        units = _lidar_units(reader, bound, report)
        radars = {
            b.sensor: RadarUnit(b.sensor, b.can_id or 0)
            for t in bound.values()
            if t.msgtype == CAN_TYPE
            for b in t.bindings
        }
        yield from _messages(reader, bound, units, radars, report)
        for sensor, unit in {**units, **radars}.items():
            unit.finish()
            report.count(sensor, unit.counters())
    except CaptureError:
        raise
    except Exception as exc:  # rosbags' and the decoders' own errors on corrupt or cut-off input
        raise BagImportError(f"{', '.join(map(str, bags))}: {type(exc).__name__}: {exc}") from None
    finally:
        reader_cm.__exit__(None, None, None)


def _bind(reader: Any, scene: Scene, mapping: Mapping | None, report: ImportReport) -> dict[str, _Bound]:
    """topic -> what it feeds, for the topics imported; the rest go to `report.skipped` with why."""
    bound: dict[str, _Bound] = {}
    for topic, info in sorted(reader.topics.items()):
        msgtype = info.msgtype or ""
        if mapping is not None:
            bindings = mapping.topics.get(topic)
            if not bindings:
                report.skipped[topic] = "not in the mapping"
                continue
        else:
            found = auto_sensor(topic, _first_frame_id(reader, topic), list(scene.sensors))
            if found is None:
                report.skipped[topic] = "names no scene sensor"
                continue
            bindings = [Binding(sensor=found)]
        kind = KIND_OF_TYPE.get(msgtype)
        names = ", ".join(b.sensor for b in bindings)
        if kind is None:
            if mapping is not None:
                raise BagImportError(f"topic {topic}: type {msgtype} cannot be imported (mapped to {names})")
            report.skipped[topic] = f"type {msgtype} is not imported"
            continue
        for b in bindings:
            if scene.sensor(b.sensor).kind != kind:
                raise BagImportError(
                    f"topic {topic}: a {msgtype} cannot feed {b.sensor}, a {scene.sensor(b.sensor).kind}"
                )
        if len(bindings) > 1 and msgtype != CAN_TYPE:
            raise BagImportError(f"topic {topic}: only a CAN topic feeds several sensors (mapped to {names})")
        bound[topic] = _Bound(tuple(bindings), msgtype)
        report.mapped[topic] = names
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


def packets_of(msg: Any, stamp_ns: int) -> list[tuple[bytes, int]]:
    """(payload, stamp ns) of every packet a driver's message holds: its own stamp where set, else the
    message's."""
    items = msg.packets if hasattr(msg, "packets") else [msg]
    out = []
    for p in items:
        own = getattr(p, "stamp", None)
        own_ns = int(own.sec) * NS_PER_S + int(own.nanosec) if own is not None else 0
        out.append((bytes(p.data), own_ns or stamp_ns))
    return out


def _lidar_units(
    reader: Any, bound: dict[str, _Bound], report: ImportReport
) -> dict[str, RobosenseUnit | VelodyneUnit]:
    """A decoder per lidar fed by packet topics, its model from its first packets (or the mapping),
    a Robosense unit given its first DIFOP before any revolution."""
    topics_of: dict[str, list[str]] = {}
    for topic, t in bound.items():
        if t.msgtype in PACKET_TYPES:
            topics_of.setdefault(t.sensor, []).append(topic)
    units: dict[str, RobosenseUnit | VelodyneUnit] = {}
    for sensor, topics in topics_of.items():
        binding = _one_binding(sensor, [bound[t].bindings[0] for t in topics])
        difop, velodyne_model, velodyne_seen = _first_packets(reader, topics)
        where = f"topic {', '.join(topics)}"
        if not velodyne_seen and difop is None and not (binding.device or "").startswith(("vlp", "hdl")):
            raise BagImportError(f"{where}: Robosense packets without a DIFOP: the unit's angles are unknown")
        unit = lidar_unit(binding, difop, velodyne_model if velodyne_seen else None, where)
        if isinstance(unit, RobosenseUnit) and difop is not None:
            unit.on_packet(difop, 0)
        units[sensor] = unit
        report.devices[sensor] = unit.device
    return units


def _one_binding(sensor: str, bindings: list[Binding]) -> Binding:
    """The topics of one lidar (its packets, its DIFOP) as one binding: what any of them gives
    (`device`, `calibration`); two that say different things are refused."""
    merged: dict[str, object] = {"sensor": sensor}
    for b in bindings:
        for key in ("device", "calibration"):
            value = getattr(b, key)
            if value is not None and merged.setdefault(key, value) != value:
                raise BagImportError(f"{sensor}: its topics' mappings give {key} {merged[key]} and {value}")
    return Binding.model_validate(merged)


def _first_packets(reader: Any, topics: list[str]) -> tuple[bytes | None, str | None, bool]:
    """A Robosense unit's first DIFOP (however far into the bag: a unit sends one a second, among
    hundreds of MSOP packets a second), or a Velodyne unit's model and that Velodyne data came."""
    connections = [c for c in reader.connections if c.topic in topics]
    difop, model, seen = None, None, False
    for i, (connection, bag_ns, raw) in enumerate(reader.messages(connections=connections)):
        if difop is not None or seen:
            break
        msg = _deserialize(reader, raw, connection.msgtype, connection.topic, i)
        for payload, _ in packets_of(msg, bag_ns):
            kind = identify.packet_kind(payload)
            if kind == "robosense_difop" and difop is None:
                difop = payload
            elif kind == "velodyne_data":
                seen, model = True, identify.velodyne_model(payload)
    return difop, model, seen


def _deserialize(reader: Any, raw: bytes, msgtype: str, topic: str, i: int) -> Any:
    try:
        return reader.deserialize(raw, msgtype)
    except Exception as exc:
        raise BagImportError(f"topic {topic} message {i}: does not deserialize ({exc})") from None


def _messages(
    reader: Any,
    bound: dict[str, _Bound],
    units: dict[str, RobosenseUnit | VelodyneUnit],
    radars: dict[str, RadarUnit],
    report: ImportReport,
) -> Iterator[Item]:
    connections = [c for c in reader.connections if c.topic in bound]
    index: dict[str, int] = {}
    last_stamp: dict[str, int] = {}
    for connection, bag_time_ns, raw in reader.messages(connections=connections):
        topic = connection.topic
        i = index[topic] = index.get(topic, -1) + 1
        target = bound[topic]
        msg = _deserialize(reader, raw, connection.msgtype, topic, i)
        stamp_ns = _stamp_ns(msg, bag_time_ns)
        if stamp_ns < last_stamp.get(topic, stamp_ns):
            raise BagImportError(
                f"topic {topic} message {i}: stamp {stamp_ns} before the previous {last_stamp[topic]}"
            )
        last_stamp[topic] = stamp_ns
        if target.msgtype in PACKET_TYPES:
            unit = units[target.sensor]
            for payload, packet_ns in packets_of(msg, stamp_ns):
                for message, frame_ns in unit.on_packet(payload, packet_ns):
                    yield frame_ns, unit.sensor, message
            continue
        if target.msgtype == CAN_TYPE:
            yield from _can_frame(msg, stamp_ns, target, radars)
            continue
        try:
            message = _convert(msg, target.msgtype, target.sensor, stamp_ns)
        except ValueError as exc:
            raise BagImportError(f"topic {topic} message {i}: {exc}") from None
        yield stamp_ns, target.sensor, message


def _can_frame(msg: Any, stamp_ns: int, target: _Bound, radars: dict[str, RadarUnit]) -> Iterator[Item]:
    """One can_msgs/Frame to the radar whose sensor id its identifier carries (error frames to all)."""
    units = [radars[b.sensor] for b in target.bindings]
    if msg.is_error:
        for unit in units:
            unit.on_error_frame(int(msg.id))
        return
    if msg.is_rtr or msg.is_extended:
        return
    _, sensor_id = ars408.split_id(int(msg.id))
    data = bytes(msg.data)[: int(msg.dlc)]
    for unit in units:
        if unit.can_id == sensor_id:
            for message, list_ns in unit.on_frame(int(msg.id), data, stamp_ns / NS_PER_S):
                yield list_ns, unit.sensor, message


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
