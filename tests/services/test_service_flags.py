"""Every service takes the same flags for the same things: its instance, the log interval of rates and
counters, the Zenoh flags; a settings file with `--settings` and the scene with `--scene` wherever it
has them (a flag given overrides the file)."""

from __future__ import annotations

import argparse
import importlib

import pytest

from shared.service import DEFAULT_REPORT_INTERVAL_S, report_interval_s

SERVICES = (
    "router",
    "sim",
    "sensor",
    "device",
    "mec",
    "coordinator",
    "recorder",
    "viewer",
    "vehicle",
    "watchdog",
)
WITH_SETTINGS = ("sim", "sensor", "mec", "coordinator")
WITH_SCENE = ("sim", "sensor", "mec", "coordinator", "viewer")
COMMON = ("--instance", "--report-interval-s", "--config", "--connect", "--listen", "--cfg")


def help_text(service: str, capsys: pytest.CaptureFixture[str]) -> str:
    cli = importlib.import_module(f"services.{service}.main").cli
    with pytest.raises(SystemExit) as exit_:
        cli(["--help"])
    assert exit_.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("service", SERVICES)
def test_the_same_flags_everywhere(service: str, capsys: pytest.CaptureFixture[str]) -> None:
    text = help_text(service, capsys)
    for flag in COMMON:
        assert flag in text, (service, flag)
    assert ("--settings" in text) == (service in WITH_SETTINGS), service
    assert ("--scene" in text) == (service in WITH_SCENE), service


def test_the_report_interval_flag_overrides_the_settings_file() -> None:
    assert report_interval_s(argparse.Namespace(report_interval_s=None)) == DEFAULT_REPORT_INTERVAL_S
    assert report_interval_s(argparse.Namespace(report_interval_s=None), 30.0) == 30.0
    assert report_interval_s(argparse.Namespace(report_interval_s=2.5), 30.0) == 2.5


@pytest.mark.parametrize("bad", ["0", "-1", "nan", "inf", "ten"])
def test_a_bad_report_interval_is_refused_by_argparse(bad: str, capsys: pytest.CaptureFixture[str]) -> None:
    cli = importlib.import_module("services.router.main").cli
    with pytest.raises(SystemExit) as exit_:
        cli(["--report-interval-s", bad])
    assert exit_.value.code == 2
    assert "--report-interval-s" in capsys.readouterr().err
