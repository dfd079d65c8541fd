"""Faults on the whole system: what `make up` does when a sensor group freezes, or the router restarts
or freezes.

    python -m tests.bench.fault_bench [--group agent1-lidars] [--freeze-s 15] [--warmup-s 45]
                                      [--router-freeze-s 5] [--readme]

The fault tests (tests/integration/test_mec_faults.py, test_router_restart.py) run small chains that
fit a CI machine; this runs the same faults with everything `make up` starts, on a host as busy as the
default system makes it. Starts the system (refuses if it is up), lets it settle, then:

- F3: SIGSTOP one sensor group (`--group`) for `--freeze-s`, then SIGCONT. Measured on its agent's
  object lists (subscribed here): when the output is DEGRADED naming one of the group's sensors, the
  output rate and largest gap while frozen (wall clock and stamps), and when it is FULL again.
- R1: SIGKILL the router (supervisord starts it again at once; the clients reconnect on their retry
  schedule). Measured: when every agent's object lists flow again, whether any agent changed state in
  the coordinator's maps, and the coordinator's plan counters (given up, resent) over the fault.
- R1 xN: SIGKILL the router `--router-kills` times, `--kill-every-s` apart (issue 34): per kill, when it
  was up again, held or not, when every agent's lists flowed and when `rmmdet health` was OK; the
  vehicles' route requests over all of them (unanswered, asked again, given up).
- R2: SIGSTOP the router for `--router-freeze-s` (its TCP connections stay open, nothing is forwarded),
  then SIGCONT. Measured as R1, from SIGCONT; and which programs were restarted meanwhile (a loop
  blocked on a full socket must not look stalled to the watchdog).

Results go to `tests/bench/results/faults.json` (one run per call, with the machine and the commit);
`--readme` puts the latest run in the README (`fault-bench`).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh
from rmmdet.v1.perception_pb2 import INPUT_STATE_OK, PERCEPTION_STATUS_DEGRADED, PERCEPTION_STATUS_FULL

from shared.bus.codec import Counters, MessageDecoder
from shared.bus.session import open_session
from shared.bus.streams import get_stream
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.machine import git_commit, machine_info
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.readme import replace_section
from shared.scene.scene import Scene
from shared.supervision.verdict import probe, query_health
from tests.bench.system_bench import supervised_pids
from tests.integration.coordinator_client import STATE_NAMES

RESULTS = REPO_ROOT / "tests" / "bench" / "results" / "faults.json"
SUPERVISORCTL = [
    str(REPO_ROOT / ".venv" / "bin" / "supervisorctl"),
    "-c",
    str(REPO_ROOT / "deploy/local/supervisord.conf"),
]
AGENTS = ("agent1", "agent2", "agent3")


@dataclass
class Watch:
    """Object lists per agent (wall arrival, stamp s, status, inputs not OK) and maps (arrival, states)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    objects: dict[str, list[tuple[float, float, int, frozenset[str]]]] = field(
        default_factory=lambda: {a: [] for a in AGENTS}
    )
    maps: list[tuple[float, dict[str, str]]] = field(default_factory=list)

    def subscribe(self, session: zenoh.Session) -> list[Any]:
        objects, maps = get_stream("objects"), get_stream("traffic_map")
        obj_dec = MessageDecoder(objects.message_type, Counters())
        map_dec = MessageDecoder(maps.message_type, Counters())

        def on_objects(sample: zenoh.Sample) -> None:
            d = obj_dec.decode(sample.payload.to_bytes(), str(sample.encoding))
            if d is None:
                return
            agent = objects.id_of(str(sample.key_expr), "agent")
            bad = frozenset(i.sensor_id for i in d.message.inputs if i.state != INPUT_STATE_OK)
            row = (time.monotonic(), d.header.stamp.ToNanoseconds() / 1e9, d.message.status, bad)
            with self.lock:
                self.objects.setdefault(agent, []).append(row)

        def on_map(sample: zenoh.Sample) -> None:
            d = map_dec.decode(sample.payload.to_bytes(), str(sample.encoding))
            if d is not None:
                states = {c.agent_id: STATE_NAMES.get(c.state, "?") for c in d.message.coverage}
                with self.lock:
                    self.maps.append((time.monotonic(), states))

        return [
            session.declare_subscriber(objects.pattern(), on_objects),
            session.declare_subscriber(maps.pattern(), on_map),
        ]

    def rows(
        self, agent: str, t0: float, t1: float = float("inf")
    ) -> list[tuple[float, float, int, frozenset[str]]]:
        with self.lock:
            return [r for r in self.objects[agent] if t0 <= r[0] < t1]


def first(rows: list, pred) -> float | None:
    return next((r[0] for r in rows if pred(r)), None)


def sensors_of_group(group: str) -> set[str]:
    agent, kind = group.split("-")
    return {s.id for s in Scene.load(DEFAULT_SCENE).sensors_of(agent, kind.removesuffix("s"))}  # type: ignore[arg-type]


def freeze(watch: Watch, group: str, freeze_s: float) -> dict[str, Any]:
    agent, sensors = group.split("-")[0], sensors_of_group(group)
    pid = supervised_pids()[group]
    before = watch.rows(agent, time.monotonic() - 1.0)[-1:]
    t_stop = time.monotonic()
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(freeze_s)
    finally:
        os.kill(pid, signal.SIGCONT)
    t_cont = time.monotonic()
    time.sleep(5.0)
    during = before + watch.rows(agent, t_stop, t_cont)
    wall_gaps = [b[0] - a[0] for a, b in itertools.pairwise(during)]
    stamp_gaps = [b[1] - a[1] for a, b in itertools.pairwise(during)]
    span = during[-1][1] - during[0][1] if len(during) > 1 else 0.0
    degraded = first(
        watch.rows(agent, t_stop), lambda r: r[2] == PERCEPTION_STATUS_DEGRADED and bool(r[3] & sensors)
    )
    full = first(watch.rows(agent, t_cont), lambda r: r[2] == PERCEPTION_STATUS_FULL)
    return {
        "group": group,
        "freeze_s": freeze_s,
        "degraded_after_s": None if degraded is None else degraded - t_stop,
        "rate_hz_wall": (len(during) - 1) / (during[-1][0] - during[0][0]) if len(during) > 1 else 0.0,
        "rate_hz_stamps": (len(during) - 1) / span if span > 0 else 0.0,
        "max_gap_s_wall": max(wall_gaps, default=None),
        "max_gap_s_stamps": max(stamp_gaps, default=None),
        "full_after_sigcont_s": None if full is None else full - t_cont,
    }


def coordinator_counters(session: zenoh.Session) -> dict[str, int]:
    reports, _ = query_health(session)
    return {c.name: c.value for r in reports if r.service == "coordinator" for c in r.counters}


def router_restart(watch: Watch, session: zenoh.Session) -> dict[str, Any]:
    before, pids = coordinator_counters(session), supervised_pids()
    old_pid = pids["router"]
    t_kill = time.monotonic()
    subprocess.run([*SUPERVISORCTL, "signal", "KILL", "router"], check=True, capture_output=True)
    deadline = t_kill + 30.0
    while supervised_pids().get("router", old_pid) == old_pid:  # a new router process RUNNING
        if time.monotonic() > deadline:
            raise SystemExit("the router did not come back")
        time.sleep(0.05)
    t_back = time.monotonic()
    return {
        "router_up_after_kill_s": t_back - t_kill,
        **router_aftermath(watch, session, t_kill, t_back, before, pids),
    }


def sim_counters(session: zenoh.Session) -> dict[str, int]:
    reports, _ = query_health(session)
    return {c.name: c.value for r in reports if r.service == "sim" for c in r.counters}


def health_ok_after(session: zenoh.Session, scene: Scene, t_from: float, limit_s: float) -> float | None:
    """Seconds from `t_from` until `rmmdet health`'s verdict is OK (probing every 0.25 s), None if not
    within `limit_s`."""
    while time.monotonic() - t_from <= limit_s:
        if probe(session, scene, timeout_s=1.0).ok:
            return time.monotonic() - t_from
        time.sleep(0.25)
    return None


def objects_again(watch: Watch, t_from: float, limit_s: float) -> dict[str, float | None]:
    """When each agent's first object list after `t_from` arrived (monotonic s), waiting for them up to
    `limit_s` after `t_from`; None for an agent with none by then."""
    while True:
        flowing = {a: first(watch.rows(a, t_from), lambda _r: True) for a in AGENTS}
        if all(t is not None for t in flowing.values()) or time.monotonic() - t_from > limit_s:
            return flowing
        time.sleep(0.05)


def router_kills(
    watch: Watch,
    session: zenoh.Session,
    kills: int,
    every_s: float,
    scene: Scene,
    health_limit_s: float | None = None,
) -> dict[str, Any]:
    """The router SIGKILLed `kills` times, `every_s` apart (issue 34: a transient fault of the one process
    everything depends on must not become an outage). Per kill: when supervisord had it up again, when
    every agent's object lists flowed again and when `rmmdet health` was OK, from its return; whether
    the watchdog held it (not RUNNING 5 s after a kill). Over all: the vehicles' route requests
    (requested, unanswered meanwhile, asked again, given up). `rmmdet health` is probed for up to
    `health_limit_s` after each return (default: until 2 s before the next kill)."""
    sim0 = sim_counters(session)
    rows = []
    for _ in range(kills):
        old_pid = supervised_pids()["router"]
        t_kill = time.monotonic()
        subprocess.run([*SUPERVISORCTL, "signal", "KILL", "router"], check=True, capture_output=True)
        while supervised_pids().get("router", old_pid) == old_pid:
            if time.monotonic() > t_kill + 5.0:
                break  # held or not restarted: recorded below
            time.sleep(0.05)
        t_back = time.monotonic()
        held = supervised_pids().get("router", old_pid) == old_pid
        limit_s = every_s - 2.0 if health_limit_s is None else health_limit_s
        health_s = None if held else health_ok_after(session, scene, t_back, limit_s)
        # Health can be OK again before the first object list arrives: wait for those too.
        flowing = objects_again(watch, t_back, every_s - 2.0)
        rows.append(
            {
                "router_up_after_kill_s": None if held else t_back - t_kill,
                "held": held,
                "objects_again_s": {a: None if t is None else t - t_back for a, t in flowing.items()},
                "health_ok_after_s": health_s,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
        time.sleep(max(0.0, t_kill + every_s - time.monotonic()))
    time.sleep(20.0)  # the last requests' retries (1 + 2 + 4 + 8 s) are over
    sim1 = sim_counters(session)
    names = ("plans/requested", "plans/replied", "plans/no_reply", "plans/retried", "plans/given_up")
    errors = sorted(k for k in sim1 if k.startswith("plans/error_"))  # refused: none expected
    requests = {k: sim1.get(k, 0) - sim0.get(k, 0) for k in (*names, *errors)}
    return {"kills": kills, "every_s": every_s, "each": rows, "requests": requests}


def router_freeze(watch: Watch, session: zenoh.Session, freeze_s: float) -> dict[str, Any]:
    before, pids = coordinator_counters(session), supervised_pids()
    t_stop = time.monotonic()
    subprocess.run([*SUPERVISORCTL, "signal", "STOP", "router"], check=True, capture_output=True)
    try:
        time.sleep(freeze_s)
    finally:
        subprocess.run([*SUPERVISORCTL, "signal", "CONT", "router"], check=True, capture_output=True)
    t_cont = time.monotonic()
    return {"freeze_s": freeze_s, **router_aftermath(watch, session, t_stop, t_cont, before, pids)}


def router_aftermath(
    watch: Watch, session: zenoh.Session, t_fault: float, t_back: float, before: dict[str, int], pids: dict
) -> dict[str, Any]:
    """What a router fault (at `t_fault`, over at `t_back`) did, 10 s after it was over."""
    time.sleep(10.0)
    after = coordinator_counters(session)
    now_pids = supervised_pids()
    flowing = {a: first(watch.rows(a, t_back), lambda _r: True) for a in AGENTS}
    with watch.lock:
        maps = [s for t, s in watch.maps if t >= t_fault]
    changes = {a: [k for k, _ in itertools.groupby(s.get(a, "?") for s in maps)] for a in AGENTS}
    return {
        "objects_again_after_restart_s": {a: None if t is None else t - t_back for a, t in flowing.items()},
        "restarted": sorted(p for p, pid in pids.items() if p != "router" and now_pids.get(p) != pid),
        "coverage_in_maps": changes,
        "plans": {
            k: after.get(k, 0) - before.get(k, 0) for k in ("plans/pushed", "plans/resent", "plans/given_up")
        },
        "missed": {k: v - before.get(k, 0) for k, v in after.items() if k.startswith("missed/")},
    }


def ms(v: float | None) -> str:
    return "–" if v is None else f"{v * 1e3:.0f} ms"


def router_row(rr: dict[str, Any]) -> str:
    """The measured side of a router fault's README row."""
    objects = ", ".join(f"{a} {ms(t)}" for a, t in rr["objects_again_after_restart_s"].items())
    coverage = "; ".join(f"{a} {' → '.join(s)}" for a, s in rr["coverage_in_maps"].items())
    restarted = ", ".join(rr.get("restarted", [])) or "none"
    return (
        f"object lists again {objects} after; coverage in the maps: {coverage}; plans {rr['plans']}; "
        f"missed {rr['missed'] or 0}; programs restarted: {restarted} |"
    )


def readme_table(r: dict[str, Any]) -> str:
    f, rr = r["freeze"], r["router"]
    rows = [
        f"| R1: router SIGKILLed (supervisord restarts it: up {rr['router_up_after_kill_s']:.2f} s later; "
        "times from then) | " + router_row(rr)
    ]
    if "router_kills" in r:
        rk = r["router_kills"]
        each = rk["each"]
        worst_objects = max(
            (t for row in each for t in row["objects_again_s"].values() if t is not None), default=None
        )
        health = [row["health_ok_after_s"] for row in each]
        worst_health = None if None in health else max(health, default=None)
        rows.append(
            f"| R1 x{rk['kills']}: router SIGKILLed {rk['kills']} times, {rk['every_s']:.0f} s apart "
            f"(times from each return) | held {sum(row['held'] for row in each)} times; object lists "
            f"again within {ms(worst_objects)} (worst agent, worst kill); `rmmdet health` OK within "
            f"{ms(worst_health)}; route requests {rk['requests']} |"
        )
    if "router_freeze" in r:
        rf = r["router_freeze"]
        rows.append(
            f"| R2: router SIGSTOPped {rf['freeze_s']:.0f} s (times from SIGCONT) | " + router_row(rf)
        )
    return "\n".join(
        [
            f"`python -m tests.bench.fault_bench --readme` at {r['commit']} ({r['machine']['cpu_model']}, "
            f"{r['machine']['cpu_count']} cores), with everything `make up` starts:",
            "",
            "| Fault | Measured |",
            "|---|---|",
            f"| F3: `{f['group']}` SIGSTOPped {f['freeze_s']:.0f} s | DEGRADED naming it "
            f"{ms(f['degraded_after_s'])} after; output {f['rate_hz_wall']:.2f} Hz (wall) / "
            f"{f['rate_hz_stamps']:.2f} Hz (stamps), largest gap {ms(f['max_gap_s_wall'])} (wall) / "
            f"{ms(f['max_gap_s_stamps'])} (stamps); FULL {ms(f['full_after_sigcont_s'])} after SIGCONT |",
            *rows,
        ]
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--group", default="agent1-lidars", help="sensor group to freeze")
    p.add_argument("--freeze-s", type=float, default=15.0)
    p.add_argument("--warmup-s", type=float, default=45.0)
    p.add_argument("--router-freeze-s", type=float, default=5.0, help="R2: the router SIGSTOPped this long")
    p.add_argument("--router-kills", type=int, default=5, help="R1 xN: the router SIGKILLed this many times")
    p.add_argument("--kill-every-s", type=float, default=15.0, help="R1 xN: seconds between the kills")
    p.add_argument("--readme", action="store_true", help="put the result in the README (fault-bench)")
    args = p.parse_args(argv)
    if supervised_pids():
        raise SystemExit("the system is already up: `make down` first (this benchmark starts it itself)")
    commit = git_commit()  # of the code `make up` starts
    subprocess.run(["make", "-C", str(REPO_ROOT), "up"], check=True, stdout=subprocess.DEVNULL)
    try:
        session = open_session(zenoh_config(DEFAULT_CLIENT_CONFIG), timeout_s=10)
        watch = Watch()
        subs = watch.subscribe(session)
        print(f"system up; warming up {args.warmup_s:.0f} s", flush=True)
        time.sleep(args.warmup_s)
        result = {"freeze": freeze(watch, args.group, args.freeze_s)}
        print(json.dumps(result["freeze"]), flush=True)
        time.sleep(5.0)
        result["router"] = router_restart(watch, session)
        print(json.dumps(result["router"]), flush=True)
        time.sleep(5.0)
        if args.router_kills:
            scene = Scene.load(DEFAULT_SCENE)
            result["router_kills"] = router_kills(watch, session, args.router_kills, args.kill_every_s, scene)
            print(json.dumps(result["router_kills"]["requests"]), flush=True)
            time.sleep(5.0)
        result["router_freeze"] = router_freeze(watch, session, args.router_freeze_s)
        print(json.dumps(result["router_freeze"]), flush=True)
        for s in subs:
            s.undeclare()
        session.close()
    finally:
        subprocess.run(["make", "-C", str(REPO_ROOT), "down"], stdout=subprocess.DEVNULL)
    result.update(commit=commit, machine=machine_info(), time=time.strftime("%Y-%m-%dT%H:%M:%S"))
    runs = json.loads(RESULTS.read_text())["runs"] if RESULTS.exists() else []
    RESULTS.write_text(json.dumps({"runs": [*runs, result]}, indent=1) + "\n")
    print(readme_table(result))
    if args.readme:
        replace_section("fault-bench", readme_table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
