"""Nonlinear MPC with CasADi + IPOPT, multiple shooting.

Decision variables ``X`` (12, N + 1) and ``U`` (4, N); constraints
``X[:, k + 1] = F(X[:, k], U[:, k])``, ``X[:, 0] = measured state``, the
rotor-feasible wrench set ``0 <= M^-1 U[:, k] / n_max^2 <= 1`` and attitude
bounds on ``X[3:5, 1:]``; cost as the LTV-MPC (tracking ``Q`` against the
reference states, ``R`` on ``u - u_ff`` with ``u_ff`` the model's own
feed-forward, Riccati terminal cost ``P``).

``F`` over the whole horizon is one CasADi function of ``(X[:, :N], U)``:

* analytic model: the CasADi RK4 step mapped over the horizon;
* ONNX model: a ``casadi.Callback`` that evaluates all N stages in one
  onnxruntime call, with a Jacobian callback that takes ``A_k``, ``B_k`` from
  the derivative graph in one call and a declared block-diagonal sparsity
  (``has_jac_sparsity`` / ``get_jac_sparsity``).

By default IPOPT uses a limited-memory Hessian for every model (callbacks
give no second derivatives; the analytic model gets the same, for a fair
timing comparison), iteration and CPU-time limits, and a warm start from the
shifted previous solution. ``NMPCSettings(hessian="exact")`` gives it the
exact Hessian of the Lagrangian instead: the analytic model's, or an ONNX
model's through its graph imported as a CasADi expression
(:mod:`mpc.prediction.symbolic`; dense networks). That converges where the limited-memory Hessian stops at
IPOPT's "acceptable" level, at several seconds per solve with a PINN: a
reference for converged solutions, not a controller. Failures are handled as
in :mod:`mpc.controllers.ltv`.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from sim.params import NU

from .base import MPCBase, shift_stages
from .controller import ControlInfo, Reference, Timer, check_common_settings, check_measured, check_state
from ..errors import ConfigurationError
from ..prediction.models import AnalyticModel, PredictionModel

SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


@dataclass(frozen=True)
class NMPCSettings:
    """Settings of :class:`NMPC` (units in comments)."""

    horizon: int = 30                 # steps of DT = 0.01 s
    attitude_limit_rad: float = 1.0   # |roll|, |pitch| bound on predicted states, rad
    max_iter: int = 100               # IPOPT iterations per period
    # IPOPT CPU-time limit per period, s (0 = none). A period stopped by it depends on the machine's speed, so a
    # flight in ideal timing runs without it (mpc.controllers.factory.make_controller) and is reproducible.
    time_limit_s: float = 1.0
    # IPOPT tolerance (on the scaled problem). Measured (figure-8, one run): 1e-6 took 68 ms per period with
    # the proposed PINN (18 iterations) and 86 ms with the oracle; 1e-4 took 45 and 57 ms, same tracking error.
    tol: float = 1e-4
    hessian: str = "limited-memory"   # IPOPT's Hessian: "limited-memory" or "exact" (see the module docstring)

    def __post_init__(self):
        check_common_settings(self.horizon, self.attitude_limit_rad, self.max_iter)
        if not self.time_limit_s >= 0:
            raise ConfigurationError(f"time_limit_s must be >= 0 (0: no limit); found {self.time_limit_s}")
        if self.hessian not in ("limited-memory", "exact"):
            raise ConfigurationError(f"hessian must be 'limited-memory' or 'exact'; found {self.hessian!r}")


def _block_diagonal(n_stages: int, rows: int, cols: int):
    """Sparsity of a block-diagonal (rows N) x (cols N) matrix and the CCS order of its dense blocks."""
    r, c, ids = [], [], []
    for k in range(n_stages):
        for j in range(cols):
            for i in range(rows):
                r.append(k * rows + i)
                c.append(k * cols + j)
                ids.append(k * rows * cols + i * cols + j)   # index into blocks (N, rows, cols) raveled
    sp = ca.Sparsity.triplet(n_stages * rows, n_stages * cols, r, c)
    # Column-major order of (col, row) pairs is exactly the order generated above.
    return sp, np.asarray(ids)


class _HorizonJacobian(ca.Callback):
    """Jacobian of :class:`_Horizon`: block-diagonal A_k and B_k from the derivative graph."""

    def __init__(self, name, model, n, opts):
        ca.Callback.__init__(self)
        self.model, self.n, self.nx = model, n, model.nx
        self.sp_x, self.ids_x = _block_diagonal(n, self.nx, self.nx)
        self.sp_u, self.ids_u = _block_diagonal(n, self.nx, NU)
        self.construct(name, opts)

    def get_n_in(self):
        return 3

    def get_n_out(self):
        return 2

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(NU if i == 1 else self.nx, self.n)  # X, U, then the nominal output

    def get_sparsity_out(self, i):
        return self.sp_x if i == 0 else self.sp_u

    def eval(self, arg):
        _, A, B = self.model.linearize(np.asarray(arg[0]).T, np.asarray(arg[1]).T)
        return [ca.DM(self.sp_x, A.ravel()[self.ids_x]), ca.DM(self.sp_u, B.ravel()[self.ids_u])]


class _Horizon(ca.Callback):
    """All N stages of an ONNX model in one onnxruntime call: (nx x N, 4 x N) -> nx x N."""

    def __init__(self, name, model, n, opts=None):
        ca.Callback.__init__(self)
        self.model, self.n, self.nx = model, n, model.nx
        self.construct(name, {} if opts is None else opts)

    def get_n_in(self):
        return 2

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.nx if i == 0 else NU, self.n)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(self.nx, self.n)

    def eval(self, arg):
        return [ca.DM(self.model.step(np.asarray(arg[0]).T, np.asarray(arg[1]).T).T)]

    def has_jacobian(self):
        return True

    def get_jacobian(self, name, inames, onames, opts):
        # Keep a reference: CasADi does not own Python callbacks.
        self._jac = _HorizonJacobian(name, self.model, self.n, opts)
        return self._jac

    def has_jac_sparsity(self, oind, iind):
        return True

    def get_jac_sparsity(self, oind, iind, symmetric):
        return _block_diagonal(self.n, self.nx, self.nx if iind == 0 else NU)[0]


class NMPC(MPCBase):
    """Nonlinear MPC on any :class:`mpc.prediction.models.PredictionModel` (parameters as in
    :class:`mpc.controllers.ltv.LTVMPC`)."""

    def __init__(self, model: PredictionModel, reference: Reference | None = None,
                 settings: NMPCSettings | None = None, spec=None, Q=None, R=None):
        self._setup(model, reference, spec, Q, R)
        self._offset: np.ndarray | None = None    # a disturbance's one-period effect (offset-free control)
        self.s = NMPCSettings() if settings is None else settings
        self.N = N = self.s.horizon
        self._build(N)
        self._w: np.ndarray | None = None

    def _symbolic_step(self):
        """The model's one-period step as a CasADi function (for the exact Hessian)."""
        F = getattr(self.model, "casadi_step", None)
        if F is not None:
            return F
        path = getattr(self.model, "path", None)
        if path is None:
            raise ConfigurationError(f"hessian='exact' needs a model with a CasADi expression; "
                                     f"{type(self.model).__name__} has none")
        from ..prediction.symbolic import casadi_step

        return casadi_step(path)

    def _build(self, N: int) -> None:
        # IPOPT works on scaled variables: X = sx * Xs, U = u_hover + su * Us, with sx and su the
        # acceptable deviations of the default weights (torques are ~1e-3 N m; unscaled, the
        # limited-memory Hessian needed ~50 iterations per period).
        nx = self.nx
        self.inputs = self.lqr.inputs      # what may be commanded at the model's level
        self._sx = self.state_scale.copy()
        self._su = self.inputs.scale
        Xs = ca.MX.sym("Xs", nx, N + 1)
        Us = ca.MX.sym("Us", NU, N)
        X = ca.mtimes(ca.diag(ca.DM(self._sx)), Xs)
        U = ca.repmat(ca.DM(self.u_hover), 1, N) + ca.mtimes(ca.diag(ca.DM(self._su)), Us)
        x0 = ca.MX.sym("x0", nx)
        ref = ca.MX.sym("ref", nx, N + 1)
        uref = ca.MX.sym("uref", NU, N)
        exact = self.s.hessian == "exact"
        if isinstance(self.model, AnalyticModel):
            F = self.model.casadi_step.map(N, "serial")
            self._horizon = None
        elif exact:
            F = self._symbolic_step().map(N, "serial")
            self._horizon = None
        else:
            self._horizon = F = _Horizon("horizon", self.model, N)
        off = ca.MX.sym("off", nx)          # a disturbance's one-period effect G d (offset-free control)
        Xn = F(X[:, :N], U) + ca.repmat(off, 1, N)
        Q, R, P = ca.DM(self.Q), ca.DM(self.R), ca.DM(self.P)
        E = X - ref
        D = U - uref
        cost = (ca.sum2(ca.sum1(E[:, :N] * ca.mtimes(Q, E[:, :N]))) + ca.sum2(ca.sum1(D * ca.mtimes(R, D)))
                + ca.mtimes([E[:, N].T, P, E[:, N]]))
        load = ca.DM(self.inputs.matrix)     # lower <= L u <= upper (the wrench level: rotor loads n^2 / n_max^2)
        inv_sx = ca.DM(1.0 / self._sx)
        g = ca.vertcat(ca.vec((Xn - X[:, 1:]) * ca.repmat(inv_sx, 1, N)), (X[:, 0] - x0) * inv_sx,
                       ca.vec(ca.mtimes(load, U)))
        self._n_dyn = nx * N + nx
        w = ca.vertcat(ca.vec(Xs), ca.vec(Us))
        nlp = {"x": w, "f": cost, "g": g, "p": ca.vertcat(x0, ca.vec(ref), ca.vec(uref), off)}
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                "ipopt.hessian_approximation": self.s.hessian, "ipopt.max_iter": self.s.max_iter,
                "ipopt.tol": self.s.tol, "error_on_fail": False}
        if self.s.time_limit_s > 0:
            opts["ipopt.max_cpu_time"] = self.s.time_limit_s
        if isinstance(self.model, AnalyticModel):
            opts["expand"] = True   # analytic model: SX graph, much cheaper to evaluate than MX
        self._solver = ca.nlpsol("nmpc", "ipopt", nlp, {
            **opts, "ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-9,
            "ipopt.warm_start_mult_bound_push": 1e-9, "ipopt.mu_init": 1e-5, "ipopt.mu_strategy": "adaptive"})
        lim = self.s.attitude_limit_rad
        lbX = np.full((nx, N + 1), -np.inf)
        ubX = np.full((nx, N + 1), np.inf)
        lbX[3:5, 1:], ubX[3:5, 1:] = -lim / self._sx[3:5, None], lim / self._sx[3:5, None]
        self._lbw = np.concatenate([lbX.ravel(order="F"), np.full(NU * N, -np.inf)])
        self._ubw = np.concatenate([ubX.ravel(order="F"), np.full(NU * N, np.inf)])
        self._lbg = np.concatenate([np.zeros(self._n_dyn), np.tile(self.inputs.lower, N)])
        self._ubg = np.concatenate([np.zeros(self._n_dyn), np.tile(self.inputs.upper, N)])
        self._nX = nx * (N + 1)
        self._lam = None

    def update_settings(self, **changes) -> None:
        """Change settings (for example ``time_limit_s``); rebuilds the solver, keeps the warm start."""
        import dataclasses

        new = dataclasses.replace(self.s, **changes)
        if new.horizon != self.N:
            raise ConfigurationError("horizon cannot change after construction; build a new NMPC")
        self.s = new
        w = self._w
        self._build(self.N)
        self._w = w

    def _unpack(self, w):
        """Physical X (N + 1, nx) and U (N, 4) from the scaled decision vector."""
        N = self.N
        return (w[:self._nX].reshape(N + 1, self.nx) * self._sx,
                self.u_hover + w[self._nX:].reshape(N, NU) * self._su)

    def _pack(self, X, U):
        return np.concatenate([(X / self._sx).ravel(), ((U - self.u_hover) / self._su).ravel()])

    def _guess(self, x, u_ref):
        N = self.N
        if self._w is None:
            return self._pack(np.tile(x, (N + 1, 1)), u_ref)
        X, U = self._unpack(self._w)
        X, U = shift_stages(X), shift_stages(U)
        X[0] = x
        return self._pack(X, U)

    def solve_from(self, x, t: float, X0, U0):
        """Solve the period at ``(x, t)`` from the guess ``(X0 (N + 1, nx), U0 (N, 4))``, no warm start.

        ``x`` is the full state (nx,). Returns ``(X (N + 1, nx), U (N, 4), IPOPT's return status)``; the
        controller's own warm start is left as it was.
        """
        x = check_state(x, nx=self.nx)
        X0, U0 = np.asarray(X0, dtype=float), np.asarray(U0, dtype=float)
        if X0.shape != (self.N + 1, self.nx) or U0.shape != (self.N, NU):
            raise ConfigurationError(f"X0 must be ({self.N + 1}, {self.nx}) and U0 ({self.N}, 4); "
                                     f"found {X0.shape} and {U0.shape}")
        ref, u_ref = self._horizon_reference(t)
        X0 = X0.copy()
        X0[0] = x
        sol = self._solver(x0=self._pack(X0, U0), p=self._parameters(x, ref, u_ref),
                           lbx=self._lbw, ubx=self._ubw, lbg=self._lbg, ubg=self._ubg)
        X, U = self._unpack(np.asarray(sol["x"]).ravel())
        return X, U, self._solver.stats().get("return_status", "unknown")

    def _parameters(self, x, ref, u_ref) -> np.ndarray:
        off = np.zeros(self.nx) if self._offset is None else self._offset
        return np.concatenate([x, ref.ravel(), u_ref.ravel(), off])

    def _set_offset(self, offset) -> None:
        self._offset = offset

    def __call__(self, x, t: float):
        """Input (4,) and :class:`ControlInfo` for the measured state ``x`` at time ``t`` (s)."""
        x = check_measured(x, self.model)
        N = self.N
        with Timer() as tm:
            x = self.tracker.full(x, t)     # the measured state, with the model's extra states carried
            ref, u_ref = self._horizon_reference(t)
            args = dict(x0=self._guess(x, u_ref), p=self._parameters(x, ref, u_ref),
                        lbx=self._lbw, ubx=self._ubw,
                        lbg=self._lbg, ubg=self._ubg)
            if self._lam is not None:
                args.update(lam_x0=self._lam[0], lam_g0=self._lam[1])
            sol = self._solver(**args)
            st = self._solver.stats()
            status = st.get("return_status", "unknown")
            w = np.asarray(sol["x"]).ravel()
            ok = status in SUCCESS and np.all(np.isfinite(w))
            fallback = None
            if ok:
                self._w = w
                self._lam = (np.asarray(sol["lam_x"]).ravel(), np.asarray(sol["lam_g"]).ravel())
                self._success()
                u = self._unpack(w)[1][0]
            else:
                self._lam = None
                fallback = self._failure(self._w is not None)
                if fallback == "lqr":
                    u = self.lqr.input(x, ref[0], u_ref[0])
                    self._w = None
                else:
                    X, U = self._unpack(self._w)
                    self._w = self._pack(shift_stages(X), shift_stages(U))
                    u = U[1]
            u = self.inputs.project(u)
        predicted = None if self._w is None else self._unpack(self._w)[0].copy()
        return u, ControlInfo(solve_time_s=tm.elapsed, status="optimal" if ok else status,
                              iterations=int(st.get("iter_count", 0)), predicted=predicted, fallback=fallback,
                              extra={"counts": dict(self.counts), "ipopt_status": status})
