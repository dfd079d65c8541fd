"""Heading of the tracks: a measured axis known modulo pi, its sign from a full heading or the motion.

Yaw measurements known only modulo pi (lidar boxes) are averaged as unit vectors of the doubled angle
(the track's ``AXIS2`` attributes), so 0.1 and 0.1 + pi reinforce instead of cancelling. The sign is
taken, in this order, from measured full headings (the ``HEAD`` attributes), from the velocity when the
track moves clearly (speed above ``min_speed_mps`` and ``min_speed_sigmas`` standard deviations of its
estimate), else from the previous frame's resolved heading (a stopped car keeps its heading). A track
that never measured a yaw (radar or camera only) takes the velocity heading, or the previous one.
"""

from __future__ import annotations

import numpy as np

from shared.tracking.kalman import VX, VY, FloatArray
from shared.tracking.measurement import AXIS2, COS, HEAD, SIN, NDBool


def wrap(a: FloatArray) -> FloatArray:
    """Angles wrapped into (-pi, pi], rad; NaN stays NaN.

    Same convention as `shared.geometry.transforms.wrap_angle`, but NaN-tolerant.
    """
    return np.asarray(np.pi - np.mod(np.pi - a, 2.0 * np.pi))


def resolve_yaw(
    x: FloatArray,
    P: FloatArray,
    attrs: FloatArray,
    previous_yaw: FloatArray,
    previous_sign_known: NDBool,
    *,
    min_speed_mps: float,
    min_speed_sigmas: float,
) -> tuple[FloatArray, NDBool]:
    """Output yaw of N tracks: measured axis, sign from heading / motion / previous frame.

    Parameters
    ----------
    x, P : numpy.ndarray, shapes (N, 4) and (N, 4, 4)
        Kalman states [x, y, vx, vy] (m, m/s) and covariances.
    attrs : numpy.ndarray, shape (N, N_ATTRS)
        Smoothed track attributes (`shared.tracking.measurement`); NaN where never measured.
    previous_yaw : numpy.ndarray, shape (N,)
        Last resolved yaw, rad (NaN: unknown).
    previous_sign_known : numpy.ndarray of bool, shape (N,)
    min_speed_mps, min_speed_sigmas : float
        The velocity gives the sign only above this speed and this many standard deviations of it.

    Returns
    -------
    yaw : numpy.ndarray, shape (N,)
        In (-pi, pi] when the sign is known, else in (-pi/2, pi/2] (mod pi) or NaN (nothing known).
    sign_known : numpy.ndarray of bool, shape (N,)
    """
    vx, vy = x[:, VX], x[:, VY]
    speed = np.hypot(vx, vy)
    speed_std = np.sqrt(np.maximum(0.5 * (P[:, VX, VX] + P[:, VY, VY]), 0.0))
    moving = speed > np.maximum(min_speed_mps, min_speed_sigmas * speed_std)
    head, axis2 = attrs[:, HEAD], attrs[:, AXIS2]
    ref = np.where(
        ~np.isnan(head[:, COS]),
        np.arctan2(head[:, SIN], head[:, COS]),
        np.where(moving, np.arctan2(vy, vx), np.where(previous_sign_known, previous_yaw, np.nan)),
    )
    has_ref = ~np.isnan(ref)
    axis = 0.5 * np.arctan2(axis2[:, SIN], axis2[:, COS])  # (-pi/2, pi/2]; NaN if never measured
    flip = np.abs(wrap(np.where(has_ref, ref, 0.0) - axis)) > 0.5 * np.pi
    yaw = np.where(np.isnan(axis), ref, wrap(axis + np.pi * (flip & has_ref)))
    return np.asarray(yaw), np.asarray(has_ref)
