"""Device sources: one reader per real sensor, turning its wire format into the message the simulated
sensor publishes (lidar foxglove.PointCloud, radar rmmdet.v1.RadarScan, camera foxglove.CompressedImage
JPEG), with the time it was taken and which clock gave it.

Each source reads on its own thread and hands `Output`s to a callback; it never raises out of the
thread: bad input is counted by reason (`counters`), a lost device is reconnected with backoff, and
`status()` says in one line what is wrong with the device (no DIFOP yet, radar not configured,
bus-off, stream down), which the device service reports in its health beside the sensors that went
silent (judged there, on the clock of record).

- `LidarSource`: MSOP and DIFOP UDP sockets (kernel receive stamps, SO_TIMESTAMPNS) -> LidarStream.
- `VelodyneSource`: a VLP-16 / VLP-32C data port -> velodyne-decoder's StreamDecoder.
- `RadarSource`: a python-can bus (socketcan, slcan, udp_multicast, virtual) -> ListAssembler; sends
  the configuration at start and again every second until RadarState confirms it.
- `CameraSource`: OpenCV's FFmpeg backend on the stream URL; an MJPEG source's JPEG packets are passed
  through undecoded (CAP_PROP_FORMAT -1), any other codec is decoded and encoded as JPEG; one
  latest-frame thread per camera, reopened with backoff when a read fails. A camera on its own clock
  (`clock: device`, HTTP MJPEG only) is read part by part (shared/devices/mjpeg.py) for the capture
  time each part's X-Timestamp header carries.
"""

from __future__ import annotations

import logging
import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Generator, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.sensors_pb2 import RadarScan, RadarTarget

from shared.devices import ars408, robosense, serial_urls, velodyne
from shared.devices.mjpeg import TIMESTAMP_HEADER, MjpegStream, StreamError
from shared.devices.redact import redacted
from shared.devices.site import Ars408Radar, RobosenseLidar, SiteFile, StreamCamera, VelodyneLidar
from shared.perception.decode import INTENSITY_FULL_SCALE, point_cloud_message
from shared.scene.model import SensorSpec
from shared.timebase import NS_PER_S

log = logging.getLogger(__name__)

# A stalled stream (connection open, nothing coming) is reopened after this; a closed one at once. Long
# enough for a camera asked for one frame in ten under a slow sim (the device service judges silence
# on the clock of record; this only decides when to reconnect).
STREAM_READ_TIMEOUT_S = 10.0
JPEG_QUALITY = 85
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@qq")


@dataclass(frozen=True)
class Output:
    """One frame of one sensor: the message (stamp fields unset) and its time."""

    sensor_id: str
    message: Message
    stamp_ns: int
    on_wall_clock: bool  # True: host receive time (wall); False: the device's own clock
    cycle: int | None = None  # the device's cycle counter, where its receive times are to be smoothed


OutputFn = Callable[[Output], None]


class _Source:
    """Shared plumbing: counters, frames out, a thread that survives its own failures."""

    def __init__(self, sensor_id: str, emit: OutputFn) -> None:
        self.sensor_id = sensor_id
        self.emit = emit
        self.counters: dict[str, int] = {}
        self.frames = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._guarded_run, name=f"device-{sensor_id}", daemon=True)
        self._lock = threading.Lock()

    def count(self, reason: str, n: int = 1) -> None:
        with self._lock:
            self.counters[reason] = self.counters.get(reason, 0) + n

    def counters_snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

    def _from_unit(self, sock: socket.socket, unit_address: str) -> Iterator[tuple[bytes, int]]:
        """The datagrams waiting on `sock` that came from `unit_address`, with their receive times; any
        other sender's refused and counted (its points and angle tables are not the unit's)."""
        while (got := _recv_stamped(sock)) is not None:
            data, recv_ns, sender = got
            if sender != unit_address:
                self.count("rejected/foreign_sender")
                continue
            yield data, recv_ns

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:  # started
            self._thread.join(timeout=3.0)

    def _frame_out(self, output: Output) -> None:
        self.frames += 1
        self.emit(output)

    def _guarded_run(self) -> None:
        while not self._stop.is_set():
            try:
                self._run()
                return
            except Exception:  # never let a device kill its thread: count, wait, go on
                self.count("errors/internal")
                log.exception("%s: reader failed; restarting it in 1 s", self.sensor_id)
                self._stop.wait(1.0)

    def _run(self) -> None:
        raise NotImplementedError

    def status(self) -> str:
        """'' when all is well, else what is wrong."""
        raise NotImplementedError


# --- lidar ------------------------------------------------------------------------------------------


def lidar_frame_message(frame: robosense.Frame, sensor_id: str, returns: str = "first") -> Any:
    """foxglove.PointCloud of a decoded frame (first returns only unless `returns` is 'all')."""
    pts = frame.points
    xyz_m, intensity = pts.xyz_m, pts.intensity
    if returns != "all" and pts.ret.any():  # single-return frames (no second returns) are taken whole
        keep = pts.ret == 0
        xyz_m, intensity = xyz_m[keep], intensity[keep]
    return point_cloud_message(
        xyz_m, intensity.astype(np.float32) / INTENSITY_FULL_SCALE, sensor_id, frame.stamp_ns
    )


def _udp_socket(bind: str, port: int) -> socket.socket:
    # No SO_REUSEADDR: with it on both sockets, another local process could bind the same port (its
    # own socket with the option) and be handed the unit's datagrams in place of this adapter (Linux
    # gives a unicast datagram to one of them); a UDP port has no TIME_WAIT to wait out on restart.
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)  # a turn of RS-LiDAR-32 is 187 kB
    sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    sock.bind((bind, port))
    sock.setblocking(False)
    return sock


def _recv_stamped(sock: socket.socket) -> tuple[bytes, int, str] | None:
    """One datagram, its kernel receive time (wall ns; now if the kernel gave none) and its sender's
    address."""
    try:
        data, ancdata, _flags, addr = sock.recvmsg(2048, 64)
    except BlockingIOError:
        return None
    for level, kind, payload in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack(payload[: _TIMESPEC.size])
            return data, sec * NS_PER_S + nsec, addr[0]
    return data, time.time_ns(), addr[0]


class LidarSource(_Source):
    """A Robosense unit on its MSOP / DIFOP UDP ports."""

    def __init__(self, sensor_id: str, spec: RobosenseLidar, emit: OutputFn) -> None:
        super().__init__(sensor_id, emit)
        self.spec = spec
        model = robosense.MODELS[spec.device]
        clock = robosense.StampClock(spec.clock)
        self.stream = robosense.LidarStream(model, clock, spec.min_range_m, spec.max_range_m)
        self.msop = _udp_socket(spec.bind, spec.msop_port)
        self.difop = _udp_socket(spec.bind, spec.difop_port)
        self._last_packet_mono = time.monotonic()
        # An open frame whose packets stopped for two revolutions is dropped (counted).
        self.expire_after_s = 0.2

    def close(self) -> None:
        super().close()
        self.msop.close()
        self.difop.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.msop, self.difop], [], [], 0.1)
            for sock in ready:
                for data, recv_ns in self._from_unit(sock, self.spec.unit_address):
                    if sock is self.difop:
                        self.stream.on_difop(data)
                        continue
                    self._last_packet_mono = time.monotonic()
                    for frame in self.stream.on_msop(data, recv_ns):
                        self._frame_out(
                            Output(
                                self.sensor_id,
                                lidar_frame_message(frame, self.sensor_id, self.spec.returns),
                                frame.stamp_ns,
                                frame.clock is robosense.StampClock.RECEIVE,
                            )
                        )
            if self.stream.open_packets and time.monotonic() - self._last_packet_mono > self.expire_after_s:
                self.stream.expire()

    def counters_snapshot(self) -> dict[str, int]:
        return super().counters_snapshot() | self.stream.counters

    def status(self) -> str:
        if self.stream.info is None:
            return "no DIFOP yet: no cloud until the unit's angles arrive"
        if self.spec.clock == "device" and not self.stream.info.clock_locked:
            return "clock not locked (DIFOP): stamped on receive"
        return ""


class VelodyneSource(_Source):
    """A Velodyne unit on its data port, decoded by `velodyne.VelodyneStream` (velodyne-decoder: a scan
    per revolution, cut at its default angle; stamped with its first packet)."""

    def __init__(self, sensor_id: str, spec: VelodyneLidar, emit: OutputFn) -> None:
        super().__init__(sensor_id, emit)
        self.spec = spec
        self.stream = velodyne.VelodyneStream(
            spec.device, spec.min_range_m, spec.max_range_m, spec.calibration_file
        )
        self.sock = _udp_socket(spec.bind, spec.data_port)

    def close(self) -> None:
        super().close()
        self.sock.close()

    def on_packet(self, data: bytes, recv_ns: int) -> None:
        scan = self.stream.on_packet(data, recv_ns)
        if scan is None:
            return
        stamp_ns, wall = (scan.device_ns, False) if self.spec.clock == "device" else (scan.host_ns, True)
        message = velodyne_scan_message(scan, self.sensor_id, stamp_ns)
        self._frame_out(Output(self.sensor_id, message, stamp_ns, wall))

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.sock], [], [], 0.1)
            if ready:
                for data, recv_ns in self._from_unit(self.sock, self.spec.unit_address):
                    self.on_packet(data, recv_ns)

    def counters_snapshot(self) -> dict[str, int]:
        return super().counters_snapshot() | dict(self.stream.counters)

    def status(self) -> str:
        return ""


def velodyne_scan_message(scan: velodyne.Scan, sensor_id: str, stamp_ns: int) -> Any:
    """foxglove.PointCloud of a Velodyne scan (intensity 0-255 scaled to [0, 1])."""
    pts = scan.points
    intensity = pts[:, velodyne.INTENSITY] / INTENSITY_FULL_SCALE
    return point_cloud_message(pts[:, :3], intensity, sensor_id, stamp_ns)


# --- radar ------------------------------------------------------------------------------------------


def radar_scan_message(detections: ars408.Detections, sensor_id: str) -> RadarScan:
    """rmmdet.v1.RadarScan of one ARS 408 list: each detection's range and azimuth in the radar's
    plane (elevation 0: the ARS 408 reports none), range rate along the line of sight, RCS; the
    ARS 408 reports no SNR (left 0)."""
    rng, az, rate = detections.polar()
    scan = RadarScan(sensor_id=sensor_id)
    for i in range(len(detections)):
        scan.targets.append(
            RadarTarget(
                range_m=float(rng[i]),
                azimuth_rad=float(az[i]),
                elevation_rad=0.0,
                range_rate_mps=float(rate[i]),
                rcs_dbsm=float(detections.rcs_dbsm[i]),
                target_index=i,
            )
        )
    return scan


CONFIG_RETRY_S = 1.0
RECONNECT_MIN_S = 0.2


class RadarSource(_Source):
    """An ARS 408 on a CAN bus (python-can), configured at start."""

    def __init__(
        self,
        sensor_id: str,
        spec: Ars408Radar,
        emit: OutputFn,
        bus_factory: Callable[[], Any] | None = None,
        reconnect_max_s: float = 2.0,
    ) -> None:
        super().__init__(sensor_id, emit)
        self.spec = spec
        self.config = ars408.RadarConfig(
            sensor_id=spec.can_id,
            output=ars408.OutputType.CLUSTERS if spec.output == "clusters" else ars408.OutputType.OBJECTS,
        )
        self.assembler = ars408.ListAssembler(self.config)
        self.bus_factory = bus_factory or self._open_bus
        self.reconnect_max_s = reconnect_max_s
        self.connected = False

    def _open_bus(self) -> Any:
        import can  # python-can: imported where a bus is opened (its import is slow)

        kwargs: dict[str, Any] = {"interface": self.spec.interface, "channel": self.spec.channel}
        if self.spec.interface == "slcan":
            serial_urls.use()  # socket:// with a receive buffer
            kwargs |= {"bitrate": self.spec.bitrate, "sleep_after_open": 0.0}
        elif self.spec.interface == "socketcan":
            kwargs |= {"receive_own_messages": False}
        return can.Bus(**kwargs)

    def _run(self) -> None:
        backoff = RECONNECT_MIN_S
        while not self._stop.is_set():
            try:
                bus = self.bus_factory()
            except Exception as exc:  # no device, no adapter, refused: retry
                self.count("can/open_failed")
                log.warning(
                    "%s: cannot open CAN %s %s: %s",
                    self.sensor_id,
                    self.spec.interface,
                    self.spec.channel,
                    exc,
                )
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.reconnect_max_s)
                continue
            self.connected = True
            backoff = RECONNECT_MIN_S
            try:
                self._read(bus)
            finally:
                self.connected = False
                try:
                    bus.shutdown()
                except Exception:
                    self.count("can/shutdown_failed")

    def _read(self, bus: Any) -> None:
        import can

        next_config = 0.0
        while not self._stop.is_set():
            if not self.assembler.configured and time.monotonic() >= next_config:
                can_id, data = self.config.frame()
                try:
                    bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
                    self.count("can/config_sent")
                except can.CanError:
                    self.count("can/send_failed")
                next_config = time.monotonic() + CONFIG_RETRY_S
            try:
                msg = bus.recv(0.1)
            except (can.CanError, OSError, ValueError) as exc:
                # The link broke (adapter unplugged, socket closed) or a line did not parse.
                self.count("can/read_failed")
                log.warning("%s: CAN read failed (%s): reconnecting", self.sensor_id, exc)
                return
            if msg is None:
                continue
            if msg.is_error_frame:
                self.assembler.on_error_frame(msg.arbitration_id)
                continue
            if msg.is_remote_frame or msg.is_extended_id:
                self.count("rejected/foreign_frame")
                continue
            stamp_s = msg.timestamp if msg.timestamp and math.isfinite(msg.timestamp) else time.time()
            for detections in self.assembler.on_frame(msg.arbitration_id, bytes(msg.data), stamp_s):
                if self.assembler.configured:
                    self._frame_out(
                        Output(
                            self.sensor_id,
                            radar_scan_message(detections, self.sensor_id),
                            round(detections.stamp_s * NS_PER_S),
                            True,
                            detections.meas_counter if self.spec.clock == "cycle" else None,
                        )
                    )
                else:
                    self.count("lists/before_configured")

    def counters_snapshot(self) -> dict[str, int]:
        return super().counters_snapshot() | self.assembler.counters

    def status(self) -> str:
        if not self.connected:
            return f"CAN {self.spec.interface} {self.spec.channel} not open"
        if self.assembler.bus_off:
            return "CAN bus-off"
        if not self.assembler.configured:
            state = self.assembler.state
            wrong = state.mismatches(self.config) if state else ["no RadarState yet"]
            return f"radar not configured ({', '.join(wrong)})"
        if self.assembler.state and self.assembler.state.errors:
            return f"radar reports {', '.join(self.assembler.state.errors)}"
        return ""


# --- camera -----------------------------------------------------------------------------------------

MJPEG_FOURCC = cv2.VideoWriter.fourcc(*"MJPG")


def open_capture(url: str, timeout_s: float) -> cv2.VideoCapture:
    """An OpenCV capture of `url`: a digit string or /dev/video* opens that V4L2 device, anything else
    goes to FFmpeg with open and read timeouts."""
    timeout_ms = round(timeout_s * 1000)
    if url.isdigit() or url.startswith("/dev/video"):
        return cv2.VideoCapture(int(url) if url.isdigit() else url, cv2.CAP_V4L2)
    return cv2.VideoCapture(
        url,
        cv2.CAP_FFMPEG,
        [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, timeout_ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, timeout_ms],
    )


class CameraSource(_Source):
    """A camera stream: the newest frame goes out as soon as it is read."""

    def __init__(
        self, sensor_id: str, spec: StreamCamera, emit: OutputFn, timeout_s: float = STREAM_READ_TIMEOUT_S
    ) -> None:
        super().__init__(sensor_id, emit)
        self.spec = spec
        self.timeout_s = timeout_s
        self.connected = False
        self.reconnects = 0
        self.no_device_stamp = False  # clock: device, and the last frame came without its time
        self._stream: MjpegStream | None = None

    def _run(self) -> None:
        backoff = RECONNECT_MIN_S
        while not self._stop.is_set():
            frames = self._open()
            if frames is None:
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.spec.reconnect_max_s)
                continue
            self.connected = True
            backoff = RECONNECT_MIN_S
            try:
                for jpeg, device_ns in frames:
                    recv_ns = time.time_ns()
                    if self.spec.clock == "device" and device_ns is None:
                        self.count("clock/no_device_stamp")
                    self.no_device_stamp = self.spec.clock == "device" and device_ns is None
                    self._frame_out(
                        Output(
                            self.sensor_id,
                            CompressedImage(frame_id=self.sensor_id, format="jpeg", data=jpeg),
                            recv_ns if device_ns is None else device_ns,
                            device_ns is None,
                        )
                    )
                    if self._stop.is_set():
                        break
            finally:
                self.connected = False
                frames.close()
            if not self._stop.is_set():
                self.reconnects += 1
                self.count("stream/reconnects")

    def close(self) -> None:
        self._stop.set()
        stream = self._stream
        if stream is not None:
            stream.close()  # ends a read blocked on a silent camera now, not at its timeout
        super().close()

    def _open(self) -> Generator[tuple[bytes, int | None], None, None] | None:
        """The stream's frames as (JPEG, device time ns or None), or None (counted) if it will not open."""
        if self.spec.clock == "device":
            try:
                stream = MjpegStream(self.spec.url, self.timeout_s)
            except StreamError as exc:
                self.count(f"stream/{exc.reason}")
                return None
            return self._mjpeg_frames(stream)
        cap = open_capture(self.spec.url, self.timeout_s)
        if not cap.isOpened():
            cap.release()
            self.count("stream/open_failed")
            return None
        return self._capture_frames(cap)

    def _mjpeg_frames(self, stream: MjpegStream) -> Generator[tuple[bytes, int | None], None, None]:
        self._stream = stream
        try:
            for part in stream.parts():
                if part.stamp_problem:
                    self.count("clock/bad_device_stamp")
                    if self.counters_snapshot()["clock/bad_device_stamp"] == 1:  # the first only
                        log.warning("%s: %s; stamped on receive", self.sensor_id, part.stamp_problem)
                if not part.jpeg.startswith(b"\xff\xd8"):
                    self.count("rejected/not_jpeg")
                    continue
                yield part.jpeg, part.device_ns
        except StreamError as exc:
            self.count(f"stream/{exc.reason}")
        finally:
            self._stream = None
            stream.close()

    def _capture_frames(self, cap: cv2.VideoCapture) -> Generator[tuple[bytes, int | None], None, None]:
        """OpenCV's reader: an MJPEG source's JPEG passed through, any other codec encoded as JPEG; no
        device time (OpenCV gives none)."""
        try:
            fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
            passthrough = fourcc == MJPEG_FOURCC and cap.set(cv2.CAP_PROP_FORMAT, -1)
            url = self.spec.url
            is_file = not (url.isdigit() or "://" in url or url.startswith("/dev/"))
            fps = cap.get(cv2.CAP_PROP_FPS)
            frame_s = 1.0 / fps if is_file and fps > 0 else 0.0
            while not self._stop.is_set():
                ok, frame = cap.read()
                if not ok or frame is None:
                    self.count("stream/read_failed")
                    return
                if passthrough:
                    jpeg = frame.tobytes()
                    if not jpeg.startswith(b"\xff\xd8"):
                        self.count("rejected/not_jpeg")
                        continue
                else:
                    ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
                    if not ok:
                        self.count("rejected/encode_failed")
                        continue
                    jpeg = buf.tobytes()
                yield jpeg, None
                if frame_s:
                    self._stop.wait(frame_s)  # a file plays at its own rate, not as fast as it decodes
        finally:
            cap.release()

    def status(self) -> str:
        if not self.connected:
            return f"stream {redacted(self.spec.url)} not open"
        if self.no_device_stamp:
            return f"no {TIMESTAMP_HEADER} from the camera: stamped on receive"
        return ""


Source = LidarSource | VelodyneSource | RadarSource | CameraSource


def source_for(site: SiteFile, spec: SensorSpec, emit: OutputFn) -> Source:
    """The source reading `spec`'s device as `site` describes it (by its kind of device)."""
    device = site.device(spec.id)
    if isinstance(device, RobosenseLidar):
        return LidarSource(spec.id, device, emit)
    if isinstance(device, VelodyneLidar):
        return VelodyneSource(spec.id, device, emit)
    if isinstance(device, Ars408Radar):
        return RadarSource(spec.id, device, emit)
    return CameraSource(spec.id, device, emit)


def counters_by_reason(sources: Mapping[str, Source]) -> dict[str, int]:
    """Every source's own counters as `<reason>/<sensor id>` (what `rmmdet health` shows)."""
    return {
        f"{reason}/{sid}": n for sid, src in sources.items() for reason, n in src.counters_snapshot().items()
    }
