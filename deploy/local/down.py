"""`make down`: stop supervisord and every service it runs, and prove nothing is left behind.

Asks supervisord to stop every program at once (each program's whole process group gets SIGINT,
then SIGKILL after stopwaitsecs), then to shut down, waits for it to exit, then looks for any process
still running from this checkout's virtualenv and kills it, so a crashed supervisord cannot leave
orphans.
"""

from __future__ import annotations

import argparse
import contextlib
import subprocess
import sys
import time
import xmlrpc.client
from pathlib import Path

import psutil

from shared.paths import REPO_ROOT

RUN_DIR = REPO_ROOT / ".run"
VENV_PYTHON_PREFIX = str(REPO_ROOT / ".venv" / "bin")
ROUTER = "router"  # supervisord.conf's program name of the Zenoh router
CLI_MODULE = "services.cli"  # the rmmdet tool: the user's, not make up's


def supervisord_pid() -> int | None:
    pidfile = RUN_DIR / "supervisord.pid"
    try:
        pid = int(pidfile.read_text().strip())
    except (FileNotFoundError, ValueError):
        return None
    return pid if psutil.pid_exists(pid) else None


def is_leftover(cmdline: list[str]) -> bool:
    """A process `make up` starts, run from this checkout's .venv: supervisord or a service
    (`python -m services.<name>`). The `rmmdet` tool (`services.cli`, e.g. a study or a recording the
    user started) is not one: `make down` leaves it running."""
    if not any(part.startswith(VENV_PYTHON_PREFIX) for part in cmdline[:2]):
        return False
    if any("supervisord" in part for part in cmdline[:3]):
        return True
    modules = [cmdline[i + 1] for i, part in enumerate(cmdline[:-1]) if part == "-m"]
    return any(m.startswith("services.") and not m.startswith(CLI_MODULE) for m in modules)


def leftovers() -> list[psutil.Process]:
    """Processes `make up` started from this checkout's .venv (`is_leftover`), except ourselves."""
    me = psutil.Process()
    found = []
    for proc in psutil.process_iter(["pid", "cmdline"]):
        if proc.pid not in (me.pid, me.ppid()) and is_leftover(proc.info["cmdline"] or []):
            found.append(proc)
    return found


def stop_all_at_once(socket: Path, timeout_s: float) -> bool:
    """Ask supervisord to stop every program without waiting for each (its own shutdown and `stop all`
    stop one after another: ~1 s each, 15 s in all), the router last (the others close their sessions
    through it); each gets its stopsignal once and is not restarted. Then supervisord shuts down.
    False if supervisord could not be asked (the caller falls back to `supervisorctl shutdown`)."""
    from supervisor.xmlrpc import SupervisorTransport

    proxy = xmlrpc.client.ServerProxy(
        "http://127.0.0.1", transport=SupervisorTransport(None, None, f"unix://{socket}")
    )
    deadline = time.monotonic() + timeout_s
    try:
        names = [p["name"] for p in proxy.supervisor.getAllProcessInfo()]
        for batch in ([n for n in names if n != ROUTER], [n for n in names if n == ROUTER]):
            for name in batch:
                with contextlib.suppress(xmlrpc.client.Fault):  # not running: nothing to stop
                    proxy.supervisor.stopProcess(name, False)
            while time.monotonic() < deadline:
                states = {p["statename"] for p in proxy.supervisor.getAllProcessInfo() if p["name"] in batch}
                if not states & {"RUNNING", "STOPPING", "STARTING", "BACKOFF"}:
                    break
                time.sleep(0.05)
        proxy.supervisor.shutdown()
        return True
    except (OSError, xmlrpc.client.Error) as err:
        print(f"stopping all at once failed ({err}); supervisord shuts down one by one")
        return False


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--conf", default=str(REPO_ROOT / "deploy/local/supervisord.conf"))
    parser.add_argument("--timeout-s", type=float, default=30.0)
    args = parser.parse_args()

    pid = supervisord_pid()
    if pid is None:
        print("supervisord not running")
    else:
        if not stop_all_at_once(RUN_DIR / "supervisor.sock", args.timeout_s):
            ctl = Path(sys.executable).parent / "supervisorctl"
            subprocess.run([str(ctl), "-c", args.conf, "shutdown"], check=False)
        deadline = time.monotonic() + args.timeout_s
        while psutil.pid_exists(pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        if psutil.pid_exists(pid):
            print(f"supervisord {pid} still alive after {args.timeout_s} s: killing it")
            psutil.Process(pid).kill()

    stray = leftovers()
    for proc in stray:
        print(f"killing leftover process {proc.pid}: {' '.join(proc.cmdline())}")
        with contextlib.suppress(psutil.NoSuchProcess):
            proc.kill()
    psutil.wait_procs(stray, timeout=5)
    remaining = leftovers()
    for sock in ("supervisor.sock", "supervisord.pid"):
        (RUN_DIR / sock).unlink(missing_ok=True)
    if remaining:
        print(f"error: {len(remaining)} processes survived", file=sys.stderr)
        return 1
    print("down: no RMMDet process left")
    return 0


if __name__ == "__main__":
    sys.exit(main())
