"""Extra states: what the controllers need to plan with a model whose state is longer than the rigid body's.

A prediction model may carry states beyond the 12 rigid-body ones
(:attr:`mpc.prediction.models.PredictionModel.extra_names`): actuator states (rotor
speeds, the realized wrench of a lagging motor) or a window of past states and
inputs (a shift register). No sensor measures them. The controllers plan over
the whole state ``z = (x, e)`` and obtain ``e`` in three ways:

* **at rest**, the model's own equilibrium: with the rigid-body state ``x``
  and the input ``u`` held, ``e`` such that the model maps ``(x, e)`` to
  ``e`` again (:func:`extra_equilibrium`, Newton's method on the model's own
  Jacobian, which converges in one step for extra states that are linear in
  themselves, as a lag or a shift register);
* **along a reference**, the same model flown along the reference states
  with the feed-forward inputs (:class:`mpc.references.feedforward.FeedForward`);
* **in flight**, propagated by the model from the inputs actually applied
  (:class:`ExtraStateTracker`): each period the model's prediction of the
  extra states from the last measured state, the last estimate and the
  input that was in effect; or, with a state estimator
  (:mod:`mpc.estimators.estimator`), the estimate itself.

For the feed-forward fit the rigid-body response to an input is taken with
the extra states settled at their equilibrium for that input
(:func:`quasi_steady_input_jacobian`): the fitted input is the one that
flies the reference once the actuators have caught up, and the MPC adds the
lead a lag needs from its own prediction.
"""

from __future__ import annotations

import numpy as np

from sim.params import NX

from ..errors import ConfigurationError

#: Newton iterations of the extra-state equilibrium, and its tolerance (relative to the states' scale).
EQUILIBRIUM_ITERATIONS = 20
EQUILIBRIUM_RTOL = 1e-10


def free_extra(model) -> np.ndarray:
    """Indices (into the extra states) of those that come to rest by themselves: all but the model's
    :attr:`~mpc.prediction.models.PredictionModel.integrators`."""
    held = set(getattr(model, "integrators", ()))
    return np.array([i for i, n in enumerate(model.extra_names) if n not in held], dtype=np.intp)


def extra_equilibrium(model, x: np.ndarray, u: np.ndarray, e0: np.ndarray | None = None) -> np.ndarray:
    """The model's extra states at rest (K, n_extra) for rigid-body states ``x`` (K, 12) and inputs ``u`` (K, 4).

    Solves ``f((x, e), u)[12:] = e`` by Newton's method with the model's
    Jacobian, from ``e0`` (K, n_extra) or zeros. Integrating extra states (an inner loop's integrals,
    :attr:`~mpc.prediction.models.PredictionModel.integrators`) have no rest value of their own: they keep their
    value from ``e0``, and the others come to rest with them.

    Raises
    ------
    ConfigurationError
        If the model's output is not finite there, or the iteration does not
        settle (extra states that do not come to rest when the state and input
        are held cannot be planned with).
    """
    x = np.atleast_2d(np.asarray(x, dtype=float))
    u = np.atleast_2d(np.asarray(u, dtype=float))
    ne = model.n_extra
    e = np.zeros((len(x), ne)) if e0 is None else np.array(np.broadcast_to(e0, (len(x), ne)), dtype=float)
    free = free_extra(model)
    if len(free) == 0:
        return e
    eye = np.eye(len(free))
    r = np.full((len(x), len(free)), np.inf)
    for _ in range(EQUILIBRIUM_ITERATIONS):
        with np.errstate(all="ignore"):
            zn, A, _ = model.linearize(np.hstack([x, e]), u)
        r = zn[:, NX + free] - e[:, free]
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(A))):
            raise ConfigurationError(f"model {model.name!r}: its extra states {list(model.extra_names)} are not finite "
                                     f"at rest (state and input held)")
        if np.all(np.abs(r) <= EQUILIBRIUM_RTOL * np.maximum(np.abs(e[:, free]), 1.0)):
            return e
        try:
            Aff = A[:, NX + free][:, :, NX + free]
            e[:, free] = e[:, free] + np.linalg.solve(eye - Aff, r[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError as exc:
            raise ConfigurationError(f"model {model.name!r}: its extra states have no equilibrium with the state and "
                                     f"input held (I - de'/de is singular)") from exc
    worst = float(np.max(np.abs(r) / np.maximum(np.abs(e[:, free]), 1.0)))
    raise ConfigurationError(f"model {model.name!r}: its extra states {list(model.extra_names)} do not settle with "
                             f"the state and input held (relative change {worst:.2g} after "
                             f"{EQUILIBRIUM_ITERATIONS} Newton steps)")


def quasi_steady_input_jacobian(A: np.ndarray, B: np.ndarray, free: np.ndarray | None = None) -> np.ndarray:
    """d x_next / d u (K, 12, 4) with the extra states at rest: ``B_x + A_xe (I - A_ee)^-1 B_e``.

    ``A`` (K, nx, nx), ``B`` (K, nx, 4): the model's Jacobians at an equilibrium of its extra states. ``free``: the
    indices of the extra states that come to rest (:func:`free_extra`; all when None); the others are held.
    """
    ne = A.shape[1] - NX
    if ne == 0:
        return B
    f = np.arange(ne) if free is None else np.asarray(free, dtype=np.intp)
    if len(f) == 0:
        return B[:, :NX, :]
    de = np.linalg.solve(np.eye(len(f)) - A[:, NX + f][:, :, NX + f], B[:, NX + f, :])   # (K, nf, 4): d e_rest / d u
    return B[:, :NX, :] + A[:, :NX][:, :, NX + f] @ de


def extra_scale(model, e_hover: np.ndarray) -> np.ndarray:
    """Acceptable deviations (n_extra,) of the extra states: the model's own, or a tenth of their hover values.

    Extra states that are zero at hover (a torque, a past body rate) get a
    scale of 1 in their own unit, unless the model declares its own.
    """
    if model.extra_scale is not None:
        return np.asarray(model.extra_scale, dtype=float)
    e = np.abs(np.asarray(e_hover, dtype=float))
    return np.where(e > 0.0, 0.1 * e, 1.0)


class ExtraStateTracker:
    """The extra states of a model in flight, propagated by the model from the inputs actually applied.

    ``full(x_measured)`` gives the state the controller plans from, ``(x, e)``;
    ``applied(u)`` is told, after every period, the input that was in effect
    during it. The propagation happens at the next ``full`` call, so a
    controller that is timed is charged for it.

    Parameters
    ----------
    model : PredictionModel
    start : callable
        ``start(x (12,), t) -> e (n_extra,)``: the extra states at the first call, at time ``t`` (s)
        (for example the model's equilibrium under the first feed-forward input).
    """

    def __init__(self, model, start):
        self.model = model
        self._start = start
        self._z: np.ndarray | None = None      # last full state the controller planned from
        self._pending: list[np.ndarray] = []
        self._ahead: tuple | None = None       # (input, the next full state under it), made by ahead()

    @property
    def active(self) -> bool:
        """True when the model has extra states to track."""
        return self.model.n_extra > 0

    def reset(self) -> None:
        """Forget the flight (the next call starts from the equilibrium again)."""
        self._z, self._pending, self._ahead = None, [], None

    def ahead(self, u) -> np.ndarray | None:
        """Propagate the last full state now, under the input ``u`` (4,) just sent, before the period is flown: the
        next :meth:`full` takes this step instead of making it, when the input it is told was applied is exactly
        ``u`` (otherwise it propagates as usual). For a controller with time after its input is out (the real-time
        iteration's preparation): the model's step leaves the next input's path.

        Returns the model's next full state (nx,) from the last full state under ``u``, or None (no extra states,
        or nothing to propagate from)."""
        self._ahead = None
        if not self.active or self._z is None or self._pending:
            return None
        with np.errstate(all="ignore"):
            self._ahead = (np.array(u, dtype=float), self.model.step(self._z, u)[0])
        return self._ahead[1].copy()

    def applied(self, u) -> None:
        """The input (4,) that was in effect during the period just flown."""
        if self.active and self._z is not None:
            self._pending.append(np.asarray(u, dtype=float).copy())

    def full(self, x: np.ndarray, t: float = 0.0) -> np.ndarray:
        """The full state (nx,) for the rigid-body state ``x`` (12,) measured at time ``t`` (s).

        A state of the model's full length (nx,), an estimator's, is taken as it is.
        """
        if not self.active:
            return x
        if len(x) == self.model.nx:
            self._pending, self._ahead = [], None
            self._z = np.array(x, dtype=float)
            return self._z.copy()
        if self._z is None:
            e = np.asarray(self._start(x, t), dtype=float).reshape(-1)
        else:
            z, pending = self._z, self._pending
            if self._ahead is not None and len(pending) == 1 and np.array_equal(pending[0], self._ahead[0]):
                z, pending = self._ahead[1], []          # propagated ahead under this very input
            with np.errstate(all="ignore"):
                for u in pending:
                    z = self.model.step(z, u)[0]
                    if not np.all(np.isfinite(z)):
                        break
            e = z[NX:]
            if not np.all(np.isfinite(e)):      # a model that diverged: restart from its equilibrium
                e = np.asarray(self._start(x, t), dtype=float).reshape(-1)
        self._pending, self._ahead = [], None
        self._z = np.concatenate([x, e])
        return self._z.copy()

    @property
    def extra(self) -> np.ndarray | None:
        """The extra states of the last full state (n_extra,), or None before the first call."""
        return None if self._z is None else self._z[NX:].copy()


__all__ = ["ExtraStateTracker", "extra_equilibrium", "extra_scale", "free_extra", "quasi_steady_input_jacobian"]
