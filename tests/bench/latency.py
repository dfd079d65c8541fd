"""Latency summaries of the benchmarks' results files: one shape for every real-size bench."""

from __future__ import annotations

import numpy as np

MS_PER_S = 1e3


def latency_ms(values_s: list[float]) -> dict[str, float]:
    """Count, p50, p95 and max of durations given in seconds, in milliseconds (2 decimals)."""
    a = np.asarray(values_s, float) * MS_PER_S
    return {
        "n": int(a.size),
        "p50_ms": round(float(np.percentile(a, 50)), 2),
        "p95_ms": round(float(np.percentile(a, 95)), 2),
        "max_ms": round(float(a.max()), 2),
    }
