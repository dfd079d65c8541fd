"""Access-control rules generated from proto/streams.yaml: known answers per identity."""

from __future__ import annotations

import json

import pytest
import zenoh

from shared.bus.streams import data_keys, get_stream, streams, wide_key
from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from shared.security.acl import access_control, grant_permissions, identity_grants
from shared.security.identities import deployment_identities

PUT_IN = ("put", "ingress")


def perms(*names: str) -> dict[tuple[str, str], set[str]]:
    return grant_permissions(identity_grants(names))


@pytest.mark.parametrize(
    ("identity", "puts"),
    [
        (
            "mec-agent1",
            {
                "rmmdet/v1/agent1/objects",
                "rmmdet/v1/agent1/capture_demand/*",
                "rmmdet/v1/agent1/perception/detections_2d/*",
                "rmmdet/v1/agent1/perception/detections_3d/*",
            },
        ),
        ("sensor-agent1-cameras", {"rmmdet/v1/agent1/sensor/camera/*"}),
        ("sensor-agent2-radars", {"rmmdet/v1/agent2/sensor/radar/*"}),
        # must-deliver streams: no puts under their advanced publisher's `@adv` key space (it runs
        # without heartbeats; its token and cache queryable there are granted as such, not as puts)
        ("vehicle-v7", {"rmmdet/v1/vehicles/v7/plan_ack"}),
        (
            "coordinator",
            {
                "rmmdet/v1/cloud/plans/*",
                "rmmdet/v1/cloud/plans_served/*",
                "rmmdet/v1/cloud/maps/traffic",
                "rmmdet/v1/cloud/regions/*/traffic",  # a shard's (services/coordinator/shard.py)
                "rmmdet/v1/cloud/regions/*/clique",
            },
        ),
        ("recorder", set()),
        ("operator", set()),
    ],
)
def test_each_identity_publishes_only_its_own_keys(identity: str, puts: set[str]) -> None:
    assert perms(identity).get(PUT_IN, set()) == puts


def test_only_the_coordinator_publishes_plans_and_serves_the_route_rpc(test_scene: Scene) -> None:
    plan = zenoh.KeyExpr(get_stream("route_plan").key(vehicle="v1"))
    rpc = get_stream("route_rpc").pattern()
    for name in [*deployment_identities(test_scene), "vehicle-v1"]:
        p = perms(name)
        may_put_plan = any(zenoh.KeyExpr(k).intersects(plan) for k in p.get(PUT_IN, set()))
        may_serve = rpc in p.get(("declare_queryable", "ingress"), set())
        assert may_put_plan == may_serve == (name == "coordinator"), name


def test_only_coordinators_exchange_cliques_and_hand_vehicles_over(test_scene: Scene) -> None:
    release = get_stream("release_rpc").pattern()
    clique = zenoh.KeyExpr(get_stream("region_clique").key(region="1"))
    for name in [*deployment_identities(test_scene), "vehicle-v1", "recorder", "operator"]:
        p = perms(name)
        coordinator = name == "coordinator"
        assert (release in p.get(("declare_queryable", "ingress"), set())) == coordinator, name
        assert (
            any(
                zenoh.KeyExpr(k).intersects(zenoh.KeyExpr(release))
                for k in p.get(("query", "ingress"), set())
            )
            == coordinator
        ), name
        assert any(zenoh.KeyExpr(k).intersects(clique) for k in p.get(PUT_IN, set())) == coordinator, name


def test_a_vehicle_queries_the_route_rpc_and_reads_only_its_plans() -> None:
    p = perms("vehicle-v7")
    own_plans = "rmmdet/v1/cloud/plans/v7"
    # ... and the plan publisher's cache for its own plans (recovery), nobody else's
    assert p[("query", "ingress")] == {get_stream("route_rpc").key(vehicle="v7"), f"{own_plans}/@adv/**"}
    assert p[("declare_subscriber", "ingress")] == {own_plans, f"{own_plans}/@adv/**"}
    assert p[("reply", "egress")] >= {own_plans}  # the cache's replies carry the plans' own keys


def test_readers_subscribe_to_every_stream_and_query_health() -> None:
    p = perms("operator")
    assert set(data_keys()) <= p[("declare_subscriber", "ingress")]
    assert "rmmdet/v1/**" not in p[("declare_subscriber", "ingress")]  # stream by stream, never at once
    # health, and the caches of the must-deliver streams (a reader's advanced subscriber recovers too)
    adv = {f"{s.pattern()}/@adv/**" for s in streams().values() if s.advanced}
    assert adv and p[("query", "ingress")] == {"rmmdet/v1/*/@health/*/*", *adv}
    assert set(data_keys()) <= perms("recorder")[("declare_subscriber", "ingress")]


def test_a_site_router_holds_the_union_of_its_site() -> None:
    site = perms("router-agent1", "sensor-agent1-lidars", "mec-agent1")
    assert site[PUT_IN] == perms("mec-agent1")[PUT_IN] | {"rmmdet/v1/agent1/sensor/lidar/*"}


def test_wide_keys() -> None:
    assert wide_key(get_stream("objects")) == "rmmdet/v1/*/objects"
    assert wide_key(get_stream("health")) == "rmmdet/v1/*/@health/**"
    assert wide_key(get_stream("route_rpc")) == "rmmdet/v1/cloud/@rpc/route/**"


def test_access_control_section_is_default_deny_with_one_policy_per_subject() -> None:
    acl = access_control({"mec-agent1": ["mec-agent1"], "router-agent2": ["router-agent2", "mec-agent2"]})
    assert acl["enabled"] and acl["default_permission"] == "deny"
    ids = [r["id"] for r in acl["rules"]]
    assert len(ids) == len(set(ids))
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {
        "mec-agent1": ["mec-agent1"],
        "router-agent2": ["router-agent2"],
    }
    assert sorted(p["subjects"][0] for p in acl["policies"]) == ["mec-agent1", "router-agent2"]
    assert all(r["permission"] == "allow" and len(r["flows"]) == 1 for r in acl["rules"])
    zenoh.Config().insert_json5("access_control", json.dumps(acl))  # Zenoh accepts it


def test_every_stream_names_known_roles_only() -> None:
    for stream in streams().values():
        assert stream.access, stream.name
    perms(*deployment_identities(Scene.load(DEFAULT_SCENE)))  # role_matches raises on an unknown role


@pytest.mark.parametrize(
    ("identity", "token"),
    [
        ("sensor-agent1-cameras", "rmmdet/v1/agent1/@alive/sensor/agent1-cameras"),
        ("mec-agent2", "rmmdet/v1/agent2/@alive/mec/agent2"),
        ("coordinator", "rmmdet/v1/*/@alive/coordinator/*"),
    ],
)
def test_a_node_holds_presence_and_serves_health_only_under_its_own_instance(
    identity: str, token: str
) -> None:
    """Issue 34 item 5: a sensor group's and a MEC's instance chunk is bound to the identity (a sibling
    group of the same agent cannot hold its token or answer its health); one-of-a-kind roles stay `*`."""
    p = perms(identity)
    assert {k for k in p[("liveliness_token", "ingress")] if "/@alive/" in k} == {token}
    health = token.replace("/@alive/", "/@health/")
    assert {k for k in p[("declare_queryable", "ingress")] if "/@health/" in k} == {health}


def test_interest_only_in_the_key_spaces_of_ones_own_streams() -> None:
    """Issue 34 item 11, issue 52 item 9: a publisher is told of subscriptions on its own streams' key
    spaces (where the recorder subscribes too), never of the whole data space (which told a vehicle
    every other vehicle's plan subscription); a queryable and a querier learn of queries and queryables
    on their own stream's key space only."""
    p = perms("mec-agent1")
    assert "rmmdet/v1/**" not in p[("declare_subscriber", "egress")]
    assert "rmmdet/v1/*/objects" in p[("declare_subscriber", "egress")]
    vehicle = perms("vehicle-v7")[("declare_subscriber", "egress")]
    assert not {k for k in vehicle if k.startswith("rmmdet/v1/cloud/plans")}, vehicle
    assert "rmmdet/v1/**" not in p[("query", "egress")]  # its health queryable
    assert p[("query", "egress")] == {"rmmdet/v1/*/@health/**"}
    assert "rmmdet/v1/**" not in perms("vehicle-v7")[("declare_queryable", "egress")]


def test_a_shard_publishes_only_its_own_region_and_holds_only_its_own_presence() -> None:
    p = perms("coordinator-region1")
    puts = p.get(PUT_IN, set())
    assert "rmmdet/v1/cloud/regions/1/clique" in puts and "rmmdet/v1/cloud/regions/1/traffic" in puts
    other = zenoh.KeyExpr(get_stream("region_clique").key(region="0"))
    assert not any(zenoh.KeyExpr(k).intersects(other) for k in puts)  # no forging region 0's clique
    assert get_stream("release_rpc").pattern() in p[("declare_queryable", "ingress")]
    assert "rmmdet/v1/*/@health/coordinator/region1" in p[("declare_queryable", "ingress")]
    assert not any("region0" in k for k in p[("declare_queryable", "ingress")])  # not region 0's health


def test_a_shard_reads_every_region_s_clique() -> None:
    p = perms("coordinator-region1")
    other = zenoh.KeyExpr(get_stream("region_clique").key(region="0"))
    assert any(zenoh.KeyExpr(k).intersects(other) for k in p[("declare_subscriber", "ingress")])
