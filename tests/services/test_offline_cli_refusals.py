"""Offline commands refuse bad settings with one line and exit 2, before any work (no traceback)."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from services.cli.main import app


def test_a_flow_experiment_with_one_seed_is_refused(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["experiments", "flow", "--seed", "301", "--out", str(tmp_path)])
    assert result.exit_code == 2 and "at least 2 items" in result.output
    assert not any(tmp_path.iterdir())


def test_a_dataset_at_an_unknown_scene_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    result = CliRunner().invoke(app, ["dataset", "generate", "--out", str(out), "--scene", "nosuch"])
    assert result.exit_code == 2 and "no profile deploy/profiles/scene/nosuch.yaml" in result.output
    assert not out.exists()
