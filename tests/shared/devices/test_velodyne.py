"""Velodyne VLP-16 through `velodyne-decoder`: packets emulated from the user manual's layout come
back as the points they describe; the device source stamps and publishes them; bad packets are
counted. (The second lidar family: the sim's wire profile emulates Robosense units only.)"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from shared.devices import velodyne
from shared.devices.site import VelodyneLidar
from shared.devices.sources import Output, VelodyneSource
from shared.devices.velodyne import HOUR_NS
from shared.perception.decode import point_cloud_to_array
from sim.emulators.velodyne import PACKET_LEN, VLP16_ELEVATION_DEG, vlp16_packet
from tests.helpers import free_port

T0_NS = 1_790_000_000 * 1_000_000_000


def test_packet_layout_known_answer() -> None:
    distance = np.zeros((12, 32))
    distance[0, 0] = 2.0  # 1000 x 2 mm
    reflectivity = np.zeros((12, 32), int)
    reflectivity[0, 0] = 100
    pkt = vlp16_packet(np.arange(12) * 40 + 4800, distance, reflectivity, 123_456)
    assert len(pkt) == PACKET_LEN == 1206
    assert pkt[0:2] == b"\xff\xee" and struct.unpack_from("<H", pkt, 2)[0] == 4800
    assert struct.unpack_from("<HB", pkt, 4) == (1000, 100)
    assert struct.unpack_from("<IBB", pkt, 1200) == (123_456, 0x37, 0x22)
    assert VLP16_ELEVATION_DEG[:4] == (-15.0, 1.0, -13.0, 3.0) and VLP16_ELEVATION_DEG[-1] == 15.0


def revolution(turn: int, returns: dict[tuple[int, int, int], float]) -> list[bytes]:
    """76 packets (a turn and the next one's first): (packet, block, channel) -> metres."""
    out = []
    for p in range(76):
        distance = np.zeros((12, 32))
        reflectivity = np.zeros((12, 32), int)
        for (pp, b, c), d in returns.items():
            if pp == p:
                distance[b, c], reflectivity[b, c] = d, 128
        out.append(
            vlp16_packet((np.arange(12) + 12 * p) * 40, distance, reflectivity, turn * 100_000 + p * 1_333)
        )
    return out


@pytest.fixture
def source() -> tuple[VelodyneSource, list[Output]]:
    outputs: list[Output] = []
    spec = VelodyneLidar(
        device="vlp16", unit_address="127.0.0.1", bind="127.0.0.1", data_port=free_port(), clock="device"
    )
    src = VelodyneSource("lidar_12", spec, outputs.append)
    yield src, outputs
    src.close()


def test_returns_come_back_where_the_packets_put_them(source) -> None:
    src, outputs = source
    returns = {(10, 0, 0): 2.0, (10, 0, 17): 3.0}  # laser 0 (-15 deg) at 48.0 deg; laser 1 (+1 deg) at 48.2
    host_ns = T0_NS + 5 * HOUR_NS // 1000
    for turn in range(2):
        for i, pkt in enumerate(revolution(turn, returns)):
            src.on_packet(pkt, host_ns + turn * 100_000_000 + i * 1_333_000)
    assert len(outputs) >= 1
    points = point_cloud_to_array(outputs[0].message)
    assert len(points) == 2
    for (x, y, z, intensity), (distance, azimuth, elevation) in zip(
        points, [(2.0, 48.0, -15.0), (3.0, 48.2, 1.0)], strict=True
    ):
        rng = math.sqrt(x * x + y * y + z * z)
        # the decoder applies the unit's factory corrections (a few mm, a fraction of a degree)
        assert rng == pytest.approx(distance, abs=0.01)
        assert math.degrees(math.atan2(-y, x)) == pytest.approx(azimuth, abs=0.05)  # clockwise, y left
        assert math.degrees(math.asin(z / rng)) == pytest.approx(elevation, abs=0.5)
        assert intensity == pytest.approx(128 / 255)
    assert not outputs[0].on_wall_clock
    assert src.counters_snapshot()["packets"] == 152


def test_device_time_is_put_on_the_hosts_hour() -> None:
    hour = 5 * HOUR_NS
    assert velodyne.on_host_hour(10_000_000, hour + 20_000_000) == hour + 10_000_000
    # just after the hour turned on the host, a packet from just before it: the previous hour
    assert velodyne.on_host_hour(HOUR_NS - 5_000_000, hour + 1_000_000) == hour - 5_000_000


def test_bad_packets_are_counted(source) -> None:
    src, outputs = source
    src.on_packet(b"\x00" * 100, T0_NS)
    src.on_packet(b"\x00" * PACKET_LEN, T0_NS)  # no block flags: decoded as nothing, not a crash
    assert src.counters_snapshot()["rejected/packet/bad_length"] == 1
    assert outputs == []
