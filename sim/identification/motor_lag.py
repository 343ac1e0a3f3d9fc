"""Identification with the motor lag: (m, Jxx, Jyy, Jzz, kt, kq, tau_m) from logged flights.

The nominal model has no motor: the commanded wrench acts at once. On a
vehicle whose rotors lag, a transition ``x_k -> x_{k+1}`` then depends on
rotor speeds the model does not have, and the six parameters absorb the
difference (the high-fidelity rows of Table VI). Here the rotor speeds are
part of the state, ``z = (x, n)`` (16,), as the flight logs have them
(rotor telemetry), and the motor time constant ``tau_m`` is a seventh
parameter::

    z_{k+1} = F(z_k, u_k; theta, tau_m) + e_k,
    dn/dt = (n_cmd(u_k; kt, kq) - n) / tau_m,   wrench = M(kt, kq) n^2,

``F`` one control period (RK4, 10 substeps of 1 ms, as the simulator),
``n_cmd = sqrt(M^-1 u)`` the rotor command of the commanded wrench. The
noise on both ends of a transition enters the residual as in
:mod:`sim.identification.fisher`: covariance ``Sigma_z + A Sigma_z A^T`` with
``A = dF/dz`` and ``Sigma_z`` the state and rotor-telemetry variances.

:func:`lag_fisher` gives the Fisher information and the Cramér-Rao bounds of
the seven parameters (relative coordinates, as :mod:`sim.identification.fisher`);
:func:`estimate_with_lag` the weighted least-squares fit (Gauss-Newton in
relative coordinates, weights fixed at a pilot estimate, as
:func:`sim.identification.estimate.estimate_theta`). Transitions whose command saturated a
rotor are left out (their rotor command is not ``sqrt(M^-1 u)``), as are the
first period of each flight (its starting rotor speeds are not logged).

Rotor drag and gyroscopic torque are not in this model: on the high-fidelity
simulator's data they remain unmodelled (they move no parameter of the
nominal fit either; see ``docs/identification.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..equations.compiled import compiled
from ..equations.dynamics_casadi import lagged_rates_casadi, rk4_casadi, rotor_command_casadi
from ..errors import SimInputError
from ..params import DT, NOMINAL, NX, SUBSTEPS, THETA_NAMES, NoiseModel, QuadParams

#: The identified parameters: the nominal six and the motor time constant (s).
LAG_THETA_NAMES = THETA_NAMES + ("tau_m",)
NZ = NX + 4

_FUNCS: dict = {}


def lag_sensitivity_function(p: QuadParams, state: bool = True) -> ca.Function:
    """CasADi ``(z (16), u (4), theta (7)) -> (dF/dtheta (16, 7), dF/dz (16, 16), F (16))`` of one period.

    Built from one RK4 substep function called :data:`sim.params.SUBSTEPS` times (an MX graph: its C code is
    small and compiles in seconds). ``p`` gives the known constants (``g``, ``c_d``, arm, rotor limit).
    Without ``state`` its second output is ``dF/dn`` (16, 4) alone, the rotor columns of ``dF/dz`` (the
    estimator's iterations need the rest only for their weights), at a fraction of the cost.
    """
    z, u, th = ca.SX.sym("z", NZ), ca.SX.sym("u", 4), ca.SX.sym("theta", 7)
    vals = {n: getattr(p, n) for n in ("g", "c_d", "d")}
    vals.update({n: th[i] for i, n in enumerate(THETA_NAMES)})
    n_cmd = rotor_command_casadi(u, vals, p.n_max_sq)

    def f(s):
        return lagged_rates_casadi(s, n_cmd, vals, NOMINAL, th[6])

    sub = ca.Function("lag_substep", [z, u, th], [rk4_casadi(f, z, DT / SUBSTEPS, 1)])
    Z, U, TH = ca.MX.sym("z", NZ), ca.MX.sym("u", 4), ca.MX.sym("theta", 7)
    zz = Z
    for _ in range(SUBSTEPS):
        zz = sub(zz, U, TH)
    if state:
        dz = ca.jacobian(zz, Z)
    else:
        seeds = ca.DM.zeros(NZ, 4)
        seeds[NX:, :] = ca.DM.eye(4)
        dz = ca.jtimes(zz, Z, seeds)        # four forward directions: the rotor speeds only
    return ca.Function("sens_lag" + ("_state" if state else ""), [Z, U, TH],
                       [ca.densify(ca.jacobian(zz, TH)), ca.densify(dz), zz])


def _function(p: QuadParams, state: bool) -> ca.Function:
    key = (p.g, p.c_d, p.d, p.n_max_sq, state)
    if key not in _FUNCS:
        _FUNCS[key] = compiled(lag_sensitivity_function(p, state), "batch")
    return _FUNCS[key]


def lag_sensitivities(z, u, theta7, p: QuadParams, chunk: int = 5000, state: bool = True):
    """``(S (N, 16, 7), A (N, 16, 16), F (N, 16))`` at ``theta7`` for transitions from ``z`` (N, 16) under ``u``
    (without ``state``, ``A`` is its rotor columns (N, 16, 4) alone)."""
    from .fisher import _map_eval

    f = _function(p, state)
    th = np.asarray(theta7, dtype=float)
    parts = [_map_eval(f, z[lo:lo + chunk], u[lo:lo + chunk], th) for lo in range(0, z.shape[0], chunk)]
    S, A, F = (np.concatenate([q[i] for q in parts]) for i in range(3))
    return S, A, F[..., 0]


def true_theta7(ds) -> np.ndarray:
    """The dataset's true ``(m, Jxx, Jyy, Jzz, kt, kq, tau_m)``."""
    return np.r_[QuadParams(**ds.meta["params"]).theta, float(ds.meta.get("fidelity", {}).get("motor_tau", 0.0))]


#: Periods at the start of each flight left out of the fit: the rotors' model starts at the first command's speed,
#: an assumption forgotten after a few time constants (20 periods are more than six of 30 ms).
SETTLE_PERIODS = 20


def rotor_trajectory(u: np.ndarray, theta7, p: QuadParams):
    """Rotor speeds the model gives along the commands ``u`` (F, K, 4) of F flights, and their sensitivities.

    The motor is linear in its speed with the command held over a period, so one period is exact:
    ``n_{k+1} = c_k + (n_k - c_k) a`` with ``a = exp(-dt / tau_m)`` and ``c_k`` the rotor command
    (``sqrt(M^-1 u_k)``, clipped to the rotor limits), from ``n_0 = c_0``. Returns ``n`` (F, K + 1, 4) at the
    period boundaries and ``dn / dtheta`` (F, K + 1, 4, 7), absolute units.
    """
    from .fisher import rotor_sensitivities

    th = np.asarray(theta7, dtype=float)
    tau = th[6]
    # The rotor command and its derivative with respect to kt and kq, as the Fisher information's telemetry channel
    # has them (NaN where the allocation is negative), then clipped to the rotor limits.
    n_cmd, dn_cmd = rotor_sensitivities(u.reshape(-1, 4), p.with_theta(th[:6]))
    n_max = np.sqrt(p.n_max_sq)
    with np.errstate(invalid="ignore"):
        free = (n_cmd > 0.0) & (n_cmd < n_max)
    c = np.where(np.isnan(n_cmd), 0.0, np.minimum(n_cmd, n_max)).reshape(u.shape)
    dc = np.zeros(u.shape[:2] + (4, 7))
    dc[..., :6] = np.where(free[:, :, None], dn_cmd, 0.0).reshape(u.shape + (6,))
    a = np.exp(-DT / tau)
    da = a * DT / tau ** 2
    F, K = u.shape[:2]
    n = np.empty((F, K + 1, 4))
    dn = np.zeros((F, K + 1, 4, 7))
    n[:, 0], dn[:, 0] = c[:, 0], dc[:, 0]
    for k in range(K):
        n[:, k + 1] = c[:, k] + (n[:, k] - c[:, k]) * a
        dn[:, k + 1] = dc[:, k] * (1.0 - a) + a * dn[:, k]
        dn[:, k + 1, :, 6] += (n[:, k] - c[:, k]) * da
    return n, dn


def _flights(ds, split):
    from .excitation import SPLIT_NAMES

    sel = np.ones(ds.x.shape[0], dtype=bool) if split is None else ds.split == SPLIT_NAMES.index(split)
    return ds.x[sel], ds.u[sel], ds.x_next[sel], ds.rotor_speed[sel], ds.saturated[sel]


def _sigma(noise: NoiseModel) -> np.ndarray:
    return np.r_[noise.state_std, np.full(4, noise.rotor_speed)] ** 2


def _linearize(theta, flights, p: QuadParams, stride: int = 1, state: bool = True):
    """Residual pieces at ``theta``: rigid-body predictions and sensitivities, rotor predictions and sensitivities.

    Returns ``(F_x (N, 12), S_x (N, 12, 7), A_xx (N, 12, 12) or None without state, use (F, K), n_pred (M, 4),
    S_n (M, 4, 7), ok (F, K))``
    over the used transitions ``use`` (after :data:`SETTLE_PERIODS`, not saturated, every ``stride``-th period)
    and rotor readings ``ok`` (after the same periods). The rotor model runs along every period regardless.
    """
    x, u, _, _, sat = flights
    n, dn = rotor_trajectory(u, theta, p)
    use = ~np.any(sat, axis=-1)
    use[:, :SETTLE_PERIODS] = False
    use[:, np.arange(use.shape[1]) % stride != 0] = False
    z = np.concatenate([x, n[:, :-1]], axis=-1)[use]
    S, A, Fz = lag_sensitivities(z, u[use], theta, p, state=state)
    dF_dn = A[:, :NX, NX:] if state else A[:, :NX]
    S_x = S[:, :NX] + np.einsum("nij,njk->nik", dF_dn, dn[:, :-1][use])   # through the rotor speeds too
    ok = np.ones(n.shape[:2], dtype=bool)[:, 1:]
    ok[:, :SETTLE_PERIODS] = False
    ok[:, np.arange(ok.shape[1]) % stride != 0] = False
    return Fz[:, :NX], S_x, (A[:, :NX, :NX] if state else None), use, n[:, 1:][ok], dn[:, 1:][ok], ok


@dataclass(frozen=True)
class LagFisher:
    """Fisher information of the seven parameters (relative coordinates) and their Cramér-Rao bounds."""

    theta: np.ndarray       # (7,) true values
    fim: np.ndarray         # (7, 7)
    crlb_rel: np.ndarray    # (7,) CRLB standard deviation / true value
    n_samples: int

    @property
    def crlb_std(self) -> np.ndarray:
        """CRLB standard deviations in the parameters' units (7,)."""
        return self.crlb_rel * self.theta


def lag_fisher(clean, noise: NoiseModel | None = None, split: str | None = "train") -> LagFisher:
    """Fisher information of the lag model on a noise-free dataset (its states are the truth).

    ``noise``: the measurement noise the bound is for (default: ``NoiseModel()``): the states' on both ends
    of each transition, the rotor telemetry's on each reading.
    """
    noise = NoiseModel() if noise is None else noise
    if np.any(_sigma(noise) <= 0):
        raise SimInputError("the lag model's Fisher information needs positive state and rotor-speed noise")
    p = QuadParams(**clean.meta["params"])
    theta = true_theta7(clean)
    if not theta[6] > 0:
        raise SimInputError("the dataset's simulator has no motor lag (fidelity motor_tau = 0)")
    _, S_x, A, _, _, S_n, _ = _linearize(theta, _flights(clean, split), p)
    Sig = np.diag(noise.state_std ** 2)
    cov = Sig + A @ Sig @ np.swapaxes(A, 1, 2)
    Sx, Sn = S_x * theta, S_n * theta
    fim = np.einsum("nij,nik->jk", Sx, np.linalg.solve(cov, Sx)) + np.einsum("nij,nik->jk", Sn, Sn) \
        / noise.rotor_speed ** 2
    fim = 0.5 * (fim + fim.T)
    return LagFisher(theta=theta, fim=fim, crlb_rel=np.sqrt(np.diag(np.linalg.inv(fim))), n_samples=len(S_x))


@dataclass(frozen=True)
class LagEstimate:
    """Result of :func:`estimate_with_lag` (units of :data:`LAG_THETA_NAMES`)."""

    theta: np.ndarray       # (7,)
    std_rel: np.ndarray     # (7,) the fit's own relative standard deviations
    iterations: int
    converged: bool
    n_transitions: int

    def as_dict(self) -> dict:
        return dict(zip(LAG_THETA_NAMES, map(float, self.theta)))


#: Weight passes: the residual covariance is evaluated at the first guess, then again at each pass's estimate.
WEIGHT_PASSES = 2
#: Transitions of the passes before the last (every k-th period of every flight).
PILOT_SIZE = 7000


def estimate_with_lag(ds, theta0=None, noise: NoiseModel | None = None, split: str = "train",
                      max_iter: int = 30, tol: float = 1e-2) -> LagEstimate:
    """Fit ``(m, Jxx, Jyy, Jzz, kt, kq, tau_m)`` to a dataset's flights by weighted least squares.

    The rotor speeds are the model's own along the logged commands (:func:`rotor_trajectory`), so their
    telemetry is a measurement (weighted by its noise) and never a noisy regressor. ``theta0``: the first
    guess (default: the reference values 30 % too high, as the PINNs start, and ``tau_m`` = 50 ms);
    ``noise``: the residuals' weights (default: the dataset's own noise model).
    """
    noise = NoiseModel(**ds.meta["noise"]) if noise is None else noise
    if np.any(_sigma(noise) <= 0):
        raise SimInputError("the estimator weights residuals by the noise: every standard deviation must be > 0")
    p = QuadParams(**ds.meta["params"])
    theta = np.r_[QuadParams().theta * 1.3, 0.05] if theta0 is None else np.asarray(theta0, dtype=float).copy()
    if theta.shape != (7,) or not np.all(theta > 0):
        raise SimInputError(f"theta0 must be 7 positive values {LAG_THETA_NAMES}; found {theta0!r}")
    flights = _flights(ds, split)
    x, _, y, n_meas, _ = flights
    Sig = np.diag(noise.state_std ** 2)

    def residuals(th, L, stride):
        F_x, S_x, _, use, n_pred, S_n, ok = _linearize(th, flights, p, stride, state=False)
        r = np.concatenate([np.linalg.solve(L, (y[use] - F_x)[..., None]).ravel(),
                            ((n_meas[ok] - n_pred) / noise.rotor_speed).ravel()])
        J = -np.concatenate([np.linalg.solve(L, S_x * th).reshape(-1, 7),
                             (S_n * th / noise.rotor_speed).reshape(-1, 7)])
        return J, r

    def fit(th, L, stride):
        J, r = residuals(th, L, stride)
        for it in range(1, max_iter + 1):
            cost = 0.5 * float(r @ r)
            delta = np.linalg.lstsq(J, -r, rcond=None)[0]
            std = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
            step = 1.0
            while True:     # halve a step that does not lower the cost
                trial = th * (1.0 + step * delta)
                if np.all(trial > 0):
                    J_t, r_t = residuals(trial, L, stride)
                    if 0.5 * float(r_t @ r_t) <= cost or step < 1e-6:
                        break
                step *= 0.5
            th, J, r = trial, J_t, r_t
            if np.max(np.abs(step * delta) / std) < tol:
                return th, J, it, True
        return th, J, max_iter, False

    # The first passes on every k-th period (about PILOT_SIZE transitions), the last on all of them.
    pilot = max(1, int(np.sum(~np.any(flights[4], axis=-1))) // PILOT_SIZE)
    iterations = 0
    for k in range(WEIGHT_PASSES):
        stride = 1 if k == WEIGHT_PASSES - 1 else pilot
        _, _, A, use, _, _, _ = _linearize(theta, flights, p, stride)
        L = np.linalg.cholesky(Sig + A @ Sig @ np.swapaxes(A, 1, 2))
        theta, J, it, converged = fit(theta, L, stride)
        iterations += it
    std = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    return LagEstimate(theta=theta, std_rel=std, iterations=iterations, converged=converged,
                       n_transitions=int(use.sum()))


__all__ = ["LAG_THETA_NAMES", "LagEstimate", "LagFisher", "estimate_with_lag", "lag_fisher",
           "lag_sensitivities", "lag_sensitivity_function", "rotor_trajectory", "true_theta7"]
