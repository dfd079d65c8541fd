"""A device frame's stamp on the clock of record, and under a sim the tick it belongs to.

Real site (no sim clock): the stamp is the device's own time, or the host's receive time less the
site file's `latency_s`; tick and epoch stay 0 (the MEC joins real sensors by stamp).

Under a sim (`SimTime` follows a sim clock), an emulated device is one of the sim's sensors, and each
frame is given the capture tick of its sensor with that tick's exact stamp, as the simulated sensor
would have carried: the MEC then joins it tick-exactly like any simulated frame. A frame on the
device's own clock (an emulated unit's clock is sim time) gets the last capture at or before its
stamp (`Scene.latest_capture_tick`, less the clock's resolution `TOLERANCE_NS`): a frame is never
taken after it was made. A receive time is moved onto sim time (`SimTime.now_ns` of the wall time),
less the device's latency (the site file's `latency_s`, which the emulators also deliver at), and
gets the nearest capture (`Scene.nearest_capture_tick`): what remains is jitter either way, under
half a period (50 ms at 10 Hz). A frame whose delay strays further is given the neighbouring capture:
that is what receive-time stamping does with a jittery link, and it is counted (`repeated`: a capture
given to two frames in a row) and logged with the spread of the offsets (`snap_ns`); correcting the
next frames to make up for it would carry one late frame's error on to every frame after it.
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
        self.repeated = 0  # frames given the same capture as the frame before them (a late one)
        self._last: tuple[int, int] | None = None  # (epoch, tick) of the last frame

    def stamp(self, stamp_ns: int, on_wall_clock: bool) -> Stamp:
        """`stamp_ns` is wall-clock ns (receive time) when `on_wall_clock`, else the device's time
        (already on the clock of record: a GPS-locked unit on a real site, sim time from an emulator)."""
        if on_wall_clock:
            stamp_ns = self.sim_time.now_ns(stamp_ns) - self.latency_ns
        hz, epoch = self.sim_time.tick_hz, self.sim_time.epoch_ns
        if not self.sim_time.following or hz is None or epoch is None:
            return Stamp(stamp_ns)
        at = (stamp_ns - epoch) * hz / NS_PER_S
        if on_wall_clock:  # a receive time less the device's latency: jitter either way
            tick = self.scene.nearest_capture_tick(self.spec, at, hz)
        else:  # the device's own time: never after its capture (but for the clock's resolution)
            tick = self.scene.latest_capture_tick(self.spec, at + TOLERANCE_NS * hz / NS_PER_S, hz)
        if tick is None:
            self.unsnapped += 1
            return Stamp(stamp_ns)
        if self._last == (epoch, tick):
            self.repeated += 1
        self._last = (epoch, tick)
        snapped = tick_stamp_ns(epoch, tick, hz)
        self.snap_ns.append(stamp_ns - snapped)
        return Stamp(snapped, tick, epoch)

    def snap_summary_ms(self) -> tuple[float, float, float]:
        """Smallest, median and largest signed offset (stamp - its capture's) over the recent frames,
        ms (zeros: none)."""
        if not self.snap_ns:
            return 0.0, 0.0, 0.0
        offsets = np.fromiter(self.snap_ns, np.int64) / 1e6
        return float(offsets.min()), float(np.median(offsets)), float(offsets.max())
