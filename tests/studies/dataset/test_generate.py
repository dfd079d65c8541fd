"""Dataset generation: labels agree with the sensor data, splits follow seeds, runs resume and repeat."""

from __future__ import annotations

import json

import numpy as np
import pytest

from shared.datasets import kitti, openpcdet, voc, yolo
from shared.datasets.layout import MIN_LIDAR_POINTS, SPLITS, DatasetLayout
from shared.geometry.boxes import box3d_corners
from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from studies.dataset.config import DatasetSettings, SplitSeeds
from studies.dataset.generate import generate, marker_path

BOX_TOLERANCE_M = 0.03  # lidar noise + the body parts sit inside the box


def settings() -> DatasetSettings:
    return DatasetSettings(
        seeds=SplitSeeds(train=[1], val=[101], test=[201]),
        warmup_s=2.0,
        duration_s=1.0,
        camera_sample_hz=1.0,
        lidar_sample_hz=1.0,
    )


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> DatasetLayout:
    root = tmp_path_factory.mktemp("ds")
    generate(settings(), root, progress=False)
    return DatasetLayout(root)


def test_every_split_has_images_labels_and_lidar_frames(dataset: DatasetLayout) -> None:
    manifest = json.loads(dataset.manifest.read_text())
    for split in SPLITS:
        stems = dataset.camera_stems(split)
        assert len(stems) == 13 == manifest["splits"][split]["camera_images"]  # 13 cameras x 1 sample
        assert len(dataset.lidar_stems(split)) == 2  # 2 agents with lidars x 1 sample
        seed = manifest["splits"][split]["seeds"][0]
        assert all(s.startswith(f"s{seed:04d}_") for s in stems + dataset.lidar_stems(split))
    assert sum(manifest["splits"][s]["camera_labelled_vehicles"] for s in SPLITS) > 0


def test_yolo_voc_and_meta_boxes_agree(dataset: DatasetLayout) -> None:
    model = Scene.load(DEFAULT_SCENE).sensors_of(kind="camera")[0].camera
    assert model is not None
    for split in SPLITS:
        for stem in dataset.camera_stems(split):
            boxes, _ = yolo.read_yolo(dataset.yolo_label(split, stem), model.width_px, model.height_px)
            meta = json.loads(dataset.camera_meta(split, stem).read_text())
            assert np.allclose(boxes, np.asarray(meta["boxes"]).reshape(-1, 4), atol=1e-6)
            assert np.allclose(voc.read_voc(dataset.voc_label(split, stem)).boxes_px, boxes, atol=1e-6)
            assert dataset.camera_image(split, stem).read_bytes()[:2] == b"\xff\xd8"  # JPEG


def test_lidar_labels_enclose_their_points_and_match_kitti(dataset: DatasetLayout) -> None:
    checked = 0
    for split in SPLITS:
        for stem in dataset.lidar_stems(split):
            points = openpcdet.read_points(dataset.pcdet_points(stem))
            boxes, names = openpcdet.read_labels(dataset.pcdet_label(stem))
            assert set(names) <= {"Car"}
            assert np.array_equal(kitti.read_velodyne(dataset.kitti_velodyne(stem)), points)
            calib = kitti.KittiCalib.from_text(dataset.kitti_calib(stem).read_text())
            back = kitti.kitti_to_boxes(kitti.read_label(dataset.kitti_label(stem)), calib)
            assert np.allclose(back[:, :6], boxes[:, :6], atol=1e-6)
            for box in boxes:
                if abs(box[2] - 0.105) > 0.01:
                    continue  # pitched on a ramp: the upright label box is looser there
                local = points[:, :3] - box[:3]
                c, s = np.cos(-box[6]), np.sin(-box[6])
                x, y = c * local[:, 0] - s * local[:, 1], s * local[:, 0] + c * local[:, 1]
                half = box[3:6] / 2 + BOX_TOLERANCE_M
                inside = (np.abs(x) <= half[0]) & (np.abs(y) <= half[1]) & (np.abs(local[:, 2]) <= half[2])
                assert inside.sum() >= MIN_LIDAR_POINTS
                checked += 1
            assert box3d_corners(boxes).shape == (len(boxes), 8, 3)
    assert checked > 0


def test_rerun_skips_done_seeds_and_redoes_a_missing_one_identically(dataset: DatasetLayout) -> None:
    stem = dataset.camera_stems("val")[0]
    before = dataset.camera_image("val", stem).read_bytes()
    label_before = dataset.pcdet_label(dataset.lidar_stems("val")[0]).read_text()
    marker_path(dataset, "val", 101).unlink()
    dataset.camera_image("val", stem).unlink()
    mtime_train = dataset.camera_image("train", dataset.camera_stems("train")[0]).stat().st_mtime_ns
    generate(settings(), dataset.root, progress=False)
    assert dataset.camera_image("val", stem).read_bytes() == before
    assert dataset.pcdet_label(dataset.lidar_stems("val")[0]).read_text() == label_before
    assert dataset.camera_image("train", dataset.camera_stems("train")[0]).stat().st_mtime_ns == mtime_train


def test_split_seeds_must_be_disjoint() -> None:
    with pytest.raises(ValueError, match="disjoint"):
        SplitSeeds(train=[1, 2], val=[2], test=[3])


def test_seed_conditions_are_reproducible_and_vary() -> None:
    from studies.dataset.conditions import SeedConditions

    variation = settings().variation
    assert SeedConditions.draw(variation, 5) == SeedConditions.draw(variation, 5)
    drawn = [SeedConditions.draw(variation, s) for s in range(10)]
    assert len({json.dumps({**c.as_dict(), "seed": 0}) for c in drawn}) == 10  # not just the seed differs
    assert {c.vehicles for c in drawn} <= set(variation.vehicles)
    assert {c.camera_noise_std for c in drawn} <= set(variation.camera_noise_std)


def test_seed_conditions_reach_the_lockstep_sensors_and_the_cars() -> None:
    from sim.config import SimSettings
    from sim.sensors.rig import CameraSensor
    from studies.dataset.conditions import COLOUR_MAX, COLOUR_MIN, SeedConditions

    conditions = SeedConditions.draw(settings().variation, 7)
    scene = Scene.load(DEFAULT_SCENE)
    with conditions.lockstep(scene, SimSettings(seed=7), sensor_ids=["cam_11"]) as sim:
        camera = sim.rig.sensors["cam_11"]
        assert isinstance(camera, CameraSensor)
        assert camera.noise_std == conditions.camera_noise_std
        assert camera.renderer.lighting == conditions.lighting
        colours = [v.rgba[:3] for v in sim.traffic.vehicles]
    assert all(COLOUR_MIN <= c <= COLOUR_MAX for rgb in colours for c in rgb)
    assert len(set(colours)) == len(colours)  # every car its own colour
