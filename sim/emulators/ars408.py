"""Emulated Continental ARS 408-21: simulated radar targets as the radar's CAN frames, and its answer
to a configuration.

Written bit by bit from the documented layouts (`docs/references.md` "ARS 408": start bit |
length, factor, offset, Motorola order), apart from the adapter's decoder (cantools over the DBC in
shared/devices, and a numpy batch decoder): a round trip checks each against the other, the
known-answer tests check both against hand-made frames.

A scan becomes one list: in cluster mode (the default: the simulated radar reports detections, which
is what clusters are) Cluster_0_Status, then a Cluster_1_General per target, then a Cluster_2_Quality
each if quality was asked for; in object mode Obj_0_Status, Obj_1_General, Obj_2_Quality and
Obj_3_Extended (class car), one object per target, ids the targets' order in the scan. Positions are
projected on the radar's horizontal plane (DistLong forward, DistLat left); the velocity is the
target's range rate along its line of sight (the simulated radar measures nothing else); every value is
quantised as the radar quantises it (0.2 m, 0.25 m/s, 0.5 dBm^2) and clipped to its range.

The radar keeps the configuration a RadarConfiguration frame (0x200) sets and reports it in RadarState
(0x201), sent on every configuration and once a second.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from shared.devices.slcan import SlcanServer

SENSOR_STRIDE = 0x10  # sensor n adds 0x10 * n to every identifier
INTERFACE_VERSION = 1


def put(buf: bytearray, start_bit: int, length: int, raw: int) -> None:
    """Write `raw` into a Motorola (big-endian) signal whose most significant bit is DBC bit
    `start_bit` (bit b of byte k is k * 8 + b, bit 7 the byte's MSB) and which runs `length` bits
    towards the following bytes."""
    if not 0 <= raw < (1 << length):
        raise ValueError(f"{raw} does not fit {length} bits")
    byte, bit = divmod(start_bit, 8)
    for i in range(length - 1, -1, -1):  # most significant bit first
        if raw >> i & 1:
            buf[byte] |= 1 << bit
        else:
            buf[byte] &= ~(1 << bit) & 0xFF
        if bit == 0:
            byte, bit = byte + 1, 7
        else:
            bit -= 1


def get(buf: bytes, start_bit: int, length: int) -> int:
    """Read a Motorola signal (see `put`)."""
    byte, bit = divmod(start_bit, 8)
    raw = 0
    for _ in range(length):
        raw = (raw << 1) | (buf[byte] >> bit & 1)
        if bit == 0:
            byte, bit = byte + 1, 7
        else:
            bit -= 1
    return raw


def quantise(value: float, factor: float, offset: float, length: int) -> int:
    """Raw value of a physical one: round((value - offset) / factor), clipped to the field."""
    raw = round((value - offset) / factor)
    return min(max(raw, 0), (1 << length) - 1)


@dataclass(frozen=True)
class Target:
    """One simulated detection in the radar frame (m, rad, m/s, dBsm)."""

    range_m: float
    azimuth_rad: float
    elevation_rad: float
    range_rate_mps: float
    rcs_dbsm: float


@dataclass
class Ars408Emulator:
    """One emulated radar: its configuration and its frames."""

    sensor_id: int = 0
    output: int = 2  # 1 objects, 2 clusters (the radar's state until configured)
    send_quality: bool = True
    send_extended: bool = True
    max_distance_m: int = 196
    counter: int = 0

    def can_id(self, base: int) -> int:
        return base + SENSOR_STRIDE * self.sensor_id

    def on_config(self, data: bytes) -> bool:
        """Apply a RadarConfiguration payload (its valid bits choose what changes); True if it was one."""
        if len(data) < 8:
            return False
        if get(data, 3, 1):  # OutputType_valid
            self.output = get(data, 36, 2)
        if get(data, 4, 1):
            self.send_quality = bool(get(data, 42, 1))
        if get(data, 5, 1):
            self.send_extended = bool(get(data, 43, 1))
        if get(data, 0, 1):
            self.max_distance_m = get(data, 15, 10) * 2
        if get(data, 1, 1):
            self.sensor_id = get(data, 34, 3)
        return True

    def state_frame(self) -> tuple[int, bytes]:
        buf = bytearray(8)
        put(buf, 15, 10, self.max_distance_m // 2)
        put(buf, 34, 3, self.sensor_id)
        put(buf, 43, 2, self.output)
        put(buf, 44, 1, int(self.send_quality))
        put(buf, 45, 1, int(self.send_extended))
        return self.can_id(0x201), bytes(buf)

    def scan_frames(self, targets: Sequence[Target], cycle: int | None = None) -> list[tuple[int, bytes]]:
        """One measurement cycle's list: the counter is `cycle` (the radar's cycle number: a list the
        host never got still counted) or, without one, advances by one."""
        self.counter = (self.counter + 1 if cycle is None else cycle) & 0xFFFF
        targets = list(targets)[: 250 if self.output == 2 else 100]
        frames: list[tuple[int, bytes]] = []
        if self.output == 2:
            status = bytearray(5)
            put(status, 7, 8, len(targets))  # all near-scan clusters: the table is within its 70 m
            put(status, 15, 8, 0)
            put(status, 23, 16, self.counter)
            put(status, 39, 4, INTERFACE_VERSION)
            frames.append((self.can_id(0x600), bytes(status)))
            frames += [(self.can_id(0x701), self._general(i, t, cluster=True)) for i, t in enumerate(targets)]
            if self.send_quality:
                frames += [(self.can_id(0x702), self._cluster_quality(i)) for i in range(len(targets))]
        elif self.output == 1:
            status = bytearray(4)
            put(status, 7, 8, len(targets))
            put(status, 15, 16, self.counter)
            put(status, 31, 4, INTERFACE_VERSION)
            frames.append((self.can_id(0x60A), bytes(status)))
            frames += [
                (self.can_id(0x60B), self._general(i, t, cluster=False)) for i, t in enumerate(targets)
            ]
            if self.send_quality:
                frames += [(self.can_id(0x60C), self._object_quality(i)) for i in range(len(targets))]
            if self.send_extended:
                frames += [(self.can_id(0x60D), self._object_extended(i)) for i in range(len(targets))]
        return frames

    @staticmethod
    def _general(ident: int, t: Target, cluster: bool) -> bytes:
        ground = t.range_m * math.cos(t.elevation_rad)
        x, y = ground * math.cos(t.azimuth_rad), ground * math.sin(t.azimuth_rad)
        vx, vy = t.range_rate_mps * math.cos(t.azimuth_rad), t.range_rate_mps * math.sin(t.azimuth_rad)
        buf = bytearray(8)
        put(buf, 7, 8, ident & 0xFF)
        put(buf, 15, 13, quantise(x, 0.2, -500.0, 13))
        if cluster:
            put(buf, 17, 10, quantise(y, 0.2, -102.3, 10))
        else:
            put(buf, 18, 11, quantise(y, 0.2, -204.6, 11))
        put(buf, 39, 10, quantise(vx, 0.25, -128.0, 10))
        put(buf, 45, 9, quantise(vy, 0.25, -64.0, 9))
        put(buf, 50, 3, 0)  # dynamic property: moving (the simulated radar does not classify)
        put(buf, 63, 8, quantise(t.rcs_dbsm, 0.5, -64.0, 8))
        return bytes(buf)

    @staticmethod
    def _cluster_quality(ident: int) -> bytes:
        buf = bytearray(5)
        put(buf, 7, 8, ident & 0xFF)
        put(buf, 26, 3, 1)  # PdH0: lowest false-alarm bucket
        return bytes(buf)

    @staticmethod
    def _object_quality(ident: int) -> bytes:
        buf = bytearray(7)
        put(buf, 7, 8, ident & 0xFF)
        put(buf, 52, 3, 1)  # MeasState: measured
        put(buf, 55, 3, 7)  # ProbOfExist: 100 %
        return bytes(buf)

    @staticmethod
    def _object_extended(ident: int) -> bytes:
        buf = bytearray(8)
        put(buf, 7, 8, ident & 0xFF)
        put(buf, 15, 11, quantise(0.0, 0.01, -10.0, 11))
        put(buf, 20, 9, quantise(0.0, 0.01, -2.5, 9))
        put(buf, 26, 3, 1)  # class: car
        put(buf, 39, 10, quantise(0.0, 0.4, -180.0, 10))
        return bytes(buf)


class SlcanRadarServer(SlcanServer):
    """The radar behind a serial-line CAN adapter (a CANable-style SLCAN device), served on a TCP port
    (shared/devices/slcan.py): it applies RadarConfiguration frames it receives and answers each with
    RadarState, sends RadarState once a second and each scan's list as it comes. Fault injection:
    `bus_off` silences the radar (a node in bus-off sends nothing) until cleared."""

    def __init__(self, emulator: Ars408Emulator, host: str, port: int) -> None:
        self.emulator = emulator
        self.bus_off = False
        self.configs = 0
        super().__init__(host, port, on_frame=self._on_frame, on_tick=self._send_state)

    def send_scan(self, targets: Sequence[Target], cycle: int | None = None) -> None:
        """One measurement cycle's list to the client (dropped if none is connected, as on a bus with
        no other node: the radar transmits regardless)."""
        if self.bus_off:
            return
        self.send(self.emulator.scan_frames(targets, cycle))

    def _send_state(self) -> None:
        if not self.bus_off:
            self.send([self.emulator.state_frame()])

    def _on_frame(self, can_id: int, data: bytes) -> None:
        if can_id == self.emulator.can_id(0x200) and self.emulator.on_config(data):
            self.configs += 1
            self._send_state()
