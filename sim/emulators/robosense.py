"""Emulated Robosense RS-LiDAR-16 / RS-LiDAR-32: a simulated scan as the unit's MSOP and DIFOP packets.

Written from the protocol facts (`docs/references.md` "RS-LiDAR"), byte by byte, apart from the
decoder in shared/devices/robosense.py (which reads packets through numpy structured dtypes): a round
trip through both is a check of each against the other, and the known-answer tests check both against
hand-made packets.

A revolution is every firing of the device at its motor speed (1800 at 600 rpm for both models); the
simulated lidar samples some of them (`firing_of_sample`): the others carry zero distances, which the
device also sends for a ray with no return. So the packets and their rate are the device's (RS-LiDAR-16
at 600 rpm: 75 packets a turn, 750 a second; RS-LiDAR-32: 150 and 1500) whatever the simulated
resolution. Packet k of a revolution that starts at `start_ns` is stamped start + its first firing's
share of the revolution period, as the unit's clock (locked to GPS: DIFOP says so) would stamp it.
"""

from __future__ import annotations

import calendar
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from shared.devices.robosense import MODELS, RobosenseModel, firing_of_sample, firings_per_turn
from shared.timebase import NS_PER_S

PACKET_LEN = 1248
MSOP_MAGIC = b"\x55\xaa\x05\x0a\x5a\xa5\x50\xa0"
DIFOP_MAGIC = b"\xa5\xff\x00\x5a\x11\x11\x55\x55"
MSOP_TAIL = b"\x00\xff"  # RS-LiDAR-16 manual p.19: 4 reserved bytes, then 00 FF
DIFOP_TAIL = b"\x0f\xf0"  # [unverified]: no decoder reads it
BLOCK_START = 42
BLOCK_LEN = 100
BLOCKS = 12
MM_PER_UNIT = 5.0  # distance unit, mm
TEMPERATURE_C = 40.0
SEND_GRANULARITY_S = 0.01  # LidarSender wakes at most this often


def ymd_fields(t_ns: int) -> bytes:
    """10 bytes: year-2000, month, day, hour, minute, second, ms (u16 BE), us (u16 BE), UTC."""
    seconds, rest_ns = divmod(t_ns, NS_PER_S)
    tm = time.gmtime(seconds)
    ms, us = divmod(rest_ns // 1000, 1000)
    return struct.pack(
        ">6BHH", tm.tm_year - 2000, tm.tm_mon, tm.tm_mday, tm.tm_hour, tm.tm_min, tm.tm_sec, ms, us
    )


def utc_ns(year: int, month: int, day: int, hour: int, minute: int, second: int) -> int:
    """ns since the UNIX epoch of a UTC calendar time (tests build known answers with it)."""
    return calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0)) * NS_PER_S


@dataclass
class RobosenseEmulator:
    """One emulated unit.

    Parameters
    ----------
    device : "rs16" | "rs32"
    samples : int
        Azimuth samples per revolution of the simulated lidar feeding it.
    rpm : int
    dual : bool
        Dual-return mode: both returns of every ray are the simulated one (one surface).
    gps_locked : bool
        DIFOP reports PPS and GPRMC lock (the adapter trusts the unit's clock only then).
    vertical_deg, horizontal_deg : channel angles the DIFOP carries (the example unit's by default).
    """

    device: str
    samples: int
    rpm: int = 600
    dual: bool = False
    gps_locked: bool = True
    vertical_deg: tuple[float, ...] | None = None
    horizontal_deg: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        self.model: RobosenseModel = MODELS[self.device]
        self.firings = firings_per_turn(self.model, self.rpm)
        self.firing_of = firing_of_sample(self.samples, self.firings)
        self.vertical = self.vertical_deg or self.model.example_vertical_deg
        self.horizontal = self.horizontal_deg or self.model.example_horizontal_deg
        self.az_step = 36000 // self.firings  # 0.01 deg per firing
        self.packet_index = 0

    # --- layout ------------------------------------------------------------------------------------

    @property
    def blocks_per_turn(self) -> int:
        if self.model.lasers == 16:
            return self.firings if self.dual else self.firings // 2
        return self.firings * (2 if self.dual else 1)

    @property
    def packets_per_turn(self) -> int:
        return -(-self.blocks_per_turn // BLOCKS)

    @property
    def period_ns(self) -> int:
        return round(60e9 / self.rpm)

    def _slots(self, firing: np.ndarray, laser: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For each return: (block of the turn, channel in the block) of the first return and the
        block / channel of the second (dual mode; -1 otherwise)."""
        if self.model.lasers == 16:
            if self.dual:  # one firing a block: channels 0-15 the first return, 16-31 the second
                return firing, laser, laser + 16
            return firing // 2, (firing % 2) * 16 + laser, np.full_like(laser, -1)
        if self.dual:  # a pair of blocks per firing, same azimuth
            return firing * 2, laser, laser
        return firing, laser, np.full_like(laser, -1)

    # --- packets -----------------------------------------------------------------------------------

    def msop_packets(
        self,
        laser: np.ndarray,
        sample: np.ndarray,
        range_m: np.ndarray,
        intensity: np.ndarray,
        start_ns: int,
    ) -> list[bytes]:
        """One revolution's MSOP packets. Each return: its channel `laser`, the simulated azimuth
        `sample` it was taken on, its `range_m` from the lens and `intensity` in [0, 1]."""
        n_blocks = self.packets_per_turn * BLOCKS
        dist = np.zeros((n_blocks, 32), np.int64)
        refl = np.zeros((n_blocks, 32), np.int64)
        firing = self.firing_of[np.asarray(sample, np.int64)]
        laser = np.asarray(laser, np.int64)
        units = np.clip(np.round(np.asarray(range_m, float) * 1000.0 / MM_PER_UNIT), 0, 0xFFFF).astype(
            np.int64
        )
        value = np.clip(np.round(np.asarray(intensity, float) * 255.0), 0, 255).astype(np.int64)
        block, chan, chan2 = self._slots(firing, laser)
        dist[block, chan] = units
        refl[block, chan] = value
        if self.dual:
            second_block = block if self.model.lasers == 16 else block + 1
            dist[second_block, chan2] = units
            refl[second_block, chan2] = value
        # Block azimuths: the azimuth of the block's first firing.
        blocks = np.arange(n_blocks)
        if self.model.lasers == 16:
            first_firing = blocks if self.dual else blocks * 2
        else:
            first_firing = blocks // 2 if self.dual else blocks
        block_az = (first_firing * self.az_step) % 36000
        body = np.zeros((n_blocks, BLOCK_LEN), np.uint8)
        body[:, 0], body[:, 1] = 0xFF, 0xEE
        body[:, 2], body[:, 3] = block_az >> 8, block_az & 0xFF
        body[:, 4::3] = dist >> 8
        body[:, 5::3] = dist & 0xFF
        body[:, 6::3] = refl
        packets = []
        for p in range(self.packets_per_turn):
            first = first_firing[p * BLOCKS]
            stamp = start_ns + (int(first) * self.period_ns) // self.firings
            buf = bytearray(PACKET_LEN)
            buf[0:8] = MSOP_MAGIC
            buf[20:30] = ymd_fields(stamp)
            buf[38:40] = temperature_le(TEMPERATURE_C)
            buf[BLOCK_START : BLOCK_START + BLOCKS * BLOCK_LEN] = body[
                p * BLOCKS : (p + 1) * BLOCKS
            ].tobytes()
            struct.pack_into(">I", buf, 1242, self.packet_index & 0xFFFFFFFF)
            buf[1246:1248] = MSOP_TAIL
            self.packet_index += 1
            packets.append(bytes(buf))
        return packets

    def difop_packet(self, t_ns: int) -> bytes:
        """The unit's DIFOP at `t_ns`: motor speed, full field of view, return mode, clock status,
        channel angles."""
        buf = bytearray(PACKET_LEN)
        buf[0:8] = DIFOP_MAGIC
        struct.pack_into(">H", buf, 8, self.rpm)
        struct.pack_into(">HH", buf, 32, 0, 36000)
        buf[300] = 0 if self.dual else 1  # 0 dual, 1 strongest
        buf[303:313] = ymd_fields(t_ns)
        buf[357] = 0x07 if self.gps_locked else 0x00  # PPS, GPRMC, UTC lock
        if self.model.lasers == 16:
            for i, angle in enumerate(self.vertical):
                # magnitudes in 0.0001 deg: channels 0-7 are below the horizon by the table's layout
                if (angle < 0) != (i < 8) and angle != 0:
                    raise ValueError(f"RS-LiDAR-16 channel {i} cannot point at {angle} deg")
                buf[1165 + 3 * i : 1168 + 3 * i] = round(abs(angle) * 10000).to_bytes(3, "big")
        else:
            for i, (v, h) in enumerate(zip(self.vertical, self.horizontal, strict=True)):
                struct.pack_into(">BH", buf, 468 + 3 * i, 1 if v < 0 else 0, round(abs(v) * 1000))
                struct.pack_into(">BH", buf, 564 + 3 * i, 1 if h < 0 else 0, round(abs(h) * 1000))
        buf[1246:1248] = DIFOP_TAIL
        return bytes(buf)


def temperature_le(celsius: float) -> bytes:
    """MSOP temperature: units of 0.0625 deg C, | 5 lsb bits, 3 padding | sign, 7 msb bits | (rs_driver
    parseTempInLe)."""
    units = round(abs(celsius) / 0.0625)
    return bytes([(units & 0x1F) << 3, (0x80 if celsius < 0 else 0) | ((units >> 5) & 0x7F)])


@dataclass
class _Turn:
    packets: list[bytes]
    first_ns: int  # wall time the first packet is due
    next: int = 0


class LidarSender:
    """Sends an emulated unit's packets over UDP as the unit does: a revolution's MSOP packets spread
    over the revolution (packet k at start + k x period / packets: the last one leaves as the turn
    ends, so a frame is complete one period after its first firing, as with the device) and a DIFOP
    once a second. A revolution handed in while the previous one is still going out has that one's
    remaining packets sent at once first (counted in `hurried`): the emulated unit's turns follow the
    sim's ticks, which jitter, and no return is lost to it."""

    def __init__(
        self, emulator: RobosenseEmulator, host: str, msop_port: int, difop_port: int, paced: bool = True
    ) -> None:
        self.emulator = emulator
        self.msop_addr = (host, msop_port)
        self.difop_addr = (host, difop_port)
        self.paced = paced
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sent = 0
        self.hurried = 0  # turns whose tail was sent at once because the next one was due
        self.withheld_difop = False  # fault injection: stop sending DIFOP
        self.cut_after: int | None = None  # fault injection: send only the first n packets of each turn
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._turns: deque[_Turn] = deque()
        self._thread = threading.Thread(target=self._run, name="lidar-sender", daemon=True)
        self._thread.start()

    def send_turn(self, packets: list[bytes]) -> None:
        with self._lock:
            if self._turns and self._turns[-1].next < len(self._turns[-1].packets):
                self.hurried += 1  # the previous turn's remaining packets go out at once
            self._turns.append(_Turn(list(packets), time.time_ns()))
        self._wake.set()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        self.sock.close()

    def _run(self) -> None:
        interval_ns = self.emulator.period_ns // max(self.emulator.packets_per_turn, 1)
        next_difop = time.monotonic()
        while not self._stop.is_set():
            if time.monotonic() >= next_difop:
                if not self.withheld_difop:
                    self._send(self.emulator.difop_packet(time.time_ns()), self.difop_addr)
                next_difop = time.monotonic() + 1.0
            due: list[bytes] | None = None  # packets taken off the turn now (None: none was due)
            wait_s = 0.05
            with self._lock:
                while self._turns and self._turns[0].next >= len(self._turns[0].packets):
                    self._turns.popleft()
                if self._turns:
                    turn = self._turns[0]
                    # A turn with another queued behind it is late: the rest of it goes out now.
                    end = len(turn.packets)
                    if self.paced and len(self._turns) == 1:
                        end = min(end, (time.time_ns() - turn.first_ns) // interval_ns + 1)
                    if end > turn.next:
                        # Every packet due by now, sent in one go (the lock is not taken per packet).
                        cut = end if self.cut_after is None else min(end, self.cut_after)
                        due = turn.packets[turn.next : max(cut, turn.next)]
                        turn.next = end
                    else:
                        # Sleep at least SEND_GRANULARITY_S: the packets due meanwhile then go out
                        # together (the device's rate on average; a wake-up per packet costs the
                        # emulator more than the sending).
                        due_ns = turn.first_ns + turn.next * interval_ns
                        wait_s = max((due_ns - time.time_ns()) / NS_PER_S, SEND_GRANULARITY_S)
            if due is not None:
                for packet in due:
                    self._send(packet, self.msop_addr)
                continue
            self._wake.wait(max(0.0, min(wait_s, next_difop - time.monotonic())))
            self._wake.clear()

    def _send(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            self.sock.sendto(data, addr)
            self.sent += 1
        except OSError:
            pass  # nobody listening (ICMP refused) or the network is down: a device sends regardless
