"""Dynamically feasible references from flat outputs.

A quadrotor with the nominal model (rigid body, thrust along the body z axis,
quadratic drag) is differentially flat in its position and yaw: given the
position ``p(t)`` (NED, m) and yaw ``psi(t)`` (rad), smooth up to the fourth
derivative (snap), the whole state and the wrench that flies it follow
algebraically. This module holds the trajectories (flat outputs as functions
of time) and that map::

    traj = Figure8(period=3.0)
    x_ref = traj(times)                        # (K, 12) reference states
    x_ref, u_ff = flat_state(traj.flat(times), spec)   # and the wrench (K, 4)

The map, for ``v = p'``, ``a = p''``, drag ``D(v) = c_d v|v|``:

* thrust direction: ``t = g e3 - a - D(v)``, thrust ``T = m |t|``, body z
  axis ``z_b = t / |t|`` (NED: z points down, so hover has ``z_b = e3``);
* attitude: with ``w = Rz(-psi) z_b``, ``theta = atan2(w_x, w_z)``,
  ``phi = asin(-w_y)`` (ZYX Euler angles);
* body rates and angular accelerations from the first and second time
  derivatives of ``phi, theta, psi`` (jerk and snap enter here);
* torques from Euler's equations, ``tau = J w' + w x J w``.

With quadratic drag the torque jumps where a velocity component changes
sign (``v|v|`` has no second derivative at 0); the states stay smooth.

The state part needs only ``g`` and ``c_d``; the wrench needs ``m`` and ``J``
as well, so each controller evaluates it with the parameters it knows
(:class:`mpc.prediction.spec.VehicleSpec`), never with the plant's.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim.params import DT, NU, NX

from ..errors import ConfigurationError
from ..prediction.spec import VehicleSpec

class FlatOutputs(NamedTuple):
    """Flat outputs and their derivatives at K times (NED, SI units)."""

    pos: np.ndarray       # (K, 3) position, m
    vel: np.ndarray       # (K, 3) velocity, m/s
    acc: np.ndarray       # (K, 3) acceleration, m/s^2
    jerk: np.ndarray      # (K, 3) m/s^3
    snap: np.ndarray      # (K, 3) m/s^4
    yaw: np.ndarray       # (K,) rad
    yaw_rate: np.ndarray  # (K,) rad/s
    yaw_acc: np.ndarray   # (K,) rad/s^2


def _times(times) -> np.ndarray:
    t = np.asarray(times, dtype=float).ravel()
    if not np.all(np.isfinite(t)):
        raise ConfigurationError("times must be finite")
    return t


class FlatTrajectory:
    """A reference given by its flat outputs. Subclasses implement :meth:`flat`.

    Calling the trajectory gives the reference states ``(K, 12)`` of the
    nominal model (the datasheet's ``g`` and ``c_d``); :func:`flat_state` gives
    states and wrench for other parameters.
    """

    #: Length of the trajectory, s (None: unbounded). Beyond it the flat outputs hold their end values.
    duration_s: float | None = None

    def flat(self, times) -> FlatOutputs:  # pragma: no cover - interface
        """Flat outputs at ``times`` (K,), s."""
        raise NotImplementedError

    def __call__(self, times) -> np.ndarray:
        return flat_state(self.flat(times))[0]

    def describe(self) -> dict:
        """JSON-ready description."""
        return {"kind": type(self).__name__}


class Hover(FlatTrajectory):
    """Constant position (m, NED; default 1 m height) and yaw (rad)."""

    def __init__(self, position=(0.0, 0.0, -1.0), yaw: float = 0.0):
        self.position = np.asarray(position, dtype=float).reshape(-1)
        if self.position.shape != (3,) or not np.all(np.isfinite(self.position)):
            raise ConfigurationError(f"position must be 3 finite numbers; found {position!r}")
        if not np.isfinite(yaw):
            raise ConfigurationError(f"yaw must be finite; found {yaw}")
        self.yaw = float(yaw)

    def flat(self, times) -> FlatOutputs:
        t = _times(times)
        z3 = np.zeros((t.size, 3))
        z = np.zeros(t.size)
        return FlatOutputs(np.tile(self.position, (t.size, 1)), z3, z3.copy(), z3.copy(), z3.copy(),
                           np.full(t.size, self.yaw), z, z.copy())

    def describe(self) -> dict:
        return {"kind": "hover", "position_m": self.position.tolist(), "yaw_rad": self.yaw}


class Figure8(FlatTrajectory):
    """Lemniscate ``x = A sin(wt), y = A sin(wt) cos(wt)`` at ``height`` (m), ``w = 2 pi / period``, yaw 0.

    Every derivative is analytic. ``amplitude`` in m, ``period`` in s.
    """

    def __init__(self, amplitude: float = 0.75, period: float = 6.0, height: float = 1.0, center=(0.0, 0.0)):
        for name, v in (("amplitude", amplitude), ("period", period), ("height", height)):
            if not (np.isfinite(v) and v > 0):
                raise ConfigurationError(f"{name} must be finite and > 0; found {v}")
        c = np.asarray(center, dtype=float).reshape(-1)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise ConfigurationError(f"center must be 2 finite numbers; found {center!r}")
        self.amplitude, self.period, self.height = float(amplitude), float(period), float(height)
        self.center = c

    @property
    def omega(self) -> float:
        """Angular rate of the lap, rad/s."""
        return 2 * np.pi / self.period

    def flat(self, times) -> FlatOutputs:
        t = _times(times)
        A, w = self.amplitude, self.omega
        s, c = np.sin(w * t), np.cos(w * t)
        s2, c2 = np.sin(2 * w * t), np.cos(2 * w * t)
        K = t.size
        out = [np.zeros((K, 3)) for _ in range(5)]
        # x = A sin(wt); y = (A/2) sin(2wt); derivatives k = 0..4.
        xs = (A * s, A * w * c, -A * w ** 2 * s, -A * w ** 3 * c, A * w ** 4 * s)
        ys = (A / 2 * s2, A * w * c2, -2 * A * w ** 2 * s2, -4 * A * w ** 3 * c2, 8 * A * w ** 4 * s2)
        for k in range(5):
            out[k][:, 0] = xs[k]
            out[k][:, 1] = ys[k]
        out[0][:, 0] += self.center[0]
        out[0][:, 1] += self.center[1]
        out[0][:, 2] = -self.height
        z = np.zeros(K)
        return FlatOutputs(*out, z, z.copy(), z.copy())

    def speeds(self, n: int = 20000) -> tuple[float, float]:
        """``(mean, peak)`` speed over one lap, m/s (mean = lap length / period)."""
        t = np.linspace(0.0, self.period, n, endpoint=False)
        v = np.linalg.norm(self.flat(t).vel, axis=1)
        return float(np.mean(v)), float(np.max(v))

    def describe(self) -> dict:
        mean, peak = self.speeds()
        return {"kind": "figure8", "amplitude_m": self.amplitude, "period_s": self.period,
                "height_m": self.height, "mean_speed_mps": mean, "peak_speed_mps": peak}


class YawTurn(FlatTrajectory):
    """Hover at ``position`` while the yaw turns by ``angle`` (rad) in ``turn_s`` (s), starting at ``start_s``.

    The yaw follows the rest-to-rest polynomial ``35 s^4 - 84 s^5 + 70 s^6 - 20 s^7``
    (``s`` the fraction of the turn), smooth to its third derivative; its peak
    angular acceleration is ``7.51 angle / turn_s^2``.
    """

    def __init__(self, angle: float = np.pi, turn_s: float = 0.25, start_s: float = 1.0,
                 position=(0.0, 0.0, -1.0)):
        for name, v in (("turn_s", turn_s), ("start_s", start_s)):
            if not (np.isfinite(v) and v > 0):
                raise ConfigurationError(f"{name} must be finite and > 0; found {v}")
        if not np.isfinite(angle):
            raise ConfigurationError(f"angle must be finite; found {angle}")
        self.angle, self.turn_s, self.start_s = float(angle), float(turn_s), float(start_s)
        self._hover = Hover(position)

    def flat(self, times) -> FlatOutputs:
        t = _times(times)
        s = np.clip((t - self.start_s) / self.turn_s, 0.0, 1.0)
        inside = (t > self.start_s) & (t < self.start_s + self.turn_s)
        T = self.turn_s
        y = self.angle * (35 * s ** 4 - 84 * s ** 5 + 70 * s ** 6 - 20 * s ** 7)
        y1 = self.angle * (140 * s ** 3 - 420 * s ** 4 + 420 * s ** 5 - 140 * s ** 6) / T * inside
        y2 = self.angle * (420 * s ** 2 - 1680 * s ** 3 + 2100 * s ** 4 - 840 * s ** 5) / T ** 2 * inside
        return self._hover.flat(t)._replace(yaw=y, yaw_rate=y1, yaw_acc=y2)

    def describe(self) -> dict:
        return {"kind": "yaw_turn", "angle_rad": self.angle, "turn_s": self.turn_s, "start_s": self.start_s,
                "position_m": self._hover.position.tolist()}


class StateReference(FlatTrajectory):
    """Wrap a plain callable ``ref(times) -> (K, 12)`` (no flat outputs, no feed-forward)."""

    def __init__(self, fn):
        if not callable(fn):
            raise ConfigurationError(f"reference must be callable; found {type(fn).__name__}")
        self.fn = fn

    def flat(self, times):
        raise ConfigurationError("this reference is a plain state function; it has no flat outputs")

    def __call__(self, times) -> np.ndarray:
        out = np.asarray(self.fn(np.asarray(times, dtype=float)), dtype=float)
        t = np.atleast_1d(times)
        if out.shape != (t.size, NX):
            raise ConfigurationError(f"reference(times) must return shape ({t.size}, 12); found {out.shape}")
        return out


def _euler_and_derivatives(t, t1, t2, yaw, yaw1, yaw2):
    """ZYX angles and their first two time derivatives from the thrust vector ``t`` (K, 3) and its derivatives."""
    n = np.linalg.norm(t, axis=1, keepdims=True)
    zb = t / n
    n1 = np.sum(zb * t1, axis=1, keepdims=True)
    zb1 = (t1 - zb * n1) / n
    n2 = np.sum(zb1 * t1, axis=1, keepdims=True) + np.sum(zb * t2, axis=1, keepdims=True)
    zb2 = (t2 - 2 * zb1 * n1 - zb * n2) / n
    c, s = np.cos(yaw), np.sin(yaw)

    def rot(v):      # Rz(-psi) v
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=1)

    def drot(v):     # d/dpsi Rz(-psi) v
        return np.stack([-s * v[:, 0] + c * v[:, 1], -c * v[:, 0] - s * v[:, 1], np.zeros(len(v))], axis=1)

    def ddrot(v):    # d2/dpsi2 Rz(-psi) v
        return -np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], np.zeros(len(v))], axis=1)

    y1, y2 = yaw1[:, None], yaw2[:, None]
    w = rot(zb)
    w1 = rot(zb1) + y1 * drot(zb)
    w2 = rot(zb2) + 2 * y1 * drot(zb1) + y2 * drot(zb) + y1 ** 2 * ddrot(zb)
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    a = wx ** 2 + wz ** 2
    theta = np.arctan2(wx, wz)
    num = wz * w1[:, 0] - wx * w1[:, 2]
    theta1 = num / a
    num1 = wz * w2[:, 0] - wx * w2[:, 2]
    a1 = 2 * (wx * w1[:, 0] + wz * w1[:, 2])
    theta2 = (num1 * a - num * a1) / a ** 2
    cw = np.sqrt(a)
    phi = np.arctan2(-wy, cw)
    cw1 = -wy * w1[:, 1] / cw
    phi1 = -w1[:, 1] / cw
    phi2 = -(w2[:, 1] * cw - w1[:, 1] * cw1) / cw ** 2
    return n[:, 0], (phi, theta), (phi1, theta1), (phi2, theta2)


def flat_state(f: FlatOutputs, spec=None, linear_drag=None) -> tuple[np.ndarray, np.ndarray]:
    """Reference states (K, 12) and wrench (K, 4) of flat outputs ``f``.

    Parameters
    ----------
    f : FlatOutputs
    spec : object with ``m, Jxx, Jyy, Jzz, g, c_d``, optional
        Parameters of the map (for example a :class:`mpc.prediction.spec.VehicleSpec`);
        the datasheet's (``VehicleSpec()``) when omitted.
        The states depend on ``g`` and ``c_d`` only.
    linear_drag : tuple of three ndarrays (K,), optional
        ``(c, dc/dt, d2c/dt2)``, 1/s: a drag force ``-m c (v - (z_b . v) z_b)``
        perpendicular to the body's z axis, as rotor drag (blade flapping)
        makes it with ``c = k_d sum(n) / m``. The thrust direction then is
        that of ``g e3 - a - c_d v|v| - c v``, and the thrust grows by
        ``m c (z_b . v)``.

    Returns
    -------
    x : ndarray, shape (K, 12)
    u : ndarray, shape (K, 4)
        Wrench ``[T, tau_x, tau_y, tau_z]`` (N, N m) at each instant.
    """
    spec = VehicleSpec() if spec is None else spec
    g, c_d = spec.g, spec.c_d
    v, a, j, s = f.vel, f.acc, f.jerk, f.snap
    av = np.abs(v)
    sv = np.sign(v)
    e3 = np.array([0.0, 0.0, 1.0])
    t0 = g * e3 - a - c_d * v * av
    t1 = -j - 2 * c_d * av * a
    t2 = -s - 2 * c_d * (sv * a * a + av * j)
    if linear_drag is not None:
        c, c1, c2 = (np.asarray(q, dtype=float)[:, None] for q in linear_drag)
        t0, t1, t2 = t0 - c * v, t1 - c * a - c1 * v, t2 - c * j - 2 * c1 * a - c2 * v
    n, (phi, th), (phi1, th1), (phi2, th2) = _euler_and_derivatives(t0, t1, t2, f.yaw, f.yaw_rate, f.yaw_acc)
    psi, psi1, psi2 = f.yaw, f.yaw_rate, f.yaw_acc
    sp, cp, st, ct = np.sin(phi), np.cos(phi), np.sin(th), np.cos(th)
    # Body rates from Euler rates (inverse of the ZYX kinematics).
    p = phi1 - psi1 * st
    q = th1 * cp + psi1 * sp * ct
    r = -th1 * sp + psi1 * cp * ct
    p1 = phi2 - psi2 * st - psi1 * ct * th1
    q1 = th2 * cp - th1 * sp * phi1 + psi2 * sp * ct + psi1 * (cp * phi1 * ct - sp * st * th1)
    r1 = -th2 * sp - th1 * cp * phi1 + psi2 * cp * ct + psi1 * (-sp * phi1 * ct - cp * st * th1)
    K = len(psi)
    x = np.empty((K, NX))
    x[:, 0:3] = f.pos
    x[:, 3], x[:, 4], x[:, 5] = phi, th, psi
    x[:, 6], x[:, 7], x[:, 8] = p, q, r
    x[:, 9:12] = v
    m, Jxx, Jyy, Jzz = spec.m, spec.Jxx, spec.Jyy, spec.Jzz
    u = np.empty((K, NU))
    u[:, 0] = m * n
    if linear_drag is not None:
        u[:, 0] += m * linear_drag[0] * np.sum(t0 / n[:, None] * v, axis=1)
    u[:, 1] = Jxx * p1 - (Jyy - Jzz) * q * r
    u[:, 2] = Jyy * q1 - (Jzz - Jxx) * p * r
    u[:, 3] = Jzz * r1 - (Jxx - Jyy) * p * q
    return x, u


#: Time step of the differences that give the rotor-drag coefficient's derivatives in :func:`actuated_flat_state`, s.
DRAG_FD_STEP = 1e-3
#: Fixed-point iterations of :func:`actuated_flat_state` (rotor speeds -> drag and gyroscopic torque -> wrench).
ACTUATED_ITERATIONS = 4


def actuated_flat_state(traj: "FlatTrajectory", times, params, fidelity) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The flatness map of the high-fidelity equations: states (K, 12), rotor speeds (K, 4, RU) and wrench (K, 4).

    With rotor drag (``fidelity.rotor_drag``) the body feels ``-k_d sum(n)``
    times its velocity perpendicular to z_b, a linear drag whose coefficient
    depends on the rotor speeds (:func:`flat_state`'s ``linear_drag``); with
    gyroscopic torque (``fidelity.rotor_gyro``) the rotors add
    ``-k_g (sum s_i n_i) (q, -p, 0)`` to the torque the body needs. Both depend
    on the rotor speeds, which depend on the wrench: a fixed point, reached in
    :data:`ACTUATED_ITERATIONS` passes. The drag coefficient's time
    derivatives come from five-point differences over :data:`DRAG_FD_STEP`.
    ``params`` is a :class:`sim.QuadParams` (mass, inertia, ``kt``, ``kq``,
    arm, rotor limit, ``g``, ``c_d``); the rotor speeds are those that make
    the wrench (clipped to the rotor limits), which a lagging motor reaches
    only if commanded ahead of time.
    """
    from sim.vehicles.rotors import SPIN, realize

    t = _times(times)
    h = DRAG_FD_STEP
    offsets = h * np.arange(-2, 3)
    f = traj.flat((t[:, None] + offsets[None, :]).ravel())
    K = t.size
    c = np.zeros((K, 5))
    c1 = c2 = np.zeros(K * 5)
    for _ in range(ACTUATED_ITERATIONS):
        drag = (c.ravel(), c1, c2) if fidelity.rotor_drag > 0.0 else None
        x, u = flat_state(f, params, linear_drag=drag)
        n = np.zeros((len(u), 4))
        for _ in range(ACTUATED_ITERATIONS if fidelity.rotor_gyro > 0.0 else 1):
            wr = u.copy()
            if fidelity.rotor_gyro > 0.0:
                omega_r = np.sum(SPIN * n, axis=1)
                wr[:, 1] += fidelity.rotor_gyro * omega_r * x[:, 7]
                wr[:, 2] -= fidelity.rotor_gyro * omega_r * x[:, 6]
            n = np.sqrt(realize(wr, params).n_sq)
        c = (fidelity.rotor_drag * np.sum(n, axis=1) / params.m).reshape(K, 5)
        d1 = (c[:, 0] - 8 * c[:, 1] + 8 * c[:, 3] - c[:, 4]) / (12 * h)
        d2 = (-c[:, 0] + 16 * c[:, 1] - 30 * c[:, 2] + 16 * c[:, 3] - c[:, 4]) / (12 * h * h)
        c1, c2 = np.repeat(d1, 5), np.repeat(d2, 5)
    mid = np.arange(K) * 5 + 2
    return x[mid], n[mid], wr[mid]


#: Gauss-Legendre nodes and weights on [0, 1] (3 points, exact for degree 5).
_GL_NODES = 0.5 + 0.5 * np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GL_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 18.0


def held_wrench(traj: FlatTrajectory, times, spec=None, dt: float = DT) -> np.ndarray:
    """Wrench (K, 4) to hold over each ``[t_k, t_k + dt)``: the interval mean of the flatness wrench.

    A wrench held constant over a control period reproduces the flat
    trajectory to second order in ``dt`` when it is the mean of the
    continuous wrench over that period (3-point Gauss-Legendre).
    """
    return held_input(traj, times, spec, dt)


def held_input(traj: FlatTrajectory, times, spec=None, dt: float = DT, level: str = "wrench") -> np.ndarray:
    """The input (K, 4) at command level ``level`` to hold over each ``[t_k, t_k + dt)``: the interval mean (as
    :func:`held_wrench`) of the flatness map's thrust and, after it, its torques (``wrench``), its body rates
    (``ctbr``), or its roll, pitch and yaw rate (``ctatt``). At ``ctbr`` and ``ctatt`` a first guess that the
    controllers' fit through their model refines (:mod:`mpc.references.feedforward`)."""
    t = _times(times)
    tt = (t[:, None] + dt * _GL_NODES[None, :]).ravel()
    x, u = flat_state(traj.flat(tt), spec)
    if level != "wrench":
        u = np.hstack([u[:, :1], x[:, (6, 7, 8) if level == "ctbr" else (3, 4, 8)]])
    return np.einsum("kjn,j->kn", u.reshape(t.size, 3, NU), _GL_WEIGHTS)


def reference_spec(plant: str, vehicle):
    """The vehicle numbers of the flatness map that makes a reference feasible on ``plant`` (a name of
    :data:`sim.plants.named.PLANTS`) flying ``vehicle``: the vehicle's, with the drag of the plant's own equations
    where they are known (none on ``rotorpy-ideal``)."""
    import dataclasses

    from sim.plants.named import known_equations

    spec = VehicleSpec.from_vehicle(vehicle)
    own = known_equations(plant, vehicle.params)
    return spec if own is None or own.c_d == spec.c_d else dataclasses.replace(spec, c_d=own.c_d)


def reference_states(ref, times: np.ndarray, spec) -> np.ndarray:
    """The reference states (K, 12) of flat trajectory ``ref`` at ``times`` (K,), s, through the flatness map of
    ``spec`` (its gravity and drag enter the attitude; the positions are the flat outputs themselves)."""
    return flat_state(ref.flat(times), spec)[0]


def flown_reference(ref, times: np.ndarray, plant: str, vehicle,
                    high_fidelity: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """The reference ``ref`` as the plant ``plant`` flying ``vehicle`` can fly it: states (K, 12) at ``times``
    (K,), s, and its rotor speeds at the first time (4,) where the plant's motors lag (else None).

    ``high_fidelity`` (the reference simulator with the vehicle's high-fidelity effects): the flatness map of the
    high-fidelity equations (:func:`actuated_flat_state`: rotor drag tilts the thrust); otherwise the flatness map
    of the plant's own rigid-body equations (:func:`reference_spec`). Positions and yaw are the flat outputs either
    way.
    """
    if high_fidelity:
        x, n, _ = actuated_flat_state(ref, times, vehicle.params, vehicle.fidelity)
        return x, (n[0] if vehicle.fidelity.motor_tau > 0.0 else None)
    return reference_states(ref, times, reference_spec(plant, vehicle)), None
