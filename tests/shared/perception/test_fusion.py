"""Known answers for radar-camera (Algorithm 1), lidar-camera (Algorithm 2 + merge), camera-only."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry.transforms import matrix_from_xyz_rpy
from shared.paths import DEFAULT_SCENE
from shared.perception import camera_only, lidar_camera, radar_camera
from shared.perception.radar_camera import RadarTargets, RoiSizeConfig
from shared.perception.views import CameraView, RoadSurface
from shared.scene.scene import Scene

CAR = (0.33, 0.22, 0.21)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


@pytest.fixture(scope="module")
def cam(scene: Scene) -> CameraView:
    return CameraView.from_scene(scene, "cam_11")


def car(x: float, y: float, yaw: float, z: float = CAR[2] / 2) -> np.ndarray:
    return np.array([x, y, z, *CAR, yaw])


def targets(r: list[float], az: list[float]) -> RadarTargets:
    n = len(r)
    return RadarTargets(np.array(r), np.array(az), np.zeros(n), np.zeros(n), np.zeros(n))


# --- Algorithm 1 -----------------------------------------------------------------------------------


def test_radar_polar_to_world_uses_the_full_pose() -> None:
    T = matrix_from_xyz_rpy([1.0, 2.0, 0.3], [0.0, 0.0, np.pi / 2])  # looking along +y
    world = radar_camera.targets_to_world(targets([2.0, 1.0], [0.0, np.pi / 2]), T)
    np.testing.assert_allclose(world, [[1.0, 4.0, 0.3], [0.0, 2.0, 0.3]], atol=1e-12)


def test_roi_size_follows_alpha_over_d_plus_beta() -> None:
    cfg = RoiSizeConfig(width_factor=1.0, beta_width_px=4, height_factor=2.0, beta_height_px=2)
    alpha = cfg.alpha_px_m(200.0, (0.5, 0.2, 0.125))  # 1 x 200 x 0.5 = 100, 2 x 200 x 0.125 = 50 px m
    assert alpha == pytest.approx((100.0, 50.0))
    rois = radar_camera.roi_boxes(np.array([[320.0, 240.0], [10.0, 10.0]]), np.array([2.0, -1.0]), cfg, alpha)
    np.testing.assert_allclose(rois[0], [320 - 27, 240 - 13.5, 320 + 27, 240 + 13.5])
    assert np.isnan(rois[1]).all()  # behind the camera


def test_the_roi_of_the_table_camera_keeps_its_tuned_size() -> None:
    # 130 and 98 px m were tuned at fx 353.35 px for the 0.33 x 0.22 x 0.21 m car; the factors keep them.
    width, height = RoiSizeConfig().alpha_px_m(353.35, (0.33, 0.22, 0.21))
    assert width == pytest.approx(130.0, abs=0.05) and height == pytest.approx(98.0, abs=0.05)


def test_hungarian_on_iou_keeps_pairs_above_threshold() -> None:
    rois = np.array([[0, 0, 10, 10], [100, 100, 110, 110], [50, 50, 60, 60], [np.nan] * 4], float)
    boxes = np.array([[101, 100, 111, 110], [0, 0, 10, 11], [55, 50, 65, 60]], float)
    m = radar_camera.match_rois(rois, boxes, min_iou=0.6)
    pairs = sorted(zip(m.radar_index.tolist(), m.camera_index.tolist(), strict=True))
    assert pairs == [(0, 1), (1, 0)]  # roi 2 overlaps box 2 by IoU 1/3 < 0.6: dropped
    np.testing.assert_allclose(sorted(m.iou), sorted([100 / 110, 90 / 110]))


def test_roi_assignment_gates_before_maximising() -> None:
    # ROI 0 fits box 0 (IoU 0.69); the crossed pairs are below 0.6 each but sum to more (0.27 + 0.5).
    rois = np.array([[4, 0, 15, 10], [10, 0, 20, 10]], float)
    boxes = np.array([[6, 0, 17, 10], [0, 0, 8, 10]], float)
    m = radar_camera.match_rois(rois, boxes, min_iou=0.6)
    assert m.radar_index.tolist() == [0] and m.camera_index.tolist() == [0]
    assert m.iou[0] == pytest.approx(9 / 13)


def test_pairing_keeps_a_close_pair_that_raw_distances_would_split() -> None:
    # Raw Hungarian: 0.1 + 20.0 > 10.0 + 9.9, so it would pair across and lose the one real pair.
    a = np.array([[0.0, 0.0], [10.0, 0.0]])
    b = np.array([[0.1, 0.0], [-10.0, 0.0]])
    pairs, only_a, only_b = radar_camera.pair_observations(a, b, gate_m=0.5)
    assert pairs == [(0, 0)] and only_a == [1] and only_b == [1]


def test_target_height_picks_the_deck_or_the_lane_beneath(scene: Scene) -> None:
    # (0.15, 3.3): the northbound table lane l2 (x = 0.15) passes under the westbound deck (y = 3.3).
    surface = RoadSurface(scene, half_width_m=0.2, sample_step_m=0.05)
    xy = np.array([[0.15, 3.3], [0.15, 3.3]])
    # A radar sees the top edge of a car on the table (0.21 m) and the bottom edge of one on the deck.
    level = radar_camera.level_ranges(np.array([0.21, 0.40]), CAR[2], 0.05)
    np.testing.assert_allclose(level, [[-0.05, 0.26], [0.14, 0.45]])
    np.testing.assert_allclose(surface.heights_near(xy, level), [0.0, 0.4])
    np.testing.assert_allclose(surface.lane_heading(xy, level), [np.pi / 2, np.pi], atol=1e-9)
    # Off the road stays off the road whatever the height; no sample at that level: nearest in xy.
    far = surface.nearest_sample(np.array([[0.0, -4.8], [1.75, 2.5]]), np.array([[-1, 1], [0.9, 1.0]]))
    assert far[0] == -1 and surface.points_m[far[1], 2] == pytest.approx(0.4)


def test_lane_constraint_moves_a_position_across_the_lane_only() -> None:
    xy = np.array([[2.0, 1.1], [2.0, 1.1]])
    cov = np.tile(np.diag([0.02**2, 0.01**2]), (2, 1, 1))
    # Lane along +x through (0, 1), lateral std 0.01 m = the measurement's: halfway across, x untouched.
    lane_xy = np.array([[0.0, 1.0], [0.0, 1.0]])
    out, out_cov = radar_camera.constrain_to_lane(xy, cov, lane_xy, np.array([0.0, np.nan]), 0.01)
    np.testing.assert_allclose(out[0], [2.0, 1.05], atol=1e-12)
    np.testing.assert_allclose(out_cov[0], np.diag([0.02**2, 0.01**2 / 2]), atol=1e-15)
    np.testing.assert_array_equal(out[1], xy[1])  # no lane direction: unchanged
    np.testing.assert_array_equal(out_cov[1], cov[1])


def test_covariance_weighted_fusion_takes_each_sensor_where_it_is_precise() -> None:
    truth = np.array([[3.0, 0.0]])
    # Radar at the origin: 1 cm in range (x here), 10 cm across (y). Camera at (-1, 0), 4 m away along
    # the same line: precise across the ray (1 px at fx 400 = 1 cm), coarse along it (2.5 % = 10 cm).
    cov_r = radar_camera.radar_position_cov(truth, np.array([0.0, 0.0]), np.array([3.0]), 0.01, 0.1 / 3)
    cov_c = radar_camera.camera_position_cov(truth, np.array([-1.0, 0.0]), 1.0, 400.0, 0.025)
    np.testing.assert_allclose(np.sqrt(np.diag(cov_r[0])), [0.01, 0.1], rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(cov_c[0])), [0.1, 0.01], rtol=1e-9)
    radar_xy, camera_xy = truth + np.array([0.0, 0.1]), truth + np.array([0.1, 0.0])
    xy, cov = radar_camera.fuse_positions(radar_xy, cov_r, camera_xy, cov_c)
    np.testing.assert_allclose(xy, truth + np.array([0.1, 0.1]) / 101, atol=1e-12)
    assert np.sqrt(cov[0, 0, 0]) < 0.0100 and np.sqrt(cov[0, 1, 1]) < 0.0100


def test_radar_reflection_gives_the_centre_of_a_car_with_known_heading() -> None:
    rng = np.random.default_rng(5)
    centres = rng.uniform([1.0, 1.0], [4.0, 4.0], (40, 2))
    yaws = rng.uniform(-np.pi, np.pi, 40)
    radar = np.array([0.0, 0.0])
    reflections = radar_camera.nearest_footprint_point(centres, yaws, CAR[:2], radar)
    # The reflection lies on the footprint's boundary, on the radar's side.
    assert np.all(np.linalg.norm(reflections - radar, axis=1) < np.linalg.norm(centres - radar, axis=1))
    found = radar_camera.centres_from_reflections(reflections, yaws, CAR[:2], radar, 0.12)
    # Every centre found explains its reflection; a face reflection leaves the position along the face
    # open (any centre sliding along it fits), so most but not all are the true centre.
    again = radar_camera.nearest_footprint_point(found, yaws, CAR[:2], radar)
    np.testing.assert_allclose(again, reflections, atol=1e-6)
    err = np.linalg.norm(found - centres, axis=1)
    assert np.mean(err < 1e-3) >= 0.9 and err.max() <= CAR[0] / 2
    # Unknown heading: the fixed offset along the line of sight.
    guess = radar_camera.centres_from_reflections(reflections[:1], np.array([np.nan]), CAR[:2], radar, 0.12)
    assert np.linalg.norm(guess[0] - reflections[0]) == pytest.approx(0.12)


def test_centre_over_uncertain_heading_lies_between_the_corners_it_could_be() -> None:
    radar = np.array([0.0, 0.0])
    # Seen end-on 4 m ahead: 0.1 rad of heading decides which rear corner reflects.
    truth, lane_yaw = np.array([[0.05, 4.0]]), np.array([np.pi / 2])
    for yaw_off in (-0.1, 0.1):
        reflection = radar_camera.nearest_footprint_point(truth, lane_yaw + yaw_off, CAR[:2], radar)
        one = radar_camera.centres_from_reflections(reflection, lane_yaw, CAR[:2], radar, 0.12)
        mean, cov = radar_camera.centres_over_yaw(reflection, lane_yaw, 0.1, CAR[:2], radar, 0.12)
        # The lane heading alone puts the centre a car width off for one of the two headings; the mean
        # over headings lies within about two of its stds of the truth, the spread is mostly across.
        across_std = np.sqrt(cov[0, 0, 0])
        assert abs(mean[0, 0] - truth[0, 0]) <= 2 * across_std
        assert across_std > 3 * np.sqrt(cov[0, 1, 1])
        if abs(one[0, 0] - truth[0, 0]) > 0.15:
            assert abs(mean[0, 0] - truth[0, 0]) < abs(one[0, 0] - truth[0, 0])
    # Seen at 45 degrees the same corner reflects for every heading near the lane's: the mean is the
    # centre, the spread small.
    side = np.array([[3.0, 3.0]])
    reflection = radar_camera.nearest_footprint_point(side, lane_yaw, CAR[:2], radar)
    mean, cov = radar_camera.centres_over_yaw(reflection, lane_yaw, 0.05, CAR[:2], radar, 0.12)
    assert np.linalg.norm(mean[0] - side[0]) < 0.01 and np.sqrt(np.trace(cov[0])) < 0.02
    # No spread: the lane heading alone; unknown heading: the first guess, no spread either.
    mean, cov = radar_camera.centres_over_yaw(reflection, lane_yaw, 0.0, CAR[:2], radar, 0.12)
    np.testing.assert_allclose(
        mean, radar_camera.centres_from_reflections(reflection, lane_yaw, CAR[:2], radar, 0.12)
    )
    assert not cov.any()
    mean, cov = radar_camera.centres_over_yaw(reflection, np.array([np.nan]), 0.1, CAR[:2], radar, 0.12)
    assert np.linalg.norm(mean[0] - reflection[0]) == pytest.approx(0.12)
    np.testing.assert_allclose(cov, 0.0, atol=1e-20)


def test_viaduct_radar_places_a_car_yawed_off_its_lane_on_the_lane(scene: Scene) -> None:
    from shared.geometry.transforms import cartesian_to_polar, invert_transform
    from shared.perception.config import MecSettings
    from shared.perception.pipeline import AgentInputs, AgentPipeline

    # A car on the west deck (lane x = -3.7, southbound, deck 0.4 m) leaving the corner 0.12 rad off its
    # lane: radar_2, 4.5 m south and 0.2 m west, sees its east front corner, the lane's heading says
    # the west one. Nearest point of the box to the radar (below the deck): on the box's bottom face.
    truth_xy, yaw = np.array([-3.7, 2.6]), -np.pi / 2 - 0.12
    T = np.asarray(scene.T_world_from_sensor("radar_2"), float)
    corner = radar_camera.nearest_footprint_point(truth_xy[None], np.array([yaw]), CAR[:2], T[:2, 3])
    local = (invert_transform(T) @ np.r_[corner[0], 0.4, 1.0])[:3]
    r, az, el = cartesian_to_polar(local[None])
    scan = RadarTargets(r, az, el, np.zeros(1), np.zeros(1))
    found = {}
    for lane_std, yaw_std in ((None, 0.0), (0.03, 0.0), (0.03, 0.1)):
        settings = MecSettings()
        update = {"lane_lateral_std_m": lane_std, "lane_yaw_std_rad": yaw_std}
        settings = settings.model_copy(
            update={"radar_camera": settings.radar_camera.model_copy(update=update)}
        )
        pipe = AgentPipeline(scene, "agent2", settings, sensor_ids=["radar_2"])
        ((m,),) = pipe.radar_measurements(AgentInputs(stamp_ns=0, radar={"radar_2": scan}))
        assert m.z_m == pytest.approx(0.4 + scene.spec.vehicle.height_m / 2)  # half a car over the deck
        found[lane_std, yaw_std] = abs(m.position_m - truth_xy)
    off_lane = found[None, 0.0][0]
    assert off_lane > 0.15  # the corner on the wrong side: off by about the car's width
    # Across the line of sight the radar position has std ~0.064 m (azimuth + reflection spread), the
    # lane 0.03 m: about a fifth of the offset remains.
    assert found[0.03, 0.0][0] < off_lane / 5
    # With the heading uncertain the centre starts between the two corners and says so in its
    # covariance: the lane takes most of what remains.
    assert found[0.03, 0.1][0] < found[0.03, 0.0][0] / 2
    for err in found.values():
        assert err[1] < 0.05  # the range still places it along the lane


# --- Algorithm 2 ------------------------------------------------------------------------------------


def projected(view: CameraView, boxes: np.ndarray) -> np.ndarray:
    img, visible, _ = view.image_boxes(boxes)
    assert visible.all()
    return np.column_stack([img, np.full(len(img), 0.9), np.zeros(len(img))])


def test_algorithm2_matches_each_box_to_its_projection(scene: Scene, cam: CameraView) -> None:
    boxes = np.stack([car(-0.6, 1.9, 0.0), car(-0.2, 2.4, 1.2), car(-0.9, 2.6, 0.5)])
    dets = projected(cam, boxes)[[2, 0, 1]]  # the detector's order differs
    res = lidar_camera.match_boxes(boxes, np.array([0.5, 0.9, 0.7]), [cam], {"cam_11": dets}, 0.7)
    assert sorted((i, j) for i, _, j, _ in res.matches) == [(0, 1), (1, 2), (2, 0)]
    assert all(iou == pytest.approx(1.0) for *_, iou in res.matches)
    assert res.unmatched_3d == [] and res.unused_2d == {"cam_11": []}


def test_algorithm2_masks_a_second_cameras_box_and_leaves_disjoint_boxes(scene: Scene) -> None:
    a, b = CameraView.from_scene(scene, "cam_3"), CameraView.from_scene(scene, "cam_6")  # overlapping views
    box = car(4.4, 4.4, 0.3)
    assert all(v.image_boxes(box[None])[2][0] for v in (a, b)), "both cameras must see the car whole"
    both = {"cam_3": projected(a, box[None]), "cam_6": projected(b, box[None])}
    res = lidar_camera.match_boxes(box[None], np.array([0.9]), [a, b], both, 0.7)
    # Matched in the nearer camera, and the other camera's box is masked (used, not a second match).
    nearest = min((a, b), key=lambda v: np.linalg.norm(v.center_m - box[:3])).sensor_id
    assert [(c, j) for _, c, j, _ in res.matches] == [(nearest, 0)] and res.masked == 1
    assert res.unused_2d == {"cam_3": [], "cam_6": []}
    # A 2D box far from the projection (disjoint in u and v) never matches: IoU is clamped at 0.
    far = projected(a, box[None]) + np.array([-200, -150, -200, -150, 0, 0])
    res = lidar_camera.match_boxes(box[None], np.array([0.9]), [a], {"cam_3": far}, 0.01)
    assert res.matches == [] and res.unmatched_3d == [0] and res.unused_2d == {"cam_3": [0]}


def test_merge_moves_the_centre_by_the_camera_weight(cam: CameraView) -> None:
    truth = car(-0.6, 2.0, 0.0)
    lidar = truth + np.array([0.05, 0, 0, 0, 0, 0, 0])  # 5 cm off across the camera's view (+y)
    det = projected(cam, truth[None])[0]
    cfg = lidar_camera.LidarCameraConfig(camera_weight=0.4, merge_centre=True, refine_yaw=False)
    merged, applied = lidar_camera.merge_box(lidar, det, cam, cfg)
    assert applied
    # Not exactly 0.6 x 5 cm: box centres are not projected centres under perspective.
    assert merged[0] == pytest.approx(truth[0] + 0.6 * 0.05, abs=5e-3)
    assert merged[1] == pytest.approx(truth[1], abs=5e-3)
    full = lidar_camera.merge_box(lidar, det, cam, cfg.model_copy(update={"camera_weight": 1.0}))[0]
    assert np.linalg.norm(full[:2] - truth[:2]) < 3e-3


def test_yaw_refinement_moves_toward_the_cameras_aspect(cam: CameraView) -> None:
    truth = car(-0.6, 2.0, 0.4)
    lidar = truth + np.array([0, 0, 0, 0, 0, 0, 0.1])
    det = projected(cam, truth[None])[0]
    cfg = lidar_camera.LidarCameraConfig(
        camera_weight=1.0, merge_centre=False, refine_yaw=True, yaw_search_rad=0.15
    )
    merged, _ = lidar_camera.merge_box(lidar, det, cam, cfg)
    assert abs(merged[6] - truth[6]) < 0.02


def test_truncated_detection_is_not_merged(cam: CameraView) -> None:
    box = car(-0.6, 2.0, 0.0)
    det = projected(cam, box[None])[0]
    det[0] = 0.0  # touches the left border
    merged, applied = lidar_camera.merge_box(box, det, cam, lidar_camera.LidarCameraConfig(merge_centre=True))
    assert not applied and np.array_equal(merged, box)


# --- camera only ------------------------------------------------------------------------------------


def test_camera_only_places_cars_on_the_lane_surface(scene: Scene) -> None:
    surface = RoadSurface(scene, half_width_m=0.2, sample_step_m=0.05)
    lane = scene.spec.lanes[0]
    line = np.asarray(scene.lane_centreline(lane.id))
    views = {c.id: CameraView.from_scene(scene, c.id) for c in scene.sensors_of(kind="camera")}
    # A car on a lane, seen by whichever cameras show it whole.
    p, q = line[len(line) // 2], line[len(line) // 2 + 1]
    yaw = float(np.arctan2(q[1] - p[1], q[0] - p[0]))
    truth = car(p[0], p[1], yaw, z=p[2] + CAR[2] / 2)
    dets = {}
    for cid, v in views.items():
        img, visible, inside = v.image_boxes(truth[None])
        if visible[0] and inside[0]:
            dets[cid] = np.column_stack([img, [0.9], [0.0]])
    assert dets, "test car must be visible to some camera"
    (obj,) = camera_only.locate(views, dets, surface, camera_only.CameraOnlyConfig(), CAR)
    assert np.linalg.norm(obj.box[:2] - truth[:2]) < 0.06
    assert obj.box[2] == pytest.approx(truth[2], abs=0.02)
    assert obj.yaw_known and np.cos(obj.box[6] - yaw) > 0.99
    assert set(obj.sensor_ids) == set(dets)


def test_merge_nearby_fuses_one_car_seen_twice() -> None:
    a = camera_only.CameraObject(car(0, 0, 0), np.eye(2) * 0.01, True, 0.9, ("a",))
    b = camera_only.CameraObject(car(0.1, 0, 0), np.eye(2) * 0.01, True, 0.8, ("b",))
    c = camera_only.CameraObject(car(1.0, 0, 0), np.eye(2) * 0.01, True, 0.7, ("c",))
    merged = camera_only.merge_nearby([c, b, a], radius_m=0.2)
    assert len(merged) == 2
    assert merged[0].box[0] == pytest.approx(0.05) and merged[0].sensor_ids == ("a", "b")


def test_fast_projection_paths_equal_the_validated_geometry(cam: CameraView) -> None:
    from shared.geometry.boxes import box3d_corners
    from shared.geometry.camera import box3d_to_image_box, pixel_to_world_on_plane

    rng = np.random.default_rng(3)
    boxes = np.stack([car(x, y, yaw) for x, y, yaw in rng.uniform([-1.5, 0.5, -3], [0.5, 3.5, 3], (50, 3))])
    fast, fast_visible, _ = cam.image_boxes(boxes)
    ref, ref_visible = box3d_to_image_box(
        box3d_corners(boxes), cam.T_optical_from_world, cam.K, cam.width_px, cam.height_px
    )
    np.testing.assert_array_equal(fast_visible, ref_visible)
    np.testing.assert_allclose(fast[fast_visible], ref[ref_visible], atol=1e-9)
    uv = rng.uniform([0, 0], [cam.width_px, cam.height_px], (50, 2))
    z = rng.uniform(0.0, 0.3, 50)
    fast_pts = cam.to_plane(uv, z)
    for p, q, h in zip(fast_pts, uv, z, strict=True):
        ref_pt = pixel_to_world_on_plane(q[None], cam.T_world_from_optical, cam.K, plane_offset=h)[0][0]
        np.testing.assert_allclose(p, ref_pt, atol=1e-9, equal_nan=True)


def test_batched_merge_equals_one_at_a_time(cam: CameraView) -> None:
    truths = np.stack([car(-0.6, 2.0, 0.2), car(-0.3, 1.8, 1.0), car(-0.8, 2.4, -0.4)])
    lidar = truths + np.array([0.03, -0.02, 0, 0, 0, 0, 0.08])
    dets = projected(cam, truths)
    cfg = lidar_camera.LidarCameraConfig(merge_centre=True, refine_yaw=True)
    batch, applied = lidar_camera.merge_boxes(lidar, dets, cam, cfg)
    for k in range(len(truths)):
        one, ok = lidar_camera.merge_box(lidar[k], dets[k], cam, cfg)
        np.testing.assert_allclose(batch[k], one, atol=1e-12)
        assert ok == applied[k]


def test_centre_fit_reports_rays_that_miss_and_keeps_the_others(cam: CameraView) -> None:
    truth = car(-0.6, 2.0, 0.2)
    det = projected(cam, truth[None])[0, :4]
    sky = np.array([300.0, 0.0, 340.0, 2.0])  # above the horizon: its ray never meets the plane
    xy = cam.fit_centres(np.stack([truth, truth]), np.stack([det, sky]))
    assert np.isfinite(xy[0]).all() and np.isnan(xy[1]).all()
    np.testing.assert_allclose(xy[0], truth[:2], atol=3e-3)
