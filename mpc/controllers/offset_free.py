"""Offset-free control: a disturbance estimate in the controllers' prediction and in their steady-state target.

An estimator (:mod:`mpc.estimators.estimator`) gives a disturbance ``d`` (6,): an
acceleration ``a`` (3, m/s^2, world NED) and an angular acceleration
``alpha`` (3, rad/s^2, body) that the model lacks. A controller told ``d``
(``controller.set_disturbance(d, x)``) does two things with it:

* **prediction**: every step of its model becomes ``f(x, u) + G d``
  (:func:`disturbance_matrix`, the same ``G`` as the estimator's), ``d``
  held constant over the horizon;
* **target**: the reference it tracks is recomputed so that the model with
  the disturbance can fly it. The flatness map gets the acceleration the
  rotors must make, ``a_ref - a`` (:class:`ShiftedTrajectory`: the attitude
  tilts against a wind, the thrust grows with a payload), and the
  feed-forward input is fitted through ``f + G d``
  (:meth:`mpc.references.feedforward.FeedForward.horizon`).

The second matters as much as the first: with the disturbance in the
prediction but the input still weighed against the undisturbed feed-forward,
the optimum balances the input cost against the position error and leaves an
offset even with ``d`` known exactly.
"""

from __future__ import annotations

import numpy as np

from sim.params import DT

from ..references.trajectory import FlatOutputs, FlatTrajectory

#: Length of the disturbance vector.
ND = 6


def euler_rate_matrix(eta: np.ndarray) -> np.ndarray:
    """``W(eta)`` (3, 3) with ``d(eta)/dt = W(eta) omega`` for ZYX Euler angles ``eta`` = (phi, theta, psi)."""
    phi, th = eta[0], eta[1]
    sp, cp, ct, tt = np.sin(phi), np.cos(phi), np.cos(th), np.tan(th)
    return np.array([[1.0, sp * tt, cp * tt], [0.0, cp, -sp], [0.0, sp / ct, cp / ct]])


def disturbance_matrix(eta: np.ndarray, nx: int, dt: float = DT) -> np.ndarray:
    """``G`` (nx, 6): what a disturbance held over one period adds to the state at Euler angles ``eta`` (3,).

    Velocity ``dt a``, position ``dt^2 a / 2``, body rates ``dt alpha``,
    Euler angles ``dt^2 W(eta) alpha / 2``; nothing to extra states.
    """
    G = np.zeros((nx, ND))
    G[0:3, 0:3] = 0.5 * dt * dt * np.eye(3)
    G[9:12, 0:3] = dt * np.eye(3)
    G[6:9, 3:6] = dt * np.eye(3)
    G[3:6, 3:6] = 0.5 * dt * dt * euler_rate_matrix(eta)
    return G


def disturbance_offset(d, x, nx: int) -> np.ndarray | None:
    """``G d`` (nx,) at the state ``x`` (its Euler angles), or None for no (or a zero) disturbance."""
    if d is None:
        return None
    d = np.asarray(d, dtype=float).reshape(-1)
    if d.shape != (ND,) or not np.all(np.isfinite(d)):
        from ..errors import ConfigurationError
        raise ConfigurationError(f"disturbance must be 6 finite numbers (acceleration, angular acceleration); "
                                 f"found {d!r}")
    if not np.any(d):
        return None
    eta = np.zeros(3) if x is None else np.asarray(x, dtype=float)[3:6]
    return disturbance_matrix(eta, nx) @ d


class ShiftedTrajectory(FlatTrajectory):
    """A flat trajectory whose acceleration is reduced by a constant ``a`` (3,), m/s^2: what the rotors must make.

    Positions, velocities, jerk, snap and yaw are the trajectory's own; the
    flatness map of the result gives the attitude and thrust that fly the
    trajectory under the extra acceleration ``a``.
    """

    def __init__(self, trajectory: FlatTrajectory, a):
        self.trajectory = trajectory
        self.a = np.asarray(a, dtype=float).reshape(3)

    def flat(self, times) -> FlatOutputs:
        f = self.trajectory.flat(times)
        return f._replace(acc=f.acc - self.a)

    def describe(self) -> dict:
        return {**self.trajectory.describe(), "disturbance_acceleration": self.a.tolist()}


class DisturbedModel:
    """A prediction model plus a constant offset ``G d`` on every step (the controllers' prediction).

    Forwards everything else to the wrapped model. With no offset its
    outputs are the model's own, bit for bit.
    """

    def __init__(self, model):
        self.base = model
        self.offset: np.ndarray | None = None

    def __getattr__(self, name):
        if name == "base":          # not set yet (a copy being made): no recursion
            raise AttributeError(name)
        return getattr(self.base, name)

    def step(self, x, u) -> np.ndarray:
        xn = self.base.step(x, u)
        return xn if self.offset is None else xn + self.offset

    def linearize(self, x, u):
        xn, A, B = self.base.linearize(x, u)
        return (xn if self.offset is None else xn + self.offset), A, B

    def linearize_single(self, x, u):
        xn, A, B = self.base.linearize_single(x, u)
        return (xn if self.offset is None else xn + self.offset), A, B

    def jacobians(self, x, u):
        return self.base.jacobians(x, u)      # a constant offset has no derivatives


#: The states a steady-state target holds at the reference: position (NED) and yaw. The rest (attitude, rates,
#: velocity, extra states) and the inputs are free, so the target problem is square (Pannocchia's rank condition:
#: as many tracked outputs as inputs).
TARGET_FIXED = (0, 1, 2, 5)
#: Newton iterations and stopping test (scaled residual) of :func:`steady_target`.
TARGET_ITERATIONS = 8
TARGET_TOL = 1e-9
#: A target whose scaled residual stays above this is not used (the controllers keep the flatness-map target).
TARGET_ACCEPT = 1e-4
#: Levenberg damping of the target's Newton step (scaled units): keeps the step finite if a model's Jacobian is
#: singular, far below any scale that matters.
TARGET_DAMPING = 1e-10


def steady_target(model, x_guess, u_guess, offset, state_scale, u_scale, iterations: int = TARGET_ITERATIONS):
    """The steady state of the model under a constant offset that holds the reference's position and yaw.

    Solves ``x = f(x, u) + offset`` for ``(x, u)`` with ``x[TARGET_FIXED]``
    held at ``x_guess``'s values (Newton's method on the scaled residual,
    from the guess). This is the target of offset-free MPC: a learned model
    whose hover is not an equilibrium of its own (it drifts a little, or its
    attitude must tilt to stand still) is still given a target it can hold,
    so that the estimate, and the measured position with it, settles on the
    reference.

    Parameters
    ----------
    model : PredictionModel
    x_guess : ndarray, shape (nx,)
        The nominal target state (its position and yaw are kept).
    u_guess : ndarray, shape (4,)
        The nominal target input (N, N m).
    offset : ndarray, shape (nx,) or None
        Added to every step (``G d``).
    state_scale : ndarray, shape (nx,)
        Acceptable deviations of the state (residuals are measured in these).
    u_scale : ndarray, shape (4,)
        Input scales.

    Returns
    -------
    x : ndarray, shape (nx,)
    u : ndarray, shape (4,)
    residual : float
        Largest scaled residual ``|x - f(x, u) - offset| / state_scale`` left.
    """
    x = np.array(x_guess, dtype=float).reshape(-1).copy()
    u = np.array(u_guess, dtype=float).reshape(-1).copy()
    nx = x.size
    off = np.zeros(nx) if offset is None else np.asarray(offset, dtype=float).reshape(nx)
    free = np.setdiff1d(np.arange(nx), TARGET_FIXED)
    sx = np.asarray(state_scale, dtype=float)
    zs = np.concatenate([sx[free], np.asarray(u_scale, dtype=float)])      # unknowns' scales
    eye = np.eye(nx)
    res = np.inf
    for i in range(iterations + 1):
        with np.errstate(all="ignore"):
            xn, A, B = model.linearize(x[None], u[None])
        r = (xn[0] + off - x) / sx
        res = float(np.max(np.abs(r)))
        if not np.isfinite(res) or res < TARGET_TOL or i == iterations:
            break
        J = np.hstack([(A[0] - eye)[:, free], B[0]]) / sx[:, None] * zs[None, :]
        H = J.T @ J + TARGET_DAMPING * np.eye(J.shape[1])
        step = -np.linalg.solve(H, J.T @ r) * zs
        if not np.all(np.isfinite(step)):
            break
        x[free] += step[:free.size]
        u += step[free.size:]
    return x, u, res


__all__ = ["DisturbedModel", "ShiftedTrajectory", "disturbance_matrix", "disturbance_offset", "euler_rate_matrix",
           "steady_target"]
