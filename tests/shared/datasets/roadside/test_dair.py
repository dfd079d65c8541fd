"""The DAIR-V2X infrastructure reader (issue 50). No DAIR-V2X frame is public outside the dataset's
archives, so the reader meets a real frame in its layout: the first TUMTraf A9 frame (its real cloud,
image and labels) written here as DAIR-V2X-I writes a frame (data_info.json, a binary_compressed PCD,
cam_K / virtuallidar_to_camera, labels with numbers as strings, as the dataset's tools expect). The
known answer is TUMTraf's own: the points in each box are its num_points."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from shared.datasets.roadside.dair import CAMERA_ID, LIDAR_ID, read_dair
from shared.datasets.roadside.model import RoadsideDataset, RoadsideFormatError
from shared.datasets.roadside.pcd import read_header, read_pcd
from shared.geometry.transforms import invert_transform

CAMERA = "s110_camera_basler_south2_8mm"
LIDAR = "s110_lidar_ouster_south"


def write_dair(tumtraf: RoadsideDataset, root: Path) -> Path:
    """TUMTraf's first frame in DAIR-V2X-I's layout, its lidar frame as the virtual lidar's."""
    frame, lidar, cam = tumtraf.frames[0], tumtraf.sensors[LIDAR], tumtraf.sensors[CAMERA]
    for folder in (
        "velodyne",
        "image",
        "calib/camera_intrinsic",
        "calib/virtuallidar_to_camera",
        "label/virtuallidar",
    ):
        (root / folder).mkdir(parents=True, exist_ok=True)
    cloud = o3d.t.io.read_point_cloud(frame.clouds[lidar.id])
    o3d.t.io.write_point_cloud(root / "velodyne/000000.pcd", cloud, write_ascii=False, compressed=True)
    shutil.copy(frame.images[cam.id], root / "image/000000.jpg")
    assert cam.K is not None
    (root / "calib/camera_intrinsic/000000.json").write_text(
        json.dumps({"cam_K": cam.K.ravel().tolist(), "cam_D": [0, 0, 0, 0, 0]})
    )
    T = invert_transform(cam.T_site_from_sensor) @ lidar.T_site_from_sensor  # lidar -> camera
    (root / "calib/virtuallidar_to_camera/000000.json").write_text(
        json.dumps({"rotation": T[:3, :3].tolist(), "translation": T[:3, 3:].tolist()})
    )
    to_lidar = invert_transform(lidar.T_site_from_sensor)
    objects = []
    for label in frame.labels:
        assert label.T_site_from_box is not None and label.size_m is not None
        box = to_lidar @ label.T_site_from_box  # yaw-only in the lidar's frame, as TUMTraf labelled it
        length, width, height = label.size_m
        objects.append(
            {
                "type": label.category.capitalize(),  # DAIR writes "Car", "Truck", "Pedestrian"
                "truncated_state": 0,
                "occluded_state": 0,
                "alpha": 0,
                "2d_box": {"xmin": 0, "ymin": 0, "xmax": 0, "ymax": 0},
                "3d_dimensions": {"h": str(height), "w": str(width), "l": str(length)},
                "3d_location": {"x": str(box[0, 3]), "y": str(box[1, 3]), "z": str(box[2, 3])},
                "rotation": str(np.arctan2(box[1, 0], box[0, 0])),
                "num_points_tumtraf": label.num_points,
            }
        )
    (root / "label/virtuallidar/000000.json").write_text(json.dumps(objects))
    info = [
        {
            "image_path": "image/000000.jpg",
            "pointcloud_path": "velodyne/000000.pcd",
            "label_virtuallidar_path": "label/virtuallidar/000000.json",
            "label_camera_path": "label/camera/000000.json",
            "calib_virtuallidar_to_camera_path": "calib/virtuallidar_to_camera/000000.json",
            "calib_camera_intrinsic_path": "calib/camera_intrinsic/000000.json",
        }
    ]
    (root / "data_info.json").write_text(json.dumps(info))
    return root


@pytest.fixture()
def dair_root(tumtraf: RoadsideDataset, tmp_path: Path) -> Path:
    return write_dair(tumtraf, tmp_path / "single-infrastructure-side")


def test_a_real_frame_in_dair_layout_reads_back(dair_root: Path, tumtraf: RoadsideDataset) -> None:
    assert read_header(dair_root / "velodyne/000000.pcd").data == "binary_compressed"
    (site,) = read_dair(dair_root)
    assert set(site.sensors) == {LIDAR_ID, CAMERA_ID} and not site.sequence
    (frame,) = site.frames
    assert len(frame.labels) == 15 and frame.missing == ()
    xyz = read_pcd(frame.clouds[LIDAR_ID]).xyz_m
    want = [
        o["num_points_tumtraf"]
        for o in json.loads((dair_root / "label/virtuallidar/000000.json").read_text())
    ]
    assert [int(lab.contains(xyz).sum()) for lab in frame.labels] == want  # TUMTraf's own counts
    assert {lab.label for lab in frame.labels} == {"car", "truck", None}
    cam = site.sensors[CAMERA_ID]
    assert (cam.width_px, cam.height_px) == (1920, 1200)
    # the camera sees the labels where TUMTraf's calibration puts them
    ref_cam, ref_lidar = tumtraf.sensors[CAMERA], tumtraf.sensors[LIDAR]
    centre = frame.labels[4].box_m[:3]
    ours = cam.K @ (invert_transform(cam.T_site_from_sensor) @ np.append(centre, 1))[:3]
    site_point = ref_lidar.T_site_from_sensor @ np.append(centre, 1)
    theirs = ref_cam.K @ (invert_transform(ref_cam.T_site_from_sensor) @ site_point)[:3]
    np.testing.assert_allclose(ours[:2] / ours[2], theirs[:2] / theirs[2], atol=1e-6)


def _edit(root: Path, rel: str, change) -> None:
    path = root / rel
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(
    ("rel", "change", "message"),
    [
        ("calib/camera_intrinsic/000000.json", lambda d: d.update(cam_K=[1, 2]), "no 9-value cam_K"),
        (
            "calib/virtuallidar_to_camera/000000.json",
            lambda d: d.update(rotation=[[2, 0, 0]] * 3),
            "not a rotation",
        ),
        ("label/virtuallidar/000000.json", lambda d: d[0].pop("type"), "object 0 is not a labelled object"),
        (
            "label/virtuallidar/000000.json",
            lambda d: d[0].update(rotation="left"),
            "rotation 'left' is not a number",
        ),
        ("label/virtuallidar/000000.json", lambda d: d[1]["3d_dimensions"].update(l="0"), "size <= 0"),
        ("data_info.json", lambda d: d[0].pop("label_virtuallidar_path"), "no lidar label path"),
    ],
)
def test_bad_files_are_refused_by_name(dair_root: Path, rel: str, change, message: str) -> None:
    _edit(dair_root, rel, change)
    with pytest.raises(RoadsideFormatError, match=message):
        read_dair(dair_root)


def test_not_a_dair_folder(tmp_path: Path) -> None:
    with pytest.raises(RoadsideFormatError, match=r"no data_info\.json"):
        read_dair(tmp_path)
    (tmp_path / "data_info.json").write_text("{}")
    with pytest.raises(RoadsideFormatError, match="not a list of frames"):
        read_dair(tmp_path)


def test_missing_files_are_the_frames_own(dair_root: Path) -> None:
    (dair_root / "image/000000.jpg").unlink()
    (site,) = read_dair(dair_root)
    assert site.frames[0].missing == ("image/000000.jpg",) and not site.frames[0].images
