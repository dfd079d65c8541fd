"""A site without a lane map (issue 49 item 4): the MEC builds, its road surface is the bare ground
around the agent's sensors, and lidar and radar objects come out without lanes."""

from __future__ import annotations

import numpy as np
import pytest

from shared.config import read_yaml
from shared.detection.oracle import OracleLidarDetector
from shared.geometry.transforms import cartesian_to_polar, invert_transform
from shared.perception.config import MecSettings
from shared.perception.pipeline import AgentInputs, AgentPipeline
from shared.perception.radar_camera import RadarTargets
from shared.perception.views import RoadSurface, bare_ground_m
from shared.scene.model import SceneSpec
from shared.scene.scene import Scene

TEST_SCENE = "tests/data/test_scene.yaml"


@pytest.fixture(scope="module")
def site() -> Scene:
    """The unit-test scene with its lanes and junctions taken away: sensors, areas and agents only."""
    from shared.paths import REPO_ROOT

    data = read_yaml(REPO_ROOT / TEST_SCENE)
    for key in ("lanes", "junctions", "road"):
        data.pop(key, None)
    data["design_speed_mps"] = 0.5
    return Scene(SceneSpec.model_validate(data))


def test_a_site_without_lanes_needs_a_design_speed(site: Scene) -> None:
    spec = site.spec.model_copy(update={"design_speed_mps": None})
    with pytest.raises(ValueError, match="design_speed_mps"):
        _ = spec.top_speed_mps


def test_its_surface_is_the_ground_around_the_agents_sensors(site: Scene) -> None:
    settings = MecSettings().for_site(site, "agent2")
    half = settings.surface_half_width_m
    surface = RoadSurface(site, half, settings.surface_sample_step_m, "agent2")
    radar = np.asarray(site.T_world_from_sensor("radar_ramp"))[:2, 3]
    near = radar + np.array([[3.0, 0.5], [-2.0, 4.0]])
    np.testing.assert_array_equal(surface.heights_near(near), [0.0, 0.0])
    assert np.isnan(surface.lane_heading(near)).all()  # no direction of travel without lanes
    far = radar + np.array([[200.0, 0.0]])
    assert np.isnan(surface.heights_near(far)).all()  # beyond every sensor's reach: off the site
    # Spaced at the lookup radius: the grid's size follows the site, not a fixed step.
    assert len(bare_ground_m(site, half, "agent2")) < 4 * np.pi * (30.0 + half) ** 2 / half**2


def test_lidar_objects_are_tracked_without_lanes(site: Scene) -> None:
    lidar = OracleLidarDetector(seed=0)
    pipe = AgentPipeline(site, "agent1", MecSettings(), lidar=lidar, sensor_ids=["lidar_nw"])
    origin = pipe.origin_m
    truth = np.array([[1.0, 0.5, 0.105, 0.33, 0.22, 0.21, 0.3]])  # agent frame
    tracks = []
    for frame in range(4):
        lidar.set_truth(truth)
        cloud = np.zeros((10, 4), np.float32)
        tracks = pipe.process(AgentInputs(stamp_ns=frame * 100_000_000, clouds={"lidar_nw": cloud})).tracks
    assert len(tracks) == 1
    np.testing.assert_allclose(tracks[0].position_m, origin[:2] + truth[0, :2], atol=1e-6)


def test_a_radar_target_is_placed_on_the_ground_without_lanes(site: Scene) -> None:
    pipe = AgentPipeline(site, "agent2", MecSettings(), sensor_ids=["radar_ramp"])
    T = np.asarray(site.T_world_from_sensor("radar_ramp"), float)
    reflection = T[:3, 3] + T[:3, :3] @ np.array([3.0, 0.0, 0.0])
    reflection[2] = 0.1  # on a car's side, 0.1 m above the ground
    local = (invert_transform(T) @ np.r_[reflection, 1.0])[:3]
    r, az, el = cartesian_to_polar(local[None])
    scan = RadarTargets(r, az, el, np.zeros(1), np.zeros(1))
    ((m,),) = pipe.radar_measurements(AgentInputs(stamp_ns=0, radar={"radar_ramp": scan}))
    assert m.z_m == pytest.approx(site.spec.vehicle.height_m / 2)  # half a car above the bare ground
    assert m.yaw_rad is None  # no lane: no heading
    assert np.hypot(*(m.position_m - reflection[:2])) < site.spec.vehicle.length_m
