"""LTV-MPC with OSQP.

Each control period the prediction model is linearized along the shifted
previous plan in one batched call, ``x_{k+1} = A_k x_k + B_k u_k + c_k``,
and one sparse QP is solved::

    min  sum_k (x_k - r_k)' Q (x_k - r_k) + (u_k - f_k)' R (u_k - f_k) + (x_N - r_N)' P (x_N - r_N)
    s.t. x_0 = measured state, the linearized dynamics,
         0 <= M^-1 u_k / n_max^2 <= 1  (rotor-feasible wrench set, linear in u; each row a rotor's load)
         |phi_k|, |theta_k| <= attitude limit,   k = 1 .. N

with ``r_k`` the reference states, ``f_k`` the model's own feed-forward
along them (:mod:`mpc.feedforward`), ``P`` the discrete Riccati solution of
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
from collections import deque
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from sim.params import NU
from sim.rotors import load_matrix, realize

from .base import MPCBase
from .controller import ControlInfo, Reference, Timer, check_common_settings, check_measured
from .errors import ConfigurationError
from .models import PredictionModel

#: OSQP's "no time limit" (its default setting), s.
NO_TIME_LIMIT = 1e10
#: Status of a period whose plan could not be made before its deadline (:meth:`LTVMPC.set_deadline`).
DEADLINE_STATUS = "deadline"
#: Least time OSQP is given before a deadline, s: with less, the period takes its fallback at once.
MIN_QP_TIME_S = 3e-4
#: The expected time of a period's first derivatives and QP assembly (for the deadline) is the median of this
#: many recent periods (one slow period does not make the next ones give up).
RECENT_PERIODS = 20


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

    def __post_init__(self):
        check_common_settings(self.horizon, self.attitude_limit_rad, self.max_iter)
        if self.time_limit_s < 0:
            raise ConfigurationError(f"time_limit_s must be >= 0; found {self.time_limit_s}")
        if self.jacobians not in ("float32", "float64"):
            raise ConfigurationError(f"jacobians must be 'float32' or 'float64'; found {self.jacobians!r}")
        for name in ("scaling", "check_termination"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ConfigurationError(f"{name} must be an integer >= 0; found {v!r}")


class LTVMPC(MPCBase):
    """Linear time-varying MPC on any :class:`mpc.models.PredictionModel`.

    Parameters
    ----------
    model : PredictionModel
        Prediction model (analytic or ONNX).
    reference : FlatTrajectory or callable, optional
        A flat trajectory (:mod:`mpc.trajectory`) or ``reference(times) -> (K, 12)``;
        hover at 1 m when omitted.
    settings : LTVSettings, optional
    spec : VehicleSpec, optional
        What the controller knows of the vehicle: rotor limits and mixer
        (:meth:`mpc.spec.VehicleSpec.from_model` when omitted). The hover
        trim, feed-forward, terminal cost and fallback come from the model.
    Q, R : array_like, optional
        Weights (:func:`mpc.lqr.default_weights` when omitted).
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
        self._load = load_matrix(self.spec)     # wrench -> rotor loads n^2 / n_max^2 (unit-free)
        from .lqr import input_scale

        self._sx, self._su = self.state_scale, input_scale(self.spec)   # step sizes are measured in these
        self._build_pattern()
        self._status = osqp.SolverStatus
        self._deadline: float | None = None
        self._recent_s = {"derivatives": deque(maxlen=RECENT_PERIODS), "assembly": deque(maxlen=RECENT_PERIODS),
                          "line_search": deque(maxlen=RECENT_PERIODS)}
        self._solver = osqp.OSQP()
        settings_ = dict(verbose=False, warm_starting=True, max_iter=self.s.max_iter, eps_abs=self.s.eps_abs,
                         eps_rel=self.s.eps_rel, polishing=self.s.polish,
                         scaling=self.s.scaling, check_termination=self.s.check_termination)
        if self.s.time_limit_s > 0:
            settings_["time_limit"] = self.s.time_limit_s
        self._solver.setup(self._H, np.zeros(self._H.shape[0]), self._A0, self._l0, self._u0, **settings_)
        self._plan_x: np.ndarray | None = None
        self._plan_u: np.ndarray | None = None
        self._z: np.ndarray | None = None
        self._plan_is_current = False   # the plan was made for the next call's time (a pre-flight plan): no shift

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
        their median times over :data:`RECENT_PERIODS` periods), or OSQP
        stops at the time left, the call returns at once with the fallback of
        a failed solve (the shifted plan, or the LQR) and the status
        :data:`DEADLINE_STATUS`. A cold start (no plan to fall back on) ignores
        the deadline. Without a deadline the period runs to its budget and
        iteration limit, whatever they take.
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
            lo.append(np.zeros(N * NU))
            hi.append(np.ones(N * NU))
            sel = np.zeros((2, nx))
            sel[0, 3] = sel[1, 4] = 1.0
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

    def _build_hessian(self):
        """The QP's cost Hessian (upper triangle, CSC): ``Q`` per stage, ``P`` at the end, ``R`` per input."""
        N = self.N
        return sp.triu(sp.block_diag([sp.csc_matrix(self.Q)] * N + [sp.csc_matrix(self.P)]
                                     + [sp.csc_matrix(self.R)] * N, format="csc"), format="csc")

    def _hessian_values(self, X, U, y):
        """``(Px, dq)``: the QP's Hessian values (CSC order) and linear-cost change for the iterate ``(X, U)`` and the
        dynamics multipliers ``y`` (N, 12) of the last QP, or None to keep the cost's own Hessian."""
        return None

    # ------------------------------------------------------------- control
    def _nominal(self, x: np.ndarray, u_ref: np.ndarray):
        """First iterate (N + 1, nx), (N, 4): the shifted previous plan, or the state held under the feed-forward."""
        N = self.N
        if self._plan_x is None:
            return np.tile(x, (N + 1, 1)), u_ref.copy()
        if self._plan_is_current:
            xs, us = self._plan_x.copy(), self._plan_u.copy()
        else:
            xs = np.vstack([self._plan_x[1:], self._plan_x[N:N + 1]])
            us = np.vstack([self._plan_u[1:], self._plan_u[-1:]])
        xs[0] = x
        return xs, us

    def _shifts_plan(self) -> bool:
        """This period's first iterate is the previous plan shifted by one period (not a cold start, and not a plan
        made for this very period before take-off)."""
        return self._plan_x is not None and not self._plan_is_current

    def _iteration_plan(self):
        """``(max_iterations, line_search, time_budget_s or None, (step_tol, defect_tol))`` of one period.

        The LTV-MPC is the real-time iteration: one QP along the shifted
        previous plan, full step. :class:`mpc.sqp.SQPMPC` iterates.
        """
        return 1, False, None, (0.0, 0.0)

    def __call__(self, x, t: float):
        """Input (4,) and :class:`ControlInfo` for the measured state ``x`` at time ``t`` (s)."""
        x = check_measured(x, self.model)
        with Timer() as tm:
            z = self.tracker.full(x, t)     # the measured state, with the model's extra states carried
            ref, u_ref = self._horizon_reference(t)
            out = self._iterate(z, ref, u_ref, tm)
        return out[0], ControlInfo(solve_time_s=tm.elapsed, **out[1])

    def _iterate(self, x, ref, u_ref, tm, guess=None):
        """Gauss-Newton SQP iterations of one period (one for the LTV-MPC); ``(u, ControlInfo fields)``.

        ``x``: the full state (nx,). ``guess``: a first iterate ``(X (N + 1, nx), U (N, 4))`` that replaces the
        shifted plan (and the cold start), also as OSQP's primal start.
        """
        N = self.N
        max_it, line_search, budget, tol = self._iteration_plan()
        shifted = False   # the first iterate is the previous plan shifted by one period
        if guess is None:
            cold = self._plan_x is None
            shifted = self._shifts_plan()
            X, U = self._initial_iterate(x, ref, u_ref)
            if cold:
                max_it, budget = self._cold_start_plan(max_it, budget)
            first_warm = None if self._z is None else self._z if self._plan_is_current else self._shifted(self._z)
        else:
            cold = False
            X, U = np.array(guess[0], dtype=float), np.array(guess[1], dtype=float)
            X[0] = x
            first_warm = np.concatenate([X.ravel(), U.ravel()])
        self._plan_is_current = False
        merits, alphas = [], []
        split = {"derivatives": 0.0, "assembly": 0.0, "osqp": 0.0, "line_search": 0.0}
        done, qp_iterations, status, ok_any, converged = 0, 0, "", False, False
        ls_failures = late_steps = 0
        longest = 0.0    # the longest iteration of this period, s (the first with the period's set-up)
        mu = 0.0
        y_last = None    # the last QP's dynamics multipliers (N, nx)
        every = self._jacobian_every()
        f_next = None    # the model's step along the line search's new iterate (N, nx), when it made one
        deadline, self._deadline = self._deadline, None    # for this call only
        if cold:
            deadline = None     # a cold start makes a plan whatever it takes: its fallback (the LQR) has none
        expect = {k: float(np.median(v)) if v else 0.0 for k, v in self._recent_s.items()}
        # A line search takes a varying number of model steps: the longest of the recent ones is expected.
        expect["line_search"] = max(self._recent_s["line_search"], default=0.0)
        while done < max_it:
            t_it = tm.now()
            if deadline is not None and done == 0 and \
                    t_it + expect["derivatives"] + expect["assembly"] + MIN_QP_TIME_S > deadline:
                status, ok = DEADLINE_STATUS, False      # no plan in time: the fallback's input goes out now
                break
            # An iteration between Jacobian evaluations keeps A_k, B_k (and OSQP's factorization) and takes only the
            # model's step at the new iterate (from the line search when it made one).
            reuse = done % every != 0
            with np.errstate(all="ignore"):
                if reuse:
                    fx = f_next if f_next is not None else self.model.step(X[:N], U)
                else:
                    fx, A, B = self._linearize(X[:N], U)
            split["derivatives"] += tm.now() - t_it
            if done == 0:
                self._recent_s["derivatives"].append(tm.now() - t_it)
            # A reuse iteration's A, B passed this check when they were evaluated (a non-finite one ends the period).
            finite = np.all(np.isfinite(fx)) and (reuse or (np.all(np.isfinite(A)) and np.all(np.isfinite(B))))
            if finite and shifted and done == 0:
                first_warm = self._close_tail(X, U, fx, first_warm)
            if finite and deadline is not None:
                # OSQP gets what is left before the deadline once its problem is assembled; too little for the
                # period's first QP: no QP (a later iteration is bounded by the budget).
                qp_left = max(deadline - tm.now() - expect["assembly"], 1e-4)
                if done == 0 and qp_left < MIN_QP_TIME_S:
                    status, finite = DEADLINE_STATUS, False
            if finite:
                limit = NO_TIME_LIMIT
                if budget is not None and done > 0:
                    # After the first QP of a period (which must give a plan), one hard QP must not overrun the
                    # budget: OSQP gets the time left.
                    limit = max(budget - (tm.now() - tm.start), 1e-4)
                if deadline is not None:
                    limit = min(limit, qp_left)
                if budget is not None or deadline is not None:
                    self._solver.update_settings(time_limit=limit)
                assembly_before = split["assembly"]
                warm = first_warm if done == 0 else None
                t_h = tm.now()
                hess = self._hessian_values(X[:N + 1], U, y_last)
                split["derivatives"] += tm.now() - t_h
                res = self._solve_qp(x, ref, u_ref, X[:N], U, fx, A, B, warm=warm, split=split, hess=hess,
                                     same_matrices=reuse)
                status, qp_iterations = res.info.status, qp_iterations + int(res.info.iter)
                solved = (self._status.OSQP_SOLVED, self._status.OSQP_SOLVED_INACCURATE)
                ok = res.info.status_val in solved and res.x is not None and np.all(np.isfinite(res.x))
                if done == 0:
                    self._recent_s["assembly"].append(split["assembly"] - assembly_before)
                    if not ok and deadline is not None and tm.now() > deadline - MIN_QP_TIME_S:
                        status = DEADLINE_STATUS    # OSQP stopped at the deadline's time limit
            elif status != DEADLINE_STATUS:  # a model that returns NaN/inf along the plan: OSQP never sees it
                status, ok = "non-finite model output", False
            else:
                ok = False
            if not ok:
                break
            done += 1
            ok_any = True
            y_last = res.y[self.nx:self._n_eq].reshape(N, self.nx).copy()
            optimal = res.info.status_val == self._status.OSQP_SOLVED
            Xq = res.x[:self.nx_var].reshape(N + 1, self.nx)
            Uq = res.x[self.nx_var:].reshape(N, NU)
            # With a budget, a period whose QP ended past it, or so close to it that the longest recent line search
            # would end past it, takes the QP's full step (the real-time iteration) and stops: no line search (its
            # model steps and any correction's QP) on top of an overrun.
            elapsed = tm.now() - tm.start
            late = budget is not None and (elapsed > budget or
                                           (line_search and elapsed + expect["line_search"] > budget))
            if late:
                late_steps += 1
            if line_search and not late:
                t_ls = tm.now()
                qp_before = split["assembly"] + split["osqp"]   # a correction's QP is counted there, not here
                mu = max(mu, self._merit_factor * float(np.max(np.abs(y_last))) + 1e-9)
                Xl, Ul = X[:N], U     # the linearization point, for the second-order correction's QP

                iteration_time = tm.now() - t_it     # derivatives + QP: more than the correction's QP needs

                def resolve(shift, Xl=Xl, Ul=Ul, fx=fx, A=A, B=B, iteration_time=iteration_time, hess=hess):
                    if budget is not None:
                        left = budget - (tm.now() - tm.start)
                        if left < iteration_time:   # no time for the correction's QP: the caller backtracks instead
                            return None
                        self._solver.update_settings(time_limit=left)
                    # The same matrices (A_k, B_k, Hessian): only the bounds change, OSQP keeps its factorization.
                    return self._solve_qp(x, ref, u_ref, Xl, Ul, fx + shift, A, B, split=split, hess=hess,
                                          same_matrices=True)

                Xn, Un, alpha, accepted, phi0, phi, defect, f_next = self._line_search(X, U, Xq, Uq, fx, ref,
                                                                                       u_ref, mu, resolve)
                merits.append((phi0, phi, accepted))
                ls_failures += not accepted
                split["line_search"] += tm.now() - t_ls - (split["assembly"] + split["osqp"] - qp_before)
                if budget is not None:
                    self._recent_s["line_search"].append(tm.now() - t_ls)
            else:
                Xn, Un, alpha, defect, f_next = Xq, Uq, 1.0, np.inf, None
            alphas.append(alpha)
            # Converged when the QP's full step is small (a step shortened by the line search is not convergence).
            step = max(np.max(np.abs(Xq - X) / self._sx), np.max(np.abs(Uq - U) / self._su))
            X, U = Xn, Un
            # Only an iteration with new Jacobians can say that the plan is a KKT point.
            if not reuse and (step < tol[0] or defect < tol[1]):
                converged = True
                break
            # Another iteration only if one as long as the longest so far still fits the budget (the first one
            # carries the period's set-up, so the rule errs towards stopping).
            longest = max(longest, tm.now() - (tm.start if done == 1 else t_it))
            if late or (budget is not None and tm.now() - tm.start + longest > budget):
                break
        fallback = None
        if ok_any:
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
                self._plan_x = np.vstack([self._plan_x[1:], self._plan_x[-1:]])
                self._plan_u = np.vstack([self._plan_u[1:], self._plan_u[-1:]])
                u = self._plan_u[0]
            info_status = status
        u = self._rotor_feasible(u)
        extra = {"counts": dict(self.counts)}
        iterations = qp_iterations
        if self._reports_sqp:
            iterations = done
            extra.update(qp_iterations=qp_iterations, converged=converged, cold_start=cold,
                         line_search_failures=ls_failures, late_full_steps=late_steps, time_split_s=split, merit=merits,
                         step_lengths=alphas)
        return u, dict(status=info_status, iterations=iterations,
                       predicted=None if self._plan_x is None else self._plan_x.copy(), fallback=fallback,
                       extra=extra)

    #: The LTV-MPC reports OSQP's iterations; the SQP its own (and OSQP's in ``extra``).
    _reports_sqp = False

    def _initial_iterate(self, x, ref, u_ref):
        return self._nominal(x, u_ref)

    def _jacobian_every(self) -> int:
        """The model's Jacobians are evaluated at the iterations ``0, k, 2k, ...`` of a period (one iteration here)."""
        return 1

    def _rotor_feasible(self, u):
        """``u`` (4,) if the rotors can realize it, else its exact projection onto the rotor-feasible set."""
        load = self._load @ u
        if np.all(load >= 0.0) and np.all(load <= 1.0):
            return u
        return realize(u, self.spec).wrench

    def _close_tail(self, X, U, fx, warm):
        """After the first linearization along a shifted plan: complete its last stage; OSQP's primal start.

        The LTV-MPC keeps the shifted plan as it is (its last state and input
        repeated) and starts OSQP from the shifted previous solution.
        """
        return warm

    def _cold_start_plan(self, max_it, budget):
        return max_it, budget

    def _line_search(self, X, U, Xq, Uq, fx, ref, u_ref, mu, resolve):  # pragma: no cover - SQP only
        raise NotImplementedError

    def _solve_qp(self, x, ref, u_ref, xb, ub, fx, A, B, warm=None, split=None, hess=None, same_matrices=False):
        """Update the QP's values along ``(xb, ub)`` and solve it; OSQP's result.

        ``warm``: a primal start (else OSQP starts from its last solution);
        ``split``: a dict whose ``assembly`` and ``osqp`` times (s) are increased;
        ``hess``: ``(Px, dq)`` from :meth:`_hessian_values`;
        ``same_matrices``: ``A``, ``B`` (and ``Px``) are those of the last QP (only the vectors are updated,
        and OSQP reuses its factorization).
        """
        t0 = time.perf_counter()
        c = fx - (A @ xb[:, :, None])[:, :, 0] - (B @ ub[:, :, None])[:, :, 0]
        mats = {} if same_matrices else {"Ax": self._constraint_values(A, B)}
        lo, hi = self._l0.copy(), self._u0.copy()
        lo[:self.nx] = hi[:self.nx] = x
        lo[self.nx:self._n_eq] = hi[self.nx:self._n_eq] = -c.ravel()
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
        """Change OSQP settings between periods (for example ``max_iter`` or ``time_limit``)."""
        self._solver.update_settings(**settings)

    def _shifted(self, z: np.ndarray) -> np.ndarray:
        N = self.N
        xs = z[:self.nx_var].reshape(N + 1, self.nx)
        us = z[self.nx_var:].reshape(N, NU)
        return np.concatenate([np.vstack([xs[1:], xs[-1:]]).ravel(), np.vstack([us[1:], us[-1:]]).ravel()])
