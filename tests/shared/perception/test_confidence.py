"""Calibrated confidence: known answers, properties of the isotonic curves, application and storage."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.perception.confidence import ScoreCalibration, evidence_key, fit_curve
from shared.tracking.measurement import Measurement


def test_evidence_key_sorts_modalities() -> None:
    assert evidence_key("fused", {"radar", "camera"}) == "fused/camera+radar"
    assert evidence_key("alone", frozenset({"lidar"})) == "alone/lidar"
    with pytest.raises(ValueError, match="unknown evidence source"):
        evidence_key("tracked", {"lidar"})


def test_fit_curve_known_answer() -> None:
    """Outcomes 0 1 0 1 at raw 0.1..0.4: the violator pair (1, 0) pools to 0.5."""
    curve = fit_curve(np.array([0.4, 0.1, 0.3, 0.2]), np.array([True, False, False, True]))
    np.testing.assert_allclose(curve.raw, [0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(curve.calibrated, [0.0, 0.5, 0.5, 1.0])
    assert curve(0.25) == pytest.approx(0.5)
    assert curve(0.15) == pytest.approx(0.25)  # linear between knots
    assert curve(0.0) == 0.0 and curve(1.0) == 1.0  # flat beyond the ends
    assert curve.samples == 4 and curve.precision == 0.5


def test_constant_raw_score_calibrates_to_its_precision() -> None:
    """Radar targets carry no score of their own: the calibrated score is the measured precision."""
    curve = fit_curve(np.full(10, 0.5), np.array([True] * 7 + [False] * 3))
    assert curve.raw.tolist() == [0.5]
    assert curve(0.5) == pytest.approx(0.7)
    assert curve(0.9) == pytest.approx(0.7)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.sampled_from([0.1, 0.2, 0.35, 0.5, 0.8, 0.95]), st.booleans()), min_size=1, max_size=60
    )
)
def test_curve_is_monotone_bounded_and_keeps_the_mean(samples: list[tuple[float, bool]]) -> None:
    raw = np.array([r for r, _ in samples])
    matched = np.array([m for _, m in samples])
    curve = fit_curve(raw, matched)
    assert np.all(np.diff(curve.calibrated) >= -1e-12)
    assert np.all((curve.calibrated >= 0) & (curve.calibrated <= 1))
    # Isotonic regression preserves the total: on its own samples the mean score is the true share.
    assert np.mean(curve(raw)) == pytest.approx(matched.mean())
    # Knots are fewer than the distinct scores unless every one is needed.
    assert len(curve.raw) <= len(np.unique(raw))


def _m(modalities: set[str], score: float) -> Measurement:
    return Measurement(np.zeros(2), np.eye(2), 0.0, modalities=frozenset(modalities), score=score)


def test_apply_calibrates_by_evidence_and_counts_what_it_cannot() -> None:
    radar = fit_curve(np.full(40, 0.5), np.array([True] * 10 + [False] * 30))
    cal = ScoreCalibration({"fused/radar": radar})
    given_ms = [_m({"radar"}, 0.5), _m({"camera", "radar"}, 1.0)]
    counts: Counter[str] = Counter()
    out = cal.apply("fused", given_ms, counts)
    assert [m.score for m in out] == [pytest.approx(0.25), 1.0]  # no curve: raw, counted
    assert counts == {"score/uncalibrated": 1}
    assert given_ms[0].score == 0.5  # the input is not modified
    assert cal.apply("alone", given_ms, counts)[0].score == 0.5  # another source, another key
    assert ScoreCalibration().apply("fused", given_ms) is given_ms  # empty: raw scores


def test_fit_leaves_out_small_keys_and_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    raw = rng.uniform(size=200)
    samples = {
        "alone/camera": (raw, rng.uniform(size=200) < raw),
        "fused/camera+lidar": (np.full(5, 0.9), np.ones(5, bool)),
    }
    cal = ScoreCalibration.fit(samples, min_samples=30)
    assert set(cal.curves) == {"alone/camera"}
    path = tmp_path / "cal.json"
    cal.save(path, fitted_on={"seeds": [1]})
    back = ScoreCalibration.load(path)
    x = np.linspace(0, 1, 11)
    np.testing.assert_allclose(back.curves["alone/camera"](x), cal.curves["alone/camera"](x), atol=1e-6)


def test_the_mec_reads_the_shipped_calibration(tmp_path: Path) -> None:
    """The pipeline loads the fitted curves its settings name (raw scores when told none)."""
    from shared.paths import DEFAULT_SCENE
    from shared.perception.config import DEFAULT_SCORE_CALIBRATION, MecSettings
    from shared.perception.pipeline import AgentPipeline
    from shared.scene.scene import Scene
    from tests.shared.perception.stubs import CountingCameras, NoCars

    scene = Scene.load(DEFAULT_SCENE)
    shipped = ScoreCalibration.load(DEFAULT_SCORE_CALIBRATION)
    assert any(key.startswith("fused/") for key in shipped.curves)
    pipe = AgentPipeline(scene, "agent1", MecSettings(), cameras=CountingCameras(), lidar=NoCars())
    assert set(pipe.calibration.curves) == set(shipped.curves)
    raw = AgentPipeline(
        scene, "agent1", MecSettings(score_calibration=None), cameras=CountingCameras(), lidar=NoCars()
    )
    assert raw.calibration.curves == {}


@pytest.mark.parametrize(
    "text",
    [
        "not json",
        '{"curves": {"fused/radar": {"raw": [0.5]}}}',
        '{"curves": {"fused/radar": {"raw": [0.5, 0.4], "calibrated": [0.1, 0.2], '
        '"samples": 2, "precision": 0.1}}}',
        '{"curves": {"fused/radar": {"raw": [0.5], "calibrated": [1.5], "samples": 2, "precision": 0.1}}}',
    ],
)
def test_a_bad_calibration_file_is_a_clear_config_error(tmp_path: Path, text: str) -> None:
    from shared.config import ConfigError

    path = tmp_path / "cal.json"
    path.write_text(text)
    with pytest.raises(ConfigError, match=r"cal\.json"):
        ScoreCalibration.load(path)
    with pytest.raises(ConfigError, match=r"missing\.json"):
        ScoreCalibration.load(tmp_path / "missing.json")
