"""A classical estimator of (m, Jxx, Jyy, Jzz, kt, kq): weighted nonlinear least squares, no network.

It fits the parameters to the same logged flights a PINN trains on, through
the nominal model, with the measurement model of :mod:`sim.identification.fisher`:

* every transition ``y_k = F(x_k, u_k; theta) + e_k`` (``F`` one control
  period: RK4, 10 substeps of 1 ms), with the residual's covariance
  ``Sigma + A_k Sigma A_k^T`` (noise on both ends, ``A_k = dF/dx``);
* every rotor reading ``n_ki = sqrt((M(kt, kq)^-1 u_k)_i) + e_n`` above
  :data:`sim.identification.fisher.MIN_ROTOR_FRACTION` of hover speed.

Minimizing the whitened residuals (weighted least squares, the weights
taken at the current estimate) is the maximum-likelihood estimator of that
model up to the weights' own dependence on theta, so its spread should
approach the Cramér-Rao bound that :func:`sim.identification.fisher.fisher_information`
computes for the same samples.
Samples with a saturated rotor are left out when the data log the command
(their applied wrench is not the command), kept when they log the realized
wrench. The solver is Gauss-Newton in relative coordinates (a step
``theta <- theta (1 + delta)``), halving a step that does not lower the cost.
On large data sets a pilot fit on every k-th transition comes first, then
the full data with the pilot's weights held fixed (a full training split of
70,000 transitions takes well under a minute on 2 cores).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SimInputError
from .fisher import MIN_ROTOR_FRACTION, residual_covariance, rotor_sensitivities, sensitivities
from ..params import NX, THETA_NAMES, NoiseModel, QuadParams


@dataclass(frozen=True)
class Estimate:
    """Result of :func:`estimate_theta`.

    Attributes
    ----------
    theta : ndarray (6,)
        Estimated ``(m, Jxx, Jyy, Jzz, kt, kq)``, SI units.
    iterations : int
        Gauss-Newton iterations made.
    converged : bool
        Whether the last step was below the tolerance (in standard deviations of each parameter).
    cost : float
        Half the sum of squared whitened residuals at ``theta``.
    n_transitions, n_rotor_readings : int
        Samples used.
    std_rel : ndarray (6,)
        Relative standard deviations from the inverse Gauss-Newton Hessian at ``theta`` (the estimator's own
        error bars; close to the Cramér-Rao bound when the model holds).
    """

    theta: np.ndarray
    iterations: int
    converged: bool
    cost: float
    n_transitions: int
    n_rotor_readings: int
    std_rel: np.ndarray

    def as_dict(self) -> dict:
        return dict(zip(THETA_NAMES, map(float, self.theta)))


def _weights(theta, x, u, noise: NoiseModel, base: QuadParams):
    """Sensitivities ``S`` (N, 12, 6) at ``theta`` and the Cholesky factor of each transition's residual covariance."""
    S, A = sensitivities(x, u, base.with_theta(theta), "wrench")
    return S, np.linalg.cholesky(residual_covariance(A, noise))               # (N, 12, 12)


def _residuals(theta, L, x, u, y, n_meas, use, noise: NoiseModel, base: QuadParams):
    """Whitened residuals of the transitions (covariance factor ``L``) and of the rotor readings."""
    from ..equations.simulator import Simulator

    pred = Simulator(base.with_theta(theta)).step(x, u)
    r_dyn = np.linalg.solve(L, (y - pred)[..., None])[..., 0]                  # (N, 12)
    n_pred, _ = rotor_sensitivities(u, base.with_theta(theta))
    r_rot = np.where(use, (n_meas - n_pred) / noise.rotor_speed, 0.0)         # (N, 4)
    return np.concatenate([r_dyn.ravel(), r_rot[use]])


def _jacobian(theta, S, L, u, use, noise: NoiseModel, base: QuadParams):
    """d r / d (relative theta): minus the whitened sensitivities times theta."""
    J_dyn = -np.linalg.solve(L, S * theta)                                     # (N, 12, 6)
    _, dn = rotor_sensitivities(u, base.with_theta(theta))
    J_rot = -(dn * theta) / noise.rotor_speed                                  # (N, 4, 6)
    return np.concatenate([J_dyn.reshape(-1, 6), J_rot[use]])


def _gauss_newton(theta, data, noise, base, max_iter: int, tol: float, L=None, S=None):
    """Gauss-Newton in relative coordinates from ``theta``; returns (theta, J, r, iterations, converged).

    Converged when a step is below ``tol`` standard deviations (from the Gauss-Newton covariance at the
    iterate it starts from) for every parameter; that step is taken and the last linearization stands.

    Without ``L`` the residual weights are evaluated anew at each iterate; with ``L`` they stay fixed
    (and only the parameter sensitivities are evaluated, about a third of the cost; ``S``: those at ``theta``,
    if already known).
    """
    x, u, y, n_meas, use = data
    fixed = L is not None

    def linearize(th, S_known=None):
        nonlocal L
        if fixed:
            S_th = S_known if S_known is not None else sensitivities(x, u, base.with_theta(th), "wrench",
                                                                      state=False)
        else:
            S_th, L = _weights(th, x, u, noise, base)
        return _jacobian(th, S_th, L, u, use, noise, base), _residuals(th, L, x, u, y, n_meas, use, noise, base)

    J, r = linearize(theta, S)
    for it in range(1, max_iter + 1):
        cost = 0.5 * float(r @ r)
        delta = np.linalg.lstsq(J, -r, rcond=None)[0]
        std = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
        step = 1.0
        while True:   # halve a step that does not lower the cost (under this iterate's weights)
            trial = theta * (1.0 + step * delta)
            if np.all(trial > 0):
                r_t = _residuals(trial, L, x, u, y, n_meas, use, noise, base)
                if 0.5 * float(r_t @ r_t) <= cost or step < 1e-6:
                    break
            step *= 0.5
        theta = trial
        if np.max(np.abs(step * delta) / std) < tol:
            return theta, J, r_t, it, True
        J, r = linearize(theta)
    return theta, J, r, max_iter, False


#: Transitions of the first stage: Gauss-Newton on every k-th transition (k = N // PILOT_SIZE) brings theta
#: close; the full data then need a few iterations with fixed weights.
PILOT_SIZE = 7000
#: The pilot stops when its last step is below this many of its own standard deviations.
PILOT_TOL = 0.1


def estimate_theta(ds, theta0=None, noise: NoiseModel | None = None, split: str = "train", max_iter: int = 30,
                   tol: float = 1e-2) -> Estimate:
    """Fit ``theta`` to a :class:`sim.identification.excitation.Dataset` by weighted nonlinear least squares.

    Parameters
    ----------
    ds : Dataset
        Logged flights (measured states and rotor speeds, commanded wrench), as a PINN trains on them.
    theta0 : array_like (6,), optional
        Initial guess; default the reference values 30 % too high, the PINNs' starting point.
    noise : NoiseModel, optional
        The measurement noise the residuals are weighted by; default the dataset's own.
    split : {"train", "val", "test"}
        Trajectories used.
    max_iter, tol : int, float
        Gauss-Newton iteration limit, and the largest step, in the estimate's own standard deviations of each
        parameter, that counts as converged.

    Returns
    -------
    Estimate
    """
    from .excitation import SPLIT_NAMES

    noise = NoiseModel(**ds.meta["noise"]) if noise is None else noise
    if np.any(noise.state_std <= 0) or noise.rotor_speed <= 0:
        raise SimInputError("the estimator weights residuals by the noise: every standard deviation must be > 0 "
                            "(a noise-free dataset needs an explicit noise model)")
    if split not in SPLIT_NAMES:
        raise SimInputError(f"split must be one of {', '.join(SPLIT_NAMES)}; found {split!r}")
    sel = ds.split == SPLIT_NAMES.index(split)

    def flat(name):
        a = getattr(ds, name)[sel]
        return a.reshape(-1, a.shape[-1])
    realized = ds.meta.get("inputs", "commanded") == "realized"
    keep = slice(None) if realized else ~np.any(flat("saturated"), axis=1)
    x, u, y, n_meas = (flat(k)[keep] for k in ("x", "u", "x_next", "rotor_speed"))
    # The known constants (g, drag, arm, rotor limit) come from the dataset's parameters; m, J, kt, kq never do.
    base = QuadParams(**ds.meta["params"])
    if theta0 is None:
        theta0 = QuadParams().theta * 1.3
    theta = np.asarray(theta0, dtype=float).copy()
    if theta.shape != (6,) or not np.all(theta > 0):
        raise SimInputError(f"theta0 must be 6 positive values {THETA_NAMES}; found {theta0!r}")
    # Rotor readings near zero speed are left out, as in the Fisher information (judged on the readings).
    use = np.isfinite(n_meas) & (n_meas >= MIN_ROTOR_FRACTION * np.median(n_meas))
    data = (x, u, y, n_meas, use)
    k = max(1, x.shape[0] // PILOT_SIZE)
    if k > 1:
        # Pilot on a thinned sample, then the full data with the weights of the pilot's estimate (a consistent
        # estimate, so the weighted fit keeps its efficiency) held fixed.
        pilot = tuple(a[::k] for a in data)
        theta, _, _, it1, _ = _gauss_newton(theta, pilot, noise, base, max_iter, max(tol, PILOT_TOL))
        S, L = _weights(theta, x, u, noise, base)
        theta, J, r, it2, converged = _gauss_newton(theta, data, noise, base, max_iter, tol, L=L, S=S)
        it = it1 + it2
    else:
        theta, J, r, it, converged = _gauss_newton(theta, data, noise, base, max_iter, tol)
    cost = 0.5 * float(r @ r)
    cov = np.linalg.inv(J.T @ J)
    return Estimate(theta=theta, iterations=it, converged=converged, cost=cost, n_transitions=int(x.shape[0]),
                    n_rotor_readings=int(use.sum()), std_rel=np.sqrt(np.diag(cov)))
