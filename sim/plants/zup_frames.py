"""Our frames against those of the simulators that are z-up with a forward-left-up body (RotorPy, drone-models,
crazyflow).

Ours are NED and FRD with ZYX Euler angles. With ``F = diag(1, -1, -1)`` (a half turn about x) every vector converts
as ``F v`` in both frames (position, velocity, body rates, torques, a wind's acceleration), the attitude as
``R_zup = F R F = Rz(-psi) Ry(-theta) Rx(phi)`` (so the ZYX angles of the z-up attitude are ``(phi, -theta, -psi)``),
and a thrust is unchanged. Quaternions are (x, y, z, w).
"""

from __future__ import annotations

import math

import numpy as np

#: The frame flip ``diag(F)``: NED <-> z-up world, FRD <-> FLU body.
FLIP = np.array([1.0, -1.0, -1.0])


def quat_from_euler(phi: float, theta: float, psi: float) -> np.ndarray:
    """The z-up/FLU quaternion (xyzw) of our ZYX Euler angles: ``R_zup = F R F = Rz(-psi) Ry(-theta) Rx(phi)``."""
    cr, sr = math.cos(0.5 * phi), math.sin(0.5 * phi)
    cp, sp = math.cos(-0.5 * theta), math.sin(-0.5 * theta)
    cy, sy = math.cos(-0.5 * psi), math.sin(-0.5 * psi)
    return np.array([sr * cp * cy - cr * sp * sy,
                     cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy,
                     cr * cp * cy + sr * sp * sy])


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """Our ZYX Euler angles (phi, theta, psi) of a z-up/FLU quaternion (xyzw), |theta| <= pi/2, others in [-pi, pi]."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    # Rotation matrix of the z-up/FLU attitude; ours is F R F: R[i, j] * F_i * F_j.
    r00 = 1.0 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + z * w)
    r20 = 2.0 * (x * z - y * w)
    r21 = 2.0 * (y * z + x * w)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    # Ours: R00 = r00, R10 = -r10, R20 = -r20, R21 = r21, R22 = r22.
    phi = math.atan2(r21, r22)
    theta = math.atan2(r20, math.hypot(r21, r22))
    psi = math.atan2(-r10, r00)
    return np.array([phi, theta, psi])


def unwrap_euler(angles, previous) -> np.ndarray:
    """The ZYX Euler angles of the attitude ``angles`` (3,) nearest to ``previous`` (3,), rad.

    Both representations of one attitude, ``(phi, theta, psi)`` and ``(phi + pi, pi - theta, psi + pi)``, are
    shifted by whole turns towards ``previous``; the nearer one is returned, so angles integrated through +-pi
    (and beyond) stay continuous.
    """
    a = np.asarray(angles, dtype=float)
    prev = np.asarray(previous, dtype=float)
    best, best_d = None, math.inf
    for cand in (a, np.array([a[0] + math.pi, math.pi - a[1], a[2] + math.pi])):
        shifted = cand + 2.0 * math.pi * np.round((prev - cand) / (2.0 * math.pi))
        dist = float(np.sum((shifted - prev) ** 2))
        if dist < best_d:
            best, best_d = shifted, dist
    return best
