"""Confidence intervals of the studies: one home for the mean and its Student-t interval, used for paired
differences over seeds (the same seed run under two arms, models or policies)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats

#: Two-sided confidence of every interval the studies report.
CONFIDENCE = 0.95


def mean_ci(values: Sequence[float | None]) -> dict[str, float]:
    """Mean of the defined `values` and the half-width `ci95` of its `CONFIDENCE` t-interval (NaN below
    two values); `n` counts the values used."""
    x = np.asarray([v for v in values if v is not None], float)
    if len(x) == 0:
        return {"mean": math.nan, "ci95": math.nan, "n": 0}
    half = (
        float(stats.t.ppf(0.5 + CONFIDENCE / 2, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x)))
        if len(x) > 1
        else math.nan
    )
    return {"mean": float(x.mean()), "ci95": half, "n": len(x)}


def paired_differences(before: Sequence[float | None], after: Sequence[float | None]) -> dict[str, float]:
    """`mean_ci` of after - before over the pairs where both are defined (e.g. an AP is None on a seed
    with nothing to score)."""
    return mean_ci([b - a for a, b in zip(before, after, strict=True) if a is not None and b is not None])


def significant(d: dict[str, float]) -> bool:
    """The interval of `d` (a `mean_ci`) excludes zero."""
    return bool(d.get("n", 0) > 1 and math.isfinite(d["ci95"]) and abs(d["mean"]) > d["ci95"])


def paired_cell(d: dict[str, float], fmt: str) -> str:
    """A table cell `+x ± ci` of a `mean_ci` (`fmt` with its sign, e.g. "{:+.3f}"), bold when the
    interval excludes zero; "-" without an interval."""
    if not d.get("n") or not math.isfinite(d["ci95"]):
        return "-"
    text = f"{fmt.format(d['mean'])} ± {fmt.replace('+', '').format(d['ci95'])}"
    return f"**{text}**" if significant(d) else text
