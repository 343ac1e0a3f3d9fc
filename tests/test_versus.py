"""Learned against nominal: the improvement and its interval, the study's runs, a plant's rows and verdict."""

import numpy as np
import pytest

from scenarios.errors import ScenarioError
from scenarios.closed_loop.library import get_scenario, ladder_names, ladder_speeds
from scenarios.studies.stats import improvement
from scenarios.studies.versus import (VERSUS_PLANTS, VERSUS_SCENARIO, WIN_FRACTION, parse_plants, summarize_plant,
                                      versus_specs)

TOL = {
    "exact": 1e-12,            # arithmetic on constant samples
    "fraction_normal": 0.03,   # improvement of two large normal samples against the ratio of their centres
    "ci_width_rel": 0.25,      # width of its 95 % interval against the delta-method width (bootstrap of a median)
}


def test_improvement_of_constant_samples_is_exact():
    out = improvement([0.040] * 10, [0.016] * 10)
    assert abs(out["fraction"] - 0.6) < TOL["exact"]
    np.testing.assert_allclose(out["fraction_ci95"], [0.6, 0.6], atol=TOL["exact"])
    assert out["apart"] is True
    same = improvement([0.040, 0.041, 0.042], [0.040, 0.041, 0.042])
    assert abs(same["fraction"]) < TOL["exact"] and same["apart"] is False
    assert same["fraction_ci95"][0] < 0 < same["fraction_ci95"][1]


def test_improvement_interval_matches_the_delta_method():
    # Medians of n normal samples: sd ~ 1.2533 sigma / sqrt(n). The fraction 1 - mv/mr has sd by the delta method
    # sqrt((sv/mr)^2 + (mv sr / mr^2)^2).
    rng = np.random.default_rng(3)
    n, mr, mv, s = 400, 0.040, 0.020, 0.004
    out = improvement(rng.normal(mr, s, n), rng.normal(mv, s, n), n_boot=4000)
    assert abs(out["fraction"] - 0.5) < TOL["fraction_normal"]
    se = 1.2533 * s / np.sqrt(n)
    sd = np.hypot(se / mr, mv * se / mr ** 2)
    width = out["fraction_ci95"][1] - out["fraction_ci95"][0]
    assert abs(width / (2 * 1.96 * sd) - 1) < TOL["ci_width_rel"]
    assert out["apart"] is True


def test_improvement_is_seeded_and_refuses_bad_samples():
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0.03, 0.05, 10), rng.uniform(0.02, 0.03, 10)
    assert improvement(a, b) == improvement(a, b)
    assert improvement(a, b, seed=1) != improvement(a, b, seed=2)
    for bad in ([0.1], [0.1, np.nan], [0.1, 0.0]):
        with pytest.raises(ScenarioError, match="values"):
            improvement(a, bad)
    with pytest.raises(ScenarioError, match="level"):
        improvement(a, b, level=1.0)


def test_ladder_rungs_have_a_high_fidelity_variant():
    for rung in ladder_names():
        hf = get_scenario(rung + "+highfi")
        base = get_scenario(rung)
        assert hf.high_fidelity and not base.high_fidelity
        t = np.linspace(0.0, base.duration_s, 7)
        for a, b in zip(hf.reference().flat(t), base.reference().flat(t)):
            np.testing.assert_array_equal(a, b)
        assert hf.duration_s == base.duration_s
    with pytest.raises(ScenarioError, match="unknown scenario"):
        get_scenario("figure8-2.2s+wind")


def test_specs_reuse_the_ensemble_as_its_rung():
    sp = versus_specs("highfi", ["nominal", "oracle"], members=3, ladder_members=2)
    for m in ("nominal", "oracle"):
        assert sp["ladder"][m][VERSUS_SCENARIO] is sp["ensemble"][m]
        assert [s.member for s in sp["ensemble"][m]] == [0, 1, 2]
        assert all(len(v) == 2 for r, v in sp["ladder"][m].items() if r != VERSUS_SCENARIO)
        assert all(s.scenario.endswith("+highfi") for v in sp["ladder"][m].values() for s in v)
    ids = [s.run_id for m in sp["ensemble"] for s in sp["ensemble"][m]]
    ids += [s.run_id for m in sp["ladder"] for r, v in sp["ladder"][m].items() if r != VERSUS_SCENARIO
            for s in v]
    assert len(ids) == len(set(ids)) == 2 * (3 + 2 * (len(ladder_names()) - 1))
    rp = versus_specs("rotorpy", ["nominal"], members=1, ladder_members=1)
    assert {s.plant for s in rp["ensemble"]["nominal"]} == {"rotorpy"}
    with pytest.raises(ScenarioError, match="members"):
        versus_specs("highfi", ["nominal"], members=0)


def test_parse_plants():
    assert parse_plants(None) == ["highfi", "rotorpy"]          # the plants with open-loop models
    assert parse_plants("crazyflie") == ["crazyflie"] and "crazyflie" in VERSUS_PLANTS
    assert parse_plants("rotorpy, highfi,rotorpy") == ["rotorpy", "highfi"]
    for bad in ("", "sim", "highfi,wind"):
        with pytest.raises(ScenarioError, match="plants"):
            parse_plants(bad)


def _results(table: dict) -> dict:
    """Synthetic results: ``table[model][rung]`` = list of RMSE (None: crashed)."""
    out, i = {}, 0
    for m, rungs in table.items():
        for rung, vals in rungs.items():
            for v in vals:
                out[i] = {"_model": m, "_rung": None if rung == VERSUS_SCENARIO else rung, "crashed": v is None,
                          "rmse_position_m": 0.5 if v is None else v, "error": None}
                i += 1
    return out


def test_plant_rows_and_verdict_from_known_results(tmp_path):
    nominal = [0.038, 0.039, 0.040, 0.041, 0.042]
    good = [0.017, 0.018, 0.019, 0.020, 0.021]
    ok = [0.025, 0.026, 0.027, 0.028, 0.029]
    rungs = [r for r in ladder_names() if r != VERSUS_SCENARIO]
    table = {
        "nominal": {VERSUS_SCENARIO: nominal, **{r: [0.03, 0.03] for r in rungs}},
        "a.onnx": {VERSUS_SCENARIO: good, **{r: ([0.05, None] if r == "figure8-2.2s" else [0.02, 0.02])
                                             for r in rungs}},
        "b.onnx": {VERSUS_SCENARIO: ok, **{r: [0.02, 0.02] for r in rungs}},
        "c.onnx": {VERSUS_SCENARIO: [0.001, 0.002, None, 0.001, 0.001], **{r: [0.02, 0.02] for r in rungs}},
    }
    for name in ("a", "b", "c"):                 # RunSpec wants the files to exist; the facts are stubbed
        (tmp_path / f"{name}.onnx").write_bytes(b"")
    table = {(m if m == "nominal" else str(tmp_path / m)): t for m, t in table.items()}
    import scenarios.studies.versus as v

    facts = v._model_facts
    v._model_facts = lambda spec: {"architecture": "test", "extra_states": []}
    try:
        out = summarize_plant("highfi", list(table), _results(table), ladder_speeds())
    finally:
        v._model_facts = facts
    rows = out["models"]
    assert rows["nominal"]["versus_nominal"] is None
    assert abs(rows["a"]["versus_nominal"]["fraction"] - (1 - 0.019 / 0.040)) < TOL["exact"]
    assert rows["c"]["versus_nominal"] is None and rows["c"]["ensemble"]["crashes"] == 1   # a crash disqualifies
    assert rows["c"]["members_rmse_m"] == [0.001, 0.002, None, 0.001, 0.001]
    assert out["verdict"]["best"] == "a" and out["verdict"]["met"] is True and out["verdict"]["goal"] == WIN_FRACTION
    speeds = ladder_speeds()
    assert rows["a"]["ladder"]["max_speed"]["speed_mps"] == speeds["figure8-2.4s"]      # 2.2 s: a member crashed
    assert rows["b"]["ladder"]["max_speed"]["speed_mps"] == speeds["figure8-2.0s"]
    assert rows["a"]["ladder"]["rungs"]["figure8-2.2s"]["crashes"] == 1
    assert rows["nominal"]["ladder"]["rungs"][VERSUS_SCENARIO]["runs"] == 5
