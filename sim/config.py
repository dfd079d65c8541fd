"""Simulation parameters: traffic, vehicle control, the simulated world, timing. Typed, with defaults
and descriptions.

Loaded from `deploy/sim/sim.yaml` (if given) with environment overrides `RMMDET_SIM_<FIELD>`, nested
with `__` (e.g. `RMMDET_SIM_TRAFFIC__VEHICLES=20`). Sizes, speeds and accelerations (`Length`, `Speed`,
`Acceleration`, ...) are stated for the sand table and scaled to the scene by what builds on them
(`TrafficSim`, the worlds of sim/world.py, the board and bird's-eye tools: `at_scale`,
shared/scene/scale.py); a value given in a settings file or the environment is taken as written, in the
scene's units, so the base file gives none.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from shared.config import RmmdetSettings, deep_merge, load_settings, settings_config
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.scene.model import LEVEL_SEPARATION_M
from shared.scene.scale import ACCELERATION, LENGTH, Acceleration, Length, PerLength, Speed
from shared.timebase import MAX_SIM_SPEED
from shared.vehicle.config import PlanClientSettings

DEFAULT_SIM_CONFIG = REPO_ROOT / "deploy" / "sim" / "sim.yaml"

RoutePolicy = Literal["random", "shortest", "plan"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class IdmParams(_Model):
    """Intelligent Driver Model (Treiber et al. 2000) car following; accelerations scale with the scene
    vehicle's (`max_accel_mps2` is exactly its max_accel_mps2), gaps with its length."""

    max_accel_mps2: Acceleration = Field(
        0.6,
        gt=0,
        description="a: maximum acceleration (the sand table's DeepRacer's, scaled to the scene's car)",
    )
    comfort_decel_mps2: Acceleration = Field(1.0, gt=0, description="b: comfortable deceleration")
    max_decel_mps2: Acceleration = Field(4.0, gt=0, description="hard braking limit")
    min_gap_m: Length = Field(0.1, ge=0, description="s0: standstill bumper-to-bumper gap")
    time_headway_s: float = Field(0.5, ge=0, description="T: desired time headway")
    exponent: float = Field(4.0, gt=0, description="delta: free-road acceleration exponent")


class PursuitParams(_Model):
    """Pure-pursuit lane following on the kinematic bicycle model."""

    lookahead_min_m: Length = Field(0.2, gt=0, description="look-ahead distance at standstill")
    lookahead_gain_s: float = Field(0.4, ge=0, description="look-ahead grows by speed x gain")


def fleet_ids(count: int) -> list[str]:
    """The ids of a fleet of `count` vehicles, in the order they are placed (v00, v01, ...)."""
    return [f"v{index:02d}" for index in range(count)]


class TrafficSettings(_Model):
    vehicles: int = Field(10, ge=0, le=200, description="number of vehicles")
    max_speed_mps: Speed = Field(
        0.5,
        gt=0,
        description="vehicle top speed (lane limits also apply); by default the site's top lane speed limit",
    )
    route_policy: RoutePolicy = Field(
        "random", description="turns at junctions: random (paper baseline), shortest, or plan (bus)"
    )
    connected_fraction: float = Field(
        1.0, ge=0, le=1, description="share of vehicles that follow plans when route_policy=plan"
    )
    junction_request_m: Length = Field(
        0.7, gt=0, description="distance before a lane's end at which a vehicle asks to enter the junction"
    )
    plan_request_m: Length = Field(
        1.0,
        gt=0,
        description="distance before a lane's end at which a connected vehicle asks for a plan (more "
        "than junction_request_m, so the plan is there when the vehicle picks its exit)",
    )
    horizon_m: Length = Field(2.5, gt=0, description="car-following look-ahead along the route")
    project_window_m: Length = Field(
        0.4, gt=0, description="a vehicle's progress is searched this far around its predicted progress"
    )
    level_separation_m: Length = Field(
        LEVEL_SEPARATION_M,
        gt=0,
        description="vehicles further apart in height are on different road levels (deck / ground): they "
        "neither collide nor take each other's spawn place",
    )
    detour_after_s: float = Field(
        10.0,
        gt=0,
        description="a vehicle first in line whose exit lane stays full this long takes another exit "
        "with room (drivers avoid a blocked road; resolves gridlock in saturated networks)",
    )
    trip_draws: Literal["shared", "per_vehicle"] = Field(
        "shared",
        description="destinations from the traffic's one generator (shared: the datasets' and evaluations' "
        "traffic) or from one generator per vehicle (per_vehicle: each vehicle's k-th trip is the same "
        "whatever the routing policy, so policies compare on the same trips)",
    )
    curve_lateral_accel_mps2: Annotated[float | None, ACCELERATION] = Field(
        None,
        gt=0,
        description="drivers slow for bends: the speed ahead is held to sqrt(this / curvature), reached "
        "by braking at the IDM's comfortable deceleration half a pursuit look-ahead before each point "
        "(curvature over the pursuit's standstill look-ahead); None: bends are taken at the lane's speed "
        "(the sand table's model cars)",
    )
    idm: IdmParams = IdmParams()
    pursuit: PursuitParams = PursuitParams()


class WorldSettings(_Model):
    """The simulated world's own geometry and ray-casting tolerances (sim/world.py and the sensor
    models): what the scene does not say. Sand-table values, scaled to the scene by the worlds."""

    table_thickness_m: Length = Field(0.02, gt=0, description="the table slab under the textured top")
    table_slab_drop_m: Length = Field(
        0.002, ge=0, description="the slab's top lies this far below the textured tiles (no z-fighting)"
    )
    table_tile_m: Length = Field(
        0.5,
        gt=0,
        description="side of the square tiles the table top is made of: small triangles keep TinyRenderer's "
        "texture interpolation stable at grazing view angles",
    )
    texture_px_per_m: PerLength = Field(
        128.0, gt=0, description="road texture resolution (the same pixel count at every scale)"
    )
    marking_width_m: Length = Field(0.012, gt=0, description="lane edge marking line width")
    marking_dash_m: Length = Field(0.08, gt=0, description="lane edge marking: dash length, and gap length")
    deck_piece_m: Length = Field(
        0.12,
        gt=0,
        description="the deck is built of boxes this long following the lane (grade and curvature)",
    )
    deck_piece_overlap_m: Length = Field(
        0.01,
        ge=0,
        description="each deck box reaches this far past its ends (no gaps between boxes at bends)",
    )
    pillar_min_z_m: Length = Field(
        0.15,
        ge=0,
        description="the deck stands on pillars only where it is higher than this (ramps rest on the ground)",
    )
    parked_z_m: Length = Field(
        -50.0,
        lt=0,
        description="height of unused bodies (vehicles not in the tick, a board), under the table",
    )
    vehicle_ray_margin_m: Length = Field(
        0.005,
        ge=0,
        description="lidar: vehicle boxes grown by this much when picking the rays to cast at them",
    )
    occlusion_tolerance_m: Length = Field(
        0.005, ge=0, description="radar: a ray hit this close before a face sample counts as reaching it"
    )
    camera_roi_full_res_max_px: int | None = Field(
        None,
        gt=0,
        description="cameras: a vehicle's image rectangle larger than this many pixels is rendered at 1/k "
        "of its size per side, k = ceil(sqrt(area / this)), and scaled up; None: always at full size. "
        "TinyRenderer spends 100-350 ns a pixel on a near car's large triangles (95 ms for a 375k px car "
        "beside a 1920 x 1200 camera), so one near car held a three-camera group past its frame period. "
        "Set by the intersection's profile; the sand table renders everything at full size",
    )


class BoardSessionSettings(_Model):
    """Where the simulated calibration session puts its board (sim/sensors/board.py). Sand-table values,
    scaled to the scene there (the board's own size is the board's: `shared.calibration.solve.Board`)."""

    table_clearance_m: Length = Field(
        0.001, ge=0, description="a board laid on the table lies this far above it (no z-fighting)"
    )
    view_distance_m: Annotated[tuple[float, float], LENGTH] = Field(
        (0.3, 0.6),
        description="intrinsics views: the board this far along the camera's optical axis (min, max)",
    )
    ahead_m: Annotated[tuple[float, float], LENGTH] = Field(
        (0.2, 3.0), description="standing boards: candidates this far ahead of the camera's foot (from, to)"
    )
    across_m: Length = Field(
        0.6, gt=0, description="standing boards: candidates up to this far to either side"
    )
    step_m: Length = Field(0.05, gt=0, description="standing boards: spacing of the candidate grid")
    row_gap_m: Length = Field(
        0.15,
        ge=0,
        description="standing boards: each row of placements at least this far beyond the one before",
    )
    flat_m: Length = Field(
        0.002,
        ge=0,
        description="a board's base is level if the surface under its ends and middle agrees this well",
    )
    lens_clearance_m: Length = Field(
        0.05,
        ge=0,
        description="lines of sight start this far out of the camera (its own mast is not in the way)",
    )
    survey_top_m: Length = Field(
        10.0, description="the surface under a candidate is found by a ray down from this height ..."
    )
    survey_bottom_m: Length = Field(-1.0, description="... to this one")


class BirdsEyeSettings(_Model):
    """The bird's-eye map of `rmmdet snapshot` (sim/snapshot.py). Sand-table values, scaled to the scene
    there: the same picture size and proportions at every scale."""

    px_per_m: PerLength = Field(100.0, gt=0, description="map resolution")
    camera_fov_m: Length = Field(1.6, gt=0, description="cameras' field of view drawn out to this range")
    radar_fov_m: Length = Field(
        2.5,
        gt=0,
        description="radars' field of view drawn out to this range (their own if shorter: the "
        "sand table's 8 m would tint the whole table)",
    )
    lidar_ring_m: Length = Field(1.0, gt=0, description="lidars (360 deg) drawn as a ring of this radius")
    arrow_every_m: Length = Field(0.8, gt=0, description="one lane direction arrow per this much lane")


class PacingSettings(_Model):
    """The live sim's pacing to its consumers (sim/pacing.py)."""

    enabled: bool = Field(True, description="hold ticks back while a consumer lags (live runs only)")
    streams: list[str] = Field(
        ["objects", "camera_image", "point_cloud", "radar_scan"],
        description="streams whose outputs pace the sim (stamp = sim time of the data): the MECs and the "
        "sensor services, every consumer of ground truth",
    )
    max_lag_s: float = Field(
        0.1,
        gt=0,
        description="largest lag of a consumer's newest output behind the next tick beyond the consumer's "
        "own output period, s of sim time: with a 0.1 s sensor period a frame is never older than the "
        "MECs' 0.2 s freshness limit on arrival only because the sim ran ahead",
    )
    consumer_timeout_s: float = Field(
        1.0,
        gt=0,
        description="a consumer silent this long (wall s) no longer holds the sim; one with a short cadence "
        "is let go after 2 of its own wall cadences (at least 0.15 s; sim/pacing.py)",
    )


class SimSettings(RmmdetSettings, PlanClientSettings):
    """The sim; its vehicles' plan client settings (route_policy=plan) are PlanClientSettings'."""

    model_config = settings_config(env_prefix="RMMDET_SIM_")

    scene: Path = Field(DEFAULT_SCENE, description="scene YAML")
    seed: int = Field(0, ge=0, description="scenario seed: traffic and sensor noise derive from it")
    tick_hz: float = Field(60.0, gt=0, description="simulation ticks per simulated second")
    speed: float = Field(
        1.0,
        ge=0,
        le=MAX_SIM_SPEED,
        description="simulated seconds per wall second; 0 = as fast as possible (lock-step)",
    )
    clock_publish_hz: float = Field(
        20.0,
        gt=0,
        description="SimClock publication rate: other processes follow sim time from it (shared/timebase.py)",
    )
    calibration_publish_hz: float = Field(1.0, gt=0, description="per-agent CalibrationSet republish rate")
    collision_check_hz: float = Field(10.0, gt=0, description="rate of the vehicle overlap monitor")
    traffic: TrafficSettings = TrafficSettings()
    world: WorldSettings = WorldSettings()
    pacing: PacingSettings = PacingSettings()


def load_sim_settings(
    path: Path = DEFAULT_SIM_CONFIG, vehicles: int | None = None, **overrides: object
) -> SimSettings:
    """Sim settings from `path` with top-level `overrides` (e.g. seed=3); `vehicles` replaces only the
    traffic's vehicle count, validated like the YAML value. A relative scene path is taken from the repo
    root, so the result does not depend on the working directory."""
    nested: dict[str, Any] = {"traffic": {"vehicles": vehicles}} if vehicles is not None else {}
    settings = load_settings(SimSettings, path, **deep_merge(overrides, nested))
    if not settings.scene.is_absolute():
        settings.scene = REPO_ROOT / settings.scene
    settings.resolve_paths()
    return settings
