"""Scene file schema: road network, areas, agents and sensors of the sand table (one YAML file).

Everything spatial in the system derives from this file: no offset is hard-coded anywhere else.
Units: table metres, radians, Hz. World frame: z up, yaw counter-clockwise from +x.

Sensor poses are full SE(3) world poses of the sensor *body* frame (+x forward, +y left, +z up), given
either as `rpy_rad` (URDF convention R = Rz(yaw) Ry(pitch) Rx(roll)) or as a unit quaternion
`quat_xyzw`. Camera intrinsics are derived from resolution and horizontal field of view.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

Id = Annotated[str, StringConstraints(pattern=r"^[a-z0-9][a-z0-9_\-]{0,63}$")]
Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
SensorKindName = Literal["camera", "lidar", "radar"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PoseSpec(_Strict):
    position_m: Vec3
    rpy_rad: Vec3 | None = Field(None, description="roll, pitch, yaw (URDF: R = Rz Ry Rx)")
    quat_xyzw: tuple[float, float, float, float] | None = Field(None, description="unit quaternion")

    @model_validator(mode="after")
    def _one_orientation(self) -> PoseSpec:
        if (self.rpy_rad is None) == (self.quat_xyzw is None):
            raise ValueError("give exactly one of rpy_rad or quat_xyzw")
        values = [*self.position_m, *(self.rpy_rad or ()), *(self.quat_xyzw or ())]
        if not all(math.isfinite(v) for v in values):
            raise ValueError("pose values must be finite")
        if self.quat_xyzw is not None and abs(math.fsum(q * q for q in self.quat_xyzw) - 1.0) > 1e-6:
            raise ValueError("quat_xyzw must be a unit quaternion")
        return self


class CameraModel(_Strict):
    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)
    hfov_rad: float = Field(gt=0, lt=math.pi, description="horizontal field of view")
    distortion: list[float] = Field(default_factory=list, description="plumb_bob k1 k2 p1 p2 k3, or empty")
    near_m: float = Field(0.02, gt=0, description="render clip plane")
    far_m: float = Field(30.0, gt=0, description="render clip plane")

    @model_validator(mode="after")
    def _check(self) -> CameraModel:
        if self.distortion and len(self.distortion) not in (4, 5):
            raise ValueError("distortion needs 4 or 5 plumb_bob coefficients")
        if self.far_m <= self.near_m:
            raise ValueError("far_m must exceed near_m")
        return self


class LidarModel(_Strict):
    channels: int = Field(gt=0)
    horizontal_samples: int = Field(gt=0, description="rays per revolution")
    vertical_min_rad: float = Field(ge=-math.pi / 2, le=math.pi / 2)
    vertical_max_rad: float = Field(ge=-math.pi / 2, le=math.pi / 2)
    min_range_m: float = Field(ge=0)
    max_range_m: float = Field(gt=0)
    range_noise_std_m: float = Field(0.0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> LidarModel:
        if self.vertical_max_rad < self.vertical_min_rad:
            raise ValueError("vertical_max_rad < vertical_min_rad")
        if self.max_range_m <= self.min_range_m:
            raise ValueError("max_range_m must exceed min_range_m")
        return self


class RadarModel(_Strict):
    hfov_rad: float = Field(gt=0, le=2 * math.pi)
    vfov_rad: float = Field(gt=0, le=math.pi)
    min_range_m: float = Field(ge=0)
    max_range_m: float = Field(gt=0)
    range_noise_std_m: float = Field(0.0, ge=0)
    azimuth_noise_std_rad: float = Field(0.0, ge=0)
    range_rate_noise_std_mps: float = Field(0.0, ge=0)
    max_targets: int = Field(64, gt=0)

    @model_validator(mode="after")
    def _check(self) -> RadarModel:
        if self.max_range_m <= self.min_range_m:
            raise ValueError("max_range_m must exceed min_range_m")
        return self


class SensorSpec(_Strict):
    id: Id
    agent: Id
    kind: SensorKindName
    pose: PoseSpec = Field(description="world pose of the sensor body frame (+x forward, +y left, +z up)")
    rate_hz: float = Field(gt=0)
    camera: CameraModel | None = None
    lidar: LidarModel | None = None
    radar: RadarModel | None = None
    paired_camera: Id | None = Field(None, description="radar: camera it is fused with")

    @model_validator(mode="after")
    def _model_matches_kind(self) -> SensorSpec:
        given = {k for k in ("camera", "lidar", "radar") if getattr(self, k) is not None}
        if given != {self.kind}:
            raise ValueError(
                f"sensor {self.id}: kind {self.kind} needs exactly a `{self.kind}` block, got {sorted(given)}"
            )
        if self.paired_camera is not None and self.kind != "radar":
            raise ValueError(f"sensor {self.id}: only radars have a paired_camera")
        return self


class JunctionSpec(_Strict):
    id: Id
    number: int = Field(ge=1, description="the paper's flow-count point number")
    position_m: Vec3


class LaneSpec(_Strict):
    id: Id
    from_junction: Id
    to_junction: Id
    area: Id
    points_m: list[Vec3] = Field(min_length=2, description="centreline polyline, driving direction")
    speed_limit_mps: float = Field(gt=0)


class AreaSpec(_Strict):
    id: Id
    name: str
    polygon_m: list[Vec2] = Field(min_length=3, description="footprint on the table")
    z_min_m: float = Field(-1.0, description="membership also needs z in [z_min_m, z_max_m]")
    z_max_m: float = Field(10.0)


class AgentSpec(_Strict):
    id: Id
    name: str
    areas: list[Id] = Field(description="areas this agent's sensors cover")


class TableSpec(_Strict):
    size_x_m: float = Field(gt=0)
    size_y_m: float = Field(gt=0)
    origin_m: Vec2 = Field((0.0, 0.0), description="world xy of the table's min corner")


class SceneSpec(_Strict):
    scene_id: Id
    description: str = ""
    table: TableSpec
    junctions: list[JunctionSpec] = Field(default_factory=list)
    lanes: list[LaneSpec] = Field(default_factory=list)
    areas: list[AreaSpec] = Field(default_factory=list)
    agents: list[AgentSpec] = Field(default_factory=list)
    sensors: list[SensorSpec] = Field(default_factory=list)

    @model_validator(mode="after")
    def _references(self) -> SceneSpec:
        for what, items in (
            ("junction", self.junctions),
            ("lane", self.lanes),
            ("area", self.areas),
            ("agent", self.agents),
            ("sensor", self.sensors),
        ):
            ids = [i.id for i in items]
            dupes = sorted({i for i in ids if ids.count(i) > 1})
            if dupes:
                raise ValueError(f"duplicate {what} ids: {dupes}")
        numbers = [j.number for j in self.junctions]
        if len(set(numbers)) != len(numbers):
            raise ValueError("duplicate junction numbers")
        junctions = {j.id for j in self.junctions}
        areas = {a.id for a in self.areas}
        agents = {a.id for a in self.agents}
        cameras = {s.id for s in self.sensors if s.kind == "camera"}
        for lane in self.lanes:
            for end in (lane.from_junction, lane.to_junction):
                if end not in junctions:
                    raise ValueError(f"lane {lane.id}: unknown junction {end}")
            if lane.area not in areas:
                raise ValueError(f"lane {lane.id}: unknown area {lane.area}")
        for agent in self.agents:
            for area in agent.areas:
                if area not in areas:
                    raise ValueError(f"agent {agent.id}: unknown area {area}")
        for sensor in self.sensors:
            if sensor.agent not in agents:
                raise ValueError(f"sensor {sensor.id}: unknown agent {sensor.agent}")
            if sensor.paired_camera is not None and sensor.paired_camera not in cameras:
                raise ValueError(f"sensor {sensor.id}: paired_camera {sensor.paired_camera} is not a camera")
        return self
