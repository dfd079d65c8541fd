"""The mapping file of `rmmdet import` / `rmmdet devices replay`: which recorded source feeds which of
the scene's sensors, and what device it is where its bytes do not say.

    topics:                                  # ROS 1 / ROS 2 bags, by topic
      /rslidar_packets: lidar_11             # the model from the unit's DIFOP
      /rslidar_packets_difop: lidar_11
      /velodyne_packets: {sensor: lidar_12, calibration: VLP16.yaml}   # the unit's own file
      /camera/image_raw: cam_11
      /can_tx: [{sensor: radar_21, can_id: 0}, {sensor: radar_22, can_id: 1}]
    units:                                   # pcap / pcapng, by source address [: destination port]
      192.168.1.200: lidar_11
      192.168.1.201:2370: {sensor: lidar_12, device: vlp16}
    radars:                                  # CAN logs: a radar by its sensor id (and channel)
      radar_21: {can_id: 0, channel: can1}

`device` is needed only where the bytes do not say it (shared/captures/identify.py); given and
contradicted by the bytes, the import stops naming both. Paths in the file are relative to it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from shared.captures.errors import MappingError
from shared.devices import robosense, velodyne
from shared.scene.scene import Scene

LIDAR_DEVICES = (*sorted(robosense.MODELS), *velodyne.DEVICES)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Binding(_Strict):
    """One recorded source bound to a scene sensor."""

    sensor: str
    device: str | None = Field(
        None, description="rs16 | rs32 | vlp16 | vlp32c | hdl32e, if the bytes do not say"
    )
    calibration: Path | None = Field(None, description="a Velodyne unit's own calibration file")
    can_id: int | None = Field(None, ge=0, le=7, description="an ARS 408's sensor id (frames of that radar)")
    channel: str | None = Field(None, description="a CAN log's channel ('can1', '1'); any when unset")

    @field_validator("device")
    @classmethod
    def _known_device(cls, value: str | None) -> str | None:
        if value is not None and value not in LIDAR_DEVICES:
            raise ValueError(f"device {value!r} is none of {list(LIDAR_DEVICES)}")
        return value


class Mapping(_Strict):
    topics: dict[str, list[Binding]] = Field(default_factory=dict)
    units: dict[str, Binding] = Field(default_factory=dict)
    radars: dict[str, Binding] = Field(default_factory=dict)

    @field_validator("topics", mode="before")
    @classmethod
    def _topic_lists(cls, value: Any) -> Any:
        if not isinstance(value, dict):
            return value
        return {str(t): v if isinstance(v, list) else [v] for t, v in value.items()}

    @field_validator("topics", "units", "radars", mode="before")
    @classmethod
    def _short_form(cls, value: Any, info: ValidationInfo) -> Any:
        """`<key>: <sensor id>` is `<key>: {sensor: <sensor id>}`; under `radars:` the key is the sensor."""
        if not isinstance(value, dict):
            return value

        def one(key: str, v: Any) -> Any:
            if isinstance(v, str):
                return {"sensor": v}
            if info.field_name == "radars" and isinstance(v, dict):
                return {"sensor": key, **v}
            return v

        return {
            str(k): [one(str(k), x) for x in v] if isinstance(v, list) else one(str(k), v)
            for k, v in value.items()
        }

    def sensors(self) -> set[str]:
        bound = [b for bs in self.topics.values() for b in bs]
        return {b.sensor for b in [*bound, *self.units.values()]} | set(self.radars)

    def unit_for(self, address: str, port: int) -> tuple[str, Binding] | None:
        """The `units:` entry of a data packet from `address` to `port`: `address:port`, else `address`."""
        for key in (f"{address}:{port}", address):
            if key in self.units:
                return key, self.units[key]
        return None

    def units_at(self, address: str) -> list[Binding]:
        """Every `units:` entry of `address` (a DIFOP or a position packet goes to another port than its
        unit's data: it belongs to the unit at its address)."""
        return [b for key, b in self.units.items() if key == address or key.rpartition(":")[0] == address]

    def radar_bindings(self) -> list[Binding]:
        """The `radars:` section's bindings."""
        return list(self.radars.values())


def load_mapping(path: Path | None, scene: Scene) -> Mapping | None:
    """The mapping at `path` checked against `scene` (None: no mapping given); MappingError naming the
    file and what is wrong."""
    if path is None:
        return None
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise MappingError(f"{path}: {exc}") from None
    if not isinstance(data, dict):
        raise MappingError(f"{path}: expected `topics:`, `units:` and / or `radars:` sections")
    try:
        mapping = Mapping.model_validate(data)
    except ValidationError as err:
        raise MappingError(f"{path}: {err}") from None
    unknown = sorted(s for s in mapping.sensors() if s not in scene.sensors)
    if unknown:
        raise MappingError(f"{path}: sensor(s) {unknown} are not in scene {scene.scene_id}")
    return _relative_to(mapping, path.parent)


def _relative_to(mapping: Mapping, base: Path) -> Mapping:
    """Calibration paths given relative to the mapping file, made absolute."""

    def fix(b: Binding) -> Binding:
        if b.calibration is None or b.calibration.is_absolute():
            return b
        return b.model_copy(update={"calibration": base / b.calibration})

    return mapping.model_copy(
        update={
            "topics": {t: [fix(b) for b in bs] for t, bs in mapping.topics.items()},
            "units": {u: fix(b) for u, b in mapping.units.items()},
            "radars": {r: fix(b) for r, b in mapping.radars.items()},
        }
    )
