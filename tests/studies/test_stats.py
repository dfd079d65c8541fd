"""studies/stats.py: the studies' mean and t-interval, paired differences, table cells."""

from __future__ import annotations

import math

import pytest

from studies import stats


def test_mean_ci_known_answer() -> None:
    out = stats.mean_ci([1.0, 2.0, 3.0])
    # t(0.975, 2) = 4.3027; sd = 1; half-width = 4.3027 / sqrt(3)
    assert out["mean"] == pytest.approx(2.0)
    assert out["ci95"] == pytest.approx(4.302653 / math.sqrt(3), rel=1e-5)
    assert out["n"] == 3
    assert math.isnan(stats.mean_ci([5.0])["ci95"])
    assert stats.mean_ci([None, None])["n"] == 0


def test_paired_differences_skip_undefined_pairs() -> None:
    d = stats.paired_differences([0.9, None, 0.8, 0.7], [0.92, 0.5, 0.83, None])
    assert d["n"] == 2
    assert d["mean"] == pytest.approx(0.025)
    # t(0.975, 1) = 12.706; sd of (0.02, 0.03) = 0.00707; half-width = 12.706 * 0.00707 / sqrt(2)
    assert d["ci95"] == pytest.approx(12.7062 * 0.0070711 / math.sqrt(2), rel=1e-4)


def test_significant_and_cell() -> None:
    sure = stats.mean_ci([0.02, 0.021, 0.019, 0.02])
    unsure = stats.mean_ci([0.02, -0.03, 0.01])
    assert stats.significant(sure) and not stats.significant(unsure)
    assert stats.paired_cell(sure, "{:+.3f}") == "**+0.020 ± 0.001**"
    assert stats.paired_cell(unsure, "{:+.3f}").startswith("+0.000 ± ")
    assert stats.paired_cell(stats.mean_ci([0.1]), "{:+.3f}") == "-"
