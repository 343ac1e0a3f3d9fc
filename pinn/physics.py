"""Quadrotor dynamics, torch backend, for the physics losses.

The third backend of the nominal model, beside :mod:`sim.dynamics` (numpy)
and :mod:`sim.dynamics_casadi`; ``tests/test_pinn.py`` (``test_torch_dynamics_equals_numpy``) holds it equal
to the numpy one. Parameters ``theta = (m, Jxx, Jyy, Jzz, kt, kq)`` are
tensors so that the physics residual can be differentiated with respect to
them.
"""

from __future__ import annotations

import math

import torch

from sim.params import DT, SUBSTEPS, QuadParams
from sim.rotors import mixer


def dynamics_torch(x: torch.Tensor, u: torch.Tensor, theta: torch.Tensor, g: float, c_d: float) -> torch.Tensor:
    """``dx/dt`` of the nominal model.

    Parameters
    ----------
    x : torch.Tensor, shape (..., 12)
        State (m, rad, rad/s, m/s; NED, ZYX Euler angles).
    u : torch.Tensor, shape (..., 4)
        Wrench ``[T, tau_x, tau_y, tau_z]``, N and N m.
    theta : torch.Tensor, shape (6,)
        ``(m, Jxx, Jyy, Jzz, kt, kq)``; only the first four enter.
    g : float
        Gravity, m/s^2.
    c_d : float
        Quadratic drag coefficient, 1/m.
    """
    phi, th, psi = x[..., 3], x[..., 4], x[..., 5]
    wp, wq, wr = x[..., 6], x[..., 7], x[..., 8]
    vx, vy, vz = x[..., 9], x[..., 10], x[..., 11]
    thrust, tx, ty, tz = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    m, Jxx, Jyy, Jzz = theta[0], theta[1], theta[2], theta[3]

    sphi, cphi = torch.sin(phi), torch.cos(phi)
    sth, cth = torch.sin(th), torch.cos(th)
    spsi, cpsi = torch.sin(psi), torch.cos(psi)

    qs_rc = wq * sphi + wr * cphi
    phid = wp + qs_rc * (sth / cth)
    thd = wq * cphi - wr * sphi
    psid = qs_rc / cth

    pd = ((Jyy - Jzz) * wq * wr + tx) / Jxx
    qd = ((Jzz - Jxx) * wp * wr + ty) / Jyy
    rd = ((Jxx - Jyy) * wp * wq + tz) / Jzz

    tm = thrust / m
    ax = -tm * (cpsi * sth * cphi + spsi * sphi) - c_d * vx * vx.abs()
    ay = -tm * (spsi * sth * cphi - cpsi * sphi) - c_d * vy * vy.abs()
    az = g - tm * (cth * cphi) - c_d * vz * vz.abs()
    return torch.stack([vx, vy, vz, phid, thd, psid, pd, qd, rd, ax, ay, az], dim=-1)


def rk4_increment(x: torch.Tensor, u: torch.Tensor, theta: torch.Tensor, p: QuadParams,
                  dt: float = DT, substeps: int = SUBSTEPS) -> torch.Tensor:
    """``x(t + dt) - x(t)`` by RK4 with ``substeps`` steps, input held.

    Returned as an increment (accumulated without forming ``x + dx``) so
    that the small increments of large states keep their float32 precision.
    """
    h = dt / substeps
    z = torch.zeros_like(x)
    for _ in range(substeps):
        s = x + z
        k1 = dynamics_torch(s, u, theta, p.g, p.c_d)
        k2 = dynamics_torch(s + 0.5 * h * k1, u, theta, p.g, p.c_d)
        k3 = dynamics_torch(s + 0.5 * h * k2, u, theta, p.g, p.c_d)
        k4 = dynamics_torch(s + h * k3, u, theta, p.g, p.c_d)
        z = z + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    return z


def mixer_torch(theta: torch.Tensor, p: QuadParams) -> torch.Tensor:
    """Mixer ``M`` (4, 4) with ``wrench = M n^2``, from ``kt, kq`` of ``theta`` (see :mod:`sim.rotors`)."""
    return torch.stack([torch.stack(list(row)) for row in mixer(theta[4], theta[5], p.d / math.sqrt(2.0))])


def rotor_sq_from_wrench(w: torch.Tensor, theta: torch.Tensor, p: QuadParams) -> torch.Tensor:
    """Rotor speeds squared (..., 4), RU^2, that ``kt, kq`` of ``theta`` allocate for wrench ``w`` (..., 4)."""
    return w @ torch.linalg.inv(mixer_torch(theta, p)).T


def mechanical_energy(x: torch.Tensor, theta: torch.Tensor, g: float) -> torch.Tensor:
    """Kinetic plus potential energy (..., ), J: 1/2 m |v|^2 + 1/2 w^T J w - m g z (NED)."""
    m, J = theta[0], theta[1:4]
    return 0.5 * m * (x[..., 9:12] ** 2).sum(-1) + 0.5 * (J * x[..., 6:9] ** 2).sum(-1) - m * g * x[..., 2]


def power_balance(x: torch.Tensor, u: torch.Tensor, theta: torch.Tensor, g: float, c_d: float) -> torch.Tensor:
    """``P_thrust + P_torque - P_drag`` (..., ), W: the rate of change of :func:`mechanical_energy`.

    ``P_thrust = -T v . b`` (b the body z axis in the world frame),
    ``P_torque = w . tau`` and ``P_drag = m c_d sum |v_i|^3`` (paper Eq. 12).
    """
    phi, th, psi = x[..., 3], x[..., 4], x[..., 5]
    sphi, cphi = torch.sin(phi), torch.cos(phi)
    sth, cth = torch.sin(th), torch.cos(th)
    spsi, cpsi = torch.sin(psi), torch.cos(psi)
    b = torch.stack([cpsi * sth * cphi + spsi * sphi, spsi * sth * cphi - cpsi * sphi, cth * cphi], dim=-1)
    v = x[..., 9:12]
    p_thrust = -u[..., 0] * (v * b).sum(-1)
    p_torque = (x[..., 6:9] * u[..., 1:4]).sum(-1)
    p_drag = theta[0] * c_d * (v.abs() ** 3).sum(-1)
    return p_thrust + p_torque - p_drag
