"""`rmmdet import` of captures and CAN logs (shared/captures/importer.py): real captures and a real
radar log into recordings (bound by the mapping, models from the bytes), several inputs merged by
time, the drivers' packet messages in bags written here (rslidar_sdk's 2022 layout, can_msgs), and
what cannot be imported named with nothing written."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from shared.captures.errors import CaptureError, MappingError
from shared.captures.importer import import_files
from shared.captures.mapping import load_mapping
from shared.captures.rosbag import LEGACY_MSG_DIR, MSG_DIR, register_msg_dir
from shared.captures.units import RobosenseUnit
from shared.paths import DEFAULT_SCENE
from shared.recording.reader import decode_record, read_records
from shared.scene.scene import Scene
from sim.emulators.robosense import RobosenseEmulator

REAL = Path(__file__).parents[2] / "fixtures" / "real"
VLP16_GPS = REAL / "mrpt_velodyne" / "sample_velodyne_vlp16_gps.pcap"
CAN_LOG = REAL / "ars408_candump" / "candump-2026-06-24_154259.log"
T0_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def _mapping(tmp_path: Path, scene: Scene, text: str):
    path = tmp_path / "map.yaml"
    path.write_text(text)
    return load_mapping(path, scene)


def _records(path: Path) -> list:
    return [decode_record(r) for r in read_records(path)]


def test_a_real_capture_and_a_real_radar_log_make_one_recording(tmp_path: Path, scene: Scene) -> None:
    mapping = _mapping(tmp_path, scene, "units:\n  10.0.0.100: lidar_11\nradars:\n  radar_2: {can_id: 0}\n")
    out = tmp_path / "rec.mcap"
    report = import_files([VLP16_GPS, CAN_LOG], out, scene, mapping)
    # The VLP-16 (recognised by its factory byte): 3 whole revolutions of its 293 packets; 57 GPS packets.
    assert report.messages == {"lidar_11": 3, "radar_2": 515}
    assert report.counters["lidar_11"]["position_packets"] == 57
    assert report.mapped == {f"{VLP16_GPS.name} 10.0.0.100": "lidar_11", f"{CAN_LOG.name} radar 0": "radar_2"}
    records = _records(out)
    stamps = [r.record.publish_time_ns for r in records]
    assert stamps == sorted(stamps)  # merged by time, though the two were recorded years apart
    clouds = [r for r in records if "lidar_11" in r.record.key]
    assert len(clouds) == 3 and all(len(c.message.data) > 100_000 for c in clouds)


def test_a_capture_needs_units_and_says_what_it_holds(tmp_path: Path, scene: Scene) -> None:
    out = tmp_path / "rec.mcap"
    with pytest.raises(MappingError, match=r"10\.0\.0\.100 -> port 2368: velodyne vlp16"):
        import_files([VLP16_GPS], out, scene, None)
    wrong = _mapping(tmp_path, scene, "units:\n  10.0.0.100: {sensor: lidar_11, device: vlp32c}\n")
    with pytest.raises(MappingError, match="the mapping says vlp32c, the unit's packets say vlp16"):
        import_files([VLP16_GPS], out, scene, wrong)
    radar = _mapping(tmp_path, scene, "units:\n  10.0.0.100: radar_2\n")
    with pytest.raises(MappingError, match="radar_2 is a radar, not a lidar"):
        import_files([VLP16_GPS], out, scene, radar)
    with pytest.raises(MappingError, match=r"ARS 408 sensor ids in it: \[0\]"):
        import_files([CAN_LOG], out, scene, None)
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(CaptureError, match="neither a ROS bag"):
        import_files([tmp_path / "notes.txt"], out, scene, None)
    assert not out.exists() and not out.with_name(out.name + ".partial").exists()


def _robosense_packets(device: str, turns: int) -> tuple[list[tuple[int, bytes]], bytes]:
    emulator = RobosenseEmulator(device, samples=400)
    lasers = emulator.model.lasers
    laser, sample = np.repeat(np.arange(lasers), 400), np.tile(np.arange(400), lasers)
    packets = []
    for k in range(turns):
        start = T0_NS + k * emulator.period_ns
        turn = emulator.msop_packets(
            laser, sample, np.full(laser.shape, 3.0 + k), np.full(laser.shape, 0.5), start
        )
        packets += [(start + j * 500_000, p) for j, p in enumerate(turn)]
    return packets, emulator.difop_packet(T0_NS)


def test_robosense_capture_model_from_its_difop_even_when_the_difop_comes_late(
    tmp_path: Path, scene: Scene
) -> None:
    """Written here (no public Robosense capture): an RS-LiDAR-32's MSOP on port 6699 with its DIFOP
    only after its second revolution; the importer takes the DIFOP first (its survey pass), so no
    revolution is lost, and recognises the model from it."""
    packets, difop = _robosense_packets("rs32", 4)
    frames = []
    for i, (stamp, data) in enumerate(packets):
        frames.append((stamp, 200, 6699, data))
        if i == len(packets) // 2:
            frames.append((stamp, 200, 7788, difop))
    path = _capture(tmp_path / "rs32.pcapng", frames)
    mapping = _mapping(tmp_path, scene, "units:\n  192.168.1.200: lidar_12\n")
    report = import_files([path], tmp_path / "rec.mcap", scene, mapping)
    expected = RobosenseUnit("lidar_12", "rs32")
    expected.on_packet(difop, 0)
    want = [m for stamp, data in packets for m, _ in expected.on_packet(data, stamp)]
    assert report.messages == {"lidar_12": len(want)} and len(want) >= 3
    got = [r.message for r in _records(tmp_path / "rec.mcap")]
    assert all(a.data == b.data for a, b in zip(got, want, strict=True))


def _capture(path: Path, frames: list[tuple[int, int, int, bytes]]) -> Path:
    """A pcapng of (stamp ns, source host 192.168.1.<n>, port, payload) UDP datagrams."""
    import dpkt

    with path.open("wb") as f:
        w = dpkt.pcapng.Writer(f)
        for stamp, host, port, data in frames:
            u = dpkt.udp.UDP(sport=port, dport=port, data=data)
            u.ulen = len(u)
            ip = dpkt.ip.IP(src=bytes([192, 168, 1, host]), dst=bytes([192, 168, 1, 102]), p=17, data=u)
            ip.len = len(ip)
            w.writepkt(bytes(dpkt.ethernet.Ethernet(data=ip)), ts=stamp / 1e9)
    return path


def test_units_at_one_address_are_told_apart_by_port(tmp_path: Path, scene: Scene) -> None:
    """Two Velodynes at the factory address 192.168.1.201 on two data ports, a VLP-16 and (its factory
    byte rewritten here) a VLP-32C: each unit its own model. Two Robosense units at one address are
    refused: their DIFOP packets, on one port, cannot be told apart."""
    from shared.captures.pcap import PcapReader

    vlp16 = [g.payload for g in PcapReader(VLP16_GPS) if len(g.payload) == 1206][:40]
    as_32c = [p[:1205] + bytes([0x28]) for p in vlp16]
    frames = [(T0_NS + i * 10**6, 201, 2368, p) for i, p in enumerate(vlp16)]
    frames += [(T0_NS + i * 10**6 + 500, 201, 2369, p) for i, p in enumerate(as_32c)]
    path = _capture(tmp_path / "two.pcapng", sorted(frames))
    from shared.captures.importer import survey_capture

    (unit,) = survey_capture(path)[0].values()
    assert unit.velodyne_model(2368) == "vlp16" and unit.velodyne_model(2369) == "vlp32c"
    packets, difop = _robosense_packets("rs16", 1)
    rs = [(T0_NS, 200, 7788, difop)] + [(s, 200, 6699 + k % 2, p) for k, (s, p) in enumerate(packets)]
    mapping = _mapping(
        tmp_path, scene, "units:\n  192.168.1.200:6699: lidar_11\n  192.168.1.200:6700: lidar_12\n"
    )
    with pytest.raises(MappingError, match="their DIFOP packets cannot be told apart"):
        import_files([_capture(tmp_path / "rs.pcapng", rs)], tmp_path / "x.mcap", scene, mapping)


def test_a_bag_s_difop_is_found_however_far_in(tmp_path: Path, scene: Scene) -> None:
    """rslidar_sdk's current layout, one packet a message, the first DIFOP after 250 MSOP packets
    (a unit sends one a second among ~800 MSOP; the search once stopped at 200): found, and every
    packet decoded."""
    packets, difop = _robosense_packets("rs16", 16)
    items = [(s, d, 0) for s, d in packets]
    assert len(items) > 250
    items.insert(250, (items[249][0], difop, 1))
    bag = _rslidar_bag(tmp_path / "late_difop", items)
    mapping = _mapping(tmp_path, scene, "topics:\n  /rslidar_packets: lidar_11\n")
    report = import_files([bag], tmp_path / "rec.mcap", scene, mapping)
    assert report.devices == {"lidar_11": "rs16"} and report.counters["lidar_11"]["msop"] == len(packets)


def _rslidar_bag(path: Path, items: list[tuple[int, bytes, int]]) -> Path:
    """A ROS 2 mcap bag of rslidar_sdk's current `RslidarPacket` messages, one (stamp ns, packet,
    is_difop) a message on /rslidar_packets."""
    store = _store(legacy=False)
    t_cls, h_cls = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    p_cls = store.types["rslidar_msg/msg/RslidarPacket"]
    with Ros2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/rslidar_packets", "rslidar_msg/msg/RslidarPacket", typestore=store)
        for stamp, data, is_difop in items:
            header = h_cls(stamp=t_cls(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="rslidar")
            msg = p_cls(
                header=header, is_difop=is_difop, is_frame_begin=0, data=np.frombuffer(data, np.uint8)
            )
            writer.write(conn, stamp, store.serialize_cdr(msg, "rslidar_msg/msg/RslidarPacket"))
    return path


def _store(legacy: bool):
    store = get_typestore(Stores.ROS2_HUMBLE)
    for folder in (LEGACY_MSG_DIR if legacy else None, MSG_DIR):
        if folder is not None:
            register_msg_dir(store, folder, only_new=True)
    return store


def test_rslidar_sdk_2022_layout_packet_arrays(tmp_path: Path, scene: Scene) -> None:
    """rslidar_sdk's 2022 messages (RslidarScan: arrays of {stamp, uint8[1248] data}; DIFOP alone on
    its own topic), as a real RS-LiDAR-16 bag holds them (its packets' own stamps zero), written here
    in a sqlite3 bag that stores no definitions: imported with only the topics mapped."""
    packets, difop = _robosense_packets("rs16", 3)
    store = _store(legacy=True)
    time_cls = store.types["builtin_interfaces/msg/Time"]
    header_cls, packet_cls = store.types["std_msgs/msg/Header"], store.types["rslidar_msg/msg/RslidarPacket"]
    scan_cls = store.types["rslidar_msg/msg/RslidarScan"]

    def t(ns: int):
        return time_cls(sec=ns // 10**9, nanosec=ns % 10**9)

    bag = tmp_path / "rs16_2022"
    with Ros2Writer(bag, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        scans = writer.add_connection("/rslidar_packets", "rslidar_msg/msg/RslidarScan", typestore=store)
        difops = writer.add_connection(
            "/rslidar_packets_difop", "rslidar_msg/msg/RslidarPacket", typestore=store
        )
        d = packet_cls(stamp=t(0), data=np.frombuffer(difop, np.uint8))
        writer.write(difops, T0_NS, store.serialize_cdr(d, "rslidar_msg/msg/RslidarPacket"))
        for k in range(0, len(packets), 25):
            chunk = packets[k : k + 25]
            stamp = chunk[-1][0]
            msg = scan_cls(
                header=header_cls(stamp=t(stamp), frame_id="rslidar"),
                packets=[packet_cls(stamp=t(0), data=np.frombuffer(p, np.uint8)) for _, p in chunk],
            )
            writer.write(scans, stamp, store.serialize_cdr(msg, "rslidar_msg/msg/RslidarScan"))
    with sqlite3.connect(next(bag.glob("*.db3"))) as db:  # as rosbag2 before Iron wrote it: no definitions
        db.execute("DELETE FROM message_definitions")
    mapping = _mapping(
        tmp_path, scene, "topics:\n  /rslidar_packets: lidar_11\n  /rslidar_packets_difop: lidar_11\n"
    )
    report = import_files([bag], tmp_path / "rec.mcap", scene, mapping)
    assert report.messages["lidar_11"] >= 2
    assert report.counters["lidar_11"]["msop"] == len(packets)


def test_can_msgs_frames_in_a_bag(tmp_path: Path, scene: Scene) -> None:
    """The real radar log's frames as can_msgs/Frame (ros2_socketcan's message), written here: the same
    lists as from the log itself."""
    from shared.captures.canlog import CanLogReader

    store = _store(legacy=False)
    frame_cls = store.types["can_msgs/msg/Frame"]
    header_cls, time_cls = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    bag = tmp_path / "can"
    with Ros2Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/from_can_bus", "can_msgs/msg/Frame", typestore=store)
        for f in CanLogReader(CAN_LOG):
            ns = round(f.stamp_s * 1e9)
            data = np.zeros(8, np.uint8)
            data[: len(f.data)] = np.frombuffer(f.data, np.uint8)
            msg = frame_cls(
                header=header_cls(stamp=time_cls(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="can1"),
                id=f.can_id, is_rtr=False, is_extended=False, is_error=False, dlc=len(f.data), data=data,
            )  # fmt: skip
            writer.write(conn, ns, store.serialize_cdr(msg, "can_msgs/msg/Frame"))
    mapping = _mapping(tmp_path, scene, "topics:\n  /from_can_bus: {sensor: radar_2, can_id: 0}\n")
    from_bag = import_files([bag], tmp_path / "a.mcap", scene, mapping)
    radars = _mapping(tmp_path, scene, "radars:\n  radar_2: {can_id: 0, channel: can1}\n")
    from_log = import_files([CAN_LOG], tmp_path / "b.mcap", scene, radars)
    assert from_bag.messages == from_log.messages == {"radar_2": 515}
    a = [r.message for r in _records(tmp_path / "a.mcap")]
    b = [r.message for r in _records(tmp_path / "b.mcap")]
    assert a == b


NEBULA_VLP16 = REAL / "nebula_velodyne" / "vlp16" / "bag"


def test_a_real_velodyne_bag_and_the_same_packets_as_nebula_packets(tmp_path: Path, scene: Scene) -> None:
    """nebula's real VLP-16 bag (velodyne_msgs/VelodyneScan, no stored definitions) imported with only
    its topic mapped and the unit's own calibration file; its packets rewritten here as
    nebula_msgs/NebulaPackets import to the same clouds."""
    from rosbags.highlevel import AnyReader

    from shared.captures.units import VelodyneUnit

    calibration = REAL / "nebula_velodyne" / "calibration" / "VLP16.yaml"
    mapping = _mapping(
        tmp_path, scene, f"topics:\n  /velodyne_packets: {{sensor: lidar_11, calibration: {calibration}}}\n"
    )
    report = import_files([NEBULA_VLP16], tmp_path / "a.mcap", scene, mapping)
    assert report.devices == {"lidar_11": "vlp16"} and report.counters["lidar_11"]["packets"] == 603
    store = _store(legacy=False)
    packets = []
    with AnyReader([NEBULA_VLP16], default_typestore=store) as reader:
        for c, _, raw in reader.messages():
            msg = reader.deserialize(raw, c.msgtype)
            packets += [(p.stamp.sec * 10**9 + p.stamp.nanosec, bytes(p.data)) for p in msg.packets]
    unit = VelodyneUnit("lidar_11", "vlp16", calibration)
    expected = [m for stamp, data in packets for m, _ in unit.on_packet(data, stamp)]
    got = [r.message for r in _records(tmp_path / "a.mcap")]
    assert len(got) == len(expected) == report.messages["lidar_11"] >= 3
    assert all(a.data == b.data for a, b in zip(got, expected, strict=True))
    t_cls, h_cls = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    p_cls, s_cls = store.types["nebula_msgs/msg/NebulaPacket"], store.types["nebula_msgs/msg/NebulaPackets"]
    bag = tmp_path / "nebula"
    with Ros2Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/velodyne_packets", "nebula_msgs/msg/NebulaPackets", typestore=store)
        for k in range(0, len(packets), 100):
            chunk = packets[k : k + 100]
            stamp = chunk[-1][0]

            def t(ns: int):
                return t_cls(sec=ns // 10**9, nanosec=ns % 10**9)

            msg = s_cls(
                header=h_cls(stamp=t(stamp), frame_id="velodyne"),
                packets=[p_cls(stamp=t(s), data=np.frombuffer(d, np.uint8)) for s, d in chunk],
            )
            writer.write(conn, stamp, store.serialize_cdr(msg, "nebula_msgs/msg/NebulaPackets"))
    import_files([bag], tmp_path / "b.mcap", scene, mapping)
    again = [r.message for r in _records(tmp_path / "b.mcap")]
    assert [m.data for m in again] == [m.data for m in got]


def test_ros1_driver_layouts(tmp_path: Path, scene: Scene) -> None:
    """ROS 1 bags as ros_rslidar writes them (rslidar_msgs/rslidarScan arrays, a DIFOP as
    rslidar_msgs/rslidarPacket; an emulated RS-LiDAR-16 written here) and as the ROS 1 velodyne driver
    writes single packets (velodyne_msgs/VelodynePacket; nebula's real VLP-16 packets rewritten here)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer as Ros1Writer

    from shared.captures.units import VelodyneUnit

    store = get_typestore(Stores.ROS1_NOETIC)
    register_msg_dir(store, MSG_DIR, only_new=True)
    t_cls, h_cls = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]

    def t(ns: int):
        return t_cls(sec=ns // 10**9, nanosec=ns % 10**9)

    packets, difop = _robosense_packets("rs16", 3)
    packet_type, scan_type = "rslidar_msgs/msg/rslidarPacket", "rslidar_msgs/msg/rslidarScan"
    rs_packet, rs_scan = store.types[packet_type], store.types[scan_type]
    v_packet = store.types["velodyne_msgs/msg/VelodynePacket"]
    velodyne = []
    with AnyReader([NEBULA_VLP16], default_typestore=_store(legacy=False)) as reader:
        for c, _, raw in reader.messages():
            msg = reader.deserialize(raw, c.msgtype)
            velodyne += [(p.stamp.sec * 10**9 + p.stamp.nanosec, bytes(p.data)) for p in msg.packets]
    bag = tmp_path / "drivers.bag"
    with Ros1Writer(bag) as writer:
        scans = writer.add_connection("/rslidar_packets", scan_type, typestore=store)
        difops = writer.add_connection("/rslidar_packets_difop", packet_type, typestore=store)
        vlp = writer.add_connection("/velodyne_packets", "velodyne_msgs/msg/VelodynePacket", typestore=store)
        d = rs_packet(stamp=t(T0_NS), data=np.frombuffer(difop, np.uint8))
        writer.write(difops, T0_NS, store.serialize_ros1(d, packet_type))
        for k in range(0, len(packets), 30):
            chunk = packets[k : k + 30]
            msg = rs_scan(
                header=h_cls(seq=k, stamp=t(chunk[-1][0]), frame_id="rslidar"),
                packets=[rs_packet(stamp=t(s), data=np.frombuffer(p, np.uint8)) for s, p in chunk],
            )
            writer.write(scans, chunk[-1][0], store.serialize_ros1(msg, scan_type))
        for stamp, data in velodyne:  # another time, another unit: the bag holds both
            p = v_packet(stamp=t(stamp), data=np.frombuffer(data, np.uint8))
            writer.write(vlp, stamp, store.serialize_ros1(p, "velodyne_msgs/msg/VelodynePacket"))
    mapping = _mapping(
        tmp_path, scene, "topics:\n  /rslidar_packets: lidar_11\n  /rslidar_packets_difop: lidar_11\n"
        "  /velodyne_packets: lidar_12\n"
    )  # fmt: skip
    report = import_files([bag], tmp_path / "rec.mcap", scene, mapping)
    assert report.devices == {"lidar_11": "rs16", "lidar_12": "vlp16"}
    assert report.counters["lidar_11"]["msop"] == len(packets) and report.messages["lidar_11"] >= 2
    unit = VelodyneUnit("lidar_12", "vlp16")
    expected = [m for stamp, data in velodyne for m, _ in unit.on_packet(data, stamp)]
    got = [r.message for r in _records(tmp_path / "rec.mcap") if "lidar_12" in r.record.key]
    assert [m.data for m in got] == [m.data for m in expected] and len(got) >= 3


def test_a_wrong_length_packet_is_counted_not_a_reason_to_refuse_the_bag(
    tmp_path: Path, scene: Scene
) -> None:
    """rslidar_sdk's current layout with one packet cut to 1000 bytes half-way: the layout is decided
    on the first packet, the short one is the decoder's to count (it once sent the import to the
    2022 layout and refused the bag whole)."""
    packets, difop = _robosense_packets("rs16", 3)
    packets[len(packets) // 2] = (packets[len(packets) // 2][0], packets[len(packets) // 2][1][:1000])
    bag = _rslidar_bag(tmp_path / "current", [(T0_NS, difop, 1), *((s, d, 0) for s, d in packets)])
    mapping = _mapping(tmp_path, scene, "topics:\n  /rslidar_packets: lidar_11\n")
    report = import_files([bag], tmp_path / "rec.mcap", scene, mapping)
    assert report.counters["lidar_11"]["rejected/msop/bad_length"] == 1
    assert report.counters["lidar_11"]["msop"] == len(packets) - 1 and report.messages["lidar_11"] >= 1
