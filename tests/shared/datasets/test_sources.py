"""Datasets the project did not write, read for training (issue 36 item 2): YOLO in both folder
conventions the format allows, KITTI object with and without ImageSets; boxes worked by hand."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shared.datasets.sources import (
    DatasetError,
    DataSource,
    camera_items,
    detect_format,
    lidar_items,
    split_stems,
)

W, H = 200, 100


def image(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (W, H), (10, 20, 30)).save(path)


def write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_yolo_ultralytics_layout_maps_class_names_and_ignores(tmp_path: Path) -> None:
    """`images/train/x.jpg` -> `labels/train/x.txt`; names as a list; truck boxes ignored on request."""
    write(
        tmp_path / "data.yaml", "path: .\ntrain: images/train\nval: images/val\nnames: [person, car, truck]\n"
    )
    image(tmp_path / "images" / "train" / "a.jpg")
    image(tmp_path / "images" / "val" / "b.png")
    write(
        tmp_path / "labels" / "train" / "a.txt", "1 0.5 0.5 0.2 0.4\n0 0.1 0.1 0.1 0.1\n2 0.25 0.5 0.1 0.2\n"
    )
    assert detect_format(tmp_path) == "yolo"
    source = DataSource(ignore_classes=("truck",))
    (item,) = camera_items(tmp_path, "train", source)
    boxes, ignore = item.labels(W, H)
    np.testing.assert_allclose(boxes, [[80, 30, 120, 70]])  # the car; the person dropped
    np.testing.assert_allclose(ignore, [[40, 40, 60, 60]])  # the truck
    (val,) = camera_items(tmp_path, "val", source)
    assert val.stem == "b" and val.labels(W, H)[0].shape == (0, 4)  # no label file: no objects


def test_yolo_roboflow_layout_with_a_mapping_and_no_val_split(tmp_path: Path) -> None:
    """`train/images/x.jpg` -> `train/labels/x.txt`; names as a mapping; no `val`: split here."""
    write(tmp_path / "dataset.yml", "train: train/images\nnames: {0: Car, 1: bus}\n")
    for i in range(10):
        image(tmp_path / "train" / "images" / f"f{i}.jpg")
        write(tmp_path / "train" / "labels" / f"f{i}.txt", "0 0.5 0.5 0.5 0.5\n")
    train = camera_items(tmp_path, "train", DataSource(val_fraction=0.2))
    val = camera_items(tmp_path, "val", DataSource(val_fraction=0.2))
    assert [i.stem for i in val] == ["f4", "f9"] and len(train) == 8
    np.testing.assert_allclose(train[0].labels(W, H)[0], [[50, 25, 150, 75]])


@pytest.mark.parametrize(
    ("yaml_text", "label", "message"),
    [
        ("train: images/train\nnames: [bus]\n", "0 0.5 0.5 0.1 0.1\n", "no class named"),
        ("train: images/train\nnames: [car]\n", "0 0.5 0.5\n", r"a\.txt:1: expected"),
        ("train: images/train\nnames: [car]\n", "0 x 0.5 0.1 0.1\n", r"a\.txt:1: not numbers"),
        ("train: images/train\nnames: [car]\n", "0 0.5 0.5 -0.1 0.1\n", "out of range"),
        ("train: nowhere\nnames: [car]\n", "", "not a folder nor"),
    ],
)
def test_bad_yolo_datasets_name_the_file_and_line(
    tmp_path: Path, yaml_text: str, label: str, message: str
) -> None:
    write(tmp_path / "data.yaml", yaml_text)
    image(tmp_path / "images" / "train" / "a.jpg")
    write(tmp_path / "labels" / "train" / "a.txt", label)
    with pytest.raises(DatasetError, match=message):
        for item in camera_items(tmp_path, "train"):
            item.labels(W, H)


# KITTI: a level camera looking along the velodyne's +x (the standard KITTI axes), 1 m above it.
R_CAM_FROM_VELO = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
T_CAM_FROM_VELO = np.array([0.0, 1.0, 0.0])  # the camera 1 m above the velodyne: y_cam down


def kitti_calib() -> str:
    tr = np.column_stack([R_CAM_FROM_VELO, T_CAM_FROM_VELO])
    p2 = np.array([[100, 0, 100, 0], [0, 100, 50, 0], [0, 0, 1, 0]], float)
    fmt = lambda a: " ".join(f"{v:.6f}" for v in np.ravel(a))  # noqa: E731
    return f"P2: {fmt(p2)}\nR0_rect: {fmt(np.eye(3))}\nTr_velo_to_cam: {fmt(tr)}\n"


def test_kitti_camera_and_lidar_boxes(tmp_path: Path) -> None:
    """A car 10 m ahead, 2 m left, heading along +y of the velodyne (yaw pi/2): rotation_y = -pi;
    its bottom centre in the camera is (-2, 1 + 0.0, 10) with the velodyne's ground at z = 0."""
    base = tmp_path / "training"
    image(base / "image_2" / "000001.png")
    write(base / "calib" / "000001.txt", kitti_calib())
    (base / "velodyne").mkdir(parents=True)
    np.array([[10, 2, 0.5, 0.3]], "<f4").tofile(base / "velodyne" / "000001.bin")
    lines = [
        f"Car 0.00 0 0.0 10 20 60 70 1.5 1.8 4.0 -2.0 1.0 10.0 {-math.pi:.6f}",
        "Van 0.00 0 0.0 100 20 150 70 2.0 2.0 5.0 3.0 1.0 20.0 0.0",
        "DontCare -1 -1 -10 150 30 190 60 -1 -1 -1 -1000 -1000 -1000 -10",
        "Pedestrian 0.00 0 0.0 80 20 90 70 1.7 0.6 0.8 1.0 1.0 8.0 0.0",
    ]
    write(base / "label_2" / "000001.txt", "\n".join(lines) + "\n")
    assert detect_format(tmp_path) == "kitti"
    (item,) = camera_items(tmp_path, "train", DataSource(val_fraction=0.5))  # one frame: all in train
    boxes, ignore = item.labels(W, H)
    np.testing.assert_allclose(boxes, [[10, 20, 60, 70]])
    np.testing.assert_allclose(ignore, [[100, 20, 150, 70], [150, 30, 190, 60]])  # Van, DontCare
    (frame,) = lidar_items(tmp_path, "train", DataSource(val_fraction=0.5))
    # bottom (x, y, z) velo = (10, 2, 0); centre z + h / 2 = 0.75; dx = l = 4, dy = w = 1.8, dz = h = 1.5
    np.testing.assert_allclose(frame.boxes, [[10, 2, 0.75, 4.0, 1.8, 1.5, math.pi / 2]], atol=1e-5)
    np.testing.assert_allclose(frame.ignore[:, :3], [[20, -3, 1.0]], atol=1e-5)
    assert frame.points().shape == (1, 4)


def test_kitti_splits_from_image_sets_and_broken_files(tmp_path: Path) -> None:
    base = tmp_path / "training"
    for stem in ("000001", "000002"):
        image(base / "image_2" / f"{stem}.png")
        write(base / "label_2" / f"{stem}.txt", "Car 0 0 0 1 1 5 5 1 1 1 0 1 5 0\n")
    write(tmp_path / "ImageSets" / "val.txt", "000002\n")
    assert [i.stem for i in camera_items(tmp_path, "val")] == ["000002"]
    write(base / "label_2" / "000002.txt", "Car 0 0 0\n")
    with pytest.raises(DatasetError, match=r"000002\.txt"):
        camera_items(tmp_path, "val")[0].labels(W, H)
    with pytest.raises(DatasetError, match=r"calib"):
        lidar_items(tmp_path, "val")[0]


def test_split_stems_is_even_and_deterministic() -> None:
    stems = [f"{i:03d}" for i in range(10)]
    assert split_stems(stems, "val", 0.25) == ["003", "007"]
    assert len(split_stems(stems, "train", 0.25)) == 8 and split_stems(stems, "test", 0.25) == []
    with pytest.raises(DatasetError):
        split_stems(stems, "dev", 0.25)


def test_an_unknown_folder_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="neither"):
        detect_format(tmp_path)
