"""A simulated sensor group speaking its devices' wire formats: each capture goes out as the device the
site file names would send it (a Robosense unit's UDP packets, an ARS 408's CAN frames through a
serial-line CAN adapter, a network camera's MJPEG stream), for the device service
(services/device) to read as it would read the real one.

The site file's addresses are the adapter's side: the lidar emulator sends to the adapter's bind
address and ports (0.0.0.0 is sent to loopback), the radar and camera emulators serve on the host and
port of the adapter's `socket://` channel and stream URL.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import urlsplit

from shared.devices.site import Ars408Radar, RobosenseLidar, SiteFile, StreamCamera
from shared.scene.model import SensorSpec
from shared.timebase import NS_PER_S
from sim.emulators.ars408 import Ars408Emulator, SlcanRadarServer, Target
from sim.emulators.mjpeg import MjpegServer
from sim.emulators.robosense import LidarSender, RobosenseEmulator
from sim.sensors.lidar import LidarScan
from sim.sensors.radar import SimRadarTarget
from sim.sensors.rig import Capture

log = logging.getLogger(__name__)


def _socket_address(channel: str) -> tuple[str, int]:
    parts = urlsplit(channel)
    if parts.scheme != "socket" or parts.hostname is None or parts.port is None:
        raise ValueError(f"an emulated radar serves slcan on socket://host:port, not {channel!r}")
    return parts.hostname, parts.port


def _http_address(url: str) -> tuple[str, int]:
    parts = urlsplit(url)
    if parts.scheme != "http" or parts.hostname is None or parts.port is None:
        raise ValueError(f"an emulated camera serves MJPEG on http://host:port/..., not {url!r}")
    return parts.hostname, parts.port


@dataclass
class _Lidar:
    emulator: RobosenseEmulator
    sender: LidarSender


class WireGroup:
    """Emulators for `specs` per `site`; `send(capture)` puts one capture on the wire."""

    def __init__(self, site: SiteFile, specs: list[SensorSpec]) -> None:
        self.delays_ns = {
            s.id: round(d.latency_s * NS_PER_S)
            for s in specs
            if isinstance(d := site.device(s.id), (Ars408Radar, StreamCamera))
        }
        self.late = 0
        self._scheduler = _Scheduler()
        self.lidars: dict[str, _Lidar] = {}
        self.radars: dict[str, SlcanRadarServer] = {}
        self.cameras: dict[str, MjpegServer] = {}
        try:
            for spec in specs:
                device = site.device(spec.id)
                if isinstance(device, RobosenseLidar):
                    if spec.lidar is None or spec.lidar.device != device.device:
                        raise ValueError(f"{spec.id}: the scene's lidar is not a {device.device}")
                    emulator = RobosenseEmulator(device.device, spec.lidar.horizontal_samples, spec.lidar.rpm)
                    host = "127.0.0.1" if device.bind == "0.0.0.0" else device.bind
                    self.lidars[spec.id] = _Lidar(
                        emulator, LidarSender(emulator, host, device.msop_port, device.difop_port)
                    )
                elif isinstance(device, Ars408Radar):
                    if device.interface != "slcan":
                        raise ValueError(f"{spec.id}: an emulated ARS 408 is reached over slcan")
                    host, port = _socket_address(device.channel)
                    radar = Ars408Emulator(sensor_id=device.can_id)
                    self.radars[spec.id] = SlcanRadarServer(radar, host, port)
                elif isinstance(device, StreamCamera):
                    host, port = _http_address(device.url)
                    self.cameras[spec.id] = MjpegServer(host, port)
        except BaseException:
            self.close()
            raise

    def send(self, capture: Capture, tick_wall_ns: int | None = None) -> None:
        """Put `capture` on the wire; a radar's or camera's `latency_s` (site file) after
        `tick_wall_ns` (the wall time its tick arrived: the moment of capture), as the device delivers
        its output a fixed time after its measurement; at once if that has passed (counted `late`).
        A lidar's packets go out over its revolution (LidarSender)."""
        sid = capture.spec.id
        delay_ns = self.delays_ns.get(sid, 0)
        if delay_ns and tick_wall_ns is not None:
            due_ns = tick_wall_ns + delay_ns
            if time.time_ns() < due_ns:
                self._scheduler.at(due_ns, lambda: self._send_now(capture))
                return
            self.late += 1
        self._send_now(capture)

    def _send_now(self, capture: Capture) -> None:
        sid = capture.spec.id
        if sid in self.lidars:
            lidar = self.lidars[sid]
            scan = capture.data
            assert isinstance(scan, LidarScan)
            samples = lidar.emulator.samples
            packets = lidar.emulator.msop_packets(
                scan.channel, scan.ray_index % samples, scan.range_m, scan.intensity, capture.stamp_ns
            )
            lidar.sender.send_turn(packets)
        elif sid in self.radars:
            targets = capture.data
            assert isinstance(targets, list)
            # The radar's cycle number: its captures are one period of sim time apart.
            cycle = round(capture.stamp_ns / NS_PER_S * capture.spec.rate_hz)
            self.radars[sid].send_scan([radar_target(t) for t in targets], cycle)
        elif sid in self.cameras:
            self.cameras[sid].publish(capture.message.data, capture.stamp_ns)  # type: ignore[attr-defined]

    def status(self) -> str:
        parts = [f"{self.late} late"] if self.late else []
        parts += [f"{sid} {lidar.sender.sent} packets" for sid, lidar in self.lidars.items()]
        parts += [f"{sid} {srv.frames_sent} frames" for sid, srv in self.radars.items()]
        parts += [f"{sid} {srv.frames} images, {srv.clients} clients" for sid, srv in self.cameras.items()]
        return ", ".join(parts)

    def close(self) -> None:
        self._scheduler.close()
        for lidar in self.lidars.values():
            lidar.sender.close()
        for radar in self.radars.values():
            radar.close()
        for camera in self.cameras.values():
            camera.stop()


class _Scheduler:
    """Runs callables at wall times, in order, on one thread (the delayed device outputs)."""

    def __init__(self) -> None:
        self._queue: list[tuple[int, int, Callable[[], None]]] = []
        self._count = 0
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="wire-scheduler", daemon=True)
        self._thread.start()

    def at(self, due_ns: int, fn: Callable[[], None]) -> None:
        with self._cond:
            self._count += 1
            heapq.heappush(self._queue, (due_ns, self._count, fn))
            self._cond.notify()

    def close(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stop and (not self._queue or self._queue[0][0] > time.time_ns()):
                    wait_s = (self._queue[0][0] - time.time_ns()) / NS_PER_S if self._queue else None
                    self._cond.wait(wait_s)
                if self._stop:
                    return
                _, _, fn = heapq.heappop(self._queue)
            try:
                fn()
            except Exception:  # a device that cannot take the frame now: never the scheduler's end
                log.exception("delayed device output failed")


def radar_target(t: SimRadarTarget) -> Target:
    return Target(t.range_m, t.azimuth_rad, t.elevation_rad, t.range_rate_mps, t.rcs_dbsm)
