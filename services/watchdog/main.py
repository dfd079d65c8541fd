"""Watchdog service: supervisord's programs watched through their health reports.

    python -m services.watchdog [--supervisor-url unix:///.../supervisor.sock] [--poll-s 0.25]
        [--stall-after-s 3] [--crash-starts 3] [--crash-window-s 60] [--backoff-s 30]

Every `--poll-s` it asks supervisord (XML-RPC on its socket) for its programs and every service for
its health (each report carries its pid and its main loop's heartbeat age; a pid claimed by two
replies, one of them forged, is not judged for a while: counted and logged; nor is a stall claimed
longer than the process has been up, nor one not seen uncontested over several polls), lets
`shared/supervision/watchdog.py` decide, and applies the decision through supervisord: a stalled
program is killed (supervisord's autorestart starts it afresh), a crash-looping one is stopped for its
backoff and started again after; a critical program (the router) is never held, and started again if
supervisord gives up on it. Its own health (scope `site`) is DEGRADED while a program is held and
names it, so `rmmdet health` reports crash loops; restarts and holds are counted. Runs under the same
supervisord (`deploy/local/supervisord.conf`); never acts on itself.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import xmlrpc.client

import zenoh
from supervisor.xmlrpc import SupervisorTransport

from shared.bus import names
from shared.bus.health import DEGRADED, NOMINAL
from shared.bus.node import Node
from shared.paths import RUN_DIR
from shared.service import exit_process, run_service
from shared.shutdown import GracefulShutdown
from shared.supervision.verdict import query_health
from shared.supervision.watchdog import Action, Program, Watchdog, WatchdogConfig, unambiguous_loop_ages

log = logging.getLogger("services.watchdog")

SCOPE = "site"
SERVICE = names.WATCHDOG
DEFAULT_SUPERVISOR_URL = f"unix://{RUN_DIR / 'supervisor.sock'}"
DEFAULT_CRITICAL = sorted(WatchdogConfig().critical)
CONFLICT_LOG_EVERY_S = 10.0


def supervisor_proxy(url: str) -> xmlrpc.client.ServerProxy:
    """supervisord's XML-RPC interface (a unix socket URL or http://host:port)."""
    return xmlrpc.client.ServerProxy("http://127.0.0.1", transport=SupervisorTransport(None, None, url))


def programs(proxy: xmlrpc.client.ServerProxy, own_pid: int) -> list[Program]:
    infos = proxy.supervisor.getAllProcessInfo()  # type: ignore[attr-defined]
    return [
        Program(i["name"], i["statename"], int(i["pid"]), float(i["start"]))
        for i in infos
        if int(i["pid"]) != own_pid
    ]


def apply(proxy: xmlrpc.client.ServerProxy, action: Action) -> None:
    try:
        if action.kind == "restart":
            proxy.supervisor.signalProcess(action.program, "KILL")  # type: ignore[attr-defined]
        elif action.kind == "hold":
            proxy.supervisor.stopProcess(action.program, False)  # type: ignore[attr-defined]
        else:
            proxy.supervisor.startProcess(action.program, False)  # type: ignore[attr-defined]
    except xmlrpc.client.Fault as err:  # e.g. it exited meanwhile: the next poll sees the new state
        log.warning("%s %s: supervisord says %s", action.kind, action.program, err.faultString)


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    try:
        cfg = WatchdogConfig(
            stall_after_s=args.stall_after_s,
            crash_starts=args.crash_starts,
            crash_window_s=args.crash_window_s,
            backoff_s=args.backoff_s,
            backoff_max_s=max(args.backoff_s, args.backoff_max_s),
            min_run_s=args.min_run_s,
            critical=frozenset(args.critical or DEFAULT_CRITICAL),
        )
    except ValueError as err:  # bad flags: one clear line, not a traceback
        raise SystemExit(f"watchdog: {err}") from None
    watchdog = Watchdog(cfg)
    proxy = supervisor_proxy(args.supervisor_url)
    own_pid = os.getpid()
    with Node(conf, service=SERVICE, instance=args.instance, scope=SCOPE, stop=shutdown.event) as node:
        held: dict[str, float] = {}
        last_conflict_log = -CONFLICT_LOG_EVERY_S

        def status() -> tuple[int, str]:
            if held:
                names = ", ".join(f"{n} (crash loop, held {s:.0f} s more)" for n, s in sorted(held.items()))
                return DEGRADED, names
            return NOMINAL, f"{watchdog.restarts} stalled restarts, {watchdog.holds} crash-loop holds"

        node.health.set_status(status)
        log.info(
            "watching %s: stall after %.1f s, crash loop %d starts in %.0f s (runs under %.0f s), backoff "
            "%.0f s, never held: %s",
            args.supervisor_url,
            cfg.stall_after_s,
            cfg.crash_starts,
            cfg.crash_window_s,
            cfg.min_run_s,
            cfg.backoff_s,
            ", ".join(sorted(cfg.critical)),
        )
        while not shutdown.wait(args.poll_s):
            node.health.beat()
            try:
                progs = programs(proxy, own_pid)
            except (OSError, xmlrpc.client.Error) as err:
                node.counters.inc("supervisor_unreachable")
                log.warning("supervisord unreachable: %s", err)
                continue
            reports, _ = query_health(node.session, timeout_s=args.poll_s)
            loop_age, conflicting = unambiguous_loop_ages((r.pid, r.loop_age_s) for r in reports)
            supervised_conflicts = conflicting & {p.pid for p in progs}
            if supervised_conflicts:
                node.counters.inc("health/conflicting_claims", len(supervised_conflicts))
                if time.monotonic() - last_conflict_log >= CONFLICT_LOG_EVERY_S:
                    last_conflict_log = time.monotonic()
                    log.warning(
                        "health replies disagree about pids %s: not judged", sorted(supervised_conflicts)
                    )
            implausible = watchdog.implausible_claims
            for action in watchdog.observe(time.time(), progs, loop_age, supervised_conflicts):
                log.warning("%s %s: %s", action.kind, action.program, action.reason)
                node.counters.inc(f"actions/{action.kind}")
                apply(proxy, action)
            if watchdog.implausible_claims > implausible:
                node.counters.inc("health/implausible_claims", watchdog.implausible_claims - implausible)
            held = watchdog.held(time.time())
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--supervisor-url", default=DEFAULT_SUPERVISOR_URL, help="supervisord XML-RPC URL")
    parser.add_argument("--poll-s", type=float, default=0.25, help="how often to look, s")
    defaults = WatchdogConfig()  # the one home of the decision's defaults
    parser.add_argument(
        "--stall-after-s", type=float, default=defaults.stall_after_s, help="restart a loop this stalled"
    )
    parser.add_argument(
        "--crash-starts",
        type=int,
        default=defaults.crash_starts,
        help="starts within the window that are a crash loop",
    )
    parser.add_argument("--crash-window-s", type=float, default=defaults.crash_window_s)
    parser.add_argument(
        "--backoff-s", type=float, default=defaults.backoff_s, help="first hold of a crash loop"
    )
    parser.add_argument("--backoff-max-s", type=float, default=defaults.backoff_max_s)
    parser.add_argument(
        "--min-run-s",
        type=float,
        default=defaults.min_run_s,
        help="a run at least this long before its exit is no crash",
    )
    parser.add_argument(
        "--critical",
        action="append",
        help=f"program never held, started again when supervisord gives up (repeatable; {DEFAULT_CRITICAL})",
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service(SERVICE, main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())
