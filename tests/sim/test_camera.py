"""Camera model: composited frames agree with the camera model and with full renders."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from shared.geometry.camera import project_points
from shared.scene.scene import Scene
from sim.sensors.camera import CameraRenderer, render, vehicle_box_corners
from sim.world import FullWorld, StaticWorld, VehiclePose, VehicleWorld


@pytest.fixture(scope="module")
def worlds(
    static: StaticWorld, vehicles: VehicleWorld, full: FullWorld
) -> tuple[StaticWorld, VehicleWorld, FullWorld]:
    return static, vehicles, full


def _poses(scene: Scene) -> list[VehiclePose]:
    h = scene.spec.vehicle.height_m
    # On lane l3's southbound end (north arm of the intersection), in view of cam_11 and cam_13.
    return [
        VehiclePose("v00", (-0.15, 2.6, h / 2), -1.5708, 0.0, (0.9, 0.1, 0.1, 1.0)),
        VehiclePose("v01", (0.15, 3.2, h / 2), 1.5708, 0.0, (0.1, 0.3, 0.9, 1.0)),
        # On the south arm, in view of cam_13 (looking south from the north-east corner).
        VehiclePose("v02", (0.15, 0.4, h / 2), 1.5708, 0.0, (0.1, 0.8, 0.3, 1.0)),
    ]


@pytest.mark.parametrize("camera_id", ["cam_11", "cam_13"])
def test_vehicle_pixels_lie_inside_the_projection_of_its_box(scene: Scene, worlds, camera_id: str) -> None:
    static, vehicles, _ = worlds
    poses = _poses(scene)
    vehicles.update(poses)
    cam = CameraRenderer(scene, camera_id, static, vehicles)
    frame = cam.render(poses)
    assert frame.visible_px, "the test vehicles should be in view"
    T, K = np.asarray(scene.T_optical_from_world(camera_id)), np.asarray(scene.K(camera_id))
    for pose in poses:
        if pose.vehicle_id not in frame.visible_boxes:
            continue
        uv, _ = project_points(vehicle_box_corners(pose, vehicles.size_m), T, K)
        u0, v0, u1, v1 = frame.visible_boxes[pose.vehicle_id]
        assert u0 >= np.floor(uv[:, 0].min()) - 1 and u1 <= np.ceil(uv[:, 0].max()) + 1
        assert v0 >= np.floor(uv[:, 1].min()) - 1 and v1 <= np.ceil(uv[:, 1].max()) + 1


def test_composite_equals_a_full_render(scene: Scene, worlds) -> None:
    static, vehicles, full = worlds
    poses = _poses(scene)
    vehicles.update(poses)
    full.update(poses)
    camera_id = "cam_11"
    cam = CameraRenderer(scene, camera_id, static, vehicles)
    frame = cam.render(poses)
    model = scene.sensor(camera_id).camera
    T, K = np.asarray(scene.T_optical_from_world(camera_id)), np.asarray(scene.K(camera_id))
    reference, _, _ = render(
        full.cid, T, K, (0, 0, model.width_px, model.height_px), model.near_m, model.far_m
    )
    differs = np.any(frame.rgb.astype(int) - reference.astype(int) != 0, axis=2)
    # Identical except for rasterisation seams along silhouettes.
    assert differs.mean() < 0.01


def test_frame_without_vehicles_in_view_is_the_background(scene: Scene, worlds) -> None:
    static, vehicles, _ = worlds
    far = [VehiclePose("v00", (3.35, -4.0, 0.105), 1.57, 0.0, (0.9, 0.1, 0.1, 1.0))]
    vehicles.update(far)
    cam = CameraRenderer(scene, "cam_11", static, vehicles)
    frame = cam.render(far)
    assert frame.rois == [] and frame.rgb is cam.background


def test_a_repeated_view_is_not_rendered_again(scene: Scene, worlds) -> None:
    static, vehicles, _ = worlds
    poses = _poses(scene)
    vehicles.update(poses)
    cam = CameraRenderer(scene, "cam_11", static, vehicles)
    first = cam.render(poses, labels=False)
    assert first.rois and cam.reused == 0
    # Exactly the same poses in view: the same frame back, read-only, and what a render would give.
    again = cam.render(poses, labels=False)
    assert again is first and cam.reused == 1 and not again.rgb.flags.writeable
    fresh = CameraRenderer(scene, "cam_11", static, vehicles).render(poses, labels=False)
    assert np.array_equal(fresh.rgb, first.rgb)
    # Labels asked for: rendered (the cached frame has none).
    assert cam.render(poses, labels=True).visible_px and cam.reused == 1
    # A vehicle in view moves by 1 mm: rendered again.
    moved = [replace(poses[0], center_m=(poses[0].center_m[0] + 0.001, *poses[0].center_m[1:])), *poses[1:]]
    vehicles.update(moved)
    assert cam.render(moved, labels=False) is not first and cam.reused == 1
    # A vehicle out of view moves: nothing in view changed.
    out_of_view = VehiclePose("v09", (3.35, -4.0, 0.105), 1.57)
    vehicles.update([*moved, out_of_view])
    frame = cam.render([*moved, out_of_view], labels=False)
    vehicles.update([*moved, replace(out_of_view, yaw_rad=0.0)])
    assert cam.render([*moved, replace(out_of_view, yaw_rad=0.0)], labels=False) is frame


def test_a_vehicle_through_the_camera_plane_out_of_view_is_not_rendered(scene: Scene, worlds) -> None:
    # A vehicle passing under a camera, its rear behind the camera plane, its front below the image:
    # nothing of it is in view, so nothing is rendered (it used to cost a full-frame render: on the
    # intersection's 1920 x 1200 cameras, 70-140 ms each, one camera render in six), and the frame is
    # still what a full render shows. The extent of a visible straddling box: test_camera.py in
    # tests/shared/geometry.
    static, vehicles, full = worlds
    camera_id = "cam_11"
    model = scene.sensor(camera_id).camera
    T, K = np.asarray(scene.T_optical_from_world(camera_id)), np.asarray(scene.K(camera_id))
    T_world = np.linalg.inv(T)
    forward = T_world[:3, 2] / np.linalg.norm(T_world[:3, 2][:2])  # optical z, unit length in the plane
    yaw = float(np.arctan2(forward[1], forward[0]))
    h = scene.spec.vehicle.height_m
    centre = T_world[:3, 3] + 0.1 * scene.spec.vehicle.length_m * forward
    pose = VehiclePose("v00", (float(centre[0]), float(centre[1]), h / 2), yaw, 0.0, (0.9, 0.1, 0.1, 1.0))
    _, depth = project_points(vehicle_box_corners(pose, vehicles.size_m), T, K)
    assert (depth < 0).any() and (depth > model.near_m).any(), "the vehicle should straddle the camera plane"
    vehicles.update([pose])
    full.update([pose])
    cam = CameraRenderer(scene, camera_id, static, vehicles)
    frame = cam.render([pose])
    assert frame.rois == [] and frame.rgb is cam.background
    reference, _, _ = render(
        full.cid, T, K, (0, 0, model.width_px, model.height_px), model.near_m, model.far_m
    )
    differs = np.any(frame.rgb.astype(int) - reference.astype(int) != 0, axis=2)
    assert differs.mean() < 0.01


def test_a_large_vehicle_rectangle_renders_at_a_reduced_size_with_the_same_silhouette(
    scene: Scene, worlds
) -> None:
    static, vehicles, _ = worlds
    poses = _poses(scene)
    vehicles.update(poses)
    exact = CameraRenderer(scene, "cam_11", static, vehicles)
    assert exact.roi_full_res_max_px is None  # the sand table's default: every rectangle at full size
    reference = exact.render(poses)
    reduced = CameraRenderer(scene, "cam_11", static, vehicles)
    reduced.roi_full_res_max_px = max(1, min((r[2] - r[0]) * (r[3] - r[1]) for r in reference.rois) // 4)
    frame = reduced.render(poses)
    assert reduced.reduced == len(reference.rois) and exact.reduced == 0
    assert frame.rgb.shape == reference.rgb.shape and frame.visible_px.keys() == reference.visible_px.keys()
    for vid, px in reference.visible_px.items():
        assert frame.visible_px[vid] == pytest.approx(px, rel=0.15), vid
    differs = np.any(frame.rgb.astype(int) - reference.rgb.astype(int) != 0, axis=2)
    assert 0 < differs.mean() < 0.01  # rendered differently (scaled up), only along edges
