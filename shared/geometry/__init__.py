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

Modules (import them directly; this package re-exports nothing)
---------------------------------------------------------------
- :mod:`shared.geometry.transforms`: rigid transforms, body/optical frames, polar coordinates, angles.
- :mod:`shared.geometry.camera`: intrinsics, projection, pixel rays, ray-plane back-projection.
- :mod:`shared.geometry.boxes`: box corners, 2D / rotated BEV / 3D IoU matrices, 2D box centres.
- :mod:`shared.geometry.grid`: the metric cell grid of the traffic and heat maps.
"""
