"""Known answers for the robustness perturbations: how far the MEC's calibration moves, which frames a
delayed range sensor delivers, and what the noise and density perturbations change."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from sim.sensors.rig import Capture
from studies.dataset.conditions import SeedConditions
from studies.dataset.config import Variation
from studies.evaluation.fusion import RangeDelay
from studies.evaluation.robustness import CLEAN, PERTURBATIONS, RADAR_PERTURBATIONS, miscalibrated

BY_NAME = {p.name: p for p in (*PERTURBATIONS, *RADAR_PERTURBATIONS)}


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def test_miscalibration_moves_every_sensor_by_exactly_the_error(scene: Scene) -> None:
    wrong = miscalibrated(scene, 0.01, math.radians(0.5), seed=7)
    for spec in scene.spec.sensors:
        true_T, wrong_T = scene.T_world_from_sensor(spec.id), wrong.T_world_from_sensor(spec.id)
        assert np.linalg.norm(wrong_T[:3, 3] - true_T[:3, 3]) == pytest.approx(0.01, abs=1e-9)
        turn = Rotation.from_matrix(wrong_T[:3, :3] @ true_T[:3, :3].T).magnitude()
        assert turn == pytest.approx(math.radians(0.5), abs=1e-9)
    again = miscalibrated(scene, 0.01, math.radians(0.5), seed=7)
    assert np.array_equal(again.T_world_from_sensor("lidar_11"), wrong.T_world_from_sensor("lidar_11"))
    assert CLEAN.mec_scene(scene, 7) is scene  # no error: the true scene itself


def _capture(scene: Scene, sensor_id: str, stamp_s: float) -> Capture:
    stamp_ns = round(stamp_s * NS_PER_S)
    return Capture(scene.sensor(sensor_id), round(stamp_s * 60), stamp_ns, [], None)  # type: ignore[arg-type]


def test_range_delay_delivers_range_frames_a_delay_old_and_cameras_as_they_are(scene: Scene) -> None:
    delay = RangeDelay(0.1)
    delivered = []
    for k in range(5):
        t = k * 0.1
        frames = delay.captures(
            round(t * NS_PER_S), [_capture(scene, "cam_41", t), _capture(scene, "lidar_41", t)]
        )
        delivered.append([round(c.stamp_ns / NS_PER_S, 3) for c in frames])
    # The first frame passes (nothing older yet); after that the lidar is one 10 Hz frame behind.
    assert delivered == [[0.0, 0.0], [0.1, 0.0], [0.2, 0.1], [0.3, 0.2], [0.4, 0.3]]
    assert RangeDelay(0.0).captures(0, [_capture(scene, "lidar_41", 0.0)])[0].stamp_ns == 0


def test_noise_and_density_perturbations_change_only_their_own_conditions(scene: Scene) -> None:
    variation = Variation()
    base = SeedConditions.draw(variation, 501)
    noisy = BY_NAME["noise_x2"].conditions(base, variation)
    assert noisy.camera_noise_std == 2 * max(variation.camera_noise_std)
    assert noisy.lidar_range_noise_std_m == 2 * max(variation.lidar_range_noise_std_m)
    radar = noisy.model_overrides(scene)["radar"]
    model = scene.sensor("radar_2").radar
    assert model is not None and radar["range_noise_std_m"] == 2 * model.range_noise_std_m
    assert (noisy.vehicles, noisy.lighting) == (base.vehicles, base.lighting)
    dense = BY_NAME["dense"].conditions(base, variation)
    assert dense.vehicles == 32 and dense.camera_noise_std == base.camera_noise_std
    assert "radar" not in base.model_overrides(scene)  # the scene's own radar noise when unscaled
    for scale in (2, 4):
        radar_only = BY_NAME[f"radar_noise_x{scale}"].conditions(base, variation)
        radar = radar_only.model_overrides(scene)["radar"]
        for name in ("range_noise_std_m", "azimuth_noise_std_rad", "range_rate_noise_std_mps"):
            assert radar[name] == pytest.approx(scale * getattr(model, name))
        assert dataclasses.replace(radar_only, radar_noise_scale=1.0) == base  # nothing else changed
