"""`compare_table` reads both files' numbers for the agent and outputs asked, and says what is missing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from studies.evaluation.compare import compare_table, compare_tables


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


def test_paired_column_from_per_seed_figures_on_the_same_seeds() -> None:
    def results(commit: str, aps: list[float], motas: list[float]) -> dict[str, object]:
        seeds = {str(s): {"ap_bev_0.7": a, "mota": m} for s, a, m in zip((1, 2, 3), aps, motas, strict=True)}
        return {
            "commit": commit,
            "split": "tuning",
            "agents": ["agent1"],
            "agent1": {"tracked": {"ap_bev_0.7": 0.9, "tracking": {"mota": 0.95}, "pose_error_p95_m": 0.03}},
            "per_seed": {"agent1": seeds},
        }

    before = results("aaa", [0.90, 0.80, 0.70], [0.95, 0.95, 0.95])
    after = results("bbb", [0.92, 0.82, 0.72], [0.96, 0.94, 0.95])
    lines = compare_table(before, after, "agent1", ["tracked"]).splitlines()
    assert lines[0].endswith("| after - before, 3 seeds (95 % CI) |")
    ap = next(line for line in lines if line.startswith("| tracked AP-BEV@0.7"))
    assert ap.endswith("| **+0.020 ± 0.000** |")  # the same gain on every seed: significant
    mota = next(line for line in lines if line.startswith("| tracked MOTA"))
    assert "+0.000 ± " in mota and "**" not in mota
    pose = next(line for line in lines if line.startswith("| tracked pose error"))
    assert pose.endswith("| - |")  # not kept per seed
    other_seeds = results("ccc", [0.9, 0.8, 0.7], [0.9, 0.9, 0.9])
    other_seeds["per_seed"] = {"agent1": {"7": {"ap_bev_0.7": 0.9, "mota": 0.9}}}
    assert "CI" not in compare_table(before, other_seeds, "agent1", ["tracked"])  # not paired
    both = compare_tables(before, after, ["agent1", "agent9"], ["tracked"])
    assert both.count("| agent1, tuning |") == 1 and "agent9" not in both


def test_previous_section_needs_the_same_seeds() -> None:
    from studies.evaluation.compare import previous_section

    row = {"tracked": {"ap_bev_0.7": 0.95}}
    new = {"commit": "bbb", "seeds": [1, 2], "agents": ["agent1"], "agent1": row, "all": row}
    old = {**new, "commit": "aaa", "agent1": {"tracked": {"ap_bev_0.7": 0.94}}}
    text = previous_section(old, new, "docs/eval/fusion/previous_results.json")
    assert "commit aaa" in text and "| tracked AP-BEV@0.7 | 0.940 | 0.950 |" in text and "| all, " in text
    with pytest.raises(ValueError, match="ran seeds"):
        previous_section({**old, "seeds": [3]}, new, "x")
