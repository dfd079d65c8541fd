"""Identity names -> roles and bindings; the deployment's identities from the scene."""

from __future__ import annotations

import pytest

from shared.config import ConfigError
from shared.scene.scene import Scene
from shared.security.identities import Grant, deployment_identities, parse_identity, site_identities


@pytest.mark.parametrize(
    ("name", "grants"),
    [
        ("coordinator", (Grant("coordinator"),)),
        ("sim", (Grant("sim"),)),  # its vehicles each have their own identity
        ("router-cloud", (Grant("router"),)),
        ("router-agent2", (Grant("router", {"site": "agent2"}),)),
        ("mec-agent1", (Grant("mec", {"agent": "agent1"}),)),
        ("sensor-agent3-lidars", (Grant("sensors", {"agent": "agent3", "kind": "lidar"}),)),
        ("vehicle-v17", (Grant("vehicles", {"vehicle": "v17"}),)),
    ],
)
def test_names_map_to_grants(name: str, grants: tuple[Grant, ...]) -> None:
    assert parse_identity(name).grants == grants


@pytest.mark.parametrize("name", ["mallory", "sensor-agent1-sonars", "mec-", "vehicle-"])
def test_unknown_names_are_config_errors(name: str) -> None:
    with pytest.raises(ConfigError):
        parse_identity(name)


def test_every_site_has_its_router_groups_and_mec(test_scene: Scene) -> None:
    names = deployment_identities(test_scene)
    assert len(names) == len(set(names))
    for agent in test_scene.agents:
        site = site_identities(test_scene, agent)
        assert site[0] == f"router-{agent}" and site[-1] == f"mec-{agent}"
        kinds = {s.kind for s in test_scene.sensors_of(agent)}
        assert {f"sensor-{agent}-{k}s" for k in kinds} == set(site[1:-1])
        assert set(site) <= set(names)
    for name in names:
        parse_identity(name)
