"""The local system's profiles: what `make up` runs, composed from deploy/profiles/ and rendered, not copied.

    python -m shared.supervision.profiles [--scene sand_table] [--sensors sim|wire] [--shards 1|N]
        [--site FILE] [--set KEY.PATH=YAML ...] [--out .run/profile]

A profile is deploy/profiles/base.yaml with one overlay per axis merged in, section by section
(`shared.config.deep_merge`), in this order: `scene/<SCENE>.yaml` (a scene without one:
`deploy/scenes/<SCENE>.yaml` or a path to a scene file, nothing else), `sensors/<SENSORS>.yaml`,
`coordinator/shards.yaml` with `coordinator_shards: N` for N > 1 shards, then `--site` and each `--set`.
base.yaml documents the keys. The programs follow from the profile and the scene: one per `programs`
entry, or one per agent, per sensor group (each agent's cameras / lidars / radars it has) or per
coordinator shard. Each service's settings file with the profile's `overrides` merged in is written to
`<out>/<service>.yaml` (validated by its settings class) and reaches the service as `--settings`; the
programs go to `<out>/programs.conf`, which deploy/local/supervisord.conf includes. No program gets
environment beyond PYTHONUNBUFFERED: a profile changes a service only through its flags.

A profile value that does not exist (an unknown SENSORS=, a scene without a file, SHARDS=N without a
region map of N regions, a site file of another scene) is one line naming it and what exists; exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import string
import sys
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic_settings import BaseSettings

from shared.bus.streams import SENSOR_STREAM, sensor_group, shard_instance
from shared.config import ConfigError, deep_merge, load_settings, read_yaml, validation_summary
from shared.paths import DEFAULT_SCENE, DEPLOY_DIR, REPO_ROOT, RUN_DIR
from shared.supervision.programs import Program, render_program

PROFILES_DIR = DEPLOY_DIR / "profiles"
SCENES_DIR = DEPLOY_DIR / "scenes"
DEFAULT_OUT = RUN_DIR / "profile"
LOG_DIR = RUN_DIR / "logs"
#: deploy/local/supervisord.conf's socket (its [unix_http_server] file), which the watchdog talks to.
SUPERVISOR_SOCKET = RUN_DIR / "supervisor.sock"
PYTHON = REPO_ROOT / ".venv" / "bin" / "python"
PROGRAMS_CONF = "programs.conf"
SCENE_AXIS, SENSORS_AXIS, COORDINATOR_AXIS = "scene", "sensors", "coordinator"
SHARDS_OVERLAY = "shards"  # coordinator/shards.yaml: the overlay of every N > 1


class ProfileError(ConfigError):
    """A profile that cannot be composed or rendered: one line naming the value and what exists."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SettingsSpec(_Strict):
    file: Path = Field(description="the service's settings file")
    type: str | None = Field(None, description="module:Class validating the composed file")
    overrides: dict[str, Any] = Field({}, description="merged into the file (placeholders allowed)")


class ProgramSpec(_Strict):
    module: str
    args: list[str] = []
    extra_args: list[str] = Field([], description="appended to args (what an overlay adds)")
    name: str | None = Field(None, description="program name template (default: the entry's key)")
    each: Literal["agent", "sensor_group", "shard"] | None = None
    enabled: bool = True
    priority: int
    startsecs: int = Field(1, ge=0)


class Profile(_Strict):
    scene: Path | None = None
    site: Path | None = None
    coordinator_shards: int = Field(1, ge=1)
    region_maps: dict[int, Path] = {}
    settings: dict[str, SettingsSpec] = {}
    programs: dict[str, ProgramSpec]


@dataclass(frozen=True)
class Choice:
    """The make variables: SCENE, SENSORS, SHARDS, SITE, and `--set KEY.PATH=YAML` overrides."""

    scene: str = "sand_table"
    sensors: str = "sim"
    shards: str = "1"
    site: str | None = None
    sets: tuple[str, ...] = ()

    def label(self) -> str:
        return f"SCENE={self.scene} SENSORS={self.sensors} SHARDS={self.shards}" + (
            f" SITE={self.site}" if self.site else ""
        )


@dataclass(frozen=True)
class Rendered:
    profile: Profile
    overlays: list[str]
    programs: list[Program]
    conf: Path
    settings: dict[str, Path]


def repo_path(path: Path | str) -> Path:
    """A profile's path: relative ones are the checkout's (the services run in its root)."""
    path = Path(path)
    return path if path.is_absolute() else REPO_ROOT / path


def shown(path: Path) -> str:
    """`path` as a program's argument: relative to the checkout's root when inside it."""
    path = repo_path(path)
    return str(path.relative_to(REPO_ROOT)) if path.is_relative_to(REPO_ROOT) else str(path)


def _names(directory: Path) -> str:
    return ", ".join(sorted(p.stem for p in directory.glob("*.yaml"))) or "none"


def _overlay(path: Path) -> dict[str, Any]:
    data = read_yaml(path)
    if not isinstance(data, dict):  # pragma: no cover - read_yaml checks the top level
        raise ProfileError(f"{path}: not a mapping")
    return data


def scene_overlay(name: str, profiles_dir: Path) -> tuple[str, dict[str, Any]]:
    overlay = profiles_dir / SCENE_AXIS / f"{name}.yaml"
    if overlay.is_file():
        return shown(overlay), _overlay(overlay)
    for scene_file in (SCENES_DIR / f"{name}.yaml", repo_path(name)):
        if scene_file.suffix in (".yaml", ".yml") and scene_file.is_file():
            return f"SCENE={name}", {"scene": shown(scene_file)}
    raise ProfileError(
        f"SCENE={name}: no profile {shown(overlay)} and no scene {shown(SCENES_DIR / f'{name}.yaml')}"
        f" (profiles: {_names(profiles_dir / SCENE_AXIS)}; scenes: {_names(SCENES_DIR)})"
    )


def axis_overlay(variable: str, axis: str, name: str, profiles_dir: Path) -> tuple[str, dict[str, Any]]:
    path = profiles_dir / axis / f"{name}.yaml"
    if not path.is_file():
        raise ProfileError(f"{variable}={name}: no such profile (one of: {_names(profiles_dir / axis)})")
    return shown(path), _overlay(path)


def parse_set(item: str) -> dict[str, Any]:
    """`a.b.c=VALUE` (VALUE as YAML) as the overlay {a: {b: {c: VALUE}}}."""
    key, sep, value = item.partition("=")
    if not sep or not key or not all(key.split(".")):
        raise ProfileError(f"--set {item}: expected KEY.PATH=VALUE")
    try:
        node: Any = yaml.safe_load(value)
    except yaml.YAMLError as err:
        raise ProfileError(f"--set {item}: value is not YAML ({' '.join(str(err).split())})") from None
    for part in reversed(key.split(".")):
        node = {part: node}
    return node


def overlays(choice: Choice, profiles_dir: Path = PROFILES_DIR) -> list[tuple[str, dict[str, Any]]]:
    """(label, overlay) in merge order, the base first."""
    base = profiles_dir / "base.yaml"
    layers = [(shown(base), _overlay(base)), scene_overlay(choice.scene, profiles_dir)]
    layers.append(axis_overlay("SENSORS", SENSORS_AXIS, choice.sensors, profiles_dir))
    if not choice.shards.isdigit() or int(choice.shards) < 1:
        raise ProfileError(f"SHARDS={choice.shards}: must be a number of coordinator shards (1, 2, ...)")
    if int(choice.shards) > 1:
        layers.append(axis_overlay("SHARDS", COORDINATOR_AXIS, SHARDS_OVERLAY, profiles_dir))
        layers.append((f"SHARDS={choice.shards}", {"coordinator_shards": int(choice.shards)}))
    if choice.site:
        layers.append((f"SITE={choice.site}", {"site": choice.site}))
    layers += [(f"--set {item}", parse_set(item)) for item in choice.sets]
    return layers


def compose(choice: Choice, profiles_dir: Path = PROFILES_DIR) -> tuple[Profile, list[str]]:
    """The profile `choice` names: base.yaml with its overlays merged in; and the overlays' labels."""
    layers = overlays(choice, profiles_dir)
    data: dict[str, Any] = {}
    for _, layer in layers:
        data = deep_merge(data, layer)
    try:
        profile = Profile.model_validate(data)
    except ValidationError as err:
        raise ProfileError(f"profile {choice.label()}: {validation_summary(err)}") from None
    if profile.scene is None:
        raise ProfileError(f"profile {choice.label()}: no scene (the scene overlay sets `scene:`)")
    return profile, [label for label, _ in layers]


# --- rendering ------------------------------------------------------------------------------------------


class _Lazy:
    """A placeholder value computed (and checked) when a template uses it: the site file only when a
    program reads it, the region map only when the coordinator is sharded."""

    def __init__(self, compute: Callable[[], str]) -> None:
        self._compute = compute
        self._value: str | None = None

    def __format__(self, spec: str) -> str:
        if self._value is None:
            self._value = self._compute()
        return format(self._value, spec)


def fill(template: str, context: Mapping[str, Any], where: str) -> str:
    try:
        return string.Formatter().vformat(template, (), context)
    except ConfigError:  # a placeholder's value that is not there (`_Lazy`)
        raise
    except (KeyError, IndexError, AttributeError, ValueError) as err:
        known = ", ".join(sorted(context))
        raise ProfileError(f"{where}: {template!r}: no placeholder {err} (have: {known})") from None


def fill_values(value: Any, context: Mapping[str, Any], where: str) -> Any:
    if isinstance(value, str) and "{" in value:
        return fill(value, context, where)
    if isinstance(value, dict):
        return {k: fill_values(v, context, f"{where}.{k}") for k, v in value.items()}
    if isinstance(value, list):
        return [fill_values(v, context, where) for v in value]
    return value


def load_scene(path: Path) -> Any:
    from shared.scene.scene import Scene  # numpy, shapely: only when rendering

    return Scene.load(repo_path(path))


def site_value(profile: Profile, scene_path: Path) -> str:
    """The profile's site file, checked: it exists, is of this scene, and names devices of its sensors."""
    if profile.site is None:
        raise ProfileError(
            f"scene {shown(scene_path)}: no device site file for the sensors on the wire"
            " (`site:` in its deploy/profiles/scene/ overlay, or SITE=)"
        )
    from shared.devices.site import SiteFile

    site = SiteFile.load(repo_path(profile.site))
    if site.scene.resolve() != repo_path(scene_path).resolve():
        raise ProfileError(
            f"site file {shown(profile.site)} is of scene {shown(site.scene)}, not {shown(scene_path)}"
        )
    try:
        site.check_against({s.id: s.kind for s in load_scene(scene_path).spec.sensors})
    except ValueError as err:
        raise ProfileError(f"site file {shown(profile.site)}: {err}") from None
    return shown(profile.site)


def region_map_value(profile: Profile) -> str:
    """The scene's region map of `coordinator_shards` regions, checked to have that many."""
    shards = profile.coordinator_shards
    path = profile.region_maps.get(shards)
    if path is None:
        have = ", ".join(str(n) for n in sorted(profile.region_maps)) or "none"
        raise ProfileError(
            f"SHARDS={shards}: scene {shown(profile.scene or Path())} has no region map of {shards}"
            f" regions (region_maps in its deploy/profiles/scene/ overlay: {have})"
        )
    from shared.traffic.regions import RegionMap

    try:
        regions = RegionMap.load(repo_path(path)).regions
    except (OSError, ValueError, KeyError) as err:
        raise ProfileError(f"region map {shown(path)}: {err}") from None
    if regions != shards:
        raise ProfileError(f"SHARDS={shards}: region map {shown(path)} has {regions} regions")
    return shown(path)


def sensor_groups(scene: Any) -> list[tuple[str, str]]:
    """(agent, group) of each sensor group of the scene: every agent's cameras, then lidars, then radars,
    each only where the agent has such sensors."""
    agents = [a.id for a in scene.spec.agents]
    return [
        (agent, sensor_group(agent, kind))
        for kind in SENSOR_STREAM
        for agent in agents
        if scene.sensors_of(agent, kind)
    ]


def expand(spec: ProgramSpec, key: str, profile: Profile, scene: Any) -> Iterator[tuple[str, dict[str, str]]]:
    """(name template, extra placeholders) of each program of entry `key`; shards add `--shard`."""
    name = spec.name or key
    if spec.each is None:
        yield name, {}
    elif spec.each == "agent":
        for agent in (a.id for a in scene.spec.agents):
            yield name, {"agent": agent}
    elif spec.each == "sensor_group":
        for agent, group in sensor_groups(scene):
            yield name, {"agent": agent, "group": group}
    else:  # shard
        shards = profile.coordinator_shards
        for region in range(shards):
            shard_name = name if region == 0 else f"{name}-{shard_instance(region)}"
            yield shard_name, ({"shard": str(region)} if shards > 1 else {})


def programs_of(profile: Profile, context: Mapping[str, Any], scene: Any) -> list[Program]:
    programs: list[Program] = []
    for key, spec in profile.programs.items():
        if not spec.enabled:
            continue
        for name_template, extra in expand(spec, key, profile, scene):
            ctx = {**context, **extra}
            name = fill(name_template, ctx, f"programs.{key}.name")
            args = [fill(a, ctx, f"program {name}") for a in [*spec.args, *spec.extra_args]]
            if "shard" in extra:
                args += ["--shard", extra["shard"]]
            programs.append(Program(name, ["-m", spec.module, *args], spec.priority, spec.startsecs))
    names = [p.name for p in programs]
    if twice := sorted({n for n in names if names.count(n) > 1}):
        raise ProfileError(f"programs named twice: {', '.join(twice)}")
    return programs


def settings_class(spec: SettingsSpec, service: str) -> type[BaseSettings] | None:
    """The settings class `type` names (`module:Class`), or None where the profile names none."""
    if spec.type is None:
        return None
    module, _, name = spec.type.partition(":")
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        cls = None
    if not (isinstance(cls, type) and issubclass(cls, BaseSettings)):
        raise ProfileError(f"settings.{service}.type: {spec.type!r} is no settings class")
    return cls


def composed_settings(profile: Profile, context: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Each service's settings: its file with the profile's overrides merged in, validated by its class
    (with the environment's overrides, as the service will read it)."""
    composed = {}
    for service, spec in profile.settings.items():
        overrides = fill_values(spec.overrides, context, f"settings.{service}.overrides")
        data = deep_merge(read_yaml(repo_path(spec.file)), overrides)
        cls = settings_class(spec, service)
        if cls is not None:
            try:
                load_settings(cls, None, **data)
            except ConfigError as err:
                where = f"settings.{service} ({shown(spec.file)} with the profile's overrides)"
                raise ProfileError(f"{where}: {str(err).partition(': ')[2]}") from None
        composed[service] = data
    return composed


def render(
    choice: Choice, out_dir: Path = DEFAULT_OUT, profiles_dir: Path = PROFILES_DIR, logs: Path = LOG_DIR
) -> Rendered:
    """Compose `choice`'s profile and write its settings files, programs.conf and the composed profile
    (profile.yaml) under `out_dir`, replacing what was there, the programs logging into `logs`; nothing
    is written for a profile that does not render."""
    profile, labels = compose(choice, profiles_dir)
    scene_path = profile.scene or Path()
    scene = load_scene(scene_path)
    files = {service: out_dir / f"{service}.yaml" for service in profile.settings}
    context: dict[str, Any] = {
        "scene": shown(scene_path),
        "site": _Lazy(lambda: site_value(profile, scene_path)),
        "region_map": _Lazy(lambda: region_map_value(profile)),
        "settings": {service: shown(path) for service, path in files.items()},
        "supervisor_url": f"unix://{SUPERVISOR_SOCKET}",
    }
    settings = composed_settings(profile, context)
    programs = programs_of(profile, context, scene)
    out_dir.mkdir(parents=True, exist_ok=True)
    logs.mkdir(parents=True, exist_ok=True)
    for stale in [*out_dir.glob("*.yaml"), out_dir / PROGRAMS_CONF]:
        stale.unlink(missing_ok=True)
    for service, data in settings.items():
        source = shown(profile.settings[service].file)
        header = f"# generated by `make up`: {source} with the profile's overrides ({' + '.join(labels)})\n"
        files[service].write_text(header + yaml.safe_dump(data, sort_keys=False))
    command = " ".join(["python -m shared.supervision.profiles", *cli_args(choice)])
    sections = [render_program(p, python=PYTHON, directory=REPO_ROOT, logs=logs) for p in programs]
    conf = out_dir / PROGRAMS_CONF
    conf.write_text(
        f"; generated by `make up` ({command})\n; from {' + '.join(labels)}: edit those, not this\n\n"
        + "\n".join(sections)
    )
    (out_dir / "profile.yaml").write_text(
        f"# the composed profile: {' + '.join(labels)}\n"
        + yaml.safe_dump(profile.model_dump(mode="json"), sort_keys=False)
    )
    return Rendered(profile, labels, programs, conf, files)


def running_scene(out_dir: Path = DEFAULT_OUT) -> Path | None:
    """The scene of the profile `make up` last rendered under `out_dir` (its profile.yaml), None if
    there is none or it cannot be read: what `rmmdet health` judges the loop against by default."""
    try:
        scene = yaml.safe_load((out_dir / "profile.yaml").read_text()).get("scene")
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    return repo_path(scene) if isinstance(scene, str) and scene else None


@dataclass(frozen=True)
class SceneProfile:
    """What a scene's profile gives its services, for offline runs (benches, evaluations) that build
    the cores themselves: the scene file, each service's overrides and its composed settings."""

    scene: Path
    overrides: dict[str, dict[str, Any]]
    settings: dict[str, dict[str, Any]]


def scene_profile(scene: str) -> SceneProfile:
    """`make up SCENE=<scene>`'s scene file and settings (the other axes at their defaults)."""
    profile, _ = compose(Choice(scene=scene))
    path = repo_path(profile.scene or Path())
    context: dict[str, Any] = {
        "scene": shown(path),
        "site": _Lazy(lambda: site_value(profile, path)),
        "region_map": _Lazy(lambda: region_map_value(profile)),
        "settings": {},
        "supervisor_url": "",
    }
    overrides = {
        service: fill_values(spec.overrides, context, f"settings.{service}.overrides")
        for service, spec in profile.settings.items()
    }
    return SceneProfile(path, overrides, composed_settings(profile, context))


def cli_args(choice: Choice) -> list[str]:
    args = ["--scene", choice.scene, "--sensors", choice.sensors, "--shards", choice.shards]
    if choice.site:
        args += ["--site", choice.site]
    for item in choice.sets:
        args += ["--set", item]
    return args


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m shared.supervision.profiles",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--scene", default="sand_table", help="SCENE: a scene/ profile or scene file")
    parser.add_argument("--sensors", default="sim", help="SENSORS: a sensors/ profile (sim, wire)")
    parser.add_argument("--shards", default="1", help="SHARDS: coordinator shards (1: one coordinator)")
    parser.add_argument("--site", help="SITE: the device site file instead of the scene overlay's")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY.PATH=YAML", help="override a profile key"
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory")
    args = parser.parse_args(argv)
    choice = Choice(args.scene, args.sensors, args.shards, args.site, tuple(args.set))
    try:
        rendered = render(choice, args.out.resolve())
    except ConfigError as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(
        f"profile {choice.label()}: {' + '.join(rendered.overlays)} -> {len(rendered.programs)} programs"
        f" in {shown(rendered.conf)}"
    )
    scene = rendered.profile.scene or Path()
    if repo_path(scene).resolve() != DEFAULT_SCENE.resolve():
        print(f"scene {shown(scene)}: rmmdet health --scene {shown(scene)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
