"""Agreement with a reference decoder on real recordings (issue 51): velodyne-decoder, configured from
each unit's own calibration file, against nebula's ground-truth clouds of a VLP-16 and a VLP-32C bag
(tests/fixtures/real/nebula_velodyne/). The measured facts: the same points, one to one; the same
range, elevation and ring; every azimuth difference the one its named cause predicts; every decoded
point the reference left out with a named cause. A wrong calibration breaks them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from studies.recordings.reference import (
    CLOUD_WINDOW,
    CUT_NEXT,
    CUT_PREVIOUS,
    FOV_GAP,
    ROUNDING_DEG,
    UNITS,
    compare_unit,
    markdown,
)

NAMED = {CLOUD_WINDOW, CUT_PREVIOUS, CUT_NEXT}
BY_UNIT = {run.unit: run for run in UNITS}


@pytest.fixture(scope="module")
def results() -> dict[str, dict[str, Any]]:
    return {run.unit: compare_unit(run) for run in UNITS}


@pytest.mark.parametrize("unit", sorted(BY_UNIT))
def test_the_same_points_one_to_one(results: dict[str, dict[str, Any]], unit: str) -> None:
    r = results[unit]
    assert r["matched"] == r["reference_points"] > 10_000
    assert r["reference_only"] == {}
    assert r["ring_identical"]
    assert r["cloud_named_by_its_last_message"]
    # every decoded point of the cloud's packets that the reference left out, with its named cause
    assert set(r["decoded_only"]) <= NAMED, r["decoded_only"]
    assert r["decoded_points_in_packets"] == r["matched"] + sum(r["decoded_only"].values())


def test_the_counts_measured(results: dict[str, dict[str, Any]]) -> None:
    """The known answer of the two recordings (docs/recordings.md): nebula drops the 359-360 deg wedge
    (VLP-16, cloud_max_angle 359) and the blocks past 90 deg (VLP-32C, window 270-90 deg), and cuts the
    VLP-16's last packet at 0 deg."""
    vlp16, vlp32c = results["VLP-16"], results["VLP-32C"]
    assert (vlp16["reference_points"], vlp16["matched"]) == (14831, 14831)
    assert vlp16["decoded_only"] == {CLOUD_WINDOW: 48, CUT_NEXT: 32}
    assert vlp16["return_mode"] == ["dual"] and vlp16["intensity_identical"] == 1.0
    assert (vlp32c["reference_points"], vlp32c["matched"]) == (26216, 26216)
    assert vlp32c["decoded_only"] == {CLOUD_WINDOW: 114}
    assert vlp32c["return_mode"] == ["strongest"]


@pytest.mark.parametrize("unit", sorted(BY_UNIT))
def test_range_elevation_agree_and_the_azimuth_is_the_whole_difference(
    results: dict[str, dict[str, Any]], unit: str
) -> None:
    dev = results[unit]["deviation"]
    assert dev["range_mm"]["max"] < 0.01
    assert dev["elevation_deg"]["max"] < 1e-4
    assert dev["residual_with_reference_azimuth_mm"]["max"] < 0.01
    assert dev["xyz_mm"]["max"] > 40  # the azimuths do differ


@pytest.mark.parametrize("unit", sorted(BY_UNIT))
def test_every_azimuth_difference_is_its_named_cause(results: dict[str, dict[str, Any]], unit: str) -> None:
    r = results[unit]
    assert r["deviation"]["azimuth_explained"] == 1.0
    assert r["deviation"]["azimuth_minus_cause_deg"]["max"] <= ROUNDING_DEG
    assert all(c["explained"] == 1.0 for c in r["by_cause"].values())


def test_velodyne_decoder_is_the_one_off_in_the_vlp32c_fov_gap(results: dict[str, dict[str, Any]]) -> None:
    """The VLP-32C is set to a 270-90 deg field of view: in the 5 packets that jump across the gap,
    velodyne-decoder's packet-wide rotation rate puts returns up to 10 deg off (nebula's per-block
    step is right there); elsewhere the difference stays under 0.2 deg."""
    r = results["VLP-32C"]
    assert r["fov_gap_packets"] == 5
    gap = r["by_cause"][FOV_GAP]
    assert 5 < gap["azimuth_deg"]["max"] < 11
    rest = [c["azimuth_deg"]["max"] for name, c in r["by_cause"].items() if name != FOV_GAP]
    assert max(rest) < 0.2


def test_the_project_stream_decodes_the_same_points(results: dict[str, dict[str, Any]]) -> None:
    for r in results.values():
        assert r["stream"]["scans"] >= 3 and r["stream"]["identical"]


def test_a_wrong_calibration_is_caught(tmp_path: Path) -> None:
    """One laser's azimuth correction and another's vertical angle 1 mrad off (0.057 deg) in the
    VLP-16's file: its azimuths no longer follow the causes, its elevations disagree."""
    run = BY_UNIT["VLP-16"]
    doc = yaml.safe_load(run.calibration.read_text())
    for laser in doc["lasers"]:
        if laser["laser_id"] == 3:
            laser["rot_correction"] += 0.001
        if laser["laser_id"] == 5:
            laser["vert_correction"] += 0.001
    wrong = tmp_path / "VLP16.yaml"
    wrong.write_text(yaml.safe_dump(doc))
    dev = compare_unit(run, calibration=wrong)["deviation"]
    assert dev["azimuth_explained"] < 0.95
    assert dev["elevation_deg"]["max"] > 0.05
    assert dev["residual_with_reference_azimuth_mm"]["max"] > 1


def test_the_table_names_every_unit_and_cause(results: dict[str, dict[str, Any]]) -> None:
    text = markdown(
        {
            "decoder": "velodyne-decoder",
            "reference": {"repository": "tier4/nebula", "commit": "606ac41f"},
            "units": list(results.values()),
            "commit": "abc1234",
        }
    )
    for unit, r in results.items():
        assert f"| {unit} |" in text
        assert all(name in text for name in r["by_cause"])
