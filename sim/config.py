"""Simulation parameters: traffic, vehicle control, timing. Typed, with defaults and descriptions.

Loaded from `deploy/sim/sim.yaml` (if given) with environment overrides `RMMDET_SIM_<FIELD>`, nested
with `__` (e.g. `RMMDET_SIM_TRAFFIC__VEHICLES=20`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from shared.config import RmmdetSettings, deep_merge, load_settings, settings_config
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.timebase import MAX_SIM_SPEED
from shared.vehicle.config import PlanClientSettings

DEFAULT_SIM_CONFIG = REPO_ROOT / "deploy" / "sim" / "sim.yaml"

RoutePolicy = Literal["random", "shortest", "plan"]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class IdmParams(_Model):
    """Intelligent Driver Model (Treiber et al. 2000) car following, table scale."""

    max_accel_mps2: float = Field(0.6, gt=0, description="a: maximum acceleration")
    comfort_decel_mps2: float = Field(1.0, gt=0, description="b: comfortable deceleration")
    max_decel_mps2: float = Field(4.0, gt=0, description="hard braking limit")
    min_gap_m: float = Field(0.1, ge=0, description="s0: standstill bumper-to-bumper gap")
    time_headway_s: float = Field(0.5, ge=0, description="T: desired time headway")
    exponent: float = Field(4.0, gt=0, description="delta: free-road acceleration exponent")


class PursuitParams(_Model):
    """Pure-pursuit lane following on the kinematic bicycle model."""

    lookahead_min_m: float = Field(0.2, gt=0, description="look-ahead distance at standstill")
    lookahead_gain_s: float = Field(0.4, ge=0, description="look-ahead grows by speed x gain")


def fleet_ids(count: int) -> list[str]:
    """The ids of a fleet of `count` vehicles, in the order they are placed (v00, v01, ...)."""
    return [f"v{index:02d}" for index in range(count)]


class TrafficSettings(_Model):
    vehicles: int = Field(10, ge=0, le=200, description="number of vehicles")
    max_speed_mps: float = Field(0.5, gt=0, description="vehicle top speed (lane limits also apply)")
    route_policy: RoutePolicy = Field(
        "random", description="turns at junctions: random (paper baseline), shortest, or plan (bus)"
    )
    connected_fraction: float = Field(
        1.0, ge=0, le=1, description="share of vehicles that follow plans when route_policy=plan"
    )
    junction_request_m: float = Field(
        0.7, gt=0, description="distance before a lane's end at which a vehicle asks to enter the junction"
    )
    plan_request_m: float = Field(
        1.0,
        gt=0,
        description="distance before a lane's end at which a connected vehicle asks for a plan (more "
        "than junction_request_m, so the plan is there when the vehicle picks its exit)",
    )
    horizon_m: float = Field(2.5, gt=0, description="car-following look-ahead along the route")
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
    idm: IdmParams = IdmParams()
    pursuit: PursuitParams = PursuitParams()


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
