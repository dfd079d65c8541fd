"""The OpenLABEL reader on two real TUMTraf A9 frames (issue 50): the labels' own point counts
reproduced from the real clouds, the cameras' transforms against the dataset's calibration files, and
malformed files refused by name."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from shared.datasets.roadside.model import RoadsideDataset, RoadsideFormatError
from shared.datasets.roadside.openlabel import read_openlabel
from shared.datasets.roadside.pcd import read_pcd
from shared.geometry.transforms import invert_transform
from tests.shared.datasets.roadside.conftest import TUMTRAF

LIDAR = "s110_lidar_ouster_south"
# Frame 2's labels whose num_points this frame's cloud does not give (object id prefix: ours, theirs).
# Counted in the box as labelled, with any margin up to 0.5 m none of them comes to the label's figure
# for the two boxes that hold no point at all (a car at 100 m, a pedestrian at 62 m): the counts were
# not taken on this cloud as it is (the dataset labels on clouds registered from both S110 lidars; the
# north one is not here), so they are the dataset's, not a reading error. Frame 1's 15 all agree.
FRAME2_DISAGREE = {"4ab00d2d": (0, 6), "36d9e637": (0, 7), "9850f3a2": (3, 6), "fe2bc0c4": (76, 89),
                   "15b30a46": (29, 28), "b7eee858": (118, 121)}  # fmt: skip


def test_the_site_its_sensors_and_frames(tumtraf: RoadsideDataset) -> None:
    assert tumtraf.site_frame == "s110_base"
    assert {s.name: s.kind for s in tumtraf.sensors.values()} == {
        LIDAR: "lidar",
        "s110_camera_basler_south1_8mm": "camera",
        "s110_camera_basler_south2_8mm": "camera",
    }
    first, second = tumtraf.frames
    assert (first.stamp_ns, second.stamp_ns) == (1646667310_053239541, 1646667315_454719936)
    assert first.sensor_stamps_ns["s110_camera_basler_south1_8mm"] == 1646667310_044372291  # from the name
    assert (len(first.labels), len(second.labels)) == (15, 17)
    assert first.missing == () and second.missing == (
        "1646667315_484371032_s110_camera_basler_south1_8mm.jpg",
    )
    lidar = tumtraf.sensors[LIDAR]
    assert lidar.T_site_from_sensor[2, 3] == pytest.approx(7.48077521)  # pose_wrt_parent, lidar -> base
    cars = [lab for lab in first.labels if lab.label == "car"]
    assert len(cars) == 11 and {lab.category for lab in first.labels} == {"CAR", "PEDESTRIAN", "TRUCK"}


def test_points_in_each_cuboid_are_the_datasets_num_points(tumtraf: RoadsideDataset) -> None:
    lidar = tumtraf.sensors[LIDAR]
    disagree = {}
    for frame in tumtraf.frames:
        xyz = read_pcd(frame.clouds[lidar.id]).xyz_m
        site = xyz @ lidar.T_site_from_sensor[:3, :3].T + lidar.T_site_from_sensor[:3, 3]
        for label in frame.labels:
            assert label.num_points is not None
            got = int(label.contains(site).sum())
            if got != label.num_points:
                disagree[(frame.index, label.object_id[:8])] = (got, label.num_points)
    assert disagree == {(1, k): v for k, v in FRAME2_DISAGREE.items()}


def _calibration_projection(camera: str) -> np.ndarray:
    data = json.loads((TUMTRAF / "calib" / f"{camera}.json").read_text())
    return np.asarray(data["projection_from_s110_lidar_ouster_south"], np.float64)


@pytest.mark.parametrize(
    ("camera", "within_px"),
    # south1: the labels' transform is the calibration file's, to rounding. south2: the calibration
    # file is a later calibration of that camera (its projection differs from the labels' transform by
    # 5 px at the median, 9 px at most at these labels), so the labels' own is read and checked to it.
    [("s110_camera_basler_south1_8mm", 0.5), ("s110_camera_basler_south2_8mm", 9.0)],
)
def test_cameras_project_as_the_datasets_calibration(
    tumtraf: RoadsideDataset, camera: str, within_px: float
) -> None:
    """Label centres projected through the reader's camera (K and T_cam_from_lidar) land where the
    dataset's own projection matrix puts them; read the standard's way round they do not."""
    lidar, cam = tumtraf.sensors[LIDAR], tumtraf.sensors[camera]
    P_cal = _calibration_projection(camera)
    T_cam_from_lidar = invert_transform(cam.T_site_from_sensor) @ lidar.T_site_from_sensor
    centres = np.array([lab.box_m[:3] for f in tumtraf.frames for lab in f.labels])
    X = np.column_stack([centres, np.ones(len(centres))]) @ invert_transform(lidar.T_site_from_sensor).T
    ours, theirs = (cam.K @ T_cam_from_lidar[:3]) @ X.T, P_cal @ X.T
    seen = (ours[2] > 0) & (theirs[2] > 0)
    uv, uv_cal = ours[:2, seen] / ours[2, seen], theirs[:2, seen] / theirs[2, seen]
    in_image = (uv_cal[0] >= 0) & (uv_cal[0] < 1920) & (uv_cal[1] >= 0) & (uv_cal[1] < 1200)
    assert in_image.sum() >= 10
    assert np.linalg.norm(uv - uv_cal, axis=0)[in_image].max() <= within_px
    standard = read_openlabel(TUMTRAF, camera_pose="camera_in_parent").sensors[camera]
    T_std = invert_transform(standard.T_site_from_sensor) @ lidar.T_site_from_sensor
    wrong = (standard.K @ T_std[:3]) @ X.T
    far = np.linalg.norm(wrong[:2, seen] / wrong[2, seen] - uv_cal, axis=0)[in_image]
    assert far.min() > 100


def _copy_with(tmp: Path, change) -> Path:
    """The first TUMTraf frame (label, cloud) in a new folder, its label JSON changed by `change`."""
    src = sorted((TUMTRAF / "labels_point_clouds").rglob("*.json"))[0]
    doc = json.loads(src.read_text())
    change(doc["openlabel"])
    (tmp / src.name).write_text(json.dumps(doc))
    cloud = sorted((TUMTRAF / "point_clouds").rglob("*.pcd"))[0]
    (tmp / cloud.name).symlink_to(cloud)
    return tmp


def _first_object(doc: dict) -> dict:
    frame = next(iter(doc["frames"].values()))
    return next(iter(frame["objects"].values()))["object_data"]


def test_names_as_the_world_writes_them(tmp_path: Path) -> None:
    """Capitals and other characters in sensor names become scene ids; a flat folder reads too."""

    def rename(doc: dict) -> None:
        cs = doc["coordinate_systems"]
        cs["S110 Lidar_Ouster_South"] = cs.pop(LIDAR)
        cs["s110_base"]["children"] = ["S110 Lidar_Ouster_South"]
        for cam in ("s110_camera_basler_south1_8mm", "s110_camera_basler_south2_8mm"):
            cs[cam]["parent"] = "S110 Lidar_Ouster_South"
        props = next(iter(doc["frames"].values()))["frame_properties"]
        props["point_cloud_file_name"] = "x_S110 Lidar_Ouster_South.pcd"

    root = _copy_with(tmp_path, rename)
    (root / "x_S110 Lidar_Ouster_South.pcd").symlink_to(sorted((TUMTRAF / "point_clouds").rglob("*.pcd"))[0])
    data = read_openlabel(root)
    assert "s110_lidar_ouster_south" in data.sensors
    assert data.frames[0].clouds["s110_lidar_ouster_south"].name == "x_S110 Lidar_Ouster_South.pcd"
    assert set(data.frames[0].missing) == {p.name for p in (TUMTRAF / "images").rglob("*10_0*.jpg")}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: _first_object(d)["cuboid"].update(val=[1, 2, 3]), "3 values, not 9 or 10"),
        (lambda d: _first_object(d)["cuboid"].update(val=[0] * 6 + [1, 4, -1, 1.5]), "size <= 0"),
        (
            lambda d: _first_object(d)["cuboid"].update(val=[0] * 7 + [4, 2, 1.5]),
            "zero or unbounded quaternion",
        ),
        (lambda d: _first_object(d)["cuboid"].update(val="12"), "not a list of numbers"),
        (lambda d: _first_object(d)["cuboid"].update(val=[1, "x"] + [0] * 8), "not a list of numbers"),
        (lambda d: _first_object(d).pop("type"), "has no type"),
        (lambda d: d["coordinate_systems"][LIDAR].update(pose_wrt_parent={"euler": 1}), "neither matrix4x4"),
        (
            lambda d: d["coordinate_systems"][LIDAR].update(pose_wrt_parent={"matrix4x4": [2] * 16}),
            "not a rigid",
        ),
        (
            lambda d: d["streams"]["s110_camera_basler_south1_8mm"].update(stream_properties={}),
            "no intrinsics",
        ),
        (
            lambda d: next(iter(d["frames"].values()))["frame_properties"].pop("timestamp"),
            "no numeric timestamp",
        ),
    ],
)
def test_malformed_label_files_are_refused_by_name(tmp_path: Path, change, message: str) -> None:
    root = _copy_with(tmp_path, change)
    with pytest.raises(RoadsideFormatError, match=message):
        read_openlabel(root)


def test_a_file_that_is_not_openlabel_is_refused(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_text('{"labels": []}')
    with pytest.raises(RoadsideFormatError, match="not an OpenLABEL file"):
        read_openlabel(tmp_path)
    with pytest.raises(RoadsideFormatError, match="no OpenLABEL"):
        read_openlabel(tmp_path / "empty")


def test_the_standards_layout_reads_as_tumtrafs(tmp_path: Path, tumtraf: RoadsideDataset) -> None:
    """ASAM OpenLABEL keeps an object's type in the file's top-level `objects` and a frame's cuboids as
    a list, each naming its coordinate system (as the specification's own cuboid example does): the
    first TUMTraf frame rewritten so reads the same labels; a cuboid in the site frame too."""
    lidar_pose = tumtraf.sensors[LIDAR].T_site_from_sensor

    def standard(doc: dict) -> None:
        frame = next(iter(doc["frames"].values()))
        doc["objects"] = {}
        for n, (uid, obj) in enumerate(frame["objects"].items()):
            data = obj["object_data"]
            doc["objects"][uid] = {"name": data.pop("name"), "type": data.pop("type")}
            cuboid = {**data["cuboid"], "coordinate_system": LIDAR}
            if n == 0:  # this one in the site frame: the same box, expressed there
                box = np.eye(4)
                box[:3, :3] = Rotation.from_quat(cuboid["val"][3:7]).as_matrix()
                box[:3, 3] = cuboid["val"][:3]
                site = lidar_pose @ box
                quat = Rotation.from_matrix(site[:3, :3]).as_quat()
                cuboid = {
                    **cuboid,
                    "coordinate_system": "s110_base",
                    "val": [*site[:3, 3], *quat, *cuboid["val"][7:]],
                }
            data["cuboid"] = [cuboid]

    root = _copy_with(tmp_path, standard)
    got = read_openlabel(root).frames[0].labels
    want = tumtraf.frames[0].labels
    assert [lab.category for lab in got] == [lab.category for lab in want]
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a.T_site_from_box, b.T_site_from_box, atol=1e-9)

    def elsewhere(doc: dict) -> None:
        _first_object(doc)["cuboid"]["coordinate_system"] = "s110_camera_basler_south1_8mm"

    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(RoadsideFormatError, match="read are the lidar's and the site's"):
        read_openlabel(_copy_with(other, elsewhere))


def test_frames_a_frame_period_apart_are_a_sequence(tmp_path: Path, tumtraf: RoadsideDataset) -> None:
    """The vendored frames, 5.4 s apart, are independent samples; the same two frames restamped 200 ms
    apart (a dropped frame between them, as in TUMTraf's sequences) are one sequence. A frame's instant
    is its cloud's name (TUMTraf's `<s>_<ns>_<lidar>.pcd`), else the label's timestamp."""
    assert not tumtraf.sequence
    labels = sorted((TUMTRAF / "labels_point_clouds").rglob("*.json"))
    for k, src in enumerate(labels):
        doc = json.loads(src.read_text())
        (frame,) = doc["openlabel"]["frames"].values()
        props = frame["frame_properties"]
        cloud = next((TUMTRAF / "point_clouds").rglob(props["point_cloud_file_name"]))
        props["point_cloud_file_name"] = f"1646667310_{253239541 + k * 200_000_000}_{LIDAR}.pcd"
        (tmp_path / props["point_cloud_file_name"]).symlink_to(cloud)
        (tmp_path / src.name).write_text(json.dumps(doc))
    site = read_openlabel(tmp_path)
    assert np.diff([f.stamp_ns for f in site.frames]).tolist() == [200_000_000] and site.sequence
