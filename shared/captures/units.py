"""A recorded unit's packets or CAN frames -> the messages its scene sensor publishes, through the
decoders the live adapters use (shared/devices: Robosense `LidarStream`, Velodyne `VelodyneStream`,
ARS 408 `ListAssembler`), so an imported recording holds what the device service would have sent.

Stamps: a lidar frame gets its packets' capture (receive) time as the live adapters' `receive` clock
does (Robosense: the frame's last packet less one packet's duration; Velodyne: its first packet's);
a radar list the capture time of its status frame. Every decoder counts what it refuses (`counters`).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Protocol

from google.protobuf.message import Message

from shared.captures import identify
from shared.captures.errors import MappingError
from shared.captures.mapping import Binding
from shared.devices import ars408, robosense, velodyne
from shared.devices.sources import lidar_frame_message, radar_scan_message, velodyne_scan_message
from shared.timebase import NS_PER_S

Out = list[tuple[Message, int]]  # (message, stamp ns)
#: A radar's frames held until its first RadarState says how to read its lists: about 30 s of a full
#: object list at 14 Hz (a log whose radar never sends its state is refused by count, not by memory).
MAX_HELD_FRAMES = 100_000


class PacketUnit(Protocol):
    sensor: str

    def on_packet(self, payload: bytes, stamp_ns: int) -> Out: ...

    def counters(self) -> dict[str, int]: ...


class RobosenseUnit:
    """MSOP and DIFOP packets of one RS-LiDAR (told apart by their ids, whatever port they came on)."""

    def __init__(self, sensor: str, device: str, returns: str = "first") -> None:
        if device not in robosense.MODELS:
            raise MappingError(f"{sensor}: Robosense device {device!r} is none of {sorted(robosense.MODELS)}")
        self.sensor, self.device, self.returns = sensor, device, returns
        self.stream = robosense.LidarStream(robosense.MODELS[device], robosense.StampClock.RECEIVE)

    def on_packet(self, payload: bytes, stamp_ns: int) -> Out:
        if payload[:8] == robosense.DIFOP_ID:
            self.stream.on_difop(payload)
            return []
        frames = self.stream.on_msop(payload, stamp_ns)
        return [(lidar_frame_message(f, self.sensor, self.returns), f.stamp_ns) for f in frames]

    def finish(self) -> None:
        """The recording ended: a frame still open is incomplete (counted by the stream)."""
        self.stream.expire()

    def counters(self) -> dict[str, int]:
        return dict(self.stream.counters)


class VelodyneUnit:
    """Data packets of one Velodyne; position packets (GPS) are counted, not decoded."""

    def __init__(self, sensor: str, device: str, calibration: Path | None = None) -> None:
        try:
            self.stream = velodyne.VelodyneStream(device, calibration=calibration)
        except ValueError as exc:
            raise MappingError(f"{sensor}: {exc}") from None
        self.sensor, self.device = sensor, device
        self.position_packets = 0

    def on_packet(self, payload: bytes, stamp_ns: int) -> Out:
        if len(payload) == velodyne.POSITION_PACKET_BYTES:
            self.position_packets += 1
            return []
        scan = self.stream.on_packet(payload, stamp_ns)
        if scan is None:
            return []
        return [(velodyne_scan_message(scan, self.sensor, scan.host_ns), scan.host_ns)]

    def finish(self) -> None:
        """velodyne-decoder holds the last partial revolution: it is not a scan (nothing to emit)."""

    def counters(self) -> dict[str, int]:
        return dict(self.stream.counters) | (
            {"position_packets": self.position_packets} if self.position_packets else {}
        )


def radar_config_from_state(state: ars408.RadarState) -> ars408.RadarConfig:
    """The configuration a recorded radar ran with, as its RadarState frame reports it."""
    output = ars408.OutputType(state.output)
    return ars408.RadarConfig(
        sensor_id=state.sensor_id,
        output=output,
        send_quality=state.send_quality,
        send_extended=state.send_extended,
    )


class RadarUnit:
    """CAN frames of one ARS 408 (its sensor id's frames) -> detection lists, assembled by the live
    adapter's ListAssembler. The lists' layout (objects or clusters, quality and extended frames) is
    the radar's own, read from the RadarState frames of the log; until one comes, frames are held
    back (a log that holds none is refused: without it the lists cannot be read)."""

    def __init__(self, sensor: str, can_id: int) -> None:
        self.sensor, self.can_id = sensor, can_id
        self.assembler: ars408.ListAssembler | None = None
        self._held: list[tuple[int, bytes, float]] = []
        self._counts: Counter[str] = Counter()

    def on_frame(self, can_id: int, data: bytes, stamp_s: float) -> Out:
        base, _ = ars408.split_id(can_id)
        assembler = self.assembler
        if assembler is not None and base != ars408.ID_STATE:  # the usual frame: straight to the lists
            return self._assemble(can_id, data, stamp_s)
        if base == ars408.ID_STATE and (assembler is None or not assembler.configured):
            try:
                state = ars408.decode_state(data)
            except ValueError:
                self._counts["rejected/short/state"] += 1
                return []
            if state.output not in ars408.OutputType._value2member_map_:
                self._counts["rejected/state/output"] += 1
                return []
            self.assembler = ars408.ListAssembler(radar_config_from_state(state))
            held, self._held = self._held, []
            out: Out = []
            for frame in [*held, (can_id, data, stamp_s)]:
                out += self._assemble(*frame)
            return out
        if self.assembler is None:
            if len(self._held) < MAX_HELD_FRAMES:
                self._held.append((can_id, data, stamp_s))
            else:
                self._counts["rejected/before_radar_state"] += 1
            return []
        return self._assemble(can_id, data, stamp_s)

    def on_error_frame(self, error_class: int) -> None:
        if self.assembler is not None:
            self.assembler.on_error_frame(error_class)
        else:
            self._counts["can/error_frames"] += 1

    def _assemble(self, can_id: int, data: bytes, stamp_s: float) -> Out:
        assert self.assembler is not None
        lists = self.assembler.on_frame(can_id, data, stamp_s)
        return [(radar_scan_message(d, self.sensor), round(d.stamp_s * NS_PER_S)) for d in lists]

    def finish(self) -> None:
        if self.assembler is None and self._held:
            self._counts["rejected/no_radar_state"] += len(self._held)

    def counters(self) -> dict[str, int]:
        return dict(self._counts + Counter(self.assembler.counters if self.assembler is not None else {}))


def lidar_unit(
    binding: Binding, robosense_difop: bytes | None, velodyne_model: str | None, where: str
) -> RobosenseUnit | VelodyneUnit:
    """The decoder of one recorded lidar: the family its packets show, the model its bytes say (else the
    mapping's); MappingError when neither says, or they disagree."""
    if velodyne_model is not None or (binding.device or "").startswith(("vlp", "hdl")):
        device = _model(binding.device, velodyne_model, where)
        return VelodyneUnit(binding.sensor, device, binding.calibration)
    said = identify.robosense_model(robosense_difop) if robosense_difop is not None else None
    device = _model(binding.device, said, where)
    return RobosenseUnit(binding.sensor, device)


def _model(given: str | None, said: str | None, where: str) -> str:
    if given is not None and said is not None and given != said:
        raise MappingError(f"{where}: the mapping says {given}, the unit's packets say {said}")
    device = given or said
    if device is None:
        raise MappingError(
            f"{where}: the packets do not say which model this is: give `device:` in the mapping"
        )
    return device
