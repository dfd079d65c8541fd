"""The Rope3D reader on the dataset's published demo frame (issue 50): boxes stood on the dataset's
ground plane project onto the dataset's own 2D boxes; the PNG named .jpg, the 2D-only rows and bad
files handled by name."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from shared.datasets.roadside.model import RoadsideDataset, RoadsideFormatError
from shared.datasets.roadside.rope3d import CAMERA_ID, ground_frame, read_rope3d
from shared.datasets.roadside.site import image_format
from shared.geometry.boxes import box3d_corners, iou2d_matrix
from tests.shared.datasets.roadside.conftest import ROPE3D

# Projected cuboids against the dataset's 2D boxes: the dataset's 2D boxes are its 3D boxes projected
# (to the pixel: the traffic cones agree to 0.1 px); the residual grows with the box (up to 1.9 px on
# the nearest cars' 250-420 px boxes, < 1 % of their size), as it would from the 3D box not standing
# exactly upright on the plane (rounded ry, size and location, 6-10 digits, at 15-100 m).
MAX_EDGE_ERROR_PX = 2.0
MIN_IOU = 0.96


@pytest.fixture(scope="module")
def rope3d() -> RoadsideDataset:
    (data,) = read_rope3d(ROPE3D)
    return data


def test_the_frame_its_camera_and_labels(rope3d: RoadsideDataset) -> None:
    camera = rope3d.sensors[CAMERA_ID]
    assert (camera.width_px, camera.height_px) == (1920, 1080)
    assert camera.K is not None and camera.K[0, 0] == pytest.approx(2763.176803)
    assert camera.T_site_from_sensor[2, 3] == pytest.approx(7.0044, abs=1e-3)  # denorm's d: 7 m up
    (frame,) = rope3d.frames
    assert len(frame.labels) == 48
    boxed = [lab for lab in frame.labels if lab.has_box]
    assert len(boxed) == 44  # 4 rows are 2D boxes with a zero 3D box (labelled in the image only)
    assert sum(lab.label == "car" for lab in boxed) == 15
    image = frame.images[CAMERA_ID]
    assert image.suffix == ".jpg" and image_format(image.read_bytes(), image) == "png"
    bottoms = np.array([lab.box_m[2] - lab.box_m[5] / 2 for lab in boxed])
    # the labels' bottoms lie near the dataset's ground plane (within 0.07 m at the median, 0.44 m at
    # most: a fitted plane under a road that is not one)
    assert np.median(np.abs(bottoms)) < 0.1 and np.abs(bottoms).max() < 0.5


def test_cuboids_project_onto_the_datasets_2d_boxes(rope3d: RoadsideDataset) -> None:
    camera = rope3d.sensors[CAMERA_ID]
    assert camera.K is not None
    T_cam_from_site = np.linalg.inv(camera.T_site_from_sensor)
    errors, ious = [], []
    for label in rope3d.frames[0].labels:
        if not label.has_box:
            continue
        corners = box3d_corners(label.box_m[None])[0]
        cam = corners @ T_cam_from_site[:3, :3].T + T_cam_from_site[:3, 3]
        uv = (camera.K @ cam.T)[:2] / cam[:, 2]
        projected = np.clip([uv[0].min(), uv[1].min(), uv[0].max(), uv[1].max()], 0, [1920, 1080, 1920, 1080])
        given = np.array(label.boxes_px[CAMERA_ID])
        errors.append(np.abs(projected - given).max())
        ious.append(iou2d_matrix(projected[None], given[None])[0, 0])
    assert max(errors) <= MAX_EDGE_ERROR_PX and min(ious) >= MIN_IOU
    assert np.median(errors) < 0.5


def test_the_ground_frame_of_a_plane() -> None:
    """A camera 7 m up looking 30 deg down: its site pose is at (0, 0, 7), optical axis forward-down."""
    pitch = np.radians(30)
    up_in_camera = np.array([0.0, -np.cos(pitch), -np.sin(pitch)])  # camera y is down, z forward
    T = ground_frame(np.array([*up_in_camera, 7.0]))
    np.testing.assert_allclose(T[:3, 3], [0, 0, 7], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [0, 0, 1], [np.cos(pitch), 0, -np.sin(pitch)], atol=1e-12)
    np.testing.assert_allclose(ground_frame(np.array([*-up_in_camera, -7.0])), T)  # either sign


def _copy(tmp: Path) -> Path:
    shutil.copytree(ROPE3D, tmp / "r", ignore=shutil.ignore_patterns("extrinsics", "LICENSE", "*.md"))
    return tmp / "r"


def _edit(root: Path, folder: str, text: str) -> None:
    (path,) = (root / folder).glob("*.txt")
    path.write_text(text)


@pytest.mark.parametrize(
    ("folder", "text", "message"),
    [
        ("calib", "P1: 1 2 3\n", "no P2 line"),
        ("calib", "P2: 1 0 0 0 0 1 0 0 0 0 x 0\n", "not 12 numbers"),
        ("calib", "P2: 1000 0 960 5 0 1000 540 0 0 0 1 0\n", "not K"),
        ("denorm", "0 -1 0\n", "expected 4"),
        ("denorm", "0 0 0 7\n", "zero normal"),
        ("label_2", "car 0 0 0 1 2 3 4 1.5 1.8\n", "10 fields"),
        ("label_2", "car 0 0 0 1 2 3 4 1.5 -1.8 4 0 1 20 0\n", "size <= 0"),
        ("label_2", "car 0 0 0 1 2 3 4 1.5 1.8 4 0 nan 20 0\n", "non-finite"),
    ],
)
def test_bad_files_are_refused_by_name(tmp_path: Path, folder: str, text: str, message: str) -> None:
    root = _copy(tmp_path)
    _edit(root, folder, text)
    with pytest.raises(RoadsideFormatError, match=message):
        read_rope3d(root)


def test_a_folder_that_is_not_rope3d_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RoadsideFormatError, match="not a Rope3D folder"):
        read_rope3d(tmp_path)
    root = _copy(tmp_path)
    (image,) = (root / "image_2").iterdir()
    image.write_bytes(b"not an image")
    with pytest.raises(RoadsideFormatError, match="not an image"):
        read_rope3d(root)
    image.unlink()
    (data,) = read_rope3d(root)
    assert data.frames[0].missing and not data.frames[0].images
