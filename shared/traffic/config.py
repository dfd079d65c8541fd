"""Coordinator settings: maps, coverage, planning, plan delivery. Typed, with defaults and descriptions.

Sizes and speeds (`Length`, `Speed`) are stated for the sand table and scaled to the scene the
coordinator runs (`CoordinatorCore` builds with `at_scale`, shared/scene/scale.py); a value given in a
settings file or the environment is taken as written, in the scene's units, so the base file gives none.

Loaded from `deploy/coordinator/coordinator.yaml` with environment overrides `RMMDET_COORD_<SECTION>__<FIELD>`
(e.g. `RMMDET_COORD_PLANNER__POLICY=shortest`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from shared.config import RmmdetSettings, load_settings, settings_config
from shared.paths import DEFAULT_PKI_DIR, DEFAULT_SCENE, REPO_ROOT
from shared.scene.model import LEVEL_SEPARATION_M
from shared.scene.scale import Length, Speed
from shared.security.pki import plan_key_paths

DEFAULT_COORDINATOR_CONFIG = REPO_ROOT / "deploy" / "coordinator" / "coordinator.yaml"

PolicyName = Literal["random", "paper_rule", "shortest", "dynamic_ground_truth", "balanced"]
SpeedSource = Literal["perceived", "free"]
RequestReplan = Literal["always", "on_gain"]
POLICIES: tuple[PolicyName, ...] = ("random", "paper_rule", "shortest", "dynamic_ground_truth", "balanced")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class MapConfig(_Section):
    smoothing_time_constant_s: float = Field(
        5.0, gt=0, description="exponential smoothing of densities and speeds (time constant)"
    )
    speed_valid_s: float = Field(
        15.0, gt=0, description="a lane/area/cell speed without a new sample for this long is invalid"
    )
    grid_cell_m: Length = Field(0.25, gt=0, description="cell size of the density/speed grid")
    dedup_gate_m: Length = Field(
        0.3, gt=0, description="objects of two agents closer than this (same level) are one vehicle"
    )
    level_separation_m: Length = Field(
        LEVEL_SEPARATION_M,
        gt=0,
        description="objects further apart in z are on different levels (deck / ground)",
    )
    lane_match_max_m: Length = Field(
        0.3, gt=0, description="an object further than this from every lane centreline is off-lane"
    )
    lane_level_weight: float = Field(
        3.0, ge=1, description="z distance counts this many times more than xy when matching a lane"
    )
    heading_gate_rad: float = Field(
        math.pi / 2, gt=0, le=math.pi, description="a moving object's heading must agree with its lane's"
    )
    min_speed_for_heading_mps: Speed = Field(
        0.05, ge=0, description="below this speed the velocity direction is not used to pick the lane"
    )
    min_existence_probability: float = Field(
        0.0, ge=0, le=1, description="objects with a lower existence probability are ignored"
    )


class CoverageConfig(_Section):
    stale_after_s: float = Field(
        0.5, gt=0, description="agent data older than this (or presence gone): STALE"
    )
    lost_after_s: float = Field(
        3.0, gt=0, description="agent data older than this: LOST (docs/reliability.md R4)"
    )
    bus_silent_after_s: float = Field(
        0.3,
        gt=0,
        description="nothing at all heard from the bus for this long (object lists, sim clock, acks: tens"
        " a second): the link is suspected, not every agent; coverage is held (docs/reliability.md R2)",
    )
    bus_silence_max_s: float = Field(
        12.0,
        gt=0,
        description="... for at most this much longer: more than Zenoh's 10 s lease, after which a frozen"
        " router's transport closes and the outage is plain",
    )


class PlannerConfig(_Section):
    policy: PolicyName = Field("balanced", description="route policy served to vehicles")
    junction_service_s: float = Field(
        1.0, gt=0, description="time a junction takes to pass one queued vehicle (queue delay per car)"
    )
    load_weight: float = Field(
        2.0, ge=0, description="cost of one other vehicle planned onto a lane, in junction services"
    )
    load_horizon_lanes: int = Field(
        3, ge=1, description="lanes ahead of each planned vehicle counted as its future load"
    )
    min_speed_mps: Speed = Field(
        0.05, gt=0, description="perceived speeds are floored here (a stopped queue is slow, not closed)"
    )
    detour_min_saving: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="balanced: keep the free-flow shortest route unless the fastest route on the maps is "
        "expected to save more than this share of its time (0: always the fastest). Rerouting on "
        "short-lived queues costs turns and spreads jams; only a clear saving is worth a detour",
    )
    speed_source: SpeedSource = Field(
        "perceived",
        description="balanced's lane time: length at the perceived mean speed, or at the free speed where "
        "slow lanes are mostly queues at red lights (sensors near junctions see the queue, not the lane) "
        "and the per-car junction service already charges them",
    )
    turn_penalty_s: float = Field(
        0.0,
        ge=0,
        description="extra time per right angle of heading change at a junction (vehicles slow down to "
        "turn); 0 on the table, whose vehicles keep their speed through connectors",
    )
    plan_ttl_s: float = Field(120.0, gt=0, description="validity of a plan; vehicles fall back after")
    seed: int = Field(0, ge=0, description="random policy's generator seed")


class DeliveryConfig(_Section):
    ack_timeout_s: float = Field(
        0.5, gt=0, description="resend a pushed plan not acknowledged this long after its first send"
    )
    ack_timeout_max_s: float = Field(
        4.0, gt=0, description="the wait after each later send doubles up to this (exponential backoff)"
    )
    max_sends: int = Field(5, ge=1, description="a pushed plan is sent at most this many times")
    vehicle_idle_s: float = Field(
        300.0, gt=0, description="a vehicle without a request or acknowledgement for this long is forgotten"
    )

    def ack_wait_s(self, sends: int) -> float:
        """How long after its `sends`-th send (1 = the first) a pushed plan waits for its acknowledgement.

        Doubling: over Zenoh's reliable channel a resend only helps across a reconnect, while TCP's own
        retransmissions back off from 200 ms, doubling, so a burst of loss delays an acknowledgement by
        seconds (stop 58's fresh clone: 20 % loss each way, one plan of 29 acknowledged after the fixed
        5 x 0.5 s and counted given up). The defaults give up 11.5 s after the first send, past the 10 s
        lease after which Zenoh itself declares the link dead and the vehicle's requests take over."""
        return min(self.ack_timeout_s * 2.0 ** max(0, sends - 1), self.ack_timeout_max_s)


class ServiceConfig(_Section):
    """Bus-side knobs of the coordinator process."""

    map_update_max_hz: float = Field(
        20.0,
        gt=0,
        description="maps are rebuilt when object lists arrive, at most this often (plans use fresh maps)",
    )
    objects_queue_per_agent: int = Field(
        4, ge=1, description="latest-wins queue depth of incoming object lists, per agent"
    )
    max_vehicles: int = Field(
        256,
        ge=1,
        description="vehicles whose plans are tracked at once; a further one replaces the longest idle "
        "of those that never accepted a plan (then of the rest)",
    )
    new_vehicles_per_s: float = Field(
        20.0,
        gt=0,
        description="route requests from vehicles the coordinator holds no plan for are served at most "
        "this often on average (shared/bus/admission.py); more are refused at once (UNAVAILABLE) and "
        "ask again at their next lane. Vehicles it holds are never limited",
    )
    new_vehicle_burst: int = Field(
        20,
        ge=1,
        description="... and at most this many at once (a fleet asking together after a coordinator "
        "restart: twice the table's 10; raise it for a larger fleet)",
    )


class ShardConfig(_Section):
    """A sharded coordinator (one process per region of `regions`; which one: the service's `--shard`)."""

    regions: Path | None = Field(
        None, description="region map JSON (shared/traffic/regions.py RegionMap); none: one coordinator"
    )
    clique_stale_after_s: float = Field(
        3.0,
        gt=0,
        description="a region whose shard published no valid clique for this long is planned on a prior",
    )
    release_timeout_s: float = Field(
        0.3, gt=0, description="how long a shard waits for the others to hand over a vehicle that asks it"
    )


class CoordinatorSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_COORD_")

    scene: Path = Field(DEFAULT_SCENE, description="scene YAML (road network, areas, agents)")
    maps: MapConfig = MapConfig()
    coverage: CoverageConfig = CoverageConfig()
    planner: PlannerConfig = PlannerConfig()
    delivery: DeliveryConfig = DeliveryConfig()
    service: ServiceConfig = ServiceConfig()
    shards: ShardConfig = ShardConfig()
    plan_signing_key: Path = Field(
        plan_key_paths(DEFAULT_PKI_DIR).key,
        description="Ed25519 private key (PEM) that signs every plan (`rmmdet pki init` creates it); "
        "shard K signs with its own beside it, `<name>.region<K>.key` (`rmmdet pki init --shards N`)",
    )
    map_publish_hz: float = Field(2.0, gt=0, description="traffic map update and publication rate")
    replan_interval_s: float = Field(
        2.0, gt=0, description="pushed plans are re-checked this often against the current maps"
    )
    replan_gain: float = Field(
        0.2, ge=0, description="push a new plan when it is expected to save this share of the trip time"
    )
    request_replan: RequestReplan = Field(
        "always",
        description="a request from a vehicle following its plan is planned afresh (always), or keeps the "
        "rest of that plan unless a new route saves `replan_gain` of its time (on_gain: the push rule, so "
        "noisy maps do not send a car zig-zagging between equally good roads)",
    )
    report_interval_s: float = Field(10.0, gt=0, description="log interval of rates and counters")


def load_coordinator_settings(path: Path | None = DEFAULT_COORDINATOR_CONFIG) -> CoordinatorSettings:
    settings = load_settings(CoordinatorSettings, path)
    if not settings.scene.is_absolute():
        settings.scene = REPO_ROOT / settings.scene
    if settings.shards.regions is not None and not settings.shards.regions.is_absolute():
        settings.shards.regions = REPO_ROOT / settings.shards.regions
    if not settings.plan_signing_key.is_absolute():
        settings.plan_signing_key = REPO_ROOT / settings.plan_signing_key
    return settings
