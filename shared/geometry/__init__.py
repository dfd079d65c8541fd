"""Geometry library for RMMDet: frames, camera model and box IoU on the 1:18 sand table.

Conventions (details in each module's docstring)
------------------------------------------------
- World frame: table metres, right-handed, +z up, yaw counter-clockwise from +x.
- ``T_a_from_b`` is a 4x4 homogeneous matrix with ``p_a = T_a_from_b @ p_b``.
- Sensor body frame (lidar, radar, camera mount): +x forward, +y left, +z up. Camera optical frame
  (OpenCV): +x right, +y down, +z forward; ``T_OPTICAL_FROM_BODY`` converts between them.
- Projection (paper Eq. 1-2): ``Z_c [u, v, 1]^T = K [R | t] X_w`` with ``[R | t]`` from
  ``T_optical_from_world``; continuous pixel coordinates (column i covers [i, i + 1)).
- Intrinsics from FOV: ``fx = fy = W / (2 tan(hfov / 2))``, ``cx = W / 2``, ``cy = H / 2``.
- 3D boxes: OpenPCDet ``(x, y, z, dx, dy, dz, heading)``; 2D boxes ``(x1, y1, x2, y2)`` pixels.

Modules
-------
- :mod:`shared.geometry.transforms`: rigid transforms, body/optical frames, polar coordinates, angles.
- :mod:`shared.geometry.camera`: intrinsics, projection, pixel rays, ray-plane back-projection.
- :mod:`shared.geometry.boxes`: box corners, 2D / rotated BEV / 3D IoU matrices.
"""

from shared.geometry.boxes import (
    bev_corners,
    bev_intersection_area_matrix,
    bev_iou_matrix,
    box3d_corners,
    iou2d_matrix,
    iou3d_matrix,
)
from shared.geometry.camera import (
    box3d_to_image_box,
    intrinsics_from_fov,
    pixel_rays,
    pixel_to_world_on_plane,
    project_points,
    projection_matrix,
    ray_plane_intersection,
    vertical_fov_rad,
)
from shared.geometry.transforms import (
    OPTICAL_FROM_BODY,
    R_OPTICAL_FROM_BODY,
    T_BODY_FROM_OPTICAL,
    T_OPTICAL_FROM_BODY,
    camera_optical_from_world,
    camera_world_from_optical,
    cartesian_to_polar,
    invert_transform,
    matrix_from_pose,
    matrix_from_xyz_rpy,
    polar_to_cartesian,
    pose_from_matrix,
    transform_points,
    wrap_angle,
    xyz_rpy_from_matrix,
    yaw_from_matrix,
)

__all__ = [
    "OPTICAL_FROM_BODY",
    "R_OPTICAL_FROM_BODY",
    "T_BODY_FROM_OPTICAL",
    "T_OPTICAL_FROM_BODY",
    "bev_corners",
    "bev_intersection_area_matrix",
    "bev_iou_matrix",
    "box3d_corners",
    "box3d_to_image_box",
    "camera_optical_from_world",
    "camera_world_from_optical",
    "cartesian_to_polar",
    "intrinsics_from_fov",
    "invert_transform",
    "iou2d_matrix",
    "iou3d_matrix",
    "matrix_from_pose",
    "matrix_from_xyz_rpy",
    "pixel_rays",
    "pixel_to_world_on_plane",
    "polar_to_cartesian",
    "pose_from_matrix",
    "project_points",
    "projection_matrix",
    "ray_plane_intersection",
    "transform_points",
    "vertical_fov_rad",
    "wrap_angle",
    "xyz_rpy_from_matrix",
    "yaw_from_matrix",
]
