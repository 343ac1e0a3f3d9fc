"""Runs flown ahead at idle priority: saved as a sweep saves them, found flown by the sweep, stopped at once."""

import os
import sys
import time
from pathlib import Path

import pytest

import scenarios.runner as runner
from scenarios import learn
from scenarios.ahead import STOP_WAIT_S, FlyAhead, fly_ahead
from scenarios.learn import LearnSettings
from scenarios.metrics import TIMING_FIELDS
from scenarios.runner import RunSpec
from scenarios.sweep import sweep
from scenarios.versus import VERSUS_SCENARIO, versus_specs

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "models" / "baseline.onnx")
SPECS = [RunSpec("hover", "lqr", "oracle"), RunSpec("hover", "sqp", BASELINE)]
#: Seconds allowed for the ahead process to fly SPECS (each a few seconds), and to end once stopped.
FLY_WAIT_S = 120.0
STOPPED_WITHIN_S = STOP_WAIT_S + 1.0


def reproducible(result):
    return {k: v for k, v in result.items() if k not in TIMING_FIELDS}


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    return sweep(SPECS, tmp_path_factory.mktemp("sweep"), jobs=1, progress=False)


def _no_flying(monkeypatch):
    def refuse(*a, **k):
        raise RuntimeError("flown again")

    monkeypatch.setattr(runner, "fly", refuse)


def test_a_run_flown_ahead_is_the_sweeps_own_and_the_sweep_does_not_fly_it_again(swept, tmp_path, monkeypatch):
    assert fly_ahead(SPECS, tmp_path) == len(SPECS)
    assert fly_ahead(SPECS, tmp_path) == 0                      # saved: not flown twice
    _no_flying(monkeypatch)                                     # a run flown again would come back as an error
    got = sweep(SPECS, tmp_path, jobs=1, progress=False)
    assert [reproducible(r) for r in got] == [reproducible(r) for r in swept]
    assert all(r.get("error") is None for r in got)


def test_the_ahead_process_flies_at_idle_priority_and_its_runs_are_found(swept, tmp_path, monkeypatch):
    ahead = FlyAhead(SPECS, tmp_path).start()
    try:
        if sys.platform.startswith("linux"):
            t0 = time.monotonic()
            while os.sched_getscheduler(ahead._proc.pid) != os.SCHED_IDLE and time.monotonic() - t0 < FLY_WAIT_S:
                time.sleep(0.05)
            assert os.sched_getscheduler(ahead._proc.pid) == os.SCHED_IDLE
        t0 = time.monotonic()
        while ahead.running and time.monotonic() - t0 < FLY_WAIT_S:
            time.sleep(0.2)
        assert not ahead.running                                  # done with every run
    finally:
        ahead.stop()
    _no_flying(monkeypatch)
    got = sweep(SPECS, tmp_path, jobs=1, progress=False)
    assert [reproducible(r) for r in got] == [reproducible(r) for r in swept]


def test_stop_ends_the_process_at_once_and_leaves_no_torn_file(tmp_path):
    long = [RunSpec("figure8-slow", "sqp", BASELINE, member=k) for k in range(3)]
    ahead = FlyAhead(long, tmp_path).start()
    time.sleep(3.0)                                              # mid-import or mid-flight
    t0 = time.monotonic()
    ahead.stop()
    assert time.monotonic() - t0 < STOPPED_WITHIN_S
    assert not ahead.running
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    ahead.stop()                                                 # stopping twice is harmless


def test_no_specs_start_no_process(tmp_path):
    with FlyAhead([], tmp_path) as ahead:
        assert ahead._proc is None and not ahead.running


@pytest.mark.parametrize("plant", ["highfi", "rotorpy"])
def test_the_study_flies_ahead_exactly_the_evaluation_runs_that_depend_on_nothing_it_computes(plant):
    s = LearnSettings(plant=plant)
    shipped = ROOT / "models" / "learn" / plant
    final, upper = str(shipped / f"learn_{plant}_it3.onnx"), str(shipped / f"learn_{plant}_upper.onnx")
    best = str(ROOT / "models" / s.spec.best_open_loop)
    evaluation, tags = learn._evaluation_runs(s, ["nominal", best, final, upper], ["nominal", final])
    curve_first = versus_specs(s.spec.versus, ["nominal"], s.members, ladder_members=1)["ensemble"]["nominal"]
    curve_last = versus_specs(s.spec.versus, [final], s.members, ladder_members=1)["ensemble"][final]
    early = {r.run_id for r in learn._independent_runs(s, ROOT / "models")}
    late = {r.run_id for r in learn._final_ladder_runs(s, final)}
    by_model = {m: {r.run_id for r, (mm, _) in zip(evaluation, tags) if mm == m} for m in ("nominal", best, final)}
    assert early == (by_model["nominal"] | by_model[best]) - {r.run_id for r in curve_first}
    assert late == by_model[final] - {r.run_id for r in curve_last}
    assert not early & late
    n_rungs = len({rung for _, rung in tags if rung is not None})
    assert len(early) == s.members + n_rungs * s.ladder_members
    assert all(VERSUS_SCENARIO not in r.scenario or r.model == best
               for r in learn._independent_runs(s, ROOT / "models"))
