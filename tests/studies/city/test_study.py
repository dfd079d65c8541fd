"""The city study on a toy grid: every arm on every seed, the coverage-free arms once per seed, and the
coordinator compared with each baseline paired by seed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from shared.paths import REPO_ROOT
from studies.city.config import CityStudySettings
from studies.city.study import markdown_table, run_study


def test_toy_study_compares_the_coordinator_with_every_baseline(tmp_path: Path) -> None:
    s = CityStudySettings(
        grid_side=3, demand={"light": 20}, departures_s=40.0, duration_s=400.0, seeds=[1, 2],
        coverage=[1.0, 0.5], reroute_period_s=20.0, workers=1,
    )  # fmt: skip
    results = run_study(s, tmp_path / "work", tmp_path / "out")
    runs = results["runs"]
    # 2 seeds x (as_given + shortest + sumo_oracle + 2 coverages x (sumo_covered + rmmdet)) runs.
    assert len(runs) == 2 * (3 + 2 * 2)
    assert all(r["trips"]["trips"] > 0 for r in runs)
    assert (tmp_path / "out" / "results.json").exists()
    for key in ("light@1", "light@0.5"):
        row = results["comparisons"][key]
        assert set(row) == {"as_given", "shortest", "sumo_oracle", "sumo_covered"}
        for base in row.values():
            assert all(
                base[k]["n"] == 2 for k in ("travel_time_mean_s", "time_loss_mean_s", "trips_per_hour")
            )
    table = markdown_table(results)
    assert "| light @ 1 |" not in table and "| light@1 |" in table and "vs sumo_oracle" in table


def test_tuning_refuses_the_held_out_seeds_and_unknown_levels() -> None:
    """`studies.city.tune` runs tuning seeds only: a study seed is held out."""
    for argv, said in (
        (["--seed", "1", "--level", "free_flow"], "held-out"),
        (["--seed", "101", "--level", "x"], "unknown level"),
    ):
        out = subprocess.run(
            [sys.executable, "-m", "studies.city.tune", *argv], cwd=REPO_ROOT, capture_output=True, text=True
        )
        assert out.returncode == 2 and said in out.stderr, out.stderr
