"""LTV-MPC with OSQP.

Each control period the prediction model is linearized along the shifted
previous plan in one batched call, ``x_{k+1} = A_k x_k + B_k u_k + c_k``,
and one sparse QP is solved::

    min  sum_k (x_k - r_k)' Q (x_k - r_k) + (u_k - f_k)' R (u_k - f_k) + (x_N - r_N)' P (x_N - r_N)
    s.t. x_0 = measured state, the linearized dynamics,
         0 <= M^-1 u_k / n_max^2 <= 1  (rotor-feasible wrench set, linear in u; each row a rotor's load; at the
                                        ctbr and ctatt levels, bounds on thrust, rates and angles instead:
                                        mpc.prediction.spec.InputSet)
         |phi_k|, |theta_k| <= attitude limit,   k = 1 .. N

with ``r_k`` the reference states, ``f_k`` the model's own feed-forward
along them (:mod:`mpc.references.feedforward`), ``P`` the discrete Riccati solution of
the hover LQR and ``M``, ``n_max`` from the vehicle spec. The sparsity
pattern is built once; each period only its values, the linear cost and the
bounds are updated (``OSQP.update``) and the solver is warm-started with the
shifted previous solution.

Failure is data: a QP that does not solve makes the controller apply the
next input of the previous plan ("shifted_plan"); three failures in a row
fall back to the hover LQR ("lqr_fallback"). Both are counted.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from sim.params import NU

from .base import MPCBase, shift_stages
from .controller import ControlInfo, Reference, Timer, check_common_settings, check_measured
from .dense_qp import QP_SOLVERS
from ..errors import ConfigurationError
from ..prediction.models import PredictionModel
from .timing import PeriodClock

#: Status of a period whose plan could not be made before its deadline (:meth:`LTVMPC.set_deadline`).
DEADLINE_STATUS = "deadline"
#: Status of a period whose model returned NaN or inf along the plan (OSQP never sees it).
NON_FINITE_STATUS = "non-finite model output"
#: The parts of a period's time the QP controllers measure (s): the model's derivatives (and steps), the QP's
#: assembly (including OSQP's matrix update), OSQP's solve and the SQP's line search.
SPLIT = ("derivatives", "assembly", "osqp", "line_search")


def csc_in_entry_order(rows, cols, vals, shape):
    """A CSC matrix of the entries ``(rows[i], cols[i], vals[i])`` and ``perm``: CSC slot -> entry index.

    Later value updates in entry order go to OSQP as ``new_vals[perm]``. Every
    entry is kept in the pattern, zeros included (give placeholders for values
    that are zero now but may not be later).
    """
    vals = np.asarray(vals, dtype=float)
    ids = sp.csc_matrix((np.arange(1, len(vals) + 1, dtype=float), (rows, cols)), shape=shape)
    ids.sort_indices()
    perm = ids.data.astype(np.int64) - 1
    return sp.csc_matrix((vals[perm], ids.indices, ids.indptr), shape=shape), perm


@dataclass(frozen=True)
class LTVSettings:
    """Settings of :class:`LTVMPC` (units in comments)."""

    horizon: int = 30                 # steps of DT = 0.01 s
    attitude_limit_rad: float = 1.0   # |roll|, |pitch| bound on predicted states, rad (57 deg)
    constraints: bool = True          # rotor-feasible set and attitude bounds (False: unconstrained)
    max_iter: int = 4000              # OSQP iterations per period
    time_limit_s: float = 0.0         # OSQP wall-time limit per period, s (0 = none)
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5
    polish: bool = False
    # OSQP re-equilibrates the problem on every matrix update, and checks termination every
    # `check_termination` iterations. Measured (proposed PINN, N = 30, one run): its defaults 10 and 25
    # took 2.04 ms per period, 2 and 10 took 1.60 ms, with the same tracking error and no failures.
    scaling: int = 2                  # Ruiz equilibration iterations (OSQP `scaling`)
    check_termination: int = 10       # OSQP termination check interval, iterations
    # Precision of the model's Jacobians A, B in the QP ("float32" or "float64"; the model's step, and so the
    # defects, stay exact). A QP needs no more than 7 significant digits of them, and the float32 derivative graph
    # is the larger part of a period's time: measured (5x128 PINNs, 30 stages, one run) 1.2-2.0 ms against 2.1-2.7.
    jacobians: str = "float32"
    # The QP solver: "osqp" (sparse, states and inputs) or "daqp" (the QP condensed onto the inputs, a dense
    # active-set solver: mpc.controllers.dense_qp, the optional extra `dense`). A QP with the SQP's own Hessian stays
    # on OSQP.
    qp: str = "osqp"

    def __post_init__(self):
        check_common_settings(self.horizon, self.attitude_limit_rad, self.max_iter)
        if self.qp not in QP_SOLVERS:
            raise ConfigurationError(f"qp must be one of {', '.join(QP_SOLVERS)}; found {self.qp!r}")
        if self.time_limit_s < 0:
            raise ConfigurationError(f"time_limit_s must be >= 0; found {self.time_limit_s}")
        if self.jacobians not in ("float32", "float64"):
            raise ConfigurationError(f"jacobians must be 'float32' or 'float64'; found {self.jacobians!r}")
        for name in ("scaling", "check_termination"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ConfigurationError(f"{name} must be an integer >= 0; found {v!r}")


class LTVMPC(MPCBase):
    """Linear time-varying MPC on any :class:`mpc.prediction.models.PredictionModel`.

    Parameters
    ----------
    model : PredictionModel
        Prediction model (analytic or ONNX).
    reference : FlatTrajectory or callable, optional
        A flat trajectory (:mod:`mpc.references.trajectory`) or ``reference(times) -> (K, 12)``;
        hover at 1 m when omitted.
    settings : LTVSettings, optional
    spec : VehicleSpec, optional
        What the controller knows of the vehicle: rotor limits and mixer
        (:meth:`mpc.prediction.spec.VehicleSpec.from_model` when omitted). The hover
        trim, feed-forward, terminal cost and fallback come from the model.
    Q, R : array_like, optional
        Weights (:func:`mpc.controllers.lqr.default_weights` when omitted).
    """

    def __init__(self, model: PredictionModel, reference: Reference | None = None,
                 settings: LTVSettings | None = None, spec=None, Q=None, R=None):
        import osqp

        self._setup(model, reference, spec, Q, R)
        from .offset_free import DisturbedModel

        self.model = DisturbedModel(model)     # the prediction: the model plus a disturbance's offset, if any
        self.s = LTVSettings() if settings is None else settings
        N = self.s.horizon
        self.N = N
        self.nx_var = (N + 1) * self.nx
        # What may be commanded: lower <= L u <= upper (at the wrench level the rotor loads n^2 / n_max^2, unit-free).
        self.inputs = self.lqr.inputs
        self._load = self.inputs.matrix
        self._sx, self._su = self.state_scale, self.inputs.scale   # step sizes are measured in these
        self._build_pattern()
        self._status = osqp.SolverStatus
        self._deadline: float | None = None
        self.clock = PeriodClock()      # the timing rules of a period (its budget, its deadline, recent times)
        self._solver = osqp.OSQP()
        settings_ = dict(verbose=False, warm_starting=True, max_iter=self.s.max_iter, eps_abs=self.s.eps_abs,
                         eps_rel=self.s.eps_rel, polishing=self.s.polish,
                         scaling=self.s.scaling, check_termination=self.s.check_termination)
        if self.s.time_limit_s > 0:
            settings_["time_limit"] = self.s.time_limit_s
        self._solver.setup(self._H, np.zeros(self._H.shape[0]), self._A0, self._l0, self._u0, **settings_)
        self._dense_limit: float | None = None     # the time limit of the next dense QP, s (None: none)
        #: The last dense QP's condensed matrices (mpc.controllers.dense_qp.Condensed), or None.
        self._condensed = None
        if self.s.qp == "daqp":
            from .dense_qp import require_daqp

            require_daqp()
            # The dense QP's constraints (L, lo_u, hi_u, S, lo_s, hi_s): the sparse QP's rotor loads and attitude
            # bounds, or none.
            if self.s.constraints:
                lim = self.s.attitude_limit_rad
                self._dense_constraints = (self._load, self.inputs.lower, self.inputs.upper, self._attitude_rows(),
                                           np.full(2, -lim), np.full(2, lim))
            else:
                self._dense_constraints = (np.zeros((0, NU)), np.zeros(0), np.zeros(0), np.zeros((0, self.nx)),
                                           np.zeros(0), np.zeros(0))
        self._plan_x: np.ndarray | None = None
        self._plan_u: np.ndarray | None = None
        self._z: np.ndarray | None = None

    def _set_offset(self, offset) -> None:
        self.model.offset = offset

    def _linearize(self, X, U):
        """``(f(X, U), A, B)`` from the prediction model, with the Jacobians in :attr:`LTVSettings.jacobians`."""
        if self.s.jacobians == "float32":
            return self.model.linearize_single(X, U)
        return self.model.linearize(X, U)

    def prepare(self, t_end: float, x0=None) -> None:
        """Before a flight: the reference and feed-forward (see :class:`MPCBase`), and one call of the model at the
        horizon's batch size (onnxruntime allocates its buffers for a new shape on the first call, about 0.5 ms
        that would otherwise fall into the first period)."""
        super().prepare(t_end, x0)
        X, U = self._horizon_reference(0.0)
        with np.errstate(all="ignore"):
            self._linearize(X[:self.N], U)
            self.model.step(X[:self.N], U)
            self.model.step(X[0], U[0])

    def set_deadline(self, at: float | None) -> None:
        """The wall-clock time (``time.perf_counter()``, s) by which the next call's input must be out, or None.

        For the next call only (a real-time loop sets it every period). When
        the period's first derivatives and QP would not fit before it (from
        their median times over :data:`mpc.controllers.timing.RECENT_PERIODS` periods), or OSQP
        stops at the time left, the call returns at once with the fallback of
        a failed solve (the shifted plan, or the LQR) and the status
        :data:`DEADLINE_STATUS`. The LTV-MPC's cold start (no plan to fall back
        on) ignores the deadline; the SQP's cold start in flight keeps it, or
        is put off while the LQR flies (:class:`mpc.controllers.sqp.SQPMPC`). Without a
        deadline the period runs to its budget and iteration limit, whatever
        they take.
        """
        self._deadline = None if at is None else float(at)

    # ----------------------------------------------------------- QP set-up
    def _xi(self, k):
        return k * self.nx

    def _ui(self, k):
        return self.nx_var + k * NU

    def _build_pattern(self) -> None:
        """Constant Hessian and the constraint matrix pattern (entries in a fixed order)."""
        N = self.N
        self._H = self._build_hessian()
        rows, cols, vals = [], [], []
        self._dyn_slots = []  # (entry index range) of A_k and B_k per stage

        def add(r0, c0, block):
            b = np.atleast_2d(block)
            rr, cc = np.meshgrid(np.arange(b.shape[0]), np.arange(b.shape[1]), indexing="ij")
            start = len(vals)
            rows.extend((r0 + rr).ravel())
            cols.extend((c0 + cc).ravel())
            vals.extend(b.ravel())
            return start, len(vals)

        nx = self.nx
        add(0, self._xi(0), np.eye(nx))                     # x_0 = measured state (and the extra states carried)
        r = nx
        for k in range(N):
            add(r, self._xi(k + 1), -np.eye(nx))            # -x_{k+1} + A_k x_k + B_k u_k = -c_k
            a = add(r, self._xi(k), np.ones((nx, nx)))
            b = add(r, self._ui(k), np.ones((nx, NU)))
            self._dyn_slots.append((a, b))
            r += nx
        self._n_eq = r
        lo, hi = [np.zeros(r)], [np.zeros(r)]
        if self.s.constraints:
            for k in range(N):
                add(r, self._ui(k), self._load)
                r += NU
            lo.append(np.tile(self.inputs.lower, N))
            hi.append(np.tile(self.inputs.upper, N))
            sel = self._attitude_rows()
            for k in range(1, N + 1):
                add(r, self._xi(k), sel)
                r += 2
            lim = self.s.attitude_limit_rad
            lo.append(np.full(2 * N, -lim))
            hi.append(np.full(2 * N, lim))
        # Entry indices of all A_k and B_k, in the order of A.ravel() and B.ravel() of (N, nx, *) arrays.
        self._idx_A = np.concatenate([np.arange(a0, a1) for (a0, a1), _ in self._dyn_slots])
        self._idx_B = np.concatenate([np.arange(b0, b1) for _, (b0, b1) in self._dyn_slots])
        self._vals = np.asarray(vals, dtype=float)
        self._A0, self._perm = csc_in_entry_order(rows, cols, self._vals, (r, self.nx_var + N * NU))
        self._l0, self._u0 = np.concatenate(lo), np.concatenate(hi)

    def _attitude_rows(self) -> np.ndarray:
        """The rows (2, nx) that pick roll and pitch out of a state: the attitude bounds' constraint rows."""
        sel = np.zeros((2, self.nx))
        sel[0, 3] = sel[1, 4] = 1.0
        return sel

    def _build_hessian(self):
        """The QP's cost Hessian (upper triangle, CSC): ``Q`` per stage, ``P`` at the end, ``R`` per input."""
        N = self.N
        return sp.triu(sp.block_diag([sp.csc_matrix(self.Q)] * N + [sp.csc_matrix(self.P)]
                                     + [sp.csc_matrix(self.R)] * N, format="csc"), format="csc")

    # ------------------------------------------------------------- control
    def _nominal(self, x: np.ndarray, u_ref: np.ndarray):
        """First iterate (N + 1, nx), (N, 4): the previous plan shifted by one period, or the state held under the
        feed-forward."""
        N = self.N
        if self._plan_x is None:
            return np.tile(x, (N + 1, 1)), u_ref.copy()
        xs, us = shift_stages(self._plan_x), shift_stages(self._plan_u)
        xs[0] = x
        return xs, us

    def __call__(self, x, t: float):
        """Input (4,) and :class:`ControlInfo` for the measured state ``x`` at time ``t`` (s)."""
        x = check_measured(x, self.model)
        with Timer(self.clock.now) as tm:
            z = self.tracker.full(x, t)     # the measured state, with the model's extra states carried
            ref, u_ref = self._horizon_reference(t)
            u, fields = self._period(z, ref, u_ref, tm)
        return u, ControlInfo(solve_time_s=tm.elapsed, **fields)

    def _take_deadline(self) -> float | None:
        """The deadline of this call (:meth:`set_deadline`), cleared for the next one."""
        deadline, self._deadline = self._deadline, None
        return deadline

    def _period(self, x, ref, u_ref, tm):
        """One period of the LTV-MPC: one QP along the shifted previous plan, full step; ``(u, ControlInfo fields)``.

        ``x``: the full state (nx,); ``tm``: the call's :class:`Timer`.
        """
        N = self.N
        cold = self._plan_x is None
        X, U = self._nominal(x, u_ref)
        warm = None if self._z is None else self._shifted(self._z)
        deadline = self._take_deadline()
        clock = self.clock.begin(tm.start, None, None if cold else deadline)   # a cold start plans whatever it takes
        split = dict.fromkeys(SPLIT, 0.0)
        res, ok, status = None, False, DEADLINE_STATUS
        if not clock.no_time_to_start():
            fx, A, B = self._derivatives(X, U, clock, split, first=True)
            if not self._finite(fx, A, B):
                status = NON_FINITE_STATUS
            elif clock.qp_window(first=True):
                res, ok, status = self._qp(x, ref, u_ref, X[:N], U, fx, A, B, clock, split, first=True, warm=warm)
        if ok:
            X, U = self._unpack(res.x)
        optimal = ok and res.info.status_val == self._status.OSQP_SOLVED
        u, fields = self._finish(ok, X, U, status, optimal, x, ref, u_ref)
        fields["iterations"] = 0 if res is None else int(res.info.iter)
        return u, fields

    def _derivatives(self, X, U, clock, split, first: bool):
        """``(f(X, U), A, B)`` along the plan's first N stages, timed (the period's first ones also recorded)."""
        t0 = clock.now()
        with np.errstate(all="ignore"):
            fx, A, B = self._linearize(X[:self.N], U)
        seconds = clock.now() - t0
        split["derivatives"] += seconds
        if first:
            clock.record("derivatives", seconds)
        return fx, A, B

    @staticmethod
    def _finite(fx, A=None, B=None) -> bool:
        """The model's step (and, when given, its Jacobians) along the plan are finite."""
        return bool(np.all(np.isfinite(fx)) and (A is None or np.all(np.isfinite(A)))
                    and (B is None or np.all(np.isfinite(B))))

    def _qp(self, x, ref, u_ref, xb, ub, fx, A, B, clock, split, first: bool, warm=None, hess=None,
            same_matrices=False):
        """Solve the QP linearized along ``(xb, ub)`` within the clock's limits; ``(OSQP result, ok, status)``.

        ``ok``: OSQP solved it (also inaccurately) with a finite solution. A
        period's ``first`` QP records its assembly and (when solved) solve times, and a failure of it
        that ran into the deadline has the status :data:`DEADLINE_STATUS`.
        """
        limit = clock.qp_time_limit(first)
        if limit is not None:
            self.update_settings(time_limit=limit)
        assembly_before, qp_before = split["assembly"], split["osqp"]
        res = self._solve_qp(x, ref, u_ref, xb, ub, fx, A, B, warm=warm, split=split, hess=hess,
                             same_matrices=same_matrices)
        ok = self._solved(res)
        status = res.info.status
        if first:
            clock.record("assembly", split["assembly"] - assembly_before)
            if ok:      # a QP stopped by its time limit says nothing of what a solve takes
                clock.record("qp", split["osqp"] - qp_before)
            if not ok and clock.missed():
                status = DEADLINE_STATUS    # OSQP stopped at the deadline's time limit
        return res, ok, status

    def _solved(self, res) -> bool:
        """OSQP solved the QP (also inaccurately) and its solution is finite."""
        return res.info.status_val in (self._status.OSQP_SOLVED, self._status.OSQP_SOLVED_INACCURATE) and \
            res.x is not None and bool(np.all(np.isfinite(res.x)))

    def _unpack(self, z):
        """States (N + 1, nx) and inputs (N, 4) of a QP solution (views)."""
        return z[:self.nx_var].reshape(self.N + 1, self.nx), z[self.nx_var:].reshape(self.N, NU)

    def _finish(self, ok: bool, X, U, status: str, optimal: bool, x, ref, u_ref):
        """The period's input and its record's fields (no ``iterations``) after a plan ``(X, U)`` was made (``ok``),
        or the fallback of a failed period (the shifted plan, or the LQR)."""
        fallback = None
        if ok:
            self._z = np.concatenate([X.ravel(), U.ravel()])
            self._plan_x, self._plan_u = X, U
            self._success()
            u = U[0]
            info_status = "optimal" if optimal else status
        else:
            fallback = self._failure(self._plan_u is not None)
            if fallback == "lqr":
                u = self.lqr.input(x, ref[0], u_ref[0])
                self._plan_x = self._plan_u = self._z = None
            else:
                self._plan_x, self._plan_u = shift_stages(self._plan_x), shift_stages(self._plan_u)
                u = self._plan_u[0]
            info_status = status
        u = self._rotor_feasible(u)
        return u, dict(status=info_status, predicted=None if self._plan_x is None else self._plan_x.copy(),
                       fallback=fallback, extra={"counts": dict(self.counts)})

    def _rotor_feasible(self, u):
        """``u`` (4,) if it may be commanded, else its projection (:meth:`mpc.prediction.spec.InputSet.project`: at
        the wrench level onto the rotor-feasible set)."""
        return u if self.inputs.contains(u, tol=0.0) else self.inputs.project(u)

    def _solve_qp(self, x, ref, u_ref, xb, ub, fx, A, B, warm=None, split=None, hess=None, same_matrices=False):
        """Update the QP's values along ``(xb, ub)`` and solve it; OSQP's result.

        ``warm``: a primal start (else OSQP starts from its last solution);
        ``split``: a dict whose ``assembly`` and ``osqp`` times (s) are increased;
        ``hess``: ``(Px, dq)``, the Hessian's values (CSC order) and a change of the linear cost, or None (the
        cost's own Hessian);
        ``same_matrices``: ``A``, ``B`` (and ``Px``) are those of the last QP (only the vectors are updated,
        and OSQP reuses its factorization).
        """
        t0 = time.perf_counter()
        c = self._constant_terms(fx, A, B, xb, ub)
        if self.s.qp == "daqp" and hess is None:
            return self._solve_dense(x, ref, u_ref, c, A, B, split, t0, same_matrices)
        self._condensed = None      # the dense path's matrices may differ from OSQP's from here on
        mats = {} if same_matrices else {"Ax": self._constraint_values(A, B)}
        lo, hi = self._bounds(x, c)
        q = self._linear_cost(ref, u_ref)
        if hess is not None:
            q = q + hess[1]
            if not same_matrices:
                mats["Px"] = hess[0]
        self._solver.update(q=q, l=lo, u=hi, **mats)
        if warm is not None:
            self._solver.warm_start(x=warm)
        t1 = time.perf_counter()
        res = self._solver.solve(raise_error=False)  # failure is data: the caller handles it
        if split is not None:
            split["assembly"] += t1 - t0
            split["osqp"] += time.perf_counter() - t1
        return res

    def _solve_dense(self, x, ref, u_ref, c, A, B, split, t0, same_matrices=False):
        """The QP condensed and solved by DAQP (:mod:`mpc.controllers.dense_qp`), as a result OSQP's callers read. With
        ``same_matrices`` the last dense QP's condensed matrices are reused (only its vectors are condensed)."""
        from .dense_qp import solve_ltv_qp

        qp = self._ltv_qp(x, ref, u_ref, c, A, B)
        reuse, self._condensed = self._condensed if same_matrices else None, None
        sol = solve_ltv_qp(qp, self._dense_limit, reuse)
        self._condensed = sol.matrices
        res = _DenseResult(sol, self._status)
        if split is not None:
            split["assembly"] += sol.condense_s + (time.perf_counter() - t0 - sol.solve_s)
            split["osqp"] += sol.solve_s - sol.condense_s
        return res

    @staticmethod
    def _constant_terms(fx, A, B, xb, ub):
        """The linearized dynamics' constant terms (N, nx): ``c_k = f(xb_k, ub_k) - A_k xb_k - B_k ub_k``."""
        return fx - (A @ xb[:, :, None])[:, :, 0] - (B @ ub[:, :, None])[:, :, 0]

    def _bounds(self, x, c):
        """The sparse QP's bounds ``(lo, hi)`` for the initial state ``x`` (nx,) and the dynamics' constant terms
        ``c`` (N, nx): equalities in their rows, the constraints' own bounds in the others (new arrays)."""
        lo, hi = self._l0.copy(), self._u0.copy()
        lo[:self.nx] = hi[:self.nx] = x
        lo[self.nx:self._n_eq] = hi[self.nx:self._n_eq] = -c.ravel()
        return lo, hi

    def _ltv_qp(self, x, ref, u_ref, c, A, B):
        """The QP as :mod:`mpc.controllers.dense_qp` takes it (an ``LTVQP``), with the dense path's constraints."""
        from .dense_qp import LTVQP

        L, lo_u, hi_u, S, lo_s, hi_s = self._dense_constraints
        return LTVQP(A=A, B=B, c=c, x0=np.asarray(x, dtype=float), Q=self.Q, P=self.P, R=self.R, ref=ref,
                     u_ref=u_ref, L=L, lo_u=lo_u, hi_u=hi_u, S=S, lo_s=lo_s, hi_s=hi_s)

    def _constraint_values(self, A, B):
        """Values of the QP's constraint matrix (CSC order of ``_A0``) with the dynamics ``A`` (N, nx, nx) and ``B``
        (N, nx, 4)."""
        vals = self._vals.copy()
        vals[self._idx_A] = A.ravel()
        vals[self._idx_B] = B.ravel()
        return vals[self._perm]

    def _linear_cost(self, ref, u_ref):
        """The QP's linear cost term for the reference ``ref`` (N + 1, nx) and feed-forward ``u_ref`` (N, 4): the cost
        is ``z' H z / 2 + q' z`` with ``H`` the cost's Hessian."""
        N = self.N
        return np.concatenate([-(ref[:N] @ self.Q).ravel(), -(self.P @ ref[N]), -(u_ref @ self.R).ravel()])

    def update_settings(self, **settings) -> None:
        """Change OSQP settings between periods (for example ``max_iter`` or ``time_limit``; a time limit applies to
        the dense QP too)."""
        if "time_limit" in settings:
            self._dense_limit = settings["time_limit"] or None
        self._solver.update_settings(**settings)

    def _shifted(self, z: np.ndarray) -> np.ndarray:
        N = self.N
        xs = z[:self.nx_var].reshape(N + 1, self.nx)
        us = z[self.nx_var:].reshape(N, NU)
        return np.concatenate([shift_stages(xs).ravel(), shift_stages(us).ravel()])


class _DenseInfo:
    def __init__(self, status: str, status_val: int, iterations: int):
        self.status, self.status_val, self.iter = status, status_val, iterations


class _DenseResult:
    """A :class:`mpc.controllers.dense_qp.DenseSolution` as OSQP's result reads: ``x`` (states then inputs), ``y`` (the
    multipliers in the rows of the sparse QP: initial state, dynamics, rotor loads, attitude) and ``info``."""

    def __init__(self, sol, osqp_status):
        self.x = np.concatenate([sol.x.ravel(), sol.u.ravel()]) if sol.solved else None
        self.y = np.concatenate([sol.y_init, sol.y_dyn.ravel(), sol.y_u.ravel(), sol.y_s.ravel()])
        status, val = (("solved", osqp_status.OSQP_SOLVED) if sol.solved else
                       (f"DAQP exit flag {sol.flag}", osqp_status.OSQP_MAX_ITER_REACHED))
        self.info = _DenseInfo(status, val, sol.iterations)
