"""Every service refuses a configuration it cannot start with the same way (issue 38 item 7): exit
status 2 and one line on stderr naming the file or flag and the field, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from shared.paths import REPO_ROOT
from shared.service import CONFIG_ERROR_EXIT

#: Each service's module and the arguments it needs to get as far as reading its configuration.
SERVICES = {
    "router": [],
    "sim": [],
    "sensor": ["--group", "agent1-cameras"],
    "mec": ["--instance", "agent1"],
    "coordinator": [],
    "recorder": [],
    "viewer": [],
    "watchdog": [],
    "device": ["--group", "agent1-cameras", "--site", "deploy/devices/sand_table_wire.yaml"],
    "vehicle": ["--instance", "v01"],
}
TIMEOUT_S = 60


def refused(args: list[str], env: dict[str, str] | None = None) -> str:
    """Run `python <args>`; assert it exited 2 with one stderr line (returned)."""
    import os

    proc = subprocess.run(
        [sys.executable, *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        env={**os.environ, **(env or {})},
    )
    # PyBullet's C module prints its build time when imported (the sim and the sensors import it).
    lines = [line for line in proc.stderr.strip().splitlines() if not line.startswith("pybullet build time")]
    assert proc.returncode == CONFIG_ERROR_EXIT and len(lines) == 1, (proc.returncode, proc.stderr[-2000:])
    assert "Traceback" not in proc.stderr
    return lines[0]


@pytest.mark.parametrize("service", sorted(SERVICES))
def test_a_malformed_zenoh_setting_exits_2_with_one_line(service: str) -> None:
    line = refused(["-m", f"services.{service}", *SERVICES[service], "--cfg", "mode"])
    assert "configuration error" in line and "--cfg expects KEY:VALUE" in line


@pytest.mark.parametrize("service", ["sim", "mec", "coordinator"])
def test_a_bad_settings_file_exits_2_naming_file_and_field(service: str, tmp_path: Path) -> None:
    missing = tmp_path / "missing.yaml"
    assert str(missing) in refused(
        ["-m", f"services.{service}", *SERVICES[service], "--settings", str(missing)]
    )
    bad = tmp_path / "bad.yaml"
    bad.write_text("report_interval_s: -1\n" if service != "mec" else "tracking: 5\n")
    line = refused(["-m", f"services.{service}", *SERVICES[service], "--settings", str(bad)])
    assert str(bad) in line and ("report_interval_s" in line or "tracking" in line), line


@pytest.mark.parametrize("service", sorted(SERVICES))
def test_a_missing_key_file_exits_2_naming_the_setting_and_the_file(service: str, tmp_path: Path) -> None:
    """A TLS key or certificate the Zenoh config names but that is not there (Zenoh would retry for ever)."""
    key = tmp_path / "no-such-key.pem"
    args = ["--cfg", f'transport/link/tls/connect_private_key:"{key}"']
    line = refused(["-m", f"services.{service}", *SERVICES[service], *args])
    assert "transport/link/tls/connect_private_key" in line and str(key) in line, line


def test_a_sensor_group_that_is_not_the_scene_s_exits_2() -> None:
    line = refused(["-m", "services.sensor", "--group", "agent9-cameras"])
    assert "agent9-cameras" in line


def test_a_missing_plan_key_exits_2_naming_it(tmp_path: Path) -> None:
    key = tmp_path / "no-such.key"
    line = refused(["-m", "services.coordinator"], env={"RMMDET_COORD_PLAN_SIGNING_KEY": str(key)})
    assert str(key) in line and "plan-signing key not found" in line
