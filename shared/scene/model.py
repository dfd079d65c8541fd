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

from shared.devices.robosense import MODELS, firings_per_turn

Id = Annotated[str, StringConstraints(pattern=r"^[a-z0-9][a-z0-9_\-]{0,63}$")]
Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
SensorKindName = Literal["camera", "lidar", "radar"]


#: Vehicles further apart in height than this are on different road levels (viaduct deck / table):
#: they neither collide nor are they one vehicle seen twice. The deck is 0.4 m above the table; the
#: ramps climb 0.4 m over 2 m, so two cars a car length apart on a ramp differ by ~0.07 m. The
#: reference (sand table) value only: the default of the scaled `Length` settings that use it (the
#: coordinator's MapConfig.level_separation_m, the sim's TrafficSettings.level_separation_m), scaled
#: to the scene they run (shared/scene/scale.py); no code compares heights against it directly.
LEVEL_SEPARATION_M = 0.1


#: How far a traffic mix's fractions may sum from 1 (fractions written with a few decimals).
MIX_SUM_TOLERANCE = 1e-6


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
    image_noise_std: float = Field(0.0, ge=0, le=1, description="Gaussian pixel noise, fraction of 255")
    intrinsics_px: tuple[float, float, float, float] | None = Field(
        None, description="calibrated fx, fy, cx, cy (a site's camera); default: from hfov, centred"
    )

    @model_validator(mode="after")
    def _check(self) -> CameraModel:
        if self.distortion and len(self.distortion) not in (4, 5):
            raise ValueError("distortion needs 4 or 5 plumb_bob coefficients")
        if self.far_m <= self.near_m:
            raise ValueError("far_m must exceed near_m")
        if self.intrinsics_px is not None and not (
            self.intrinsics_px[0] > 0
            and self.intrinsics_px[1] > 0
            and all(map(math.isfinite, self.intrinsics_px))
        ):
            raise ValueError("intrinsics_px: fx, fy must be positive and every value finite")
        return self


LidarDevice = Literal["rs16", "rs32"]


class LidarModel(_Strict):
    """A spinning lidar. A generic one spaces `channels` evenly from `vertical_min_rad` to
    `vertical_max_rad`; a `device` (a Robosense RS-LiDAR-16 / -32, shared/devices/robosense.py) fires
    the example unit's calibrated channel angles on that device's firing grid at `rpm`, from its lens
    centre, so that the emulated unit's packets (sim/emulators/robosense.py) carry exactly these rays."""

    channels: int = Field(gt=0)
    horizontal_samples: int = Field(gt=0, description="rays per revolution")
    vertical_min_rad: float | None = Field(None, ge=-math.pi / 2, le=math.pi / 2, description="generic only")
    vertical_max_rad: float | None = Field(None, ge=-math.pi / 2, le=math.pi / 2, description="generic only")
    min_range_m: float = Field(ge=0)
    max_range_m: float = Field(gt=0)
    range_noise_std_m: float = Field(0.0, ge=0)
    device: LidarDevice | None = Field(None, description="a real model's channel angles and firing grid")
    rpm: Literal[300, 600, 1200] = Field(600, description="device motor speed (10 Hz = 600)")

    @model_validator(mode="after")
    def _check(self) -> LidarModel:
        if self.device is None:
            if self.vertical_min_rad is None or self.vertical_max_rad is None:
                raise ValueError("a generic lidar needs vertical_min_rad and vertical_max_rad")
            if self.vertical_max_rad < self.vertical_min_rad:
                raise ValueError("vertical_max_rad < vertical_min_rad")
        else:
            model = MODELS[self.device]
            if self.vertical_min_rad is not None or self.vertical_max_rad is not None:
                raise ValueError(
                    f"{self.device}: the channel angles are the device's, give no vertical range"
                )
            if self.channels != model.lasers:
                raise ValueError(f"{self.device} has {model.lasers} channels, not {self.channels}")
            if self.horizontal_samples > firings_per_turn(model, self.rpm):
                raise ValueError(
                    f"{self.device} at {self.rpm} rpm fires {firings_per_turn(model, self.rpm)} times a "
                    f"turn: horizontal_samples {self.horizontal_samples} is more"
                )
        if self.max_range_m <= self.min_range_m:
            raise ValueError("max_range_m must exceed min_range_m")
        return self

    @property
    def vertical_range_rad(self) -> tuple[float, float]:
        """Lowest and highest channel elevation."""
        if self.device is None:
            assert self.vertical_min_rad is not None and self.vertical_max_rad is not None
            return self.vertical_min_rad, self.vertical_max_rad
        table = MODELS[self.device].example_vertical_deg
        return math.radians(min(table)), math.radians(max(table))


class RadarModel(_Strict):
    hfov_rad: float = Field(gt=0, le=2 * math.pi)
    vfov_rad: float = Field(gt=0, le=math.pi)
    min_range_m: float = Field(ge=0)
    max_range_m: float = Field(gt=0)
    range_noise_std_m: float = Field(0.0, ge=0)
    azimuth_noise_std_rad: float = Field(0.0, ge=0)
    range_rate_noise_std_mps: float = Field(0.0, ge=0)
    max_targets: int = Field(64, gt=0)
    detection_probability: float = Field(1.0, ge=0, le=1, description="per visible vehicle and scan")
    clutter_per_scan: float = Field(0.0, ge=0, description="mean number of false targets (Poisson)")
    vehicle_rcs_dbsm: float = Field(-5.0, description="mean radar cross-section of a vehicle")
    rcs_noise_std_db: float = Field(1.0, ge=0)
    clutter_rcs_dbsm: float = Field(-20.0, description="mean RCS of clutter targets")
    occlusion_max_fraction: float = Field(
        0.6, ge=0, le=1, description="a vehicle is dropped when more of its sampled face is blocked"
    )
    occlusion_samples: int = Field(5, gt=0, description="samples per side of the occlusion grid")

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
    radius_m: float = Field(0.4, gt=0, description="control zone: lanes end/start on its edge")


class LaneSpec(_Strict):
    id: Id
    from_junction: Id
    to_junction: Id
    area: Id
    points_m: list[Vec3] = Field(
        min_length=2, description="centreline control points, driving direction; corners are rounded"
    )
    speed_limit_mps: float = Field(gt=0)
    corner_radius_m: float | None = Field(None, ge=0, description="fillet radius (default: road's)")
    reverse_lane: Id | None = Field(None, description="the opposite lane of the same road (no U-turns)")
    next_lanes: list[Id] | None = Field(
        None,
        description="the lanes this one leads onto at its end junction (a real crossing's turn "
        "restrictions); None: every lane leaving that junction but its reverse",
    )
    circulating: bool = Field(
        False, description="roundabout ring lane: has priority at its junctions; entries are metered"
    )


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
    sensor_phase_ticks: int = Field(
        0,
        ge=0,
        description="this agent's sensors fire this many sim ticks after the scene's sensor ticks; "
        "agents on different phases do not render, send and detect all at the same instant",
    )


class DeckSpec(_Strict):
    """An elevated deck (the sand table's viaduct): where lanes leave the ground."""

    min_z_m: float = Field(ge=0, description="lane points above this are on the deck")
    width_m: float = Field(gt=0)
    thickness_m: float = Field(gt=0)
    pillar_spacing_m: float = Field(gt=0)
    pillar_radius_m: float = Field(gt=0)


class RoadSpec(_Strict):
    """Road geometry of a site with a lane map, in the scene's metres (no defaults: a default would be
    one site's size)."""

    lane_width_m: float = Field(gt=0)
    corner_radius_m: float = Field(ge=0, description="default fillet radius of lane corners")
    sample_step_m: float = Field(gt=0, description="resampling step of lane centrelines")
    deck: DeckSpec | None = Field(None, description="an elevated deck; None: every lane on the ground")

    @property
    def elevated_min_z_m(self) -> float:
        """Lane points above this are on the deck (infinite without a deck)."""
        return math.inf if self.deck is None else self.deck.min_z_m


#: Ground-truth object classes a vehicle class may carry (rmmdet.v1.ObjectClass OBJECT_CLASS_<upper>).
VehicleLabel = Literal["car", "truck", "bus"]


class VehicleSpec(_Strict):
    """Body and drive of one vehicle class. No defaults for sizes: the scene file is the one home of each
    class's size and acceleration; the scene's `vehicle` (the reference class) sets the scale of every
    scaled setting (shared/scene/scale.py)."""

    name: Id = Field("car", description="class name, unique in the scene (the ground truth carries it)")
    label: VehicleLabel = Field("car", description="its ground-truth object class")
    length_m: float = Field(gt=0)
    width_m: float = Field(gt=0)
    height_m: float = Field(gt=0)
    wheelbase_m: float = Field(gt=0)
    max_steer_rad: float = Field(gt=0, lt=1.57)
    max_accel_mps2: float = Field(gt=0, description="acceleration it drives with (car following)")

    @property
    def size_m(self) -> tuple[float, float, float]:
        """(length, width, height), m."""
        return (self.length_m, self.width_m, self.height_m)


class StaticObjectSpec(_Strict):
    """Buildings, poles and other occluders: a box or an upright cylinder standing on the table; a
    signal head is a box housing (its colour `rgba`) with three round lamp faces (red over amber over
    green, unlit colours) on its +x face, so `yaw_rad` is the direction the lamps face."""

    id: Id
    kind: Literal["box", "cylinder", "signal_head"]
    position_m: Vec3 = Field(description="centre of the base")
    size_m: Vec3 = Field(
        description="box, signal head: x, y, z extents (signal head: depth, width, height); cylinder: "
        "diameter, diameter, height"
    )
    yaw_rad: float = 0.0
    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    collision: bool = Field(True, description="seen by lidar / radar rays")


class TableSpec(_Strict):
    size_x_m: float = Field(gt=0)
    size_y_m: float = Field(gt=0)
    origin_m: Vec2 = Field((0.0, 0.0), description="world xy of the table's min corner")


class SceneSpec(_Strict):
    scene_id: Id
    description: str = ""
    table: TableSpec
    road: RoadSpec | None = Field(None, description="road geometry; required with a lane map")
    design_speed_mps: float | None = Field(
        None,
        gt=0,
        description="the site's top speed where no lane gives one (a site without a lane map): the "
        "characteristic speed of its scale (shared/scene/scale.py)",
    )
    vehicle: VehicleSpec = Field(description="the reference vehicle class: it sets the site's scale")
    vehicle_classes: list[VehicleSpec] = Field(
        default_factory=list, description="further vehicle classes (vans, trucks), each its own size"
    )
    traffic_mix: dict[Id, float] | None = Field(
        None,
        description="fraction of the fleet per class name (the reference class's too), summing to 1; "
        "None: every vehicle is the reference class",
    )
    static_objects: list[StaticObjectSpec] = Field(default_factory=list)
    junctions: list[JunctionSpec] = Field(default_factory=list)
    lanes: list[LaneSpec] = Field(default_factory=list)
    areas: list[AreaSpec] = Field(default_factory=list)
    agents: list[AgentSpec] = Field(default_factory=list)
    sensors: list[SensorSpec] = Field(default_factory=list)

    @property
    def top_speed_mps(self) -> float:
        """The site's characteristic speed: its highest lane speed limit, else `design_speed_mps`."""
        if self.lanes:
            return max(lane.speed_limit_mps for lane in self.lanes)
        if self.design_speed_mps is not None:
            return self.design_speed_mps
        raise ValueError(f"scene {self.scene_id}: no lanes and no design_speed_mps: its top speed is unknown")

    @property
    def fleet_mix(self) -> list[tuple[VehicleSpec, float]]:
        """(class, fraction of the fleet) for every class in the mix, the reference class first, in the
        scene's order; the reference class alone without a mix."""
        if self.traffic_mix is None:
            return [(self.vehicle, 1.0)]
        classes = [self.vehicle, *self.vehicle_classes]
        return [(c, self.traffic_mix[c.name]) for c in classes if self.traffic_mix.get(c.name, 0.0) > 0]

    def vehicle_class(self, name: str) -> VehicleSpec:
        """The vehicle class called `name` (the reference class included)."""
        for c in (self.vehicle, *self.vehicle_classes):
            if c.name == name:
                return c
        raise KeyError(f"scene {self.scene_id}: no vehicle class {name!r}")

    def _check_fleet(self) -> None:
        names = [c.name for c in (self.vehicle, *self.vehicle_classes)]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"duplicate vehicle class names (the reference `vehicle` included): {dupes}")
        if self.traffic_mix is None:
            if self.vehicle_classes:
                raise ValueError(
                    f"vehicle_classes {names[1:]} given without a traffic_mix: say what fraction of the "
                    "fleet each class is"
                )
            return
        unknown = sorted(set(self.traffic_mix) - set(names))
        if unknown:
            raise ValueError(f"traffic_mix names unknown vehicle classes {unknown} (known: {names})")
        bad = {n: f for n, f in self.traffic_mix.items() if not (math.isfinite(f) and 0.0 <= f <= 1.0)}
        if bad:
            raise ValueError(f"traffic_mix fractions must lie in [0, 1]: {bad}")
        total = math.fsum(self.traffic_mix.values())
        if abs(total - 1.0) > MIX_SUM_TOLERANCE:
            raise ValueError(f"traffic_mix fractions must sum to 1, they sum to {total:.6g}")

    @model_validator(mode="after")
    def _references(self) -> SceneSpec:
        self._check_fleet()
        for what, items in (
            ("junction", self.junctions),
            ("lane", self.lanes),
            ("area", self.areas),
            ("agent", self.agents),
            ("sensor", self.sensors),
            ("static object", self.static_objects),
        ):
            ids = [i.id for i in items]
            dupes = sorted({i for i in ids if ids.count(i) > 1})
            if dupes:
                raise ValueError(f"duplicate {what} ids: {dupes}")
        if self.lanes and self.road is None:
            raise ValueError(
                "a scene with lanes needs a `road` block (lane width, corner radius, sample step)"
            )
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
            if lane.reverse_lane is not None:
                rev = next((other for other in self.lanes if other.id == lane.reverse_lane), None)
                if rev is None or (rev.from_junction, rev.to_junction) != (
                    lane.to_junction,
                    lane.from_junction,
                ):
                    raise ValueError(f"lane {lane.id}: reverse_lane {lane.reverse_lane} is not its opposite")
        starts = {lane.id: lane.from_junction for lane in self.lanes}
        for lane in self.lanes:
            for after in lane.next_lanes or ():
                if starts.get(after) != lane.to_junction:
                    raise ValueError(f"lane {lane.id}: next lane {after} does not leave its end junction")
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
