"""Rigid-body quadrotor dynamics, numpy backend.

``dynamics(x, u, p)`` is the nominal model shared by the simulator, the data
and the physics checks; :mod:`sim.equations.dynamics_casadi` is the same model written
for CasADi, held equal to this one by ``tests/test_dynamics.py``.
"""

from __future__ import annotations

import numpy as np

from .._validate import as_batch
from ..params import NU, NX, QuadParams


def dynamics(x, u, p: QuadParams | None = None) -> np.ndarray:
    """Time derivative of the state under the nominal model.

    Parameters
    ----------
    x : array_like, shape (..., 12)
        State ``[x, y, z, phi, theta, psi, p, q, r, vx, vy, vz]`` (m, rad,
        rad/s, m/s; NED world frame, ZYX Euler angles).
    u : array_like, shape (..., 4)
        Wrench ``[T, tau_x, tau_y, tau_z]`` (N, N m), broadcast against ``x``.
    p : QuadParams, optional
        Parameters; reference values when omitted.

    Returns
    -------
    numpy.ndarray, shape (..., 12)
        ``dx/dt`` in state order.

    Raises
    ------
    SimInputError
        If ``x`` or ``u`` has the wrong last axis or non-finite entries.
    """
    x = as_batch(x, "x", NX)
    u = as_batch(u, "u", NU)
    return rates(x, u, QuadParams() if p is None else p)


def rates(x: np.ndarray, u: np.ndarray, p: QuadParams, accel=None, torque=None) -> np.ndarray:
    """Unchecked :func:`dynamics` with optional extra terms (hot path).

    Parameters
    ----------
    x, u : numpy.ndarray
        As in :func:`dynamics`, already validated.
    p : QuadParams or object with the same attributes
        ``m`` may be an array broadcastable to ``x[..., 0]`` (payload studies).
    accel : numpy.ndarray, shape (..., 3), optional
        Extra world-frame acceleration (wind, rotor drag), m/s^2.
    torque : numpy.ndarray, shape (..., 3), optional
        Extra body-frame torque (rotor gyroscopic torque), N m.
    """
    phi, th, psi = x[..., 3], x[..., 4], x[..., 5]
    wp, wq, wr = x[..., 6], x[..., 7], x[..., 8]
    vx, vy, vz = x[..., 9], x[..., 10], x[..., 11]
    thrust, tx, ty, tz = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    if torque is not None:
        tx, ty, tz = tx + torque[..., 0], ty + torque[..., 1], tz + torque[..., 2]

    sphi, cphi = np.sin(phi), np.cos(phi)
    sth, cth = np.sin(th), np.cos(th)
    spsi, cpsi = np.sin(psi), np.cos(psi)

    # Euler-angle kinematics (ZYX).
    qs_rc = wq * sphi + wr * cphi
    phid = wp + qs_rc * (sth / cth)
    thd = wq * cphi - wr * sphi
    psid = qs_rc / cth

    # Euler's equations (paper Eq. 2).
    Jxx, Jyy, Jzz = p.Jxx, p.Jyy, p.Jzz
    pd = ((Jyy - Jzz) * wq * wr + tx) / Jxx
    qd = ((Jzz - Jxx) * wp * wr + ty) / Jyy
    rd = ((Jxx - Jyy) * wp * wq + tz) / Jzz

    # v' = g e3 - (T/m) R e3 - c_d v|v|, with R e3 the body z axis in the world frame.
    tm = thrust / p.m
    c_d = p.c_d
    ax = -tm * (cpsi * sth * cphi + spsi * sphi) - c_d * vx * np.abs(vx)
    ay = -tm * (spsi * sth * cphi - cpsi * sphi) - c_d * vy * np.abs(vy)
    az = p.g - tm * (cth * cphi) - c_d * vz * np.abs(vz)
    if accel is not None:
        ax, ay, az = ax + accel[..., 0], ay + accel[..., 1], az + accel[..., 2]

    return _columns((vx, vy, vz, phid, thd, psid, pd, qd, rd, ax, ay, az), x.shape[:-1])


def _columns(cols, shape) -> np.ndarray:
    """``np.stack(np.broadcast_arrays(*cols), axis=-1)``, written into one array when every column is float64 of
    ``shape`` (the usual case: a third of :func:`rates`'s time on a few states went to the general form)."""
    for c in cols:
        if getattr(c, "shape", None) != shape or getattr(c, "dtype", None) != np.float64:
            return np.stack(np.broadcast_arrays(*cols), axis=-1)
    out = np.empty(shape + (len(cols),))
    for i, c in enumerate(cols):
        out[..., i] = c
    return out


def rotation_matrix(phi, theta, psi) -> np.ndarray:
    """Body-to-world rotation R = Rz(psi) Ry(theta) Rx(phi), shape (..., 3, 3)."""
    sphi, cphi = np.sin(phi), np.cos(phi)
    sth, cth = np.sin(theta), np.cos(theta)
    spsi, cpsi = np.sin(psi), np.cos(psi)
    row0 = np.stack([cpsi * cth, cpsi * sth * sphi - spsi * cphi, cpsi * sth * cphi + spsi * sphi], axis=-1)
    row1 = np.stack([spsi * cth, spsi * sth * sphi + cpsi * cphi, spsi * sth * cphi - cpsi * sphi], axis=-1)
    row2 = np.stack([-sth, cth * sphi, cth * cphi], axis=-1)
    return np.stack([row0, row1, row2], axis=-2)


def rk4_step(f, x: np.ndarray, h: float, n: int = 1) -> np.ndarray:
    """Advance ``x' = f(x)`` by ``n`` classical RK4 steps of size ``h``.

    Parameters
    ----------
    f : callable
        ``f(x) -> dx/dt`` with the shape of ``x``.
    x : numpy.ndarray
        Initial value.
    h : float
        Step size, s.
    n : int
        Number of steps.
    """
    half = 0.5 * h
    sixth = h / 6.0
    for _ in range(n):
        k1 = f(x)
        k2 = f(x + half * k1)
        k3 = f(x + half * k2)
        k4 = f(x + h * k3)
        x = x + sixth * (k1 + 2.0 * (k2 + k3) + k4)
    return x
