"""`make up`'s profiles (shared/supervision/profiles.py, deploy/profiles/): composed from a base and one
overlay per make variable, the programs following from the scene; the default profile runs exactly the
programs of the hand-written supervisord.conf it replaced, with the same settings; a profile reaches the
services only through their flags."""

from __future__ import annotations

import configparser
import shlex
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml
from supervisor.options import ServerOptions

from shared.config import ConfigError, load_settings
from shared.paths import DEFAULT_SCENE, REPO_ROOT, RUN_DIR
from shared.supervision import profiles
from shared.supervision.profiles import Choice, compose, render

SCENE = "deploy/scenes/sand_table.yaml"
WATCHDOG_URL = f"unix://{RUN_DIR / 'supervisor.sock'}"
GROUPS = [
    "agent1-cameras",
    "agent2-cameras",
    "agent3-cameras",
    "agent1-lidars",
    "agent3-lidars",
    "agent2-radars",
]

# The hand-written deploy/local/supervisord.conf this replaces (at 495123a): program -> python arguments,
# priority, startsecs; and the settings its `environment=` lines changed.
TODAY: dict[str, tuple[list[str], int, int]] = {
    "router": (["-m", "services.router"], 10, 1),
    "sim": (["-m", "services.sim"], 20, 1),
    **{g: (["-m", "services.sensor", "--group", g], 30, 1) for g in GROUPS},
    **{f"mec-{a}": (["-m", "services.mec", "--instance", a], 40, 3) for a in ("agent1", "agent2", "agent3")},
    "coordinator": (["-m", "services.coordinator"], 40, 2),
    "viewer": (["-m", "services.viewer"], 45, 2),
    "watchdog": (["-m", "services.watchdog", "--supervisor-url", WATCHDOG_URL], 50, 2),
}
TODAY_ENV = {
    "sim": {"RMMDET_SIM_TRAFFIC__ROUTE_POLICY": "plan"},
    "mec": {"RMMDET_MEC_DETECTORS__CAMERA_THREADS": "1", "RMMDET_MEC_DETECTORS__LIDAR_THREADS": "1"},
    "coordinator": {},
}
POLICY = {  # today's restart policy, every program
    "autorestart": "true",
    "startretries": "1000",
    "stopsignal": "INT",
    "stopwaitsecs": "5",
    "stopasgroup": "true",
    "killasgroup": "true",
    "redirect_stderr": "true",
    "stdout_logfile_maxbytes": "10MB",
    "stdout_logfile_backups": "2",
}


def programs_of(conf: Path) -> dict[str, dict[str, str]]:
    parser = configparser.RawConfigParser()
    parser.read(conf)
    return {
        s.removeprefix("program:"): dict(parser[s]) for s in parser.sections() if s.startswith("program:")
    }


def args_of(program: dict[str, str]) -> list[str]:
    python, *args = shlex.split(program["command"])
    assert python == str(REPO_ROOT / ".venv" / "bin" / "python")
    return args


def pop_flag(args: list[str], flag: str) -> str | None:
    if flag not in args:
        return None
    i = args.index(flag)
    value = args[i + 1]
    del args[i : i + 2]
    return value


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    import os

    for key in os.environ:
        if key.startswith("RMMDET_"):
            monkeypatch.delenv(key)
    return monkeypatch


def test_the_default_profile_runs_todays_programs_with_todays_settings(
    tmp_path: Path, clean_env: pytest.MonkeyPatch
) -> None:
    rendered = render(Choice(), tmp_path)
    programs = programs_of(rendered.conf)
    assert set(programs) == set(TODAY)
    for name, program in programs.items():
        args = args_of(program)
        scene = pop_flag(args, "--scene")
        assert scene in (None, SCENE), name
        settings = pop_flag(args, "--settings")
        assert (args, int(program["priority"]), int(program["startsecs"])) == TODAY[name], name
        assert program["directory"] == str(REPO_ROOT)
        assert program["stdout_logfile"] == str(RUN_DIR / "logs" / f"{name}.log")
        assert {k: program[k] for k in POLICY} == POLICY, name
        assert "autostart" not in program  # every program of a profile starts
        if settings is not None:
            # the sensor groups render with the sim's settings (its world), as lock-step runs do
            service = "sim" if name in GROUPS else name.split("-")[0]
            assert settings == profiles.shown(rendered.settings[service])
    # what reached the services through environment lines is in their settings files
    for service, env in TODAY_ENV.items():
        spec = rendered.profile.settings[service]
        cls = profiles.settings_class(spec, service)
        assert cls is not None
        composed = load_settings(cls, rendered.settings[service]).model_dump()
        for key, value in env.items():
            clean_env.setenv(key, value)
        today = load_settings(cls, REPO_ROOT / spec.file).model_dump()
        for key in env:
            clean_env.delenv(key)
        assert composed == today, service


def test_no_program_gets_environment_but_pythonunbuffered(tmp_path: Path) -> None:
    for choice in (Choice(), Choice(sensors="wire"), Choice(shards="2")):
        for name, program in programs_of(render(choice, tmp_path).conf).items():
            assert program["environment"] == 'PYTHONUNBUFFERED="1"', (choice, name)
    makefile = (REPO_ROOT / "Makefile").read_text()
    assert "RMMDET_" not in makefile and "ifeq" not in makefile  # no settings in make conditionals


def test_wire_adds_a_device_service_per_sensor_group(tmp_path: Path) -> None:
    site = "deploy/devices/sand_table_wire.yaml"
    rendered = render(Choice(sensors="wire"), tmp_path)
    programs = programs_of(rendered.conf)
    assert set(programs) == set(TODAY) | {f"{g}-device" for g in GROUPS}
    for group in GROUPS:
        assert args_of(programs[group]) == [
            "-m",
            "services.sensor",
            "--group",
            group,
            "--scene",
            SCENE,
            "--settings",
            profiles.shown(rendered.settings["sim"]),
            "--wire",
            site,
        ]
        assert args_of(programs[f"{group}-device"]) == [
            "-m",
            "services.device",
            "--group",
            group,
            "--site",
            site,
        ]
        assert programs[f"{group}-device"]["priority"] == "30"
    other = tmp_path / "other_site.yaml"
    other.write_text((REPO_ROOT / site).read_text())
    programs = programs_of(render(Choice(sensors="wire", site=str(other)), tmp_path).conf)
    assert args_of(programs["agent1-lidars-device"])[-1] == str(other)  # SITE=


def test_shards_split_the_coordinator_over_the_scenes_region_map(tmp_path: Path) -> None:
    rendered = render(Choice(shards="2"), tmp_path)
    programs = programs_of(rendered.conf)
    assert set(programs) == set(TODAY) | {"coordinator-region1"}
    for name, shard in (("coordinator", "0"), ("coordinator-region1", "1")):
        args = args_of(programs[name])
        assert pop_flag(args, "--shard") == shard and pop_flag(args, "--scene") == SCENE
        assert pop_flag(args, "--settings") == str(rendered.settings["coordinator"])
        assert args == ["-m", "services.coordinator"]
        assert (programs[name]["priority"], programs[name]["startsecs"]) == ("40", "2")
    coordinator = yaml.safe_load(rendered.settings["coordinator"].read_text())
    assert coordinator["shards"]["regions"] == "deploy/coordinator/regions/sand_table_2.json"
    # unsharded, the coordinator settings are the file's
    one = render(Choice(), tmp_path)
    assert yaml.safe_load(one.settings["coordinator"].read_text()) == yaml.safe_load(
        (REPO_ROOT / "deploy/coordinator/coordinator.yaml").read_text()
    )


def one_agent_scene(tmp_path: Path) -> Path:
    """The table with only its roundabout agent, and of that agent's sensors only the cameras."""
    scene = yaml.safe_load(DEFAULT_SCENE.read_text())
    scene["agents"] = [a for a in scene["agents"] if a["id"] == "agent3"]
    scene["sensors"] = [s for s in scene["sensors"] if s["agent"] == "agent3" and s["kind"] == "camera"]
    path = tmp_path / "one_agent.yaml"
    path.write_text(yaml.safe_dump(scene))
    return path


def test_a_one_agent_scene_runs_its_agent_and_its_sensor_groups(tmp_path: Path) -> None:
    scene = one_agent_scene(tmp_path)
    programs = programs_of(render(Choice(scene=str(scene)), tmp_path / "out").conf)
    assert set(programs) == {
        "router",
        "sim",
        "agent3-cameras",
        "mec-agent3",
        "coordinator",
        "viewer",
        "watchdog",
    }
    for program in programs.values():
        args = args_of(program)
        assert "--scene" not in args or pop_flag(args, "--scene") == str(scene)
    # no site file and no region map: said in one line
    with pytest.raises(ConfigError, match="no device site file"):
        render(Choice(scene=str(scene), sensors="wire"), tmp_path / "out")
    with pytest.raises(ConfigError, match="no region map of 2 regions"):
        render(Choice(scene=str(scene), shards="2"), tmp_path / "out")
    # the table's site file is of another scene
    with pytest.raises(ConfigError, match=r"is of scene deploy/scenes/sand_table\.yaml"):
        render(
            Choice(scene=str(scene), sensors="wire", site="deploy/devices/sand_table_wire.yaml"),
            tmp_path / "out",
        )


@pytest.mark.parametrize(
    ("argv", "error"),
    [
        (["--sensors", "radio"], "error: SENSORS=radio: no such profile (one of: sim, wire)"),
        (["--shards", "two"], "error: SHARDS=two: must be a number of coordinator shards"),
        (
            ["--shards", "3"],
            "error: SHARDS=3: scene deploy/scenes/sand_table.yaml has no region map of 3 regions",
        ),
        (["--scene", "mars"], "error: SCENE=mars: no profile deploy/profiles/scene/mars.yaml and no scene"),
        (["--set", "settings.sim.overrides.speedo=2"], "error: settings.sim (deploy/sim/sim.yaml with the"),
        (
            ["--set", "programs.sim.priorty=1"],
            "error: profile SCENE=sand_table SENSORS=sim SHARDS=1: programs.",
        ),
    ],
)
def test_an_unknown_profile_value_is_one_line(
    argv: list[str], error: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert profiles.main([*argv, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(error) and err.count("\n") == 1, err
    assert not (tmp_path / "programs.conf").exists()  # nothing written


def write(path: Path, data: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data))


def test_overlays_merge_section_by_section_in_order(tmp_path: Path) -> None:
    d = tmp_path / "profiles"
    detectors = {"camera_threads": 1, "lidar_threads": 1}
    write(
        d / "base.yaml",
        {
            "settings": {"mec": {"file": "deploy/mec/mec.yaml", "overrides": {"detectors": detectors}}},
            "programs": {
                "a": {"module": "m.a", "args": ["--x"], "priority": 10},
                "b": {"module": "m.b", "priority": 20, "startsecs": 3},
            },
        },
    )
    write(
        d / "scene" / "s.yaml",
        {"scene": SCENE, "settings": {"mec": {"overrides": {"detectors": {"camera_threads": 2}}}}},
    )
    write(d / "sensors" / "x.yaml", {"programs": {"a": {"extra_args": ["--y"]}, "b": {"enabled": False}}})
    write(
        d / "coordinator" / "shards.yaml",
        {"region_maps": {2: "r2.json"}, "programs": {"a": {"priority": 11}}},
    )
    profile, labels = compose(Choice("s", "x", "2", sets=("programs.a.priority=5", "site=s.yaml")), d)
    assert profile.settings["mec"].overrides == {"detectors": {"camera_threads": 2, "lidar_threads": 1}}
    a, b = profile.programs["a"], profile.programs["b"]
    assert (a.args, a.extra_args, a.priority, a.module) == (["--x"], ["--y"], 5, "m.a")  # --set last
    assert (b.enabled, b.module, b.startsecs) == (False, "m.b", 3)  # the overlay changed one key
    assert profile.coordinator_shards == 2 and profile.region_maps == {2: Path("r2.json")}
    assert profile.site == Path("s.yaml") and profile.scene == Path(SCENE)
    assert [label.removeprefix(f"{d}/") for label in labels] == [
        "base.yaml",
        "scene/s.yaml",
        "sensors/x.yaml",
        "coordinator/shards.yaml",
        "SHARDS=2",
        "--set programs.a.priority=5",
        "--set site=s.yaml",
    ]
    write(d / "sensors" / "typo.yaml", {"programs": {"a": {"priorty": 1}}})
    with pytest.raises(ConfigError, match=r"programs\.a\.priorty: Extra inputs"):
        compose(Choice("s", "typo"), d)


def test_supervisord_reads_the_committed_conf_with_the_rendered_programs(tmp_path: Path) -> None:
    """deploy/local/supervisord.conf includes .run/profile/programs.conf: supervisord's own parser, on a
    copy of the layout, sees every program; the watchdog's URL is the conf's socket."""
    conf = tmp_path / "deploy" / "local" / "supervisord.conf"
    conf.parent.mkdir(parents=True)
    shutil.copy(REPO_ROOT / "deploy" / "local" / "supervisord.conf", conf)
    (tmp_path / ".run" / "logs").mkdir(parents=True)
    rendered = render(Choice(shards="2"), tmp_path / ".run" / "profile", logs=tmp_path / ".run" / "logs")
    options = ServerOptions()
    options.configfile = str(conf)
    options.process_config(do_usage=False)
    seen = {p.name: p for g in options.process_group_configs for p in g.process_configs}
    assert set(seen) == {p.name for p in rendered.programs}
    assert seen["coordinator-region1"].command.endswith("--shard 1")
    assert all(p.environment == {"PYTHONUNBUFFERED": "1"} for p in seen.values())
    socket = options.configroot.supervisord.server_configs[0]["file"]
    assert Path(socket) == tmp_path / ".run" / "supervisor.sock"
    assert profiles.SUPERVISOR_SOCKET == RUN_DIR / "supervisor.sock"  # the same place in the checkout
    assert rendered.conf == tmp_path / ".run" / "profile" / profiles.PROGRAMS_CONF
    assert profiles.DEFAULT_OUT == RUN_DIR / "profile"


def test_health_judges_the_scene_make_up_started(tmp_path: Path, clean_env: pytest.MonkeyPatch) -> None:
    assert profiles.running_scene(tmp_path) is None  # nothing started: the caller's default
    render(Choice(scene="intersection"), tmp_path)
    assert profiles.running_scene(tmp_path) == REPO_ROOT / "deploy" / "scenes" / "intersection.yaml"
    render(Choice(), tmp_path)  # a later make up replaces it
    assert profiles.running_scene(tmp_path) == REPO_ROOT / SCENE
    (tmp_path / "profile.yaml").write_text("[not, a, mapping")
    assert profiles.running_scene(tmp_path) is None
