"""Scene loading, validation and the camera/lidar/radar transform chain on every test-scene sensor."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml

from shared.config import ConfigError
from shared.geometry.camera import pixel_to_world_on_plane, project_points
from shared.geometry.transforms import (
    cartesian_to_polar,
    invert_transform,
    matrix_from_pose,
    polar_to_cartesian,
    transform_points,
)
from shared.scene.calibration import calibration_set
from shared.scene.model import SceneSpec
from shared.scene.scene import Scene
from tests.helpers import TEST_SCENE

RNG = np.random.default_rng(7)


def _points_in_view(scene: Scene, camera_id: str, n: int = 200) -> np.ndarray:
    """Random world points in front of a camera that project inside its image."""
    cam = scene.sensor(camera_id).camera
    K = scene.K(camera_id)
    uv = RNG.uniform([0, 0], [cam.width_px, cam.height_px], size=(n, 2))
    depth = RNG.uniform(0.2, 6.0, size=n)
    xy_norm = (uv - K[:2, 2]) / np.diag(K)[:2]
    pts_optical = np.column_stack([xy_norm * depth[:, None], depth])
    return transform_points(scene.T_world_from_optical(camera_id), pts_optical)


@pytest.mark.parametrize("camera_id", ["cam_level", "cam_pitched", "cam_rolled", "cam_quat"])
def test_world_pixel_ray_plane_round_trip(test_scene: Scene, camera_id: str) -> None:
    """Paper Eq. 1-2 both ways: world -> pixel -> ray -> plane z = point z recovers the point."""
    world = _points_in_view(test_scene, camera_id)
    dist = test_scene.distortion(camera_id)
    uv, depth = project_points(
        world, test_scene.T_optical_from_world(camera_id), test_scene.K(camera_id), dist
    )
    assert np.all(depth > 0)
    for point, pixel in zip(world, uv, strict=True):
        recovered, _ = pixel_to_world_on_plane(
            pixel[None, :],
            test_scene.T_world_from_optical(camera_id),
            test_scene.K(camera_id),
            plane_normal=(0.0, 0.0, 1.0),
            plane_offset=point[2],
            distortion=dist,
        )
        assert np.allclose(recovered[0], point, atol=1e-6), (camera_id, point, recovered[0])


def test_every_camera_sensor_is_covered(test_scene: Scene) -> None:
    cams = {s.id for s in test_scene.sensors_of(kind="camera")}
    assert cams == {"cam_level", "cam_pitched", "cam_rolled", "cam_quat"}


@pytest.mark.parametrize("sensor_id", ["lidar_nw", "radar_ramp"])
def test_range_sensor_polar_round_trip(test_scene: Scene, sensor_id: str) -> None:
    """world -> sensor frame -> (range, azimuth, elevation) -> sensor frame -> world."""
    T = test_scene.T_world_from_sensor(sensor_id)
    world = RNG.uniform([-3, -3, 0], [3, 3, 0.5], size=(100, 3))
    rng_m, az, el = cartesian_to_polar(transform_points(invert_transform(T), world))
    back = transform_points(T, polar_to_cartesian(rng_m, az, el))
    assert np.allclose(back, world, atol=1e-9)


def test_radar_boresight_points_along_world_y(test_scene: Scene) -> None:
    """radar_ramp has yaw pi/2: a target straight ahead lies at +y in the world."""
    T = test_scene.T_world_from_sensor("radar_ramp")
    ahead = transform_points(T, np.array([[2.0, 0.0, 0.0]]))[0]
    origin = T[:3, 3]
    assert ahead[1] - origin[1] == pytest.approx(2.0 * np.cos(0.05), abs=1e-4)
    assert abs(ahead[0] - origin[0]) < 1e-4


def test_intrinsics_from_fov(test_scene: Scene) -> None:
    K = test_scene.K("cam_level")
    assert K[0, 0] == pytest.approx(504.78216, abs=1e-4)
    assert (K[0, 2], K[1, 2]) == (320.0, 240.0)


def test_quaternion_and_rpy_poses_agree(test_scene: Scene) -> None:
    """cam_quat's quaternion is Rz(45 deg) Ry(30 deg): the same as rpy (0, 30 deg, 45 deg)."""
    from shared.geometry.transforms import matrix_from_xyz_rpy

    expected = matrix_from_xyz_rpy((-1.4, 2.0, 0.7), (0.0, np.deg2rad(30), np.deg2rad(45)))
    assert np.allclose(test_scene.T_world_from_sensor("cam_quat"), expected, atol=1e-6)


def test_calibration_set_matches_scene(test_scene: Scene) -> None:
    msg = calibration_set(test_scene, "agent1")
    assert {s.sensor_id for s in msg.sensors} == {"cam_level", "cam_pitched", "cam_rolled", "lidar_nw"}
    for s in msg.sensors:
        p, q = s.world_from_sensor.position_m, s.world_from_sensor.orientation
        T = matrix_from_pose((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))
        assert np.allclose(T, test_scene.T_world_from_sensor(s.sensor_id), atol=1e-9)
        if s.WhichOneof("model") == "camera":
            assert s.camera.fx_px == pytest.approx(test_scene.K(s.sensor_id)[0, 0])
    radar = calibration_set(test_scene, "agent2").sensors
    assert [s.paired_camera_id for s in radar if s.sensor_id == "radar_ramp"] == ["cam_quat"]


def test_areas_and_lanes(test_scene: Scene) -> None:
    assert test_scene.area_of(3.0, 1.0, 0.3) == "viaduct"
    assert test_scene.area_of(3.0, 1.0, 0.0) == "outer_ring"  # under the deck
    assert test_scene.area_of(0.0, 0.0) == "intersection"
    assert test_scene.area_of(50.0, 0.0) is None
    # Many points at once (one spatial-index query) agree with one at a time, overlaps and levels included.
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-6, 6, 2000), rng.uniform(-6, 6, 2000), rng.choice([0.0, 0.3], 2000)])
    pts[:3] = [(3.0, 1.0, 0.3), (3.0, 1.0, 0.0), (50.0, 0.0, 0.0)]
    names = [a.id for a in test_scene.spec.areas]
    got = [names[k] if k >= 0 else None for k in test_scene.area_indices(pts)]
    assert got == [test_scene.area_of(*p) for p in pts] and got[:3] == ["viaduct", "outer_ring", None]
    assert len({g for g in got if g}) >= 3
    assert test_scene.area_indices(np.zeros((0, 3))).shape == (0,)
    assert test_scene.lane_length_m("l1") == pytest.approx(3.0)
    assert [lane.id for lane in test_scene.lanes_from("j2")] == ["l2"]
    assert test_scene.junction_by_number(3).id == "j3"


def _raw() -> dict:
    return yaml.safe_load(TEST_SCENE.read_text())


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d["sensors"].append(copy.deepcopy(d["sensors"][0])), "duplicate sensor ids"),
        (lambda d: d["lanes"][0].update(to_junction="nowhere"), "unknown junction"),
        (lambda d: d["sensors"][0].update(agent="agent9"), "unknown agent"),
        (lambda d: d["sensors"][0].update(kind="lidar"), "needs exactly a `lidar` block"),
        (lambda d: d["sensors"][3]["pose"].update(quat_xyzw=[0, 0, 0.5, 0.5]), "unit quaternion"),
        (lambda d: d["sensors"][0]["pose"].update(quat_xyzw=[0, 0, 0, 1]), "exactly one of"),
        (lambda d: d["sensors"][0]["camera"].update(hfov_rad=4.0), "less than"),
        (lambda d: d["sensors"][5].update(paired_camera="lidar_nw"), "is not a camera"),
        (lambda d: d["sensors"][0].update(id="Cam 1"), "pattern"),
        (lambda d: d["sensors"][0].update(color="red"), "Extra inputs"),
    ],
)
def test_invalid_scene_is_rejected_with_a_clear_message(mutate, message: str) -> None:
    data = _raw()
    mutate(data)
    with pytest.raises(ValueError, match=message):
        SceneSpec.model_validate(data)


def test_load_reports_the_file(tmp_path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("scene_id: x\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml"):
        Scene.load(bad)
    with pytest.raises(ConfigError, match="not found"):
        Scene.load(tmp_path / "missing.yaml")
