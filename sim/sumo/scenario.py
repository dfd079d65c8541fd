"""A SUMO scenario as SUMO reads it: a `.sumocfg`'s input files (issue 53 items 1 and 6).

Public scenarios come as a configuration naming a net, route files (vehicles with routes, trips and
flows; vTypes; persons, which the study ignores) and additional files (vTypes, signal programs,
detectors, bus stops, rerouters). `load_scenario` reads the `<input>` and `<time>` sections, paths
relative to the configuration as SUMO takes them, and checks every file is there; `SumoWorld` runs them
as given. Anything wrong is one `ScenarioError` line naming the file and the element (SUMO's own message
where SUMO refused it), never a traceback or a hang. SUMO reads the files first in a process of its own
(`preflight`): libsumo, inside this one, takes the whole process down on a net it cannot read (a
segmentation fault, seen on a net with an edge missing its end).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import sumolib

from shared.config import ConfigError

#: A configuration's root element: SUMO writes <configuration>; older tools and public scenarios (Bologna's)
#: <sumoConfiguration>, which SUMO reads the same.
CONFIG_ROOTS = ("configuration", "sumoConfiguration")
#: How long SUMO may take to read a scenario's files before it is called hung, s.
PREFLIGHT_TIMEOUT_S = 120.0


class ScenarioError(ConfigError):
    """A scenario that cannot be run, in one line naming the file and element."""


@dataclass(frozen=True)
class Scenario:
    """What a `.sumocfg` gives SUMO to run: paths resolved, times in seconds (None: SUMO's default)."""

    config: Path
    net: Path
    routes: tuple[Path, ...]
    additional: tuple[Path, ...]
    begin_s: float | None
    end_s: float | None


def _files(config: Path, element: ET.Element | None, name: str) -> tuple[Path, ...]:
    if element is None:
        return ()
    value = element.get("value")
    if value is None:
        raise ScenarioError(f"{config}: <{name}> has no value attribute")
    paths = []
    for part in value.replace(" ", ",").split(","):
        if not part:
            continue
        path = (config.parent / part).resolve()
        if not path.is_file():
            raise ScenarioError(f"{config}: <{name}> names {part!r}, which is not a file ({path})")
        paths.append(path)
    return tuple(paths)


def _seconds(config: Path, element: ET.Element | None, name: str) -> float | None:
    if element is None:
        return None
    value = element.get("value", "")
    try:
        if ":" in value:  # SUMO also takes [[D:]H:]M:S
            total = 0.0
            for part in value.split(":"):
                total = total * 60.0 + float(part)
            return total
        return float(value)
    except ValueError:
        raise ScenarioError(f"{config}: <{name} value={value!r}> is not a time") from None


def load_scenario(config: Path) -> Scenario:
    """The scenario `config` (a `.sumocfg`) describes; ScenarioError for a missing or malformed file, a
    missing net, or an input file that is not there."""
    try:
        root = ET.parse(config).getroot()
    except FileNotFoundError:
        raise ScenarioError(f"{config}: no such scenario configuration") from None
    except (ET.ParseError, OSError) as err:
        raise ScenarioError(f"{config}: not a SUMO configuration: {err}") from None
    if root.tag not in CONFIG_ROOTS:
        raise ScenarioError(f"{config}: root element <{root.tag}>, expected one of {CONFIG_ROOTS}")
    inputs = root.find("input")
    nets = _files(config, inputs.find("net-file") if inputs is not None else None, "net-file")
    if len(nets) != 1:
        raise ScenarioError(f"{config}: <input><net-file> must name exactly one net, got {len(nets)}")
    time = root.find("time")
    return Scenario(
        config=config,
        net=nets[0],
        routes=_files(config, inputs.find("route-files") if inputs is not None else None, "route-files"),
        additional=_files(
            config, inputs.find("additional-files") if inputs is not None else None, "additional-files"
        ),
        begin_s=_seconds(config, time.find("begin") if time is not None else None, "begin"),
        end_s=_seconds(config, time.find("end") if time is not None else None, "end"),
    )


def stage(scenario: Scenario, folder: Path) -> Scenario:
    """The scenario with its configuration and input files copied under `folder` (their places relative to
    the configuration kept; a file outside its folder goes to `_outside/`), so that what SUMO writes
    beside them (the detector and edge outputs an additional file names) lands in `folder`, not in the
    scenario's source (a vendored copy, or another run's)."""
    home = scenario.config.parent.resolve()

    def copy(path: Path) -> Path:
        source = path.resolve()
        inside = source.is_relative_to(home)
        target = folder / (source.relative_to(home) if inside else Path("_outside") / source.name)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
        return target

    return Scenario(
        config=copy(scenario.config),
        net=copy(scenario.net),
        routes=tuple(map(copy, scenario.routes)),
        additional=tuple(map(copy, scenario.additional)),
        begin_s=scenario.begin_s,
        end_s=scenario.end_s,
    )


def preflight(
    net: Path,
    routes: Sequence[Path],
    additional: Sequence[Path] = (),
    timeout_s: float = PREFLIGHT_TIMEOUT_S,
) -> None:
    """Let SUMO read `net`, every route (all at once: `--route-steps 0`, so an unknown vType or a route
    that does not connect is found whenever its vehicle departs) and the additional files, in a process
    of its own, simulating nothing; ScenarioError with SUMO's first error line (or how it died) if it
    refuses them or takes longer than `timeout_s`."""
    files = f"{net} + {', '.join(map(str, routes))}" + (
        f" + {', '.join(map(str, additional))}" if additional else ""
    )
    binary = Path(sumolib.checkBinary("sumo"))
    args = [
        str(binary),
        f"--net-file={net}",
        f"--route-files={','.join(map(str, routes))}",
        *([f"--additional-files={','.join(map(str, additional))}"] if additional else []),
        "--end=0",
        "--route-steps=0",
        "--no-step-log=true",
        "--no-warnings=true",
    ]
    # SUMO checks XML against the schemas under SUMO_HOME (<home>/bin/sumo); without it, not at all.
    env = {**os.environ, "SUMO_HOME": os.environ.get("SUMO_HOME") or str(binary.parents[1])}
    try:
        done = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, env=env, check=False)
    except subprocess.TimeoutExpired:
        raise ScenarioError(f"{files}: SUMO did not finish reading them in {timeout_s:g} s") from None
    if done.returncode == 0:
        return
    if done.returncode < 0:
        name = signal.Signals(-done.returncode).name
        raise ScenarioError(f"{files}: SUMO crashed reading them ({name}): check the net and routes")
    errors = [line.strip() for line in done.stderr.splitlines() if line.startswith("Error")]
    raise ScenarioError(f"{files}: SUMO refused them: {errors[0] if errors else done.stderr.strip()[:300]}")
