"""The loop verdict behind `rmmdet health`: OK exactly when every expected service answers NOMINAL."""

from __future__ import annotations

from rmmdet.v1.health_pb2 import HealthLevel, ServiceHealth

from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from shared.supervision.verdict import expected_services, judge

NOMINAL = HealthLevel.HEALTH_LEVEL_NOMINAL
DEGRADED = HealthLevel.HEALTH_LEVEL_DEGRADED


def report(source: str, level: int = NOMINAL, message: str = "") -> ServiceHealth:
    _scope, service, instance = source.split("/")
    r = ServiceHealth(service=service, instance=instance, level=level, message=message)
    r.header.source_id = source
    return r


def alive_key(source: str) -> str:
    scope, service, instance = source.split("/")
    return f"rmmdet/v1/{scope}/@alive/{service}/{instance}"


def test_expected_services_come_from_the_scene() -> None:
    expected = expected_services(Scene.load(DEFAULT_SCENE))
    assert "agent2/mec/agent2" in expected and "agent2/sensor/agent2-radars" in expected
    assert "agent1/sensor/agent1-lidars" in expected and "agent2/sensor/agent2-lidars" not in expected
    assert len(expected) == 3 + 3 + 6  # router, sim, coordinator; 3 MECs; 6 sensor groups


def test_every_expected_service_nominal_is_ok() -> None:
    expected = expected_services(Scene.load(DEFAULT_SCENE))
    verdict = judge([report(s) for s in expected], [], [alive_key(s) for s in expected], expected)
    assert verdict.ok and verdict.problems == []


def test_a_degraded_mec_a_missing_service_and_a_silent_one_are_each_named() -> None:
    expected = expected_services(Scene.load(DEFAULT_SCENE))
    answering = [s for s in expected if s not in ("agent1/mec/agent1", "cloud/coordinator/cloud")]
    reports = [
        report(s, DEGRADED, "degraded; cam_11: stale") if s == "agent3/mec/agent3" else report(s)
        for s in answering
    ]
    alive = [alive_key(s) for s in [*answering, "cloud/coordinator/cloud"]]
    verdict = judge(reports, [], alive, expected)
    assert not verdict.ok
    assert verdict.problems == [
        "agent3/mec/agent3 DEGRADED: degraded; cam_11: stale",
        "cloud/coordinator/cloud alive but no health reply",
        "agent1/mec/agent1 not running",
    ]
    assert verdict.summary().startswith("loop NOT OK: agent3/mec/agent3 DEGRADED")


def test_nothing_answering_is_not_ok_even_without_expectations() -> None:
    verdict = judge([], [], [], [])
    assert not verdict.ok and "no service answered" in verdict.problems[0]


def test_a_health_reply_is_believed_only_for_the_key_it_came_on() -> None:
    """Issue 34, item 5: `rmmdet health` believed the body's name over the key: a camera group could
    answer as the lidar group."""
    from shared.supervision.verdict import key_mismatch

    key = "rmmdet/v1/agent1/@health/sensor/agent1-lidars"
    assert key_mismatch(key, report("agent1/sensor/agent1-lidars")) is None
    assert "not believed" in (key_mismatch(key, report("agent1/sensor/agent1-cameras")) or "")
    lying = report("agent1/sensor/agent1-lidars")
    lying.header.source_id = "agent3/sensor/agent1-lidars"  # right names, another scope
    assert "not believed" in (key_mismatch(key, lying) or "")
    assert "not a health key" in (key_mismatch("rmmdet/v1/agent1/@alive/sensor/x", lying) or "")


def test_a_sharded_coordinator_meets_the_coordinator_expectation() -> None:
    expected = expected_services(Scene.load(DEFAULT_SCENE))
    present = [s for s in expected if s != "cloud/coordinator/cloud"]
    shards = ["cloud/coordinator/region0", "cloud/coordinator/region1"]
    verdict = judge(
        [report(s) for s in present + shards], [], [alive_key(s) for s in present + shards], expected
    )
    assert verdict.ok, verdict.problems
    degraded = report(shards[0], DEGRADED, "3/3 agents LIVE; regions [1] planned on a prior")
    verdict = judge(
        [report(s) for s in present] + [degraded], [], [alive_key(s) for s in present + shards[:1]], expected
    )
    assert verdict.problems == [
        "cloud/coordinator/region0 DEGRADED: 3/3 agents LIVE; regions [1] planned on a prior"
    ]
