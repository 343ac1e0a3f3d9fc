"""Reference simulator: rotor layer + RK4 at 1 kHz, input held over 10 ms.

``Simulator(p).step(x, u)`` advances one control period. High-fidelity
effects (:class:`sim.params.Fidelity`) and disturbances (payload, wind) are
options of the simulator; the nominal model of :mod:`sim.equations.dynamics` never
contains them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from .._validate import as_batch, broadcast_batch, nonnegative_finite, positive_finite, positive_int
from .dynamics import rates, rk4_step, rotation_matrix
from ..errors import SimInputError
from ..params import DT, NOMINAL, NU, NX, SUBSTEPS, Fidelity, NoiseModel, QuadParams
from ..vehicles.rotors import SPIN, RotorOutput, realize, wrench_from_rotor_sq

WindFn = Callable[[float], np.ndarray]


class StepResult(NamedTuple):
    """One control period of :meth:`Simulator.step_full`."""

    x: np.ndarray            # (..., 12) state at the end of the period
    rotor_speed: np.ndarray  # (..., 4) rotor speeds at the end of the period, RU (telemetry)
    wrench: np.ndarray       # (..., 4) realized wrench at the start of the period, N and N m
    saturated: np.ndarray    # (..., 4) bool, rotor command clipped at 0 or at n_max


class _BufferedFunction:
    """A CasADi function evaluated on numpy buffers bound to it once (``Function.buffer``).

    The same evaluation as calling the function, without converting the
    arguments and results at each call (for a function called a thousand
    times a second of flight, most of the cost). Dense inputs and outputs;
    each is passed and returned flat, in column-major order.
    """

    def __init__(self, fn):
        self.fn = fn
        self._args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self._res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._buf, self._eval = fn.buffer()
        for i, a in enumerate(self._args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self._res):
            self._buf.set_res(i, memoryview(r))

    def __call__(self, *args) -> list[np.ndarray]:
        """The results (flat copies) for ``args`` (arrays of each input's number of values, column-major)."""
        for a, v in zip(self._args, args):
            a[:] = v
        self._eval()
        if self._buf.ret() != 0:
            raise RuntimeError(f"CasADi function {self.fn.name()!r} failed (return code {self._buf.ret()})")
        return [r.copy() for r in self._res]


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
        self._chains: dict[tuple[str, int], _BufferedFunction] = {}   # periods chained in one call (kind, number)

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
        rot = self._realize(u)
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

    def _realize(self, u: np.ndarray) -> RotorOutput:
        """The rotor layer's answer to the command ``u`` (..., 4), N and N m (:func:`sim.vehicles.rotors.realize`).

        One vehicle flown in short ticks under one held command (a plant read by sensors every millisecond): the
        allocation is the same for every tick of the period, so it is computed once (the same numbers).
        """
        p = self.p
        key = u.tobytes() if u.ndim == 1 else None
        memo = getattr(self, "_realized", None)
        if key is not None and memo is not None and memo[0] == key and memo[1] is p:
            return memo[2]
        rot = realize(u, p)
        if key is not None:
            self._realized = (key, p, rot)
        return rot

    def _wind_accels(self, times) -> np.ndarray:
        """The wind (3, K) at each of ``times`` (K,), s, as :meth:`step_full` applies it over a period from there."""
        accel = np.zeros((3, len(times)))
        if self.wind is not None:
            for j, t in enumerate(times):
                wind = self._wind(float(t))
                accel[:, j] = wind if wind.shape == (3,) else np.broadcast_to(wind, (3,))
        return accel

    def _step_chain(self, x: np.ndarray, u: np.ndarray, accel: np.ndarray,
                    n0=None) -> tuple[np.ndarray, np.ndarray, StepResult]:
        """K periods of one vehicle in a row under the held command ``u``, in one CasADi call.

        The same numbers as K calls of :meth:`step_full`, each from the state and rotor speeds the one before
        returned (the same CasADi step function, chained), without their argument checks: the caller passes
        finite arrays and checks the states it gets back.

        Parameters
        ----------
        x : numpy.ndarray, shape (12,)
            State at the start of the first period.
        u : numpy.ndarray, shape (4,)
            Commanded wrench held over every period, N and N m.
        accel : numpy.ndarray, shape (3, K)
            The wind over each period, m/s^2 (:meth:`_wind_accels` of the periods' start times).
        n0 : numpy.ndarray, shape (4,), optional
            Rotor speeds at the start of the first period, RU (only used with motor lag; as in
            :meth:`step_full`).

        Returns
        -------
        states : numpy.ndarray, shape (K, 12)
            State at the end of each period.
        rotor_speed : numpy.ndarray, shape (K, 4)
            Rotor speeds at the end of each period, RU.
        last : StepResult
            What :meth:`step_full` returns for the last period.
        """
        p, fid = self.p, self.fidelity
        rot = self._realize(u)
        n_cmd = np.sqrt(rot.n_sq)
        w = rot.wrench
        k = accel.shape[1]
        a = accel.T.ravel()                 # column-major (3, K): each period's three values in turn
        if fid.is_nominal:
            xs = self._chain("nominal", k)(x, w, a)[0].reshape(k, NX)
            ns = np.broadcast_to(n_cmd, (k, 4)).copy()
            return xs, ns, StepResult(xs[-1].copy(), n_cmd.copy(), w.copy(), rot.saturated.copy())
        lag = fid.motor_tau > 0.0
        n = n_cmd if n0 is None or not lag else np.asarray(n0, dtype=float).reshape(4)
        xs, ns = self._chain("high_fidelity", k)(x, n, n_cmd, w, a)
        xs, ns = xs.reshape(k, NX), ns.reshape(k, 4)
        n_start = n if k == 1 else ns[-2].copy()          # the rotor speeds at the start of the last period
        w0 = wrench_from_rotor_sq(n_start * n_start, p) if lag else w
        return xs, ns, StepResult(xs[-1].copy(), ns[-1].copy(), w0, rot.saturated)

    def _chain(self, kind: str, k: int):
        """``k`` periods of the one-vehicle step in a row: one CasADi function, built once per simulator and ``k``.

        ``kind`` "nominal": ``G(x (12), w (4), accel (3, k)) -> states (12, k)``, chaining :meth:`_single_step`;
        "high_fidelity": ``G(x, n0 (4), n_cmd (4), w, accel) -> (states (12, k), rotor speeds (4, k))``,
        chaining :meth:`_single_step_hifi` with the rotor speeds carried (with motor lag; else each period
        starts at ``n_cmd``, as :meth:`step_full` does). Each period is a call of the same step function, so
        the chain computes exactly what separate calls compute. Called with flat arrays, column-major
        (:class:`_BufferedFunction`).
        """
        import casadi as ca

        if (kind, k) not in self._chains:
            x0, w, accel = ca.MX.sym("x", NX), ca.MX.sym("w", NU), ca.MX.sym("accel", 3, k)
            x, xs = x0, []
            if kind == "nominal":
                step = self._single_step()
                for j in range(k):
                    x = step(x, w, accel[:, j])
                    xs.append(x)
                fn = ca.Function(f"step_chain{k}", [x0, w, accel], [ca.horzcat(*xs)], ["x", "w", "accel"],
                                 ["states"])
            else:
                step, lag = self._single_step_hifi(), self.fidelity.motor_tau > 0.0
                n0, n_cmd = ca.MX.sym("n0", 4), ca.MX.sym("n_cmd", 4)
                n, ns = n0, []
                for j in range(k):
                    x, n = step(x, n if lag else n_cmd, n_cmd, w, accel[:, j])
                    xs.append(x)
                    ns.append(n)
                fn = ca.Function(f"step_chain_high_fidelity{k}", [x0, n0, n_cmd, w, accel],
                                 [ca.horzcat(*xs), ca.horzcat(*ns)], ["x", "n0", "n_cmd", "w", "accel"],
                                 ["states", "rotor_speeds"])
            self._chains[kind, k] = _BufferedFunction(fn)
        return self._chains[kind, k]

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
