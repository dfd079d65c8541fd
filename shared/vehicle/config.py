"""A connected vehicle's plan client settings, shared by the sim's fleet (SimSettings) and a real
car's client (VehicleSettings, `rmmdet vehicle`; environment RMMDET_VEHICLE_*)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from pydantic import BaseModel, Field

from shared.bus.streams import limits
from shared.config import RmmdetSettings, settings_config
from shared.paths import DEFAULT_PKI_DIR, DEFAULT_SCENE, REPO_ROOT
from shared.security.pki import trusted_plan_keys
from shared.traffic.config import PlannerConfig


class PlanClientSettings(BaseModel):
    plan_request_timeout_s: float = Field(
        1.0,
        gt=0,
        description="route_policy=plan: a route request unanswered by then is given up (the vehicle keeps "
        "its route and asks again on its next lane)",
    )
    plan_verify_keys: list[Path] = Field(
        default_factory=lambda: trusted_plan_keys(DEFAULT_PKI_DIR),
        min_length=1,
        description="route_policy=plan: Ed25519 public keys (PEM) of the coordinator; a plan signed by "
        "none of them is refused. Default: the PKI's current plan key and the next one once staged",
    )
    plan_max_ttl_s: float = Field(
        default_factory=lambda: PlannerConfig().plan_ttl_s + limits().max_clock_skew_s,
        gt=0,
        description="route_policy=plan: a plan valid for longer than this from now is refused; by default "
        "what the coordinator issues (its planner's plan_ttl_s) plus the bus's clock skew (a vehicle "
        "accepted 600 s while the coordinator issued 120 s: a recorded plan outlived its run)",
    )

    def resolve_paths(self) -> None:
        """Relative key paths are the repo root's (the result does not depend on the working directory)."""
        self.plan_verify_keys = [k if k.is_absolute() else REPO_ROOT / k for k in self.plan_verify_keys]

    def plan_key_source(self) -> Callable[[], list[Path]]:
        """Where the trusted plan keys are looked up each time (`PlanVerifier.watching`): the keys given in
        the settings, else the PKI's trusted ones as they are now (a key staged later is trusted too)."""
        if "plan_verify_keys" in self.model_fields_set:
            given = list(self.plan_verify_keys)
            return lambda: given
        return lambda: trusted_plan_keys(DEFAULT_PKI_DIR)


class VehicleSettings(RmmdetSettings, PlanClientSettings):
    """A real vehicle's plan client (`rmmdet vehicle`)."""

    model_config = settings_config(env_prefix="RMMDET_VEHICLE_")

    scene: Path = Field(DEFAULT_SCENE, description="scene YAML: the road network the plans' lanes are in")
