"""`compare_table` reads both files' numbers for the agent and outputs asked, and says what is missing."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from services.cli.main import app
from studies.evaluation.compare import compare_table


def test_rows_come_from_each_file_and_missing_values_show() -> None:
    before = {
        "commit": "aaa",
        "split": "test",
        "agent2": {"tracked": {"ap_bev_0.7": 0.8781, "pose_error_p95_m": 0.038, "tracking": {"mota": 0.944}}},
    }
    after = {
        "commit": "bbb",
        "split": "test",
        "agent2": {
            "tracked": {"ap_bev_0.7": 0.9106, "pose_error_p95_m": 0.032, "tracking": {"mota": 0.9436}},
            "radar": {"ap_bev_0.7": 0.82, "pose_error_p95_m": 0.044},
        },
    }
    lines = compare_table(before, after, "agent2", ["tracked", "radar"]).splitlines()
    assert lines[0] == "| agent2, test | before (aaa) | after (bbb) |"
    assert "| tracked AP-BEV@0.7 | 0.878 | 0.911 |" in lines
    assert "| tracked MOTA | 0.944 | 0.944 |" in lines
    assert "| tracked pose error p95 m | 0.038 | 0.032 |" in lines
    assert "| radar AP-BEV@0.7 | - | 0.820 |" in lines  # the output is new in the second file
    assert not any(line.startswith("| radar MOTA") for line in lines)  # untracked: no MOTA in either


def test_the_command_refuses_what_is_not_a_results_file_of_the_agent(tmp_path: Path) -> None:
    good = tmp_path / "good.json"
    good.write_text(json.dumps({"commit": "aaa", "agent2": {"tracked": {"ap_bev_0.7": 0.9}}}))
    broken = tmp_path / "broken.json"
    broken.write_text("{x")

    def run(*args: str) -> tuple[int, str]:
        result = CliRunner().invoke(app, ["eval", "compare", *args])
        return result.exit_code, result.output

    code, out = run(str(good), str(good), "--agent", "agent2")
    assert code == 0 and "| tracked AP-BEV@0.7 | 0.900 | 0.900 |" in out
    for args, reason in (
        ((str(tmp_path / "missing.json"), str(good)), "does not exist"),
        ((str(broken), str(good)), "not a results file"),
        ((str(good), str(good), "--agent", "agent9"), "no results for agent"),
    ):
        code, out = run(*args)
        assert code != 0 and reason in " ".join(out.split()), out
