"""Real-time nonlinear MPC: Gauss-Newton SQP on the LTV-MPC's QP.

Each control period solves the same optimal control problem as the NMPC
(:mod:`mpc.controllers.nmpc`): tracking cost ``Q``, ``R``, ``P`` against the reference and
the model's feed-forward, the model's dynamics as equality constraints, the
rotor-feasible wrench set and attitude bounds. It does so by sequential
quadratic programming:

1. linearize the model along the current iterate ``(X, U)`` in one batched
   call (``A_k``, ``B_k``, ``f(X_k, U_k)``);
2. solve the LTV-MPC's sparse QP (:class:`mpc.controllers.ltv.LTVMPC`: OSQP, pattern
   built once, values updated, warm-started) for the candidate ``(X+, U+)``;
3. a line search on the l1 merit function
   ``phi = J / 2 + mu * sum_k |f(X_k, U_k) - X_{k+1}|`` (``mu`` 1.1 times the
   QP's largest dynamics multiplier) takes the full step if the merit decreases
   enough (Armijo), else a second-order correction (the QP again with the
   model's defects at the full step: one more QP, no new derivatives), else
   the step halved up to four times;
4. stop when the QP's full step is below ``step_tol`` (in the acceptable
   deviations of the default weights) or the model's defects along the new
   plan are below ``defect_tol`` (the linearization held), after
   ``max_sqp_iter`` iterations, or when another iteration as long as the
   longest one so far would not fit in the time budget. A period whose first
   QP already ended past the budget takes that QP's full step without the
   line search (the real-time iteration; counted in the info record's
   ``late_full_steps``).

Step 1 evaluates the model's Jacobians only in the iterations ``0, k, 2k,
...`` of a period (``k = jacobian_every``, default 2). An iteration between
keeps the last ``A_k``, ``B_k`` (so OSQP keeps its factorization) and
linearizes about the new iterate with the model's step there, which the line
search has already computed: the QP then restores the model's dynamics along
the plan for about 1 ms instead of 2.5. Only an iteration with new Jacobians
may stop on the tolerances, so a converged plan is still a KKT point.

The cost is quadratic, so the QP's Hessian (the cost's) is the Gauss-Newton
Hessian; a fixed point of the iteration is a KKT point of the nonlinear
problem, the one IPOPT solves. The LTV-MPC is the one-iteration case (the
real-time iteration): one QP along the shifted previous plan, full step.

Cold start (the first period, and after an LQR fallback): the first iterate
is a rollout of the model from the measured state under the feed-forward and
the hover LQR, and the period may use ``cold_start_budget_s`` and
``cold_start_max_iter`` instead (by default the same 8 ms: the rollout is a
good first guess, and the periods after it go on converging). With a budget, each QP also gets the time
left in it as OSQP's own time limit, so that one hard QP cannot overrun it. Cold starts are counted
(``counts["cold_starts"]``) and flagged in the info record.

The real-time iteration (``scheme="rti"``) splits a period in two, as
acados does. After the input is out, the *preparation*
(:meth:`SQPMPC.prepare_next`, called by the closed loop) shifts the plan by
one period, linearizes the model along it and builds the next QP for every
initial state (condensed with DAQP, or loaded into OSQP); when the next
state arrives, the *feedback* embeds it, solves that QP and sends its first
input, full step. The measurement waits for one QP (about 0.1-0.3 ms
condensed), not for the derivatives. With offset-free control the feedback
also embeds the disturbance estimate of its own period: its offset's change
since the preparation moves every step's constant term, and its target
enters the cost (a disturbance one period late destabilizes a learned
16-state model under the estimator, measured).

The time budget is a wall-clock rule, so a run that uses it is not
reproducible bit for bit; ``time_budget_s=None`` iterates to ``step_tol``
or ``max_sqp_iter`` only (the deterministic ``ideal`` timing of the
scenarios does this).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.params import DT, NU

from .base import shift_stages
from .controller import ControlInfo, Timer, check_state
from ..errors import ConfigurationError
from .ltv import DEADLINE_STATUS, NON_FINITE_STATUS, SPLIT, LTVMPC, LTVSettings, csc_in_entry_order
from .timing import MIN_TIME_LIMIT_S, NO_TIME_LIMIT

#: Central-difference step of the exact Hessian, in acceptable deviations (of the default weights).
EXACT_FD_STEP = 1e-4
#: Smallest eigenvalue of a stage's exact Hessian block, in acceptable deviations (where the cost's is 1).
EIGEN_FLOOR = 1e-2

#: The SQP's iteration schemes (:attr:`SQPSettings.scheme`).
SCHEMES = ("sqp", "rti")

#: Armijo constant and backtracking of the line search.
ARMIJO = 1e-4
BACKTRACK = 0.5
MAX_BACKTRACKS = 4


@dataclass(frozen=True)
class SQPSettings(LTVSettings):
    """Settings of :class:`SQPMPC` (the LTV-MPC's QP settings, plus the SQP's; units in comments)."""

    # One iteration with a 5x128 PINN over 30 stages costs 2-3 ms on our 2-core machines (0.7-1 ms of it the float32
    # Jacobians), a second one without new Jacobians (see jacobian_every) about 1-1.5 ms; on figure8-fast the second
    # iteration brings the Proposed model from 0.125 m (one iteration, as the LTV-MPC) to about 0.12 m, against
    # IPOPT's 0.116 m.
    max_sqp_iter: int = 2                   # SQP iterations per period
    # OSQP iterations per QP. A QP at the rotor limits can take OSQP's 4000 (60 ms here) and fail anyway; the
    # SQP then keeps its current plan (or, in the first iteration, replays the shifted plan).
    max_iter: int = 1000
    time_budget_s: float | None = 0.008     # wall time per period, s (None: no budget)
    step_tol: float = 1e-3                  # converged when the QP's step is below this, in acceptable deviations
    # Converged, too, when the model's largest defect along the new plan is below this (acceptable deviations):
    # the QP's linearization then reproduced the model along the plan, and the next step is small. Measured on
    # figure8-fast with the Proposed model: the defect after one iteration and the second iteration's step
    # correlate (0.93 in log); with hover the second step is about 1e-5.
    defect_tol: float = 1e-3
    line_search: bool = True                # backtracking on the l1 merit function (False: full steps)
    cold_start_max_iter: int = 5            # SQP iterations of a cold-start period
    cold_start_budget_s: float | None = 0.008  # wall time of a cold-start period, s (None: no budget)
    cold_start: str = "rollout"             # first iterate: "rollout" (model under feed-forward + LQR) or "hold"
    # The QP's Hessian: "gauss-newton" (the cost's own, free) or "exact": the cost's plus the model's second
    # derivatives weighted by the last QP's dynamics multipliers, by central differences of the model's Jacobians
    # (32 more Jacobians per stage, float64: about 30x an iteration's derivative time), made positive definite per
    # stage. For converged solutions (a network's curvature can make Gauss-Newton converge slowly), not for the
    # real-time budget.
    hessian: str = "gauss-newton"
    # The last stage of a shifted plan: "model" (the last input from the LQR about the reference, the last state
    # the model's prediction under it, so that the first iterate is a trajectory of the model) or "hold" (the
    # last state and input repeated, as the LTV-MPC does).
    tail: str = "model"
    # The model's Jacobians are evaluated in the SQP iterations 0, k, 2k, ... of a period (k = jacobian_every); the
    # iterations between keep them, and OSQP's factorization, and take the model's step at the new iterate from the
    # line search (an inexact-Jacobian, "Newton-chord" iteration: it restores the dynamics along the new plan at the
    # price of a QP, about 1 ms instead of 2.5). A fixed point still needs an iteration with fresh Jacobians, so the
    # KKT points are unchanged. Measured on figure8-fast with the Proposed model over 12 starts 1e-9 m apart (ideal
    # timing): 2 gives the same RMSE as 1 (median 0.121 m both; spread 6.3 against 6.9 %) with a median solve time
    # of 2.7 ms against 4.3. The exact Hessian needs new derivatives every iteration: it ignores this setting.
    jacobian_every: int = 2
    # Which stages' Jacobians an iteration with new Jacobians evaluates: "full" (all N, in one batched call) or
    # "partial": only the stages whose point (state and input, in acceptable deviations) lies more than refresh_tol
    # from where their Jacobians were last evaluated, at most max_refresh_stages of them per iteration (the farthest
    # first; the others keep theirs until a later period), and all of them when more than full_refresh_above stages
    # moved (the plan changed: a start, a disturbance) and a deadline, if any, leaves time for it. The plan moves
    # by one stage a period, so most stages sit near the points of the period before. The model's step, and so the
    # dynamics the QP restores, is exact either way: "partial" reuses a stage's step only where the plan sits
    # exactly on a point stepped before (the line search's accepted iterate, shifted). A cold start (no Jacobians
    # yet) and the exact Hessian evaluate all of them. Measured (python -m mpc.bench --answers, ideal timing, 5
    # ensemble members, figure8-fast / figure8-slow / hover): median RMSE within 0.7 % of "full" for every shipped
    # model, the oracle's within 0.01 mm; per period about 0.65-0.8 times the time.
    jacobian_refresh: str = "partial"
    # The iteration scheme: "sqp" (each period iterates from the measured state, as above) or "rti", the real-time
    # iteration. There, once a period's input is out, its *preparation* shifts the plan, linearizes the model along
    # it (by jacobian_refresh's rules) and builds the next period's QP for a state still unknown (with qp="daqp",
    # condensed for every initial state); when the next state arrives, the *feedback* embeds it, solves that one
    # QP and sends its first input, full step: the input waits for one QP, not for the derivatives. A preparation
    # that, at the longest recent one's time, would end past the next measurement is not started, and the next
    # feedback solves the last QP prepared (counted in counts["preparations_reused"], and said in its record); the
    # preparation after it is made whatever it takes. A period without a plan (the first without a pre-flight
    # plan, after an LQR fallback) is an SQP period.
    scheme: str = "sqp"
    # With scheme="rti": SQP iterations the preparation may make on the next period's problem from the next state
    # it predicts, each when the next measurement leaves it time (at the longest recent one's time): the prepared
    # QP is solved there, its full step taken, and the QP prepared again along the new plan. 0: none (acados' RTI).
    rti_corrections: int = 0
    refresh_tol: float = 0.05               # acceptable deviations (max over the state and input)
    max_refresh_stages: int = 8             # stages refreshed per iteration at most
    full_refresh_above: int = 15            # more stages than this moved (the plan changed): all are refreshed

    def __post_init__(self):
        super().__post_init__()
        for name in ("max_sqp_iter", "cold_start_max_iter", "jacobian_every", "max_refresh_stages",
                     "full_refresh_above"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ConfigurationError(f"{name} must be an integer >= 1; found {v!r}")
        for name in ("time_budget_s", "cold_start_budget_s"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ConfigurationError(f"{name} must be None or a time > 0 s; found {v!r}")
        if self.hessian not in ("gauss-newton", "exact"):
            raise ConfigurationError(f"hessian must be 'gauss-newton' or 'exact'; found {self.hessian!r}")
        if self.tail not in ("model", "hold"):
            raise ConfigurationError(f"tail must be 'model' or 'hold'; found {self.tail!r}")
        if self.jacobian_refresh not in ("full", "partial"):
            raise ConfigurationError(f"jacobian_refresh must be 'full' or 'partial'; found {self.jacobian_refresh!r}")
        if self.scheme not in SCHEMES:
            raise ConfigurationError(f"scheme must be one of {', '.join(SCHEMES)}; found {self.scheme!r}")
        if self.scheme == "rti" and self.hessian != "gauss-newton":
            raise ConfigurationError("scheme 'rti' needs hessian 'gauss-newton' (its one QP has the cost's Hessian); "
                                     f"found {self.hessian!r}")
        if self.cold_start not in ("rollout", "hold"):
            raise ConfigurationError(f"cold_start must be 'rollout' or 'hold'; found {self.cold_start!r}")
        if isinstance(self.rti_corrections, bool) or not isinstance(self.rti_corrections, (int, np.integer)) \
                or self.rti_corrections < 0:
            raise ConfigurationError(f"rti_corrections must be an integer >= 0; found {self.rti_corrections!r}")
        for name in ("step_tol", "defect_tol", "refresh_tol"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigurationError(f"{name} must be >= 0; found {v}")


@dataclass
class Preparation:
    """The real-time iteration's QP for one period, built before its state is measured (:attr:`SQPSettings.scheme`).

    ``t``: the period it was prepared for, s; ``X`` (N + 1, nx), ``U`` (N, 4): the plan it linearizes about;
    ``dense``: the condensed QP (:class:`mpc.controllers.dense_qp.PreparedQP`) or None (OSQP holds the QP; the
    feedback sets its bounds); ``seconds``: its time;
    ``refreshed``: the stages whose Jacobians it evaluated; ``full``: it evaluated all of them; ``split``: its time
    by part (the derivatives, the QP's assembly or condensing), s; ``c`` (N, nx): the dynamics' constant terms,
    and ``offset``: the prediction's disturbance offset they hold (None: none).
    """

    t: float
    X: np.ndarray
    U: np.ndarray
    dense: object
    seconds: float
    refreshed: int
    full: bool
    split: dict
    c: np.ndarray
    offset: np.ndarray | None


def _same(a, b) -> bool:
    """Two offsets (arrays or None) are equal."""
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


class SQPMPC(LTVMPC):
    """Real-time Gauss-Newton SQP NMPC on any :class:`mpc.prediction.models.PredictionModel`.

    Parameters are those of :class:`mpc.controllers.ltv.LTVMPC`, with
    :class:`SQPSettings`. The info record's ``iterations`` are SQP
    iterations; ``extra`` carries OSQP's (``qp_iterations``), whether the
    iteration converged, whether the period was a cold start, line-search
    failures and the split of the time (``time_split_s``: derivative graph,
    QP assembly, OSQP, line search; the rest is Python). A second-order
    correction's QP counts as assembly and OSQP, not as line search.

    Under a deadline (:meth:`set_deadline`) a cold start in flight (after the
    LQR took over) starts from the model's rollout when the longest recent
    cold start's time to its first plan says it ends in time; else from the
    reference states and the feed-forward, without the rollout, when its
    derivatives (a partial refresh of the Jacobians kept from the last plan,
    or a full one) and the QP would end in time (counted in
    ``counts["cold_starts_from_reference"]``); otherwise it is put off (the
    LQR's input goes out, status :data:`DEADLINE_STATUS`, counted in
    ``counts["cold_starts_deferred"]``) and tried again next period.
    """

    #: Penalty of the merit function over the QP's largest dynamics multiplier. Measured on 50 states of the
    #: Proposed model's figure8-fast flight (no budget, 400 iterations): 1.1 took 179 iterations on average and
    #: came within 1e-4 of IPOPT's objective on 47 states; 2.0 took 252 and on 38.
    _merit_factor = 1.1

    def __init__(self, model, reference=None, settings: SQPSettings | None = None, spec=None, Q=None, R=None):
        settings = SQPSettings() if settings is None else settings
        if not isinstance(settings, SQPSettings):
            raise ConfigurationError(f"settings must be SQPSettings; found {type(settings).__name__}")
        super().__init__(model, reference, settings, spec, Q, R)
        self.counts["cold_starts"] = 0
        self.counts["cold_starts_deferred"] = 0    # cold starts in flight put off: they would not end in time
        self.counts["cold_starts_from_reference"] = 0   # cold starts in flight from the reference, without rollout
        self.counts["line_search_failures"] = 0
        self.counts["second_order_corrections"] = 0
        self.counts["full_refreshes"] = 0         # iterations that evaluated the Jacobians of every stage
        self._jac_points = self._jac_A = self._jac_B = None   # where each stage's Jacobians were evaluated, and they
        self._f_points = self._f_values = self._f_offset = None   # the model's steps along the last plan
        self._z_scale = np.r_[self._sx, self._su]
        self._refreshed = 0                       # stages whose Jacobians this period evaluated
        self._full_refreshes = 0                  # iterations of this period that evaluated all of them
        self._cold_period = False                 # this period is a cold start (or the pre-flight plan)
        self.counts["preparations"] = 0           # the real-time iteration's QPs prepared
        self.counts["preparations_skipped"] = 0   # preparations not started: they would end past the measurement
        self.counts["preparations_reused"] = 0    # feedbacks that solved a QP prepared for an earlier period
        self.counts["rti_corrections"] = 0        # SQP iterations made by preparations (rti_corrections)
        self._prepared: Preparation | None = None  # the QP the next feedback solves (scheme "rti")
        self._t_call: float | None = None         # the time of the last call, s
        self._fed = None                          # the state the last feedback embedded and the input it sent

    _preflight = False          # planning before take-off (prepare): a cold start without a budget
    _plan_is_current = False    # the plan was made for the next call's time (a pre-flight plan): no shift
    #: :class:`ControlInfo` of the plan made before take-off by :meth:`prepare` (None without one).
    preflight: ControlInfo | None = None

    def prepare(self, t_end: float, x0=None) -> None:
        """Before a flight (see :meth:`mpc.controllers.ltv.LTVMPC.prepare`); with ``x0``, also plan the first period.

        A vehicle standing at ``x0`` before take-off has time to plan: the
        cold start (a model rollout under feed-forward and LQR, then
        ``cold_start_max_iter`` SQP iterations, no time budget) is made for
        ``(x0, t = 0)`` here, and the first period starts from that plan
        (from the measured state) like any later period. It is counted in
        ``counts["cold_starts"]``; its info record is :attr:`preflight`.
        """
        super().prepare(t_end, x0)
        self.preflight = None
        if x0 is None or self.s.cold_start != "rollout" or self._plan_x is not None:
            return
        x0 = check_state(x0)
        self._preflight = True
        try:
            with Timer(self.clock.now) as tm:
                z0 = np.concatenate([x0, self.lqr.start_extra(x0, 0.0)]) if self.model.n_extra else x0
                _, fields = self._period(z0, *self._horizon_reference(0.0), tm)
        finally:
            self._preflight = False
        self.preflight = ControlInfo(solve_time_s=tm.elapsed, **fields)
        self._plan_is_current = self._plan_x is not None
        if self.s.scheme == "rti" and self._plan_x is not None:
            # the first period's QP, along the pre-flight plan: the first input waits for its feedback only
            self._prepare_qp(0.0, self.clock.begin(self.clock.now()), shift=False, record=False)

    def _shifts_plan(self) -> bool:
        """This period's first iterate is the previous plan shifted by one period (not a cold start, and not a plan
        made for this very period before take-off)."""
        return self._plan_x is not None and not self._plan_is_current

    def _initial_iterate(self, x, ref, u_ref):
        """The period's first iterate: the previous plan (shifted, unless made for this period), or at a cold start
        the model's rollout (or, with ``cold_start="hold"``, the state held under the feed-forward)."""
        if self._plan_x is not None and self._plan_is_current:
            X, U = self._plan_x.copy(), self._plan_u.copy()
            X[0] = x
            return X, U
        if self._plan_x is not None or self.s.cold_start == "hold":
            X, U = self._nominal(x, u_ref)   # the shifted plan (or, cold, the state held under the feed-forward)
            if self._shifts_plan() and self.s.tail == "model":
                U[-1] = self._tail_input(X[-2], ref[-2], u_ref[-1])
            return X, U
        return self.rollout(x, ref, u_ref)

    def __call__(self, x, t: float):
        """Input (4,) and :class:`ControlInfo` for the measured state ``x`` at time ``t`` (s)."""
        self._t_call = float(t)
        return super().__call__(x, t)

    def _period(self, x, ref, u_ref, tm, guess=None):
        """One period: the real-time iteration's feedback when a QP is prepared, else the SQP iterations;
        ``(u, ControlInfo fields)``.

        ``x``: the full state (nx,); ``tm``: the call's :class:`Timer`. ``guess``: a first iterate
        ``(X (N + 1, nx), U (N, 4))`` that replaces the shifted plan (and the cold start), also as OSQP's primal
        start.
        """
        if guess is None and self._prepared is not None and self._plan_x is not None:
            return self._feedback(x, ref, u_ref, tm)
        self._prepared = None       # this period's plan replaces the one the QP was prepared along
        return self._iterate(x, ref, u_ref, tm, guess)

    # ----------------------------------------------------------- the real-time iteration
    def _feedback(self, x, ref, u_ref, tm):
        """The real-time iteration's feedback: the prepared QP with the state ``x`` (nx,), solved; the plan it gives,
        full step. ``(u, ControlInfo fields)``."""
        prep = self._prepared      # kept: a feedback whose next preparation is not made solves it again
        age = int(round((self._t_call - prep.t) / DT))     # periods since the one it was prepared for (0: this one)
        if age:
            self.counts["preparations_reused"] += 1
        deadline = self._take_deadline()
        clock = self.clock.begin(tm.start, None, deadline)
        split = dict.fromkeys(SPLIT, 0.0)
        limit = None if deadline is None else max(deadline - clock.now(), MIN_TIME_LIMIT_S)
        X = U = None
        t0 = clock.now()
        # The disturbance estimate and its target as they are now: the offset's change since the preparation moves
        # every step's constant term, and the reference (which holds the target) enters the linear cost.
        off = self.model.offset
        delta = None if _same(off, prep.offset) else \
            (np.zeros(self.nx) if off is None else off) - (0.0 if prep.offset is None else prep.offset)
        if prep.dense is not None:
            from .dense_qp import solve_prepared

            fb = solve_prepared(prep.dense, x, limit, delta=delta, ref=ref, u_ref=u_ref)
            ok, optimal, iterations = fb.solved, fb.solved, fb.iterations
            status = "solved" if ok else f"DAQP exit flag {fb.flag}"
            if ok:
                U = fb.u
                X = prep.dense.states(x, U.ravel(), delta)
        else:
            lo, hi = self._bounds(x, prep.c if delta is None else prep.c + delta)
            self._solver.update(q=self._linear_cost(ref, u_ref), l=lo, u=hi)
            self.update_settings(time_limit=NO_TIME_LIMIT if limit is None else limit)
            res = self._solver.solve(raise_error=False)
            ok, iterations, status = self._solved(res), int(res.info.iter), res.info.status
            optimal = ok and res.info.status_val == self._status.OSQP_SOLVED
            if ok:
                X, U = (a.copy() for a in self._unpack(res.x))
        split["osqp"] += clock.now() - t0
        if not ok and clock.missed():
            status = DEADLINE_STATUS
        u, fields = self._finish(ok, X, U, status, optimal, x, ref, u_ref)
        self._fed = (np.array(x, dtype=float), np.array(u, dtype=float))
        fields["iterations"] = int(ok)
        fields["extra"].update(qp_iterations=iterations, converged=False, cold_start=False, line_search_failures=0,
                               late_full_steps=0, time_split_s=split, merit=[], step_lengths=[1.0] if ok else [],
                               refreshed_stages=prep.refreshed, full_refreshes=int(prep.full),
                               rti={"preparation_s": prep.seconds, "preparation_split_s": prep.split, "age": age,
                                    "reused": age > 0})
        return u, fields

    def prepare_next(self, until: float | None = None) -> None:
        """After a call, once its input is out: with ``scheme="rti"``, prepare the next period's QP.

        ``until``: the time (the controller's clock, s) of the next measurement, or None for no limit. A
        preparation that, at the longest recent preparation's time, would end past it is not started (counted in
        ``counts["preparations_skipped"]``): the next feedback solves the last QP prepared. Never twice in a row:
        when the QP in hand is already a period old the preparation is made whatever it takes (a QP two periods
        old tracks a reference two periods late; a late preparation only keeps the controller busy). Its
        derivatives follow :attr:`SQPSettings.jacobian_refresh` under the same limit (a full refresh that would not
        fit is cut to a partial one).
        """
        if self.s.scheme != "rti" or self._plan_x is None or self._t_call is None:
            return
        # the model's extra states for the next call, out of its input's path (and the model's step the plan starts
        # from: the tracker's last full state is the one fed back)
        ahead = None if self._fed is None else self.tracker.ahead(self._fed[1])
        clock = self.clock.begin(self.clock.now(), None, until)
        # the QP in hand was prepared for the period just flown (times k dt: compared to half a period, not bit for
        # bit, since (k - 1) dt + dt need not equal k dt)
        fresh = self._prepared is not None and abs(self._prepared.t - self._t_call) < 0.5 * DT
        if fresh and not clock.ends_in_time(clock.expect["preparation"]):
            self.counts["preparations_skipped"] += 1
            return
        self._prepare_qp(self._t_call + DT, clock, shift=True, ahead=ahead)
        for _ in range(self.s.rti_corrections):
            prep = self._prepared
            if prep is None or not clock.ends_in_time(clock.expect["correction"]):
                break
            t0 = clock.now()
            plan = self._corrected(prep)
            if plan is None:
                break
            self._prepare_qp(prep.t, clock, shift=False, record=False, plan=plan)
            self.counts["rti_corrections"] += 1
            clock.record("correction", clock.now() - t0)

    def _corrected(self, prep: Preparation):
        """One SQP iteration of the prepared period's problem at the state it predicts (``prep.X[0]``): the plan
        ``(X, U)`` of the prepared QP's full step, or None when it is not solved."""
        x = prep.X[0]
        if prep.dense is not None:
            from .dense_qp import solve_prepared

            fb = solve_prepared(prep.dense, x)
            return (prep.dense.states(x, fb.u.ravel()), fb.u) if fb.solved else None
        self.update_settings(time_limit=NO_TIME_LIMIT)
        res = self._solver.solve(raise_error=False)        # its bounds already hold x (the preparation's own)
        if not self._solved(res):
            return None
        return tuple(a.copy() for a in self._unpack(res.x))

    def _next_state(self, ahead=None) -> np.ndarray:
        """Where the next period starts, as the preparation's plan does: the model's step from the state the last
        feedback embedded under the input it sent (the QP's own prediction is linearized about the point the QP was
        prepared at, which the state may have left); the plan's next state when there is none or it is not finite.
        ``ahead``: that step already made by the extra-state tracker (without the disturbance offset), or None."""
        fed, self._fed = self._fed, None
        if fed is not None:
            if ahead is not None:
                nxt = ahead if self.model.offset is None else ahead + self.model.offset
            else:
                with np.errstate(all="ignore"):
                    nxt = self.model.step(fed[0], fed[1])[0]
            if np.all(np.isfinite(nxt)):
                return nxt
        return self._plan_x[1]

    def _prepare_qp(self, t: float, clock, shift: bool, record: bool = True, plan=None, ahead=None) -> None:
        """Build the QP of the period at ``t`` (s) along the plan (``shift``: moved on by one period, as a plan made
        for the period before), for the next feedback (:class:`Preparation`). ``record``: its time joins the recent
        preparations' (not the one before take-off, which has no limit and pays the first calls' set-up).
        ``plan``: ``(X, U)`` made for the period at ``t`` (a correction's), instead of the controller's plan;
        ``ahead``: the model's step from the state fed back, made by the extra-state tracker (:meth:`_next_state`)."""
        N = self.N
        t0 = clock.now()
        ref, u_ref = self._horizon_reference(t)
        if shift:
            X, U = self._nominal(self._next_state(ahead), u_ref)   # the plan moved on, from the next state predicted
            if self.s.tail == "model":
                U[-1] = self._tail_input(X[-2], ref[-2], u_ref[-1])
            self._shift_kept()
        else:
            X, U = (self._plan_x.copy(), self._plan_u.copy()) if plan is None else (plan[0].copy(), plan[1].copy())
        self._refreshed = self._full_refreshes = 0
        self._cold_period = False
        split = dict.fromkeys(SPLIT, 0.0)
        fx, A, B = self._derivatives(X, U, clock, split, first=True)
        if not self._finite(fx, A, B):
            self._drop_kept()       # the next call is an SQP period, whose first derivatives evaluate every stage
            self._prepared = None
            return
        if shift and self.s.tail == "model":
            X[-1] = fx[-1]
        self._keep_steps(X, U, fx)
        t_qp = clock.now()
        c = self._constant_terms(fx, A, B, X[:N], U)
        dense = None
        if self.s.qp == "daqp":
            from .dense_qp import prepare_ltv_qp

            dense = prepare_ltv_qp(self._ltv_qp(X[0], ref, u_ref, c, A, B), offsets=self.model.offset is not None)
        else:
            self._condensed = None
            lo, hi = self._bounds(X[0], c)
            self._solver.update(q=self._linear_cost(ref, u_ref), l=lo, u=hi, Ax=self._constraint_values(A, B))
            self._solver.warm_start(x=np.concatenate([X.ravel(), U.ravel()]))
        split["assembly"] += clock.now() - t_qp
        seconds = clock.now() - t0
        if record:
            clock.record("preparation", seconds)
        self.counts["preparations"] += 1
        off = self.model.offset
        self._prepared = Preparation(t=t, X=X, U=U, dense=dense, seconds=seconds,
                                     refreshed=self._refreshed, full=self._full_refreshes > 0, split=split, c=c,
                                     offset=None if off is None else np.array(off))

    def _iterate(self, x, ref, u_ref, tm, guess=None):
        """The SQP iterations of one period; ``(u, ControlInfo fields)`` (see :meth:`_period`)."""
        N, s = self.N, self.s
        max_it, budget = s.max_sqp_iter, s.time_budget_s
        cold = shifted = deferred = quick = False
        deadline = self._take_deadline()
        if guess is None:
            cold = self._plan_x is None
            shifted = self._shifts_plan()
            if cold and deadline is not None and not self._preflight:
                # A cold start in flight (the LQR flies meanwhile) keeps the deadline. It starts from the model's
                # rollout when the longest recent such start's first plan (the pre-flight plan's included) would
                # end before the deadline; else from the reference (no rollout) when its derivatives, the QP's
                # assembly and its solve would: a partial refresh of the Jacobians kept from the last plan (their
                # median time), or without any a full one (its longest recent time); else it is put off to a later
                # period. With no cold start made yet it plans whatever it takes.
                c0 = self.clock.begin(tm.start, None, deadline)
                expected = c0.expect["cold_start"]
                if expected <= 0.0:
                    deadline = None
                elif c0.now() + expected > deadline:
                    need = c0.expect["derivatives"] if self._keeps_jacobians() else 0.0
                    need = need if need > 0.0 else c0.expect["full_derivatives"]   # no partial refresh timed yet
                    quick = need > 0.0 and c0.fits(need)
                    deferred = not quick
            if deferred:
                X, U = self._nominal(x, u_ref)      # not planned from: the LQR's input goes out
                max_it = 0
                self.counts["cold_starts_deferred"] += 1
            elif quick:
                X, U = np.array(ref, dtype=float), u_ref.copy()
                X[0] = x
                self.counts["cold_starts_from_reference"] += 1
            else:
                X, U = self._initial_iterate(x, ref, u_ref)
            if cold and not deferred and not quick:
                self._drop_kept()      # a cold start evaluates every stage's derivatives
                self.counts["cold_starts"] += 1
                max_it = max(max_it, s.cold_start_max_iter)
                budget = None if self._preflight else s.cold_start_budget_s
            warm = None if self._z is None else self._z if self._plan_is_current else self._shifted(self._z)
        else:
            X, U = np.array(guess[0], dtype=float), np.array(guess[1], dtype=float)
            X[0] = x
            warm = np.concatenate([X.ravel(), U.ravel()])
        self._plan_is_current = False
        if shifted:
            self._shift_kept()
        self._refreshed = self._full_refreshes = 0
        self._cold_period = cold or self._preflight
        clock = self.clock.begin(tm.start, budget, deadline)
        every = s.jacobian_every if s.hessian == "gauss-newton" else 1
        split = dict.fromkeys(SPLIT, 0.0)
        merits, alphas = [], []
        done = qp_iterations = ls_failures = late_steps = 0
        status, optimal, converged = DEADLINE_STATUS, False, False
        mu = 0.0
        y_last = None       # the last QP's dynamics multipliers (N, nx)
        f_next = None       # the model's step along the line search's new iterate (N, nx), when it made one
        A = B = None
        while done < max_it:
            first = done == 0
            t_it = clock.now()
            if first and clock.no_time_to_start():
                break        # no plan in time: the fallback's input goes out now
            # An iteration between Jacobian evaluations keeps A_k, B_k (and OSQP's factorization) and takes only the
            # model's step at the new iterate (from the line search when it made one).
            reuse = done % every != 0
            if reuse:
                t0 = clock.now()
                with np.errstate(all="ignore"):
                    fx = f_next if f_next is not None else self.model.step(X[:N], U)
                split["derivatives"] += clock.now() - t0
                finite = self._finite(fx)   # A, B passed this check when they were evaluated
            else:
                fx, A, B = self._derivatives(X, U, clock, split, first)
                finite = self._finite(fx, A, B)
            if not finite:
                status = NON_FINITE_STATUS      # OSQP never sees it
                self._drop_kept()               # nothing non-finite is kept for the next period
                break
            if shifted and first:
                warm = self._close_tail(X, U, fx, warm)
            if not clock.qp_window(first):
                status = DEADLINE_STATUS        # too little time left for the period's first QP
                break
            t_h = clock.now()
            hess = self._hessian_values(X[:N + 1], U, y_last)
            split["derivatives"] += clock.now() - t_h
            res, ok, status = self._qp(x, ref, u_ref, X[:N], U, fx, A, B, clock, split, first,
                                       warm=warm if first else None, hess=hess, same_matrices=reuse)
            qp_iterations += int(res.info.iter)
            if not ok:
                break
            if first and cold and not quick:
                clock.record("cold_start", clock.elapsed())   # a cold start's rollout and its first plan
            done += 1
            y_last = res.y[self.nx:self._n_eq].reshape(N, self.nx).copy()
            optimal = res.info.status_val == self._status.OSQP_SOLVED
            Xq, Uq = self._unpack(res.x)
            # With a budget, a period whose QP ended past it, or so close to it that the longest recent line search
            # would end past it, takes the QP's full step (the real-time iteration) and stops: no line search (its
            # model steps and any correction's QP) on top of an overrun.
            late = clock.late(s.line_search)
            late_steps += late
            if s.line_search and not late:
                t_ls = clock.now()
                qp_before = split["assembly"] + split["osqp"]   # a correction's QP is counted there, not here
                mu = max(mu, self._merit_factor * float(np.max(np.abs(y_last))) + 1e-9)
                iteration_s = clock.now() - t_it     # derivatives + QP: more than the correction's QP needs

                def resolve(shift, Xl=X[:N], Ul=U, fx=fx, A=A, B=B, hess=hess):
                    if not clock.room(iteration_s):
                        return None     # no time for the correction's QP: the caller backtracks instead
                    limit = clock.correction_limit()
                    if limit is not None:
                        self.update_settings(time_limit=limit)
                    # The same matrices (A_k, B_k, Hessian): only the bounds change, OSQP keeps its factorization.
                    return self._solve_qp(x, ref, u_ref, Xl, Ul, fx + shift, A, B, split=split, hess=hess,
                                          same_matrices=True)

                Xn, Un, alpha, accepted, phi0, phi, defect, f_next = self._line_search(X, U, Xq, Uq, fx, ref,
                                                                                       u_ref, mu, resolve, clock)
                if f_next is not None:      # the next iteration steps nothing it has just stepped
                    self._keep_steps(Xn, Un, f_next)
                merits.append((phi0, phi, accepted))
                ls_failures += not accepted
                split["line_search"] += clock.now() - t_ls - (split["assembly"] + split["osqp"] - qp_before)
                if budget is not None:
                    clock.record("line_search", clock.now() - t_ls)
            else:
                Xn, Un, alpha, defect, f_next = Xq, Uq, 1.0, np.inf, None
            alphas.append(alpha)
            # Converged when the QP's full step is small (a step shortened by the line search is not convergence).
            step = max(np.max(np.abs(Xq - X) / self._sx), np.max(np.abs(Uq - U) / self._su))
            X, U = Xn, Un
            # Only an iteration with new Jacobians can say that the plan is a KKT point.
            if not reuse and (step < s.step_tol or defect < s.defect_tol):
                converged = True
                break
            # Another iteration only if one as long as the longest so far still fits the budget.
            if late or not clock.another_iteration(clock.now() - (clock.start if done == 1 else t_it)):
                break
        u, fields = self._finish(done > 0, X, U, status, optimal, x, ref, u_ref)
        self._keep_steps(X, U, f_next if done > 0 else None)
        fields["iterations"] = done
        fields["extra"].update(qp_iterations=qp_iterations, converged=converged, cold_start=cold and not deferred,
                               line_search_failures=ls_failures, late_full_steps=late_steps, time_split_s=split,
                               merit=merits, step_lengths=alphas, refreshed_stages=self._refreshed,
                               full_refreshes=self._full_refreshes)
        return u, fields

    def _derivatives(self, X, U, clock, split, first: bool):
        """``(f(X, U), A, B)`` along the plan's first N stages: all new (``jacobian_refresh="full"``, or nothing
        kept yet), or, with ``"partial"``, the Jacobians of the stages that moved and the steps of the stages not
        already stepped at exactly their point (:class:`SQPSettings`)."""
        N, s = self.N, self.s
        Z = np.hstack([X[:N], U])
        if self._keeps_jacobians():
            far = np.max(np.abs(Z - self._jac_points) / self._z_scale, axis=1)
            far = np.where(np.isfinite(far), far, np.inf)
            stale = np.flatnonzero(far > s.refresh_tol)
        # Under a deadline, a full refresh that would not leave time for the QP is cut to a partial one.
        if not self._keeps_jacobians() or \
                (len(stale) > s.full_refresh_above and clock.fits(clock.expect["full_derivatives"])):
            # The full path records its first derivatives as before. The partial path's expected first derivatives
            # are a partial refresh's (a full one is checked against the deadline on its own, against every full
            # refresh's time, the pre-flight plan's included: the first warm period may need one).
            full_path = s.jacobian_refresh == "full"
            t0 = clock.now()
            fx, A, B = super()._derivatives(X, U, clock, split, first=first and full_path)
            clock.record("full_derivatives", clock.now() - t0)
            self.counts["full_refreshes"] += 1
            self._full_refreshes += 1
            self._refreshed += N
            if not full_path:
                self._jac_points, self._jac_A, self._jac_B = Z, A.copy(), B.copy()
            return fx, A, B
        t0 = clock.now()
        with np.errstate(all="ignore"):
            fx = self._steps(X[:N], U, Z)
            if len(stale) > s.max_refresh_stages:
                stale = np.sort(stale[np.argsort(-far[stale], kind="stable")[:s.max_refresh_stages]])
            if len(stale):
                A_s, B_s = self.model.jacobians(X[stale], U[stale]) if s.jacobians == "float32" else \
                    self.model.linearize(X[stale], U[stale])[1:]
                self._jac_A[stale], self._jac_B[stale], self._jac_points[stale] = A_s, B_s, Z[stale]
        self._refreshed += len(stale)
        seconds = clock.now() - t0
        split["derivatives"] += seconds
        if first and not self._cold_period:
            clock.record("derivatives", seconds)
        return fx, self._jac_A.copy(), self._jac_B.copy()

    def _keeps_jacobians(self) -> bool:
        """The next Jacobian iteration may refresh only some stages: the partial path has Jacobians kept (and the
        Hessian is the Gauss-Newton one)."""
        s = self.s
        return s.jacobian_refresh == "partial" and s.hessian != "exact" and self._jac_points is not None

    def _steps(self, X, U, Z):
        """The model's steps (N, nx) at the stages ``(X, U)`` (points ``Z``): kept ones where a stage is exactly a
        point stepped before (under the same offset), new ones elsewhere (one batched call)."""
        kept = self._f_points is not None and _same(self._f_offset, self.model.offset)
        same = np.all(Z == self._f_points, axis=1) if kept else np.zeros(len(Z), dtype=bool)
        if not same.any():
            return self.model.step(X, U)
        fx = self._f_values.copy()
        if not same.all():
            miss = ~same
            fx[miss] = self.model.step(X[miss], U[miss])
        return fx

    def _keep_steps(self, X, U, f) -> None:
        """Keep the model's steps ``f`` (N, nx) along the plan ``(X, U)`` for the next iteration or period (None:
        none)."""
        if f is None or self.s.jacobian_refresh != "partial":
            self._f_points = self._f_values = None
            return
        self._f_points, self._f_values = np.hstack([X[:self.N], U]), f
        self._f_offset = None if self.model.offset is None else np.array(self.model.offset)

    def _drop_kept(self) -> None:
        """Forget the kept Jacobians and steps: the next Jacobian iteration evaluates every stage."""
        self._jac_points = self._jac_A = self._jac_B = None
        self._f_points = self._f_values = self._f_offset = None

    def _shift_kept(self) -> None:
        """The kept Jacobians and steps follow the plan's shift by one stage (the last stage keeps its own)."""
        def shift(a):
            return None if a is None else shift_stages(a)
        self._jac_points, self._jac_A, self._jac_B = (shift(a) for a in (self._jac_points, self._jac_A, self._jac_B))
        self._f_points, self._f_values = shift(self._f_points), shift(self._f_values)

    def _tail_input(self, x, r, u_ff):
        """Feed-forward plus hover LQR at a state ``x`` about reference ``r``, projected onto the rotor-feasible set."""
        return self._rotor_feasible(u_ff - self.lqr.K @ (x - r))

    def _close_tail(self, X, U, fx, warm):
        """With ``tail="model"``, the shifted plan's last state is the model's prediction from its last stage
        (``fx[-1]``, from the first linearization: no extra model call), and OSQP starts from that plan."""
        if self.s.tail != "model":
            return warm
        X[-1] = fx[-1]
        return np.concatenate([X.ravel(), U.ravel()])

    def solve_from(self, x, t: float, X0, U0):
        """Solve the period at ``(x, t)`` from the first iterate ``(X0 (N + 1, nx), U0 (N, 4))``.

        ``x`` is the full state (nx,): the measured rigid-body state followed by the model's extra states.

        The controller's warm start is replaced by this guess (and its plan by
        the result). Returns ``(X, U, info)``; for comparisons with
        :meth:`mpc.controllers.nmpc.NMPC.solve_from` from the same guess.
        """
        x = check_state(x, nx=self.nx)
        X0, U0 = np.asarray(X0, dtype=float), np.asarray(U0, dtype=float)
        if X0.shape != (self.N + 1, self.nx) or U0.shape != (self.N, 4):
            raise ConfigurationError(f"X0 must be ({self.N + 1}, {self.nx}) and U0 ({self.N}, 4); "
                                     f"found {X0.shape} and {U0.shape}")
        with Timer(self.clock.now) as tm:
            ref, u_ref = self._horizon_reference(t)
            _, fields = self._period(x, ref, u_ref, tm, guess=(X0, U0))
        return self._plan_x.copy(), self._plan_u.copy(), ControlInfo(solve_time_s=tm.elapsed, **fields)

    def rollout(self, x, ref, u_ref):
        """The model flown from ``x`` under the feed-forward and the hover LQR: ``X (N + 1, nx), U (N, 4)``.

        Inputs are projected onto the rotor-feasible set; a non-finite model
        output ends the rollout (the rest holds the last finite state).
        """
        N = self.N
        X = np.empty((N + 1, self.nx))
        U = np.empty((N, u_ref.shape[1]))
        X[0] = x
        for k in range(N):
            U[k] = self.inputs.project(u_ref[k] - self.lqr.K @ (X[k] - ref[k]))
            with np.errstate(all="ignore"):
                nxt = self.model.step(X[k], U[k])[0]
            X[k + 1] = nxt if np.all(np.isfinite(nxt)) else X[k]
        return X, U

    # ----------------------------------------------------------- exact Hessian
    def _build_hessian(self):
        """With ``hessian="exact"``, a full 16 x 16 block per stage (state and input), ``P`` at the end."""
        if self.s.hessian != "exact":
            return super()._build_hessian()
        nx = self.nx
        N, nz = self.N, nx + NU
        iu, ju = np.triu_indices(nz)
        base = np.zeros((nz, nz))
        base[:nx, :nx], base[nx:, nx:] = self.Q, self.R
        rows, cols, vals = [], [], []
        for k in range(N):
            idx = np.r_[self._xi(k) + np.arange(nx), self._ui(k) + np.arange(NU)]   # ascending: upper triangle
            rows.append(idx[iu])
            cols.append(idx[ju])
            vals.append(base[iu, ju])
        it, jt = np.triu_indices(nx)
        idx = self._xi(N) + np.arange(nx)
        rows.append(idx[it])
        cols.append(idx[jt])
        vals.append(self.P[it, jt])
        rows, cols, vals = (np.concatenate(a) for a in (rows, cols, vals))
        n_var = self.nx_var + N * NU
        self._h_vals, self._h_base, self._h_tri = vals, base, (iu, ju)
        self._h_scale = np.r_[self._sx, self._su]
        placeholder = np.where(vals == 0.0, 1e-12, vals)    # explicit entries for the pattern; replaced every QP
        H, self._h_perm = csc_in_entry_order(rows, cols, placeholder, (n_var, n_var))
        return H

    def _hessian_values(self, X, U, y):
        if self.s.hessian != "exact":
            return None
        nx = self.nx
        N, nz = self.N, nx + NU
        blocks = np.broadcast_to(self._h_base, (N, nz, nz)).copy()
        if y is not None:
            blocks += self._lagrangian_curvature(X[:N], U, y)
            # Positive definite per stage, in the acceptable deviations (where the cost's block is the identity).
            S = self._h_scale
            w, V = np.linalg.eigh(blocks * S[None, :, None] * S[None, None, :])
            w = np.maximum(w, EIGEN_FLOOR)
            blocks = ((V * w[:, None, :]) @ V.transpose(0, 2, 1)) / S[None, :, None] / S[None, None, :]
            blocks = 0.5 * (blocks + blocks.transpose(0, 2, 1))
        vals = self._h_vals.copy()
        iu, ju = self._h_tri
        vals[:N * len(iu)] = blocks[:, iu, ju].ravel()
        added = blocks - self._h_base                          # the curvature the cost does not have
        Z = np.hstack([X[:N], U])
        g = -np.einsum("kij,kj->ki", added, Z)                  # linear term of (z - z_k)' added (z - z_k) / 2
        dq = np.zeros(self.nx_var + N * NU)
        dq[:self.nx_var - nx] = g[:, :nx].ravel()
        dq[self.nx_var:] = g[:, nx:].ravel()
        return vals[self._h_perm], dq

    def _lagrangian_curvature(self, X, U, y):
        """``sum_i y_ki d2 f_i / dz2`` per stage (N, nx + 4, nx + 4) by central differences of the model's Jacobians."""
        nx = self.nx
        N, nz = self.N, nx + NU
        Z = np.hstack([X, U])
        h = EXACT_FD_STEP * self._h_scale
        E = np.diag(h)
        pts = np.concatenate([Z[:, None, :] + E[None], Z[:, None, :] - E[None]], axis=1).reshape(-1, nz)
        with np.errstate(all="ignore"):
            _, A, B = self.model.linearize(pts[:, :nx], pts[:, nx:])
        J = np.concatenate([A, B], axis=2).reshape(N, 2, nz, nx, nz)
        g = np.einsum("ksjic,ki->ksjc", J, y)                   # gradient of y_k' f at each point
        H = (g[:, 0] - g[:, 1]) / (2.0 * h[None, :, None])
        H = 0.5 * (H + H.transpose(0, 2, 1))
        return np.where(np.isfinite(H), H, 0.0)

    # ----------------------------------------------------------- merit function
    def cost(self, X, U, ref, u_ref) -> float:
        """Tracking cost ``J`` of a plan (the NMPC's objective): stage, input and terminal terms."""
        E = X - ref
        D = U - u_ref
        N = self.N
        return float(np.einsum("ki,ij,kj->", E[:N], self.Q, E[:N]) + np.einsum("ki,ij,kj->", D, self.R, D)
                     + E[N] @ self.P @ E[N])

    def _merit(self, X, U, fx, ref, u_ref, mu) -> float:
        return 0.5 * self.cost(X, U, ref, u_ref) + mu * float(np.sum(np.abs(fx - X[1:])))

    def _line_search(self, X, U, Xq, Uq, fx, ref, u_ref, mu, resolve, clock=None):
        """The next iterate: the full step, a second-order correction, or a shortened step.

        Returns ``(X, U, alpha, accepted, phi(0), phi(new), defect(new), f(new))``; ``alpha`` is 1 for
        the full step, ``-1`` for the second-order correction; ``f(new)`` (N, nx) is the model's step
        along the new iterate (for an iteration that reuses the Jacobians). A full step
        without sufficient decrease of the merit (Armijo, :data:`ARMIJO`) is
        first corrected: the QP is solved again with the model's defects at the
        full step added to its dynamics constraints (one more QP, no new
        derivatives), which removes the second-order error of the
        linearization that makes full steps fail near a solution. If that
        fails too the step is halved up to :data:`MAX_BACKTRACKS` times, each
        time only if the ``clock`` (a :class:`mpc.controllers.timing.PeriodClock`, None for
        no limit) has another trial's time left of its budget (the first
        trial's: one model step and its merit); without sufficient decrease the
        point with the lowest merit tried is taken (and counted as a failure).
        """
        N = self.N
        phi0 = self._merit(X, U, fx, ref, u_ref, mu)
        dX, dU = Xq - X, Uq - U
        E, D = X - ref, U - u_ref
        grad = (np.sum((E[:N] @ self.Q) * dX[:N]) + E[N] @ self.P @ dX[N] + np.sum((D @ self.R) * dU))
        slope = min(grad - mu * float(np.sum(np.abs(fx - X[1:]))), 0.0)
        best = (np.inf, X, U, 0.0, fx)      # merit, plan, step length, model step of the best trial

        def trial(Xt, Ut, alpha):
            nonlocal best
            with np.errstate(all="ignore"):
                ft = self.model.step(Xt[:N], Ut)
            phi = self._merit(Xt, Ut, ft, ref, u_ref, mu) if np.all(np.isfinite(ft)) else np.inf
            if phi < best[0]:
                best = (phi, Xt, Ut, alpha, ft)
            return ft, phi, phi <= phi0 + ARMIJO * abs(alpha) * slope

        t0 = None if clock is None else clock.now()
        ft, phi, ok = trial(Xq, Uq, 1.0)
        trial_s = None if clock is None else clock.now() - t0
        if ok:
            return Xq, Uq, 1.0, True, phi0, phi, self._defect(ft, Xq), ft
        if np.all(np.isfinite(ft)):
            res = resolve(ft - Xq[1:])
            if res is not None and self._solved(res):
                Xc, Uc = self._unpack(res.x)
                fc, phi, ok = trial(Xc, Uc, -1.0)
                if ok:
                    self.counts["second_order_corrections"] += 1
                    return Xc, Uc, -1.0, True, phi0, phi, self._defect(fc, Xc), fc
        alpha = BACKTRACK
        for _ in range(MAX_BACKTRACKS):
            if clock is not None and not clock.room(trial_s):
                break       # another trial would end past the budget: the best one tried so far
            Xt, Ut = X + alpha * dX, U + alpha * dU
            ft, phi, ok = trial(Xt, Ut, alpha)
            if ok:
                return Xt, Ut, alpha, True, phi0, phi, self._defect(ft, Xt), ft
            alpha *= BACKTRACK
        self.counts["line_search_failures"] += 1
        defect = self._defect(best[4], best[1]) if best[0] < np.inf else np.inf   # no finite trial: no defect
        return best[1], best[2], best[3], False, phi0, best[0], defect, best[4]

    def _defect(self, f, X) -> float:
        """Largest dynamics defect of a plan, in the acceptable deviations of the default weights."""
        return float(np.max(np.abs(f - X[1:]) / self._sx))

