"""SUMO's programs and Python tools from the pinned `eclipse-sumo` wheel: one place that finds them and
runs them, so a missing install or a failed tool is one clear error naming the command.

The wheel installs `netgenerate`, `netconvert`, `duarouter` and `sumo` as console scripts and ships
`tools/` (randomTrips.py, sumolib) in its package folder; `import sumo` sets SUMO_HOME to that folder.
Every SUMO program seeds its Mersenne Twister with a fixed default, so the same arguments give the same
files; the demand passes `--seed` explicitly.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

log = logging.getLogger(__name__)


class SumoToolError(RuntimeError):
    """A SUMO program or tool failed; the message holds the command and its stderr's tail."""


def sumo_home() -> Path:
    """The wheel's SUMO_HOME (programs in bin/, Python tools in tools/)."""
    import sumo  # the eclipse-sumo wheel: also exports SUMO_HOME for its programs

    return Path(sumo.__file__).resolve().parent


def program(name: str) -> Path:
    """A SUMO program (netgenerate, netconvert, duarouter, sumo) of the wheel."""
    path = sumo_home() / "bin" / name
    if not path.is_file():
        raise SumoToolError(f"SUMO program {name} not found at {path}: is eclipse-sumo installed?")
    return path


def tool(name: str) -> Path:
    """A SUMO Python tool (e.g. randomTrips.py) of the wheel."""
    path = sumo_home() / "tools" / name
    if not path.is_file():
        raise SumoToolError(f"SUMO tool {name} not found at {path}: is eclipse-sumo installed?")
    return path


def run(command: list[str | Path], cwd: Path | None = None, timeout_s: float = 300.0) -> str:
    """Run one SUMO command (a program, or a tool under this Python), its stdout; SumoToolError with
    the command and the end of its stderr when it fails."""
    args = [str(a) for a in command]
    name = Path(args[0]).name
    if args[0].endswith(".py"):
        args = [sys.executable, *args]
    log.debug("sumo: %s", " ".join(args))
    done = subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout_s, check=False)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-5:]
        raise SumoToolError(f"{name} failed ({done.returncode}): {' | '.join(tail)}")
    return done.stdout
