"""CI check of closed-loop error bounds (``scenarios/studies/bounds.toml``) and its negative controls.

The flights (about 4 minutes of two processes) are among CI's slower checks (``pytest -m slow``); the checks of
the file and of the comparison run by default.

Flies every case of the bounds file with the oracle beside it, and the true
equations with wrong parameters on the oracle's cases until each fails one
(two processes, once per module). Every shipped model must pass all of its
cases; every wrong-parameter model must fail at least one. Either failure prints the
whole comparison table.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from scenarios.studies.bounds import (BOUNDS_FILE, FLOOR, MARGIN, MODEL_CASES, MODEL_FLOOR, ORACLE_CASES, Bound, check,
                                      format_table, generate, load_bounds, specs_to_fly)
from scenarios.studies.campaign import shipped_models
from scenarios.errors import BoundsError
from scenarios.closed_loop.runner import RunSpec
from scenarios.sweeps.sweep import sweep

REPO = Path(__file__).resolve().parents[1]

#: The true equations with one wrong parameter: each inertia 30 % too high and too low, 10 % too much mass,
#: a 30 % too large rotor torque coefficient.
NEGATIVE_CONTROLS = (
    "analytic:Jxx*1.3", "analytic:Jyy*1.3", "analytic:Jzz*1.3",
    "analytic:Jxx*0.7", "analytic:Jyy*0.7", "analytic:Jzz*0.7",
    "analytic:m*1.1", "analytic:kq*1.3",
)

TOL = {
    # What the true model must achieve on a feasible reference (its bounds may be tighter, not looser).
    "oracle_targets": {("hover", "ltv", "settled_error_m"): 1e-3, ("figure8-slow", "ltv", "rmse_position_m"): 5e-4,
                       ("figure8-fast", "ltv", "rmse_position_m"): 1e-3, ("figure8-2.0s", "ltv", "rmse_position_m"): 5e-3},
    "rel": 1e-12,           # generated tolerances vs their formula
}


def _shipped():
    return [Path(m).stem for m in shipped_models(REPO / "models")]


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    """Results of every bound's run, the oracle beside each, and the negative controls on the oracle's cases.

    A wrong-parameter model has to fail one bound, so each flies the oracle's cases in the file's order only until
    one fails (a model that passes them all flies every case)."""
    _, bounds = load_bounds()
    oracle = [b for b in bounds if b.model == "oracle"]
    folder = tmp_path_factory.mktemp("bounds")
    results = sweep(specs_to_fly(bounds, REPO / "models"), folder, jobs=2, progress=False)
    pending = list(NEGATIVE_CONTROLS)
    for b in oracle:
        if not pending:
            break
        results += sweep([RunSpec(b.scenario, b.controller, neg) for neg in pending], folder, jobs=2, progress=False)
        pending = [neg for neg in pending if all(r["ok"] for r in _negative_rows(neg, [b], results))]
    return results


def _negative_rows(neg, oracle_bounds, results):
    """The check's rows of the wrong model ``neg`` against the oracle's own (absolute) bounds: it claims to be the
    true equations. Only the cases it flew: a case it did not fly is no failure."""
    rows = check([dataclasses.replace(b, model=neg, relative=False) for b in oracle_bounds], results)
    return [r for r in rows if r["why"] != "not run"]


def test_bounds_file_is_well_formed_and_covers_the_required_cases():
    settings, bounds = load_bounds()
    keys = {(b.model, b.scenario, b.controller, b.metric) for b in bounds}
    assert {("oracle", *c) for c in ORACLE_CASES} <= keys
    for m in _shipped():
        assert {(m, *c) for c in MODEL_CASES} <= keys, m
    assert settings["margin"] == MARGIN
    for b in bounds:
        assert b.measured is not None and b.oracle_measured is not None
        if b.model == "oracle":
            assert not b.relative and not b.known_failure
            assert b.tolerance_m == pytest.approx(b.measured * (1 + MARGIN) + FLOOR[b.metric], rel=1e-5)
            target = TOL["oracle_targets"].get((b.scenario, b.controller, b.metric))
            if target is not None:
                assert b.tolerance_m <= target, b
        elif not b.known_failure:
            assert b.relative
            excess = max(b.measured - b.oracle_measured, 0.0)
            assert b.tolerance_m == pytest.approx(excess * (1 + MARGIN) + MODEL_FLOOR[b.metric], rel=1e-5)


@pytest.mark.slow
def test_every_shipped_model_and_the_oracle_stay_within_their_bounds(flown):
    _, bounds = load_bounds()
    rows = check(bounds, flown)
    table = format_table(rows)
    print("\n" + table)
    if not all(r["ok"] is not False for r in rows):
        pytest.fail("closed-loop bounds exceeded:\n" + table, pytrace=False)


@pytest.mark.slow
def test_each_wrong_parameter_model_fails_at_least_one_bound(flown):
    _, bounds = load_bounds()
    oracle = [b for b in bounds if b.model == "oracle"]
    lines, missed = [], []
    for neg in NEGATIVE_CONTROLS:
        rows = _negative_rows(neg, oracle, flown)     # the cases up to its first failure
        lines.append(format_table(rows))
        if all(r["ok"] for r in rows):
            missed.append(neg)
    table = "\n\n".join(lines)
    print("\n" + table)
    if missed:
        pytest.fail(f"wrong-parameter models that pass every bound: {missed}\n{table}", pytrace=False)


def _result(scenario, controller, model, **metrics):
    base = {"rmse_position_m": None, "settled_error_m": None, "rmse_yaw_rad": None, "crashed": False,
            "crash_time_s": None, "crash_reason": None, "error": None}
    return {"scenario": scenario, "controller": controller, "model": model, **base, **metrics}


def _synthetic_results(crash_model="m1"):
    out = []
    for model, scale in (("oracle", 1.0), ("m1", 10.0), ("m2", 20.0)):
        for sc, ctrl, metric in (*ORACLE_CASES, *MODEL_CASES):
            r = _result(sc, ctrl, model, **{metric: 1e-4 * scale})
            if model == crash_model and (sc, ctrl) == ("figure8-fast", "ltv"):
                r.update(crashed=True, crash_time_s=2.5, crash_reason="below ground")
            out.append(r)
    return out


def test_generate_sets_tolerances_from_a_measured_run(tmp_path):
    f = tmp_path / "b.toml"
    f.write_text(generate(_synthetic_results(), ["m1", "m2"], "a synthetic run"))
    settings, bounds = load_bounds(f)
    by = {(b.model, b.scenario, b.controller, b.metric): b for b in bounds}
    o = by[("oracle", "figure8-fast", "ltv", "rmse_position_m")]
    assert not o.relative and o.tolerance_m == pytest.approx(1e-4 * (1 + MARGIN) + FLOOR["rmse_position_m"],
                                                             rel=TOL["rel"])
    m2 = by[("m2", "figure8-slow", "ltv", "rmse_position_m")]
    assert m2.relative and m2.tolerance_m == pytest.approx((2e-3 - 1e-4) * (1 + MARGIN) + MODEL_FLOOR["rmse_position_m"],
                                                           rel=TOL["rel"])
    crashed = by[("m1", "figure8-fast", "ltv", "rmse_position_m")]
    assert crashed.known_failure
    assert sum(b.known_failure for b in bounds) == 1
    # Checked against the same results, everything passes and the crash is reported outside the pass/fail set.
    rows = check(bounds, _synthetic_results())
    assert [r["ok"] for r in rows].count(None) == 1 and all(r["ok"] is not False for r in rows)
    assert "known failure" in format_table(rows)
    # A run missing from the results is a clear error.
    with pytest.raises(BoundsError, match="no run of m3"):
        generate(_synthetic_results(), ["m3"])
    # The same cases flown on another plant or vehicle (the main job's RotorPy runs) do not set these bounds.
    elsewhere = [{**r, "plant": "rotorpy", "rmse_position_m": 9.0, "crashed": False}
                 for r in _synthetic_results()]
    elsewhere += [{**r, "vehicle": "hummingbird", "crashed": True} for r in _synthetic_results()]
    assert generate(_synthetic_results() + elsewhere, ["m1", "m2"], "a synthetic run") == f.read_text()


def test_check_reports_each_kind_of_violation():
    bounds = [Bound("hover", "ltv", "oracle", "settled_error_m", 1e-3),
              Bound("hover", "ltv", "a", "settled_error_m", 1e-3),
              Bound("hover", "ltv", "b", "settled_error_m", 1e-3),
              Bound("hover", "ltv", "c", "settled_error_m", 1e-3, known_failure=True),
              Bound("hover", "ltv", "d", "settled_error_m", 1e-3)]
    results = [_result("hover", "ltv", "oracle", settled_error_m=5e-4),
               _result("hover", "ltv", "a", settled_error_m=1.4e-3),     # within oracle + 1 mm
               _result("hover", "ltv", "b", settled_error_m=1.6e-3),     # above it
               _result("hover", "ltv", "c", settled_error_m=None, crashed=True, crash_time_s=1.0,
                       crash_reason="tilt > 80 deg")]
    rows = check(bounds, results)
    assert [r["ok"] for r in rows] == [True, True, False, None, False]
    assert rows[1]["limit"] == pytest.approx(1.5e-3, rel=TOL["rel"])
    assert "above bound" in rows[2]["why"]
    assert "crashed" in rows[3]["why"]
    assert rows[4]["why"] == "not run"
    table = format_table(rows)
    assert table.count("FAIL") == 2 and "0.00160" in table and "known failure" in table


@pytest.mark.parametrize("text, match", [
    ("", "no \\[\\[case\\]\\]"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'ltv'\n", "missing"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'pid'\nmodel = 'oracle'\nmetric = 'rmse_position_m'\n"
     "tolerance_m = 0.1\n", "controller"),
    ("[[case]]\nscenario = 'hovr'\ncontroller = 'ltv'\nmodel = 'oracle'\nmetric = 'rmse_position_m'\n"
     "tolerance_m = 0.1\n", "unknown scenario"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'ltv'\nmodel = 'oracle'\nmetric = 'rmse_position_m'\n"
     "tolerance_m = -1\n", "tolerance_m"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'ltv'\nmodel = 'oracle'\nmetric = 'speed'\ntolerance_m = 1\n",
     "metric"),
    ("[[case]\n", "not valid TOML"),
])
def test_malformed_bounds_files_are_rejected(tmp_path, text, match):
    f = tmp_path / "b.toml"
    f.write_text(text)
    with pytest.raises(BoundsError, match=match):
        load_bounds(f)


def test_the_shipped_bounds_file_is_the_default():
    assert BOUNDS_FILE == REPO / "scenarios" / "studies" / "bounds.toml"
