"""Real-time timing: when a computed input takes effect, overruns, what a run records; ideal timing unchanged."""

import time
from pathlib import Path

import numpy as np
import pytest

from mpc.controllers.controller import ControlInfo
from scenarios.errors import ScenarioError
from scenarios.closed_loop.library import get_scenario
from scenarios.closed_loop.loop import DEADLINE_MARGIN_S, IdealClock, RealtimeClock, StateSensor, fly_loop
from scenarios.closed_loop.runner import RunSpec, fly
from scenarios.sweeps.sweep import sweep_batches
from sim import QuadParams, Simulator
from sim.plants.plant import SimPlant
from sim.params import DT

ROOT = Path(__file__).resolve().parents[1]
P = QuadParams()
HOVER_U = np.array([P.m * P.g, 0.0, 0.0, 0.0])
TOL = {"state_abs": 1e-12}   # the clock's pieces against the same pieces flown by hand (rounding only)


def hover_state():
    x = np.zeros(12)
    x[2] = -1.0
    x[9] = 0.2            # moving, so that when the input changes shows in the state
    return x


def piece(x, u, ms, t=0.0):
    """``ms`` substeps of 1 ms with ``u`` held (the simulator's own equations)."""
    return Simulator(P, dt=ms * DT / 10, substeps=ms).step(x, u, t=t)


def plant_at(x):
    """The reference simulator as a plant, in state ``x``."""
    plant = SimPlant()
    plant.reset(x)
    return plant


def fly_period(clock, k, x):
    """Period ``k`` of ``clock`` from state ``x``: (state at its end, input in effect at its end)."""
    plant = plant_at(x)
    u = clock.fly_period(plant, k)
    return plant.x, u


def test_an_input_takes_effect_after_its_latency_rounded_up_to_a_substep():
    u = HOVER_U + np.array([0.05, 1e-4, 0.0, 0.0])
    clock = RealtimeClock(HOVER_U, get_scenario("hover").delay_steps)
    assert clock.idle(0)
    clock.command(0, u, 3.2e-3)                 # returns after 3.2 ms: takes effect from 4 ms
    x1, u_end = fly_period(clock, 0, hover_state())
    expected = piece(piece(hover_state(), HOVER_U, 4), u, 6)
    np.testing.assert_allclose(x1, expected, rtol=0, atol=TOL["state_abs"])
    assert np.array_equal(u_end, u) and clock.idle(1)
    # A different rounding is a different state: the test can see a 1 ms error.
    assert np.max(np.abs(piece(piece(hover_state(), HOVER_U, 3), u, 7) - expected)) > 1e3 * TOL["state_abs"]


def test_an_overrun_keeps_the_previous_input_and_skips_periods_until_it_returns():
    u0 = HOVER_U + np.array([0.02, 0.0, 0.0, 0.0])
    u1 = HOVER_U + np.array([-0.03, 0.0, 2e-4, 0.0])
    clock = RealtimeClock(HOVER_U, get_scenario("hover").delay_steps)
    plant = plant_at(hover_state())
    clock.command(0, u0, 0.4e-3)                # 0.4 ms -> from 1 ms
    clock.fly_period(plant, 0)
    x = plant.x
    assert clock.idle(1)
    clock.command(1, u1, 23.5e-3)               # an overrun: returns at 10 + 24 = 34 ms
    assert not clock.idle(2) and not clock.idle(3) and clock.idle(4)
    ua = clock.fly_period(plant, 1)
    ub = clock.fly_period(plant, 2)
    x_b = plant.x
    uc = clock.fly_period(plant, 3)
    x_c = plant.x
    assert np.array_equal(ua, u0) and np.array_equal(ub, u0) and np.array_equal(uc, u1)
    np.testing.assert_allclose(x_b, piece(piece(x, u0, 10), u0, 10), rtol=0, atol=TOL["state_abs"])
    np.testing.assert_allclose(x_c, piece(piece(x_b, u0, 4), u1, 6), rtol=0, atol=TOL["state_abs"])


def test_delay_periods_add_to_the_latency():
    u = HOVER_U + np.array([0.05, 0.0, 0.0, 0.0])
    clock = RealtimeClock(HOVER_U, get_scenario("hover+delay").delay_steps)   # 3 periods of delay
    clock.command(0, u, 1.5e-3)                 # takes effect at 30 + 2 = 32 ms
    plant = plant_at(hover_state())
    for k in range(3):
        uk = clock.fly_period(plant, k)
        assert np.array_equal(uk, HOVER_U)
    x = plant.x
    u3 = clock.fly_period(plant, 3)
    x3 = plant.x
    assert np.array_equal(u3, u)
    np.testing.assert_allclose(x3, piece(piece(x, HOVER_U, 2), u, 8), rtol=0, atol=TOL["state_abs"])


def test_a_realtime_run_records_its_timing_latencies_and_skipped_periods():
    r, tr = fly(RunSpec("yaw-turn", "nmpc", "oracle", timing="realtime"))
    assert r["timing"] == "realtime" and r["run_id"].endswith("__realtime")
    called = tr["called"]
    assert called[0] and np.all(np.isfinite(tr["latency_s"][called])) and np.all(np.isnan(tr["latency_s"][~called]))
    assert r["skipped_periods"] == int(np.sum(~called))
    # Each call is followed by the first period that starts after it returned (latency rounded up to 1 ms).
    k_called = np.flatnonzero(called)
    lat_ms = np.maximum(1, np.ceil(tr["latency_s"][called] * 1e3 - 1e-9))
    np.testing.assert_array_equal(np.diff(k_called), np.ceil(lat_ms[:-1] / 10.0).astype(int))
    assert r["skipped_periods"] > 0      # an IPOPT solve here often takes longer than the 10 ms period


def test_ideal_timing_is_the_default_and_is_recorded():
    spec = RunSpec("hover", "lqr", "oracle")
    assert spec.timing == "ideal" and not spec.run_id.endswith("realtime")
    r, tr = fly(spec)
    assert r["timing"] == "ideal" and "skipped_periods" not in r and bool(np.all(tr["called"]))


def test_an_unknown_timing_is_a_clear_error():
    with pytest.raises(ScenarioError, match="timing must be one of ideal, realtime"):
        RunSpec("hover", "ltv", "oracle", timing="fast")


def test_realtime_runs_are_flown_alone_after_the_others():
    ideal = [RunSpec("hover", "ltv", "oracle"), RunSpec("figure8-fast", "nmpc", "oracle")]
    rt = [RunSpec("figure8-fast", "sqp", "oracle", timing="realtime"), RunSpec("hover", "ltv", "oracle", timing="realtime")]
    batches = sweep_batches([rt[0], ideal[0], rt[1], ideal[1]], jobs=2)
    assert batches == [(2, [ideal[1], ideal[0]]), (1, rt)]     # the NMPC (longest) first
    assert sweep_batches(ideal, 2) == [(2, [ideal[1], ideal[0]])]


def test_a_realtime_sqp_run_plans_before_take_off_and_leaves_the_garbage_collector_on():
    import gc

    r, tr = fly(RunSpec("hover", "sqp", "oracle", timing="realtime"))
    assert gc.isenabled()
    pre = r["preflight"]
    assert pre["status"] == "optimal" and pre["iterations"] >= 1 and r["preflight_ms"] > 0
    assert r["crashed"] is False and bool(tr["called"][0])


def test_two_ideal_sqp_runs_give_identical_results_but_for_their_timing_fields():
    from scenarios.closed_loop.metrics import TIMING_FIELDS, TRACE_TIMING_FIELDS

    spec = RunSpec("hover", "sqp", "oracle")
    (r1, t1), (r2, t2) = fly(spec), fly(spec)
    assert r1["preflight"] is not None     # the SQP's pre-flight plan is part of what must reproduce
    assert {k: v for k, v in r1.items() if k not in TIMING_FIELDS} == {k: v for k, v in r2.items()
                                                                          if k not in TIMING_FIELDS}
    for k in set(t1) - set(TRACE_TIMING_FIELDS):
        np.testing.assert_array_equal(t1[k], t2[k])


class DeadlineRecorder:
    """A controller that holds hover and records the deadline it is given and when each call starts."""

    def __init__(self):
        self.deadlines, self.starts = [], []

    def set_deadline(self, at):
        self.deadlines.append(at)

    def applied(self, u):
        pass

    def prepare_next(self, until=None):
        pass

    def __call__(self, x, t):
        self.starts.append(time.perf_counter())
        return HOVER_U.copy(), ControlInfo(solve_time_s=0.0, status="optimal")


def test_in_real_time_each_call_is_told_its_deadline_and_in_ideal_timing_none():
    x_ref = np.tile(hover_state(), (11, 1))
    rec = DeadlineRecorder()
    fly_loop(plant_at(hover_state()), StateSensor(None, None), rec, RealtimeClock(HOVER_U), x_ref, 10)
    assert len(rec.deadlines) == len(rec.starts) == 10
    ahead = np.array(rec.deadlines) - np.array(rec.starts)
    # Set just before the call: the period less the margin, less the (tiny) time between the two clock reads.
    assert np.all(ahead <= DT - DEADLINE_MARGIN_S) and np.all(ahead > DT - DEADLINE_MARGIN_S - 1e-3)
    ideal = DeadlineRecorder()
    fly_loop(plant_at(hover_state()), StateSensor(None, None), ideal, IdealClock(HOVER_U), x_ref, 10)
    assert ideal.deadlines == [] and len(ideal.starts) == 10
