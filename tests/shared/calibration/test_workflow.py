"""The calibration workflow on files (shared/calibration/workflow.py): poses as the scene writes them,
a lidar's pose from surveyed targets into a site file, and what it refuses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from shared.calibration import workflow
from shared.calibration.solve import pose_error
from shared.devices.site import SiteFile
from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene


def transform(rotvec: list[float], position_m: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = position_m
    return T


def test_pose_spec_and_pose_matrix_round_trip() -> None:
    T = transform([0.1, -0.2, 1.3], [1.5, -2.0, 0.8])
    back = workflow.pose_matrix(workflow.pose_spec(T).model_dump(exclude_none=True))
    assert np.allclose(back, T, atol=1e-12)
    # roll-pitch-yaw as the scene writes it: yaw about z first
    rpy = workflow.pose_matrix({"position_m": [0, 0, 0], "rpy_rad": [0.0, 0.0, np.pi / 2]})
    assert np.allclose(rpy[:3, 0], [0, 1, 0], atol=1e-12)


@pytest.fixture
def site(tmp_path: Path) -> Path:
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump({"site_id": "t", "scene": str(DEFAULT_SCENE), "sensors": {}}))
    return path


def test_a_lidar_pose_from_surveyed_targets_goes_into_the_site_file(site: Path, tmp_path: Path) -> None:
    truth = transform([0.0, 0.05, 2.1], [-1.2, 0.4, 0.35])
    rng = np.random.default_rng(3)
    sensor_m = rng.uniform([-3, -3, -0.3], [3, 3, 0.3], (8, 3))
    world_m = sensor_m @ truth[:3, :3].T + truth[:3, 3]
    survey = tmp_path / "targets.yaml"
    points = [{"world_m": w.tolist(), "sensor_m": s.tolist()} for w, s in zip(world_m, sensor_m, strict=True)]
    survey.write_text(yaml.safe_dump({"points": points}))
    fit = workflow.sensor_pose_into_site(site, "lidar_11", survey)
    assert fit.points == 8 and fit.rms < 1e-9
    scene = SiteFile.load(site).calibrated_scene(Scene.load(DEFAULT_SCENE))
    dt_m, dr_deg = pose_error(np.asarray(scene.T_world_from_sensor("lidar_11")), truth)
    assert dt_m < 1e-9 and dr_deg < 1e-6
    assert "8 targets" in SiteFile.load(site).calibration["lidar_11"].note


def test_what_the_workflow_refuses(site: Path, tmp_path: Path) -> None:
    survey = tmp_path / "empty.yaml"
    survey.write_text(yaml.safe_dump({"points": [{"world_m": [0, 0, 0]}]}))
    with pytest.raises(ValueError, match="sensor_m"):
        workflow.sensor_pose_into_site(site, "lidar_11", survey)
    with pytest.raises(ValueError, match="not a sensor"):
        workflow.update_site(site, "lidar_99", note="x")
    with pytest.raises(ValueError, match="no images"):
        workflow.intrinsics_into_site([], site, "cam_11", "checkerboard:8x5:0.02", False, workflow.Skipped())
    (tmp_path / "noise.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="not an image"):
        workflow.intrinsics_into_site(
            [tmp_path / "noise.png"], site, "cam_11", "checkerboard:8x5:0.02", False, workflow.Skipped()
        )


def test_a_placement_that_disagrees_with_the_others_is_left_out() -> None:
    """Three placements fitted alone: two near the camera's pose, one read turned (180 deg off, as
    well reprojected): the joint fit takes the two."""
    from shared.calibration.solve import PoseFit

    near = transform([0.0, 0.0, 0.5], [1.0, 2.0, 0.45])
    fits = [
        (np.zeros((1, 3)), np.zeros((1, 2)), PoseFit(near, 0.4, 40)),
        (np.ones((1, 3)), np.ones((1, 2)), PoseFit(transform([0.0, 0.01, 0.5], [1.01, 2.0, 0.45]), 0.3, 40)),
        (
            np.full((1, 3), 2.0),
            np.full((1, 2), 2.0),
            PoseFit(near @ transform([0.0, 0.0, np.pi], [0, 0, 0]), 0.2, 40),
        ),
    ]
    skipped = workflow.Skipped()
    kept = workflow.agreeing(fits, skipped)
    assert [k[0][0, 0] for k in kept] == [0.0, 1.0]
    assert skipped.reasons == ["a placement disagrees with the others: left out"]
    assert workflow.agreeing(fits[2:], workflow.Skipped()) == fits[2:]  # alone: kept
