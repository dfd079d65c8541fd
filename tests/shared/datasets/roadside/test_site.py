"""A dataset's site as the project's (issue 50): the ground the real lidar sees levelled to z = 0, the
scene written from the calibration (no lanes), the frames as the messages a MEC decodes."""

from __future__ import annotations

import numpy as np
import pytest

from shared.datasets.roadside import site
from shared.datasets.roadside.model import RoadsideDataset, RoadsideFormatError
from shared.datasets.roadside.pcd import read_pcd
from shared.geometry.transforms import camera_optical_from_world, matrix_from_pose
from shared.perception.decode import PNG_MAGIC, FrameDecoder, point_cloud_to_array
from shared.scene.scene import Scene


@pytest.fixture(scope="module")
def levelled(tumtraf: RoadsideDataset) -> RoadsideDataset:
    return site.level_to_ground(tumtraf, site.fit_site_ground(tumtraf))


def test_the_ground_the_lidar_sees_is_levelled_to_zero(
    tumtraf: RoadsideDataset, levelled: RoadsideDataset
) -> None:
    """In s110_base the road is ~1 m down; levelled, the labelled vehicles stand on z = 0 (the labels'
    own bottoms scatter by a few decimetres: they are hand-placed boxes on a road with a crown)."""

    def bottoms(data: RoadsideDataset) -> np.ndarray:
        return np.array(
            [lab.box_m[2] - lab.box_m[5] / 2 for f in data.frames for lab in f.labels if lab.label]
        )

    assert np.median(bottoms(tumtraf)) < -0.5
    assert abs(np.median(bottoms(levelled))) < 0.15
    assert np.percentile(np.abs(bottoms(levelled)), 90) < 0.5
    lidar = next(s for s in levelled.sensors.values() if s.kind == "lidar")
    assert 8.0 < lidar.T_site_from_sensor[2, 3] < 8.5  # the pole's lidar, above the road
    # xy and headings barely move (a 0.8 deg levelling)
    a, b = tumtraf.frames[0].labels[0].box_m, levelled.frames[0].labels[0].box_m
    assert np.hypot(*(a[:2] - b[:2])) < 0.5 and abs(a[6] - b[6]) < 0.01


def test_the_scene_comes_from_the_calibration(levelled: RoadsideDataset) -> None:
    spec = site.site_scene(levelled)
    scene = Scene(spec)
    assert not spec.lanes and spec.design_speed_mps == pytest.approx(13.9)
    assert spec.vehicle.length_m == pytest.approx(4.5)  # the real-size reference car
    lidar = scene.sensors["s110_lidar_ouster_south"]
    assert lidar.lidar is not None and lidar.lidar.channels == 64
    assert (
        -0.40 < lidar.lidar.vertical_min_rad < -0.36 and lidar.lidar.vertical_max_rad < 0
    )  # a below-horizon OS1-64
    cam = scene.sensors["s110_camera_basler_south2_8mm"]
    assert cam.camera is not None and cam.camera.intrinsics_px == pytest.approx(
        (1296.38, 1337.75, 957.363, 604.919)
    )
    # the camera's pose in the scene reproduces the dataset's projection of a label centre
    K = np.array([[1296.38, 0, 957.363], [0, 1337.75, 604.919], [0, 0, 1]])
    T = levelled.sensors[cam.id].T_site_from_sensor
    centre = levelled.frames[0].labels[4].box_m[:3]
    want = K @ (np.linalg.inv(T) @ np.append(centre, 1))[:3]
    T_world_from_body = matrix_from_pose(cam.pose.position_m, cam.pose.quat_xyzw)
    got = K @ (camera_optical_from_world(T_world_from_body) @ np.append(centre, 1))[:3]
    np.testing.assert_allclose(got[:2] / got[2], want[:2] / want[2], atol=1e-6)


def test_frames_become_the_messages_a_mec_decodes(levelled: RoadsideDataset) -> None:
    frame = levelled.frames[0]
    messages = {sid: (stamp, msg) for sid, stamp, msg in site.frame_messages(levelled, frame)}
    assert set(messages) == {
        "s110_lidar_ouster_south",
        "s110_camera_basler_south1_8mm",
        "s110_camera_basler_south2_8mm",
    }
    stamp, cloud = messages["s110_lidar_ouster_south"]
    points = point_cloud_to_array(cloud)
    raw = read_pcd(frame.clouds["s110_lidar_ouster_south"])
    np.testing.assert_allclose(points[:, :3], raw.xyz_m, atol=1e-5)
    assert points[:, 3].min() >= 0 and points[:, 3].max() <= 1
    assert stamp == frame.stamp_ns
    image = FrameDecoder().image(
        "s110_camera_basler_south2_8mm", messages["s110_camera_basler_south2_8mm"][1]
    )
    assert image.shape == (1200, 1920, 3)


def test_an_image_is_told_by_its_bytes_not_its_name(tmp_path) -> None:
    png = tmp_path / "a.jpg"
    png.write_bytes(PNG_MAGIC + b"rest")
    assert site.image_format(png.read_bytes(), png) == "png"
    with pytest.raises(RoadsideFormatError, match="neither a JPEG nor a PNG"):
        site.image_format(b"GIF89a", png)


def test_is_sequence_known_answers() -> None:
    from shared.datasets.roadside.model import FRAME_PERIOD_NS as T
    from shared.datasets.roadside.model import is_sequence

    assert is_sequence([0, T, 2 * T, 5 * T])  # up to two dropped frames
    assert not is_sequence([0, T, 5 * T])  # three dropped: a new sequence
    assert not is_sequence([0]) and not is_sequence([])  # one frame tracks nothing
    assert not is_sequence([0, 0, T])  # two files of one instant are not consecutive frames
