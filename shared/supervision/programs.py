"""supervisord `[program:x]` sections: the one renderer of both deployments, the local system `make up`
runs (`profiles`: one host, every service) and a host of a multi-host site (`shared.security.sites`).

Every program runs one Python service from the checkout with the same restart policy: restarted
whenever it exits (supervisord) and stalled ones by the watchdog, stopped with SIGINT and then SIGKILL
after 5 s with its whole process group, its stdout and stderr in `<logs>/<name>.log` (10 MB, 2 backups).
"""

from __future__ import annotations

import shlex
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

#: The only environment a program gets besides its `env`: Python's output unbuffered (logs in order).
BASE_ENVIRONMENT = {"PYTHONUNBUFFERED": "1"}


@dataclass(frozen=True)
class Program:
    name: str
    args: list[str]  # python arguments: ["-m", "services.mec", "--instance", "agent1"]
    priority: int | None = None  # start order (lower first); supervisord's default 999 when None
    startsecs: int = 1  # running this long counts as started
    env: Mapping[str, str] = field(default_factory=dict)  # extra environment (a site's key paths)


def escape(value: str) -> str:
    """`value` as supervisord reads it literally (`%` starts its `%(name)s` expansions)."""
    return value.replace("%", "%%")


def environment_value(value: str) -> str:
    """A value quoted for supervisord's `environment=` (shell-like quoting, `%` escaped)."""
    value = escape(value)
    return f"'{value}'" if '"' in value else f'"{value}"'


def render_program(program: Program, *, python: str | Path, directory: Path, logs: Path) -> str:
    """The `[program:<name>]` section: `python <args>` run in `directory`, logging to `logs`."""
    env = {**program.env, **BASE_ENVIRONMENT}
    lines = [
        f"[program:{program.name}]",
        f"command={escape(shlex.join([str(python), *program.args]))}",
        f"directory={escape(str(directory))}",
    ]
    if program.priority is not None:
        lines.append(f"priority={program.priority}")
    lines += [
        "autorestart=true",
        f"startsecs={program.startsecs}",
        "startretries=1000",
        "stopsignal=INT",
        "stopwaitsecs=5",
        "stopasgroup=true",
        "killasgroup=true",
        "redirect_stderr=true",
        f"stdout_logfile={escape(str(logs / f'{program.name}.log'))}",
        "stdout_logfile_maxbytes=10MB",
        "stdout_logfile_backups=2",
        "environment=" + ",".join(f"{k}={environment_value(v)}" for k, v in env.items()),
    ]
    return "\n".join(lines) + "\n"
