"""Site file: what each of the scene's sensors is on a real (or emulated) site.

    site_id: sand_table_wire
    scene: deploy/scenes/sand_table.yaml      # the sensors' ids, agents, poses and rates
    sensors:
      lidar_11: {device: rs16, bind: 127.0.0.1, msop_port: 6699, difop_port: 7788, clock: device}
      lidar_12: {device: vlp16, bind: 0.0.0.0, data_port: 2368}
      radar_2:  {device: ars408, interface: slcan, channel: "socket://127.0.0.1:20002", can_id: 0}
      cam_11:   {device: stream, url: "http://127.0.0.1:8101/stream.mjpg"}

A sensor keeps its scene id (keys, frame ids and calibration stay the scene's); the site file says
which device delivers it, where to listen or connect, and which clock stamps its frames:
- `device`: the unit's own clock (Robosense: the MSOP time, trusted only while DIFOP reports GPS lock;
  an HTTP MJPEG camera: each part's X-Timestamp, as mjpg-streamer and ESP32 camera servers send it);
- `receive`: the host's receive time less `latency_s` (lidar: less one packet's duration as well; CAN:
  the kernel's receive stamp where the interface gives one);
- `cycle` (ARS 408): receive times as above, smoothed over the radar's measurement counter (its cycles
  are regular: shared/devices/stamping.py `CycleFit`).
Sensors the file does not list are not this site's (a sensor group lists all of its sensors, or none).
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from shared.config import ConfigError, read_yaml
from shared.devices.redact import redacted
from shared.devices.robosense import MODELS
from shared.devices.velodyne import DEVICES as VELODYNE_DEVICES
from shared.paths import REPO_ROOT
from shared.scene.model import LidarModel, PoseSpec
from shared.scene.scene import Scene

Clock = Literal["device", "receive"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _ip_address(text: str) -> str:
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        raise ValueError(f"unit_address {text!r} is no IP address") from None


# The address a lidar's packets come from: any other sender's are refused (counted
# `rejected/foreign_sender`), so a host on the lidar network cannot feed or reset the unit's frames.
UnitAddress = Annotated[
    str,
    AfterValidator(_ip_address),
    Field(description="the unit's own IP address; packets from any other sender are refused"),
]


class RobosenseLidar(_Strict):
    device: Literal["rs16", "rs32"]
    unit_address: UnitAddress
    bind: str = Field("0.0.0.0", description="address the adapter listens on")
    msop_port: int = Field(6699, gt=0, lt=65536)
    difop_port: int = Field(7788, gt=0, lt=65536)
    clock: Clock = "receive"
    latency_s: float = Field(0.0, ge=0, le=1)
    min_range_m: float | None = Field(None, ge=0, description="default: the device's")
    max_range_m: float | None = Field(None, gt=0)
    returns: Literal["first", "all"] = Field("first", description="dual-return mode: keep which")

    @model_validator(mode="after")
    def _ports(self) -> RobosenseLidar:
        if self.msop_port == self.difop_port:
            raise ValueError("msop_port and difop_port must differ")
        return self


class VelodyneLidar(_Strict):
    """A Velodyne unit, decoded by the `velodyne-decoder` package (shared/devices/velodyne.py) with the
    unit's own calibration file where given, else the package's bundled one for the model."""

    device: Literal["vlp16", "vlp32c", "hdl32e"]
    unit_address: UnitAddress
    bind: str = Field("0.0.0.0", description="address the adapter listens on")
    data_port: int = Field(2368, gt=0, lt=65536)
    clock: Clock = "receive"  # device: the packets' microseconds past the hour on the host's hour
    latency_s: float = Field(0.0, ge=0, le=1)
    min_range_m: float = Field(0.1, ge=0)
    max_range_m: float = Field(200.0, gt=0)
    calibration_file: Path | None = Field(
        None, description="the unit's own calibration (the ROS velodyne driver's YAML)"
    )


class Ars408Radar(_Strict):
    device: Literal["ars408"]
    interface: Literal["socketcan", "slcan", "udp_multicast", "virtual"] = "socketcan"
    channel: str = Field("can0", description="can0; /dev/ttyACM0@115200 or socket://host:port (slcan)")
    bitrate: int = Field(500_000, gt=0)
    can_id: int = Field(0, ge=0, le=7, description="the radar's sensor id (adds 0x10 x id to every frame)")
    output: Literal["clusters", "objects"] = "clusters"
    # CAN frames carry no time; cycle: receive times smoothed over the lists' measurement counter
    clock: Literal["receive", "cycle"] = "receive"
    latency_s: float = Field(0.0, ge=0, le=1)


class StreamCamera(_Strict):
    device: Literal["stream"]
    url: str = Field(description="rtsp://, http(s)://...mjpg, a V4L2 index or device path, or a video file")
    clock: Clock = "receive"  # device: HTTP MJPEG parts' X-Timestamp (OpenCV gives no sensor clock)
    latency_s: float = Field(0.0, ge=0, le=1)
    reconnect_max_s: float = Field(1.0, gt=0, description="backoff ceiling between reconnects")

    @model_validator(mode="after")
    def _device_clock_over_http(self) -> StreamCamera:
        if self.clock == "device" and not self.url.startswith(("http://", "https://")):
            raise ValueError(
                f"clock: device reads an HTTP MJPEG stream's X-Timestamp; {redacted(self.url)!r} is not http(s)://"
            )
        return self


DeviceSpec = Annotated[
    RobosenseLidar | VelodyneLidar | Ars408Radar | StreamCamera, Field(discriminator="device")
]


class CameraIntrinsics(_Strict):
    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    distortion: list[float] = Field(default_factory=list, description="plumb_bob k1 k2 p1 p2 k3, or empty")


class SensorCalibration(_Strict):
    """One sensor's calibration on this site (what `rmmdet calibrate` writes): its world pose and,
    for a camera, its intrinsics; `note` says how they were obtained (solver, residual, inputs)."""

    pose: PoseSpec | None = None
    intrinsics: CameraIntrinsics | None = None
    note: str = ""


KIND_OF_DEVICE = {
    **dict.fromkeys(MODELS, "lidar"),
    **dict.fromkeys(VELODYNE_DEVICES, "lidar"),
    "ars408": "radar",
    "stream": "camera",
}


class SiteFile(_Strict):
    site_id: str
    scene: Path
    sensors: dict[str, DeviceSpec] = Field(default_factory=dict)
    calibration: dict[str, SensorCalibration] = Field(default_factory=dict)

    @classmethod
    def load(cls, path: Path) -> SiteFile:
        """The site file at `path`; ConfigError naming the file and the field for anything wrong."""
        try:
            site = cls.model_validate(read_yaml(Path(path)))
        except ValidationError as err:
            raise ConfigError(f"{path}: invalid site file: {err}") from None
        if not site.scene.is_absolute():
            site = site.model_copy(update={"scene": REPO_ROOT / site.scene})
        return site

    def device(self, sensor_id: str) -> RobosenseLidar | VelodyneLidar | Ars408Radar | StreamCamera:
        try:
            return self.sensors[sensor_id]
        except KeyError:
            raise KeyError(f"site {self.site_id}: no device for sensor {sensor_id!r}") from None

    def simulated_scene(self, scene: Scene) -> Scene:
        """`scene` as the simulator must render it to stand in for this site's devices: each lidar the
        site names as a Robosense unit fires that unit's rays (`LidarModel.device`; its pose, rate,
        ranges and noise stay the scene's)."""
        sensors = []
        for spec in scene.spec.sensors:
            device = self.sensors.get(spec.id)
            if (
                isinstance(device, RobosenseLidar)
                and spec.lidar is not None
                and spec.lidar.device != device.device
            ):
                values = spec.lidar.model_dump(exclude={"vertical_min_rad", "vertical_max_rad"})
                values |= {"device": device.device, "channels": MODELS[device.device].lasers}
                spec = spec.model_copy(update={"lidar": LidarModel.model_validate(values)})
            sensors.append(spec)
        return Scene(scene.spec.model_copy(update={"sensors": sensors}), source=scene.source)

    def calibrated_scene(self, scene: Scene) -> Scene:
        """`scene` with this site's calibration: poses and camera intrinsics replaced where given."""
        sensors = []
        for spec in scene.spec.sensors:
            cal = self.calibration.get(spec.id)
            if cal is not None:
                update: dict[str, object] = {}
                if cal.pose is not None:
                    update["pose"] = cal.pose
                if cal.intrinsics is not None:
                    if spec.camera is None:
                        raise ValueError(f"site {self.site_id}: {spec.id} is no camera: it has no intrinsics")
                    i = cal.intrinsics
                    update["camera"] = spec.camera.model_copy(
                        update={
                            "intrinsics_px": (i.fx_px, i.fy_px, i.cx_px, i.cy_px),
                            "distortion": i.distortion,
                        }
                    )
                spec = spec.model_copy(update=update)
            sensors.append(spec)
        return Scene(scene.spec.model_copy(update={"sensors": sensors}), source=scene.source)

    def save(self, path: Path) -> None:
        """Write the site file (the scene path as given, relative to the repository when inside it)."""
        data = self.model_dump(mode="json", exclude_defaults=False)
        try:
            data["scene"] = str(Path(self.scene).relative_to(REPO_ROOT))
        except ValueError:
            data["scene"] = str(self.scene)
        Path(path).write_text(yaml.safe_dump(data, sort_keys=False))

    def check_against(self, scene_sensor_kinds: dict[str, str]) -> None:
        """ValueError unless every listed sensor is in the scene and its device is of its kind."""
        for sensor_id in self.calibration:
            if sensor_id not in scene_sensor_kinds:
                raise ValueError(
                    f"site {self.site_id}: calibration of {sensor_id}, not a sensor of the scene"
                )
        for sensor_id, spec in self.sensors.items():
            kind = scene_sensor_kinds.get(sensor_id)
            if kind is None:
                raise ValueError(f"site {self.site_id}: {sensor_id} is not a sensor of the scene")
            if KIND_OF_DEVICE[spec.device] != kind:
                raise ValueError(f"site {self.site_id}: {sensor_id} is a {kind}, {spec.device} is not")
