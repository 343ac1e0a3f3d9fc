"""Ensembles: Wilson and bootstrap intervals, ensemble members, an ensemble flown and summarized."""

import numpy as np
import pytest

from scenarios.errors import ScenarioError
from scenarios.closed_loop.library import ENSEMBLE_X0_SIGMA, get_scenario
from scenarios.closed_loop.runner import RunSpec
from scenarios.studies.stats import bootstrap_ci, summarize, wilson_interval

TOL = {
    "wilson_abs": 5e-4,        # against published values given to 4 digits
    "sigma_rel": 0.3,          # sample std of 60 members' start offsets against ENSEMBLE_X0_SIGMA
    "bootstrap_width_rel": 0.15,  # bootstrap CI of a mean against 2 * 1.96 sigma / sqrt(n), n = 400
}


@pytest.mark.parametrize("k,n,expected", [
    (0, 10, (0.0, 0.2775)), (5, 10, (0.2366, 0.7634)), (10, 10, (0.7225, 1.0)), (1, 20, (0.0089, 0.2361)),
])
def test_wilson_interval_matches_published_values(k, n, expected):
    # Values of the Wilson score interval at z = 1.96 (for example Newcombe 1998, Table I, and R's prop.test
    # without continuity correction).
    np.testing.assert_allclose(wilson_interval(k, n), expected, atol=TOL["wilson_abs"])


def test_wilson_interval_is_symmetric_in_events_and_non_events():
    for n in (1, 7, 30):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            lo2, hi2 = wilson_interval(n - k, n)
            assert lo <= k / n <= hi
            assert abs(lo - (1 - hi2)) < 1e-12 and abs(hi - (1 - lo2)) < 1e-12


@pytest.mark.parametrize("k,n", [(3, 2), (0, 0), (-1, 5), (1.5, 4)])
def test_bad_counts_are_clear_errors(k, n):
    with pytest.raises(ScenarioError):
        wilson_interval(k, n)


def test_bootstrap_ci_is_seeded_and_has_the_width_of_theory():
    rng = np.random.default_rng(1)
    v = rng.normal(3.0, 2.0, 400)
    ci = bootstrap_ci(v, np.mean, n_boot=4000)
    assert ci == bootstrap_ci(v, np.mean, n_boot=4000)
    assert ci[0] < v.mean() < ci[1]
    width = 2 * 1.959964 * v.std(ddof=1) / np.sqrt(v.size)
    assert abs((ci[1] - ci[0]) - width) / width <= TOL["bootstrap_width_rel"]
    with pytest.raises(ScenarioError, match="at least 2 finite"):
        bootstrap_ci([1.0, np.nan])


def test_an_ensemble_member_is_seeded_and_perturbs_the_start_by_the_stated_spread():
    base = get_scenario("figure8-fast")
    a, b = base.member(3), base.member(3)
    assert a == b and a.seed == 3 and a.reference().describe() == base.reference().describe()
    offsets = np.array([np.subtract(base.member(k).x0, base.x0) for k in range(60)])
    np.testing.assert_allclose(offsets.std(axis=0, ddof=1), ENSEMBLE_X0_SIGMA, rtol=TOL["sigma_rel"])
    assert RunSpec("hover", "lqr", member=4).run_id == "hover__lqr__oracle__m4"
    with pytest.raises(ScenarioError, match="member or seed"):
        RunSpec("hover", "lqr", seed=1, member=4)
    with pytest.raises(ScenarioError, match="member must be"):
        RunSpec("hover", "lqr", member=-1)


def test_summarize_counts_crashes_and_takes_the_metric_over_the_runs_that_flew():
    runs = [{"crashed": False, "rmse_position_m": v} for v in (0.1, 0.2, 0.3)] + \
           [{"crashed": True, "rmse_position_m": 5.0}]
    s = summarize(runs)
    assert (s["runs"], s["crashes"], s["flown"], s["median"]) == (4, 1, 3, 0.2)
    np.testing.assert_allclose(s["crash_probability_ci95"], wilson_interval(1, 4))
    assert 0.1 <= s["median_ci95"][0] <= s["median_ci95"][1] <= 0.3


def test_an_ensemble_flies_each_member_from_its_own_start(tmp_path):
    from scenarios.studies.ensemble import fly_ensemble

    out = fly_ensemble("hover", "lqr", "oracle", members=3, out_dir=tmp_path, progress=False)
    rm = [r["rmse_position_m"] for r in out["runs"]]
    assert len(set(rm)) == 3                           # three different starts, three different flights
    assert out["summary"]["crashes"] == 0 and out["summary"]["crash_probability_ci95"][1] == pytest.approx(
        wilson_interval(0, 3)[1])
    again = fly_ensemble("hover", "lqr", "oracle", members=3, out_dir=tmp_path, progress=False)
    assert again["runs"] == out["runs"]                # reused from the folder, identical
