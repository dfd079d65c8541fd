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

A device that numbers its cycles (the ARS 408's measurement counter; site file `clock: cycle`) has its
receive times smoothed (`CycleFit`): its cycles are regular, so the receive times, once on the clock of
record and less the latency, lie on a line in the cycle number but for the link's jitter; a robust fit
(Theil-Sen: medians, so one late frame moves nothing) gives each cycle its time on that line. The
jitter goes, and so do the neighbouring captures it caused; what remains is the fit's error.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.stats import theilslopes

from shared.scene.model import SensorSpec
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S, SimTime, tick_stamp_ns

SNAP_WINDOW = 200  # recent snap offsets kept per sensor
CYCLE_WINDOW = 64  # cycles a CycleFit fits over (6.4 s at 10 Hz: drift of a real unit's cycle is followed)
CYCLE_MIN_FIT = 8  # cycles before the fit is trusted (before: the receive time, counted `settling`)
CYCLE_COUNTER_MOD = 1 << 16  # the ARS 408's measurement counters are 16 bits
# A cycle the fit puts this far from its receive time, three in a row, means the line moved (the unit
# restarted, the sim restarted): start over. One such frame alone is a late one and gets the line's time.
CYCLE_RESET_NS = NS_PER_S
CYCLE_RESET_AFTER = 3
TOLERANCE_NS = 1_000_000  # a device stamp up to this early still belongs to the tick (Robosense: 1 us)


@dataclass(frozen=True)
class Stamp:
    stamp_ns: int
    tick: int = 0
    epoch: int = 0


class CycleFit:
    """Times of a device's numbered cycles from their receive times (module docstring). ns in, ns out;
    `counter` wraps at `modulus`. A jump of the counter by 0 or by more than half its range is a restart."""

    def __init__(self, modulus: int = CYCLE_COUNTER_MOD, window: int = CYCLE_WINDOW) -> None:
        self.modulus = modulus
        self._cycles: deque[int] = deque(maxlen=window)  # unwrapped cycle numbers
        self._times: deque[int] = deque(maxlen=window)  # their receive times, ns
        self._last: int | None = None  # last raw counter
        self._n = 0
        self._astray = 0
        self.settling = 0  # frames stamped with their receive time while the fit was too short
        self.resets = 0

    def reset(self) -> None:
        self._cycles.clear()
        self._times.clear()
        self._last, self._n, self._astray = None, 0, 0
        self.resets += 1

    def stamp(self, counter: int, recv_ns: int) -> int:
        if self._last is not None:
            step = (counter - self._last) % self.modulus
            if step == 0 or step > self.modulus // 2:
                self.reset()
            else:
                self._n += step
        self._last = counter
        self._cycles.append(self._n)
        self._times.append(recv_ns)
        if len(self._cycles) < CYCLE_MIN_FIT:
            self.settling += 1
            return recv_ns
        ref = self._times[0]
        x = np.fromiter(self._cycles, np.float64)
        y = (np.fromiter(self._times, np.int64) - ref) / NS_PER_S
        slope = theilslopes(y, x).slope
        # The intercept as the median residual: scipy's (median y - slope x median x) moves with late
        # frames, which reorder the receive times.
        intercept = float(np.median(y - slope * x))
        fitted = ref + round((intercept + slope * self._n) * NS_PER_S)
        if abs(fitted - recv_ns) > CYCLE_RESET_NS:
            self._astray += 1
            if self._astray >= CYCLE_RESET_AFTER:
                self.reset()
                self._last = counter
                self._cycles.append(self._n)
                self._times.append(recv_ns)
                self.settling += 1
                return recv_ns
        else:
            self._astray = 0
        return fitted


class Stamper:
    """Stamps of one sensor's frames (see the module docstring)."""

    def __init__(self, scene: Scene, spec: SensorSpec, sim_time: SimTime, latency_s: float = 0.0) -> None:
        self.scene, self.spec, self.sim_time = scene, spec, sim_time
        self.latency_ns = round(latency_s * NS_PER_S)
        self.snap_ns: deque[int] = deque(maxlen=SNAP_WINDOW)
        self.unsnapped = 0
        self.repeated = 0  # frames given the same capture as the frame before them (a late one)
        self._last: tuple[int, int] | None = None  # (epoch, tick) of the last frame
        self.cycles = CycleFit()

    def stamp(self, stamp_ns: int, on_wall_clock: bool, cycle: int | None = None) -> Stamp:
        """`stamp_ns` is wall-clock ns (receive time) when `on_wall_clock`, else the device's time
        (already on the clock of record: a GPS-locked unit on a real site, sim time from an emulator).
        `cycle`: the device's cycle counter (a receive time is then smoothed over its cycles)."""
        if on_wall_clock:
            stamp_ns = self.sim_time.now_ns(stamp_ns) - self.latency_ns
            if cycle is not None:
                stamp_ns = self.cycles.stamp(cycle, stamp_ns)
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

    def cycles_text(self) -> str:
        """The cycle fit's counts for the periodic log ('' for a device without cycles)."""
        fit = self.cycles
        return f", cycle fit: {fit.settling} settling, {fit.resets} restarts" if fit.settling else ""

    def snap_summary_ms(self) -> tuple[float, float, float]:
        """Smallest, median and largest signed offset (stamp - its capture's) over the recent frames,
        ms (zeros: none)."""
        if not self.snap_ns:
            return 0.0, 0.0, 0.0
        offsets = np.fromiter(self.snap_ns, np.int64) / 1e6
        return float(offsets.min()), float(np.median(offsets)), float(offsets.max())


def frame_wanted(
    scene: Scene, spec: SensorSpec, tick: int, sim_time: SimTime, every_n: int, nth: int
) -> bool:
    """Is this camera frame wanted at cadence `every_n`: by its tick under a sim, else every n-th."""
    hz = sim_time.tick_hz
    if every_n <= 1:
        return True
    if tick and hz is not None:
        return scene.captures_on(spec, tick, hz, every_n)
    return nth % every_n == 0
