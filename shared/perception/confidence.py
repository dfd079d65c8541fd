"""Calibrated confidence: a measurement's score as the probability that it is a true vehicle box.

Raw scores mean different things per modality: a radar target has none of its own (0.5 when no camera
confirms it, 1.0 when one does), a detector's score is the detector's. Ranking those against each
other, as AP does, compares unlike things. `ScoreCalibration` maps each (evidence, raw score) to the
precision measured for it: the share of such measurements that matched a vehicle at BEV IoU >= 0.7
(the AP-BEV@0.7 criterion) on the tuning seeds, never the test seeds.

Evidence keys are `<source>/<modalities>`: source `fused` for what the MEC pipeline outputs (e.g.
`fused/camera+radar`, `fused/radar`: radar the cameras did not confirm, a different population from
radar alone) and `alone` for one modality by itself (the studies' baselines, e.g. `alone/radar`).
Per key: isotonic regression of the match outcome on the raw score (`scipy.optimize.
isotonic_regression`, non-decreasing), kept as knots and interpolated linearly, flat beyond the
ends. A key with too few samples, or none, keeps its raw score (counted).
"""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import isotonic_regression

from shared.config import ConfigError
from shared.tracking.measurement import Measurement

FloatArray = NDArray[np.float64]
FUSED = "fused"
ALONE = "alone"
SOURCES = (FUSED, ALONE)
MIN_SAMPLES = 30  # fewer matched-or-not measurements than this: the key is not calibrated


def evidence_key(source: str, modalities: Iterable[str]) -> str:
    """`fused/camera+radar` from ("fused", {"radar", "camera"})."""
    if source not in SOURCES:
        raise ValueError(f"unknown evidence source {source!r} (one of {SOURCES})")
    return f"{source}/{'+'.join(sorted(modalities))}"


@dataclasses.dataclass(frozen=True)
class Curve:
    """Non-decreasing map raw score -> calibrated score, by its knots."""

    raw: FloatArray  # (K,) increasing
    calibrated: FloatArray  # (K,) non-decreasing, in [0, 1]
    samples: int
    precision: float  # of all the samples

    def __call__(self, raw: float | FloatArray) -> Any:
        return np.interp(raw, self.raw, self.calibrated)


def fit_curve(raw: FloatArray, matched: NDArray[np.bool_]) -> Curve:
    """Isotonic fit of `matched` (0/1) on `raw`; knots at the ends of each constant block."""
    order = np.argsort(raw, kind="stable")
    x, y = np.asarray(raw, float)[order], np.asarray(matched, float)[order]
    fitted = isotonic_regression(y, increasing=True).x
    xs, first = np.unique(x, return_index=True)  # equal raw scores share one fitted value
    ys = np.array([fitted[a:b].mean() for a, b in zip(first, [*first[1:], len(x)], strict=True)])
    # Keep a knot where the value changes, on both sides: the step shape survives interpolation.
    change = np.flatnonzero(np.diff(ys) != 0)
    keep = np.unique(np.concatenate([[0, len(xs) - 1], change, change + 1]))
    return Curve(xs[keep], np.clip(ys[keep], 0.0, 1.0), len(x), float(y.mean()))


class ScoreCalibration:
    """Calibrated scores per evidence key (module docstring); empty: every score stays raw."""

    def __init__(self, curves: dict[str, Curve] | None = None) -> None:
        self.curves = dict(curves or {})

    @classmethod
    def fit(
        cls, samples: dict[str, tuple[FloatArray, NDArray[np.bool_]]], min_samples: int = MIN_SAMPLES
    ) -> ScoreCalibration:
        """From {key: (raw scores, matched)}; keys with fewer than `min_samples` are left out."""
        return cls({k: fit_curve(r, m) for k, (r, m) in samples.items() if len(r) >= min_samples})

    @classmethod
    def load(cls, path: Path) -> ScoreCalibration:
        """Raises ConfigError naming the file when it is missing, not JSON, or a curve is malformed."""
        try:
            data = json.loads(path.read_text())
            curves = {
                key: Curve(
                    np.asarray(c["raw"], float),
                    np.asarray(c["calibrated"], float),
                    c["samples"],
                    c["precision"],
                )
                for key, c in data["curves"].items()
            }
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ConfigError(f"{path}: not a score calibration: {err!r}") from None
        for key, c in curves.items():
            if c.raw.ndim != 1 or c.raw.shape != c.calibrated.shape or len(c.raw) == 0:
                raise ConfigError(f"{path}: curve {key!r} needs equal, non-empty raw and calibrated lists")
            if np.any(np.diff(c.raw) <= 0) or np.any((c.calibrated < 0) | (c.calibrated > 1)):
                raise ConfigError(f"{path}: curve {key!r} needs increasing raw scores and values in [0, 1]")
        return cls(curves)

    def to_dict(self) -> dict[str, Any]:
        return {
            "curves": {
                key: {
                    "raw": c.raw.round(6).tolist(),
                    "calibrated": c.calibrated.round(6).tolist(),
                    "samples": c.samples,
                    "precision": round(c.precision, 6),
                }
                for key, c in sorted(self.curves.items())
            }
        }

    def save(self, path: Path, **meta: Any) -> None:
        path.write_text(json.dumps({**meta, **self.to_dict()}, indent=1) + "\n")

    def score(self, key: str, raw: float) -> float | None:
        """The calibrated score, None when `key` has no curve."""
        curve = self.curves.get(key)
        return None if curve is None else float(curve(raw))

    def apply(
        self, source: str, measurements: list[Measurement], counts: Counter[str] | None = None
    ) -> list[Measurement]:
        """`measurements` with calibrated scores (new objects; the given ones are not changed); one
        without a curve keeps its raw score, counted as `score/uncalibrated` in `counts`."""
        if not self.curves:
            return measurements
        out = []
        for m in measurements:
            score = self.score(evidence_key(source, m.modalities), m.score)
            if score is None:
                if counts is not None:
                    counts["score/uncalibrated"] += 1
                out.append(m)
            else:
                out.append(dataclasses.replace(m, score=score))
        return out
