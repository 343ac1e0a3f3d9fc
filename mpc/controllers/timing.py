"""The timing rules of one control period: a time budget, a deadline and the times expected from recent periods.

The QP controllers (:class:`mpc.controllers.ltv.LTVMPC`, :class:`mpc.controllers.sqp.SQPMPC`) ask a
:class:`PeriodClock` every question whose answer depends on the wall clock:
may the period start its first linearization, how long may OSQP run, is there
time for a line search, a correction's QP or another iteration. Everything
else they do is independent of the machine's speed. The clock is a callable
(``time.perf_counter`` by default), so the rules are tested with a fake one.

Two limits, both optional:

* the **budget** (s from the period's start): the SQP's own limit on its
  iterations; after its first QP, which must give a plan, nothing may run past
  it;
* the **deadline** (an absolute clock time): when the input must be out. A
  period that cannot make its first plan before it (from the median times of
  the first derivatives, QP assembly and QP solve over :data:`RECENT_PERIODS`
  periods) gives up at once, so that its fallback goes out in time; model
  work that is optional (a full refresh of the Jacobians) is done only when
  it leaves the QP its expected time.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

#: OSQP's "no time limit" (its default setting), s.
NO_TIME_LIMIT = 1e10
#: Least time OSQP is given before a deadline, s: with less, the period takes its fallback at once.
MIN_QP_TIME_S = 3e-4
#: Least time limit handed to OSQP, s (a limit of zero would mean none).
MIN_TIME_LIMIT_S = 1e-4
#: The expected time of a period's first derivatives, QP assembly and QP solve is the median of this many recent
#: periods (one slow period does not make the next ones give up); that of work a period may leave out (a line
#: search, a full refresh of the Jacobians), the longest of them.
RECENT_PERIODS = 20
#: Work a period may leave out (a cold start in flight: the LQR flies meanwhile; the real-time iteration's
#: preparation: the last QP prepared is solved instead; a correction within it): its expected time is the longest
#: recent one.
OPTIONAL = ("line_search", "full_derivatives", "cold_start", "preparation", "correction")
#: What the clock keeps recent times of: a period's first derivatives, QP assembly and QP solve, line searches, the
#: derivatives of every stage (a full refresh of the SQP's partial path), and a cold start's time to its first plan
#: (from the period's start: the rollout, the derivatives and the first QP), and the real-time iteration's
#: preparations and the corrections they make.
RECORDED = ("derivatives", "assembly", "qp", "line_search", "full_derivatives", "cold_start", "preparation",
            "correction")


def period_stats(seconds) -> dict | None:
    """Median, p95, p99 and max, ms, of per-period times ``seconds`` (s; NaN, a period without a call, left out), or
    None without any."""
    ms = 1e3 * np.asarray(seconds, dtype=float)
    ms = ms[np.isfinite(ms)]
    if not ms.size:
        return None
    return {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "p99": float(np.percentile(ms, 99)),
            "max": float(np.max(ms))}


def _median(values) -> float:
    """The median of a few floats, as ``numpy.median`` gives it (0 for none); in plain Python, since numpy's costs
    tens of microseconds on a list of 20, four times a period."""
    v = sorted(values)
    n = len(v)
    if n == 0:
        return 0.0
    return float(v[n // 2]) if n % 2 else float((v[n // 2 - 1] + v[n // 2]) / 2.0)


class PeriodClock:
    """Budget and deadline rules of a control period, with the recent periods' times.

    Parameters
    ----------
    clock : callable, optional
        ``clock() -> float``, s (default ``time.perf_counter``).
    recent : int, optional
        How many periods' times are kept (:data:`RECENT_PERIODS`).

    Call :meth:`begin` at the start of each period; the other methods answer
    for that period.
    """

    def __init__(self, clock=time.perf_counter, recent: int = RECENT_PERIODS):
        if isinstance(recent, bool) or not isinstance(recent, (int, np.integer)) or recent < 1:
            raise ValueError(f"recent must be an integer >= 1; found {recent!r}")
        self.now = clock
        self._recent = {k: deque(maxlen=int(recent)) for k in RECORDED}
        self.begin(self.now())

    def begin(self, start: float, budget: float | None = None, deadline: float | None = None) -> "PeriodClock":
        """Start a period at clock time ``start`` (s) with a ``budget`` (s) and a ``deadline`` (clock time), each
        None for none. Returns the clock."""
        self.start, self.budget, self.deadline = start, budget, deadline
        #: Expected seconds: the median of the recent first derivatives, assemblies and solves, the longest of the
        #: recent optional work (:data:`OPTIONAL`).
        self.expect = {k: max(v, default=0.0) if k in OPTIONAL else _median(v) for k, v in self._recent.items()}
        self.qp_left: float | None = None     # what OSQP may take before the deadline, s (set by qp_window)
        self.longest = 0.0                    # the longest iteration so far, s
        return self

    def record(self, kind: str, seconds: float) -> None:
        """Keep the time (s) of a period's first derivatives, first QP assembly, first QP solve, a line search, a
        full refresh or a cold start's first plan (:data:`RECORDED`)."""
        self._recent[kind].append(seconds)

    def elapsed(self) -> float:
        """Seconds since the period began."""
        return self.now() - self.start

    # ----------------------------------------------------------- deadline
    def no_time_to_start(self) -> bool:
        """The period's first derivatives and QP, at their expected times, would end past the deadline."""
        return not self.fits(self.expect["derivatives"])

    def fits(self, seconds: float) -> bool:
        """Work of ``seconds`` started now, then the QP's assembly and its solve at their expected times (the solve
        at least :data:`MIN_QP_TIME_S`), ends before the deadline (or there is none)."""
        return self.deadline is None or \
            self.now() + seconds + self.expect["assembly"] + max(self.expect["qp"], MIN_QP_TIME_S) <= self.deadline

    def ends_in_time(self, seconds: float) -> bool:
        """Work of ``seconds`` started now, and nothing after it, ends before the deadline (or there is none): asked
        before the real-time iteration's preparation, whose deadline is the next measurement."""
        return self.deadline is None or self.now() + seconds <= self.deadline

    def qp_window(self, first: bool) -> bool:
        """After the derivatives: set what OSQP may take before the deadline once its problem is assembled; False
        when that is too little for the period's ``first`` QP (the period then gives up)."""
        if self.deadline is None:
            return True
        self.qp_left = max(self.deadline - self.now() - self.expect["assembly"], MIN_TIME_LIMIT_S)
        return not (first and self.qp_left < MIN_QP_TIME_S)

    def missed(self) -> bool:
        """A QP that failed stopped at the deadline (too little time was left for it)."""
        return self.deadline is not None and self.now() > self.deadline - MIN_QP_TIME_S

    # ----------------------------------------------------------- budget
    def qp_time_limit(self, first: bool) -> float | None:
        """OSQP's time limit for the next QP, s, or None to leave OSQP's setting as it is (no budget, no deadline).

        The period's ``first`` QP must give a plan: it has no budget limit. A
        later one gets what is left of the budget, and every QP no more than
        the deadline's window (:meth:`qp_window`).
        """
        if self.budget is None and self.deadline is None:
            return None
        limit = NO_TIME_LIMIT
        if self.budget is not None and not first:
            limit = max(self.budget - self.elapsed(), MIN_TIME_LIMIT_S)
        if self.deadline is not None and self.qp_left is not None:
            limit = min(limit, self.qp_left)
        return limit

    def late(self, line_search: bool) -> bool:
        """The QP just solved ended past the budget, or so close to it that the longest recent line search (when
        one would run) would end past it: the period takes the QP's full step and stops."""
        if self.budget is None:
            return False
        elapsed = self.elapsed()
        return elapsed > self.budget or (line_search and elapsed + self.expect["line_search"] > self.budget)

    def room(self, seconds: float) -> bool:
        """At least ``seconds`` are left of the budget, or there is no budget. Asked before a second-order
        correction's QP (with an iteration's derivatives and QP: more than it needs) and before each shortened step
        of a line search (with the time of its first trial step)."""
        return self.budget is None or self.budget - self.elapsed() >= seconds

    def correction_limit(self) -> float | None:
        """OSQP's time limit for a correction's QP: what is left of the budget, s; None (leave OSQP's setting, the
        deadline's window of the iteration's QP) without a budget."""
        return None if self.budget is None else self.budget - self.elapsed()

    def another_iteration(self, iteration_s: float) -> bool:
        """After an iteration of ``iteration_s`` seconds: one as long as the longest so far still fits the budget.

        Pass the first iteration's time from the period's start (it carries the
        period's set-up, so the rule errs towards stopping).
        """
        self.longest = max(self.longest, iteration_s)
        return self.budget is None or self.elapsed() + self.longest <= self.budget
