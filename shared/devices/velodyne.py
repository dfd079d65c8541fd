"""Velodyne VLP-16 / VLP-32C / HDL-32E data packets -> scans, through velodyne-decoder's compiled
StreamDecoder (one home for the live adapter, `rmmdet import` and `rmmdet devices replay`).

A data packet is 1206 bytes (UDP port 2368): 12 blocks of 100 bytes (flag `FF EE`, azimuth u16 in
0.01 deg, 32 returns of {distance u16, reflectivity u8}), a u32 time in microseconds past the hour and
two factory bytes: the return mode (0x37 strongest, 0x38 last, 0x39 dual) and the product id (0x21
HDL-32E, 0x22 VLP-16, 0x24 Puck Hi-Res, 0x28 VLP-32C, ...). A position packet (512 bytes, port 8308)
carries the GPS sentence and is not decoded here. Facts: the VLP-16 and VLP-32C user manuals (data
packet format, factory bytes), as velodyne-decoder and the ROS velodyne driver read them.

Calibration: velodyne-decoder's bundled one for the model unless the unit's own file is given
(`calibration`: the ROS velodyne driver's YAML, as VeloView and nebula ship per unit).
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.timebase import NS_PER_S

log = logging.getLogger(__name__)

DATA_PORT = 2368
POSITION_PORT = 8308
DATA_PACKET_BYTES = 1206
POSITION_PACKET_BYTES = 512
BLOCK_FLAG = bytes.fromhex("FFEE")
RETURN_MODE_OFFSET = 1204
PRODUCT_ID_OFFSET = 1205
#: The factory byte's product ids of the units supported here (the user manuals' tables).
PRODUCT_IDS = {0x21: "hdl32e", 0x22: "vlp16", 0x28: "vlp32c"}
RETURN_MODES = {0x37: "strongest", 0x38: "last", 0x39: "dual"}
DEVICES = tuple(sorted(PRODUCT_IDS.values()))
HOUR_NS = 3_600 * NS_PER_S
# velodyne-decoder's point columns (its PointField order).
X, Y, Z, INTENSITY, TIME, COLUMN, RING, RETURN_TYPE = range(8)


def product_of(packet: bytes) -> str | None:
    """The unit's model from a data packet's factory byte, or None (not a data packet, unknown id)."""
    if len(packet) != DATA_PACKET_BYTES or packet[:2] != BLOCK_FLAG:
        return None
    return PRODUCT_IDS.get(packet[PRODUCT_ID_OFFSET])


@dataclass(frozen=True)
class Scan:
    """One revolution: velodyne-decoder's (N, 8) float32 points (x, y, z in metres, intensity 0-255,
    time after the scan's stamp in s, column, ring, return type) and its stamps."""

    points: np.ndarray
    host_ns: int  # the first packet's receive time
    device_ns: int  # the first packet's own time on the host's hour (`on_host_hour`)


def on_host_hour(device_ns: int, host_ns: int) -> int:
    """A time within the hour (what a packet carries, unless it is given absolute time) on the host's
    hour: the one that puts it nearest the host's time."""
    if device_ns >= HOUR_NS:
        return device_ns  # already absolute
    base = host_ns - host_ns % HOUR_NS + device_ns
    return min((base - HOUR_NS, base, base + HOUR_NS), key=lambda t: abs(t - host_ns))


def load_calibration(path: Path) -> Any:
    """A unit's calibration file (the ROS velodyne driver's YAML) for velodyne-decoder; ValueError
    naming the file when it does not read."""
    import velodyne_decoder as vd

    try:
        return vd.Calibration.read(str(path))
    except (RuntimeError, ValueError, OSError) as exc:
        raise ValueError(f"{path}: not a Velodyne calibration file ({exc})") from None


class VelodyneStream:
    """Data packets of one unit in receive order -> scans; refused packets counted in `counters`.

    Parameters
    ----------
    device : str
        "vlp16", "vlp32c" or "hdl32e".
    min_range_m, max_range_m : float
        Returns outside [min, max] are dropped (velodyne-decoder's range gate).
    calibration : Path, optional
        The unit's own calibration file; else velodyne-decoder's bundled one for the model.
    """

    def __init__(
        self,
        device: str,
        min_range_m: float = 0.1,
        max_range_m: float = 200.0,
        calibration: Path | None = None,
    ) -> None:
        import velodyne_decoder as vd  # compiled decoder: imported where a Velodyne is used

        models = {"vlp16": vd.Model.VLP16, "vlp32c": vd.Model.VLP32C, "hdl32e": vd.Model.HDL32E}
        if device not in models:
            raise ValueError(f"Velodyne device {device!r} is none of {sorted(models)}")
        self.device = device
        config = vd.Config(
            model=models[device], min_range=min_range_m, max_range=max_range_m, timestamp_first_packet=True
        )
        if calibration is not None:
            config.calibration = load_calibration(calibration)
        self._decoder = vd.StreamDecoder(config)
        self.counters: Counter[str] = Counter()

    def on_packet(self, data: bytes, recv_ns: int) -> Scan | None:
        """One datagram received at `recv_ns` (host ns); the scan it completed, if any."""
        if len(data) != DATA_PACKET_BYTES:
            self.counters["rejected/packet/bad_length"] += 1
            return None
        if data[:2] != BLOCK_FLAG:
            self.counters["rejected/packet/bad_flag"] += 1
            return None
        product = PRODUCT_IDS.get(data[PRODUCT_ID_OFFSET])
        if product is not None and product != self.device:
            self.counters["rejected/packet/other_model"] += 1
            return None
        try:
            result = self._decoder.decode(recv_ns / NS_PER_S, data)
        except (RuntimeError, ValueError) as exc:
            self.counters["rejected/packet/undecodable"] += 1
            log.debug("%s packet: %s", self.device, exc)
            return None
        self.counters["packets"] += 1
        if result is None:
            return None
        stamps, points = result
        if points is None or len(points) == 0:
            self.counters["scans/empty"] += 1
            return None
        self.counters["scans"] += 1
        host_ns = round(stamps.host * NS_PER_S)
        device_ns = on_host_hour(round(stamps.device * NS_PER_S), host_ns)
        return Scan(np.asarray(points, np.float32), host_ns, device_ns)
