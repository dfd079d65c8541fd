"""A device frame's stamp on the clock of record, and under a sim the tick it belongs to.

Real site (no sim clock): the stamp is the device's own time, or the host's receive time less the
site file's `latency_s`; tick and epoch stay 0 (the MEC joins real sensors by stamp).

Under a sim (`SimTime` follows a sim clock), an emulated device is one of the sim's sensors: receive
times are moved onto sim time (`SimTime.now_ns` of the wall time), and the frame is given the capture
tick of its sensor at or before its stamp (`Scene.latest_capture_tick`: a frame never arrives before
it was taken; captures are a sensor period apart, 100 ms at 10 Hz, so any delay from capture to
receipt under that finds the right one; a device-clock stamp may precede its tick by the clock's
resolution, `TOLERANCE_NS`) with that tick's exact stamp, as the simulated sensor would have carried:
the MEC then joins it tick-exactly like any simulated frame. How far each stamp was moved is kept
(`snap_ns`), so a delay that grows towards a period shows in the service's log before it mislabels a
frame.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from shared.scene.model import SensorSpec
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S, SimTime, tick_stamp_ns

SNAP_WINDOW = 200  # recent snap offsets kept per sensor
TOLERANCE_NS = 1_000_000  # a device stamp up to this early still belongs to the tick (Robosense: 1 us)


@dataclass(frozen=True)
class Stamp:
    stamp_ns: int
    tick: int = 0
    epoch: int = 0


class Stamper:
    """Stamps of one sensor's frames (see the module docstring)."""

    def __init__(self, scene: Scene, spec: SensorSpec, sim_time: SimTime, latency_s: float = 0.0) -> None:
        self.scene, self.spec, self.sim_time = scene, spec, sim_time
        self.latency_ns = round(latency_s * NS_PER_S)
        self.snap_ns: deque[int] = deque(maxlen=SNAP_WINDOW)
        self.unsnapped = 0

    def stamp(self, stamp_ns: int, on_wall_clock: bool) -> Stamp:
        """`stamp_ns` is wall-clock ns (receive time) when `on_wall_clock`, else the device's time
        (already on the clock of record: a GPS-locked unit on a real site, sim time from an emulator)."""
        if on_wall_clock:
            stamp_ns = self.sim_time.now_ns(stamp_ns) - self.latency_ns
        hz, epoch = self.sim_time.tick_hz, self.sim_time.epoch_ns
        if not self.sim_time.following or hz is None or epoch is None:
            return Stamp(stamp_ns)
        tick = self.scene.latest_capture_tick(
            self.spec, (stamp_ns + TOLERANCE_NS - epoch) * hz / NS_PER_S, hz
        )
        if tick is None:
            self.unsnapped += 1
            return Stamp(stamp_ns)
        snapped = tick_stamp_ns(epoch, tick, hz)
        self.snap_ns.append(stamp_ns - snapped)
        return Stamp(snapped, tick, epoch)

    def snap_summary_ms(self) -> tuple[float, float]:
        """Median and largest |offset| moved by the snap over the recent frames, ms (0, 0: none)."""
        if not self.snap_ns:
            return 0.0, 0.0
        offsets = np.abs(np.fromiter(self.snap_ns, np.int64)) / 1e6
        return float(np.median(offsets)), float(offsets.max())
