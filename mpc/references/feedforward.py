"""The prediction model's own trim and feed-forward along a reference.

A controller follows a reference trajectory (:mod:`mpc.references.trajectory`) with the
input its *own* model says flies it, not the plant's. :class:`FeedForward`
gives, for any times on the control grid,

* the reference states: the flatness map of the trajectory with the
  vehicle spec's ``g`` and ``c_d`` (or the states of a plain state function);
* the feed-forward input: for each control period the wrench ``u_k`` that
  best carries the model from ``x_ref(t_k)`` to ``x_ref(t_k + dt)``, a
  weighted least-squares fit through the model::

      u_k = argmin_u || W^(1/2) (f(x_ref(t_k), u) - x_ref(t_k + dt)) ||^2

  solved by Gauss-Newton with the model's own input Jacobian (one batched
  call per iteration), started from the flatness wrench of the spec.

The hover trim is the same fit at a constant hover state (the model's own
equilibrium input). For the true equations the fit reproduces the plant's
inverse; for a learned model it is whatever that model believes.

A model with extra states (actuator or history states, :mod:`mpc.prediction.extended`)
is fitted with its extra states at rest for the input (its quasi-steady
response), and the reference's extra states are the model's own, flown
along the reference states with the fitted inputs from their equilibrium at
the start (:meth:`FeedForward.full_states`). A model that gives its own
reference (:meth:`mpc.prediction.models.PredictionModel.reference_states`) is fitted
over its whole state instead, extra states included.
Fitted inputs are cached by time, so a controller that slides its horizon
by one period fits one new input per period.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.params import DT, NU, NX

from ..errors import ConfigurationError
from .trajectory import FlatTrajectory, Hover, StateReference, flat_state, held_input

#: Gauss-Newton iterations of the fit (it stops earlier when the step is below STEP_TOL, in input scales).
FIT_ITERATIONS = 2
TRIM_ITERATIONS = 12
#: Iterations of the fit along a model's own reference (its extra states included: the lead of a lagging motor is
#: not in the first guess).
MODEL_REFERENCE_FIT_ITERATIONS = 4
STEP_TOL = 1e-7
#: The hover state of the trim and the hover linearization: 1 m high (NED z = -1), level, at rest.
HOVER_STATE = np.zeros(NX)
HOVER_STATE[2] = -1.0
#: Levenberg damping of the fit, relative to the input scales (keeps the 4x4 normal equations regular).
DAMPING = 1e-9


def _stationary(f) -> bool:
    """True when flat outputs ``f`` hold one point with no motion (a hover): the target is a steady state."""
    moving = (f.vel, f.acc, f.jerk, f.snap)
    return (all(not np.any(m) for m in moving) and not np.any(f.yaw_rate) and not np.any(f.yaw_acc)
            and not np.any(np.ptp(f.pos, axis=0)) and not np.ptp(f.yaw))


def fit_inputs(model, x0: np.ndarray, x1: np.ndarray, u_guess: np.ndarray, w: np.ndarray, u_scale: np.ndarray,
               iterations: int = FIT_ITERATIONS) -> np.ndarray:
    """Least-squares inputs (K, 4) with ``model.step(x0, u) ~ x1`` in the weighted norm ``w`` (12,).

    Parameters
    ----------
    model : PredictionModel
    x0, x1 : ndarray, shape (K, 12)
        States at the start and end of each control period.
    u_guess : ndarray, shape (K, 4)
        Starting inputs (N, N m).
    w : ndarray, shape (12,)
        Residual weights (1 / scale^2).
    u_scale : ndarray, shape (4,)
        Input scales for the damping and the stopping test.
    """
    return _fit(model, x0, x1, u_guess, w, u_scale, iterations)[0]


def _gauss_newton_step(B, r, w, u_scale) -> np.ndarray:
    """The damped Gauss-Newton input step (K, 4) that cancels residuals ``r`` (K, n) through ``B`` (K, n, 4) in the
    weighted norm ``w`` (n,)."""
    BtW = B.transpose(0, 2, 1) * w[None, None, :]
    H = BtW @ B + np.diag(DAMPING / u_scale ** 2)
    return -np.linalg.solve(H, BtW @ r[:, :, None])[:, :, 0]


def _fit(model, x0, x1, u_guess, w, u_scale, iterations=FIT_ITERATIONS):
    """:func:`fit_inputs` and the model's extra states at rest for the fitted inputs (K, n_extra), or None.

    ``x0``, ``x1`` of the model's full width (K, nx) with ``w`` (nx,): a fit of the whole state, extra states
    included (for a model that gives its own reference); of width 12: the rigid body, with the extra states at
    rest for each input.
    """
    from ..prediction.extended import extra_equilibrium, free_extra, quasi_steady_input_jacobian

    u = np.array(u_guess, dtype=float, copy=True)
    extended = model.n_extra > 0 and x0.shape[1] == NX
    e = None
    for _ in range(iterations):
        with np.errstate(all="ignore"):
            if extended:
                e = extra_equilibrium(model, x0, u, e)
                fx, A, B = model.linearize(np.hstack([x0, e]), u)
                fx, B = fx[:, :NX], quasi_steady_input_jacobian(A, B, free_extra(model))
            else:
                fx, _, B = model.linearize(x0, u)
        r = fx - x1
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(B))):
            raise ConfigurationError("the prediction model returned non-finite values along the reference; "
                                     "no feed-forward input can be fitted")
        step = _gauss_newton_step(B, r, w, u_scale)
        u += step
        if np.max(np.abs(step / u_scale)) < STEP_TOL:
            break
    if extended:
        e = extra_equilibrium(model, x0, u, e)
    return u, e


@dataclass(frozen=True)
class Prepared:
    """What :meth:`FeedForward.prepare` computed up to ``t_end`` (s): reference states and feed-forward inputs by
    time (ns keys), the reference's extra states by period and the input Jacobians at the feed-forward (or None).
    Its arrays are never written to."""

    t_end: float
    states: dict
    inputs: dict
    extras: list
    nominal_B: tuple | None


def _lookup(store, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where ``keys`` (K,) sit in a store whose first element is its ascending keys: ``(found (K,) bool, index (K,))``
    (the index is meaningful where found)."""
    if store is None or len(store[0]) == 0:
        return np.zeros(len(keys), dtype=bool), np.zeros(len(keys), dtype=np.intp)
    at = np.minimum(np.searchsorted(store[0], keys), len(store[0]) - 1)
    return store[0][at] == keys, at


class FeedForward:
    """Reference states and the model's feed-forward inputs along a trajectory.

    Parameters
    ----------
    model : PredictionModel
    reference : FlatTrajectory or callable, optional
        A flat trajectory, or a plain ``ref(times) -> (K, 12)``; hover at 1 m when omitted.
    spec : VehicleSpec
        What the controller knows (``g``, ``c_d`` for the states; ``m``, ``J`` for the first guess).
    weights : ndarray, shape (12,)
        Residual weights of the fit (1 / scale^2).
    u_scale : ndarray, shape (4,)
        Input scales (N, N m).
    """

    def __init__(self, model, reference, spec, weights, u_scale, dt: float = DT):
        if reference is None:
            reference = Hover()
        if not isinstance(reference, FlatTrajectory):
            reference = StateReference(reference)
        self.trajectory = reference
        self.model, self.spec, self.dt = model, spec, dt
        self.w = np.asarray(weights, dtype=float)
        self.u_scale = np.asarray(u_scale, dtype=float)
        self._states: dict[int, np.ndarray] = {}
        self._inputs: dict[int, np.ndarray] = {}
        self._extras: list[np.ndarray] = []       # the reference's extra states at periods 0, 1, ...
        self._disturbance = None                  # (d (6,), offset G d (nx,)) or None: see set_disturbance
        self._steady = None                       # the last steady-state target (x, u), the next one's first guess
        # The last disturbed fit: (times (ns, ascending), inputs (K, 4), input Jacobians (K, 12, 4) or None).
        self._disturbed_inputs: tuple | None = None
        # Input Jacobians at the feed-forward (from prepare): (times (ns, ascending), B (K, 12, 4)) or None.
        self._nominal_B: tuple | None = None
        self._prepared_to: float | None = None    # the t_end of the last prepare (or of a Prepared adopted)
        # The last two undisturbed horizons, (times, states, inputs): the real-time iteration asks for each one twice,
        # once to prepare the period and again in its feedback.
        self._recent: list[tuple] = []
        self.trim_extra = np.zeros(0)
        #: The model gives its own reference states (full width) along flat trajectories.
        self.model_reference = self.is_flat and model.reference_states(reference, np.zeros(1)) is not None
        self.trim = self.hover_trim()

    @property
    def is_flat(self) -> bool:
        """True when the reference has flat outputs (states and first guess from the flatness map)."""
        return not isinstance(self.trajectory, StateReference)

    def _keys(self, t: np.ndarray) -> np.ndarray:
        return np.round(t * 1e9).astype(np.int64)   # cache keys: times in ns

    def _cached(self, cache: dict, times, compute) -> np.ndarray:
        """Values at ``times`` from ``cache``, computing the missing ones in one batched call."""
        t = np.asarray(times, dtype=float).ravel()
        keys = self._keys(t)
        missing = [i for i, k in enumerate(keys) if int(k) not in cache]
        if missing:
            for i, v in zip(missing, compute(t[missing])):
                cache[int(keys[i])] = v
        return np.array([cache[int(k)] for k in keys])

    def states(self, times) -> np.ndarray:
        """Reference states (K, 12) at ``times`` (K,), s (computed once per time, cached)."""
        return self._cached(self._states, times, self._compute_states)[:, :NX]

    def _compute_states(self, t: np.ndarray) -> np.ndarray:
        if self.model_reference:
            return self.model.reference_states(self.trajectory, t)
        if self.is_flat:
            return flat_state(self.trajectory.flat(t), self.spec)[0]
        return self.trajectory(t)

    __call__ = states

    def hover_trim(self) -> np.ndarray:
        """The model's own hover input (4,): the fit at the constant hover state :data:`HOVER_STATE`."""
        x = HOVER_STATE[None, :]
        guess = np.array([[self.spec.m * self.spec.g, 0.0, 0.0, 0.0]])
        u, e = _fit(self.model, x, x, guess, self.w, self.u_scale, TRIM_ITERATIONS)
        if e is not None:
            self.trim_extra = e[0]
        return u[0]

    def full_states(self, times) -> np.ndarray:
        """Reference states with the model's extra states (K, nx) at ``times`` (K,) on the control grid, s.

        The extra states are the model's own along the reference: from their
        equilibrium under the first feed-forward input, flown period by period
        with the reference states and the feed-forward inputs. Without extra
        states this is :meth:`states`.
        """
        if self.model_reference:
            return self._cached(self._states, times, self._compute_states)
        x = self.states(times)
        if self.model.n_extra == 0:
            return x
        k = np.round(np.asarray(times, dtype=float).ravel() / self.dt).astype(np.int64)
        if np.any(k < 0):
            raise ConfigurationError(f"reference times must be >= 0 s; found {float(np.min(times))}")
        self._extend_extras(int(np.max(k)))
        return np.hstack([x, np.array([self._extras[i] for i in k])])

    def _extend_extras(self, k_max: int) -> None:
        """The reference's extra states up to period ``k_max`` (computed once, in order)."""
        from ..prediction.extended import extra_equilibrium

        if self.sequential:
            self._extend_sequential(k_max)
            return
        k0 = len(self._extras)
        if k0 > k_max:
            return
        if k0 == 0:
            t0 = np.zeros(1)
            self._extras.append(extra_equilibrium(self.model, self.states(t0), self.inputs(t0),
                                                  self.trim_extra[None])[0])
            k0 = 1
        times = self.dt * np.arange(k0 - 1, k_max)      # periods k0 - 1 .. k_max - 1 give extras k0 .. k_max
        xs, us = self.states(times), self.inputs(times)
        e = self._extras[-1]
        for i in range(len(times)):
            with np.errstate(all="ignore"):
                e = self.model.step(np.concatenate([xs[i], e]), us[i])[0, NX:]
            self._extras.append(e)

    def inputs(self, times) -> np.ndarray:
        """Feed-forward inputs (K, 4) for the periods starting at ``times`` (K,), s (fitted once, cached)."""
        return self._cached(self._inputs, times, self._compute_inputs).reshape(-1, NU)

    @property
    def sequential(self) -> bool:
        """True when the model integrates some of its extra states (an inner loop's integrals,
        :attr:`mpc.prediction.models.PredictionModel.integrators`): then the inputs and the extra states along the
        reference are fitted together, period after period (:meth:`_extend_sequential`), since an integral's value
        depends on every input before it."""
        return bool(getattr(self.model, "integrators", ())) and not self.model_reference

    def _extend_sequential(self, k_max: int) -> None:
        """The reference's extra states up to period ``k_max`` + 1 and its inputs up to ``k_max``, in order: each
        input fitted from the full state the previous ones left (the rigid body's reference, the extra states the
        model carried along it), each next extra state the model's."""
        k0 = max(len(self._extras) - 1, 0)
        if len(self._extras) == 0:
            self._extras.append(self.trim_extra.copy())
        if len(self._extras) > k_max + 1:
            return
        times = self.dt * np.arange(k0, k_max + 2)
        xs = self.states(times)
        flat = self.is_flat
        guess = held_input(self.trajectory, times[:-1], self.spec, self.dt, self.model.level) if flat else \
            np.tile(self.trim, (len(times) - 1, 1))
        w = np.concatenate([self.w, np.zeros(self.model.n_extra)])
        keys = self._keys(times[:-1])
        e = self._extras[k0]
        for i in range(len(times) - 1):
            z = np.concatenate([xs[i], e])[None]
            x1 = np.concatenate([xs[i + 1], e])[None]
            u = _fit(self.model, z, x1, guess[i:i + 1], w, self.u_scale, MODEL_REFERENCE_FIT_ITERATIONS)[0]
            with np.errstate(all="ignore"):
                e = self.model.step(z, u)[0, NX:]
            self._inputs[int(keys[i])] = u[0]
            self._extras.append(e)

    def _compute_inputs(self, t: np.ndarray) -> np.ndarray:
        if self.sequential:
            k = np.round(t / self.dt).astype(np.int64)
            if np.any(k < 0) or np.any(np.abs(k * self.dt - t) > 1e-9):
                raise ConfigurationError("a model with integrating extra states has its feed-forward on the control "
                                         "grid only (times k dt, k >= 0)")
            self._extend_sequential(int(np.max(k)))
            return np.array([self._inputs[int(kk)] for kk in self._keys(t)])
        if self.model_reference:
            # The model's own reference, extra states included: the fit carries the whole state from one period to
            # the next, so a lagging motor is commanded ahead of time.
            from ..prediction.extended import extra_scale

            x0, x1 = self.full_states(t), self.full_states(t + self.dt)
            w = np.concatenate([self.w, 1.0 / extra_scale(self.model, self.trim_extra) ** 2])
            guess = held_input(self.trajectory, t, self.spec, self.dt, self.model.level)
            return _fit(self.model, x0, x1, guess, w, self.u_scale, MODEL_REFERENCE_FIT_ITERATIONS)[0]
        x0, x1 = self.states(t), self.states(t + self.dt)
        if self.is_flat:
            guess = held_input(self.trajectory, t, self.spec, self.dt, self.model.level)
        else:
            guess = np.tile(self.trim, (len(t), 1))
        return fit_inputs(self.model, x0, x1, guess, self.w, self.u_scale)

    def set_disturbance(self, d, offset) -> None:
        """Track the reference under a disturbance ``d`` (6,) whose one-period effect is ``offset`` (nx,) = G d.

        None (either): no disturbance. See :mod:`mpc.controllers.offset_free`.
        """
        self._disturbance = None if d is None or offset is None else \
            (np.asarray(d, dtype=float).copy(), np.asarray(offset, dtype=float).copy())
        if self._disturbance is None:
            self._disturbed_inputs = None

    def horizon(self, times) -> tuple[np.ndarray, np.ndarray]:
        """Target states (K, nx) at ``times`` (K,) on the control grid and inputs (K - 1, 4) between them.

        Without a disturbance these are :meth:`full_states` and :meth:`inputs`
        (cached). Under one (:meth:`set_disturbance`) they are computed for
        this call: the flatness map of the trajectory with the acceleration
        the rotors must make (:class:`mpc.controllers.offset_free.ShiftedTrajectory`), and
        inputs fitted through ``f(x, u) + G d`` from the undisturbed ones;
        extra states move with their equilibrium under the new inputs. Where
        the model is not finite along that target, the undisturbed one.
        """
        t = np.asarray(times, dtype=float).ravel()
        if self._disturbance is None:
            keys = self._keys(t)        # the times as the caches see them (ns): (k - 1) dt + dt may not be k dt
            for seen, x, u in self._recent:
                if seen.shape == keys.shape and np.array_equal(seen, keys):
                    return x.copy(), u.copy()
            x, u = self.full_states(t), self.inputs(t[:-1])
            self._recent = [(keys, x, u), *self._recent[:1]]
            return x.copy(), u.copy()
        d, off = self._disturbance
        nominal_x, nominal_u = self.full_states(t), self.inputs(t[:-1])
        if self.is_flat and _stationary(self.trajectory.flat(t)):
            target = self._steady_target(nominal_x[0], nominal_u[0], d, off, t[0])
            if target is not None:
                return np.tile(target[0], (len(t), 1)), np.tile(target[1], (len(t) - 1, 1))
        try:
            return self._disturbed_horizon(t, d, off, nominal_x, nominal_u)
        except ConfigurationError:
            # The model is not finite along the disturbed target (a learned model far from its data): the flight
            # goes on with the undisturbed target, as without an estimate; the prediction keeps the disturbance.
            self._disturbed_inputs = None
            return nominal_x, nominal_u

    def _disturbed_horizon(self, t, d, off, nominal_x, nominal_u):
        """:meth:`horizon` under the disturbance ``d`` (6,) with offset ``off`` (nx,), along a moving reference;
        raises :class:`ConfigurationError` where the model is not finite along it."""
        from ..prediction.extended import extra_equilibrium, extra_scale
        from ..controllers.offset_free import ShiftedTrajectory

        traj = ShiftedTrajectory(self.trajectory, d[:3]) if self.is_flat else None
        if self.model_reference:
            X = self.model.reference_states(traj, t)
            w = np.concatenate([self.w, 1.0 / extra_scale(self.model, self.trim_extra) ** 2])
            U = _fit(self.model, X[:-1], X[1:] - off, nominal_u, w, self.u_scale,
                     MODEL_REFERENCE_FIT_ITERATIONS)[0]
            return X, U
        X = flat_state(traj.flat(t), self.spec)[0] if traj is not None else self.trajectory(t)
        # Warm start from the last call's inputs at the same times (the disturbance moves little in a period).
        keys = self._keys(t[:-1])
        warm, at = _lookup(self._disturbed_inputs, keys)
        guess = nominal_u.copy()
        if np.any(warm):
            guess[warm] = self._disturbed_inputs[1][at[warm]]
        chord = self.model.n_extra == 0 and (np.any(warm) or self._nominal_B is not None)
        if not chord:
            U = fit_inputs(self.model, X[:-1], X[1:] - off[:NX], guess, self.w, self.u_scale)
            B = None
        else:
            # A chord step: the input Jacobians of the last call at these times (or the feed-forward's from prepare;
            # any time without either evaluated here), one model step for the residual. Converges to the same fit
            # over the periods a time spends in the horizon. (After a skipped period more than one time is new:
            # still this path, so one overrun does not make the next call slower.)
            B = np.empty((len(keys), NX, NU))
            known = warm & (self._disturbed_inputs is not None and self._disturbed_inputs[2] is not None)
            if np.any(known):
                B[known] = self._disturbed_inputs[2][at[known]]
            nominal, at_n = _lookup(self._nominal_B, keys)
            use_n = nominal & ~known
            if np.any(use_n):
                B[use_n] = self._nominal_B[1][at_n[use_n]]
            cold = ~(known | use_n)
            if np.any(cold):
                with np.errstate(all="ignore"):
                    B[cold] = self.model.linearize(X[:-1][cold], guess[cold])[2][:, :NX]
            with np.errstate(all="ignore"):
                r = self.model.step(X[:-1], guess)[:, :NX] - (X[1:] - off[:NX])
            U = guess + _gauss_newton_step(B, r, self.w, self.u_scale)
            if not np.all(np.isfinite(U)):
                U = fit_inputs(self.model, X[:-1], X[1:] - off[:NX], guess, self.w, self.u_scale)
                B = None
        if B is None and not self.model.n_extra:
            with np.errstate(all="ignore"):
                B = self.model.linearize(X[:-1], U)[2][:, :NX]
        self._disturbed_inputs = (keys, U, B)
        if self.model.n_extra:
            u_all = np.vstack([U, U[-1:]])
            u_nom = np.vstack([nominal_u, nominal_u[-1:]])
            e_nom = nominal_x[:, NX:]
            shift = (extra_equilibrium(self.model, X, u_all, e_nom)
                     - extra_equilibrium(self.model, nominal_x[:, :NX], u_nom, e_nom))
            X = np.hstack([X, e_nom + shift])
        return X, U

    def _steady_target(self, x_nominal, u_nominal, d, off, t: float):
        """The model's steady state under ``off`` at the reference's position and yaw at time ``t`` (s),
        ``(x (nx,), u (4,))``, or None when Newton does not converge (:func:`mpc.controllers.offset_free.steady_target`;
        warm-started from the last one at the same point)."""
        from ..prediction.extended import extra_scale
        from ..controllers.offset_free import TARGET_ACCEPT, TARGET_FIXED, ShiftedTrajectory, steady_target

        scale = 1.0 / np.sqrt(self.w)
        if self.model.n_extra:
            scale = np.concatenate([scale, extra_scale(self.model, self.trim_extra)])
        last = self._steady
        fixed = list(TARGET_FIXED)
        if last is not None and np.array_equal(last[0][fixed], x_nominal[fixed]):
            x0, u0 = last
        else:       # the flatness map under the disturbance's acceleration: attitude and thrust close to the answer
            x0, u0 = x_nominal.copy(), u_nominal
            # at the time asked for: a path that ends away from its start holds its end point, not its start
            x0[:NX] = flat_state(ShiftedTrajectory(self.trajectory, d[:3]).flat(np.array([t])), self.spec)[0][0]
        x, u, res = steady_target(self.model, x0, u0, off, scale, self.u_scale)
        if not res < TARGET_ACCEPT:
            self._steady = None
            return None
        self._steady = (x, u)
        return x, u

    def prepare(self, t_end: float, chunk: int = 512) -> None:
        """Fit the feed-forward for every control period from 0 to ``t_end`` (s) ahead of a flight.

        The reference is known before take-off, so its states and inputs can
        be computed in a few large batched calls instead of one small call per
        control period; the controllers then only look them up. Values are the
        same fit either way (the fit is per period).
        """
        if not (np.isfinite(t_end) and t_end >= 0):
            raise ConfigurationError(f"t_end must be a finite time >= 0 s; found {t_end}")
        if self._prepared_to is not None and t_end == self._prepared_to:
            return                                # done already, or adopted: the very same values
        n = int(np.floor(t_end / self.dt + 1e-9)) + 1
        times = self.dt * np.arange(n)
        keys, jac = [], []
        for start in range(0, n, chunk):
            tt = times[start:start + chunk]
            u = self.inputs(tt)
            if self.model.n_extra == 0 and not self.model_reference:
                # The input Jacobians there: the first step of a disturbed fit in flight (see horizon) needs no
                # derivatives of its own.
                with np.errstate(all="ignore"):
                    B = self.model.linearize(self.states(tt), u)[2][:, :NX]
                ok = np.all(np.isfinite(B), axis=(1, 2))
                keys.append(self._keys(tt)[ok])
                jac.append(B[ok])
        if keys:
            self._nominal_B = (np.concatenate(keys), np.concatenate(jac))
        if self.model.n_extra and not self.model_reference:    # a model's own reference carries its extra states
            self._extend_extras(n - 1)
        self._prepared_to = float(t_end)

    def prepared(self) -> "Prepared":
        """What :meth:`prepare` computed, for another FeedForward of the same model, reference and weights to
        :meth:`adopt` (call it right after :meth:`prepare`, before anything is flown)."""
        if self._prepared_to is None:
            raise ConfigurationError("prepared() needs a prepare() first")
        return Prepared(self._prepared_to, dict(self._states), dict(self._inputs), list(self._extras),
                        self._nominal_B)

    def adopt(self, prepared: "Prepared") -> None:
        """Take what another FeedForward's :meth:`prepare` computed, instead of computing it again.

        Only for a FeedForward built like that one (same model, reference, spec, weights and input scales): the
        values are then the very ones its own :meth:`prepare` would compute. Call before :meth:`prepare`.
        """
        if self._prepared_to is not None or self._states or self._inputs or self._extras:
            raise ConfigurationError("adopt() is for a FeedForward that has computed nothing yet")
        self._states, self._inputs = dict(prepared.states), dict(prepared.inputs)
        self._extras, self._nominal_B = list(prepared.extras), prepared.nominal_B
        self._prepared_to = prepared.t_end

    def linearization_point(self) -> tuple[np.ndarray, np.ndarray]:
        """Hover state (nx,) at 1 m, with the model's extra states at rest, and the model's trim (4,)."""
        return np.concatenate([HOVER_STATE, self.trim_extra]), self.trim.copy()

    def hover_linearization(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(u_trim (4,), A (nx, nx), B (nx, 4))``: the model linearized at its own hover trim."""
        x, u = self.linearization_point()
        _, A, B = self.model.linearize(x, u)
        return u, A[0], B[0]
