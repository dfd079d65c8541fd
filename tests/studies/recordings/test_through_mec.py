"""studies/recordings/through_mec.py: an RS-LiDAR-16 bag in rslidar_sdk's 2022 layout (the layout of the
real bag the issue names, which cannot be vendored: docs/recordings.md), written here from the
emulator looking at flat empty ground from 3 m up, imported with only the topics mapped, replays
through the production MecCore: every cloud processed, the unit's height found, nothing boxed on
empty ground."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_typestore

from shared.captures.rosbag import LEGACY_MSG_DIR, MSG_DIR, register_msg_dir
from sim.emulators.robosense import RobosenseEmulator
from studies.recordings import through_mec

T0_NS = 1_660_622_130_000_000_000
HEIGHT_M = 3.0
TURNS = 8
SAMPLES = 900


def _write_bag(path: Path) -> None:
    em = RobosenseEmulator("rs16", samples=SAMPLES)
    vertical = np.radians(np.asarray(em.vertical))
    down = np.flatnonzero(vertical < -0.02)  # the lasers that see the ground within 90 m
    laser = np.repeat(down, SAMPLES)
    sample = np.tile(np.arange(SAMPLES), len(down))
    distance = HEIGHT_M / np.sin(-vertical[laser])
    store = get_typestore(Stores.ROS2_HUMBLE)
    for folder in (LEGACY_MSG_DIR, MSG_DIR):
        register_msg_dir(store, folder, only_new=True)
    t_cls, h_cls = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    p_cls, s_cls = store.types["rslidar_msg/msg/RslidarPacket"], store.types["rslidar_msg/msg/RslidarScan"]

    def t(ns: int):
        return t_cls(sec=ns // 10**9, nanosec=ns % 10**9)

    with Ros2Writer(path, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
        packet_type, scan_type = "rslidar_msg/msg/RslidarPacket", "rslidar_msg/msg/RslidarScan"
        scans = writer.add_connection("/rslidar_packets", scan_type, typestore=store)
        difops = writer.add_connection("/rslidar_packets_difop", packet_type, typestore=store)
        for k in range(TURNS):
            start = T0_NS + k * em.period_ns
            if k % 10 == 0:  # a DIFOP a second, as the unit sends it
                d = p_cls(stamp=t(0), data=np.frombuffer(em.difop_packet(start), np.uint8))
                writer.write(difops, start, store.serialize_cdr(d, packet_type))
            packets = em.msop_packets(laser, sample, distance, np.full(len(laser), 0.4), start)
            end = start + em.period_ns
            msg = s_cls(
                header=h_cls(stamp=t(end), frame_id="/rslidar"),
                packets=[p_cls(stamp=t(0), data=np.frombuffer(p, np.uint8)) for p in packets],
            )
            writer.write(scans, end, store.serialize_cdr(msg, scan_type))
    with sqlite3.connect(next(path.glob("*.db3"))) as db:  # rosbag2 before Iron stored no definitions
        db.execute("DELETE FROM message_definitions")


def test_an_rslidar_sdk_bag_replays_through_a_mec_configured_for_it(tmp_path: Path) -> None:
    bag = tmp_path / "rosbag2_rs16"
    _write_bag(bag)
    mapping = tmp_path / "map.yaml"
    mapping.write_text("topics:\n  /rslidar_packets: lidar_1\n  /rslidar_packets_difop: lidar_1\n")
    result = through_mec.study([bag], mapping, "written_here")
    assert result["device"] == "rs16"  # from its DIFOP: the mapping names no model
    assert abs(result["lidar_height_m"] - HEIGHT_M) < 0.05 and result["ground_share"] > 0.95
    lidar = result["lidar"]
    assert lidar["channels"] == 16 and math.degrees(lidar["vertical_min_rad"]) < -13
    mec = result["mec"]
    clouds = result["import"]["counters"]["frames"]
    assert mec["clouds"] == clouds >= TURNS - 2 and mec["frames_processed"] == clouds
    assert mec["clouds_rejected"] == 0 and mec["lidar_boxes_per_frame"]["max"] == 0  # empty ground
    assert "frames processed" in through_mec.markdown(result)
