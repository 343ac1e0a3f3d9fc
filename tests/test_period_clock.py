"""The timing rules of a control period (mpc.controllers.timing.PeriodClock) on a fake clock: no test here reads the
machine's.

The controllers ask the clock every question that depends on the wall clock; these tests give it a clock that
moves only when told, so each rule is checked at known times on either side of its threshold.
"""

import numpy as np
import pytest

from mpc.controllers.timing import (MIN_QP_TIME_S, MIN_TIME_LIMIT_S, NO_TIME_LIMIT, OPTIONAL, RECENT_PERIODS, RECORDED,
                                    PeriodClock)

#: Tolerance of the times compared here (s): the fake clock adds exactly, so only float rounding.
TOL = {"seconds": 1e-12,
       "busy_wait_s": 2e-6}      # a busy wait ends within one read of the fake wall clock (which moves 1e-6 a read)


class FakeClock:
    """A clock that reads ``t`` (s) and moves only by :meth:`advance`."""

    def __init__(self, t: float = 100.0):
        self.t = t

    def __call__(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


def clock_with(recent=()):
    """A PeriodClock on a fake clock, with recent times ``[(kind, seconds), ...]`` recorded."""
    fake = FakeClock()
    c = PeriodClock(fake)
    for kind, s in recent:
        c.record(kind, s)
    return c, fake


def test_without_budget_or_deadline_every_rule_lets_the_period_run():
    c, fake = clock_with([("derivatives", 5.0), ("assembly", 5.0), ("line_search", 5.0)])
    c.begin(fake())
    fake.advance(60.0)
    assert not c.no_time_to_start() and c.qp_window(first=True) and c.qp_time_limit(first=False) is None
    assert not c.late(line_search=True) and c.room(1e6) and c.correction_limit() is None
    assert c.another_iteration(1e6) and not c.missed()


def test_expected_times_are_the_recent_median_and_the_longest_line_search():
    c, fake = clock_with([("derivatives", s) for s in (1e-3, 9e-3, 2e-3)] + [("assembly", 4e-4)]
                         + [("line_search", s) for s in (1e-4, 3e-3, 2e-4)])
    c.begin(fake())
    assert c.expect["derivatives"] == pytest.approx(2e-3, abs=TOL["seconds"])
    assert c.expect["assembly"] == pytest.approx(4e-4, abs=TOL["seconds"])
    assert c.expect["line_search"] == pytest.approx(3e-3, abs=TOL["seconds"])
    for _ in range(RECENT_PERIODS):           # older periods drop out
        c.record("derivatives", 5e-4)
    assert c.begin(fake()).expect["derivatives"] == pytest.approx(5e-4, abs=TOL["seconds"])


@pytest.mark.parametrize("recent", [RECENT_PERIODS, 3])
def test_slow_periods_age_out_and_the_work_they_held_back_runs_again(recent):
    """One slow period of each kind of optional work (a line search, a full refresh, a cold start, the real-time
    iteration's preparation), and a stretch
    of ``recent`` slow first derivatives, hold that work back only while they are among the last ``recent``
    periods: once as many normal periods followed, every rule lets it run again. A history that never dropped old
    periods would keep a line search off for the rest of the flight after one slow one."""
    slow, normal, qp = 7e-3, 1e-3, 5e-4
    fake = FakeClock()
    c = PeriodClock(fake, recent=recent)
    c.record("assembly", qp)
    c.record("qp", qp)

    def allowed() -> dict:
        """What this period may do: a line search after a QP that ended 5 ms into an 8 ms budget, and with 4 ms
        left before the deadline a full refresh, a cold start from the rollout, or the period's first
        derivatives (each followed by the QP's 0.5 ms assembly and 0.5 ms solve)."""
        c.begin(fake(), budget=8e-3)
        fake.advance(5e-3)
        out = {"line_search": not c.late(line_search=True)}
        c.begin(fake(), deadline=fake() + 4e-3)
        out.update({k: c.fits(c.expect[k]) for k in ("full_derivatives", "cold_start")})
        out["derivatives"] = not c.no_time_to_start()
        out["preparation"] = c.ends_in_time(c.expect["preparation"])
        out["correction"] = c.ends_in_time(c.expect["correction"])
        return out

    kinds = (*OPTIONAL, "derivatives")
    assert all(allowed().values())                         # nothing recorded yet: every rule lets the work run
    for k in OPTIONAL:
        c.record(k, slow)                                  # one slow period of each optional work
    for _ in range(recent):
        c.record("derivatives", slow)                      # a stretch of slow periods: the median follows
    assert not any(allowed().values())
    for i in range(recent):
        now = allowed()                                    # a slow period is still among the last `recent`:
        assert not any(now[k] for k in OPTIONAL), i        # the optional work waits (its longest recent time)
        assert now["derivatives"] == (2 * i > recent), i   # the first derivatives once most are normal (median)
        for k in kinds:
            c.record(k, normal)
    assert allowed() == dict.fromkeys(kinds, True)         # all of them aged out
    c.begin(fake())
    for k in kinds:
        assert c.expect[k] == pytest.approx(normal, abs=TOL["seconds"]), k


def test_a_period_starts_only_if_its_first_derivatives_and_qp_fit_before_the_deadline():
    d, a = 2e-3, 5e-4
    c, fake = clock_with([("derivatives", d), ("assembly", a)])
    need = d + a + MIN_QP_TIME_S
    c.begin(fake(), deadline=fake() + need + 1e-6)
    assert not c.no_time_to_start()
    c.begin(fake(), deadline=fake() + need - 1e-6)
    assert c.no_time_to_start()


def test_the_expected_qp_solve_counts_against_the_deadline_too():
    d, a, q = 2e-3, 5e-4, 9e-4
    c, fake = clock_with([("derivatives", d), ("assembly", a), ("qp", q)])
    need = d + a + q                                    # the solve's median, not the least QP time
    c.begin(fake(), deadline=fake() + need + 1e-6)
    assert not c.no_time_to_start()
    c.begin(fake(), deadline=fake() + need - 1e-6)
    assert c.no_time_to_start()
    # A solve faster than the least QP time still counts as that.
    c, fake = clock_with([("derivatives", d), ("assembly", a), ("qp", MIN_QP_TIME_S / 10)])
    c.begin(fake(), deadline=fake() + d + a + MIN_QP_TIME_S - 1e-6)
    assert c.no_time_to_start()


def test_optional_work_is_expected_to_take_its_longest_recent_time_and_the_rest_their_median():
    times = (1e-3, 7e-3, 2e-3)
    c, fake = clock_with([(k, s) for k in RECORDED for s in times])
    c.begin(fake())
    for k in RECORDED:
        want = 7e-3 if k in OPTIONAL else 2e-3
        assert c.expect[k] == pytest.approx(want, abs=TOL["seconds"]), k
    assert set(OPTIONAL) == {"line_search", "full_derivatives", "cold_start", "preparation", "correction"}
    # A full refresh is judged by its longest recent time: 7 ms of it, then the assembly and the solve.
    c.begin(fake(), deadline=fake() + 7e-3 + 2e-3 + 2e-3 + 1e-6)
    assert c.fits(c.expect["full_derivatives"])
    c.begin(fake(), deadline=fake() + 7e-3 + 2e-3 + 2e-3 - 1e-6)
    assert not c.fits(c.expect["full_derivatives"])
    # A preparation by its longest recent time alone: nothing follows it before its deadline.
    c.begin(fake(), deadline=fake() + 7e-3 + 1e-6)
    assert c.ends_in_time(c.expect["preparation"])
    c.begin(fake(), deadline=fake() + 7e-3 - 1e-6)
    assert not c.ends_in_time(c.expect["preparation"])
    c.begin(fake())
    assert c.ends_in_time(1e9)                           # no deadline


def test_the_qp_window_is_what_is_left_before_the_deadline_after_the_assembly():
    c, fake = clock_with([("assembly", 5e-4)])
    c.begin(fake(), deadline=fake() + 3e-3)
    fake.advance(1e-3)                                   # the derivatives took 1 ms
    assert c.qp_window(first=True)
    assert c.qp_left == pytest.approx(3e-3 - 1e-3 - 5e-4, abs=TOL["seconds"])
    assert c.qp_time_limit(first=True) == pytest.approx(c.qp_left, abs=TOL["seconds"])
    # Too little for the first QP: the period gives up; a later QP still gets the floor.
    c.begin(fake(), deadline=fake() + 5e-4 + MIN_QP_TIME_S - 1e-6)
    assert not c.qp_window(first=True)
    c.begin(fake(), deadline=fake() - 1.0)
    assert c.qp_window(first=False) and c.qp_left == MIN_TIME_LIMIT_S


def test_the_first_qp_has_no_budget_limit_and_a_later_one_gets_what_is_left():
    c, fake = clock_with()
    c.begin(fake(), budget=8e-3)
    fake.advance(3e-3)
    assert c.qp_time_limit(first=True) == NO_TIME_LIMIT
    assert c.qp_time_limit(first=False) == pytest.approx(5e-3, abs=TOL["seconds"])
    fake.advance(10e-3)                                   # past the budget: OSQP still gets the floor, not zero
    assert c.qp_time_limit(first=False) == MIN_TIME_LIMIT_S
    # With a deadline too, the tighter of the two.
    c.begin(fake(), budget=8e-3, deadline=fake() + 4e-3)
    fake.advance(1e-3)
    assert c.qp_window(first=False)
    assert c.qp_time_limit(first=False) == pytest.approx(3e-3, abs=TOL["seconds"])


def test_a_qp_ending_near_the_budget_is_late_when_the_longest_line_search_would_not_fit():
    c, fake = clock_with([("line_search", 2e-3)])
    c.begin(fake(), budget=8e-3)
    fake.advance(5.9e-3)
    assert not c.late(line_search=True) and not c.late(line_search=False)
    fake.advance(0.2e-3)                                  # 6.1 ms: a 2 ms line search would end at 8.1
    assert c.late(line_search=True) and not c.late(line_search=False)
    fake.advance(2e-3)                                    # past the budget itself
    assert c.late(line_search=False)


def test_a_correction_or_a_shortened_step_runs_only_with_its_time_left_of_the_budget():
    c, fake = clock_with()
    c.begin(fake(), budget=8e-3)
    fake.advance(5e-3)
    assert c.room(3e-3 - 1e-6) and not c.room(3e-3 + 1e-6)
    assert c.correction_limit() == pytest.approx(3e-3, abs=TOL["seconds"])


def test_another_iteration_needs_room_for_the_longest_one_so_far():
    c, fake = clock_with()
    c.begin(fake(), budget=8e-3)
    fake.advance(3e-3)
    assert c.another_iteration(3e-3)                    # 3 + 3 <= 8
    fake.advance(1e-3)
    assert c.another_iteration(1e-3) and c.longest == 3e-3   # 4 + 3 <= 8: the longest is kept
    fake.advance(1.5e-3)
    assert not c.another_iteration(1.5e-3)              # 5.5 + 3 > 8


def test_a_failed_qp_is_put_down_to_the_deadline_only_near_it():
    c, fake = clock_with()
    c.begin(fake(), deadline=fake() + 1e-3)
    fake.advance(1e-3 - MIN_QP_TIME_S - 1e-6)
    assert not c.missed()
    fake.advance(2e-6)
    assert c.missed()


@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_a_bad_history_length_is_refused(bad):
    with pytest.raises(ValueError, match="recent"):
        PeriodClock(FakeClock(), recent=bad)


def test_the_sqp_asks_its_clock_a_deadline_it_cannot_meet_and_sends_the_shifted_plan():
    """The controller's own use of the rules, on the fake clock: a deadline already past at the period's start
    makes no derivatives and sends the shifted plan; one far away changes nothing."""
    from mpc.prediction.models import AnalyticModel
    from mpc.controllers.sqp import SQPMPC, SQPSettings
    from mpc.references.trajectory import Figure8

    fig8 = Figure8(0.75, 3.0, 1.0)
    ideal = SQPSettings(time_budget_s=None, cold_start_budget_s=None)
    sqp, twin = SQPMPC(AnalyticModel(), fig8, ideal), SQPMPC(AnalyticModel(), fig8, ideal)
    fake = FakeClock(0.0)
    sqp.clock = PeriodClock(fake)
    x = fig8(np.array([0.0]))[0]
    for c in (sqp, twin):
        c.prepare(1.0, x0=x)
    sqp.set_deadline(1e9)                  # the fake clock reads 0: far away
    u, info = sqp(x, 0.0)
    assert info.is_optimal() and np.array_equal(u, twin(x, 0.0)[0])
    plan = sqp._plan_u.copy()
    sqp.set_deadline(-1.0)                 # already past
    u, info = sqp(x, 0.01)
    assert info.status == "deadline" and info.fallback == "shifted_plan" and np.array_equal(u, plan[1])
    assert info.extra["time_split_s"]["derivatives"] == 0.0


def test_the_expected_time_is_numpys_median_to_the_last_bit():
    from mpc.controllers.timing import _median

    rng = np.random.default_rng(7)
    for n in range(1, 2 * RECENT_PERIODS):
        v = list(rng.random(n) * 1e-2)
        assert _median(v) == float(np.median(v)), n
    assert _median([]) == 0.0


def test_a_slowed_model_multiplies_its_typical_cpu_time_not_the_hosts_stalls():
    """The benchmark's slow machine (mpc.bench.SlowedModel) on fake clocks: a call of 1 ms of CPU time held up 2 ms
    more by the host takes 3 + 4 * 1 = 7 ms with factor 5, not 5 * 3 = 15 ms; its answer is the model's own. After
    ten calls of 1 ms, one that takes 3 ms of CPU time (the host made it slower; 5 ms of wall time) takes 5 + 4 * 1
    ms: the median of the recent calls is multiplied, not the odd one."""
    from mpc.bench import SlowedModel
    from mpc.prediction.models import AnalyticModel

    fake = {"wall": 0.0, "cpu": 0.0}

    def wall():
        fake["wall"] += 1e-6           # every read of the wall clock moves it a microsecond
        return fake["wall"]

    class Stalled(AnalyticModel):
        extra_cpu = 0.0

        def step(self, x, u):
            fake["cpu"] += 1e-3 + Stalled.extra_cpu         # 1 ms of work (or more, made slower by the host) ...
            fake["wall"] += 3e-3 + Stalled.extra_cpu        # ... that the host spread over 2 ms more
            return super().step(x, u)

    base = Stalled()
    slow = SlowedModel(base, 5.0)
    slow.wall, slow.cpu = wall, lambda: fake["cpu"]
    x, u = np.zeros((2, 12)), np.tile([0.3, 0.0, 0.0, 0.0], (2, 1))
    t0 = fake["wall"]
    out = slow.step(x, u)
    assert fake["wall"] - t0 == pytest.approx(3e-3 + 4 * 1e-3, abs=TOL["busy_wait_s"])
    assert np.array_equal(out, base.step(x, u))
    for _ in range(10):
        slow.step(x, u)
    Stalled.extra_cpu = 2e-3
    t0 = fake["wall"]
    slow.step(x, u)
    assert fake["wall"] - t0 == pytest.approx(5e-3 + 4 * 1e-3, abs=TOL["busy_wait_s"])
