"""Fisher information and Cramer-Rao bounds for (m, Jxx, Jyy, Jzz, kt, kq).

The measurement model is the one a one-step identifier
(the PINN's data loss) uses: each logged transition gives

    y_k = x_{k+1} = F(x_k, u_k; theta) + e_k,

with ``F`` one control period of the nominal model (RK4, 10 substeps of
1 ms, CasADi), and, with wrench inputs, rotor-speed telemetry

    n_k = sqrt(M(kt, kq)^-1 w_k) + e_n.

Sensitivities ``S_k = dF/dtheta`` come from CasADi's automatic
differentiation through the RK4 steps. The noise on ``x_k`` and on
``x_{k+1}`` both enter the residual, so its covariance is taken as
``Sigma + A_k Sigma A_k^T`` with ``A_k = dF/dx`` (first order; the
correlation between consecutive residuals is neglected). Then

    FIM = sum_k S_k^T (Sigma + A_k Sigma A_k^T)^-1 S_k  +  sum_k,i (dn_ki/dtheta)^2 / sigma_n^2.

Everything is reported in relative coordinates (per unit relative change of
each parameter), so CRLB standard deviations read directly as fractions of
the true values and the scale direction is (1, 1, 1, 1, 1, 1) / sqrt(6).

Input parameterizations:

* ``"wrench"``: the input is the realized wrench ``[T, tau]``; the rigid
  body only sees ``m`` and ``J``, and ``kt, kq`` are identifiable through
  the rotor telemetry.
* ``"motor"``: the input is the rotors' ``n^2``; the wrench is ``M(kt, kq)
  n^2``, telemetry carries no information (it is the input), and scaling
  all six parameters together leaves the dynamics unchanged: a null
  direction of the FIM.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .._validate import as_batch, broadcast_batch, choice
from ..equations.compiled import compiled
from ..equations.dynamics_casadi import step_function
from ..errors import SimInputError
from ..params import NX, THETA_NAMES, NoiseModel, QuadParams
from ..vehicles.rotors import allocate, mixer

#: Threads of a mapped CasADi evaluation of the sensitivities (each sample is computed alone, so the result
#: does not depend on the count).
MAP_THREADS = max(1, min(2, os.cpu_count() or 1))

INPUT_KINDS = ("wrench", "motor")
#: Eigenvalues below this fraction of the largest count as zero (rank).
RANK_RTOL = 1e-10
#: Rotors slower than this fraction of hover speed are left out of the telemetry channel
#: (the speed's sensitivity grows like 1 / n near zero).
MIN_ROTOR_FRACTION = 0.1


@dataclass(frozen=True)
class FisherResult:
    """Fisher information of one dataset, input kind and noise model.

    All matrices are in relative coordinates: parameter ``i`` is
    ``theta_i (1 + delta_i)`` and derivatives are taken with respect to
    ``delta``.
    """

    inputs: str                    # "wrench" or "motor"
    n_samples: int                 # transitions used
    n_rotor_samples: int           # rotor-speed readings used (telemetry channel)
    theta: np.ndarray              # (6,) true values, SI / RU units
    fim: np.ndarray                # (6, 6) total
    fim_dynamics: np.ndarray       # (6, 6) state channel
    fim_rotor: np.ndarray          # (6, 6) rotor-telemetry channel
    eigenvalues: np.ndarray        # (6,) ascending
    eigenvectors: np.ndarray       # (6, 6) columns, ascending with the eigenvalues
    rank: int                      # eigenvalues above RANK_RTOL * max
    crlb_rel: np.ndarray           # (6,) CRLB standard deviation / true value (inf if not identifiable)

    @property
    def crlb_std(self) -> np.ndarray:
        """CRLB standard deviation in the parameters' own units, (6,)."""
        return self.crlb_rel * self.theta

    @property
    def crlb_pct(self) -> np.ndarray:
        """CRLB standard deviation in % of the true value, (6,)."""
        return 100.0 * self.crlb_rel

    @property
    def weakest_direction(self) -> np.ndarray:
        """Unit eigenvector (relative coordinates) of the smallest eigenvalue, largest entry positive."""
        v = self.eigenvectors[:, 0]
        return v * np.sign(v[np.argmax(np.abs(v))])

    @property
    def weakest_direction_abs(self) -> np.ndarray:
        """The weakest direction in absolute parameter units, normalized to length 1."""
        v = self.weakest_direction * self.theta
        return v / np.linalg.norm(v)

    @property
    def scale_direction_cos(self) -> float:
        """|cos| between the weakest direction and the scale direction (all parameters scaled together).

        In relative coordinates the scale direction is (1, ..., 1) / sqrt(6); in
        absolute units it is theta itself; the cosine is the same in both.
        """
        v_abs = self.weakest_direction_abs
        return float(abs(v_abs @ self.theta) / np.linalg.norm(self.theta))

    def to_dict(self) -> dict:
        """Plain-JSON view (non-finite bounds become ``None``)."""
        def fin(a):
            return [float(v) if np.isfinite(v) else None for v in np.ravel(a)]
        return {
            "inputs": self.inputs,
            "n_samples": self.n_samples,
            "n_rotor_samples": self.n_rotor_samples,
            "parameters": list(THETA_NAMES),
            "theta_true": fin(self.theta),
            "rank": self.rank,
            "eigenvalues": fin(self.eigenvalues),
            "condition_number": (float(self.eigenvalues[-1] / self.eigenvalues[0])
                                 if self.rank == 6 else None),
            "crlb_std": dict(zip(THETA_NAMES, fin(self.crlb_std))),
            "crlb_pct": dict(zip(THETA_NAMES, fin(self.crlb_pct))),
            "weakest_direction_relative": dict(zip(THETA_NAMES, fin(self.weakest_direction))),
            "weakest_direction_absolute": dict(zip(THETA_NAMES, fin(self.weakest_direction_abs))),
            "weakest_vs_scale_direction_abs_cos": self.scale_direction_cos,
            "fim_relative": [fin(r) for r in self.fim],
        }


# ------------------------------------------------------------ sensitivities
_FUNCS: dict = {}


def _jac_function(p: QuadParams, inputs: str, state: bool = True) -> ca.Function:
    """CasADi function (x, u, theta) -> (dF/dtheta (12, 6), dF/dx (12, 12)), or dF/dtheta alone; cached.

    Compiled to C (:mod:`sim.equations.compiled`, unoptimized: it is evaluated on whole datasets, a few times per
    job), with the same results as CasADi's virtual machine; the first call on a machine compiles it (about 2 s).
    """
    # theta is an input of the function, so one function serves every theta with the same constants.
    key = (p.with_theta(QuadParams().theta), inputs, state)
    if key not in _FUNCS:
        _FUNCS[key] = compiled(sensitivity_function(p, inputs, state), "batch")
    return _FUNCS[key]


def sensitivity_function(p: QuadParams, inputs: str, state: bool = True) -> ca.Function:
    """The CasADi function of :func:`_jac_function` before compilation (for
    :func:`sim.equations.compiled.precompile`)."""
    F = step_function(p, symbolic_theta=True, inputs=inputs)
    x, u, th = ca.SX.sym("x", NX), ca.SX.sym("u", 4), ca.SX.sym("theta", 6)
    xn = F(x, u, th)
    outs = [ca.densify(ca.jacobian(xn, th))] + ([ca.densify(ca.jacobian(xn, x))] if state else [])   # for buffers
    return ca.Function(f"sens_{inputs}" + ("_state" if state else ""), [x, u, th], outs)


#: The sensitivities the Fisher table, the evaluation and the classical estimator use: (inputs, state).
USED_SENSITIVITIES = (("wrench", True), ("motor", True), ("wrench", False))
#: Those the Fisher table alone uses.
FISHER_SENSITIVITIES = (("wrench", True), ("motor", True))


def _map_eval(f: ca.Function, x: np.ndarray, u: np.ndarray, theta: np.ndarray):
    """Evaluate ``f`` (dense outputs) on N samples with one mapped CasADi call; outputs (N, rows, cols).

    The arrays are handed to CasADi as buffers, without its matrix type: a C-ordered (N, 12) array is the
    column-major (12, N) input of the map, and its (rows, N cols) output is a C-ordered (N, cols, rows) array.
    """
    n = x.shape[0]
    fm = f.map(n, "thread", MAP_THREADS)
    args = [np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(u, dtype=float),
            np.ascontiguousarray(np.broadcast_to(np.asarray(theta, dtype=float), (n, theta.shape[0])))]
    buf, evaluate = fm.buffer()
    for k, a in enumerate(args):
        buf.set_arg(k, memoryview(a))
    outs = []
    for k in range(f.n_out()):
        if f.sparsity_out(k).nnz() != f.numel_out(k):
            raise ValueError(f"{f.name()}: output {k} is sparse; build it with casadi.densify")
        o = np.empty((n, f.size2_out(k), f.size1_out(k)))
        buf.set_res(k, memoryview(o))
        outs.append(o)
    evaluate()
    return [o.transpose(0, 2, 1) for o in outs]


def sensitivities(x, u, p: QuadParams | None = None, inputs: str = "wrench",
                  chunk: int = 5000, state: bool = True):
    """Sensitivities of one control period to the parameters and to the state.

    Parameters
    ----------
    x : array_like, shape (N, 12)
        States at the start of each period.
    u : array_like, shape (N, 4)
        Realized wrench (N, N m) for ``inputs="wrench"``; rotor speeds
        squared (RU^2) for ``inputs="motor"``.
    p : QuadParams, optional
        Parameters at which to differentiate (reference values when omitted).
    inputs : {"wrench", "motor"}
        Meaning of ``u``.
    chunk : int
        Samples per CasADi call (memory bound).
    state : bool
        Also return ``A``; without it the call costs about a third.

    Returns
    -------
    S : numpy.ndarray, shape (N, 12, 6)
        ``d x_next / d theta`` in absolute units (per unit of each parameter).
    A : numpy.ndarray, shape (N, 12, 12)
        ``d x_next / d x`` (only with ``state``).
    """
    p = QuadParams() if p is None else p
    inputs = choice(inputs, "inputs", INPUT_KINDS)
    x = np.atleast_2d(as_batch(x, "x", NX))
    u = np.atleast_2d(as_batch(u, "u", 4))
    x, u = broadcast_batch(x, u)
    x, u = x.reshape(-1, NX), u.reshape(-1, 4)
    f = _jac_function(p, inputs, state)
    parts = [_map_eval(f, x[lo:lo + chunk], u[lo:lo + chunk], p.theta) for lo in range(0, x.shape[0], chunk)]
    S = np.concatenate([q[0] for q in parts])
    return (S, np.concatenate([q[1] for q in parts])) if state else S


def residual_covariance(A: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """Covariance (N, 12, 12) of ``x_{k+1} - F(x_k, u_k)`` with measurement noise on both ends: ``Sigma + A Sigma A^T``.

    ``A`` (N, 12, 12) is ``dF/dx`` at each sample, ``Sigma`` the diagonal covariance of ``noise``.
    """
    Sigma = np.diag(noise.state_std ** 2)
    return Sigma + A @ Sigma @ np.swapaxes(A, 1, 2)


def rotor_sensitivities(w, p: QuadParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rotor speeds for wrench ``w`` and their derivative with respect to theta.

    ``n_i = sqrt((M(kt, kq)^-1 w)_i)``. Since ``M = diag(kt, kt, kt, kq) M0``,
    ``n_i^2 = sum_j inv(M0)_ij w_j / c_j`` with ``c = (kt, kt, kt, kq)``.

    Parameters
    ----------
    w : array_like, shape (N, 4)
        Realized wrench, N and N m.
    p : QuadParams, optional

    Returns
    -------
    n : numpy.ndarray, shape (N, 4)
        Rotor speeds, RU (``nan`` where ``n^2 < 0``).
    dn : numpy.ndarray, shape (N, 4, 6)
        ``d n / d theta`` in absolute units; only the kt, kq columns are non-zero.
    """
    p = QuadParams() if p is None else p
    w = np.atleast_2d(as_batch(w, "w", 4))
    lever = p.lever
    M0 = np.array(mixer(1.0, 1.0, lever), dtype=float)  # the mixer with kt = kq = 1
    M0inv = np.linalg.inv(M0)
    part_t = (w[:, :3] / p.kt) @ M0inv[:, :3].T     # thrust and roll/pitch part of n^2
    part_q = np.outer(w[:, 3] / p.kq, M0inv[:, 3])  # yaw part of n^2
    n_sq = part_t + part_q
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.sqrt(n_sq)
        dn = np.zeros(w.shape[:1] + (4, 6))
        dn[:, :, 4] = -part_t / p.kt / (2.0 * n)
        dn[:, :, 5] = -part_q / p.kq / (2.0 * n)
    return n, dn


# ------------------------------------------------------------------- FIM
def fisher_information(x, u, p: QuadParams | None = None, noise: NoiseModel | None = None, *,
                       inputs: str = "wrench", rotor_telemetry: bool = True,
                       rotor_mask=None) -> FisherResult:
    """Fisher information of a set of logged transitions.

    Parameters
    ----------
    x : array_like, shape (N, 12)
        True states at the start of each transition.
    u : array_like, shape (N, 4)
        Realized wrench (``inputs="wrench"``) or rotor speeds squared
        (``inputs="motor"``) during each transition.
    p : QuadParams, optional
        True parameters (reference values when omitted).
    noise : NoiseModel, optional
        Measurement noise; ``NoiseModel()`` when omitted. Every state
        standard deviation must be > 0 (and the rotor one, if the telemetry
        channel is used).
    inputs : {"wrench", "motor"}
    rotor_telemetry : bool
        Add the rotor-speed channel (wrench inputs only: with motor inputs
        the rotor speeds are the input and carry no information).
    rotor_mask : array_like of bool, shape (N, 4), optional
        Rotor readings to leave out (for example saturated rotors).

    Returns
    -------
    FisherResult
    """
    p = QuadParams() if p is None else p
    noise = NoiseModel() if noise is None else noise
    inputs = choice(inputs, "inputs", INPUT_KINDS)
    std = noise.state_std
    if np.any(std <= 0):
        raise SimInputError("noise must have positive standard deviations for every state; "
                            f"found {dict(zip(('position', 'attitude', 'body_rate', 'velocity'), std[::3]))}")
    x = np.atleast_2d(as_batch(x, "x", NX))
    u = np.atleast_2d(as_batch(u, "u", 4))
    if x.shape[0] != u.shape[0]:
        raise SimInputError(f"x and u must have the same number of samples; found {x.shape[0]} and {u.shape[0]}")
    theta = p.theta

    S, A = sensitivities(x, u, p, inputs)
    S_rel = S * theta                                      # (N, 12, 6)
    cov = residual_covariance(A, noise)                    # (N, 12, 12)
    fim_dyn = np.einsum("nij,nik->jk", S_rel, np.linalg.solve(cov, S_rel))

    fim_rot = np.zeros((6, 6))
    n_rot = 0
    if rotor_telemetry and inputs == "wrench":
        if noise.rotor_speed <= 0:
            raise SimInputError("noise.rotor_speed must be > 0 for the rotor-telemetry channel; found 0")
        n, dn = rotor_sensitivities(u, p)
        use = np.isfinite(n) & (n >= MIN_ROTOR_FRACTION * p.n_hover)
        if rotor_mask is not None:
            mask = np.asarray(rotor_mask, dtype=bool)
            if mask.shape != n.shape:
                raise SimInputError(f"rotor_mask must have shape {n.shape}; found {mask.shape}")
            use &= ~mask
        dn_rel = np.where(use[..., None], dn, 0.0) * theta
        fim_rot = np.einsum("nij,nik->jk", dn_rel, dn_rel) / noise.rotor_speed ** 2
        n_rot = int(use.sum())

    fim = fim_dyn + fim_rot
    fim = 0.5 * (fim + fim.T)
    evals, evecs = np.linalg.eigh(fim)
    rank = int(np.sum(evals > RANK_RTOL * evals[-1]))
    if rank == 6:
        crlb_rel = np.sqrt(np.diag(np.linalg.inv(fim)))
    else:
        # A parameter with a component along the null space has no finite bound.
        null = evecs[:, :6 - rank]
        along = np.linalg.norm(null, axis=1) > 1e-6
        pinv = np.linalg.pinv(fim, rcond=RANK_RTOL, hermitian=True)
        crlb_rel = np.where(along, np.inf, np.sqrt(np.abs(np.diag(pinv))))
    return FisherResult(inputs=inputs, n_samples=int(x.shape[0]), n_rotor_samples=n_rot, theta=theta,
                        fim=fim, fim_dynamics=fim_dyn, fim_rotor=fim_rot, eigenvalues=evals,
                        eigenvectors=evecs, rank=rank, crlb_rel=crlb_rel)


def fisher_from_dataset(ds, inputs: str = "wrench", noise: NoiseModel | None = None,
                        p: QuadParams | None = None) -> FisherResult:
    """FIM of a noise-free :class:`sim.identification.excitation.Dataset` (its states are the truth).

    The noise model is the one the bound is computed for (default
    ``NoiseModel()``, the data generator's default). Saturated rotor readings
    are left out of the telemetry channel.
    """
    if not np.all(np.asarray([ds.meta["noise"][k] for k in ds.meta["noise"]]) == 0):
        raise SimInputError("dataset must be noise-free (make_dataset(..., noise=NoiseModel.none())): "
                            "the FIM is evaluated at the true states")
    p = QuadParams(**ds.meta["params"]) if p is None else p
    x = ds.x.reshape(-1, NX)
    w = ds.wrench.reshape(-1, 4)
    if inputs == "motor":
        u = np.clip(allocate(w, p), 0.0, None)
    else:
        u = w
    return fisher_information(x, u, p, noise, inputs=inputs, rotor_mask=ds.saturated.reshape(-1, 4))


def fisher_table(n_traj: int = 20, duration: float = 10.0, seed: int = 0,
                 noise: NoiseModel | None = None, progress: bool = False) -> dict:
    """FIM summary for each regime x input kind (the ``pinnmpc fisher`` table).

    Returns a JSON-ready dict with the settings and one entry per case.
    """
    from .excitation import make_dataset

    noise = NoiseModel() if noise is None else noise
    cases = []
    combos = [(r, k) for r in ("small", "aggressive") for k in INPUT_KINDS]
    it = combos
    bar = None
    if progress:
        from tqdm import tqdm
        bar = it = tqdm(combos, desc="fisher", unit="case", leave=False)
    data = {}
    for regime, kind in it:
        if bar is not None:
            bar.set_postfix_str(f"{regime}/{kind}")
        if regime not in data:
            data[regime] = make_dataset(regime, n_traj, duration, seed, noise=NoiseModel.none())
        res = fisher_from_dataset(data[regime], kind, noise)
        cases.append({"regime": regime, **res.to_dict()})
    return {
        "settings": {"n_traj": n_traj, "duration_s": duration, "seed": seed,
                     "noise": dataclasses.asdict(noise), "rank_rtol": RANK_RTOL,
                     "coordinates": "relative (per unit relative change of each parameter)"},
        "cases": cases,
    }
