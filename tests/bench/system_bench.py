"""Whole-system benchmark: exactly what `make up` starts, measured while it all runs.

    python -m tests.bench.system_bench [--minutes 10] [--warmup-s 60] [--speed 1] [--record-s 120]
                                       [--label TEXT] [--readme]
    python -m tests.bench.system_bench --render-only    # the docs' table again from the results file

Starts the system with `make up` (refuses if it is already up), lets it settle `--warmup-s`, then
measures for `--minutes` and stops it with `make down`. The judge of every performance change: a
component benchmark says what a part costs alone, this one what the loop does with everything running.

Measured (results appended to `tests/bench/results/system.json` under `runs`, one per label):
- CPU share of every process (a whole core = 1.0), resident memory, threads and file descriptors;
- the loop verdict (`shared/supervision/verdict.py`, the same as `rmmdet health`) at a probe every 10 s;
- rates of every stream, from the services' own input monitors (health reports) and, for the loop's
  outputs, from this process's subscriptions to objects, traffic maps, plans, plan acks and the clock;
- latency sensor stamp -> objects, objects -> traffic map and objects -> plan at the vehicle, p50 / p95,
  in simulated time (the sim clock's samples map each arrival to sim time) and in wall time. A plan
  reaches its vehicle as a query reply (most) or a push; either way the vehicle answers with a RouteAck
  whose header keeps the plan's stamp (the newest object list the plan's map was made from), so the ack's
  arrival closes objects -> map -> plan for every plan; pushed plans are also reported on their own;
- each MEC's output status (fraction FULL), the coordinator's coverage (fraction of maps with every
  agent LIVE, state changes per agent), the sim's real-time factor over the window;
- the CPU model and its vector flags, and the commit;
- the CPU used meanwhile by everything else on the host (`host.other_cpu_cores`: all busy CPU less the
  system's processes and this one's) and by this process itself: a run on a busy host is no measurement
  of the system (runs O-T in the README lost ~4 % real-time factor to a concurrent evaluation), so the
  README table shows it next to every run.

`--record-s N` runs `rmmdet record` of the whole bus for the first N seconds of the window (the
recording is deleted afterwards); its CPU is reported with the rest.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import zenoh
from rmmdet.v1.perception_pb2 import PerceptionStatus, TrackedObjects
from rmmdet.v1.planning_pb2 import RouteAck, RoutePlan
from rmmdet.v1.sim_pb2 import SimClock
from rmmdet.v1.traffic_pb2 import AgentState, TrafficMap

from shared.bus.codec import Counters, MessageDecoder
from shared.bus.session import open_session
from shared.bus.streams import get_stream
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.machine import git_commit, machine_info
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.readme import replace_section
from shared.scene.scene import Scene
from shared.supervision.profiles import Choice, compose
from shared.supervision.verdict import level_name, probe
from shared.timebase import NS_PER_S

RESULTS = REPO_ROOT / "tests" / "bench" / "results" / "system.json"
SUPERVISOR_CONF = REPO_ROOT / "deploy" / "local" / "supervisord.conf"
PROBE_EVERY_S = 10.0
VIEW_CLIENT = "view-client"  # --view-client: its process, sampled like the system's, not counted in it
DEFAULT_PROFILE_SCENE = Choice().scene  # `make up` without SCENE=
OTHER_LOAD_WARN_CORES = 0.1  # other work on the host beyond this makes the run no measurement of the system


def supervised_pids() -> dict[str, int]:
    """Program name -> pid of every RUNNING supervisord program."""
    out = subprocess.run(
        [str(REPO_ROOT / ".venv" / "bin" / "supervisorctl"), "-c", str(SUPERVISOR_CONF), "status"],
        capture_output=True,
        text=True,
    ).stdout
    pids = {}
    for line in out.splitlines():
        m = re.match(r"(\S+)\s+RUNNING\s+pid (\d+)", line)
        if m:
            pids[m.group(1)] = int(m.group(2))
    return pids


def pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def host_busy_s() -> float:
    """CPU seconds the whole host has been busy (all cores; idle and I/O wait excluded)."""
    t = psutil.cpu_times()
    return sum(t) - t.idle - getattr(t, "iowait", 0.0)


def own_cpu_s() -> float:
    t = psutil.Process().cpu_times()
    return t.user + t.system


class ProcessSampler:
    """CPU seconds, RSS, threads and fds of named processes (each with its children)."""

    def __init__(self) -> None:
        self.procs: dict[str, psutil.Process] = {}
        self.start_cpu: dict[str, float] = {}
        self.samples: dict[str, list[dict[str, float]]] = defaultdict(list)
        self.restarts: Counter[str] = Counter()

    def _cpu(self, proc: psutil.Process) -> float:
        total = 0.0
        for p in [proc, *proc.children(recursive=True)]:
            try:
                t = p.cpu_times()
                total += t.user + t.system
            except psutil.Error:
                pass
        return total

    def track(self, name: str, pid: int) -> None:
        if name in self.procs and self.procs[name].pid == pid:
            return
        if name in self.procs:
            self.restarts[name] += 1
        try:
            proc = psutil.Process(pid)
            self.procs[name] = proc
            self.start_cpu[name] = self.start_cpu.get(name, 0.0) - self._cpu(proc)
        except psutil.Error:
            pass

    def sample(self) -> None:
        for name, proc in self.procs.items():
            try:
                with proc.oneshot():
                    self.samples[name].append(
                        {
                            "t_s": time.monotonic(),
                            "rss_mb": proc.memory_info().rss / 1e6,
                            "threads": proc.num_threads(),
                            "fds": proc.num_fds(),
                        }
                    )
            except psutil.Error:
                pass

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds since tracking began (restarts: the processes before a restart are lost)."""
        out = {}
        for name, proc in self.procs.items():
            try:
                out[name] = self.start_cpu[name] + self._cpu(proc)
            except psutil.Error:
                out[name] = max(0.0, self.start_cpu[name])
        return out


@dataclass
class Tap:
    """What this process hears of the loop's outputs."""

    clock: list[tuple[int, int, float]] = field(default_factory=list)  # (wall ns, sim ns, rtf)
    objects: dict[str, list[tuple[int, int, int, int]]] = field(default_factory=lambda: defaultdict(list))
    maps: list[tuple[int, int, dict[str, int]]] = field(default_factory=list)  # (wall, stamp, states)
    plans: list[tuple[int, int]] = field(default_factory=list)  # pushed plans: (wall, stamp)
    acks: list[tuple[int, int]] = field(default_factory=list)  # plans applied by vehicles: (wall, stamp)
    lock: threading.Lock = field(default_factory=threading.Lock)


def subscribe(session: zenoh.Session, tap: Tap) -> list[Any]:
    counters = Counters()
    dec_clock = MessageDecoder(SimClock, counters)
    dec_obj = MessageDecoder(TrackedObjects, counters)
    dec_map = MessageDecoder(TrafficMap, counters)
    dec_plan = MessageDecoder(RoutePlan, counters)
    dec_ack = MessageDecoder(RouteAck, counters)

    def payload(sample: zenoh.Sample) -> tuple[bytes, str, bytes | None]:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        return sample.payload.to_bytes(), str(sample.encoding), att

    def on_clock(sample: zenoh.Sample) -> None:
        d = dec_clock.decode(*payload(sample))
        if d is not None:
            with tap.lock:
                tap.clock.append(
                    (time.time_ns(), d.message.sim_time.ToNanoseconds(), d.message.real_time_factor)
                )

    def on_objects(sample: zenoh.Sample) -> None:
        d = dec_obj.decode(*payload(sample))
        if d is not None:
            agent = str(sample.key_expr).split("/")[2]
            with tap.lock:
                tap.objects[agent].append(
                    (time.time_ns(), d.header.stamp.ToNanoseconds(), d.header.tick, d.message.status)
                )

    def on_map(sample: zenoh.Sample) -> None:
        d = dec_map.decode(*payload(sample))
        if d is not None:
            states = {c.agent_id: c.state for c in d.message.coverage}
            with tap.lock:
                tap.maps.append((time.time_ns(), d.header.stamp.ToNanoseconds(), states))

    def on_plan(sample: zenoh.Sample) -> None:
        d = dec_plan.decode(*payload(sample))
        if d is not None:
            with tap.lock:
                tap.plans.append((time.time_ns(), d.header.stamp.ToNanoseconds()))

    def on_ack(sample: zenoh.Sample) -> None:
        d = dec_ack.decode(*payload(sample))
        if d is not None:
            with tap.lock:
                tap.acks.append((time.time_ns(), d.header.stamp.ToNanoseconds()))

    return [
        session.declare_subscriber(get_stream("sim_clock").pattern(), on_clock),
        session.declare_subscriber(get_stream("objects").pattern(), on_objects),
        session.declare_subscriber(get_stream("traffic_map").pattern(), on_map),
        session.declare_subscriber(get_stream("route_plan").pattern(), on_plan),
        session.declare_subscriber(get_stream("route_ack").pattern(), on_ack),
    ]


def sim_time_of(clock: list[tuple[int, int, float]], wall_ns: np.ndarray) -> np.ndarray:
    """Simulated time (sim-epoch ns) at wall instants, interpolated between sim clock samples."""
    c = np.array([(w, s) for w, s, _ in clock], dtype=np.float64)
    return np.interp(wall_ns.astype(np.float64), c[:, 0], c[:, 1])


def latency_stats(sim_ms: np.ndarray, wall_ms: np.ndarray) -> dict[str, Any]:
    return {
        "count": len(sim_ms),
        "sim_p50_ms": pct(list(sim_ms), 50),
        "sim_p95_ms": pct(list(sim_ms), 95),
        "wall_p50_ms": pct(list(wall_ms), 50),
        "wall_p95_ms": pct(list(wall_ms), 95),
    }


def analyse(tap: Tap, t0_wall_ns: int, t1_wall_ns: int) -> dict[str, Any]:
    with tap.lock:
        clock = [c for c in tap.clock]
        objects = {a: list(v) for a, v in tap.objects.items()}
        maps = list(tap.maps)
        plans = list(tap.plans)
        acks = list(tap.acks)
    inside = [c for c in clock if t0_wall_ns <= c[0] <= t1_wall_ns]
    out: dict[str, Any] = {}
    if len(inside) < 2:
        return {"error": "no sim clock heard"}
    sim_s = (inside[-1][1] - inside[0][1]) / NS_PER_S
    wall_s = (inside[-1][0] - inside[0][0]) / NS_PER_S
    out["sim"] = {"sim_s": sim_s, "wall_s": wall_s, "real_time_factor": sim_s / wall_s}
    agents: dict[str, Any] = {}
    for agent, rows in sorted(objects.items()):
        r = np.array([x for x in rows if t0_wall_ns <= x[0] <= t1_wall_ns], dtype=np.int64)
        if len(r) == 0:
            agents[agent] = {"messages": 0}
            continue
        sim_ms = (sim_time_of(clock, r[:, 0]) - r[:, 1]) / 1e6
        wall_ms = (r[:, 0] - r[:, 1]) / 1e6
        ticks = np.diff(r[:, 2])
        agents[agent] = {
            "messages": len(r),
            "rate_hz_sim": len(r) / sim_s,
            "rate_hz_wall": len(r) / wall_s,
            "fraction_full": float(np.mean(r[:, 3] == PerceptionStatus.PERCEPTION_STATUS_FULL)),
            "ticks_per_output_p50": pct(list(ticks), 50) if len(ticks) else None,
            "sensor_to_objects": latency_stats(sim_ms, wall_ms),
        }
    out["agents"] = agents
    m = [x for x in maps if t0_wall_ns <= x[0] <= t1_wall_ns]
    if m:
        w = np.array([x[0] for x in m], dtype=np.int64)
        s = np.array([x[1] for x in m], dtype=np.int64)
        ok = s > 0
        all_live = [bool(x[2]) and all(v == AgentState.AGENT_STATE_LIVE for v in x[2].values()) for x in m]
        changes: Counter[str] = Counter()
        for prev, cur in itertools.pairwise(m):
            for agent, state in cur[2].items():
                if prev[2].get(agent) != state:
                    changes[agent] += 1
        out["coordinator"] = {
            "maps": len(m),
            "fraction_all_live": float(np.mean(all_live)),
            "coverage_changes": dict(changes),
            "objects_to_map": latency_stats((sim_time_of(clock, w[ok]) - s[ok]) / 1e6, (w[ok] - s[ok]) / 1e6),
        }
    for name, rows in (("objects_to_plan", acks), ("objects_to_pushed_plan", plans)):
        p = [x for x in rows if t0_wall_ns <= x[0] <= t1_wall_ns and x[1] > 0]
        if p:
            w = np.array([x[0] for x in p], dtype=np.int64)
            s = np.array([x[1] for x in p], dtype=np.int64)
            out.setdefault("coordinator", {})[name] = latency_stats(
                (sim_time_of(clock, w) - s) / 1e6, (w - s) / 1e6
            )
        else:
            out.setdefault("coordinator", {})[name] = {"count": 0}
    return out


def input_rates(reports: list[Any]) -> dict[str, dict[str, float]]:
    """Per service, the rate of each input its monitor measured (Hz of wall time)."""
    rates: dict[str, dict[str, float]] = {}
    for r in reports:
        rates[r.header.source_id] = {i.key_expr: round(i.rate_hz, 2) for i in r.inputs if i.rate_hz > 0}
    return rates


def run(args: argparse.Namespace) -> dict[str, Any]:
    if supervised_pids():
        raise SystemExit("the system is already up: `make down` first (this benchmark starts it itself)")
    env = dict(os.environ)
    make = ["make", "-C", str(REPO_ROOT), "up", f"SENSORS={args.sensors}", f"SCENE={args.scene}"] + (
        [f"SPEED={args.speed}"] if args.speed != 1.0 else []
    )
    profile, _ = compose(Choice(scene=args.scene))
    scene = Scene.load(profile.scene or DEFAULT_SCENE)
    sampler = ProcessSampler()
    tap = Tap()
    probes: list[dict[str, Any]] = []
    rates: dict[str, list[dict[str, float]]] = defaultdict(list)
    recorder: subprocess.Popen[bytes] | None = None
    view_client: subprocess.Popen[bytes] | None = None
    end = math.inf
    view_rates = Path()
    recording = Path(tempfile.mkdtemp()) / "bench.mcap"
    subprocess.run(make, check=True, env=env, stdout=subprocess.DEVNULL)
    try:
        session = open_session(zenoh_config(DEFAULT_CLIENT_CONFIG), timeout_s=10)
        subs = subscribe(session, tap)
        print(f"system up; warming up {args.warmup_s:.0f} s", flush=True)
        time.sleep(args.warmup_s)
        for name, pid in supervised_pids().items():
            sampler.track(name, pid)
        view_rates = Path(tempfile.mkdtemp()) / "view_client.json"
        if args.view_client:
            view_client = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "tests.bench.view_client",
                    "--seconds",
                    str(args.minutes * 60),
                    "--out",
                    str(view_rates),
                ],
                cwd=REPO_ROOT,
                stdout=subprocess.DEVNULL,
            )
            sampler.track(VIEW_CLIENT, view_client.pid)
        if args.record_s > 0:
            recorder = subprocess.Popen(
                [
                    str(REPO_ROOT / ".venv" / "bin" / "rmmdet"),
                    "record",
                    "--out",
                    str(recording),
                    "--duration",
                    str(args.record_s),
                ],
                stdout=subprocess.DEVNULL,
            )
            sampler.track("recorder", recorder.pid)
        t0 = time.time_ns()
        t0_mono = time.monotonic()
        host0, own0 = host_busy_s(), own_cpu_s()
        end = t0_mono + args.minutes * 60
        next_probe = t0_mono
        while time.monotonic() < end:
            time.sleep(max(0.0, min(next_probe, end) - time.monotonic()))
            if time.monotonic() >= end:
                break
            next_probe += PROBE_EVERY_S
            verdict = probe(session, scene)
            probes.append(
                {
                    "t_s": round(time.monotonic() - t0_mono, 1),
                    "ok": verdict.ok,
                    "problems": verdict.problems,
                    "levels": {r.header.source_id: level_name(r.level) for r in verdict.reports},
                }
            )
            for source, r in input_rates(verdict.reports).items():
                rates[source].append(r)
            for name, pid in supervised_pids().items():
                sampler.track(name, pid)
            sampler.sample()
            print(f"  {probes[-1]['t_s']:6.0f} s  {verdict.summary()[:160]}", flush=True)
        t1 = time.time_ns()
        wall_s = (t1 - t0) / NS_PER_S
        cpu = sampler.cpu_seconds()
        host_s, own_s = host_busy_s() - host0, own_cpu_s() - own0
        for sub in subs:
            sub.undeclare()
        session.close()
    finally:
        if view_client is not None:
            try:  # it ends with the window; on an early exit (an error, ^C) it is stopped
                view_client.wait(timeout=60 if time.monotonic() >= end else 0)
            except subprocess.TimeoutExpired:
                view_client.terminate()
                view_client.wait(timeout=10)
        if recorder is not None:
            recorder.wait(timeout=60)
        recording.unlink(missing_ok=True)
        subprocess.run(["make", "-C", str(REPO_ROOT), "down"], stdout=subprocess.DEVNULL)
    result = analyse(tap, t0, t1)
    result["processes"] = {
        name: {
            "cpu_cores": round(cpu[name] / wall_s, 4),
            "rss_mb_max": round(max((s["rss_mb"] for s in sampler.samples[name]), default=0.0), 1),
            "threads_max": max((int(s["threads"]) for s in sampler.samples[name]), default=0),
            "fds_max": max((int(s["fds"]) for s in sampler.samples[name]), default=0),
            **drift(sampler.samples[name]),
            "rss_series_mb": rss_series(sampler.samples[name]),
            "restarts": sampler.restarts[name],
        }
        for name in sorted(cpu)
    }
    if view_client is not None:
        if view_client.returncode != 0 or not view_rates.exists():
            raise SystemExit(f"the view client failed (exit {view_client.returncode}): no figures with it")
        result["view_client_topics"] = json.loads(view_rates.read_text())
    # The system's own processes; the view client is the benchmark's, like its own probes.
    system = {n: p for n, p in result["processes"].items() if n != VIEW_CLIENT}
    result["cpu_cores_total"] = round(sum(p["cpu_cores"] for p in system.values()), 3)
    bench_cores = own_s / wall_s + result["processes"].get(VIEW_CLIENT, {}).get("cpu_cores", 0.0)
    result["host"] = {
        "busy_cores": round(host_s / wall_s, 3),
        "bench_cpu_cores": round(bench_cores, 3),
        # Kernel threads and short-lived processes count here too: ~0 on a quiet host.
        "other_cpu_cores": round(max(0.0, host_s / wall_s - bench_cores - result["cpu_cores_total"]), 3),
    }
    stream_rates: dict[str, dict[str, float]] = {}
    for source, samples in rates.items():
        keys = {k for s in samples for k in s}
        stream_rates[source] = {
            k: round(float(np.median([s[k] for s in samples if k in s])), 2) for k in keys
        }
    result["input_rates_hz"] = stream_rates
    result["probes"] = {
        "count": len(probes),
        "ok": sum(p["ok"] for p in probes),
        "failures": [p for p in probes if not p["ok"]][:20],
    }
    return result


def scene_of(run: dict[str, Any]) -> str:
    """The profile scene a run was made on (runs before the option ran the default)."""
    return str(run["args"].get("scene", DEFAULT_PROFILE_SCENE))


def acceptance(r: dict[str, Any]) -> dict[str, bool]:
    """The live-system issue's acceptance points, judged on one run."""
    agents = r.get("agents", {})
    coord = r.get("coordinator", {})
    plan = plan_latency(coord)
    return {
        "health_ok_every_probe": r["probes"]["count"] > 0 and r["probes"]["ok"] == r["probes"]["count"],
        "mec_full_99": bool(agents) and all(a.get("fraction_full", 0) >= 0.99 for a in agents.values()),
        "all_live_99": coord.get("fraction_all_live", 0) >= 0.99,
        "objects_10hz_sim": bool(agents)
        and all(a.get("rate_hz_sim", 0) >= 10 * 0.98 for a in agents.values()),
        "sensor_to_objects_p95_150ms": bool(agents)
        and all((a["sensor_to_objects"]["sim_p95_ms"] or 1e9) <= 150 for a in agents.values()),
        "objects_to_map_p95_250ms": (coord.get("objects_to_map", {}).get("sim_p95_ms") or 1e9) <= 250,
        "objects_to_plan_p95_250ms": plan.get("count", 0) > 0 and (plan.get("sim_p95_ms") or 1e9) <= 250,
        "rtf_098": r.get("sim", {}).get("real_time_factor", 0) >= 0.98,
        "cpu_le_1_5_cores": r["cpu_cores_total"] <= 1.5,
    }


def plan_latency(coord: dict[str, Any]) -> dict[str, Any]:
    """Objects -> plan at the vehicle (acks); runs before acks were heard have pushed plans only."""
    acked = coord.get("objects_to_plan", {})
    return acked if acked.get("count") else coord.get("objects_to_pushed_plan", {})


def fmt(v: Any, digits: int = 0) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def cpu_name(machine: dict[str, Any]) -> str:
    """The run's CPU model, short (runs on different hosts are not comparable: the VM's CPU changed)."""
    model = str(machine.get("cpu_model", "–"))
    return " ".join(model.replace("(R)", "").replace("(TM)", "").removesuffix(" Processor").split())


def readme_table(runs: list[dict[str, Any]]) -> str:
    lines = [
        "| run (label, commit) | speed | RTF | CPU cores | health OK probes | FULL % (a1/a2/a3) "
        "| all LIVE % | objects Hz sim (a1/a2/a3) | sensor→objects p50/p95 ms | objects→map p95 ms "
        "| objects→plan p95 ms (plans) | other load (cores) | host CPU |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        r = run["result"]
        agents = [r.get("agents", {}).get(a, {}) for a in ("agent1", "agent2", "agent3")]
        coord = r.get("coordinator", {})
        lat = [a.get("sensor_to_objects", {}) for a in agents]
        lines.append(
            f"| {run['label']} ({run['commit']}) | {run['args']['speed']}"
            + (f" + record {run['args']['record_s']:.0f} s" if run["args"]["record_s"] else "")
            + (" + view client" if run["args"].get("view_client") else "")
            + (" + SENSORS=wire" if run["args"].get("sensors", "sim") == "wire" else "")
            + (f" + SCENE={scene_of(run)}" if scene_of(run) != DEFAULT_PROFILE_SCENE else "")
            + f" | {fmt(r.get('sim', {}).get('real_time_factor'), 2)} | {r['cpu_cores_total']:.2f}"
            f" | {r['probes']['ok']}/{r['probes']['count']}"
            f" | {'/'.join(fmt(100 * a.get('fraction_full', math.nan), 1) for a in agents)}"
            f" | {fmt(100 * coord['fraction_all_live'], 1) if 'fraction_all_live' in coord else '–'}"
            f" | {'/'.join(fmt(a.get('rate_hz_sim'), 1) for a in agents)}"
            f" | {' / '.join(fmt(x.get('sim_p50_ms')) + '/' + fmt(x.get('sim_p95_ms')) for x in lat)}"
            f" | {fmt(coord.get('objects_to_map', {}).get('sim_p95_ms'))}"
            f" | {fmt(plan_latency(coord).get('sim_p95_ms'))} ({plan_latency(coord).get('count', 0)})"
            f" | {fmt(r.get('host', {}).get('other_cpu_cores'), 2)}"
            f" | {cpu_name(run.get('machine', {}))} |"
        )
    # The CPU budget table is the default `make up`'s: the newest run at 1x without a recording or a
    # view client.
    plain = [
        r
        for r in runs
        if r["args"]["speed"] == 1.0
        and not r["args"]["record_s"]
        and not r["args"].get("view_client")
        and r["args"].get("sensors", "sim") == "sim"
        and scene_of(r) == DEFAULT_PROFILE_SCENE
    ]
    last = (plain or runs)[-1]
    lines += [
        "",
        f'Per process (the CPU budget of the default `make up`), run "{last["label"]}" '
        f"({last['machine']['cpu_model']}, "
        f"{last['machine']['cpu_count']} cores, flags {' '.join(last['machine']['cpu_vector_flags'])}):",
        "",
        "| process | CPU (cores) | RSS max MB | RSS slope MB/h | threads (spread) | fds (spread) |",
        "|---|---|---|---|---|---|",
    ]
    for name, p in sorted(last["result"]["processes"].items(), key=lambda kv: -kv[1]["cpu_cores"]):
        slope = f"{p['rss_slope_mb_per_h']:+.1f}" if "rss_slope_mb_per_h" in p else "–"
        threads = (
            f"{p['threads_max']} ({p['threads_spread']})" if "threads_spread" in p else f"{p['threads_max']}"
        )
        fds = f"{p['fds_max']} ({p['fds_spread']})" if "fds_spread" in p else f"{p['fds_max']}"
        lines.append(
            f"| {name} | {p['cpu_cores']:.3f} | {p['rss_mb_max']:.0f} | {slope} | {threads} | {fds} |"
        )
    wire = [
        r
        for r in runs
        if r["args"].get("sensors", "sim") == "wire"
        and r["args"]["speed"] == 1.0
        and scene_of(r) == DEFAULT_PROFILE_SCENE
    ]
    if wire:
        lines += ["", *wire_cost_table(wire[-1], last)]
    return "\n".join(lines)


WIRE_BUDGET_CORES = 0.3  # issue 33: emulators + device services over the direct path's sensor groups


def wire_cost_table(wire: dict[str, Any], direct: dict[str, Any]) -> list[str]:
    """The sensor path's cost, per group: the direct path's sensor service against the wire profile's
    emulating sensor service + its device service (SENSORS=wire)."""
    wp, dp = wire["result"]["processes"], direct["result"]["processes"]
    groups = sorted(n for n in dp if n.endswith(("-cameras", "-lidars", "-radars")))
    lines = [
        f'Sensor path, direct (run "{direct["label"]}", {direct["commit"]}) against SENSORS=wire (run '
        f'"{wire["label"]}", {wire["commit"]}): CPU cores per sensor group',
        "",
        "| group | direct: sensor service | wire: emulating sensor service | wire: device service "
        "| difference |",
        "|---|---|---|---|---|",
    ]
    total = 0.0
    for g in groups:
        direct_c = dp[g]["cpu_cores"]
        emu, dev = (
            wp.get(g, {}).get("cpu_cores", math.nan),
            wp.get(f"{g}-device", {}).get("cpu_cores", math.nan),
        )
        total += emu + dev - direct_c
        lines.append(f"| {g} | {direct_c:.3f} | {emu:.3f} | {dev:.3f} | {emu + dev - direct_c:+.3f} |")
    lines.append(
        f"| all | | | | {total:+.3f} ({'within' if total <= WIRE_BUDGET_CORES else '**over**'} the "
        f"{WIRE_BUDGET_CORES} budget) |"
    )
    return lines


def rss_series(samples: list[dict[str, float]], points: int = 60) -> list[list[float]]:
    """RSS over the window, at most `points` [minutes since the first sample, MB] pairs (the shape of
    a growth: a warm-up that levels off vs. a steady climb)."""
    if not samples:
        return []
    step = max(1, -(-len(samples) // points))  # ceil: never more than `points`
    t0 = samples[0]["t_s"]
    return [[round((s["t_s"] - t0) / 60, 1), round(s["rss_mb"], 1)] for s in samples[::step]]


def drift(samples: list[dict[str, float]]) -> dict[str, float | int]:
    """What a leak looks like over the window (the soak criteria, docs/reliability.md M1): the least-squares
    slope of RSS in MB per hour, and the spread (max - min) of threads and file descriptors."""
    if len(samples) < 2:
        return {"rss_slope_mb_per_h": 0.0, "threads_spread": 0, "fds_spread": 0}
    t_h = np.array([s["t_s"] for s in samples]) / 3600.0
    rss = np.array([s["rss_mb"] for s in samples])
    slope = float(np.polyfit(t_h - t_h[0], rss, 1)[0]) if np.ptp(t_h) > 0 else 0.0
    threads = [int(s["threads"]) for s in samples]
    fds = [int(s["fds"]) for s in samples]
    return {
        "rss_slope_mb_per_h": round(slope, 2),
        "threads_spread": max(threads) - min(threads),
        "fds_spread": max(fds) - min(fds),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--minutes", type=float, default=10.0, help="measurement window, minutes")
    parser.add_argument("--warmup-s", type=float, default=60.0, help="settling time after `make up`, s")
    parser.add_argument("--speed", type=float, default=1.0, help="sim speed (make up SPEED=...)")
    parser.add_argument("--record-s", type=float, default=0.0, help="run `rmmdet record` this long, s")
    parser.add_argument(
        "--sensors",
        choices=("sim", "wire"),
        default="sim",
        help="make up SENSORS=...: wire = emulated devices",
    )
    parser.add_argument(
        "--scene", default=DEFAULT_PROFILE_SCENE, help="make up SCENE=... (deploy/profiles/scene)"
    )
    parser.add_argument("--label", default="default", help="name of this run in the results")
    parser.add_argument(
        "--view-client",
        action="store_true",
        help="keep a Foxglove client watching the layout's topics (tests/bench/view_client.py) throughout",
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--readme", action="store_true", help="rewrite the README's system table")
    parser.add_argument(
        "--render-only",
        action="store_true",
        help="run nothing: rewrite the docs' system table from the results file (--out)",
    )
    args = parser.parse_args(argv)
    if args.render_only:
        if not args.out.is_file():
            parser.error(f"--render-only: no results file {args.out}")
        replace_section("system-bench", readme_table(json.loads(args.out.read_text())["runs"]))
        return 0
    commit = git_commit()  # of the code `make up` starts (commits made while it runs are not in it)
    result = run(args)
    passed = acceptance(result)
    if result["host"]["other_cpu_cores"] > OTHER_LOAD_WARN_CORES:
        print(
            f"WARNING: {result['host']['other_cpu_cores']:.2f} cores used by other work meanwhile", flush=True
        )
    entry = {
        "label": args.label,
        "commit": commit,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "args": {
            "minutes": args.minutes,
            "warmup_s": args.warmup_s,
            "speed": args.speed,
            "record_s": args.record_s,
            "sensors": args.sensors,
            "scene": args.scene,
            "view_client": args.view_client,
        },
        "machine": machine_info(),
        "acceptance": passed,
        "result": result,
    }
    previous = json.loads(args.out.read_text()) if args.out.exists() else {"runs": []}
    runs = [r for r in previous["runs"] if r["label"] != args.label] + [entry]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"runs": runs}, indent=1) + "\n")
    table = readme_table(runs)
    print(table)
    print(json.dumps(passed, indent=1))
    if args.readme:
        replace_section("system-bench", table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
