"""Reference simulator: rotor layer + RK4 at 1 kHz, input held over 10 ms.

``Simulator(p).step(x, u)`` advances one control period. High-fidelity
effects (:class:`sim.params.Fidelity`) and disturbances (payload, wind) are
options of the simulator; the nominal model of :mod:`sim.dynamics` never
contains them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from ._validate import as_batch, broadcast_batch, nonnegative_finite, positive_finite, positive_int
from .dynamics import rates, rk4_step, rotation_matrix
from .errors import SimInputError
from .params import DT, NOMINAL, NU, NX, SUBSTEPS, Fidelity, NoiseModel, QuadParams
from .rotors import SPIN, realize, wrench_from_rotor_sq

WindFn = Callable[[float], np.ndarray]


class StepResult(NamedTuple):
    """One control period of :meth:`Simulator.step_full`."""

    x: np.ndarray            # (..., 12) state at the end of the period
    rotor_speed: np.ndarray  # (..., 4) rotor speeds at the end of the period, RU (telemetry)
    wrench: np.ndarray       # (..., 4) realized wrench at the start of the period, N and N m
    saturated: np.ndarray    # (..., 4) bool, rotor command clipped at 0 or at n_max


class _MassParams:
    """Parameters view with the payload added to the mass (m may be an array)."""

    def __init__(self, p: QuadParams, payload: float):
        self.__dict__.update({k: getattr(p, k) for k in ("Jxx", "Jyy", "Jzz", "g", "c_d")})
        self.m = p.m + payload


class Simulator:
    """Quadrotor reference simulator (batched over leading axes).

    Parameters
    ----------
    p : QuadParams, optional
        True vehicle parameters; reference values when omitted.
    fidelity : Fidelity, optional
        Unmodelled effects; nominal (none) when omitted.
    dt : float
        Control period, s (default 0.01).
    substeps : int
        RK4 substeps per control period (default 10, i.e. 1 kHz).
    payload_kg : float
        Extra mass carried, kg. The rotor limits stay those of the vehicle.
    wind : callable, optional
        ``wind(t) -> (3,) or (..., 3)`` world-frame acceleration in m/s^2,
        evaluated once per control period at its start time ``t``.
    """

    def __init__(self, p: QuadParams | None = None, fidelity: Fidelity = NOMINAL, *,
                 dt: float = DT, substeps: int = SUBSTEPS, payload_kg: float = 0.0,
                 wind: WindFn | None = None):
        self.p = QuadParams() if p is None else p
        if not isinstance(self.p, QuadParams):
            raise SimInputError(f"p must be a QuadParams; found {type(p).__name__}")
        if not isinstance(fidelity, Fidelity):
            raise SimInputError(f"fidelity must be a Fidelity; found {type(fidelity).__name__}")
        if wind is not None and not callable(wind):
            raise SimInputError(f"wind must be a callable wind(t) -> acceleration (3,); found {type(wind).__name__}")
        self.fidelity = fidelity
        self.dt = positive_finite(dt, "dt")
        self.substeps = positive_int(substeps, "substeps")
        self.payload_kg = nonnegative_finite(payload_kg, "payload_kg")
        self.wind = wind
        self._body = _MassParams(self.p, self.payload_kg) if self.payload_kg else self.p
        self._single = None   # CasADi step of one vehicle, built on first use
        self._single_hifi = None

    # ------------------------------------------------------------------ API
    def step(self, x, u, t: float = 0.0) -> np.ndarray:
        """Advance one control period with the wrench command ``u`` held.

        Parameters
        ----------
        x : array_like, shape (..., 12)
            State at time ``t``.
        u : array_like, shape (..., 4)
            Commanded wrench ``[T, tau_x, tau_y, tau_z]``, N and N m.
        t : float
            Time at the start of the period, s (only wind uses it).

        Returns
        -------
        numpy.ndarray, shape (..., 12)
            State at ``t + dt``. With motor lag the rotors start at the
            speed of this command; use :meth:`step_full` to carry them.
        """
        return self.step_full(x, u, t=t).x

    def step_full(self, x, u, rotor_speed=None, t: float = 0.0) -> StepResult:
        """Advance one period and report rotor telemetry and the realized wrench.

        Parameters
        ----------
        x, u, t
            As in :meth:`step`.
        rotor_speed : array_like, shape (..., 4), optional
            Rotor speeds at ``t`` (RU); only used with motor lag. When
            omitted the rotors start at the commanded speed.
        """
        x = as_batch(x, "x", NX)
        u = as_batch(u, "u", NU)
        if rotor_speed is not None:
            rotor_speed = as_batch(rotor_speed, "rotor_speed", 4)
        x, u = broadcast_batch(x, u)
        return self._step(x, u, rotor_speed, float(t))

    def measure(self, x, rng: np.random.Generator, noise: NoiseModel | None = None) -> np.ndarray:
        """State as a sensor sees it: ``x`` plus Gaussian noise of ``noise`` (default NoiseModel())."""
        x = as_batch(x, "x", NX)
        std = (NoiseModel() if noise is None else noise).state_std
        return x + std * rng.standard_normal(x.shape)

    # ------------------------------------------------------------ internals
    def _wind(self, t: float):
        if self.wind is None:
            return None
        a = np.asarray(self.wind(t), dtype=float)
        if a.shape[-1:] != (3,) or not np.all(np.isfinite(a)):
            raise SimInputError(f"wind(t) must return a finite acceleration of shape (3,) or (..., 3); "
                                f"found {a.shape} at t={t}")
        return a

    def _step(self, x: np.ndarray, u: np.ndarray, n0, t: float) -> StepResult:
        """Unchecked step (the data generator calls this in its hot loop)."""
        p, fid = self.p, self.fidelity
        # One vehicle flown in short ticks under one held command (a plant read by sensors every millisecond): the
        # allocation is the same for every tick of the period, so it is computed once (the same numbers).
        key = u.tobytes() if u.ndim == 1 else None
        memo = getattr(self, "_realized", None)
        if key is not None and memo is not None and memo[0] == key and memo[1] is p:
            rot = memo[2]
        else:
            rot = realize(u, p)
            if key is not None:
                self._realized = (key, p, rot)
        n_cmd = np.sqrt(rot.n_sq)
        wind = self._wind(t)
        h = self.dt / self.substeps
        body = self._body
        w = rot.wrench

        if fid.is_nominal and x.ndim == 1 and w.ndim == 1:
            # One vehicle (a closed-loop flight): the compiled CasADi form of the same RK4 step is about
            # ten times faster than numpy on a single state. Both forms are held equal by the tests.
            a = np.zeros(3) if wind is None else np.broadcast_to(wind, (3,))
            x1 = np.asarray(self._single_step()(x, w, a)).reshape(NX)
            return StepResult(x1, n_cmd.copy(), w.copy(), rot.saturated.copy())
        if fid.is_nominal:
            x1 = rk4_step(lambda s: rates(s, w, body, accel=wind), x, h, self.substeps)
            return StepResult(x1, np.broadcast_to(n_cmd, x1.shape[:-1] + (4,)).copy(), w, rot.saturated)

        if x.ndim == 1 and w.ndim == 1:
            # One vehicle: the CasADi form of the same step (held equal by the tests), about ten times faster.
            n = n_cmd if n0 is None or fid.motor_tau == 0.0 else np.asarray(n0, dtype=float).reshape(4)
            a = np.zeros(3) if wind is None else np.broadcast_to(wind, (3,))
            x1, n1 = self._single_step_hifi()(x, n, n_cmd, w, a)
            w0 = wrench_from_rotor_sq(n * n, p) if fid.motor_tau > 0.0 else w
            return StepResult(np.asarray(x1).reshape(NX), np.asarray(n1).reshape(4), w0, rot.saturated)
        if fid.motor_tau > 0.0:
            n = n_cmd if n0 is None else np.broadcast_to(n0, n_cmd.shape)

            def f(z):
                s, nn = z[..., :NX], z[..., NX:]
                w_now = wrench_from_rotor_sq(nn * nn, p)
                return np.concatenate([self._rates_hifi(s, w_now, nn, wind), (n_cmd - nn) / fid.motor_tau], axis=-1)

            z = rk4_step(f, np.concatenate([x, np.broadcast_to(n, x.shape[:-1] + (4,))], axis=-1), h, self.substeps)
            return StepResult(z[..., :NX], z[..., NX:], wrench_from_rotor_sq(n * n, p), rot.saturated)

        x1 = rk4_step(lambda s: self._rates_hifi(s, w, n_cmd, wind), x, h, self.substeps)
        return StepResult(x1, np.broadcast_to(n_cmd, x1.shape[:-1] + (4,)).copy(), w, rot.saturated)

    def _carried_params(self) -> QuadParams:
        """The vehicle's parameters with the payload added to the mass (for the CasADi forms of the step)."""
        import dataclasses

        return dataclasses.replace(self.p, m=self.p.m + self.payload_kg) if self.payload_kg else self.p

    def _single_step(self):
        """CasADi ``F(x, u, accel) -> x_next`` of one period for one vehicle (built once per simulator)."""
        if self._single is None:
            from .dynamics_casadi import step_function

            self._single = step_function(self._carried_params(), dt=self.dt, substeps=self.substeps,
                                         accel_input=True)
        return self._single

    def _single_step_hifi(self):
        """CasADi step of one vehicle on the high-fidelity simulator (built once per simulator)."""
        if self._single_hifi is None:
            from .dynamics_casadi import high_fidelity_step_function

            self._single_hifi = high_fidelity_step_function(self._carried_params(), self.fidelity, dt=self.dt,
                                                            substeps=self.substeps)
        return self._single_hifi

    def _rates_hifi(self, s, w, n, wind):
        """Nominal rates plus rotor drag and rotor gyroscopic torque."""
        fid, body = self.fidelity, self._body
        accel = wind
        torque = None
        if fid.rotor_drag > 0.0:
            R = rotation_matrix(s[..., 3], s[..., 4], s[..., 5])
            v_b = np.einsum("...ji,...j->...i", R, s[..., 9:12])        # R^T v
            f_b = -fid.rotor_drag * np.sum(n, axis=-1)[..., None] * v_b
            f_b[..., 2] = 0.0
            a_drag = np.einsum("...ij,...j->...i", R, f_b) / np.asarray(body.m)[..., None]
            accel = a_drag if accel is None else a_drag + accel
        if fid.rotor_gyro > 0.0:
            omega_r = np.sum(SPIN * n, axis=-1)
            torque = -fid.rotor_gyro * omega_r[..., None] * np.stack(
                [s[..., 7], -s[..., 6], np.zeros_like(s[..., 6])], axis=-1)
        return rates(s, w, body, accel=accel, torque=torque)
