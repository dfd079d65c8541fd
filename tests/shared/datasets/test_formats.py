"""Dataset formats: export -> parse returns the boxes within 1e-6; malformed files are refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.datasets import kitti, openpcdet, voc, yolo
from shared.geometry.boxes import box3d_corners
from shared.geometry.camera import project_points
from shared.geometry.transforms import wrap_angle
from shared.scene.scene import Scene

TOL = 1e-6
W, H = 640, 480


@pytest.fixture
def boxes_px() -> np.ndarray:
    rng = np.random.default_rng(0)
    x0 = rng.uniform(0, 500, 20)
    y0 = rng.uniform(0, 400, 20)
    return np.column_stack([x0, y0, x0 + rng.uniform(1, 140, 20), y0 + rng.uniform(1, 80, 20)])


@pytest.fixture
def boxes3d() -> np.ndarray:
    rng = np.random.default_rng(1)
    n = 25
    return np.column_stack(
        [
            rng.uniform(-3, 3, n),
            rng.uniform(-3, 3, n),
            rng.uniform(0.1, 0.5, n),
            np.full(n, 0.33),
            np.full(n, 0.22),
            np.full(n, 0.21),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )


def test_yolo_round_trip(tmp_path: Path, boxes_px: np.ndarray) -> None:
    path = tmp_path / "labels" / "a.txt"
    yolo.write_yolo(path, boxes_px, W, H)
    back, ids = yolo.read_yolo(path, W, H)
    assert np.abs(back - boxes_px).max() < TOL
    assert (ids == 0).all()
    first = path.read_text().splitlines()[0].split()
    assert first[0] == "0" and all(0 <= float(v) <= 1 for v in first[1:])


def test_yolo_refuses_a_malformed_line() -> None:
    with pytest.raises(ValueError, match="line 2"):
        yolo.parse_yolo("0 0.5 0.5 0.1 0.1\n0 0.5 0.5\n", W, H)


def test_yolo_data_yaml_names_the_splits(tmp_path: Path) -> None:
    import yaml

    yolo.write_data_yaml(tmp_path / "data.yaml", ["car"], ["train", "val", "test"])
    data = yaml.safe_load((tmp_path / "data.yaml").read_text())
    assert data["train"] == "images/train" and data["names"] == {0: "car"}


def test_voc_round_trip_and_one_based_corners(tmp_path: Path, boxes_px: np.ndarray) -> None:
    difficult = [i % 3 == 0 for i in range(len(boxes_px))]
    ann = voc.voc_annotation("a.jpg", W, H, boxes_px, "car", difficult)
    path = tmp_path / "a.xml"
    voc.write_voc(path, ann)
    back = voc.read_voc(path)
    assert np.abs(back.boxes_px - boxes_px).max() < TOL
    assert back.difficult == difficult and back.names == ["car"] * len(boxes_px)
    assert (back.width_px, back.height_px, back.filename) == (W, H, "a.jpg")
    one = voc.to_xml(voc.voc_annotation("b.jpg", W, H, np.array([[0, 0, 10, 20]]), "car", [False]))
    assert "<xmin>1</xmin>" in one and "<xmax>10</xmax>" in one and "<truncated>1</truncated>" in one


def test_voc_refuses_a_box_without_corners() -> None:
    text = "<annotation><filename>a</filename><size><width>1</width><height>1</height></size>"
    text += "<object><name>car</name><bndbox><xmin>1</xmin></bndbox></object></annotation>"
    with pytest.raises(ValueError, match="ymin"):
        voc.from_xml(text)


def test_openpcdet_round_trip(tmp_path: Path, boxes3d: np.ndarray) -> None:
    openpcdet.write_labels(tmp_path / "l.txt", boxes3d, ["Car"] * len(boxes3d))
    back, names = openpcdet.read_labels(tmp_path / "l.txt")
    assert np.abs(back - boxes3d).max() < TOL and names == ["Car"] * len(boxes3d)
    points = np.random.default_rng(2).normal(size=(100, 4)).astype(np.float32)
    openpcdet.write_points(tmp_path / "p.npy", points)
    assert np.array_equal(openpcdet.read_points(tmp_path / "p.npy"), points)
    with pytest.raises(ValueError, match="expected 8 fields"):
        openpcdet.parse_labels("1 2 3 Car\n")


def kitti_calib(scene: Scene, camera: str, origin: np.ndarray) -> tuple[kitti.KittiCalib, np.ndarray]:
    T_world_from_agent = np.eye(4)
    T_world_from_agent[:3, 3] = origin
    T_cam_from_agent = np.asarray(scene.T_optical_from_world(camera)) @ T_world_from_agent
    K = np.asarray(scene.K(camera))
    return kitti.KittiCalib.from_camera(K, T_cam_from_agent), K


def test_kitti_round_trip_through_files(tmp_path: Path, scene: Scene, boxes3d: np.ndarray) -> None:
    calib, K = kitti_calib(scene, "cam_11", np.array([0.0, 1.5, 0.0]))
    objects = kitti.boxes_to_kitti(boxes3d, calib, K, (W, H), np.full(len(boxes3d), 30), "Car")
    (tmp_path / "calib.txt").write_text(calib.to_text())
    kitti.write_label(tmp_path / "label.txt", objects)
    calib_back = kitti.KittiCalib.from_text((tmp_path / "calib.txt").read_text())
    back = kitti.kitti_to_boxes(kitti.read_label(tmp_path / "label.txt"), calib_back)
    assert np.abs(back[:, :6] - boxes3d[:, :6]).max() < TOL
    assert np.abs(wrap_angle(back[:, 6] - boxes3d[:, 6])).max() < TOL


def test_kitti_calibration_projects_like_the_camera(scene: Scene, boxes3d: np.ndarray) -> None:
    origin = np.array([0.0, 1.5, 0.0])
    calib, K = kitti_calib(scene, "cam_11", origin)
    corners = box3d_corners(boxes3d).reshape(-1, 3)
    uv_cam, depth = project_points(corners + origin, scene.T_optical_from_world("cam_11"), K)
    homo = np.column_stack([corners, np.ones(len(corners))])
    rect = calib.R0_rect @ (calib.Tr_velo_to_cam @ homo.T)
    img = calib.P2 @ np.vstack([rect, np.ones(rect.shape[1])])
    front = depth > 0.1
    uv_kitti = (img[:2] / img[2]).T
    assert np.abs(uv_kitti[front] - uv_cam[front]).max() < 1e-6
    # rectified y is the gravity vertical: a box's bottom centre sits dz/2 below its centre in rect y
    objects = kitti.boxes_to_kitti(boxes3d, calib, K, (W, H), np.full(len(boxes3d), 30), "Car")
    centres_rect = calib.velo_to_rect(boxes3d[:, :3])
    for o, c, b in zip(objects, centres_rect, boxes3d, strict=True):
        assert o.location[1] - c[1] == pytest.approx(b[5] / 2)
        assert o.dimensions == pytest.approx((b[5], b[4], b[3]))


def test_kitti_level_camera_matches_the_standard_heading_convention() -> None:
    # Standard KITTI axes: camera at the lidar origin, looking along lidar +x, level.
    T_cam_from_velo = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], float)
    calib = kitti.KittiCalib.from_camera(np.diag([500.0, 500.0, 1.0]), T_cam_from_velo)
    assert np.allclose(calib.R0_rect, np.eye(3))
    boxes = np.array([[5.0, 1.0, 0.1, 0.33, 0.22, 0.21, yaw] for yaw in (0.0, 0.7, -2.0)])
    objects = kitti.boxes_to_kitti(boxes, calib, np.diag([500.0, 500.0, 1.0]), (W, H), np.full(3, 30), "Car")
    for o, b in zip(objects, boxes, strict=True):  # OpenPCDet: heading = -(ry + pi/2)
        assert float(wrap_angle(-(o.rotation_y + np.pi / 2) - b[6])) == pytest.approx(0.0, abs=1e-9)


def test_kitti_refuses_short_lines_and_missing_calib() -> None:
    with pytest.raises(ValueError, match="15 fields"):
        kitti.KittiObject.from_line("Car 0 0 0 1 2 3 4")
    with pytest.raises(ValueError, match="R0_rect"):
        kitti.KittiCalib.from_text("P2: " + " ".join(["0"] * 12) + "\n")


def test_kitti_velodyne_round_trip(tmp_path: Path) -> None:
    points = np.random.default_rng(3).normal(size=(50, 4)).astype(np.float32)
    kitti.write_velodyne(tmp_path / "v.bin", points)
    assert np.array_equal(kitti.read_velodyne(tmp_path / "v.bin"), points)
