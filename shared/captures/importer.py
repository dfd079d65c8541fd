"""`rmmdet import`: recordings of every container the devices' tools write -> the project's recording
(MCAP), each recorded source bound to one of the scene's sensors (shared/captures/mapping.py).

Inputs, told apart by their bytes and names: ROS 1 `.bag` files and ROS 2 bag folders / `.db3` /
`.mcap` files (shared/captures/rosbag.py), pcap / pcapng captures (`pcap.py`), CAN logs `.log` / `.asc`
/ `.blf` (`canlog.py`). Several inputs make one recording, merged by time (each input is read in its
own order; a frame that comes out up to `REORDER_WINDOW_NS` late is put back in place).

A capture is read twice: once to find its units (source address, destination port, what their packets
are, a Robosense unit's first DIFOP so its first revolution is not lost waiting for one), then to
decode. Nothing is written unless the whole import succeeds: a `CaptureError` (bad container, a unit
the mapping and the bytes cannot name, a Robosense unit with no DIFOP) leaves no output; damaged
records and packets are counted (`ImportReport.counters`) and the import goes on.
"""

from __future__ import annotations

import heapq
import itertools
import logging
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from google.protobuf.message import Message

from shared.bus.codec import encode
from shared.bus.node import make_header
from shared.bus.streams import SENSOR_STREAM, get_stream, sensor_group_source
from shared.captures import identify
from shared.captures.canlog import CanLogReader, is_can_log
from shared.captures.errors import CaptureError, CaptureFormatError, MappingError
from shared.captures.mapping import Binding, Mapping
from shared.captures.pcap import PcapReader, is_capture
from shared.captures.report import ImportReport, Item
from shared.captures.units import RadarUnit, RobosenseUnit, VelodyneUnit, lidar_unit
from shared.devices import ars408
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S

log = logging.getLogger(__name__)

#: How late (in its input) a message may come and still be written in time order.
REORDER_WINDOW_NS = 2 * NS_PER_S
#: An import's chunks are written uncompressed: what an import writes is nearly all raw clouds (float32
#: coordinates with noise in the low bits) and JPEGs, which lz4 hardly shrinks and zstd shrinks a
#: little at several times the import's own cost (tests/bench/import_bench.py writes each input with
#: each compression: its steps table); `rmmdet import --compression` chooses another.
IMPORT_COMPRESSION = "none"


def input_kind(path: Path) -> str:
    """'bag', 'capture' or 'canlog' by the file's bytes and name; CaptureFormatError otherwise."""
    path = Path(path)
    if path.is_dir() or path.suffix in (".bag", ".db3", ".mcap"):
        return "bag"
    if is_capture(path):
        return "capture"
    if is_can_log(path):
        return "canlog"
    raise CaptureFormatError(
        f"{path}: neither a ROS bag (.bag, a ROS 2 bag folder, .db3, .mcap), a pcap / pcapng capture nor a "
        "CAN log (.log candump -L, .asc, .blf)"
    )


def import_files(
    paths: Sequence[Path],
    out: Path,
    scene: Scene,
    mapping: Mapping | None = None,
    msg_dir: Path | None = None,
    rebase_to_ns: int | None = None,
    compression: str = IMPORT_COMPRESSION,
) -> ImportReport:
    """Import `paths` into the recording `out` (module docstring); CaptureError when it cannot.
    `compression`: the recording's chunk compression (shared/recording/writer.py COMPRESSIONS)."""
    from shared.captures import rosbag  # the bag reader pulls in rosbags
    from shared.recording.writer import RecordingWriter  # mcap's protobuf support, only when writing

    report = ImportReport()
    kinds: dict[str, list[Path]] = {"bag": [], "capture": [], "canlog": []}
    for p in paths:
        kinds[input_kind(p)].append(Path(p))
    streams: list[Iterable[Item]] = []
    if kinds["bag"]:
        streams.append(rosbag.bag_items(kinds["bag"], scene, mapping, msg_dir, report))
    for p in kinds["capture"]:
        streams.append(capture_items(p, scene, mapping, report))
    for p in kinds["canlog"]:
        streams.append(canlog_items(p, scene, mapping, report))
    partial = out.with_name(out.name + ".partial")
    partial.unlink(missing_ok=True)
    try:
        with RecordingWriter(partial, compression=compression) as writer:
            sink = _Sink(writer, scene, report, rebase_to_ns)
            late: Counter[str] = Counter()
            ordered = [_in_order(s, late) for s in streams]
            for stamp_ns, sensor, message in heapq.merge(*ordered, key=lambda i: i[0]):
                sink.write(sensor, message, stamp_ns)
            if late:
                report.count("import", dict(late))
    except CaptureError:
        partial.unlink(missing_ok=True)
        raise
    except Exception as exc:  # a library's own error on input this code did not foresee
        partial.unlink(missing_ok=True)
        raise CaptureError(f"{', '.join(map(str, paths))}: {type(exc).__name__}: {exc}") from None
    try:
        partial.replace(out)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise CaptureError(f"{out}: cannot be written ({exc})") from None
    report.out = out
    return report


def _in_order(items: Iterable[Item], late: Counter[str]) -> Iterator[Item]:
    """`items` in time order, for items at most REORDER_WINDOW_NS late; later ones are written where they
    come (never dropped) and counted in `late`."""
    heap: list[tuple[int, int, str, Message]] = []
    tie = itertools.count()  # equal stamps keep their input order; messages are never compared
    latest = None
    for stamp_ns, sensor, message in items:
        if latest is not None and stamp_ns < latest - REORDER_WINDOW_NS:
            late[f"late_beyond_reorder_window/{sensor}"] += 1
        heapq.heappush(heap, (stamp_ns, next(tie), sensor, message))
        latest = stamp_ns if latest is None else max(latest, stamp_ns)
        while heap and heap[0][0] < latest - REORDER_WINDOW_NS:
            s, _, sen, msg = heapq.heappop(heap)
            yield s, sen, msg
    while heap:
        s, _, sen, msg = heapq.heappop(heap)
        yield s, sen, msg


class _Sink:
    """Writes scene-sensor messages as the sensor services publish them (key, header, sequence)."""

    def __init__(self, writer: object, scene: Scene, report: ImportReport, rebase_to_ns: int | None) -> None:
        self.writer, self.scene, self.report = writer, scene, report
        self.rebase_to_ns = rebase_to_ns
        self.offset_ns: int | None = None
        self.seq: Counter[str] = Counter()

    def write(self, sensor: str, message: Message, stamp_ns: int) -> None:
        if self.offset_ns is None:
            self.report.first_stamp_ns = stamp_ns
            self.offset_ns = 0 if self.rebase_to_ns is None else self.rebase_to_ns - stamp_ns
        stamp_ns += self.offset_ns
        _restamp(message, stamp_ns)
        spec = self.scene.sensor(sensor)
        self.seq[sensor] += 1
        source = sensor_group_source(spec.agent, spec.kind)
        encoded = encode(message, make_header(source, self.seq[sensor], stamp_ns=stamp_ns, frame_id=sensor))
        key = get_stream(SENSOR_STREAM[spec.kind]).key(agent=spec.agent, sensor=sensor)
        self.writer.write(  # type: ignore[attr-defined]
            key, str(encoded.encoding), encoded.payload, encoded.attachment, stamp_ns, stamp_ns
        )
        self.report.messages[sensor] = self.report.messages.get(sensor, 0) + 1


def _restamp(message: Message, stamp_ns: int) -> None:
    """A foxglove message's own timestamp follows a rebase (the header carries the stamp of record)."""
    if message.DESCRIPTOR.fields_by_name.get("timestamp") is not None:
        message.timestamp.FromNanoseconds(stamp_ns)  # type: ignore[attr-defined]


# --- pcap / pcapng -------------------------------------------------------------------------------


@dataclass
class _UnitSurvey:
    """What one source address sent: packet kinds, data ports, the first DIFOP, Velodyne models."""

    kinds: Counter[str] = field(default_factory=Counter)
    data_ports: Counter[int] = field(default_factory=Counter)
    difop: bytes | None = None
    velodyne: dict[int, Counter[str]] = field(default_factory=dict)  # data port -> factory-byte models
    robosense_ports: set[int] = field(default_factory=set)  # data ports of MSOP packets

    def velodyne_model(self, port: int) -> str | None:
        """The model the factory bytes of the data packets to `port` say most, or None."""
        counts = self.velodyne.get(port)
        model = counts.most_common(1)[0][0] if counts else None
        return None if model == "unknown" else model


def survey_capture(path: Path) -> tuple[dict[str, _UnitSurvey], Counter[str]]:
    """Every source address of the capture's lidar traffic and what it sent; the reader's counts."""
    reader = PcapReader(path)
    units: dict[str, _UnitSurvey] = {}
    for d in reader:
        kind = identify.packet_kind(d.payload)
        if kind is None:
            continue
        u = units.setdefault(d.src[0], _UnitSurvey())
        u.kinds[kind] += 1
        if kind in ("robosense_msop", "velodyne_data"):
            u.data_ports[d.dst[1]] += 1
        if kind == "robosense_msop":
            u.robosense_ports.add(d.dst[1])
        if kind == "robosense_difop" and u.difop is None:
            u.difop = d.payload
        if kind == "velodyne_data":
            u.velodyne.setdefault(d.dst[1], Counter())[identify.velodyne_model(d.payload) or "unknown"] += 1
    return units, reader.counts


def describe_units(units: dict[str, _UnitSurvey]) -> str:
    """One line per unit of a survey, for messages that ask for a mapping."""
    lines = []
    for ip, u in sorted(units.items()):
        kinds = ", ".join(f"{k} {n}" for k, n in sorted(u.kinds.items()))
        ports: list[int | None] = [*sorted(u.data_ports)] or [None]
        for port in ports:
            if port is not None and port in u.velodyne:
                family, model = "velodyne", u.velodyne_model(port)
            else:
                family, model = "robosense", identify.robosense_model(u.difop) if u.difop else None
            lines.append(f"{ip} -> port {port or '-'}: {family} {model or '(model unknown)'} ({kinds})")
    return "; ".join(lines)


def capture_items(path: Path, scene: Scene, mapping: Mapping | None, report: ImportReport) -> Iterator[Item]:
    """The scene-sensor messages of a pcap / pcapng capture's lidar units."""
    units, first_counts = survey_capture(path)
    if not units:
        raise MappingError(f"{path}: no Robosense or Velodyne packets in it ({dict(first_counts)})")
    if mapping is None or not mapping.units:
        raise MappingError(
            f"{path}: a capture's units are bound to sensors by the mapping's `units:` "
            f"(source address[:destination port]); found: {describe_units(units)}"
        )
    decoders: dict[tuple[str, int], RobosenseUnit | VelodyneUnit] = {}
    by_ip: dict[str, list[RobosenseUnit | VelodyneUnit]] = {}
    for ip, u in sorted(units.items()):
        for port in sorted(u.data_ports):
            found = mapping.unit_for(ip, port)
            where = f"{path.name}: unit {ip} -> port {port}"
            if found is None:
                report.skipped[f"{path.name} {ip}:{port}"] = f"not in the mapping ({describe_units({ip: u})})"
                continue
            key, binding = found
            if scene.sensor(binding.sensor).kind != "lidar":
                raise MappingError(
                    f"{where}: {binding.sensor} is a {scene.sensor(binding.sensor).kind}, not a lidar"
                )
            is_velodyne = port in u.velodyne
            if not is_velodyne and len(u.robosense_ports) > 1:
                raise MappingError(
                    f"{where}: Robosense units at one address ({ip}, ports {sorted(u.robosense_ports)}): "
                    "their DIFOP packets cannot be told apart; give each unit its own address"
                )
            if not is_velodyne and u.difop is None:
                raise MappingError(
                    f"{where}: a Robosense unit without a DIFOP packet in the capture: its angles are unknown"
                )
            unit = lidar_unit(binding, u.difop, u.velodyne_model(port) if is_velodyne else None, where)
            if isinstance(unit, RobosenseUnit) and u.difop is not None:
                unit.on_packet(u.difop, 0)  # its angles before its first revolution
            decoders[(ip, port)] = unit
            report.devices[binding.sensor] = unit.device
            by_ip.setdefault(ip, []).append(unit)
            report.mapped[f"{path.name} {key}"] = binding.sensor
    reader = PcapReader(path)
    for d in reader:
        kind = identify.packet_kind(d.payload)
        if kind is None:
            reader.counts["skipped/not_lidar"] += 1
            continue
        if kind in ("robosense_difop", "velodyne_position"):
            family = RobosenseUnit if kind == "robosense_difop" else VelodyneUnit
            targets = [t for t in by_ip.get(d.src[0], []) if isinstance(t, family)]
        else:
            bound = decoders.get((d.src[0], d.dst[1]))
            targets = [bound] if bound is not None else []
        for unit in targets:
            for message, stamp_ns in unit.on_packet(d.payload, d.stamp_ns):
                yield stamp_ns, unit.sensor, message
    for unit in decoders.values():
        unit.finish()
        report.count(unit.sensor, unit.counters())
    cut = {"truncated_at_byte": reader.truncated_at} if reader.truncated_at is not None else {}
    report.count(path.name, dict(reader.counts) | cut)


# --- CAN logs ------------------------------------------------------------------------------------


def canlog_items(path: Path, scene: Scene, mapping: Mapping | None, report: ImportReport) -> Iterator[Item]:
    """The radar lists of a CAN log's ARS 408 radars, bound by the mapping's `radars:` section."""
    bindings = mapping.radar_bindings() if mapping is not None else []
    if not bindings:
        raise MappingError(
            f"{path}: a CAN log's radars are bound to sensors by the mapping's `radars:` section "
            f"({{<sensor>: {{can_id: 0..7, channel: <log channel>}}}}); the ARS 408 sensor ids in it: "
            f"{sorted(_radar_ids(path))}"
        )
    units: list[tuple[Binding, RadarUnit]] = []
    for b in bindings:
        if scene.sensor(b.sensor).kind != "radar":
            raise MappingError(f"{path.name}: {b.sensor} is a {scene.sensor(b.sensor).kind}, not a radar")
        units.append((b, RadarUnit(b.sensor, b.can_id or 0)))
        on = f" on {b.channel}" if b.channel else ""
        report.mapped[f"{path.name} radar {b.can_id or 0}{on}"] = b.sensor
    # The units a frame goes to, by its channel and its ARS 408 sensor id (a binding with no channel
    # takes every channel's); worked out once per channel the log names.
    routes: dict[str, dict[int, list[RadarUnit]]] = {}
    no_units: list[RadarUnit] = []

    def route(channel: str) -> dict[int, list[RadarUnit]]:
        found: dict[int, list[RadarUnit]] = {}
        for b, u in units:
            if b.channel is None or b.channel == channel:
                found.setdefault(b.can_id or 0, []).append(u)
        return routes.setdefault(channel, found)

    reader = CanLogReader(path)
    for frame in reader:
        by_id = routes.get(frame.channel) or route(frame.channel)
        if frame.is_error:
            for targets in by_id.values():
                for u in targets:
                    u.on_error_frame(frame.can_id)
            continue
        if frame.is_remote or frame.is_extended:
            reader.counts["skipped/not_ars408"] += 1
            continue
        targets = by_id.get(ars408.split_id(frame.can_id)[1], no_units)
        if not targets:
            reader.counts["skipped/other_radar_or_device"] += 1
            continue
        for unit in targets:
            for message, stamp_ns in unit.on_frame(frame.can_id, frame.data, frame.stamp_s):
                yield stamp_ns, unit.sensor, message
    for _, unit in units:
        unit.finish()
        report.count(unit.sensor, unit.counters())
    bad = {"first_bad_line": reader.first_bad_line} if reader.first_bad_line is not None else {}
    report.count(path.name, dict(reader.counts) | bad)


def _radar_ids(path: Path) -> set[int]:
    """The sensor ids of the ARS 408 state messages (0x201 + 0x10 id) in a CAN log."""
    found = set()
    for frame in CanLogReader(path):
        base, sensor_id = ars408.split_id(frame.can_id)
        if base == ars408.ID_STATE and not frame.is_extended:
            found.add(sensor_id)
    return found
