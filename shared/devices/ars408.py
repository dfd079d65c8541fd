"""Continental ARS 408-21 over CAN: configuration, state and detection lists (objects or clusters).

The signal layouts live in one place, the DBC beside this file (written for this project from the
documented layouts, `docs/references.md` "ARS 408"), loaded with cantools. Configuration
(0x200) is encoded and the radar's state (0x201) decoded with cantools message by message; list
frames are collected as they come and decoded together when the list is complete, with numpy from the
same DBC's signal definitions (`BatchDecoder`: a full 100-object list is 301 frames; cantools takes
about 5 us a frame, numpy a few us a list).

A list: the status frame (objects: 0x60A with the number of objects and the measurement counter;
clusters: 0x600 with the near and far counts) opens it, then one general frame per detection (0x60B /
0x701), then, if the radar was configured to send them, one quality frame each (0x60C / 0x702) and, for
objects, one extended frame each (0x60D). It is complete when every expected frame arrived; a status
frame that arrives before that closes the open list as incomplete (counted, emitted with what came, so
a lost frame costs one detection, not a scan). Sensor n (0-7) adds 0x10 n to every identifier.

Coordinates: DistLong forward along boresight, DistLat to the left, metres (ISO 8855, as the radar's
documentation and Apollo's conti_radar use them); VrelLong / VrelLat the relative velocity, m/s; RCS in
dBm^2.

Where public decoders disagree (each tested in tests/shared/devices/test_ars408.py):
- Obj_0_Status MeasCounter: the DBC has bytes 1-2 (start bit 15, 16 bits); Apollo reads bytes 2-3 and
  tier4 bytes 2 | 3 << 8. Bytes 1-2 kept: in a 4-byte frame whose byte 0 is the object count and whose
  byte 3 holds InterfaceVersion (bits 31-28), only bytes 1-2 leave both intact.
- Obj_2_Quality ProbOfExist: the DBC and Apollo read byte 6 bits 7-5; tier4 read bits 4-2, which the
  DBC gives Obj_MeasState. DBC kept.
- RadarState RCS_Threshold: the DBC has byte 7 bits 4-2; tier4's C++ driver read byte 5 (fixed in its
  PRs #35 / #37). DBC kept.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cantools
import numpy as np

DBC_PATH = Path(__file__).with_name("ars408.dbc")
SENSOR_ID_MASK = 0x70
MAX_SENSOR_ID = 7
CAN_MAX_DLC = 8
# Linux CAN error frame class bits (linux/can/error.h), in a python-can error frame's arbitration id.
CAN_ERR_BUSOFF = 0x040
CAN_ERR_RESTARTED = 0x100

ID_CONFIG = 0x200
ID_STATE = 0x201
ID_CLUSTER_STATUS = 0x600
ID_CLUSTER_GENERAL = 0x701
ID_CLUSTER_QUALITY = 0x702
ID_OBJECT_STATUS = 0x60A
ID_OBJECT_GENERAL = 0x60B
ID_OBJECT_QUALITY = 0x60C
ID_OBJECT_EXTENDED = 0x60D


def quantisation_noise(typical_range_m: float) -> tuple[float, float, float]:
    """(range m, azimuth rad at `typical_range_m`, range rate m/s) standard deviations of the ARS 408's
    quantisation: what a tracker should expect of its detections at least. A detection is off by up to
    half a step (the DBC's factors of Cluster_DistLong and Cluster_VrelLong), uniformly: step / sqrt(12)."""
    general = database().get_message_by_frame_id(ID_CLUSTER_GENERAL)
    dist_step = float(general.get_signal_by_name("Cluster_DistLong").scale)
    vrel_step = float(general.get_signal_by_name("Cluster_VrelLong").scale)
    per_axis = dist_step / math.sqrt(12)
    return per_axis, per_axis / typical_range_m, vrel_step / math.sqrt(12)


#: Obj_ProbOfExist index -> probability (DBC value table / Apollo const_vars.h).
PROB_OF_EXIST = (0.0, 0.25, 0.5, 0.75, 0.9, 0.99, 0.999, 1.0)


class OutputType(enum.IntEnum):
    NONE = 0
    OBJECTS = 1
    CLUSTERS = 2


_DB: cantools.database.can.Database | None = None


def database() -> cantools.database.can.Database:
    """The project's ARS 408 DBC (loaded once)."""
    global _DB
    if _DB is None:
        db = cantools.database.load_file(DBC_PATH, database_format="dbc")
        assert isinstance(db, cantools.database.can.Database)
        _DB = db
    return _DB


def split_id(can_id: int) -> tuple[int, int]:
    """(sensor-0 identifier, sensor id) of a frame from radar `sensor id` (tier4 SensorIdFromCanId)."""
    return can_id & ~SENSOR_ID_MASK, (can_id & SENSOR_ID_MASK) >> 4


def with_sensor(base_id: int, sensor_id: int) -> int:
    if not 0 <= sensor_id <= MAX_SENSOR_ID:
        raise ValueError(f"sensor id {sensor_id} is not 0..{MAX_SENSOR_ID}")
    return base_id | (sensor_id << 4)


@dataclass(frozen=True)
class RadarConfig:
    """What the adapter asks of the radar at start (0x200) and checks in its state (0x201)."""

    sensor_id: int = 0
    output: OutputType = OutputType.CLUSTERS
    send_quality: bool = True
    send_extended: bool = True
    max_distance_m: int | None = None  # None: leave the radar's own
    radar_power: int | None = None
    rcs_threshold: int | None = None  # 0 standard, 1 high sensitivity

    def frame(self) -> tuple[int, bytes]:
        """(CAN id, payload) of the RadarConfiguration message setting this configuration; fields left
        None are sent with their valid bit clear (the radar keeps its own). Not stored in NVM."""
        values = {s.name: 0 for s in database().get_message_by_frame_id(ID_CONFIG).signals}
        values |= {
            "RadarCfg_OutputType_valid": 1,
            "RadarCfg_OutputType": int(self.output),
            "RadarCfg_SendQuality_valid": 1,
            "RadarCfg_SendQuality": int(self.send_quality),
            "RadarCfg_SendExtInfo_valid": 1,
            "RadarCfg_SendExtInfo": int(self.send_extended),
        }
        if self.max_distance_m is not None:
            values |= {"RadarCfg_MaxDistance_valid": 1, "RadarCfg_MaxDistance": self.max_distance_m}
        if self.radar_power is not None:
            values |= {"RadarCfg_RadarPower_valid": 1, "RadarCfg_RadarPower": self.radar_power}
        if self.rcs_threshold is not None:
            values |= {"RadarCfg_RCS_Threshold_Valid": 1, "RadarCfg_RCS_Threshold": self.rcs_threshold}
        data = database().encode_message(ID_CONFIG, values, strict=True)
        return with_sensor(ID_CONFIG, self.sensor_id), bytes(data)


@dataclass(frozen=True)
class RadarState:
    """The radar's state message (0x201), as far as the adapter checks it."""

    sensor_id: int
    output: int
    send_quality: bool
    send_extended: bool
    max_distance_m: float
    rcs_threshold: int
    errors: tuple[str, ...]  # the error flags that are set

    def mismatches(self, config: RadarConfig) -> list[str]:
        """Which asked-for settings the radar does not report (empty: configuration confirmed)."""
        wrong = []
        if self.sensor_id != config.sensor_id:
            wrong.append(f"sensor_id {self.sensor_id}")
        if self.output != config.output:
            wrong.append(f"output {self.output}")
        if self.send_quality != config.send_quality:
            wrong.append(f"send_quality {self.send_quality}")
        if self.send_extended != config.send_extended:
            wrong.append(f"send_extended {self.send_extended}")
        return wrong


_STATE_ERRORS = (
    "RadarState_Persistent_Error",
    "RadarState_Interference",
    "RadarState_Temperature_Error",
    "RadarState_Temporary_Error",
    "RadarState_Voltage_Error",
)


def state_with_sensor_id(data: bytes, sensor_id: int) -> bytes:
    """A RadarState payload with its RadarState_SensorID set (the DBC's `34|3@0+`: byte 4, bits 2-0),
    every other bit kept: a recorded radar's state as the same radar configured with another id."""
    if not 0 <= sensor_id <= MAX_SENSOR_ID or len(data) < 5:
        raise ValueError(f"sensor id {sensor_id} into a {len(data)}-byte RadarState")
    out = bytearray(data)
    out[4] = (out[4] & ~0x07) | sensor_id
    return bytes(out)


def decode_state(data: bytes) -> RadarState:
    """A RadarState payload; ValueError if it is too short."""
    if len(data) < database().get_message_by_frame_id(ID_STATE).length:
        raise ValueError(f"RadarState needs 8 bytes, got {len(data)}")
    v = {name: values[0] for name, values in BatchDecoder(ID_STATE).decode([data]).items()}
    return RadarState(
        sensor_id=int(v["RadarState_SensorID"]),
        output=int(v["RadarState_OutputTypeCfg"]),
        send_quality=bool(v["RadarState_SendQualityCfg"]),
        send_extended=bool(v["RadarState_SendExtInfoCfg"]),
        max_distance_m=float(v["RadarState_MaxDistanceCfg"]),
        rcs_threshold=int(v["RadarState_RCS_Threshold"]),
        errors=tuple(name.removeprefix("RadarState_") for name in _STATE_ERRORS if v[name]),
    )


class BatchDecoder:
    """Decode many payloads of one message at once from the DBC's signal layouts (Motorola unsigned
    signals, as all of the ARS 408's are): payload -> 64-bit big-endian integer -> shift and mask."""

    def __init__(self, frame_id: int) -> None:
        message = database().get_message_by_frame_id(frame_id)
        self.length = message.length
        self.signals: list[tuple[str, int, int, float, float]] = []
        for s in message.signals:
            if s.byte_order != "big_endian" or s.is_signed:
                raise ValueError(f"{s.name}: only Motorola unsigned signals are batch-decoded")
            msb = 8 * (s.start // 8) + (7 - s.start % 8)  # bit index counted from byte 0's MSB
            shift = 64 - (msb + s.length)
            self.signals.append((s.name, shift, (1 << s.length) - 1, float(s.scale), float(s.offset)))

    def decode(self, payloads: list[bytes]) -> dict[str, np.ndarray]:
        """Physical values (raw * scale + offset) of every signal, one array each; payloads shorter
        than 8 bytes are zero-padded (the caller refuses those shorter than the message)."""
        joined = b"".join(p[:CAN_MAX_DLC].ljust(CAN_MAX_DLC, b"\0") for p in payloads)
        words = np.frombuffer(joined, ">u8")
        return {
            name: ((words >> np.uint64(shift)) & np.uint64(mask)).astype(np.float64) * scale + offset
            for name, shift, mask, scale, offset in self.signals
        }


@dataclass(frozen=True)
class Detections:
    """One complete (or closed incomplete) list, in the radar frame."""

    kind: OutputType
    sensor_id: int
    meas_counter: int
    stamp_s: float  # receive time of the list's status frame (the CAN frames carry no time)
    ids: np.ndarray  # (N,) int
    dist_long_m: np.ndarray
    dist_lat_m: np.ndarray
    vrel_long_mps: np.ndarray
    vrel_lat_mps: np.ndarray
    rcs_dbsm: np.ndarray
    dyn_prop: np.ndarray  # int
    prob_exist: np.ndarray  # objects: probability of existence (nan: no quality frame); clusters: nan
    complete: bool
    expected: int  # detections the status frame announced

    def __len__(self) -> int:
        return len(self.ids)

    def polar(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Range (m), azimuth (rad, left positive) and range rate (m/s, the relative velocity along the
        line of sight) of each detection."""
        x, y = self.dist_long_m, self.dist_lat_m
        rng = np.hypot(x, y)
        with np.errstate(invalid="ignore", divide="ignore"):
            rate = np.where(rng > 0, (x * self.vrel_long_mps + y * self.vrel_lat_mps) / rng, 0.0)
        return rng, np.arctan2(y, x), rate


@dataclass
class _OpenList:
    kind: OutputType
    counter: int
    stamp_s: float
    expected: int
    general: list[bytes] = field(default_factory=list)
    quality: list[bytes] = field(default_factory=list)
    extended: list[bytes] = field(default_factory=list)


class ListAssembler:
    """CAN frames of one radar in, complete detection lists out; every refused frame counted by reason.

    Parameters
    ----------
    config : RadarConfig
        The radar's id and the frames each list brings (quality / extended as configured).
    """

    def __init__(self, config: RadarConfig) -> None:
        self.config = config
        self.counters: dict[str, int] = {}
        self.state: RadarState | None = None
        self.bus_off = False
        self._open: _OpenList | None = None
        objects = config.output is OutputType.OBJECTS
        self._status_id = ID_OBJECT_STATUS if objects else ID_CLUSTER_STATUS
        self._parts = (
            {ID_OBJECT_GENERAL: "general", ID_OBJECT_QUALITY: "quality", ID_OBJECT_EXTENDED: "extended"}
            if objects
            else {ID_CLUSTER_GENERAL: "general", ID_CLUSTER_QUALITY: "quality"}
        )
        self._batch = {
            i: BatchDecoder(i)
            for i in (
                ID_OBJECT_STATUS,
                ID_OBJECT_GENERAL,
                ID_OBJECT_QUALITY,
                ID_OBJECT_EXTENDED,
                ID_CLUSTER_STATUS,
                ID_CLUSTER_GENERAL,
                ID_CLUSTER_QUALITY,
            )
        }
        self._lengths = {i: b.length for i, b in self._batch.items()}

    def _count(self, reason: str, n: int = 1) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + n

    @property
    def configured(self) -> bool:
        """The radar's last state matches what was asked of it."""
        return self.state is not None and not self.state.mismatches(self.config)

    def on_error_frame(self, error_class: int) -> None:
        """A CAN error frame (python-can `is_error_frame`; its id holds the Linux error class)."""
        self._count("can/error_frames")
        if error_class & CAN_ERR_BUSOFF:
            self._count("can/bus_off")
            self.bus_off = True
        if error_class & CAN_ERR_RESTARTED:
            self.bus_off = False

    def on_frame(self, can_id: int, data: bytes, stamp_s: float) -> list[Detections]:
        """One data frame received at `stamp_s`; the lists it completed or closed."""
        base, sensor = split_id(can_id)
        if sensor != self.config.sensor_id:
            self._count("rejected/other_sensor")
            return []
        self.bus_off = False  # frames flow: the controller is back on the bus
        kind = self.config.output
        if base == ID_STATE:
            try:
                self.state = decode_state(data)
            except ValueError:
                self._count("rejected/short/state")
                return []
            self._count("state")
            return []
        status_id, parts = self._status_id, self._parts
        if base != status_id and base not in parts:
            self._count("ignored/other_message")
            return []
        if len(data) < self._lengths[base]:
            self._count("rejected/short")
            return []
        out: list[Detections] = []
        if base == status_id:
            if self._open is not None:
                self._count("lists/incomplete")
                out.append(self._close(self._open, complete=False))
            v = self._batch[base].decode([data])
            if kind is OutputType.OBJECTS:
                expected, counter = int(v["Obj_NofObjects"][0]), int(v["Obj_MeasCounter"][0])
            else:
                expected = int(v["Cluster_NofClustersNear"][0] + v["Cluster_NofClustersFar"][0])
                counter = int(v["Cluster_MeasCounter"][0])
            self._open = _OpenList(kind, counter, stamp_s, expected)
        else:
            current = self._open
            if current is None:
                self._count("rejected/no_status")
                return out
            frames: list[bytes] = getattr(current, parts[base])
            if len(frames) >= current.expected:
                self._count("rejected/beyond_count")
                return out
            frames.append(data)
        current = self._open
        if current is not None and self._is_complete(current):
            out.append(self._close(current, complete=True))
        return out

    def _is_complete(self, lst: _OpenList) -> bool:
        n = lst.expected
        if len(lst.general) < n:
            return False
        if self.config.send_quality and len(lst.quality) < n:
            return False
        return not (lst.kind is OutputType.OBJECTS and self.config.send_extended and len(lst.extended) < n)

    def _close(self, lst: _OpenList, complete: bool) -> Detections:
        self._open = None
        self._count("lists" if complete else "lists/closed_incomplete")
        objects = lst.kind is OutputType.OBJECTS
        general_id = ID_OBJECT_GENERAL if objects else ID_CLUSTER_GENERAL
        g = self._batch[general_id].decode(lst.general)
        prefix = "Obj_" if objects else "Cluster_"
        ids = g[f"{prefix}ID"].astype(np.int64)
        prob = np.full(len(ids), np.nan)
        if lst.quality:
            q = self._batch[ID_OBJECT_QUALITY if objects else ID_CLUSTER_QUALITY].decode(lst.quality)
            # quality frame of each id (ids are one byte): -1 where none came
            row_of = np.full(256, -1, np.int64)
            row_of[q[f"{prefix}ID"].astype(np.int64)] = np.arange(len(lst.quality))
            rows = row_of[ids]
            unmatched = int(np.count_nonzero(rows < 0))
            if unmatched:
                self._count("rejected/quality_without_general", unmatched)
            # Clusters carry a false-alarm bucket (Cluster_PdH0) whose value table is not in the
            # documents at hand: left unread (nan) rather than guessed.
            if objects:
                have = rows >= 0
                prob[have] = np.asarray(PROB_OF_EXIST)[q["Obj_ProbOfExist"][rows[have]].astype(np.int64)]
        return Detections(
            kind=lst.kind,
            sensor_id=self.config.sensor_id,
            meas_counter=lst.counter,
            stamp_s=lst.stamp_s,
            ids=ids,
            dist_long_m=g[f"{prefix}DistLong"],
            dist_lat_m=g[f"{prefix}DistLat"],
            vrel_long_mps=g[f"{prefix}VrelLong"],
            vrel_lat_mps=g[f"{prefix}VrelLat"],
            rcs_dbsm=g[f"{prefix}RCS"],
            dyn_prop=g[f"{prefix}DynProp"].astype(np.int64),
            prob_exist=prob,
            complete=complete,
            expected=lst.expected,
        )

    def decoded_state(self) -> dict[str, Any]:
        """For health: configured?, bus-off?, the radar's error flags."""
        return {
            "configured": self.configured,
            "bus_off": self.bus_off,
            "errors": list(self.state.errors) if self.state else [],
        }
