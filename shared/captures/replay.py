"""`rmmdet devices replay`: a recorded capture played to a site's devices' ports and buses at its
recorded timing, so the site's device service (its live adapters, unchanged) and MECs run on it exactly
as on the live units.

What goes where (the site file says each sensor's device and where its adapter listens; the mapping's
`units:` / `radars:` say which recorded unit is which sensor, shared/captures/mapping.py):
- a Robosense unit's MSOP and DIFOP packets to its `msop_port` / `difop_port`, a Velodyne's data packets
  to its `data_port`, on the adapter's `bind` address (127.0.0.1 for 0.0.0.0, or `host`), sent from the
  unit's `unit_address` (the adapter refuses any other sender: it must be this host's); a Velodyne's
  position packets have no port in the site file and are counted, not sent;
- a radar's CAN frames to its bus: an `slcan` radar at `socket://host:port` is served on that port (as
  the adapter's serial-line adapter would be, shared/devices/slcan.py); a `socketcan`, `udp_multicast`
  or `virtual` bus is opened with python-can and written to. The frames carry the site's `can_id` (a
  recorded radar 0 replayed as a site's radar 2 gets 0x20 added to every identifier, and its
  RadarState says 2). Error frames are counted, not sent (a serial-line adapter cannot send one).
Inputs recorded together keep their relative timing; inputs recorded apart can be played from a
common start (`align_starts`). Pacing: each item is sent when its recorded time, less the first
item's, divided by `speed`, has passed on the host's monotonic clock; items that could not be sent on
time are sent at once and counted (`late`). The recorded stamps themselves do not travel: the
adapters stamp on receive, as live.
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.captures import identify
from shared.captures.canlog import CanLogReader, is_can_log
from shared.captures.errors import CaptureError, MappingError
from shared.captures.mapping import Binding, Mapping
from shared.captures.pcap import PcapReader, is_capture
from shared.devices import ars408
from shared.devices.site import Ars408Radar, RobosenseLidar, SiteFile, VelodyneLidar
from shared.devices.slcan import SlcanServer
from shared.timebase import NS_PER_S

log = logging.getLogger(__name__)

#: A send this much later than due counts as late.
LATE_S = 0.005
SOCKET_URL = "socket://"


@dataclass(frozen=True, slots=True)
class Send:
    """One recorded packet or CAN frame, where it goes."""

    stamp_ns: int  # recorded time
    sensor: str
    payload: bytes
    port: int | None = None  # UDP destination port (lidar); None: a CAN frame
    can_id: int = 0


def _local(bind: str, host: str | None) -> str:
    return host or ("127.0.0.1" if bind in ("0.0.0.0", "") else bind)


def lidar_sends(path: Path, site: SiteFile, mapping: Mapping, counts: Counter[str]) -> Iterator[Send]:
    """A capture's packets of the units the mapping binds, addressed to their sensors' adapters."""
    for d in PcapReader(path):
        kind = identify.packet_kind(d.payload)
        if kind is None:
            counts["skipped/not_lidar"] += 1
            continue
        binding = _unit_binding(mapping, d.src[0], d.dst[1], kind, site)
        if binding is None:
            counts["skipped/unmapped_unit"] += 1
            continue
        device = _device(site, binding.sensor)
        port = _lidar_port(device, kind, binding)
        if port is None:
            counts[f"skipped/{kind}"] += 1
            continue
        yield Send(d.stamp_ns, binding.sensor, d.payload, port=port)


def _unit_binding(mapping: Mapping, address: str, port: int, kind: str, site: SiteFile) -> Binding | None:
    """The unit a packet belongs to: a data packet by its address and port, a DIFOP or a position
    packet (sent to another port) by its address and its unit's family."""
    if kind in ("robosense_msop", "velodyne_data"):
        found = mapping.unit_for(address, port)
        return found[1] if found else None
    family = RobosenseLidar if kind == "robosense_difop" else VelodyneLidar
    at = [b for b in mapping.units_at(address) if isinstance(_device(site, b.sensor), family)]
    if len(at) > 1:
        raise MappingError(
            f"{address}: {len(at)} units of one family at one address: its {kind} cannot be told apart"
        )
    return at[0] if at else None


def _device(site: SiteFile, sensor: str) -> Any:
    try:
        return site.device(sensor)
    except KeyError as exc:
        raise MappingError(f"site {site.site_id}: no device for {sensor} (bound by the mapping)") from exc


def _lidar_port(device: Any, kind: str, binding: Binding) -> int | None:
    if isinstance(device, RobosenseLidar):
        if kind.startswith("velodyne"):
            raise MappingError(
                f"{binding.sensor}: Velodyne packets bound to a Robosense unit ({device.device})"
            )
        return device.difop_port if kind == "robosense_difop" else device.msop_port
    if isinstance(device, VelodyneLidar):
        if kind.startswith("robosense"):
            raise MappingError(
                f"{binding.sensor}: Robosense packets bound to a Velodyne unit ({device.device})"
            )
        return device.data_port if kind == "velodyne_data" else None
    raise MappingError(f"{binding.sensor}: its site device ({device.device}) is no lidar")


def radar_sends(path: Path, site: SiteFile, mapping: Mapping, counts: Counter[str]) -> Iterator[Send]:
    """A CAN log's frames of the radars the mapping binds, with the site's radar ids."""
    bindings = mapping.radar_bindings()
    for b in bindings:
        if not isinstance(_device(site, b.sensor), Ars408Radar):
            raise MappingError(f"{b.sensor}: its site device is no ARS 408")
    for frame in CanLogReader(path):
        if frame.is_error:
            counts["skipped/error_frame"] += 1
            continue
        if frame.is_remote or frame.is_extended:
            counts["skipped/not_ars408"] += 1
            continue
        base, sensor_id = ars408.split_id(frame.can_id)
        for b in bindings:
            if (b.can_id or 0) == sensor_id and (b.channel is None or b.channel == frame.channel):
                spec = site.device(b.sensor)
                assert isinstance(spec, Ars408Radar)
                can_id = ars408.with_sensor(base, spec.can_id)
                data = frame.data
                if base == ars408.ID_STATE and sensor_id != spec.can_id and len(data) >= 5:
                    data = ars408.state_with_sensor_id(data, spec.can_id)  # the state says its id too
                yield Send(round(frame.stamp_s * NS_PER_S), b.sensor, data, can_id=can_id)
                break
        else:
            counts["skipped/unmapped_radar"] += 1


def schedule(
    paths: Sequence[Path], site: SiteFile, mapping: Mapping, counts: Counter[str], align_starts: bool = False
) -> Iterator[Send]:
    """Every input's sends merged by recorded time; with `align_starts`, each input's time counted from
    its own first item (inputs recorded apart, played together)."""
    streams: list[Iterable[Send]] = []
    for p in paths:
        if is_capture(p):
            streams.append(lidar_sends(p, site, mapping, counts))
        elif is_can_log(p):
            streams.append(radar_sends(p, site, mapping, counts))
        else:
            raise CaptureError(f"{p}: replay plays pcap / pcapng captures and CAN logs (.log, .asc, .blf)")
    if align_starts:
        streams = [_from_zero(s) for s in streams]
    return heapq.merge(*streams, key=lambda s: s.stamp_ns)


def _from_zero(sends: Iterable[Send]) -> Iterator[Send]:
    first: int | None = None
    for s in sends:
        first = s.stamp_ns if first is None else first
        yield dataclasses.replace(s, stamp_ns=s.stamp_ns - first)


class _CanSink:
    """A site radar's bus as the replay writes it."""

    def __init__(self, spec: Ars408Radar, host: str | None) -> None:
        self.server: SlcanServer | None = None
        self.bus: Any = None
        if spec.interface == "slcan":
            if not spec.channel.startswith(SOCKET_URL):
                raise MappingError(
                    f"an slcan radar on {spec.channel!r}: replay serves socket:// channels only"
                )
            address, _, port = spec.channel[len(SOCKET_URL) :].rpartition(":")
            self.server = SlcanServer(host or address, int(port))
        else:
            import can

            self.bus = can.Bus(interface=spec.interface, channel=spec.channel)

    @property
    def ready(self) -> bool:
        return self.server is None or self.server.connected

    def send(self, can_id: int, data: bytes) -> bool:
        if self.server is not None:
            return self.server.send([(can_id, data)]) == 1
        import can

        self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        return True

    def close(self) -> None:
        if self.server is not None:
            self.server.close()
        if self.bus is not None:
            self.bus.shutdown()


def _sender_at(sensor: str, unit_address: str) -> socket.socket:
    """A socket sending from `unit_address` (the adapter takes a lidar's packets from there only): one
    of this host's addresses (any 127.x.y.z on loopback), else a CaptureError saying so."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    try:
        sock.bind((unit_address, 0))
    except OSError as exc:
        sock.close()
        raise CaptureError(
            f"{sensor}: the site's unit_address {unit_address} is not an address of this host ({exc}): "
            "its adapter takes the unit's packets from that address only; replay to a site whose units "
            "are at 127.0.0.1, or give this host that address"
        ) from None
    return sock


class Replayer:
    """Plays sends to a site's adapters (module docstring)."""

    def __init__(self, site: SiteFile, sensors: Iterable[str], host: str | None = None) -> None:
        self.site, self.host = site, host
        self.counts: Counter[str] = Counter()
        self.socks: dict[str, socket.socket] = {}  # a lidar's packets leave from its unit_address
        self.can: dict[str, _CanSink] = {}
        try:
            for sensor in sorted(set(sensors)):
                spec = _device(site, sensor)
                if isinstance(spec, Ars408Radar):
                    self.can[sensor] = _CanSink(spec, host)
                elif hasattr(spec, "unit_address"):
                    self.socks[sensor] = _sender_at(sensor, spec.unit_address)
        except Exception as exc:
            self.close()
            if isinstance(exc, CaptureError):
                raise
            raise CaptureError(
                f"site {site.site_id}: a radar's bus does not open ({type(exc).__name__}: {exc})"
            ) from None

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait until every served radar's adapter has connected (it connects as the live one would)."""
        deadline = time.monotonic() + timeout_s
        while not all(c.ready for c in self.can.values()):
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)
        return True

    def play(
        self, sends: Iterable[Send], speed: float = 1.0, stop: threading.Event | None = None
    ) -> Counter[str]:
        """Send everything at its recorded timing (`speed` x); the counts: sent, late, dropped."""
        if speed <= 0:
            raise ValueError(f"speed must be positive, got {speed}")
        start_wall = time.monotonic()
        first_ns: int | None = None
        for s in sends:
            if stop is not None and stop.is_set():
                self.counts["stopped"] += 1
                break
            first_ns = s.stamp_ns if first_ns is None else first_ns
            due = start_wall + (s.stamp_ns - first_ns) / NS_PER_S / speed
            wait = due - time.monotonic()
            if wait > 0:
                if stop is not None and stop.wait(wait):  # Ctrl-C during a long gap stops at once
                    self.counts["stopped"] += 1
                    break
                if stop is None:
                    time.sleep(wait)
            elif wait < -LATE_S:
                self.counts["late"] += 1
            self._send(s)
        return self.counts

    def _send(self, s: Send) -> None:
        if s.port is not None:
            spec = self.site.device(s.sensor)
            self.socks[s.sensor].sendto(s.payload, (_local(getattr(spec, "bind", ""), self.host), s.port))
            self.counts[f"sent/{s.sensor}"] += 1
            return
        if self.can[s.sensor].send(s.can_id, s.payload):
            self.counts[f"sent/{s.sensor}"] += 1
        else:
            self.counts[f"dropped/no_adapter/{s.sensor}"] += 1

    def close(self) -> None:
        for sock in self.socks.values():
            sock.close()
        for sink in self.can.values():
            sink.close()
