"""Known-answer tests for shared.geometry.camera."""

from __future__ import annotations

import numpy as np
import pytest

from shared.geometry.camera import (
    box3d_to_image_box,
    intrinsics_from_fov,
    near_clipped_extent,
    pixel_rays,
    pixel_to_world_on_plane,
    project_points,
    projection_matrix,
    ray_plane_intersection,
    vertical_fov_rad,
)
from shared.geometry.transforms import (
    camera_optical_from_world,
    camera_world_from_optical,
    invert_transform,
    matrix_from_xyz_rpy,
)

W_PX, H_PX, HFOV_RAD = 640, 480, 1.13
# fx = 640 / (2 tan(0.565)) = 640 / (2 * 0.633935...) = 504.78216
FX_PX = 504.78216
K = intrinsics_from_fov(W_PX, H_PX, HFOV_RAD)


# --- intrinsics --------------------------------------------------------------------------------------


def test_intrinsics_from_fov_known_answer() -> None:
    assert K[0, 0] == pytest.approx(FX_PX, abs=1e-4)
    assert K[1, 1] == pytest.approx(FX_PX, abs=1e-4)
    assert (K[0, 2], K[1, 2]) == (320.0, 240.0)
    np.testing.assert_array_equal(K[2], [0.0, 0.0, 1.0])
    assert K[0, 1] == 0.0 and K[1, 0] == 0.0


def test_vertical_fov() -> None:
    # Square pixels: tan(vfov/2) = tan(hfov/2) * H / W = 0.633935 * 0.75 = 0.475451 -> vfov = 0.887635 rad.
    assert vertical_fov_rad(K, H_PX) == pytest.approx(0.887635, abs=1e-6)
    assert vertical_fov_rad(K, H_PX) == pytest.approx(2 * np.arctan(np.tan(HFOV_RAD / 2) * H_PX / W_PX))
    # A square image has equal horizontal and vertical FOV.
    assert vertical_fov_rad(intrinsics_from_fov(500, 500, 1.0), 500) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("w", "h", "fov"), [(0, 480, 1.0), (640, -1, 1.0), (640, 480, 0.0), (640, 480, np.pi), (640, 480, np.nan)]
)
def test_intrinsics_from_fov_rejects_bad_values(w: int, h: int, fov: float) -> None:
    with pytest.raises(ValueError):
        intrinsics_from_fov(w, h, fov)


# --- projection --------------------------------------------------------------------------------------


def test_point_on_optical_axis_projects_to_principal_point() -> None:
    uv, depth = project_points([[0.0, 0.0, 5.0]], np.eye(4), K)
    np.testing.assert_allclose(uv, [[320.0, 240.0]], atol=1e-9)
    np.testing.assert_allclose(depth, [5.0])


def test_camera_looking_along_world_y_known_pixel() -> None:
    # Camera mount at (0, 0, 1), yaw +90 deg: forward = world +y, right = world +x, up = world +z.
    # World point (0.5, 2, 1.2) is 2 m ahead, 0.5 m right, 0.2 m up -> optical (0.5, -0.2, 2).
    # u = 320 + 504.78216 * 0.5 / 2 = 446.19554, v = 240 + 504.78216 * (-0.2) / 2 = 189.521784.
    T_optical_from_world = camera_optical_from_world(matrix_from_xyz_rpy([0, 0, 1], [0, 0, np.pi / 2]))
    uv, depth = project_points([[0.5, 2.0, 1.2]], T_optical_from_world, K)
    np.testing.assert_allclose(uv, [[446.19554, 189.521784]], atol=1e-4)
    np.testing.assert_allclose(depth, [2.0], atol=1e-12)


def test_projection_matrix_matches_eq1() -> None:
    # Z_c [u v 1]^T = K [R | t] X_w
    T_optical_from_world = camera_optical_from_world(matrix_from_xyz_rpy([1, -2, 1.5], [0.1, 0.5, 0.8]))
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (30, 3))
    uv, depth = project_points(pts, T_optical_from_world, K)
    homogeneous = (projection_matrix(K, T_optical_from_world) @ np.c_[pts, np.ones(30)].T).T
    np.testing.assert_allclose(homogeneous[:, 2], depth, atol=1e-12)
    front = depth > 0
    assert front.any() and (~front).any()
    np.testing.assert_allclose(homogeneous[front, :2] / homogeneous[front, 2:], uv[front], atol=1e-8)


def test_points_behind_camera_are_nan() -> None:
    pts = [[0.0, 0.0, -2.0], [1.0, 1.0, 0.0], [0.1, 0.0, 1.0]]
    uv, depth = project_points(pts, np.eye(4), K)
    assert np.all(np.isnan(uv[:2]))
    assert np.all(np.isfinite(uv[2]))
    np.testing.assert_allclose(depth, [-2.0, 0.0, 1.0])


def test_project_points_empty() -> None:
    uv, depth = project_points(np.zeros((0, 3)), np.eye(4), K)
    assert uv.shape == (0, 2) and depth.shape == (0,)


# --- rays and planes ---------------------------------------------------------------------------------


def test_pixel_rays_known_answers() -> None:
    # Principal point -> optical axis; one focal length to the right -> 45 deg to the right.
    rays = pixel_rays([[320.0, 240.0], [320.0 + K[0, 0], 240.0], [320.0, 240.0 - K[1, 1]]], K)
    s = np.sqrt(0.5)
    np.testing.assert_allclose(rays, [[0, 0, 1], [s, 0, s], [0, -s, s]], atol=1e-12)
    assert pixel_rays(np.zeros((0, 2)), K).shape == (0, 3)


def test_ray_plane_intersection_known_answers() -> None:
    origins = np.array([[0.0, 0.0, 2.0], [1.0, 1.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, 2.0]])
    directions = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pts, t = ray_plane_intersection(origins, directions, [0.0, 0.0, 1.0], 0.0)
    np.testing.assert_allclose(pts[:2], [[0, 0, 0], [3, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(t[:2], [2.0, 2.0])
    # Ray 2 is parallel to the plane, ray 3 points away from it.
    assert np.all(np.isnan(pts[2:])) and np.all(np.isnan(t[2:]))
    # Normal need not be unit: 2z = 1 is the plane z = 0.5.
    pts, t = ray_plane_intersection(origins[:1], directions[:1], [0.0, 0.0, 2.0], 1.0)
    np.testing.assert_allclose(pts, [[0.0, 0.0, 0.5]])
    np.testing.assert_allclose(t, [1.5])


def test_ray_plane_intersection_validates() -> None:
    with pytest.raises(ValueError, match="plane_normal"):
        ray_plane_intersection([[0, 0, 1]], [[0, 0, -1]], [0, 0, 0], 0.0)
    with pytest.raises(ValueError, match="directions"):
        ray_plane_intersection([[0, 0, 1]], [[0, 0, 0]], [0, 0, 1], 0.0)
    with pytest.raises(ValueError, match="directions"):
        ray_plane_intersection([[0, 0, 1]], [[0, 0, -1], [0, 0, -1]], [0, 0, 1], 0.0)
    with pytest.raises(ValueError, match="plane_offset"):
        ray_plane_intersection([[0, 0, 1]], [[0, 0, -1]], [0, 0, 1], np.nan)


# Camera mount poses as URDF (xyz, rpy): level, pitched down, pitched + rolled + yawed, straight down.
CAMERA_POSES = [
    ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0]),
    ([0.5, -1.0, 1.5], [0.0, 0.6, 0.3]),
    ([-2.0, 1.0, 2.0], [0.25, 0.9, 2.0]),
    ([1.0, 2.0, 0.8], [-0.3, 1.2, -2.5]),
    ([0.0, 0.0, 3.0], [0.0, np.pi / 2, 0.0]),
]


@pytest.mark.parametrize(("xyz", "rpy"), CAMERA_POSES)
@pytest.mark.parametrize("plane_z_m", [0.0, 0.05])
def test_project_then_back_project_round_trip(xyz: list[float], rpy: list[float], plane_z_m: float) -> None:
    T_world_from_body = matrix_from_xyz_rpy(xyz, rpy)
    T_optical_from_world = camera_optical_from_world(T_world_from_body)
    T_world_from_optical = camera_world_from_optical(T_world_from_body)
    np.testing.assert_allclose(T_world_from_optical, invert_transform(T_optical_from_world), atol=1e-12)

    rng = np.random.default_rng(42)
    pts = np.c_[rng.uniform(-6, 6, (400, 2)) + np.asarray(xyz[:2]), np.full(400, plane_z_m)]
    uv, depth = project_points(pts, T_optical_from_world, K)
    # Keep points clearly in front and roughly in the image so rays are not grazing the plane.
    keep = (depth > 0.1) & (np.abs(uv[:, 0] - 320) < 1000) & (np.abs(uv[:, 1] - 240) < 1000)
    assert keep.sum() >= 20
    back, back_depth = pixel_to_world_on_plane(uv[keep], T_world_from_optical, K, plane_offset=plane_z_m)
    np.testing.assert_allclose(back, pts[keep], atol=1e-6)
    np.testing.assert_allclose(back_depth, depth[keep], atol=1e-6)


def test_round_trip_with_distortion() -> None:
    distortion = np.array([-0.12, 0.03, 0.001, -0.0015, 0.0])
    T_world_from_body = matrix_from_xyz_rpy([0.0, 0.0, 1.2], [0.1, 0.7, 0.4])
    T_optical_from_world = camera_optical_from_world(T_world_from_body)
    rng = np.random.default_rng(7)
    pts = np.c_[rng.uniform(-4, 4, (400, 2)), np.zeros(400)]
    uv, depth = project_points(pts, T_optical_from_world, K, distortion)
    # The distortion polynomial is only invertible near the image; test points inside it.
    keep = (depth > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W_PX) & (uv[:, 1] >= 0) & (uv[:, 1] < H_PX)
    assert keep.sum() >= 20
    back, _ = pixel_to_world_on_plane(
        uv[keep], camera_world_from_optical(T_world_from_body), K, distortion=distortion
    )
    np.testing.assert_allclose(back, pts[keep], atol=1e-6)


def test_pixel_above_horizon_misses_ground() -> None:
    # Level camera 1 m up: the top image row looks upward and never reaches z = 0.
    T_world_from_optical = camera_world_from_optical(matrix_from_xyz_rpy([0, 0, 1], [0, 0, 0]))
    pts, depth = pixel_to_world_on_plane([[320.0, 0.0], [320.0, 479.0]], T_world_from_optical, K)
    assert np.all(np.isnan(pts[0])) and np.isnan(depth[0])
    # Bottom row: ray slope (479 - 240) / fx below the axis, so it lands fx / 239 m ahead.
    np.testing.assert_allclose(pts[1], [K[1, 1] / 239.0, 0.0, 0.0], atol=1e-9)


# --- 3D box -> image box -----------------------------------------------------------------------------


def _axis_box_corners(cx: float, cy: float, cz: float, half: float) -> np.ndarray:
    signs = np.array(
        [[1, 1, -1], [1, -1, -1], [-1, -1, -1], [-1, 1, -1], [1, 1, 1], [1, -1, 1], [-1, -1, 1], [-1, 1, 1]]
    )
    return np.array([cx, cy, cz]) + half * signs


def test_box3d_to_image_box_known_answers() -> None:
    # Camera mount at the world origin looking along +x, so world = body frame.
    T_optical_from_world = camera_optical_from_world(np.eye(4))
    f = K[0, 0]
    corners = np.stack(
        [
            _axis_box_corners(5.0, 0.0, 0.0, 0.5),  # centred cube: near face at x = 4.5 sets the extent
            _axis_box_corners(-5.0, 0.0, 0.0, 0.5),  # behind the camera
            _axis_box_corners(5.0, 100.0, 0.0, 0.5),  # far left, outside the image
            _axis_box_corners(5.0, -3.0, 0.0, 0.5),  # right edge, clipped at u = 640
        ]
    )
    boxes, visible = box3d_to_image_box(corners, T_optical_from_world, K, W_PX, H_PX)
    np.testing.assert_array_equal(visible, [True, False, False, True])
    # u = 320 - f * y / x, v = 240 - f * z / x; the extremes use the near face x = 4.5.
    d = f * 0.5 / 4.5
    np.testing.assert_allclose(boxes[0], [320 - d, 240 - d, 320 + d, 240 + d], atol=1e-9)
    np.testing.assert_array_equal(boxes[1], [0, 0, 0, 0])
    np.testing.assert_array_equal(boxes[2], [0, 0, 0, 0])
    # Box 3 spans y in [-3.5, -2.5]: leftmost u uses y = -2.5 on the far face x = 5.5.
    np.testing.assert_allclose(boxes[3], [320 + f * 2.5 / 5.5, 240 - d, 640.0, 240 + d], atol=1e-9)


def test_box3d_to_image_box_straddling_camera_uses_front_corners() -> None:
    # Cube from x = -2 to 2 around the camera: only the x = 2 face is in front.
    corners = _axis_box_corners(0.0, 0.0, 0.0, 2.0)[None]
    boxes, visible = box3d_to_image_box(corners, camera_optical_from_world(np.eye(4)), K, W_PX, H_PX)
    assert visible[0]
    # Face half-size 2 at distance 2 projects to +-f around the centre, beyond the image: clamp to it.
    np.testing.assert_allclose(boxes[0], [0.0, 0.0, 640.0, 480.0])


def test_box3d_to_image_box_validates() -> None:
    with pytest.raises(ValueError, match="corners_world"):
        box3d_to_image_box(np.zeros((2, 4, 3)), np.eye(4), K, W_PX, H_PX)
    with pytest.raises(ValueError, match="finite"):
        box3d_to_image_box(np.full((1, 8, 3), np.nan), np.eye(4), K, W_PX, H_PX)


# --- validation --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: project_points(np.zeros((3, 2)), np.eye(4), K), "points_world"),
        (lambda: project_points([[0, 0, np.nan]], np.eye(4), K), "finite"),
        (lambda: project_points([[0, 0, 1]], np.eye(3), K), "T_optical_from_world"),
        (lambda: project_points([[0, 0, 1]], np.eye(4), np.eye(2)), "K"),
        (lambda: project_points([[0, 0, 1]], np.eye(4), np.diag([-1.0, 1.0, 1.0])), "focal"),
        (lambda: project_points([[0, 0, 1]], np.eye(4), K, [0.1, 0.2, 0.3]), "distortion"),
        (lambda: pixel_rays(np.zeros((2, 3)), K), "uv_px"),
        (lambda: pixel_rays([[np.inf, 0.0]], K), "finite"),
        (lambda: vertical_fov_rad(K, 0), "height_px"),
    ],
)
def test_invalid_inputs_raise(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()


def _axis_box(lo_xyz: list[float], hi_xyz: list[float]) -> np.ndarray:
    """(1, 8, 3) corners of an axis-aligned box."""
    xs, ys, zs = zip(lo_xyz, hi_xyz, strict=True)
    return np.array([[[x, y, z] for x in xs for y in ys for z in zs]], float)


def test_near_clipped_extent_known_answer_for_a_box_through_the_camera_plane() -> None:
    # Optical frame = world; the box spans depth -1..3 m, so the renderer draws its part at 1..3 m and
    # its nearest face, on the near plane, sets the extent: x +-1 m, y +-0.5 m at 1 m depth.
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    lo, hi, in_view = near_clipped_extent(_axis_box([-1, -0.5, -1], [1, 0.5, 3]), np.eye(4), K, 1.0)
    assert in_view.tolist() == [True]
    np.testing.assert_allclose(lo[0], [-50.0, -10.0])
    np.testing.assert_allclose(hi[0], [150.0, 90.0])
    # The corners in front alone (box3d_to_image_box's rule) give the far face only: 1/3 of that size.
    front, _ = box3d_to_image_box(_axis_box([-1, -0.5, -1], [1, 0.5, 3]), np.eye(4), K, 10_000, 10_000)
    assert front[0, 2] == pytest.approx(50 + 100 / 3)


def test_near_clipped_extent_equals_the_corners_for_a_box_in_front_and_is_empty_behind() -> None:
    K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 0.0]
    box = _axis_box([-1, -0.5, 4], [1.5, 0.5, 9])
    lo, hi, in_view = near_clipped_extent(np.concatenate([box, box - [0, 0, 20]]), T, K, 0.5)
    uv, _ = project_points(box[0], T, K)
    np.testing.assert_allclose(lo[0], uv.min(axis=0))
    np.testing.assert_allclose(hi[0], uv.max(axis=0))
    assert in_view.tolist() == [True, False]
    assert np.isnan(lo[1]).all() and np.isnan(hi[1]).all()
    with pytest.raises(ValueError, match="near_m"):
        near_clipped_extent(box, T, K, 0.0)
