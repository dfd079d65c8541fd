"""`rmmdet --help` and every group's help read in an 80-column terminal: one line per command, grouped;
`rmmdet --version` prints pyproject's version."""

from __future__ import annotations

import re
from importlib.metadata import version

import pytest
from typer.testing import CliRunner

from services.cli.main import app

GROUPS = ["dataset", "train", "eval", "experiments", "calibrate", "pki"]


def _help(*args: str) -> str:
    result = CliRunner().invoke(app, [*args, "--help"], env={"COLUMNS": "80", "TERMINAL_WIDTH": "80"})
    assert result.exit_code == 0, result.output
    return result.output


def _command_rows(text: str) -> list[str]:
    """The lines inside the panels that list commands (every panel but Options)."""
    rows, inside = [], False
    for line in text.splitlines():
        if line.startswith("╭─"):
            inside = "Options" not in line and "Arguments" not in line
        elif line.startswith("╰─"):
            inside = False
        elif inside:
            rows.append(line)
    return rows


@pytest.mark.parametrize("group", [None, *GROUPS])
def test_help_fits_80_columns_one_line_per_command(group: str | None) -> None:
    text = _help(*([group] if group else []))
    assert max(len(line) for line in text.splitlines()) <= 80
    rows = _command_rows(text)
    assert rows, text
    # A wrapped description would leave a row whose command column is blank.
    assert all(re.match(r"│ [a-z]", row) for row in rows), "\n".join(rows)


def test_top_level_groups_and_version() -> None:
    text = _help()
    for panel in ("Live system", "Recordings", "Offline studies", "Sites and security"):
        assert f"─ {panel} " in text
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"rmmdet {version('rmmdet')}"
