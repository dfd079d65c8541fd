"""Robosense RS-LiDAR-16 / RS-LiDAR-32 wire protocol: MSOP point packets and DIFOP device packets.

Both models send 1248-byte UDP packets, every multi-byte field big-endian (facts and sources in
`docs/references.md` "RS-LiDAR": RoboSense rs_driver's packed structs and the RS-LiDAR-16 manual):

- MSOP (port 6699): a 42-byte header (8-byte id, the lidar clock's time at offset 20 as year-2000,
  month, day, hour, minute, second, ms u16, us u16), 12 blocks of 100 bytes (flag `FF EE`, azimuth u16
  in 0.01 deg, 32 channels of {distance u16 in 5 mm, intensity u8}), a u32 index and a u16 tail.
- DIFOP (port 7788, about once a second): the motor speed (rpm, offset 8), the return mode (300),
  the clock's sync status (357, the diagnostics' gps_status byte) and the unit's calibrated channel
  angles: RS-LiDAR-16 16 x 3-byte vertical angles at 1165 in 0.0001 deg (channels 0-7 below the
  horizon, so negative), RS-LiDAR-32 32 x {sign u8, value u16} vertical at 468 and horizontal at 564
  in 0.001 deg.

Per channel (rs_driver's decoders; angles in 0.01 deg, clockwise seen from above):
  az_chan = block_az + block_az_diff * chan_fraction[chan]      (interpolated within the block)
  h       = az_chan + horizontal_offset[laser]
  x =  d cos(v) cos(h) + RX cos(az_chan),  y = -d cos(v) sin(h) - RX sin(az_chan),  z = d sin(v)
where block_az_diff is the next block's azimuth minus this one's (wrapped; over 1 deg it is the blind
zone of a reduced field of view and the nominal step is used; the last block also takes the nominal
step) and RX is the lens centre's distance from the spin axis. Resulting frame: +x forward, +y left,
+z up, metres: the project's lidar frame.

The RS-LiDAR-16 fires its 16 lasers twice per block (channels 0-15, then 16-31, 55.5 us apart); in
dual-return mode each block holds one firing with both returns (channels 0-15 the first, 16-31 the
second). The RS-LiDAR-32 fires all 32 lasers once per block; in dual-return mode blocks come in pairs
with the same azimuth (the first return, then the second).

Everything is decoded with numpy over all packets of a frame at once (structured dtypes, no per-point
Python). Where public decoders differ, the choice and the reason are written beside the code and
tested in tests/shared/devices/test_robosense.py.
"""

from __future__ import annotations

import calendar
import datetime
import enum
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from shared.timebase import NS_PER_S

MSOP_PORT = 6699
DIFOP_PORT = 7788
PACKET_BYTES = 1248
MSOP_ID = bytes.fromhex("55AA050A5AA550A0")
DIFOP_ID = bytes.fromhex("A5FF005A11115555")
BLOCK_FLAG = bytes.fromhex("FFEE")
BLOCKS_PER_PACKET = 12
CHANNELS_PER_BLOCK = 32
AZIMUTH_PER_TURN = 36000  # azimuth units (0.01 deg) in one revolution
BLIND_ZONE_AZ_DIFF = 100  # a block-to-block step over 1 deg is the blind zone, not the spin
DISTANCE_RES_M = 0.005
DEFAULT_RPM = 600  # rs_driver's fallback when DIFOP says 0

# MSOP: the header's fields at their offsets, then the blocks; big-endian throughout.
TIMESTAMP_OFFSET = 20
_CHANNEL = np.dtype([("distance", ">u2"), ("intensity", "u1")])
_BLOCK = np.dtype([("flag", ">u2"), ("azimuth", ">u2"), ("channels", _CHANNEL, (CHANNELS_PER_BLOCK,))])
MSOP_DTYPE = np.dtype(
    {
        "names": ["id", "year", "month", "day", "hour", "minute", "second", "ms", "us", "blocks", "tail"],
        "formats": ["V8", "u1", "u1", "u1", "u1", "u1", "u1", ">u2", ">u2", (_BLOCK, (12,)), ">u2"],
        "offsets": [0, 20, 21, 22, 23, 24, 25, 26, 28, 42, 1246],
        "itemsize": PACKET_BYTES,
    }
)
BLOCK_FLAG_VALUE = 0xFFEE
assert _BLOCK.itemsize == 100 and MSOP_DTYPE.itemsize == PACKET_BYTES
# What each packet is looked at for on arrival (the points are decoded a revolution at a time with
# MSOP_DTYPE): its time fields and its blocks' azimuths, read with struct (a numpy view per packet
# cost more than the rest of the packet's handling).
_MSOP_TIME = struct.Struct(">20x6BHH")  # year (since 2000), month, day, hour, minute, second, ms, us
_BLOCK_HEAD = "2xH96x"  # flag, azimuth, 32 channels
_MSOP_AZIMUTHS = struct.Struct(">42x" + _BLOCK_HEAD * (BLOCKS_PER_PACKET - 1) + "2xH")
assert [MSOP_DTYPE.fields[f][1] for f in ("year", "us", "blocks")] == [20, 28, 42]  # type: ignore[index]
assert _MSOP_AZIMUTHS.size == 42 + 11 * _BLOCK.itemsize + 4

# DIFOP field offsets (rs_driver RS16DifopPkt / RS32DifopPkt, packed).
DIFOP_RPM_OFFSET = 8
DIFOP_FOV_OFFSET = 32  # start, end: u16 each, 0.01 deg
DIFOP_RETURN_MODE_OFFSET = 300
DIFOP_TIMESTAMP_OFFSET = 303
DIFOP_GPS_STATUS_OFFSET = 357  # diagnostics (342) + 15
DIFOP_GPRMC_OFFSET = 382
DIFOP_GPRMC_BYTES = 86
RS16_PITCH_OFFSET = 1165  # 16 x 3 bytes, 0.0001 deg
RS32_VERTICAL_OFFSET = 468  # 32 x {sign, u16}, 0.001 deg
RS32_HORIZONTAL_OFFSET = 564

# gps_status bits. The RS-LiDAR-16 manual (appendix B.13) names PPS lock, GPRMC lock and UTC lock; the
# bit order below is the order the manual lists them in and has not been checked against a device.
GPS_PPS_LOCK = 0x01
GPS_GPRMC_LOCK = 0x02
GPS_UTC_LOCK = 0x04


class ReturnMode(enum.IntEnum):
    """DIFOP return_mode byte."""

    DUAL = 0
    STRONGEST = 1
    LAST = 2


@dataclass(frozen=True)
class RobosenseModel:
    """Constants of one lidar model (rs_driver's getConstParam / calcParam)."""

    name: str
    lasers: int
    block_duration_us: float  # one firing sequence of all lasers
    firing_us: tuple[float, ...]  # each of the 32 channels' firing time within its block
    lens_offset_m: float  # RX
    min_range_m: float
    max_range_m: float
    # The example unit's calibration (ros_rslidar angle.csv), used by the emulator and by tests; a real
    # unit's angles always come from its DIFOP.
    example_vertical_deg: tuple[float, ...]
    example_horizontal_deg: tuple[float, ...] = field(default=())

    @property
    def firings_per_block(self) -> int:
        """Single-return firing sequences in one block."""
        return CHANNELS_PER_BLOCK // self.lasers

    def laser_of(self) -> np.ndarray:
        """(32,) laser index of each channel of a block."""
        return np.arange(CHANNELS_PER_BLOCK) % self.lasers

    def chan_fraction(self, dual: bool) -> np.ndarray:
        """(32,) fraction of the block-to-block azimuth step at which each channel fired."""
        fire = np.asarray(self.firing_us)
        if self.lasers == 16 and dual:
            return fire[np.arange(32) % 16] / self.block_duration_us
        return fire / (self.block_duration_us * self.firings_per_block)

    def chan_time_us(self, dual: bool) -> np.ndarray:
        """(32,) each channel's firing time after its block's start, us."""
        fire = np.asarray(self.firing_us)
        return fire[np.arange(32) % 16] if (self.lasers == 16 and dual) else fire

    def block_time_us(self, dual: bool) -> np.ndarray:
        """(12,) each block's start after the packet's first block, us."""
        blocks = np.arange(BLOCKS_PER_PACKET)
        if self.lasers == 16:  # single: two firings a block; dual: one firing (two returns) a block
            return blocks * self.block_duration_us * (1 if dual else 2)
        return (blocks // 2 if dual else blocks) * self.block_duration_us

    def block_step_us(self, dual: bool) -> float:
        """Time between blocks that start new firings, us."""
        return self.block_duration_us * (self.firings_per_block if (self.lasers == 16 and not dual) else 1)

    def packet_duration_s(self, dual: bool) -> float:
        """Time one packet's firings span (rs_driver subtracts it from the receive time)."""
        firings = BLOCKS_PER_PACKET // 2 if (dual and self.lasers == 32) else BLOCKS_PER_PACKET
        return firings * self.block_step_us(dual) * 1e-6

    def nominal_az_step(self, rpm: int, dual: bool) -> int:
        """Nominal azimuth step between firing blocks at `rpm`, 0.01 deg (rs_driver's block_az_diff)."""
        rps = max(rpm, 1) // 60 or DEFAULT_RPM // 60  # rs_driver uses whole revolutions per second
        return round(AZIMUTH_PER_TURN * rps * self.block_step_us(dual) * 1e-6)


# fmt: off
RS16 = RobosenseModel(
    name="RS-LiDAR-16",
    lasers=16,
    block_duration_us=55.5,
    # two firings a block, 2.8 us between lasers, the second 55.5 us after the first (decoder_RS16.hpp)
    firing_us=tuple(round(2.8 * i + 55.5 * s, 2) for s in range(2) for i in range(16)),
    lens_offset_m=0.03825,
    min_range_m=0.4,
    max_range_m=230.0,
    example_vertical_deg=(
        -14.9782, -12.9810, -10.9650, -8.9840, -6.9635, -4.9966, -3.0143, -1.0211,
        14.9883, 13.0014, 10.9961, 9.0015, 6.9883, 4.9753, 3.0143, 0.9925,
    ),
    example_horizontal_deg=(0.0,) * 16,
)
RS32 = RobosenseModel(
    name="RS-LiDAR-32",
    lasers=32,
    block_duration_us=55.52,
    firing_us=(
        0.00, 2.88, 5.76, 8.64, 11.52, 14.40, 17.28, 20.16, 23.04, 25.92, 28.80, 31.68, 34.56, 37.44, 40.32,
        44.64, 1.44, 4.32, 7.20, 10.08, 12.96, 15.84, 18.72, 21.60, 24.48, 27.36, 30.24, 33.12, 36.00,
        38.88, 41.76, 46.08,
    ),
    lens_offset_m=0.03997,
    min_range_m=0.4,
    max_range_m=230.0,
    example_vertical_deg=(
        -10.333, 0.333, -6.477, 0.0, 2.315, -0.333, 3.28, -0.667, 4.649, 1.667, 6.982, 1.333, 10.35, 1.0,
        14.983, 0.667, -25.029, -2.333, -14.688, -2.667, -7.963, -3.0, -5.443, -3.333, -3.703, -0.946,
        -3.982, -1.351, -4.333, -1.667, -4.667, -1.964,
    ),
    example_horizontal_deg=(
        8.19, -8.11, 8.34, -2.97, 8.24, 2.25, -7.50, 7.77, 8.18, -8.15, -7.19, -2.93, 8.39, 2.24, -7.05, 7.70,
        -7.30, -7.92, -7.25, -2.89, -6.89, 2.46, -6.90, 7.74, -8.00, -8.12, -2.75, -2.98, 2.57, 2.39, 7.94,
        7.65,
    ),
)
# fmt: on
MODELS = {"rs16": RS16, "rs32": RS32}


@dataclass(frozen=True)
class DeviceInfo:
    """What one DIFOP packet says."""

    rpm: int
    return_mode: ReturnMode | int
    fov_start: int  # 0.01 deg
    fov_end: int
    gps_status: int
    vertical_deg: np.ndarray  # (lasers,) per laser
    horizontal_deg: np.ndarray  # (lasers,)
    time_ns: int | None  # the DIFOP's own YMD time (None if the fields are not a valid date)

    @property
    def dual(self) -> bool:
        return self.return_mode == ReturnMode.DUAL

    @property
    def fov_deg(self) -> float:
        """Horizontal field of view the unit reports (a full turn when start == end)."""
        span = (self.fov_end - self.fov_start) % AZIMUTH_PER_TURN
        return (span or AZIMUTH_PER_TURN) * 0.01

    @property
    def clock_locked(self) -> bool:
        """The lidar's clock follows GPS: PPS and GPRMC both locked."""
        need = GPS_PPS_LOCK | GPS_GPRMC_LOCK
        return self.gps_status & need == need


class PacketError(ValueError):
    """A packet that is not what it claims to be; `reason` is the counter's name."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def ymd_time_ns(
    year: int, month: int, day: int, hour: int, minute: int, second: int, ms: int, us: int
) -> int:
    """ns since the UNIX epoch of a Robosense YMD time (year since 2000), read as UTC.

    rs_driver's parseTimeYMD converts with mktime (the host's local time zone); the lidar's clock is
    set from GPRMC or PTP, which are UTC, so UTC is taken here (a host in UTC gets the same answer).
    Raises PacketError("bad_time") for fields that are no calendar time."""
    if ms > 999 or us > 999:
        raise PacketError("bad_time", f"ms {ms} us {us}")
    try:
        when = datetime.datetime(2000 + year, month, day, hour, minute, second, tzinfo=datetime.UTC)
    except ValueError as exc:  # no such day or time (leap seconds are not sent: GPS time has none)
        raise PacketError("bad_time", f"{year}-{month}-{day} {hour}:{minute}:{second}") from exc
    seconds = calendar.timegm(when.utctimetuple())
    return seconds * NS_PER_S + ms * 1_000_000 + us * 1_000


def _check_packet(data: bytes, ident: bytes) -> None:
    if len(data) != PACKET_BYTES:
        raise PacketError("bad_length", f"{len(data)} bytes")
    if data[:8] != ident:
        raise PacketError("bad_id", data[:8].hex())


def decode_difop(data: bytes, model: RobosenseModel) -> DeviceInfo:
    """Parse a DIFOP packet of `model`; PacketError for a wrong length or id, or angle fields that are
    unset (all 0x00 / 0xFF: a unit that was never calibrated) or out of range."""
    _check_packet(data, DIFOP_ID)
    raw = np.frombuffer(data, np.uint8)
    rpm = int.from_bytes(data[DIFOP_RPM_OFFSET : DIFOP_RPM_OFFSET + 2], "big")
    fov_start = int.from_bytes(data[DIFOP_FOV_OFFSET : DIFOP_FOV_OFFSET + 2], "big")
    fov_end = int.from_bytes(data[DIFOP_FOV_OFFSET + 2 : DIFOP_FOV_OFFSET + 4], "big")
    mode = data[DIFOP_RETURN_MODE_OFFSET]
    return_mode: ReturnMode | int = ReturnMode(mode) if mode in ReturnMode._value2member_map_ else mode
    if model.lasers == 16:
        cali = raw[RS16_PITCH_OFFSET : RS16_PITCH_OFFSET + 48].reshape(16, 3).astype(np.int64)
        if np.all((cali == 0x00) | (cali == 0xFF)):
            raise PacketError("no_angles", "pitch table unset")
        value = (cali[:, 0] << 16) | (cali[:, 1] << 8) | cali[:, 2]
        # Channels 0-7 point below the horizon: the table holds magnitudes (rs_driver forces the sign).
        sign = np.where(np.arange(16) < 8, -1.0, 1.0)
        vertical = sign * value * 1e-4
        horizontal = np.zeros(16)
    else:
        vertical = _signed_table(raw, RS32_VERTICAL_OFFSET, 32) * 1e-3
        horizontal = _signed_table(raw, RS32_HORIZONTAL_OFFSET, 32) * 1e-3
    # rs_driver's angleCheck: [-90, 180) deg.
    if np.any(vertical < -90) or np.any(vertical >= 90) or np.any(np.abs(horizontal) >= 180):
        raise PacketError("bad_angles", f"vertical {vertical.min():.2f}..{vertical.max():.2f} deg")
    t = raw[DIFOP_TIMESTAMP_OFFSET : DIFOP_TIMESTAMP_OFFSET + 10]
    try:
        y, mo, d, h, mi, sec = (int(v) for v in t[:6])
        time_ns: int | None = ymd_time_ns(y, mo, d, h, mi, sec, _u16(t, 6), _u16(t, 8))
    except PacketError:
        time_ns = None
    return DeviceInfo(
        rpm=rpm,
        return_mode=return_mode,
        fov_start=fov_start,
        fov_end=fov_end,
        gps_status=int(data[DIFOP_GPS_STATUS_OFFSET]),
        vertical_deg=vertical,
        horizontal_deg=horizontal,
        time_ns=time_ns,
    )


def _u16(raw: np.ndarray, offset: int) -> int:
    return (int(raw[offset]) << 8) | int(raw[offset + 1])


def _signed_table(raw: np.ndarray, offset: int, n: int) -> np.ndarray:
    """n x {sign u8 (non-zero = negative), value u16 BE} as signed values; 0xFF signs mean unset."""
    entries = raw[offset : offset + 3 * n].reshape(n, 3).astype(np.int64)
    if np.any(entries[:, 0] == 0xFF):
        raise PacketError("no_angles", "angle table unset")
    value = (entries[:, 1] << 8) | entries[:, 2]
    return np.where(entries[:, 0] != 0, -value, value).astype(float)


def check_msop(data: bytes) -> None:
    """PacketError unless `data` is an MSOP packet (length and id)."""
    _check_packet(data, MSOP_ID)


def packet_times_ns(packets: np.ndarray) -> np.ndarray:
    """(P,) the lidar clock's time of each MSOP packet (records of MSOP_DTYPE), ns since the UNIX epoch;
    PacketError("bad_time") if any is no calendar time. The date is converted once per distinct day,
    the time of day with numpy (a frame's 150 packets share their day)."""
    fields = [packets[name].astype(np.int64) for name in ("hour", "minute", "second", "ms", "us")]
    hour, minute, second, ms, us = fields
    if np.any((hour > 23) | (minute > 59) | (second > 60) | (ms > 999) | (us > 999)):
        raise PacketError("bad_time", "time of day out of range")
    days = np.stack([packets["year"], packets["month"], packets["day"]], axis=-1).astype(np.int64)
    unique, index = np.unique(days, axis=0, return_inverse=True)
    day_ns = np.array([ymd_time_ns(int(y), int(m), int(d), 0, 0, 0, 0, 0) for y, m, d in unique], np.int64)
    return (
        day_ns[index.reshape(-1)]
        + ((hour * 60 + minute) * 60 + second) * NS_PER_S
        + ms * 1_000_000
        + us * 1_000
    )


@dataclass(frozen=True)
class Points:
    """Decoded returns of some packets, in the lidar frame (see the module docstring)."""

    xyz_m: np.ndarray  # (N, 3) float32
    intensity: np.ndarray  # (N,) uint8 raw reflectivity
    laser: np.ndarray  # (N,) int16
    ret: np.ndarray  # (N,) uint8: 0 first / only return, 1 second return (dual mode)
    time_offset_us: np.ndarray  # (N,) float64 after the first packet's time
    distance_m: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return len(self.distance_m)


def decode_blocks(
    packets: np.ndarray,
    block_mask: np.ndarray,
    model: RobosenseModel,
    info: DeviceInfo,
    packet_offset_us: np.ndarray,
    min_range_m: float | None = None,
    max_range_m: float | None = None,
) -> Points:
    """Decode the blocks `block_mask` (P, 12) selects of `packets` (P records of MSOP_DTYPE).

    `packet_offset_us` (P,) is each packet's start after the first one's; the angle tables and return
    mode come from `info` (a DIFOP of this unit). Returns outside [min_range_m, max_range_m] (the
    model's range by default) and zero distances are dropped. Blocks whose flag is not FF EE are
    skipped (the caller counts them)."""
    dual = info.dual
    blocks = packets["blocks"]  # (P, 12)
    az = blocks["azimuth"].astype(np.int64)  # (P, 12)
    flags_ok = blocks["flag"] == BLOCK_FLAG_VALUE
    step = model.nominal_az_step(info.rpm, dual)
    # Step to the next firing block within the packet (dual RS32: the next pair).
    stride = 2 if (dual and model.lasers == 32) else 1
    diff = np.full(az.shape, step, np.int64)
    nxt = (az[:, stride:] - az[:, :-stride]) % AZIMUTH_PER_TURN
    diff[:, :-stride] = np.where(nxt > BLIND_ZONE_AZ_DIFF, step, nxt)
    if stride == 2:  # both blocks of a pair take the pair's step; the last pair the nominal one
        diff[:, 1::2] = diff[:, 0::2]
    keep_block = block_mask & flags_ok & (az < AZIMUTH_PER_TURN)
    chans = blocks["channels"]  # (P, 12, 32)
    laser = model.laser_of()
    vert = np.deg2rad(info.vertical_deg[laser])  # (32,)
    horiz_off = np.deg2rad(info.horizontal_deg[laser])  # (32,)
    distance = chans["distance"] * DISTANCE_RES_M  # float64: 80 units is 0.4 m exactly
    lo = model.min_range_m if min_range_m is None else min_range_m
    hi = model.max_range_m if max_range_m is None else max_range_m
    valid = (distance >= lo) & (distance <= hi) & (distance > 0)
    valid &= keep_block[:, :, None]
    # Each per-point array is made dense over (P, 12, 32) and masked once (boolean masks cost less than
    # gathers by index); per-channel constants are looked up by the points' channels.
    c = np.broadcast_to(np.arange(CHANNELS_PER_BLOCK, dtype=np.intp), valid.shape)[valid]
    d = distance[valid].astype(np.float32)
    a = (az[:, :, None] + diff[:, :, None] * model.chan_fraction(dual))[valid]  # channel azimuth, 0.01 deg
    # Sines and cosines in float32 (numpy's are vectorised for float32 only here: ten times faster),
    # of the azimuth alone; the channel's horizontal offset is added by the angle-sum identities.
    # Within 0.01 mm of float64 at 30 m, 0.1 mm at the 230 m range limit (the cloud is float32).
    a_rad = np.deg2rad(a * 0.01).astype(np.float32)
    cos_a, sin_a = np.cos(a_rad), np.sin(a_rad)
    cos_o, sin_o = np.cos(horiz_off).astype(np.float32)[c], np.sin(horiz_off).astype(np.float32)[c]
    cos_h = cos_a * cos_o - sin_a * sin_o  # h = a + horizontal offset
    sin_h = sin_a * cos_o + cos_a * sin_o
    d_cos_v = d * np.cos(vert).astype(np.float32)[c]
    rx = np.float32(model.lens_offset_m)
    xyz = np.empty((len(d), 3), np.float32)
    xyz[:, 0] = d_cos_v * cos_h + rx * cos_a
    xyz[:, 1] = -d_cos_v * sin_h - rx * sin_a
    xyz[:, 2] = d * np.sin(vert).astype(np.float32)[c]
    if not dual:
        ret = np.zeros(len(c), np.uint8)
    elif model.lasers == 16:
        ret = (c >= 16).astype(np.uint8)
    else:
        block_ret = (np.arange(BLOCKS_PER_PACKET) % 2).astype(np.uint8)[None, :, None]
        ret = np.broadcast_to(block_ret, valid.shape)[valid]
    time_us = (
        packet_offset_us[:, None, None] + model.block_time_us(dual)[None, :, None] + model.chan_time_us(dual)
    )[valid]
    return Points(
        xyz_m=xyz,
        intensity=chans["intensity"][valid],
        laser=laser[c].astype(np.int16),
        ret=ret,
        time_offset_us=time_us,
        distance_m=d,
    )


class FrameSplitter:
    """Where a new revolution starts: the first block whose azimuth reaches `split_az` (0.01 deg)
    coming from below it, with the azimuth unwrapped across 360 deg (rs_driver's split by angle)."""

    def __init__(self, split_az: int = 0) -> None:
        self.split_az = split_az
        self._prev = split_az

    def first_new_block(self, azimuths: Sequence[int]) -> int | None:
        """Index of the block in one packet's 12 azimuths that starts a new frame, or None."""
        found: int | None = None
        prev = self._prev
        for i, angle in enumerate(azimuths):
            if angle >= AZIMUTH_PER_TURN:
                continue  # not an azimuth: the block is skipped by the decoder too
            if angle < prev:
                prev -= AZIMUTH_PER_TURN
            if found is None and prev < self.split_az <= angle:
                found = i
            prev = angle
        self._prev = prev
        return found


class StampClock(enum.StrEnum):
    """Which clock stamps a frame: the lidar's own (the MSOP header time; meaningful when DIFOP says
    it is locked to GPS / PTP) or the host's receive time less one packet's duration (rs_driver's
    `use_lidar_clock: false`)."""

    DEVICE = "device"
    RECEIVE = "receive"


@dataclass(frozen=True)
class Frame:
    """One revolution: its points and where its stamp came from."""

    stamp_ns: int  # time of the frame's first firing, on `clock`
    clock: StampClock
    points: Points
    packets: int
    first_az: int  # 0.01 deg
    last_az: int

    @property
    def covered_deg(self) -> float:
        """Azimuth swept from the first to the last block (a frame cut short covers less)."""
        return ((self.last_az - self.first_az) % AZIMUTH_PER_TURN) * 0.01


@dataclass
class _Partial:
    packets: list[bytes] = field(default_factory=list)
    first_block: list[int] = field(default_factory=list)  # the frame's blocks of each packet: from ...
    end_block: list[int] = field(default_factory=list)  # ... up to this one (exclusive)
    recv_ns: list[int] = field(default_factory=list)

    def masks(self) -> np.ndarray:
        """(P, 12) bool: which blocks of each packet belong to the frame."""
        block = np.arange(BLOCKS_PER_PACKET)
        first = np.asarray(self.first_block)[:, None]
        return (block >= first) & (block < np.asarray(self.end_block)[:, None])


class LidarStream:
    """MSOP + DIFOP of one lidar in, whole frames out.

    No frame is made before a DIFOP has given this unit's angle tables (rs_driver's wait_for_difop):
    MSOP packets that come first are counted (`no_difop`) and dropped. A frame ends where the next
    one begins (FrameSplitter); a frame still open when its packets stop is dropped by `expire` and
    counted (`frames/expired`). Every rejected packet is counted in `counters` by reason.

    Parameters
    ----------
    model : RobosenseModel
    clock : StampClock
        DEVICE needs a DIFOP that says the clock is locked; until then frames are stamped with the
        receive time and counted (`frames/clock_unlocked`), never dropped.
    min_range_m, max_range_m : float | None
        Range gate (the model's by default).
    max_packets : int
        A frame with more packets than this (a split never seen) is cut and emitted.
    min_coverage : float
        A frame whose blocks sweep less than this fraction of the unit's field of view (DIFOP) lost
        packets: it is dropped and counted (`frames/partial`), not passed on as a whole revolution.
    """

    def __init__(
        self,
        model: RobosenseModel,
        clock: StampClock = StampClock.RECEIVE,
        min_range_m: float | None = None,
        max_range_m: float | None = None,
        split_az: int = 0,
        max_packets: int = 4000,
        min_coverage: float = 0.9,
    ) -> None:
        self.model = model
        self.min_coverage = min_coverage
        self.clock = clock
        self.min_range_m, self.max_range_m = min_range_m, max_range_m
        self.max_packets = max_packets
        self.info: DeviceInfo | None = None
        self.counters: dict[str, int] = {}
        self._splitter = FrameSplitter(split_az)
        self._frame = _Partial()
        self._last_day: tuple[int, int, int] | None = None  # date of the last packet whose time was good
        self._az_step = 0  # the nominal azimuth step between firing blocks (DIFOP's rpm and mode)

    def _count(self, reason: str, n: int = 1) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + n

    def on_difop(self, data: bytes) -> bool:
        """A DIFOP packet; False (counted) if it was rejected."""
        try:
            info = decode_difop(data, self.model)
        except PacketError as exc:
            self._count(f"rejected/difop/{exc.reason}")
            return False
        if self.info is not None and (
            info.dual != self.info.dual
            or info.rpm != self.info.rpm
            or not np.array_equal(info.vertical_deg, self.info.vertical_deg)
        ):
            self._count("difop/changed")
            self._frame = _Partial()  # its blocks were laid out under the old settings
        self.info = info
        self._az_step = self.model.nominal_az_step(info.rpm, info.dual)
        self._count("difop")
        return True

    def on_msop(self, data: bytes, recv_ns: int) -> list[Frame]:
        """An MSOP packet received at `recv_ns` (host clock); the frames it completed (0 or 1)."""
        try:
            check_msop(data)
        except PacketError as exc:
            self._count(f"rejected/msop/{exc.reason}")
            return []
        if self.info is None:
            self._count("rejected/msop/no_difop")
            return []
        if self.clock is StampClock.DEVICE and not self._time_plausible(_MSOP_TIME.unpack_from(data)):
            self._count("rejected/msop/bad_time")
            return []
        self._count("msop")
        azimuths = _MSOP_AZIMUTHS.unpack_from(data)
        out: list[Frame] = []
        split = self._splitter.first_new_block(azimuths)
        first = 0
        if split is not None:
            if split > 0:
                self._append(data, 0, split, recv_ns)
            frame = self._finish()
            if frame is not None:
                out.append(frame)
            first = split
        self._append(data, first, BLOCKS_PER_PACKET, recv_ns)
        if self._ends_turn(azimuths):
            # The packet's last block is the revolution's last: the frame is whole now, not one packet
            # later when the next turn's first block crosses the split (the next turn may be late).
            frame = self._finish()
            if frame is not None:
                out.append(frame)
            return out
        if len(self._frame.packets) >= self.max_packets:
            self._count("frames/cut_long")
            frame = self._finish()
            if frame is not None:
                out.append(frame)
        return out

    def _time_plausible(self, fields: tuple[int, ...]) -> bool:
        """Is the packet's time (its `_MSOP_TIME` fields) a calendar time? Quick for the same date as
        the last good packet's and a valid time of day (the usual case); a new date, or a bad field,
        takes the exact check."""
        year, month, mday, hour, minute, second, ms, us = fields
        day = (year, month, mday)
        if day == self._last_day and hour < 24 and minute < 60 and second < 61 and ms < 1000 and us < 1000:
            return True
        try:
            ymd_time_ns(*fields)
        except PacketError:
            return False
        self._last_day = day
        return True

    def _ends_turn(self, azimuths: Sequence[int]) -> bool:
        """Does the next firing after this packet's last block cross the split azimuth?"""
        last = next((a for a in reversed(azimuths) if a < AZIMUTH_PER_TURN), None)
        if last is None or self.info is None:
            return False
        return (self._splitter.split_az - last - 1) % AZIMUTH_PER_TURN < self._az_step

    def flush(self) -> Frame | None:
        """The open frame as it stands (the caller knows its revolution ended: a recording's last
        one, an in-process round trip); None if nothing is open or it is partial (counted)."""
        return self._finish()

    def expire(self) -> None:
        """Drop the open frame (its packets stopped); counted if it held any."""
        if self._frame.packets:
            self._count("frames/expired")
        self._frame = _Partial()

    @property
    def open_packets(self) -> int:
        return len(self._frame.packets)

    def _append(self, data: bytes, first_block: int, end_block: int, recv_ns: int) -> None:
        self._frame.packets.append(data)
        self._frame.first_block.append(first_block)
        self._frame.end_block.append(end_block)
        self._frame.recv_ns.append(recv_ns)

    def _finish(self) -> Frame | None:
        partial, self._frame = self._frame, _Partial()
        info = self.info
        if not partial.packets or info is None:
            return None
        packets = np.frombuffer(b"".join(partial.packets), MSOP_DTYPE)
        masks = partial.masks()
        use_device = self.clock is StampClock.DEVICE and info.clock_locked
        if self.clock is StampClock.DEVICE and not info.clock_locked:
            self._count("frames/clock_unlocked")
        if use_device:
            times = packet_times_ns(packets)  # each packet's was checked on arrival
        else:
            duration_ns = round(self.model.packet_duration_s(info.dual) * NS_PER_S)
            times = np.asarray(partial.recv_ns, np.int64) - duration_ns
        first_block = int(np.argmax(masks[0]))
        start_ns = int(times[0]) + round(self.model.block_time_us(info.dual)[first_block] * 1e3)
        offset_us = (times - start_ns) / 1e3  # point times after the frame's stamp
        points = decode_blocks(
            packets, masks, self.model, info, offset_us, self.min_range_m, self.max_range_m
        )
        bad_flags = int(np.count_nonzero(masks & (packets["blocks"]["flag"] != BLOCK_FLAG_VALUE)))
        if bad_flags:
            self._count("rejected/block/bad_flag", bad_flags)
        az = packets["blocks"]["azimuth"][masks]
        az = az[az < AZIMUTH_PER_TURN]
        frame = Frame(
            stamp_ns=start_ns,
            clock=StampClock.DEVICE if use_device else StampClock.RECEIVE,
            points=points,
            packets=len(packets),
            first_az=int(az[0]) if len(az) else 0,
            last_az=int(az[-1]) if len(az) else 0,
        )
        if frame.covered_deg < self.min_coverage * info.fov_deg:
            self._count("frames/partial")
            return None
        self._count("frames")
        return frame


def firings_per_turn(model: RobosenseModel, rpm: int) -> int:
    """Firing sequences in one revolution at `rpm`: 360 deg over the azimuth the spin covers in one
    firing (0.2 deg for both models at 600 rpm)."""
    step = round(AZIMUTH_PER_TURN * (rpm // 60) * model.block_duration_us * 1e-6)
    return AZIMUTH_PER_TURN // step


@dataclass(frozen=True)
class FiringGeometry:
    """Where each laser of each firing of one revolution points, in the lidar frame (+x forward,
    +y left, +z up): rays (firing, laser) from the lens centre `origin_m` along `direction`."""

    firing_az: np.ndarray  # (F,) int: azimuth of each firing's first laser, 0.01 deg clockwise
    origin_m: np.ndarray  # (F, L, 3) lens centre at the moment each laser fires
    direction: np.ndarray  # (F, L, 3) unit vectors


def firing_geometry(
    model: RobosenseModel, rpm: int, vertical_deg: np.ndarray, horizontal_deg: np.ndarray
) -> FiringGeometry:
    """The rays of one revolution starting at azimuth 0, as the device fires them: firing f starts at
    f x (360 deg / firings_per_turn); laser l fires `firing_us[l]` into its firing sequence, when the
    head has turned that fraction of one firing's azimuth further; it points `horizontal_deg[l]` off
    that azimuth at elevation `vertical_deg[l]`; the lens centre sits `lens_offset_m` out from the
    spin axis at the head's azimuth (RS-LiDAR-16/32 manuals; rs_driver's decoders). Written from the
    protocol facts apart from `decode_blocks`, which recovers the same rays from packet azimuths."""
    n = firings_per_turn(model, rpm)
    step = AZIMUTH_PER_TURN // n
    lasers = np.arange(model.lasers)
    fire_us = np.asarray(model.firing_us[: model.lasers])
    # RS-LiDAR-16: the second firing of a block repeats the first one's timing 55.5 us later.
    within = (fire_us - fire_us.min()) / model.block_duration_us
    firing_az = np.arange(n) * step
    az = firing_az[:, None] + step * within[None, :]  # (F, L) head azimuth, 0.01 deg
    h = np.deg2rad((az + np.asarray(horizontal_deg)[lasers] * 100.0) * 0.01)
    a = np.deg2rad(az * 0.01)
    v = np.deg2rad(np.asarray(vertical_deg))[lasers][None, :]
    direction = np.stack([np.cos(v) * np.cos(h), -np.cos(v) * np.sin(h), np.sin(v) * np.ones_like(h)], -1)
    origin = model.lens_offset_m * np.stack([np.cos(a), -np.sin(a), np.zeros_like(a)], -1)
    return FiringGeometry(firing_az=firing_az, origin_m=origin, direction=direction)


def firing_of_sample(samples: int, firings: int) -> np.ndarray:
    """(samples,) the firing each of a revolution's `samples` evenly spaced rays is taken from (a
    simulated lidar may sample fewer azimuths than the device fires: the rest report no return)."""
    return np.round(np.arange(samples) * (firings / samples)).astype(np.int64) % firings
