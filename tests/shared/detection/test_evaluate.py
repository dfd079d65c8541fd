"""Detector evaluation on a tiny generated dataset: a perfect oracle scores AP 1, a noisy one less;
the registry builds detectors by name and refuses unknown names."""

from __future__ import annotations

import pytest

from shared.datasets.layout import DatasetLayout
from shared.detection import evaluate as ev
from shared.detection.lidar.cluster import ClusterLidarConfig
from shared.detection.oracle import (
    OracleCameraConfig,
    OracleCameraDetector,
    OracleLidarConfig,
    OracleLidarDetector,
)
from shared.detection.registry import camera_detector, lidar_detector
from studies.dataset.config import DatasetSettings, SplitSeeds
from studies.dataset.generate import dataset_scene, generate

TABLE_CLUSTER = ClusterLidarConfig(vehicle_size_m=(0.33, 0.22, 0.21))


@pytest.fixture(scope="module")
def layout(tmp_path_factory: pytest.TempPathFactory) -> DatasetLayout:
    root = tmp_path_factory.mktemp("ds")
    cfg = DatasetSettings(
        seeds=SplitSeeds(train=[], val=[], test=[7]), warmup_s=3.0, duration_s=2.0, camera_sample_hz=1.0
    )
    generate(cfg, root, progress=False)
    return DatasetLayout(root)


def test_perfect_oracles_score_one(layout: DatasetLayout) -> None:
    cam = ev.evaluate_camera(OracleCameraDetector(), layout, "test")
    assert cam["images"] == 26 and cam["gt_boxes"] > 0
    assert cam["ap50"] == pytest.approx(1.0) and cam["ap50_95"] == pytest.approx(1.0)
    lid = ev.evaluate_lidar(OracleLidarDetector(), layout, "test")
    assert lid["frames"] == 4 and lid["gt_boxes"] > 0
    assert lid["bev_ap70"] == pytest.approx(1.0) and lid["ap3d_70"] == pytest.approx(1.0)


def test_noisy_oracles_score_less(layout: DatasetLayout) -> None:
    noisy_cam = OracleCameraDetector(OracleCameraConfig(pixel_noise_px=6.0), seed=1)
    assert ev.evaluate_camera(noisy_cam, layout, "test")["ap50_95"] < 0.9
    noisy_lidar = OracleLidarDetector(OracleLidarConfig(position_noise_m=0.05), seed=1)
    assert ev.evaluate_lidar(noisy_lidar, layout, "test")["bev_ap70"] < 0.9


def test_latency_reports_percentiles(layout: DatasetLayout) -> None:
    samples = list(ev.lidar_samples(layout, "test"))
    lat = ev.lidar_latency(lidar_detector("cluster", cluster=TABLE_CLUSTER), samples)
    assert lat["n"] == len(samples) and 0 < lat["p50"] <= lat["p95"]


def test_registry_builds_by_name_and_refuses_unknown_names() -> None:
    assert lidar_detector("pointpillars").name == "pointpillars"
    assert lidar_detector("cluster", cluster=TABLE_CLUSTER).name == "cluster"
    with pytest.raises(ValueError, match="cluster detector needs"):
        lidar_detector("cluster")  # no site settings: no vehicle prior
    assert camera_detector("oracle").name == "oracle-camera"
    with pytest.raises(ValueError, match="unknown lidar detector"):
        lidar_detector("yolo")
    with pytest.raises(ValueError, match="unknown camera detector"):
        camera_detector("pointpillars")


def test_lidar_ap_can_sample_as_the_kitti_devkit(layout: DatasetLayout) -> None:
    """The same perfect detections: 1 interpolated at recall 1/40..1; the devkit's way one threshold per
    true positive and a step of 1/40 each, so with few boxes the top points are never reached."""
    r40 = ev.evaluate_lidar(OracleLidarDetector(), layout, "test")
    devkit = ev.evaluate_lidar(OracleLidarDetector(), layout, "test", recall_sampling="devkit")
    assert devkit["recall_sampling"] == "devkit" and r40["recall_sampling"] == "r40"
    gt = devkit["gt_boxes"]
    assert devkit["bev_ap70"] == pytest.approx(min(gt - 1, 40) / 40)  # thresholds fill points 0..gt-1
    assert r40["bev_ap70"] == pytest.approx(1.0)


def test_a_generated_dataset_knows_its_scene(layout: DatasetLayout) -> None:
    assert dataset_scene(layout).scene_id == "sand_table"
    cluster = ClusterLidarConfig.for_scene(dataset_scene(layout).spec)
    assert cluster.vehicle_size_m == (0.33, 0.22, 0.21) and cluster.max_range_m == 6.0  # the table: scale 1
