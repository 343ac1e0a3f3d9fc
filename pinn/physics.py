"""Quadrotor dynamics, torch backend, for the physics losses.

The third backend of the nominal model, beside :mod:`sim.equations.dynamics` (numpy)
and :mod:`sim.equations.dynamics_casadi`; ``tests/test_pinn.py`` (``test_torch_dynamics_equals_numpy``) holds it equal
to the numpy one. Parameters ``theta = (m, Jxx, Jyy, Jzz, kt, kq)`` are
tensors so that the physics residual can be differentiated with respect to
them.
"""

from __future__ import annotations

import math

import torch

from sim.params import DT, SUBSTEPS, QuadParams
from sim.vehicles.rotors import mixer


def _inertia_differences(theta: torch.Tensor):
    """``(Jyy - Jzz, Jzz - Jxx, Jxx - Jyy)`` of ``theta`` (6,), each a 0-dim tensor of its dtype.

    Taken as one subtraction of 3-element slices: torch's TorchScript ONNX exporter computes an operation between
    two 0-dim tensors in float32, which would put a float32 rounding into a float64 export.
    """
    d = theta[[2, 3, 1]] - theta[[3, 1, 2]]
    return d[0], d[1], d[2]


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
    dJx, dJy, dJz = _inertia_differences(theta)

    sphi, cphi = torch.sin(phi), torch.cos(phi)
    sth, cth = torch.sin(th), torch.cos(th)
    spsi, cpsi = torch.sin(psi), torch.cos(psi)

    qs_rc = wq * sphi + wr * cphi
    phid = wp + qs_rc * (sth / cth)
    thd = wq * cphi - wr * sphi
    psid = qs_rc / cth

    pd = (dJx * wq * wr + tx) / Jxx
    qd = (dJy * wp * wr + ty) / Jyy
    rd = (dJz * wp * wq + tz) / Jzz

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
    # Constants as tensors of the state's dtype: the ONNX exporter would store Python floats as float32.
    def const(v):
        return torch.tensor(v, dtype=x.dtype, device=x.device)

    h, half, sixth, g, c_d = const(dt / substeps), const(0.5 * dt / substeps), const(dt / substeps / 6.0), \
        const(p.g), const(p.c_d)
    z = torch.zeros_like(x)
    for _ in range(substeps):
        s = x + z
        k1 = dynamics_torch(s, u, theta, g, c_d)
        k2 = dynamics_torch(s + half * k1, u, theta, g, c_d)
        k3 = dynamics_torch(s + half * k2, u, theta, g, c_d)
        k4 = dynamics_torch(s + h * k3, u, theta, g, c_d)
        z = z + sixth * (k1 + 2.0 * (k2 + k3) + k4)
    return z


def dynamics_tangent_torch(x: torch.Tensor, u: torch.Tensor, theta: torch.Tensor, g: float, c_d: float,
                           dx: torch.Tensor, du: torch.Tensor):
    """:func:`dynamics_torch` and its derivative along tangents (forward mode, plain tensor operations).

    Parameters
    ----------
    x, u, theta, g, c_d
        As in :func:`dynamics_torch`; ``x`` (B, 12), ``u`` (B, 4).
    dx : torch.Tensor, shape (B, 12, k)
        Tangent of the state: ``k`` directions.
    du : torch.Tensor, shape (B, 4, k)
        Tangent of the input along the same directions.

    Returns
    -------
    f : torch.Tensor, shape (B, 12)
        ``dx/dt``.
    df : torch.Tensor, shape (B, 12, k)
        Its derivative along each direction: ``(df/dx) dx + (df/du) du``.

    The partial derivatives are written out by hand so that the result exports to ONNX as a small graph (a
    dual-number or traced autograd version was an order of magnitude larger and slower to run);
    ``tests/test_pinn.py`` holds them equal to autograd of :func:`dynamics_torch`.
    """
    f = dynamics_torch(x, u, theta, g, c_d)
    phi, th, psi = x[..., 3:4], x[..., 4:5], x[..., 5:6]
    wp, wq, wr = x[..., 6:7], x[..., 7:8], x[..., 8:9]
    m, Jxx, Jyy, Jzz = theta[0], theta[1], theta[2], theta[3]
    dJx, dJy, dJz = _inertia_differences(theta)
    d = [dx[:, i] for i in range(12)]          # each (B, k)
    dT, dtx, dty, dtz = du[:, 0], du[:, 1], du[:, 2], du[:, 3]
    sphi, cphi = torch.sin(phi), torch.cos(phi)
    sth, cth = torch.sin(th), torch.cos(th)
    spsi, cpsi = torch.sin(psi), torch.cos(psi)
    tth, sec = sth / cth, 1.0 / cth
    qs_rc = wq * sphi + wr * cphi              # (B, 1)
    qc_rs = wq * cphi - wr * sphi
    dphi, dth, dpsi = d[3], d[4], d[5]
    # kinematics
    d_phid = d[6] + qc_rs * tth * dphi + qs_rc * sec * sec * dth + sphi * tth * d[7] + cphi * tth * d[8]
    d_thd = -qs_rc * dphi + cphi * d[7] - sphi * d[8]
    d_psid = qc_rs * sec * dphi + qs_rc * tth * sec * dth + sphi * sec * d[7] + cphi * sec * d[8]
    # Euler's equations
    d_pd = (dJx * (wr * d[7] + wq * d[8]) + dtx) / Jxx
    d_qd = (dJy * (wr * d[6] + wp * d[8]) + dty) / Jyy
    d_rd = (dJz * (wq * d[6] + wp * d[7]) + dtz) / Jzz
    # translation: a = -T/m b(phi, theta, psi) + g e_z - c_d v|v|
    tm = u[..., 0:1] / m
    bx = cpsi * sth * cphi + spsi * sphi
    by = spsi * sth * cphi - cpsi * sphi
    bz = cth * cphi
    bx_phi, bx_th, bx_psi = -cpsi * sth * sphi + spsi * cphi, cpsi * cth * cphi, -spsi * sth * cphi + cpsi * sphi
    by_phi, by_th, by_psi = -spsi * sth * sphi - cpsi * cphi, spsi * cth * cphi, cpsi * sth * cphi + spsi * sphi
    bz_phi, bz_th = -cth * sphi, -sth * cphi
    drag = -2.0 * (c_d * x[..., 9:12].abs())   # d(-c_d v|v|)/dv (c_d may be a 0-dim tensor: see _inertia_differences)
    d_ax = -(bx * dT / m + tm * (bx_phi * dphi + bx_th * dth + bx_psi * dpsi)) + drag[..., 0:1] * d[9]
    d_ay = -(by * dT / m + tm * (by_phi * dphi + by_th * dth + by_psi * dpsi)) + drag[..., 1:2] * d[10]
    d_az = -(bz * dT / m + tm * (bz_phi * dphi + bz_th * dth)) + drag[..., 2:3] * d[11]
    df = torch.stack([d[9], d[10], d[11], d_phid, d_thd, d_psid, d_pd, d_qd, d_rd, d_ax, d_ay, d_az], dim=1)
    return f, df


def rk4_increment_tangent(x: torch.Tensor, u: torch.Tensor, theta: torch.Tensor, g: float, c_d: float,
                          dt: float = DT, substeps: int = SUBSTEPS):
    """:func:`rk4_increment` and its exact Jacobians (the derivative of the discrete RK4 map, input held).

    Parameters
    ----------
    x : torch.Tensor, shape (B, 12)
    u : torch.Tensor, shape (B, 4)
    theta : torch.Tensor, shape (6,)
    g, c_d : float
        Gravity (m/s^2) and the quadratic drag coefficient (1/m).
    dt : float
        Period, s.
    substeps : int
        RK4 steps per period.

    Returns
    -------
    inc : torch.Tensor, shape (B, 12)
        ``x(t + dt) - x(t)``.
    A : torch.Tensor, shape (B, 12, 12)
        ``d inc / dx`` (the identity not included).
    B : torch.Tensor, shape (B, 12, 4)
        ``d inc / du``.
    """
    n = x.shape[0]
    # Constants as tensors of the state's dtype: the ONNX exporter stores Python floats as float32.
    h = torch.tensor(dt / substeps, dtype=x.dtype, device=x.device)
    g = torch.tensor(g, dtype=x.dtype, device=x.device)
    c_d = torch.tensor(c_d, dtype=x.dtype, device=x.device)
    eye = torch.eye(16, dtype=x.dtype, device=x.device).expand(n, 16, 16)
    du = eye[:, 12:]                           # the input is held: its tangent never changes
    z = torch.zeros_like(x)
    dz = torch.zeros(n, 12, 16, dtype=x.dtype, device=x.device)
    for _ in range(substeps):
        s, ds = x + z, eye[:, :12] + dz
        k1, d1 = dynamics_tangent_torch(s, u, theta, g, c_d, ds, du)
        k2, d2 = dynamics_tangent_torch(s + 0.5 * h * k1, u, theta, g, c_d, ds + 0.5 * h * d1, du)
        k3, d3 = dynamics_tangent_torch(s + 0.5 * h * k2, u, theta, g, c_d, ds + 0.5 * h * d2, du)
        k4, d4 = dynamics_tangent_torch(s + h * k3, u, theta, g, c_d, ds + h * d3, du)
        z = z + h * (k1 + 2.0 * (k2 + k3) + k4) / 6.0
        dz = dz + h * (d1 + 2.0 * (d2 + d3) + d4) / 6.0
    return z, dz[..., :12], dz[..., 12:]


def mixer_torch(theta: torch.Tensor, p: QuadParams) -> torch.Tensor:
    """Mixer ``M`` (4, 4) with ``wrench = M n^2``, from ``kt, kq`` of ``theta`` (see :mod:`sim.vehicles.rotors`)."""
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


def rotor_command_torch(u: torch.Tensor, theta: torch.Tensor, consts: dict):
    """Rotor speeds (..., 4, RU) the rotor layer commands for the wrench ``u`` (..., 4), and where they are unclipped.

    ``n_i^2`` of the allocation ``M(kt, kq)^-1 u`` clipped to ``[1e-9 n_max_sq, n_max_sq]``, as
    :func:`sim.equations.dynamics_casadi.rotor_command_casadi`. ``consts``: ``mixer_unit`` (the mixer with ``kt = kq =
    1``)
    and its inverse ``mixer_unit_inv``, and ``n_max_sq``, tensors of ``u``'s dtype.
    """
    S0_inv, n_max_sq = consts["mixer_unit_inv"], consts["n_max_sq"]
    scale = torch.stack([theta[4], theta[4], theta[4], theta[5]])          # M = diag(kt, kt, kt, kq) S0
    n_sq_cmd = (u / scale) @ S0_inv.T
    lo = n_max_sq * 1e-9
    free = (n_sq_cmd > lo) & (n_sq_cmd < n_max_sq)
    return torch.sqrt(torch.clamp(n_sq_cmd, min=lo, max=n_max_sq)), free


def lagged_rotor_increment(x: torch.Tensor, n: torch.Tensor, u: torch.Tensor, theta: torch.Tensor,
                           tau: torch.Tensor, consts: dict, dt: float = DT, substeps: int = 1,
                           tangent: bool = False, aero: dict | None = None):
    """One period of the rigid body driven by four lagging rotors (the motor-lag model), and optionally its Jacobians.

    The rotor speeds ``n`` follow the rotor command ``c = sqrt(M(kt, kq)^-1 u)`` (each ``n_i^2`` clipped to the
    rotor limits, as the plant does) through a first-order lag of time constant ``tau``, solved exactly over the
    period with the command held: ``n(t) = c + (n - c) exp(-t / tau)``. The rigid body is integrated by RK4 with
    the wrench ``M(kt, kq) n(t)^2`` at each stage's time. Equal to
    :func:`sim.identification.motor_lag.rotor_trajectory` for the
    rotors (``tests/test_pinn.py``).

    Parameters
    ----------
    x : torch.Tensor, shape (B, 12)
        Rigid-body state.
    n : torch.Tensor, shape (B, 4)
        Rotor speeds at the start of the period, RU.
    u : torch.Tensor, shape (B, 4)
        Commanded wrench, N and N m.
    theta : torch.Tensor, shape (6,)
        ``(m, Jxx, Jyy, Jzz, kt, kq)``.
    tau : torch.Tensor, scalar
        Motor time constant, s.
    consts : dict
        ``g`` (m/s^2), ``c_d`` (1/m), ``mixer_unit`` (4, 4) the mixer with ``kt = kq = 1`` (the arm included)
        and its inverse ``mixer_unit_inv``, ``n_max_sq`` (RU^2): tensors of the state's dtype.
    dt : float
        Period, s.
    substeps : int
        RK4 steps of the rigid body per period.
    tangent : bool
        Also return the Jacobians.
    aero : dict, optional
        Aerodynamic terms (:mod:`sim.identification.aero`, name -> coefficients) added to the rigid body's
        acceleration at every RK4 stage, with that stage's rotor speeds and thrust (:func:`aero_acceleration`).

    Returns
    -------
    inc_x : torch.Tensor, shape (B, 12)
    inc_n : torch.Tensor, shape (B, 4)
        Increments over the period.
    A : torch.Tensor, shape (B, 16, 16)
        ``d (inc_x, inc_n) / d (x, n)`` (only with ``tangent``; the identity not included).
    B : torch.Tensor, shape (B, 16, 4)
        ``d (inc_x, inc_n) / du`` (only with ``tangent``).
    """
    g, c_d, S0 = consts["g"], consts["c_d"], consts["mixer_unit"]
    c, free = rotor_command_torch(u, theta, consts)
    scale = torch.stack([theta[4], theta[4], theta[4], theta[5]])
    S0_inv = consts["mixer_unit_inv"]
    h_s = dt / substeps
    h = torch.tensor(h_s, dtype=x.dtype, device=x.device)
    sixth = torch.tensor(1.0 / 6.0, dtype=x.dtype, device=x.device)

    tau_1 = tau.reshape(1)

    def rotors(t: float):
        # exp(-t / tau), shape (1,). The time (s) is a constant of the state's dtype and both operands have one
        # element, not none: torch's TorchScript ONNX exporter computes arithmetic between 0-dim tensors in float32.
        return torch.exp(torch.tensor([-t], dtype=x.dtype, device=x.device) / tau_1)

    def wrench(nt):
        return (nt * nt) @ S0.T * scale

    def rates(s, j):
        # the rigid body's rates at stage j (rotor speeds ns[j], wrench ws[j]), plus the aerodynamic terms
        f = dynamics_torch(s, ws[j], theta, g, c_d)
        if not aero:
            return f
        a = aero_acceleration(s, aero, ns[j].sum(-1), ws[j][..., 0] / theta[0])
        return torch.cat([f[..., :9], f[..., 9:] + a], dim=-1)

    def rates_tangent(s, j, ds):
        f, df = dynamics_tangent_torch(s, ws[j], theta, g, c_d, ds, dws[j])
        if not aero:
            return f, df
        a, da = aero_acceleration_tangent(s, aero, ns[j].sum(-1), ws[j][..., 0] / theta[0], ds, dns[j].sum(1),
                                          dws[j][:, 0] / theta[0])
        return torch.cat([f[..., :9], f[..., 9:] + a], dim=-1), torch.cat([df[:, :9], df[:, 9:] + da], dim=1)

    B_ = x.shape[0]
    if tangent:
        k = 16 + 4
        eye = torch.eye(k, dtype=x.dtype, device=x.device).expand(B_, k, k)
        dx0, dn0, du = eye[:, :12], eye[:, 12:16], eye[:, 16:]
        # dc/du = diag(free / (2 c)) S0^-1 diag(1 / scale)
        dc = torch.where(free, 0.5 / c, torch.zeros_like(c)).unsqueeze(-1) * \
            torch.matmul(S0_inv / scale, du)                                 # (B, 4, k)
    z = torch.zeros_like(x)
    dz = torch.zeros(B_, 12, 20, dtype=x.dtype, device=x.device) if tangent else None
    for i in range(substeps):
        t0 = h_s * i
        times = (t0, t0 + 0.5 * h_s, t0 + 0.5 * h_s, t0 + h_s)
        a = [rotors(t) for t in times]
        ns = [c + (n - c) * ai for ai in a]
        ws = [wrench(nt) for nt in ns]
        if tangent:
            dns = [dc * (1.0 - ai) + dn0 * ai for ai in a]
            dws = [torch.matmul(S0 * scale.unsqueeze(-1), 2.0 * nt.unsqueeze(-1) * dnt) for nt, dnt in zip(ns, dns)]
        s = x + z
        if tangent:
            ds = dx0 + dz
            k1, d1 = rates_tangent(s, 0, ds)
            k2, d2 = rates_tangent(s + 0.5 * h * k1, 1, ds + 0.5 * h * d1)
            k3, d3 = rates_tangent(s + 0.5 * h * k2, 2, ds + 0.5 * h * d2)
            k4, d4 = rates_tangent(s + h * k3, 3, ds + h * d3)
            dz = dz + h * sixth * (d1 + 2.0 * (d2 + d3) + d4)
        else:
            k1 = rates(s, 0)
            k2 = rates(s + 0.5 * h * k1, 1)
            k3 = rates(s + 0.5 * h * k2, 2)
            k4 = rates(s + h * k3, 3)
        z = z + h * sixth * (k1 + 2.0 * (k2 + k3) + k4)
    a_end = rotors(h_s * substeps)
    inc_n = (c - n) * (1.0 - a_end)
    if not tangent:
        return z, inc_n
    d_inc_n = (dc - dn0) * (1.0 - a_end)
    J = torch.cat([dz, d_inc_n], dim=1)                                       # (B, 16, 20)
    return z, inc_n, J[..., :16], J[..., 16:]


def rotation_torch(e: torch.Tensor) -> torch.Tensor:
    """Body-to-world rotation of ZYX Euler angles ``e`` (B, 3) as (B, 3, 3), as
    :func:`sim.equations.dynamics.rotation_matrix`."""
    sphi, cphi = torch.sin(e[:, 0]), torch.cos(e[:, 0])
    sth, cth = torch.sin(e[:, 1]), torch.cos(e[:, 1])
    spsi, cpsi = torch.sin(e[:, 2]), torch.cos(e[:, 2])
    row0 = torch.stack([cpsi * cth, cpsi * sth * sphi - spsi * cphi, cpsi * sth * cphi + spsi * sphi], -1)
    row1 = torch.stack([spsi * cth, spsi * sth * sphi + cpsi * cphi, spsi * sth * cphi - cpsi * sphi], -1)
    row2 = torch.stack([-sth, cth * sphi, cth * cphi], -1)
    return torch.stack([row0, row1, row2], -2)


def rotation_tangent(e: torch.Tensor, de: torch.Tensor) -> torch.Tensor:
    """The small body-frame rotation (B, 3, k) that the Euler-angle tangent ``de`` (B, 3, k) makes at the ZYX angles
    ``e`` (B, 3): ``d R(e) = R(e) [dth]_x`` with ``dth = E(e) de``, ``E`` the map from Euler rates to body rates."""
    sphi, cphi = torch.sin(e[:, 0])[:, None], torch.cos(e[:, 0])[:, None]
    sth, cth = torch.sin(e[:, 1])[:, None], torch.cos(e[:, 1])[:, None]
    return torch.stack([de[:, 0] - sth * de[:, 2], cphi * de[:, 1] + (cth * sphi) * de[:, 2],
                        (cth * cphi) * de[:, 2] - sphi * de[:, 1]], 1)


def cross_columns(a: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """``a x t`` for every column ``t`` of ``T`` (B, 3, k), ``a`` (B, 3)."""
    return a[:, [1, 2, 0], None] * T[:, [2, 0, 1]] - a[:, [2, 0, 1], None] * T[:, [1, 2, 0]]


def aero_acceleration(x: torch.Tensor, terms: dict, rotor_sum: torch.Tensor, thrust_m: torch.Tensor) -> torch.Tensor:
    """NED acceleration (B, 3), m/s^2, of the aerodynamic terms ``terms`` (:mod:`sim.identification.aero`: name ->
    coefficients) at the states ``x`` (B, >= 12), the rotor speeds' sum ``rotor_sum`` (B,) RU and the thrust over
    the mass ``thrust_m`` (B,) m/s^2. The terms act in the body frame: ``a = R a_b(R^T v)``."""
    from sim.identification.aero import term_acceleration

    R = rotation_torch(x[:, 3:6])
    v_b = (R.transpose(-1, -2) @ x[..., 9:12].unsqueeze(-1)).squeeze(-1)
    a_b = torch.stack(term_acceleration(terms, v_b, rotor_sum, thrust_m), dim=-1)
    return (R @ a_b.unsqueeze(-1)).squeeze(-1)


def aero_acceleration_tangent(x: torch.Tensor, terms: dict, rotor_sum: torch.Tensor, thrust_m: torch.Tensor,
                              dx: torch.Tensor, d_sum: torch.Tensor, d_thrust: torch.Tensor):
    """:func:`aero_acceleration` (B, 3) and its derivative along tangents (B, 3, k): ``dx`` (B, 12, k) of the
    state, ``d_sum`` (B, k) of the rotor speeds' sum and ``d_thrust`` (B, k) of the thrust over the mass.
    Written out by hand (plain tensor operations, for the ONNX export); ``tests/test_aero_physics.py`` holds it to
    autograd. With ``d R = R [dth]_x`` (:func:`rotation_tangent`): ``d v_b = R^T dv - dth x v_b`` and
    ``d a = R (d a_b + dth x a_b)``."""
    from sim.identification.aero import term_acceleration_tangent

    R = rotation_torch(x[:, 3:6])
    dth = rotation_tangent(x[:, 3:6], dx[:, 3:6])                           # (B, 3, k)
    v_b = (R.transpose(1, 2) @ x[:, 9:12].unsqueeze(-1)).squeeze(-1)
    dv_b = R.transpose(1, 2) @ dx[:, 9:12] + cross_columns(v_b, dth)
    a_b, da_b = term_acceleration_tangent(terms, v_b, rotor_sum, thrust_m, dv_b, d_sum, d_thrust)
    a_b = torch.stack(a_b, dim=-1)                                          # (B, 3)
    da = R @ (torch.stack(da_b, dim=-2) - cross_columns(a_b, dth))          # (B, 3, k)
    return (R @ a_b.unsqueeze(-1)).squeeze(-1), da
