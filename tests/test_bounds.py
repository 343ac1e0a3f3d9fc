"""CI check of closed-loop error bounds (``scenarios/bounds.toml``, issue 5).

Flies every case of the bounds file (two processes) and fails with the whole
comparison table when a case exceeds its RMSE bound or crashes unexpectedly.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from scenarios.bounds import BOUNDS_FILE, Bound, check, format_table, load_bounds
from scenarios.errors import BoundsError
from scenarios.runner import sweep

REPO = Path(__file__).resolve().parents[1]

TOL = {
    "min_margin": 1.05,     # every bound is at least 5 % above the measurement that set it
}


def test_bounds_file_is_well_formed_and_covers_the_required_cases():
    settings, bounds = load_bounds()
    keys = {(b.scenario, b.controller, b.model) for b in bounds}
    required = {("hover", "nmpc", "oracle"), ("figure8-slow", "nmpc", "oracle"), ("hover", "ltv", "oracle"),
                ("figure8-slow", "ltv", "oracle"), ("hover", "ltv", "proposed"), ("figure8-slow", "ltv", "proposed")}
    assert required <= keys
    assert settings["margin"] >= TOL["min_margin"] - 1.0
    for b in bounds:
        assert b.measured_rmse_m is not None
        assert b.rmse_max_m >= TOL["min_margin"] * b.measured_rmse_m, b


def test_closed_loop_errors_stay_within_their_bounds(tmp_path):
    _, bounds = load_bounds()
    results = sweep([b.spec(REPO / "models") for b in bounds], tmp_path, jobs=2, progress=False)
    rows = check(bounds, results)
    table = format_table(rows)
    print("\n" + table)
    if not all(r["ok"] for r in rows):
        pytest.fail("closed-loop bounds exceeded:\n" + table, pytrace=False)


def test_check_reports_each_kind_of_violation():
    bounds = [Bound("hover", "ltv", "a", 0.1), Bound("hover", "ltv", "b", 0.1), Bound("hover", "ltv", "c", 0.1, True),
              Bound("hover", "ltv", "d", 0.1)]
    results = [
        {"scenario": "hover", "controller": "ltv", "model": "a", "rmse_position_m": 0.09, "crashed": False},
        {"scenario": "hover", "controller": "ltv", "model": "b", "rmse_position_m": 0.11, "crashed": False},
        {"scenario": "hover", "controller": "ltv", "model": "c", "rmse_position_m": 0.05, "crashed": False},
    ]
    rows = check(bounds, results)
    assert [r["ok"] for r in rows] == [True, False, False, False]
    assert "RMSE above bound" in rows[1]["why"]
    assert "crash expected" in rows[2]["why"]
    assert rows[3]["why"] == "not run"
    table = format_table(rows)
    assert table.count("FAIL") == 3 and "0.1100" in table


@pytest.mark.parametrize("text, match", [
    ("", "no \\[\\[case\\]\\]"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'ltv'\n", "missing"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'pid'\nmodel = 'oracle'\nrmse_max_m = 0.1\n", "controller"),
    ("[[case]]\nscenario = 'hovr'\ncontroller = 'ltv'\nmodel = 'oracle'\nrmse_max_m = 0.1\n", "unknown scenario"),
    ("[[case]]\nscenario = 'hover'\ncontroller = 'ltv'\nmodel = 'oracle'\nrmse_max_m = -1\n", "rmse_max_m"),
    ("[[case]\n", "not valid TOML"),
])
def test_malformed_bounds_files_are_rejected(tmp_path, text, match):
    f = tmp_path / "b.toml"
    f.write_text(text)
    with pytest.raises(BoundsError, match=match):
        load_bounds(f)


def test_the_shipped_bounds_file_is_the_default():
    assert BOUNDS_FILE == REPO / "scenarios" / "bounds.toml"
