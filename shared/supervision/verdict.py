"""Is the closed loop doing its job? One verdict for `rmmdet health`, the system benchmark and CI.

The loop is OK exactly when every service the scene calls for answers its `@health` query and reports
NOMINAL: the router, the sim, one sensor service per sensor group, one MEC per agent (NOMINAL = its
output FULL) and the coordinator (NOMINAL = every agent LIVE). Anything else makes the verdict fail,
and its `problems` say what is missing, one line each: a service that never answered, one that is
alive (liveliness token) but silent (hung main loop), and every report below NOMINAL with its message.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import zenoh
from rmmdet.v1.health_pb2 import HealthLevel, ServiceHealth

from shared.bus import names
from shared.bus.codec import Counters, MessageDecoder
from shared.bus.liveliness import alive_tokens, source_of_token
from shared.bus.streams import get_stream, region_of_instance, sensor_group_source
from shared.scene.scene import Scene

HEALTH_STREAM = get_stream("health")
HEALTH_KEYS = HEALTH_STREAM.pattern()
ALIVE_KEYS = get_stream("alive").pattern()
COORDINATOR = f"cloud/{names.COORDINATOR}/cloud"


def level_name(level: int) -> str:
    return HealthLevel.Name(level).removeprefix("HEALTH_LEVEL_")


def _is_shard(source: str) -> bool:
    """`source` (scope/service/instance) is a coordinator region shard."""
    scope, _, rest = source.partition("/")
    service, _, instance = rest.partition("/")
    return (scope, service) == ("cloud", names.COORDINATOR) and region_of_instance(instance) is not None


def expected_services(scene: Scene) -> list[str]:
    """`scope/service/instance` of every service the closed loop needs, from the scene. The coordinator
    may run sharded instead (instances region<k>, services/coordinator/shard.py): any shard present meets
    the expectation, since each shard is DEGRADED while another region's shard is silent."""
    out = [f"site/{names.ROUTER}/main", f"sim/{names.SIM}/main", COORDINATOR]
    for agent in scene.agents:
        out.append(f"{agent}/{names.MEC}/{agent}")
        kinds = sorted({s.kind for s in scene.sensors_of(agent)})
        out += [sensor_group_source(agent, kind) for kind in kinds]
    return out


def query_health(session: zenoh.Session, timeout_s: float = 2.0) -> tuple[list[ServiceHealth], list[str]]:
    """Health reports of every service, and reply errors (undecodable replies)."""
    decoder = MessageDecoder(ServiceHealth, Counters())
    reports: list[ServiceHealth] = []
    errors: list[str] = []
    # Every queryable must answer: ALL targets, no consolidation of replies.
    replies = session.get(
        HEALTH_KEYS,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
    )
    for reply in replies:
        if reply.ok is None:
            said = reply.err.payload.to_bytes()[:200] if reply.err is not None else b""
            errors.append(f"error reply: {said!r}")
            continue
        decoded = decoder.decode(reply.ok.payload.to_bytes(), str(reply.ok.encoding))
        if decoded is None:
            errors.append(f"{reply.ok.key_expr}: undecodable health reply")
        elif problem := key_mismatch(str(reply.ok.key_expr), decoded.message):
            errors.append(problem)
        else:
            reports.append(decoded.message)
    return reports, errors


def key_mismatch(key: str, report: ServiceHealth) -> str | None:
    """Why a health reply is not believed: its body names another service than the key it came on
    (where an ACL binds keys to identities, the key is the one a replier cannot choose; the body is its
    own word), or the key is no health key; None if they agree."""
    ids = HEALTH_STREAM.ids(key)
    if ids is None:
        return f"{key}: not a health key"
    said = f"{report.header.source_id or '?'} ({report.service}/{report.instance})"
    source = f"{ids['scope']}/{ids['service']}/{ids['instance']}"
    if (report.service, report.instance) != (ids["service"], ids["instance"]) or (
        report.header.source_id and report.header.source_id != source
    ):
        return f"{key}: the reply calls itself {said}, its key {source}: not believed"
    return None


@dataclass
class Verdict:
    """The loop's state at one probe. `ok` is what `rmmdet health` exits 0 on."""

    reports: list[ServiceHealth]
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return bool(self.reports) and not self.problems

    def summary(self) -> str:
        if self.ok:
            return f"loop OK: {len(self.reports)} services NOMINAL"
        return "loop NOT OK: " + "; ".join(self.problems)


def judge(
    reports: Iterable[ServiceHealth],
    errors: Iterable[str],
    alive: Iterable[str],
    expected: Iterable[str],
    service: str | None = None,
) -> Verdict:
    """Verdict from one probe's replies, reply errors and liveliness tokens (`service`: only that one)."""
    chosen = sorted(
        (r for r in reports if service is None or r.service == service),
        key=lambda r: (r.service, r.instance),
    )
    verdict = Verdict(chosen)
    answered = {r.header.source_id for r in chosen}
    for r in chosen:
        if r.level != HealthLevel.HEALTH_LEVEL_NOMINAL:
            verdict.problems.append(f"{r.header.source_id} {level_name(r.level)}: {r.message}")
    alive_ids = set()
    for key in alive:
        source = source_of_token(key)
        if source is None:
            continue
        alive_ids.add(source)
        if source not in answered and (service is None or source.split("/")[1] == service):
            verdict.problems.append(f"{source} alive but no health reply")
    present = answered | alive_ids
    for source in expected:
        if source in present or (source == COORDINATOR and any(_is_shard(p) for p in present)):
            continue
        if service is None or source.split("/")[1] == service:
            verdict.problems.append(f"{source} not running")
    verdict.problems += list(errors)
    if not chosen:
        verdict.problems.append("no service answered (is `make up` running?)")
    return verdict


def probe(
    session: zenoh.Session, scene: Scene | None, timeout_s: float = 2.0, service: str | None = None
) -> Verdict:
    """Query every service's health and the liveliness tokens, and judge the loop (`scene` None: only
    the services that run, for a partial system)."""
    reports, errors = query_health(session, timeout_s)
    alive = alive_tokens(session, ALIVE_KEYS, timeout_s)
    return judge(reports, errors, alive, expected_services(scene) if scene else [], service)
