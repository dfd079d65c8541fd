"""Robosense MSOP / DIFOP decoding: known answers on packets made by hand from the documented layout
(`docs/references.md` "RS-LiDAR"), the public decoders' disagreements (each resolved beside its
test), frame splitting, and a round trip simulator -> emulator -> decoder."""

from __future__ import annotations

import calendar
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shared.devices import robosense as rs
from shared.scene.model import LidarModel
from sim.emulators.robosense import RobosenseEmulator, temperature_le, utc_ns
from sim.sensors.lidar import ray_layout

T0_NS = utc_ns(2026, 11, 26, 12, 34, 56) + 789_123_000  # 2026-11-26 12:34:56.789123 UTC


def hand_msop(blocks: list[tuple[int, dict[int, tuple[int, int]]]], ymd: bytes | None = None) -> bytes:
    """An MSOP packet from the manual's layout: 8-byte id, 12 reserved, 10-byte YMD time at 20, blocks
    at 42 + 100 k (FF EE, azimuth u16 BE, 32 x {distance u16 BE, intensity u8}), index, 00 FF.
    `blocks`: (azimuth, {channel: (distance units, intensity)}) for the first blocks; the rest repeat
    the last azimuth + 40 each with no returns."""
    pkt = bytearray(1248)
    pkt[0:8] = bytes([0x55, 0xAA, 0x05, 0x0A, 0x5A, 0xA5, 0x50, 0xA0])
    # 2026-11-26 12:34:56, 789 ms (0x0315), 123 us (0x007B)
    pkt[20:30] = ymd if ymd is not None else bytes([26, 11, 26, 12, 34, 56, 0x03, 0x15, 0x00, 0x7B])
    az = 0
    for k in range(12):
        if k < len(blocks):
            az, channels = blocks[k]
        else:
            az, channels = az + 40, {}
        base = 42 + 100 * k
        pkt[base : base + 2] = b"\xff\xee"
        pkt[base + 2 : base + 4] = az.to_bytes(2, "big")
        for chan, (dist, intensity) in channels.items():
            pkt[base + 4 + 3 * chan : base + 6 + 3 * chan] = dist.to_bytes(2, "big")
            pkt[base + 6 + 3 * chan] = intensity
    pkt[1246:1248] = b"\x00\xff"
    return bytes(pkt)


def hand_difop_rs16(
    pitch: list[tuple[int, int, int]], rpm: int = 600, mode: int = 1, gps: int = 0x07
) -> bytes:
    pkt = bytearray(1248)
    pkt[0:8] = bytes([0xA5, 0xFF, 0x00, 0x5A, 0x11, 0x11, 0x55, 0x55])
    pkt[8:10] = rpm.to_bytes(2, "big")
    pkt[32:36] = bytes([0, 0, 0x8C, 0xA0])  # FOV 0 .. 360.00 deg
    pkt[300] = mode
    pkt[357] = gps
    for i, triple in enumerate(pitch):
        pkt[1165 + 3 * i : 1168 + 3 * i] = bytes(triple)
    return bytes(pkt)


def one_degree_table() -> list[tuple[int, int, int]]:
    # The manual's worked example: (0 * 256^2 + 39 * 256 + 16) * 0.0001 = 1 deg, for every channel.
    return [(0, 39, 16)] * 16


# --- DIFOP ----------------------------------------------------------------------------------------


def test_rs16_difop_manual_example() -> None:
    info = rs.decode_difop(hand_difop_rs16(one_degree_table()), rs.RS16)
    assert info.rpm == 600 and info.return_mode == rs.ReturnMode.STRONGEST and not info.dual
    # channels 0-7 look down: rs_driver forces their sign, the table holds magnitudes
    assert info.vertical_deg.tolist() == pytest.approx([-1.0] * 8 + [1.0] * 8, abs=1e-12)
    assert info.horizontal_deg.tolist() == [0.0] * 16
    assert info.clock_locked and (info.fov_start, info.fov_end) == (0, 36000)


def test_rs16_difop_keeps_the_tables_full_resolution() -> None:
    """Disagreement: rs_driver's RS16DifopPkt2Adapter casts the 0.0001 deg value to whole 0.01 deg
    (uint16(v * 0.01): 14.9883 -> 14.98); the older rs_driver and ros_rslidar keep it to 0.01 deg
    too. Kept here at the table's own 0.0001 deg: truncation moves a point at 10 m by up to 1.7 mm for
    nothing, and the emulator's rays use the same table."""
    value = round(14.9883 * 10000)  # 149883 = 0x02 0x49 0x7B
    table = [(0, 0, 0)] * 8 + [tuple(value.to_bytes(3, "big"))] + [(0, 39, 16)] * 7
    table[0] = (0, 39, 16)
    info = rs.decode_difop(hand_difop_rs16(table), rs.RS16)  # type: ignore[arg-type]
    assert info.vertical_deg[8] == pytest.approx(14.9883, abs=1e-9)


def test_rs32_difop_signed_tables() -> None:
    pkt = bytearray(hand_difop_rs16([], mode=0))
    pkt[468:471] = bytes([0x01, 0x28, 0x5D])  # sign 1: -(0x285D = 10333) * 0.001 = -10.333 deg
    pkt[471:474] = bytes([0x00, 0x01, 0x4D])  # +0.333
    pkt[564:567] = bytes([0x00, 0x1F, 0xFE])  # horizontal +8.190
    pkt[567:570] = bytes([0x01, 0x1F, 0xAE])  # -8.110
    info = rs.decode_difop(bytes(pkt), rs.RS32)
    assert info.vertical_deg[:3].tolist() == pytest.approx([-10.333, 0.333, 0.0])
    assert info.horizontal_deg[:3].tolist() == pytest.approx([8.19, -8.11, 0.0])
    assert info.dual


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"\x00" * 1248, "bad_id"),
        (hand_difop_rs16(one_degree_table())[:1000], "bad_length"),
        (hand_difop_rs16([(0xFF, 0xFF, 0xFF)] * 16), "no_angles"),  # an uncalibrated unit
        (hand_difop_rs16([(0x0F, 0x00, 0x00)] * 16), "bad_angles"),  # 98.3 deg
    ],
)
def test_difop_rejections(data: bytes, reason: str) -> None:
    with pytest.raises(rs.PacketError) as exc:
        rs.decode_difop(data, rs.RS16)
    assert exc.value.reason == reason


def test_gps_lock_needs_pps_and_gprmc() -> None:
    assert not rs.decode_difop(hand_difop_rs16(one_degree_table(), gps=0x01), rs.RS16).clock_locked
    assert rs.decode_difop(hand_difop_rs16(one_degree_table(), gps=0x03), rs.RS16).clock_locked


# --- MSOP -----------------------------------------------------------------------------------------


def test_ymd_time_is_utc() -> None:
    """Disagreement: rs_driver's parseTimeYMD converts with mktime, i.e. in the host's time zone; the
    unit's clock is set from GPRMC (UTC) or PTP (TAI/UTC), so the fields are read as UTC here."""
    packets = np.frombuffer(hand_msop([(0, {})]), rs.MSOP_DTYPE)
    (stamp_ns,) = rs.packet_times_ns(packets)
    assert stamp_ns == calendar.timegm((2026, 11, 26, 12, 34, 56)) * 10**9 + 789_123_000 == T0_NS


@pytest.mark.parametrize(
    "ymd", [bytes([26, 13, 1, 0, 0, 0, 0, 0, 0, 0]), bytes([26, 1, 1, 0, 0, 0, 0x03, 0xE8, 0, 0])]
)
def test_bad_packet_time_is_refused(ymd: bytes) -> None:
    with pytest.raises(rs.PacketError, match="bad_time"):
        rs.packet_times_ns(np.frombuffer(hand_msop([(0, {})], ymd), rs.MSOP_DTYPE))


def test_rs16_single_return_point_known_answer() -> None:
    """Block 0 at 1.00 deg, block 1 at 1.40 deg: channel 0 (laser 0, -1 deg) fires at the block's
    azimuth; channel 16 (laser 0 again, second firing 55.5 us later) at 1.00 + 0.40 * 55.5/111 = 1.20.
    200 units x 5 mm = 1.000 m."""
    pkt = hand_msop([(100, {0: (200, 80), 16: (400, 7)}), (140, {})])
    info = rs.decode_difop(hand_difop_rs16(one_degree_table()), rs.RS16)
    packets = np.frombuffer(pkt, rs.MSOP_DTYPE)
    pts = rs.decode_blocks(packets, np.ones((1, 12), bool), rs.RS16, info, np.zeros(1))
    assert len(pts) == 2
    v = math.radians(-1.0)
    rx = 0.03825
    for i, (d, az_deg) in enumerate([(1.0, 1.00), (2.0, 1.20)]):
        a = math.radians(az_deg)
        expected = (
            d * math.cos(v) * math.cos(a) + rx * math.cos(a),
            -d * math.cos(v) * math.sin(a) - rx * math.sin(a),
            d * math.sin(v),
        )
        assert pts.xyz_m[i].tolist() == pytest.approx(expected, abs=1e-6)
    assert pts.intensity.tolist() == [80, 7]
    assert pts.laser.tolist() == [0, 0]
    assert pts.time_offset_us.tolist() == pytest.approx([0.0, 55.5])


def test_rs32_horizontal_offset_and_channel_timing() -> None:
    """RS-LiDAR-32 channel 16 fires 1.44 us into a 55.52 us block: 20 units x 1.44/55.52 further; its
    horizontal offset is added for the direction, not for the lens-centre term."""
    difop = bytearray(hand_difop_rs16([], mode=1))
    for i in range(32):
        difop[468 + 3 * i : 471 + 3 * i] = bytes([0, 0, 0])  # all horizontal: 0 deg
        difop[564 + 3 * i : 567 + 3 * i] = bytes([0, 0, 0])
    difop[564 + 3 * 16 : 567 + 3 * 16] = bytes([0x01, 0x1C, 0x84])  # -7.300 deg
    info = rs.decode_difop(bytes(difop), rs.RS32)
    pkt = hand_msop([(0, {16: (1000, 1)}), (20, {})])
    pts = rs.decode_blocks(
        np.frombuffer(pkt, rs.MSOP_DTYPE), np.ones((1, 12), bool), rs.RS32, info, np.zeros(1)
    )
    a = math.radians(0.2 * 1.44 / 55.52)
    h = a + math.radians(-7.3)
    rx = 0.03997
    assert pts.xyz_m[0].tolist() == pytest.approx(
        [5.0 * math.cos(h) + rx * math.cos(a), -5.0 * math.sin(h) - rx * math.sin(a), 0.0], abs=1e-6
    )
    assert pts.time_offset_us.tolist() == pytest.approx([1.44])


def test_float32_geometry_within_a_tenth_of_a_millimetre_at_the_range_limit() -> None:
    """decode_blocks computes sines and cosines in float32: against the float64 formula at 229 m (the
    last whole metre of the range gate), every azimuth a packet can hold, the horizontal offset of
    every channel: within 0.1 mm."""
    difop = bytearray(hand_difop_rs16([], mode=1))
    for i in range(32):
        off = round(abs(8.19 - 0.53 * i) * 1000)  # offsets from +8.19 to -8.24 deg, both signs
        difop[468 + 3 * i : 471 + 3 * i] = bytes([0, 0, 0])
        difop[564 + 3 * i : 567 + 3 * i] = bytes([int(8.19 - 0.53 * i < 0), off >> 8, off & 0xFF])
    info = rs.decode_difop(bytes(difop), rs.RS32)
    rng = np.random.default_rng(3)
    azimuths = [*sorted(int(a) for a in rng.integers(0, 36000, 11)), 35999]
    pkt = hand_msop([(az, {c: (45800, 9) for c in range(32)}) for az in azimuths])  # 229.000 m
    pts = rs.decode_blocks(
        np.frombuffer(pkt, rs.MSOP_DTYPE), np.ones((1, 12), bool), rs.RS32, info, np.zeros(1)
    )
    assert len(pts) == 12 * 32
    worst = 0.0
    for k, (xyz, laser) in enumerate(zip(pts.xyz_m, pts.laser, strict=True)):
        block = k // 32
        step = (azimuths[block + 1] - azimuths[block]) % 36000 if block < 11 else 20
        step = 20 if step > rs.BLIND_ZONE_AZ_DIFF else step
        a = math.radians((azimuths[block] + step * rs.RS32.chan_fraction(False)[k % 32]) * 0.01)
        h = a + math.radians(float(info.horizontal_deg[laser]))
        expected = np.array(
            [229.0 * math.cos(h) + 0.03997 * math.cos(a), -229.0 * math.sin(h) - 0.03997 * math.sin(a)]
        )
        worst = max(worst, float(np.hypot(*(xyz[:2] - expected))))
    assert worst < 1e-4, worst


def test_blind_zone_step_uses_the_nominal_azimuth_step() -> None:
    """A jump over 1 deg between blocks is the blind zone of a reduced field of view: the channel
    azimuths of the block before it use the nominal step (40 units at 600 rpm for RS-LiDAR-16)."""
    info = rs.decode_difop(hand_difop_rs16(one_degree_table()), rs.RS16)
    pkt = hand_msop([(1000, {16: (200, 1)}), (9000, {})])
    pts = rs.decode_blocks(
        np.frombuffer(pkt, rs.MSOP_DTYPE), np.ones((1, 12), bool), rs.RS16, info, np.zeros(1)
    )
    az = math.degrees(math.atan2(-(pts.xyz_m[0, 1]), pts.xyz_m[0, 0]))
    assert az == pytest.approx(10.0 + 0.4 * 55.5 / 111, abs=1e-3)


def test_rs16_dual_return_layout() -> None:
    """Disagreement: a summary of the driver says dual-return blocks come in pairs with the same azimuth;
    for the RS-LiDAR-16 both rs_driver generations (Rs16DualReturnBlockIterator, and the older
    decoder's ECHO_DUAL branch) lay out one firing per block with channels 0-15 the first return and
    16-31 the second, blocks one firing (20 units at 600 rpm) apart. The pairs are the RS-LiDAR-32's
    layout (DualReturnBlockIterator). Followed here: the decoders agree, and the manual's block holds
    32 channels for 16 lasers."""
    info = rs.decode_difop(hand_difop_rs16(one_degree_table(), mode=0), rs.RS16)
    pkt = hand_msop([(0, {3: (200, 9), 19: (210, 5)}), (20, {})])
    pts = rs.decode_blocks(
        np.frombuffer(pkt, rs.MSOP_DTYPE), np.ones((1, 12), bool), rs.RS16, info, np.zeros(1)
    )
    assert pts.ret.tolist() == [0, 1] and pts.laser.tolist() == [3, 3]
    # both returns of one ray: same direction, ranges 1.00 and 1.05 m
    dir0 = pts.xyz_m[0] / np.linalg.norm(pts.xyz_m[0])
    dir1 = pts.xyz_m[1] / np.linalg.norm(pts.xyz_m[1])
    assert float(dir0 @ dir1) == pytest.approx(1.0, abs=1e-4)
    assert pts.time_offset_us.tolist() == pytest.approx([8.4, 8.4])


def test_range_gate_and_zero_distance() -> None:
    info = rs.decode_difop(hand_difop_rs16(one_degree_table()), rs.RS16)
    pkt = hand_msop([(0, {0: (0, 1), 1: (40, 1), 2: (79, 1), 3: (80, 1)}), (40, {})])
    pts = rs.decode_blocks(
        np.frombuffer(pkt, rs.MSOP_DTYPE), np.ones((1, 12), bool), rs.RS16, info, np.zeros(1)
    )
    assert pts.distance_m.tolist() == pytest.approx([0.4])  # 0.4 m is the device's minimum
    pts = rs.decode_blocks(
        np.frombuffer(pkt, rs.MSOP_DTYPE), np.ones((1, 12), bool), rs.RS16, info, np.zeros(1), min_range_m=0.1
    )
    assert pts.distance_m.tolist() == pytest.approx([0.2, 0.395, 0.4])


def test_temperature_encoding_matches_rs_driver_layout() -> None:
    # 40 deg C = 640 units: lsb 5 bits (0) << 3, then sign | 7 msb bits (640 >> 5 = 20)
    assert temperature_le(40.0) == bytes([0x00, 0x14])
    assert temperature_le(-1.0) == bytes([0x80, 0x80])


# --- frames -------------------------------------------------------------------------------------


def turn_packets(first_az: int, n_packets: int, step: int = 40) -> list[bytes]:
    out = []
    az = first_az
    for _ in range(n_packets):
        blocks = []
        for _ in range(12):
            blocks.append((az % 36000, {0: (200, 1)}))
            az += step
        out.append(hand_msop(blocks))
    return out


def test_no_frame_before_difop_then_frames() -> None:
    stream = rs.LidarStream(rs.RS16, rs.StampClock.RECEIVE)
    for i, p in enumerate(turn_packets(35000, 10)):
        assert stream.on_msop(p, i) == []
    assert stream.counters["rejected/msop/no_difop"] == 10
    assert stream.on_difop(hand_difop_rs16(one_degree_table()))
    frames = []
    # wraps at 36000 = packet 4, block 2 (34000 + 50 * 40), and again at packet 79, block 2
    for p in turn_packets(34000, 100):
        frames += stream.on_msop(p, 0)
    # the first 50 blocks (20 deg) are a revolution's tail, not a revolution: dropped, counted
    assert stream.counters["frames/partial"] == 1
    assert len(frames) == 1 and len(frames[0].points) == 900
    assert (frames[0].first_az, frames[0].last_az) == (0, 35960) and frames[0].packets == 76


def test_split_mid_packet_puts_each_block_in_its_frame() -> None:
    stream = rs.LidarStream(rs.RS16, rs.StampClock.RECEIVE)
    stream.on_difop(hand_difop_rs16(one_degree_table()))
    frames = []
    for p in turn_packets(0, 75) + turn_packets(0, 75) + turn_packets(0, 1):
        frames += stream.on_msop(p, 0)
    assert [len(f.points) for f in frames] == [900, 900]
    assert [f.covered_deg for f in frames] == [pytest.approx(359.6)] * 2


def test_receive_clock_stamp_is_receive_time_minus_packet_duration() -> None:
    stream = rs.LidarStream(rs.RS16, rs.StampClock.RECEIVE)
    stream.on_difop(hand_difop_rs16(one_degree_table()))
    frames = []
    for i, p in enumerate(turn_packets(0, 76)):
        frames += stream.on_msop(p, 1_000_000_000 + i * 1_333_333)
    # 12 blocks x 2 firings x 55.5 us (rs_driver getPacketDuration)
    assert frames[0].stamp_ns == 1_000_000_000 - 1_332_000
    assert frames[0].clock is rs.StampClock.RECEIVE


def test_device_clock_needs_lock() -> None:
    for gps, clock in [(0x07, rs.StampClock.DEVICE), (0x00, rs.StampClock.RECEIVE)]:
        stream = rs.LidarStream(rs.RS16, rs.StampClock.DEVICE)
        stream.on_difop(hand_difop_rs16(one_degree_table(), gps=gps))
        frames = [f for p in turn_packets(0, 76) for f in stream.on_msop(p, 5)]
        assert frames[0].clock is clock
        if clock is rs.StampClock.DEVICE:
            assert frames[0].stamp_ns == T0_NS
        else:
            assert stream.counters["frames/clock_unlocked"] == 1


def test_bad_packets_are_counted_not_raised() -> None:
    stream = rs.LidarStream(rs.RS16, rs.StampClock.DEVICE)
    stream.on_difop(hand_difop_rs16(one_degree_table()))
    good = turn_packets(0, 1)[0]
    assert stream.on_msop(good[:600], 0) == []
    assert stream.on_msop(b"\x01" * 1248, 0) == []
    assert stream.on_msop(hand_msop([(0, {})], bytes([26, 2, 30, 0, 0, 0, 0, 0, 0, 0])), 0) == []
    assert not stream.on_difop(b"junk")
    assert stream.counters == {
        "difop": 1,
        "rejected/msop/bad_length": 1,
        "rejected/msop/bad_id": 1,
        "rejected/msop/bad_time": 1,
        "rejected/difop/bad_length": 1,
    }


def test_a_frame_that_lost_packets_is_dropped() -> None:
    stream = rs.LidarStream(rs.RS16)
    stream.on_difop(hand_difop_rs16(one_degree_table()))
    turn = turn_packets(0, 75)
    frames = [f for p in turn[:40] + turn_packets(0, 76) for f in stream.on_msop(p, 0)]  # cut at 40 of 75
    assert stream.counters["frames/partial"] == 1
    assert len(frames) == 1 and frames[0].covered_deg == pytest.approx(359.6)


def test_expired_frame_is_counted() -> None:
    stream = rs.LidarStream(rs.RS16)
    stream.on_difop(hand_difop_rs16(one_degree_table()))
    for p in turn_packets(0, 20):
        stream.on_msop(p, 0)
    assert stream.open_packets == 20
    stream.expire()
    assert stream.counters["frames/expired"] == 1 and stream.open_packets == 0


# --- round trip -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("device", "samples"), [("rs16", 500), ("rs32", 250), ("rs16", 1800)])
@pytest.mark.parametrize("dual", [False, True])
def test_round_trip_within_the_device_resolution(device: str, samples: int, dual: bool) -> None:
    """Simulated returns -> emulated packets -> decoded points: every return comes back once per
    return mode, on its own ray, within half the 5 mm distance step (float32 aside)."""
    em = RobosenseEmulator(device, samples=samples, dual=dual)
    model = LidarModel(
        channels=em.model.lasers, horizontal_samples=samples, min_range_m=0.1, max_range_m=12.0, device=device
    )  # type: ignore[arg-type]
    origins, dirs, _ = ray_layout(model)
    rng = np.random.default_rng(7)
    ray = np.flatnonzero(rng.random(len(dirs)) < 0.5)
    laser, sample = ray // samples, ray % samples
    range_m = rng.uniform(0.15, 11.0, len(ray))
    intensity = rng.random(len(ray))
    stream = rs.LidarStream(em.model, rs.StampClock.DEVICE, min_range_m=0.1, max_range_m=12.0)
    assert stream.on_difop(em.difop_packet(T0_NS))
    packets = em.msop_packets(laser, sample, range_m, intensity, T0_NS)
    assert len(packets) == em.packets_per_turn
    frames = [
        f
        for p in packets + em.msop_packets([], [], [], [], T0_NS + em.period_ns)[:1]
        for f in stream.on_msop(p, 0)
    ]
    assert len(frames) == 1
    frame = frames[0]
    assert abs(frame.stamp_ns - T0_NS) < 1000  # the YMD time has whole microseconds
    keep = frame.points.ret == 0
    assert np.count_nonzero(keep) == len(ray) and np.count_nonzero(~keep) == (len(ray) if dual else 0)
    # each simulated return is the nearest decoded point of exactly one
    dist, nearest = cKDTree(frame.points.xyz_m[keep].astype(float)).query(
        origins[ray] + dirs[ray] * range_m[:, None]
    )
    assert len(np.unique(nearest)) == len(ray)
    assert float(np.max(dist)) <= rs.DISTANCE_RES_M / 2 + 1e-5
    assert np.allclose(np.sort(frame.points.intensity[keep]), np.sort(np.round(intensity * 255)))
