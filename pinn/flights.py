"""Learned models of imported flight logs: the identified physics with the body rates held, plus a network.

A real log's rotor speeds explain little of the vehicle's angular acceleration, so the physics this model
starts from is the one that predicts real flights best over half a second: the identified rigid body with the
body rates held (``sim.flightlogs.logbench.physics_step`` with ``hold_rates``, its drags and biases), or the same
rigid body with its rates under the fitted onboard attitude loop (:class:`AttitudeLoopPhysics`, whose held
setpoint is four extra states of its own). A network adds what that physics misses, to the body rates and to the
velocity (in the body frame, so that the model does not depend on the heading)::

    x_next = Phi(x, u) + (0, 0, s_w NN_w(f), R(x) s_v NN_v(f))

with ``f`` the normalized roll, pitch, body rates, body-frame velocity, wrench and, for a model with history,
a register of the last ``H`` wrenches and body rates. That register is the model's extra state (the model
contract's shift register): it names ``u{k}_T``, ``u{k}_tx`` ... and ``p{k}``, ``q{k}``, ``r{k}`` for ``k`` =
1 .. H periods back, and shifts exactly.

Training fits the network to open-loop rollouts of the training flights (windows of 5, 10, 25, then 50 steps),
weighting the errors as the benchmark's table does: position, velocity, rotation and body rates, each over its
goal (0.07 m, 0.40 m/s, 0.15 rad, 0.40 rad/s). States a log did not measure are neither targets nor inputs.
Each epoch's model is scored on the validation flights (the mean of the four h=50 errors over their goals) and
the best epoch is kept: the test flights are never seen.

:func:`export_flight_model` writes the model file and, for a model with a network, its derivative graph:
``forward_jacobian`` gives the exact ``dx_next/dx`` and ``dx_next/du`` (forward-mode tangents through the physics'
RK4 stages, the network's layers and the register's shift), with plain tensor operations that export to ONNX.

The wrench the model takes is the identified one: the logged wrench (computed with the vehicle file's ``kt``)
times the identification's ``wrench_gain``, so that a controller flying the model on a plant set up with the
identified vehicle means the same thrust and torques.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from sim.flightlogs.attitudeloop import EXTRA_STATES, NOT_FLYABLE, AttitudeLoop
from sim.flightlogs.logbench import GOAL_H50 as GOALS, goal_score as score
from sim.flightlogs.logident import LOOP_SUBSTEPS
from sim.params import DT

from .physics import cross_columns, rotation_tangent, rotation_torch


HORIZONS = (5, 10, 25, 50)
PHYSICS_SUBSTEPS = 1


class HeldRatesPhysics(nn.Module):
    """:func:`sim.flightlogs.logbench.physics_step` with ``hold_rates=True`` in torch (RK4, :data:`PHYSICS_SUBSTEPS`
    substeps).

    Parameters
    ----------
    m, g, c_d : float
        Mass (kg), gravity (m/s^2) and the world-frame quadratic drag (1/m) of the rigid-body equations.
    linear_drag, quadratic_drag, accel_bias : sequence of 3 float
        Body-frame drags (1/s, 1/m) and acceleration bias (m/s^2).
    """

    level = "wrench"
    corrects_rates = True      # a network beside it corrects the body rates too (this physics holds them)
    extra_states: tuple[str, ...] = ()      # states of its own after the rigid body's (none)
    not_flyable = ""           # why a model on this physics cannot be flown, if it cannot whatever its network
    substeps = PHYSICS_SUBSTEPS  # RK4 substeps a period

    def __init__(self, m: float, g: float, c_d: float, linear_drag, quadratic_drag, accel_bias):
        super().__init__()
        self.register_buffer("consts", torch.tensor([m, g, c_d], dtype=torch.float64))
        self.register_buffer("drag", torch.tensor(np.array([linear_drag, quadratic_drag, accel_bias], dtype=float)))

    def rates(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """dx/dt (B, 12) with the body rates held."""
        c = self.consts.to(x.dtype)
        k, q, b = self.drag.to(x.dtype)
        phi, th = x[:, 3], x[:, 4]
        wp, wq, wr = x[:, 6], x[:, 7], x[:, 8]
        sphi, cphi, sth, cth = torch.sin(phi), torch.cos(phi), torch.sin(th), torch.cos(th)
        qs_rc = wq * sphi + wr * cphi
        R = rotation_torch(x[:, 3:6])
        v = x[:, 9:12]
        vb = torch.einsum("nji,nj->ni", R, v)
        a = torch.einsum("nij,nj->ni", R, -k * vb - q * vb * vb.abs() + b)
        a = a - (u[:, 0] / c[0])[:, None] * R[:, :, 2] - c[2] * v * v.abs()
        a = a + torch.stack([torch.zeros_like(phi), torch.zeros_like(phi), c[1].expand_as(phi)], -1)
        zero = torch.zeros_like(x[:, 6:9])
        return torch.cat([v, torch.stack([wp + qs_rc * sth / cth, wq * cphi - wr * sphi, qs_rc / cth], -1), zero, a],
                         -1)

    def rates_tangent(self, x: torch.Tensor, u: torch.Tensor, dx: torch.Tensor, du: torch.Tensor):
        """:meth:`rates` (B, 12), the same values, and its tangent (B, 12, k) along the tangents ``dx`` (B, 12, k)
        of the state and ``du`` (B, 4, k) of the input. The drags' ``v |v|`` has the derivative ``2 |v|``."""
        c = self.consts.to(x.dtype)
        k, q, b = self.drag.to(x.dtype)
        phi, th = x[:, 3], x[:, 4]
        wq, wr = x[:, 7], x[:, 8]
        sphi, cphi, sth, cth = torch.sin(phi), torch.cos(phi), torch.sin(th), torch.cos(th)
        qs_rc = wq * sphi + wr * cphi
        R = rotation_torch(x[:, 3:6])
        v = x[:, 9:12]
        vb = torch.einsum("nji,nj->ni", R, v)
        w = -k * vb - q * vb * vb.abs() + b
        # the Euler angles' rates
        d_phi, d_th = dx[:, 3], dx[:, 4]
        d_qs = dx[:, 7] * sphi[:, None] + dx[:, 8] * cphi[:, None] + (wq * cphi - wr * sphi)[:, None] * d_phi
        sec2 = 1.0 / (cth * cth)
        d_euler = torch.stack([dx[:, 6] + d_qs * (sth / cth)[:, None] + (qs_rc * sec2)[:, None] * d_th,
                               dx[:, 7] * cphi[:, None] - dx[:, 8] * sphi[:, None] - qs_rc[:, None] * d_phi,
                               d_qs / cth[:, None] + (qs_rc * sth * sec2)[:, None] * d_th], 1)
        # the acceleration R (w - T/m e_z) - c_d v |v| + g e_z, with dR = R [dth]_x
        dth = rotation_tangent(x[:, 3:6], dx[:, 3:6])
        dv = dx[:, 9:12]
        d_vb = cross_columns(vb, dth) + torch.matmul(R.transpose(1, 2), dv)
        d_w = -(k + q * vb.abs() * 2.0)[:, :, None] * d_vb
        e_z = torch.eye(3, dtype=x.dtype, device=x.device)[2]
        f_b = w - (u[:, 0] / c[0])[:, None] * e_z
        d_fb = d_w - cross_columns(f_b, dth) - (du[:, 0] / c[0])[:, None, :] * e_z[:, None]
        d_a = torch.matmul(R, d_fb) - (v.abs() * c[2] * 2.0)[:, :, None] * dv
        # (this class's rates, not a subclass's: the tangent is of the rigid body's 12 states)
        return HeldRatesPhysics.rates(self, x, u), torch.cat([dv, d_euler, torch.zeros_like(dx[:, 6:9]), d_a], 1)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The state one period later (B, 12 + E)."""
        return _rk4(lambda z: self.rates(z, u), x, self.substeps)

    def forward_tangent(self, x: torch.Tensor, u: torch.Tensor, dx: torch.Tensor, du: torch.Tensor):
        """:meth:`forward` (B, 12 + E), the same values, and its tangent (B, 12 + E, k) along ``dx`` (B, 12 + E, k)
        and ``du`` (B, 4, k)."""
        return _rk4_tangent(lambda z, dz: self.rates_tangent(z, u, dz, du), x, dx, self.substeps)

    def start(self, x: np.ndarray) -> np.ndarray:
        """The :attr:`extra_states` (B, E) at window starts ``x`` (B, 12) of a log: none here."""
        return np.zeros((len(x), len(self.extra_states)))

    def forward_jacobian(self, x: torch.Tensor, u: torch.Tensor):
        """Next state (B, n), ``A = dx_next/dx`` (B, n, n) and ``B = dx_next/du`` (B, n, 4), with ``n = 12 + E``
        (:attr:`extra_states`).

        Exact (forward-mode tangents through every RK4 stage), written with plain tensor operations so that it
        exports to ONNX with a dynamic batch; ``x_next`` is :meth:`forward`'s, bit for bit.
        """
        n = 12 + len(self.extra_states)
        eye = torch.eye(n + 4, dtype=x.dtype, device=x.device).expand(x.shape[0], n + 4, n + 4)
        nxt, d = self.forward_tangent(x, u, eye[:, :n], eye[:, n:])
        return nxt, d[..., :n], d[..., n:]


def _check_substeps(substeps) -> None:
    """Refuse RK4 substeps that are not an integer >= 1."""
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1; found {substeps!r}")


def _rk4(f, x: torch.Tensor, substeps: int) -> torch.Tensor:
    """``x`` advanced over one period ``DT`` by ``substeps`` classical RK4 steps of ``x' = f(x)``."""
    h = DT / substeps
    for _ in range(substeps):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        k4 = f(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    return x


def _rk4_tangent(f, x: torch.Tensor, dx: torch.Tensor, substeps: int):
    """:func:`_rk4` (the same values) carrying the tangent ``dx`` (B, n, k): ``f(x, dx)`` gives ``x'`` and its
    tangent. Returns ``(x, dx)`` after one period."""
    h = DT / substeps
    for _ in range(substeps):
        k1, d1 = f(x, dx)
        k2, d2 = f(x + 0.5 * h * k1, dx + 0.5 * h * d1)
        k3, d3 = f(x + 0.5 * h * k2, dx + 0.5 * h * d2)
        k4, d4 = f(x + h * k3, dx + h * d3)
        x = x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        dx = dx + (h / 6.0) * (d1 + 2.0 * (d2 + d3) + d4)
    return x, dx


class CtbrPhysics(HeldRatesPhysics):
    """:func:`sim.flightlogs.logbench.ctbr_physics_step` in torch: the translational equations of
    :class:`HeldRatesPhysics` with the thrust scaled by ``thrust_gain``, and the body rates moving from the state's to
    the input's (the rates reached at the period's end) at a constant angular acceleration. ``u`` is
    ``(T, p_cmd, q_cmd, r_cmd)`` (N, rad/s), the ``ctbr`` level's input. RK4 with ``substeps`` substeps.
    """

    extra_states: tuple[str, ...] = ()      # the rigid body's state only (as a FlightModel without history)
    level = "ctbr"
    corrects_rates = False     # its input is the rates reached: the next rates are the input's

    def __init__(self, m: float, g: float, c_d: float, linear_drag, quadratic_drag, accel_bias,
                 thrust_gain: float = 1.0, substeps: int = 10):
        super().__init__(m, g, c_d, linear_drag, quadratic_drag, accel_bias)
        self.register_buffer("gain", torch.tensor(float(thrust_gain), dtype=torch.float64))
        self.substeps = int(substeps)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The state one period later (B, 12)."""
        alpha = (u[:, 1:4] - x[:, 6:9]) / DT
        thrust = torch.cat([u[:, :1] * self.gain.to(x.dtype), torch.zeros_like(u[:, 1:])], -1)

        def f(z):
            d = self.rates(z, thrust)
            return torch.cat([d[:, :6], alpha, d[:, 9:]], -1)

        return _rk4(f, x, self.substeps)

    def forward_tangent(self, x: torch.Tensor, u: torch.Tensor, dx: torch.Tensor, du: torch.Tensor):
        """:meth:`forward` (B, 12), the same values, and its tangent (B, 12, k) along ``dx`` (B, 12, k) and ``du``
        (B, 4, k)."""
        alpha = (u[:, 1:4] - x[:, 6:9]) / DT
        d_alpha = (du[:, 1:4] - dx[:, 6:9]) / DT
        gain = self.gain.to(x.dtype)
        thrust = torch.cat([u[:, :1] * gain, torch.zeros_like(u[:, 1:])], -1)
        d_thrust = torch.cat([du[:, :1] * gain, torch.zeros_like(du[:, 1:])], 1)

        def f(z, dz):
            d, dd = self.rates_tangent(z, thrust, dz, d_thrust)
            return torch.cat([d[:, :6], alpha, d[:, 9:]], -1), torch.cat([dd[:, :6], d_alpha, dd[:, 9:]], 1)

        return _rk4_tangent(f, x, dx, self.substeps)


class LaggedCtbrPhysics(HeldRatesPhysics):
    """The ``ctbr`` level's nominal model in torch (:func:`sim.equations.levels_casadi.level_step_function`): the
    rigid body whose body rates follow their commands as first-order lags, ``w' = (w_cmd - w) / tau`` per axis, the
    thrust passing through. ``u`` is ``(T, p_cmd, q_cmd, r_cmd)`` (N, rad/s): the rates asked of an inner loop,
    not those it reached (:class:`CtbrPhysics`).

    The rates are the lag's exact solution, ``w(t) = w_cmd + (w - w_cmd) exp(-t / tau)``; the attitude and the
    velocity are integrated along it by RK4 with ``substeps`` substeps (the stages take the rates at their times).
    With one substep the next state is within 3e-5 (rad, rad/s, m/s) of the CasADi model's ten RK4 substeps over a
    period from random states and commands on the Crazyflie (its rate lag of 7 ms is the fastest shipped; the
    tests), and a flight model's derivative graph costs a fifth to a tenth of ten substeps'.

    Parameters
    ----------
    m, g, c_d : float
        Mass (kg), gravity (m/s^2) and the world-frame quadratic drag (1/m).
    rate_tau : sequence of 3 float
        Time constants of the roll, pitch and yaw rates' responses, s (:class:`sim.vehicles.onboard.LoopResponse`).
    substeps : int
        RK4 substeps of the attitude and velocity over the 10 ms period.
    """

    extra_states: tuple[str, ...] = ()
    level = "ctbr"
    corrects_rates = True      # the loop's response is assumed: a network may correct the rates it gives

    def __init__(self, m: float, g: float, c_d: float, rate_tau, substeps: int = 1):
        super().__init__(m, g, c_d, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3)
        tau = np.asarray(rate_tau, dtype=float)
        if tau.shape != (3,) or not np.all(np.isfinite(tau)) or np.any(tau <= 0):
            raise ValueError(f"rate_tau must be 3 finite numbers > 0, s; found {rate_tau!r}")
        _check_substeps(substeps)
        self.register_buffer("inv_tau", torch.tensor(1.0 / tau, dtype=torch.float64))
        # ones but for the rates' slots: their path is the lag's solution, not integrated
        self.register_buffer("integrated", torch.tensor([1.0] * 6 + [0.0] * 3 + [1.0] * 3, dtype=torch.float64))
        self.substeps = substeps

    def _decay(self, t: float, dtype) -> torch.Tensor:
        """``exp(-t / tau)`` (3,) at ``t`` seconds into the period."""
        return torch.exp(-self.inv_tau.to(dtype) * t)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The state one period later (B, 12)."""
        return self.forward_tangent(x, u, None, None)

    def forward_tangent(self, x: torch.Tensor, u: torch.Tensor, dx, du):
        """:meth:`forward` (B, 12) and, given the tangents ``dx`` (B, 12, k) and ``du`` (B, 4, k), its tangent
        (B, 12, k) along them (None for none: the state alone is returned)."""
        tangent = dx is not None
        w0, wc = x[:, 6:9], u[:, 1:4]
        thrust = torch.cat([u[:, :1], torch.zeros_like(u[:, 1:])], -1)
        if tangent:
            d_thrust = torch.cat([du[:, :1], torch.zeros_like(du[:, 1:])], 1)
            dw0, dwc = dx[:, 6:9], du[:, 1:4]

        def with_rates(z, dz, t):
            e = self._decay(t, x.dtype)
            w = wc + (w0 - wc) * e
            z = torch.cat([z[:, :6], w, z[:, 9:]], -1)
            if not tangent:
                return z, None
            dw = dwc + (dw0 - dwc) * e[:, None]
            return z, torch.cat([dz[:, :6], dw, dz[:, 9:]], 1)

        mask = self.integrated.to(x.dtype)

        def f(z, dz, t):
            z, dz = with_rates(z, dz, t)
            if tangent:
                d, dd = self.rates_tangent(z, thrust, dz, d_thrust)
                return d * mask, dd * mask[:, None]
            return self.rates(z, thrust) * mask, None

        h = DT / self.substeps
        z, dz = x, dx
        for i in range(self.substeps):
            t = i * h
            k1, d1 = f(z, dz, t)
            k2, d2 = f(z + 0.5 * h * k1, None if not tangent else dz + 0.5 * h * d1, t + 0.5 * h)
            k3, d3 = f(z + 0.5 * h * k2, None if not tangent else dz + 0.5 * h * d2, t + 0.5 * h)
            k4, d4 = f(z + h * k3, None if not tangent else dz + h * d3, t + h)
            z = z + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
            if tangent:
                dz = dz + (h / 6.0) * (d1 + 2.0 * (d2 + d3) + d4)
            z, dz = with_rates(z, dz, t + h)
        return (z, dz) if tangent else z


class AttitudeLoopPhysics(HeldRatesPhysics):
    """:func:`sim.flightlogs.logbench.physics_step` with an ``attitude_loop`` in torch: the translational equations
    of :class:`HeldRatesPhysics`, and body rates that follow the fitted onboard attitude loop
    (:class:`sim.flightlogs.attitudeloop.AttitudeLoop`) instead of being held. The state is 16 wide: the rigid body,
    then the loop's held roll and pitch setpoints and start velocity (:attr:`extra_states`, filled by
    :meth:`start`), which the loop keeps constant over a prediction. RK4 with ``substeps`` substeps, as the loop was
    fitted (:data:`sim.flightlogs.logident.LOOP_SUBSTEPS`).

    Parameters
    ----------
    m, g, c_d, linear_drag, quadratic_drag, accel_bias
        As :class:`HeldRatesPhysics`.
    loop : AttitudeLoop
        The loop's coefficients.
    inertia : sequence of 3 float
        The principal inertias the loop's torques are divided by, kg m^2.
    substeps : int
        RK4 substeps a period.
    """

    extra_states = EXTRA_STATES
    not_flyable = NOT_FLYABLE

    def __init__(self, m: float, g: float, c_d: float, linear_drag, quadratic_drag, accel_bias, loop: AttitudeLoop,
                 inertia, substeps: int = LOOP_SUBSTEPS):
        super().__init__(m, g, c_d, linear_drag, quadratic_drag, accel_bias)
        J = np.asarray(inertia, dtype=float)
        if J.shape != (3,) or not np.all(np.isfinite(J)) or np.any(J <= 0):
            raise ValueError(f"inertia must be 3 finite numbers > 0, kg m^2; found {inertia!r}")
        _check_substeps(substeps)
        self.loop = loop
        self.register_buffer("coefficients", torch.tensor(loop.vector(), dtype=torch.float64))
        self.register_buffer("inertia", torch.tensor(J, dtype=torch.float64))
        self.substeps = substeps

    def start(self, x: np.ndarray) -> np.ndarray:
        """The loop's extra states (B, 4) at window starts ``x`` (B, 12) of a log (:meth:`AttitudeLoop.start`)."""
        return self.loop.start(np.asarray(x, dtype=float))[:, 12:]

    def _coefficients(self, dtype):
        v = self.coefficients.to(dtype)
        return v[0:3], v[3:5], v[6:9], v[9:12], v[12]         # D, K, G, b, K_v (the lead is in the setpoint)

    def rates(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """dx/dt (B, 16): the rigid body's under the loop, the extra states constant."""
        return self._with_loop(HeldRatesPhysics.rates(self, x[:, :12], u), x, u)

    def _with_loop(self, d: torch.Tensor, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The held-rates dx/dt ``d`` (B, 12) with the loop's angular acceleration in its rates' slots, and the
        extra states' zero rates after it (B, 16)."""
        D, K, G, b, kv = self._coefficients(x.dtype)
        J = self.inertia.to(x.dtype)
        w = x[:, 6:9]
        alpha = (G * u[:, 1:4] - torch.cross(w, w * J, dim=1)) / J - D * w + b
        c, s = torch.cos(x[:, 5]), torch.sin(x[:, 5])
        dv0 = c * x[:, 9] + s * x[:, 10] - x[:, 14]
        dv1 = -s * x[:, 9] + c * x[:, 10] - x[:, 15]
        target = torch.stack([x[:, 12] - kv * dv1, x[:, 13] + kv * dv0], -1)
        alpha = torch.cat([alpha[:, :2] - K * (x[:, 3:5] - target), alpha[:, 2:]], -1)
        return torch.cat([d[:, :6], alpha, d[:, 9:12], torch.zeros_like(x[:, 12:16])], -1)

    def rates_tangent(self, x: torch.Tensor, u: torch.Tensor, dx: torch.Tensor, du: torch.Tensor):
        """:meth:`rates` (B, 16), the same values, and its tangent (B, 16, k) along ``dx`` (B, 16, k) and ``du``
        (B, 4, k)."""
        D, K, G, b, kv = self._coefficients(x.dtype)
        J = self.inertia.to(x.dtype)
        d, dd = HeldRatesPhysics.rates_tangent(self, x[:, :12], u, dx[:, :12], du)
        w, dw = x[:, 6:9], dx[:, 6:9]
        wk = w[:, :, None].expand_as(dw)
        d_gyro = torch.cross(dw, (w * J)[:, :, None].expand_as(dw), dim=1) + torch.cross(wk, J[:, None] * dw, dim=1)
        d_alpha = (G[:, None] * du[:, 1:4] - d_gyro) / J[:, None] - D[:, None] * dw
        c, s = torch.cos(x[:, 5]), torch.sin(x[:, 5])
        hv0 = c * x[:, 9] + s * x[:, 10]
        hv1 = -s * x[:, 9] + c * x[:, 10]
        d_psi, d_vx, d_vy = dx[:, 5], dx[:, 9], dx[:, 10]
        d_dv0 = c[:, None] * d_vx + s[:, None] * d_vy + hv1[:, None] * d_psi - dx[:, 14]
        d_dv1 = -s[:, None] * d_vx + c[:, None] * d_vy - hv0[:, None] * d_psi - dx[:, 15]
        d_target = torch.stack([dx[:, 12] - kv * d_dv1, dx[:, 13] + kv * d_dv0], 1)
        d_alpha = torch.cat([d_alpha[:, :2] - K[:, None] * (dx[:, 3:5] - d_target), d_alpha[:, 2:]], 1)
        return self._with_loop(d, x, u), torch.cat([dd[:, :6], d_alpha, dd[:, 9:12], torch.zeros_like(dx[:, 12:16])],
                                                   1)


#: Names of the inputs in a register's extra states, by command level.
REGISTER_INPUTS = {"wrench": ("T", "tx", "ty", "tz"), "ctbr": ("T", "p", "q", "r")}


def register_names(history: int, level: str = "wrench") -> tuple[str, ...]:
    """Names of the extra states of a model with ``history`` periods of inputs (at ``level``) and body rates."""
    return (tuple(f"u{k}_{n}" for k in range(1, history + 1) for n in REGISTER_INPUTS[level])
            + tuple(f"{n}{k}" for k in range(1, history + 1) for n in ("p", "q", "r")))


def raw_features(z: torch.Tensor, u: torch.Tensor, skip: int = 0) -> torch.Tensor:
    """Unnormalized network features (B, 12 + 7 H): roll, pitch, body rates, body-frame velocity, wrench and the
    register ``z[:, 12 + skip:]`` (``skip``: the physics' own extra states, between the rigid body and the register,
    which are not features)."""
    R = rotation_torch(z[:, 3:6])
    vb = torch.einsum("nji,nj->ni", R, z[:, 9:12])
    return torch.cat([z[:, 3:5], z[:, 6:9], vb, u, z[:, 12 + skip:]], -1)


def raw_features_tangent(z: torch.Tensor, u: torch.Tensor, skip: int = 0):
    """:func:`raw_features` (B, 12 + 7 H), the same values, and their derivatives with respect to ``(z, u)``:
    (B, 12 + 7 H, nz + 4) with ``nz = z.shape[1]``, the state's columns first."""
    n, nz = z.shape[0], z.shape[1]
    eye = torch.eye(nz + 4, dtype=z.dtype, device=z.device)
    R = rotation_torch(z[:, 3:6])
    vb = torch.einsum("nji,nj->ni", R, z[:, 9:12])
    # d vb = -[dth]_x R^T v + R^T dv = vb x dth + R^T dv
    dth = rotation_tangent(z[:, 3:6], eye[3:6].expand(n, 3, nz + 4))
    d_vb = cross_columns(vb, dth) + torch.matmul(R.transpose(1, 2), eye[9:12])
    head = torch.cat([eye[3:5], eye[6:9]]).expand(n, 5, nz + 4)
    tail = torch.cat([eye[nz:], eye[12 + skip:nz]]).expand(n, nz - 8 - skip, nz + 4)
    return raw_features(z, u, skip), torch.cat([head, d_vb, tail], 1)


class FlightModel(nn.Module):
    """Identified physics plus a network, optionally with a register of ``history`` past periods.

    With :class:`HeldRatesPhysics` (the wrench level) the network corrects the body rates and the velocity; with
    :class:`CtbrPhysics` (the ``ctbr`` level, whose input is the rates reached) only the velocity, the translational
    dynamics: the next rates stay the input's; with :class:`LaggedCtbrPhysics` (the ``ctbr`` level, whose input is
    the rates commanded) the rates and the velocity, as the inner loop's response is only assumed.

    With :class:`AttitudeLoopPhysics` (the wrench level, rates under the fitted onboard loop) the network corrects the
    rates and the velocity it gives; the loop's own extra states come after the rigid body's.

    State ``z`` (B, 12 + E + 7 H): the rigid body, the physics' ``E`` extra states (its ``extra_states``), then the
    last ``H`` inputs (newest first) and the last ``H`` body rates (newest first). ``forward(z, u)`` gives the next
    ``z``.
    """

    arch = "flight"

    def __init__(self, physics: HeldRatesPhysics, stats: dict, history: int = 0, hidden: int = 64, layers: int = 3):
        super().__init__()
        self.physics = physics
        self.history = int(history)
        self.level = physics.level
        self.corrects_rates = bool(physics.corrects_rates)
        self.own = len(physics.extra_states)          # the physics' extra states, before the register
        self.extra_states = tuple(physics.extra_states) + register_names(self.history, self.level)
        n_in = 2 + 3 + 3 + 4 + 7 * self.history
        # given the rates reached, the network's outputs are the velocity corrections alone (the last three of the
        # statistics')
        outputs = slice(0, 6) if self.corrects_rates else slice(3, 6)
        self.register_buffer("in_mean", torch.as_tensor(stats["in_mean"], dtype=torch.float32).clone())
        self.register_buffer("in_std", torch.as_tensor(stats["in_std"], dtype=torch.float32).clone())
        self.register_buffer("out_scale",
                             torch.as_tensor(np.asarray(stats["out_scale"])[outputs], dtype=torch.float32).clone())
        mods, w = [], n_in
        for _ in range(layers):
            mods += [nn.Linear(w, hidden), nn.Tanh()]
            w = hidden
        self.body = nn.Sequential(*mods)
        self.out = nn.Linear(w, outputs.stop - outputs.start)
        with torch.no_grad():    # start as the physics
            self.out.weight.zero_()
            self.out.bias.zero_()

    def forward(self, z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        x = z[:, :12]
        f = (raw_features(z, u, self.own) - self.in_mean.to(z.dtype)) / self.in_std.to(z.dtype)
        y = self.out(self.body(f)) * self.out_scale.to(z.dtype)
        R = rotation_torch(x[:, 3:6])
        # (the rigid body alone when the physics has no states of its own: the same operations, the same bits)
        nxt = self.physics(z[:, :12 + self.own] if self.own else x, u)
        dv = torch.einsum("nij,nj->ni", R, y[:, -3:])
        rates = nxt[:, 6:9] + y[:, :3] if self.corrects_rates else nxt[:, 6:9]
        parts = [nxt[:, :6], rates, nxt[:, 9:12] + dv] + ([nxt[:, 12:]] if self.own else [])
        return self._with_register(torch.cat(parts, -1), z, u)

    def _with_register(self, nxt: torch.Tensor, z: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """The next state of the physics ``nxt`` (B, 12 + E) followed by the register of ``z`` shifted by one period:
        ``u`` and the body rates of ``z`` enter as the newest, the oldest leave."""
        H, r = self.history, 12 + self.own
        if not H:
            return nxt
        reg_u, reg_w = z[:, r:r + 4 * H], z[:, r + 4 * H:]
        return torch.cat([nxt, u, reg_u[:, :4 * (H - 1)], z[:, 6:9], reg_w[:, :3 * (H - 1)]], -1)

    def network_tangent(self, z: torch.Tensor, u: torch.Tensor):
        """The scaled network output ``y`` of :meth:`forward` (B, 3 or 6), the same values, and its derivatives
        with respect to ``(z, u)`` (B, 3 or 6, nz + 4)."""
        raw, T = raw_features_tangent(z, u, self.own)
        std = self.in_std.to(z.dtype)
        h = (raw - self.in_mean.to(z.dtype)) / std
        T = T / std[:, None]
        for layer in self.body:
            if isinstance(layer, nn.Linear):
                h, T = layer(h), torch.matmul(layer.weight, T)
            elif isinstance(layer, nn.Tanh):
                h = torch.tanh(h)
                T = (1.0 - h * h)[:, :, None] * T
            else:
                raise TypeError(f"no tangent for the layer {layer!r}")
        scale = self.out_scale.to(z.dtype)
        return self.out(h) * scale, torch.matmul(self.out.weight, T) * scale[:, None]

    def forward_jacobian(self, z: torch.Tensor, u: torch.Tensor):
        """Next state (B, nz), ``A = dz_next/dz`` (B, nz, nz) and ``B = dz_next/du`` (B, nz, 4).

        Exact: the physics' forward-mode tangents through its RK4 stages, the network's through its layers (its
        features include the body-frame velocity ``R^T v``), and the register's shift as the constant rows it is.
        Written with plain tensor operations so that it exports to ONNX with a dynamic batch; ``x_next`` is
        :meth:`forward`'s, bit for bit.
        """
        n, H, r = z.shape[0], self.history, 12 + self.own
        nz = r + 7 * H
        x = z[:, :12]
        eye = torch.eye(nz + 4, dtype=z.dtype, device=z.device)
        y, dy = self.network_tangent(z, u)
        R = rotation_torch(x[:, 3:6])
        nxt, A, B = self.physics.forward_jacobian(z[:, :r], u)
        dv = torch.einsum("nij,nj->ni", R, y[:, -3:])
        # d (R y) = R ([dth]_x y + dy) = R (dy - y x dth)
        dth = rotation_tangent(x[:, 3:6], eye[3:6].expand(n, 3, nz + 4))
        d_dv = torch.matmul(R, dy[:, -3:] - cross_columns(y[:, -3:], dth))
        if H:
            J = torch.cat([A, torch.zeros_like(A[:, :, :1]).expand(n, r, 7 * H), B], -1)
        else:
            J = torch.cat([A, B], -1)
        rates = nxt[:, 6:9] + y[:, :3] if self.corrects_rates else nxt[:, 6:9]
        d_rates = J[:, 6:9] + dy[:, :3] if self.corrects_rates else J[:, 6:9]
        nxt = self._with_register(torch.cat([nxt[:, :6], rates, nxt[:, 9:12] + dv, nxt[:, 12:]], -1), z, u)
        J = torch.cat([J[:, :6], d_rates, J[:, 9:12] + d_dv, J[:, 12:]], 1)
        if H:
            shift = torch.cat([eye[nz:], eye[r:r + 4 * (H - 1)], eye[6:9], eye[r + 4 * H:nz - 3]])
            J = torch.cat([J, shift.expand(n, 7 * H, nz + 4)], 1)
        return nxt, J[..., :nz], J[..., nz:]


def register(x: np.ndarray, u: np.ndarray, idx: np.ndarray, history: int, lo=0) -> np.ndarray:
    """The register (B, 7 H) at samples ``idx`` of a flight: wrenches and body rates 1 .. H periods back (the
    flight's first sample, ``lo``: a scalar or one per sample, repeated before its start)."""
    if not history:
        return np.zeros((len(idx), 0))
    back = np.maximum(idx[:, None] - np.arange(1, history + 1), np.asarray(lo)[..., None])
    return np.concatenate([u[back].reshape(len(idx), -1), x[back][:, :, 6:9].reshape(len(idx), -1)], axis=1)


@dataclass(frozen=True)
class FlightTrainConfig:
    """Settings of :func:`train_flight_model` (the budget and the network)."""

    history: int = 0
    hidden: int = 64
    layers: int = 3
    epochs: int = 8
    steps_per_epoch: int = 25
    windows: int = 256           # windows per optimizer step
    lr: float = 3e-3
    seed: int = 0
    validation_stride: int = 10  # every how many window starts of the validation flights are scored


@dataclass
class FlightTrainResult:
    """A trained :class:`FlightModel`, the epoch kept and every epoch's validation score and errors."""

    model: FlightModel
    config: FlightTrainConfig
    best_epoch: int
    scores: list = field(default_factory=list)
    validation: list = field(default_factory=list)
    seconds: float = 0.0


def flight_stats(flights, gain, history: int) -> dict:
    """Feature normalization and output scales from the measured samples of ``flights``."""
    feats, dw, dv = [], [], []
    for f in flights:
        ok = np.flatnonzero(f.x_ok[:-1] & f.x_ok[1:])
        z = np.concatenate([f.x[ok], register(f.x, f.u * gain, ok, history)], axis=1)
        feats.append(raw_features(torch.as_tensor(z), torch.as_tensor(f.u[ok] * gain)).numpy())
        dw.append(f.x[ok + 1, 6:9] - f.x[ok, 6:9])
        dv.append(f.x[ok + 1, 9:12] - f.x[ok, 9:12])
    F = np.concatenate(feats)
    return {"in_mean": F.mean(0), "in_std": F.std(0) + 1e-8,
            "out_scale": np.r_[np.concatenate(dw).std(0), np.concatenate(dv).std(0)] + 1e-8}


def _torch_step(model):
    """``step(x, u)`` of a torch model for :func:`sim.flightlogs.logbench.prediction_errors`: float64, no gradient."""
    m = copy.deepcopy(model).double().eval()

    def step(x, u):
        with torch.no_grad():
            return m(torch.as_tensor(x), torch.as_tensor(u)).numpy()

    return step


def flight_step(model: FlightModel, gain):
    """``(step, start)`` for :func:`sim.flightlogs.logbench.prediction_errors`: the model in float64, no gradient, on
    the
    logged wrench times ``gain``; ``start`` builds the register from the log."""
    inner = _torch_step(model)
    gain = np.asarray(gain, dtype=float)

    def step(z, u):
        return inner(z, u * gain)

    def start(f, idx):
        x = np.asarray(f.x)
        return np.concatenate([x[idx], model.physics.start(x[idx]), register(x, f.u * gain, idx, model.history)],
                              axis=1)

    return step, start


class _Windows:
    """Random training windows of the flights (all flights stacked once, with the wrench times the gain)."""

    def __init__(self, flights, gain, history: int, physics: HeldRatesPhysics | None = None):
        self.physics = physics
        self.x = np.concatenate([f.x for f in flights])
        self.u = np.concatenate([f.u * gain for f in flights])
        self.ok = np.concatenate([f.x_ok for f in flights])
        ends = np.cumsum([len(f.x) for f in flights])
        self.bounds = np.stack([ends - [len(f.x) for f in flights], ends], 1)
        self.history = history
        self._starts = {}

    def starts(self, K: int) -> np.ndarray:
        """Every sample a window of ``K`` steps may start at: measured, with ``K`` more samples of its flight."""
        if K not in self._starts:
            self._starts[K] = np.concatenate([lo + np.flatnonzero(self.ok[lo:hi - K]) for lo, hi in self.bounds])
        return self._starts[K]

    def draw(self, K: int, count: int, gen):
        """z0 (W, 12 + E + 7H), states (W, K, 12), wrenches (W, K, 4), measured (W, K)."""
        s = self.starts(K)[gen.integers(0, len(self.starts(K)), count)]
        lo = self.bounds[np.searchsorted(self.bounds[:, 1], s, side="right"), 0]
        reg = register(self.x, self.u, s, self.history, lo)
        own = np.zeros((len(s), 0)) if self.physics is None else self.physics.start(self.x[s])
        idx = s[:, None] + np.arange(1, K + 1)
        T = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
        return (T(np.concatenate([self.x[s], own, reg], 1)), T(self.x[idx]), T(self.u[idx - 1]),
                torch.as_tensor(self.ok[idx]))


def rollout_loss(model: FlightModel, z0, xs, us, ok) -> torch.Tensor:
    """Mean over measured targets of the squared position, velocity, attitude and rate errors over their goals."""
    z = z0
    total, n = torch.zeros(()), ok.sum().clamp(min=1)
    for k in range(us.shape[1]):
        z = model(z, us[:, k])
        e = z[:, :12] - xs[:, k]
        ang = torch.atan2(torch.sin(e[:, 3:6]), torch.cos(e[:, 3:6]))
        per = ((e[:, 0:3] ** 2).sum(-1) / GOALS["position"] ** 2 + (e[:, 9:12] ** 2).sum(-1) / GOALS["velocity"] ** 2
               + (ang ** 2).sum(-1) / GOALS["rotation"] ** 2 + (e[:, 6:9] ** 2).sum(-1) / GOALS["angular_velocity"] ** 2)
        total = total + torch.where(ok[:, k], per, torch.zeros_like(per)).sum()
    return total / (4.0 * n)


def _identified_physics(physics_kw: dict, level: str):
    """``(physics, gain)``: the identified physics of ``physics_kw`` at ``level`` and the gain on the logged input
    (see :func:`train_flight_model`)."""
    if level not in ("wrench", "ctbr"):
        raise ValueError(f"level must be 'wrench' or 'ctbr'; found {level!r}")
    p = physics_kw["p"]
    drags = [physics_kw.get(k, (0.0,) * 3) for k in ("linear_drag", "quadratic_drag", "accel_bias")]
    if level == "ctbr":
        # one RK4 substep, as the wrench level's held-rates physics: the network answers for what it leaves
        return (CtbrPhysics(p.m, p.g, p.c_d, *drags, thrust_gain=physics_kw.get("thrust_gain", 1.0),
                            substeps=PHYSICS_SUBSTEPS), np.ones(4))
    gain = np.asarray(physics_kw.get("wrench_gain", (1.0,) * 4), dtype=float)
    if physics_kw.get("attitude_loop") is not None:
        return (AttitudeLoopPhysics(p.m, p.g, p.c_d, *drags, physics_kw["attitude_loop"], (p.Jxx, p.Jyy, p.Jzz),
                                    substeps=int(physics_kw.get("substeps", LOOP_SUBSTEPS))), gain)
    return HeldRatesPhysics(p.m, p.g, p.c_d, *drags), gain


def train_flight_model(train_flights, val_flights, physics_kw: dict | None, config: FlightTrainConfig,
                       progress=None, level: str = "wrench", physics: HeldRatesPhysics | None = None
                       ) -> FlightTrainResult:
    """Fit a :class:`FlightModel` on ``train_flights``; keep the epoch whose validation score is lowest.

    Parameters
    ----------
    train_flights, val_flights : sequence of :class:`sim.flightlogs.flightlog.Flight`
        Imported flights (their ``x``, ``u``, ``x_ok``), with the inputs of ``level`` (at ``ctbr``:
        :func:`sim.flightlogs.logbench.ctbr_inputs`).
    physics_kw : dict
        At ``wrench``, :func:`sim.flightlogs.logident.identified_model` with ``hold_rates=True``: ``p``, the drags,
        the bias and ``wrench_gain`` (:class:`HeldRatesPhysics`); with an ``attitude_loop`` too (and the ``substeps``
        it was fitted with), the rates under that loop (:class:`AttitudeLoopPhysics`, the keyword arguments of
        ``physics_step`` for it). At ``ctbr``, the keyword arguments of
        :func:`sim.flightlogs.logbench.ctbr_physics_step` (``p``, the drags, the bias, ``thrust_gain``;
        :class:`CtbrPhysics`).
        None with ``physics``.
    progress : callable, optional
        Called with one line per epoch.
    level : str
        ``"wrench"`` or ``"ctbr"``.
    physics : HeldRatesPhysics, optional
        The physics to start from instead of one built from ``physics_kw`` (its own ``level``; the inputs are taken
        as they are: at ``ctbr`` with :class:`LaggedCtbrPhysics`, the rates commanded).
    """
    from sim.flightlogs.logbench import prediction_errors

    torch.manual_seed(config.seed)
    gen = np.random.default_rng(config.seed)
    if physics is None:
        physics, gain = _identified_physics(physics_kw, level)
    else:
        gain = np.ones(4)
    model = FlightModel(physics, flight_stats(train_flights, gain, config.history), config.history, config.hidden,
                        config.layers)
    windows = _Windows(train_flights, gain, config.history, physics)
    params = [q for q in model.parameters() if q.requires_grad]
    opt = torch.optim.Adam(params, lr=config.lr)
    total = config.epochs * config.steps_per_epoch
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * k / total)))
    best, best_state, scores, errors = math.inf, None, [], []
    t0 = time.perf_counter()
    for e in range(config.epochs):
        K = HORIZONS[min(len(HORIZONS) - 1, (len(HORIZONS) * e) // config.epochs)]
        model.train()
        for _ in range(config.steps_per_epoch):
            loss = rollout_loss(model, *windows.draw(K, config.windows, gen))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 10.0)
            opt.step()
            sched.step()
        step, start = flight_step(model, gain)
        err = prediction_errors(step, val_flights, start=start, stride=config.validation_stride).to_dict()
        s = score(err)
        scores.append(s)
        errors.append(err)
        if s < best:
            best, best_state, best_epoch = s, copy.deepcopy(model.state_dict()), e + 1
        if progress:
            progress(f"  epoch {e + 1}/{config.epochs}: horizon {K}, training loss {float(loss.detach()):.3g}, validation "
                     f"score {s:.3f} (1 = the goal)")
    model.load_state_dict(best_state)
    model.eval()
    return FlightTrainResult(model=model, config=config, best_epoch=best_epoch, scores=scores, validation=errors,
                             seconds=time.perf_counter() - t0)


def export_flight_model(model: FlightModel, path, theta: dict, description: str, level: str = "wrench") -> Path:
    """Write ``model`` as an ONNX file of the model contract (float64), with its derivative graph beside it when
    ``model`` is a :class:`FlightModel`.

    Exported as :func:`pinn.export.export_model` exports (the graphs match torch to 1e-16): ``path`` gives
    ``x_next``; the derivative graph :func:`mpc.prediction.contract.jacobian_path` gives ``x_next``, ``A = dx_next/dx``
    and ``B = dx_next/du`` from the model's exact ``forward_jacobian``, so that the controllers linearize the model
    in one onnxruntime call instead of taking central differences. That pays for a network with a register (a
    history-4 ctbr model: median 31-33 ms a period of the SQP on ``figure8-fast`` against 49-50 ms), not for the
    physics alone, which is written without one: with :class:`CtbrPhysics`' ten RK4 substeps its derivative graph
    made periods slower (28-29 ms against 24 ms, where the SQP refreshes about one stage a period) and took 15 s to
    write, against about a second for a model of one substep.

    Parameters
    ----------
    model : FlightModel or CtbrPhysics
    path : path
        The ``.onnx`` file to write (its folder is created).
    theta : dict
        ``{m, Jxx, Jyy, Jzz, kt, kq}`` of the identified vehicle (the controllers' vehicle spec).
    description : str
        Stored as the file's ``architecture``.
    level : str
        The command level the model takes (:data:`sim.levels.LEVELS`), stored as the metadata ``level`` with that
        level's ``input_names``.

    Returns
    -------
    Path
        ``path`` (the derivative graph, if written, is ``jacobian_path(path)``).
    """
    import json

    from mpc.prediction.contract import CONTRACT_VERSION, jacobian_path
    from sim import __version__ as code_version
    from sim.levels import DEFAULT_LEVEL, LEVEL_INPUTS, check_level
    from sim.params import STATE_NAMES

    from .export import _export, _Jac, _Next, _set_metadata

    check_level(level)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m64 = copy.deepcopy(model).double().eval()
    extra = tuple(m64.extra_states)
    nx = 12 + len(extra)
    jac, with_graph = jacobian_path(path), isinstance(model, FlightModel)
    _export(_Next(m64), path, ["x_next"], nx)
    if with_graph:
        _export(_Jac(m64), jac, ["x_next", "A", "B"], nx)
    elif jac.exists():          # a graph of another model written to the same path before
        jac.unlink()
    meta = {"pinnmpc.contract": CONTRACT_VERSION, "architecture": description, "dt": repr(DT),
            "state_names": json.dumps(list(STATE_NAMES)), "input_names": json.dumps(list(LEVEL_INPUTS[level])),
            "theta": json.dumps({k: float(v) for k, v in theta.items()}), "code_version": code_version,
            "torch_version": torch.__version__}
    if level != DEFAULT_LEVEL:
        meta["level"] = level
    if extra:
        meta["extra_states"] = json.dumps(list(extra))
    _set_metadata(path, meta)
    if with_graph:
        _set_metadata(jac, {k: meta[k] for k in ("pinnmpc.contract", "architecture")})
    return path


# ----------------------------------------------------------------- the real-data study's learned models
#: The paper's architectures (trained by :func:`pinn.train.train`, unchanged) and the physics-plus-network model.
PAPER_ARCHITECTURES = ("baseline", "modular", "fourier", "proposed", "hybrid")
#: The register of the model with history: 4 periods, the largest motor-to-state delay measured on the benchmark.
HISTORY = 4
#: Training budgets: ``full`` for a study, ``quick`` for tests (seconds).
BUDGETS = {
    "full": {"paper": {"profile": "quick"}, "flight": {}},
    "quick": {"paper": {"profile": "quick", "epochs": 2, "steps_per_epoch": 4, "batch": 128, "n_colloc": 32,
                        "hidden": 32, "layers": 2},
              "flight": {"epochs": 2, "steps_per_epoch": 4, "windows": 32, "hidden": 16, "layers": 2}},
}


@dataclass
class LearnedModel:
    """A model trained on the training flights, at the epoch its validation score chose.

    ``step(z, u)`` and ``start(flight, idx)`` are :func:`sim.flightlogs.logbench.prediction_errors`'s (``start`` None:
    the model's state is the rigid body's); ``export(path)`` writes it as an ONNX model file and returns the path.
    ``not_flyable``: why the model cannot be flown whatever it learned (its physics'), or empty.
    """

    name: str
    step: object
    start: object
    epoch: int
    epochs: int
    validation_scores: list
    seconds: float
    export: object
    not_flyable: str = ""


def learned_models(flights: dict, vehicle, ident, fmt, budget: str = "full", progress=print,
                   attitude_loop_kw: dict | None = None) -> list[LearnedModel]:
    """Train the study's learned models on ``flights["train"]``, each at the epoch chosen on ``flights["val"]``.

    The paper's four architectures and physics plus network (:data:`PAPER_ARCHITECTURES`) as they train on
    simulated data (the ``quick`` profile, the stated vehicle as their prior, seed 0); then the identified
    held-rates physics plus a network (:class:`FlightModel`), without and with a register of :data:`HISTORY`
    periods; and, given ``attitude_loop_kw`` (``physics_step``'s keyword arguments of the identified rigid body
    with its fitted ``attitude_loop`` and ``substeps``), that physics plus a network the same two ways
    (:class:`AttitudeLoopPhysics`): the loop is identified first, then the network learns what it leaves.
    """
    from sim.flightlogs.flightlog import flights_to_dataset
    from sim.flightlogs.logbench import prediction_errors
    from sim.flightlogs.logident import identified_model, identified_vehicle

    from .export import export_model
    from .train import make_config, train

    _check_budget(flights, budget)
    b = BUDGETS[budget]
    used = flights["train"] + flights["val"]
    splits = {f.name: ("train" if f in flights["train"] else "val") for f in used}
    ds = flights_to_dataset(used, vehicle, splits, fmt)
    out = []
    for arch in PAPER_ARCHITECTURES:
        progress(f"training {arch} on the training flights")
        overrides = {k: v for k, v in b["paper"].items() if k != "profile"}
        cfg = make_config(arch, b["paper"]["profile"], 0, threads=1, **overrides)
        res = train(ds, cfg, checkpoints=range(1, cfg.epochs + 1))
        scores = [score(prediction_errors(_torch_step(m), flights["val"], stride=FlightTrainConfig.validation_stride)
                        .to_dict()) for _, m in sorted(res.checkpoints.items())]
        e = int(np.nanargmin(scores)) + 1
        best = res.checkpoints[e]

        def export(path, best=best, arch=arch, cfg=cfg):
            path = Path(path)
            return export_model(best, path.parent, path.stem, {"name": path.stem, "train": cfg.to_dict(),
                                                                "data": "real flight logs"}, 0, {},
                                torch_file=False)["onnx"]

        out.append(LearnedModel(arch, _torch_step(best), None, e, cfg.epochs, scores, res.seconds, export))
    kw = dict(identified_model(ident, vehicle, hold_rates=True), quadratic_drag=(0.0, 0.0, 0.0))
    iv = identified_vehicle(ident, vehicle)
    theta = {k: getattr(iv, k) for k in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")}
    out += _flight_models(flights, kw, theta, budget, progress, "wrench", "identified physics + network")
    if attitude_loop_kw is not None:
        out += _flight_models(flights, attitude_loop_kw, theta, budget, progress, "wrench",
                              "identified physics, attitude loop + network")
    return out


def ctbr_learned_models(flights: dict, physics_kw: dict, theta: dict, budget: str = "full",
                        progress=print) -> list[LearnedModel]:
    """The real-data study's learned models at the ``ctbr`` level: the identified translational physics
    (:class:`CtbrPhysics`, given the thrust and the body rates reached) plus a network on the translational dynamics,
    without and with a register of :data:`HISTORY` periods; each at the epoch chosen on ``flights["val"]``.

    Parameters
    ----------
    flights : dict
        ``{"train": [...], "val": [...]}``: imported flights with the ``ctbr`` inputs
        (:func:`sim.flightlogs.logbench.ctbr_inputs`).
    physics_kw : dict
        :func:`sim.flightlogs.logbench.ctbr_physics_step`'s keyword arguments of the identified physics.
    theta : dict
        ``{m, Jxx, Jyy, Jzz, kt, kq}`` written into the model file (the vehicle the model is flown with).
    budget : str
        A key of :data:`BUDGETS`.
    """
    _check_budget(flights, budget)
    return _flight_models(flights, physics_kw, theta, budget, progress, "ctbr", "identified physics, ctbr + network")


def _check_budget(flights: dict, budget: str) -> None:
    """Refuse an unknown budget or a study without validation flights; one thread for torch."""
    if budget not in BUDGETS:
        raise ValueError(f"budget must be one of {', '.join(BUDGETS)}; found {budget!r}")
    if not flights["val"]:
        raise ValueError("the learned models need validation flights (their epoch is chosen on them)")
    torch.set_num_threads(1)


def _flight_models(flights: dict, physics_kw: dict, theta: dict, budget: str, progress, level: str,
                   label: str) -> list[LearnedModel]:
    """:class:`FlightModel` at ``level`` without and with a register of :data:`HISTORY` periods, named ``label``
    (and ``label, history H``), each trained by :func:`train_flight_model` and written at ``level``."""
    gain = np.ones(4) if level == "ctbr" else physics_kw["wrench_gain"]
    out = []
    for history in (0, HISTORY):
        name = label + (f", history {history}" if history else "")
        if progress:
            progress(f"training {name} on the training flights")
        res = train_flight_model(flights["train"], flights["val"], physics_kw,
                                 FlightTrainConfig(history=history, **BUDGETS[budget]["flight"]), progress,
                                 level=level)
        step, start = flight_step(res.model, gain)

        def export(path, model=res.model, name=name):
            return export_flight_model(model, path, theta, name, level=level)

        out.append(LearnedModel(name, step, start, res.best_epoch, res.config.epochs, res.scores, res.seconds,
                                export, res.model.physics.not_flyable))
    return out
