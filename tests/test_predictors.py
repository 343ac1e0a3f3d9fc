"""Predictors of closed-loop failure: ROC AUC, bootstrap intervals, the Jacobian-error candidate, a scored folder."""

import json
from pathlib import Path

import numpy as np
import pytest

from mpc.prediction.models import AnalyticModel, OnnxModel, load_model
from scenarios.errors import ScenarioError
from scenarios.studies.predictors import (bootstrap_score_ci, chordal_distance, hover_chordal_distance, jacobian_error,
                                          predictors_of, roc_auc, score_candidates)

ROOT = Path(__file__).resolve().parents[1]
TOL = {"exact": 1e-12,   # the oracle's Jacobian error against itself
       "chordal": 1e-12}  # the chordal distance against its closed form


@pytest.mark.parametrize("scores,labels,expected", [
    ([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1], 0.75),          # the textbook example
    ([1, 2, 3, 4], [0, 0, 1, 1], 1.0), ([1, 2, 3, 4], [1, 1, 0, 0], 0.0), ([5, 5, 5, 5], [0, 1, 0, 1], 0.5),
])
def test_roc_auc_known_values(scores, labels, expected):
    assert roc_auc(scores, labels) == expected


def test_roc_auc_is_undefined_with_one_class_and_checks_shapes():
    assert roc_auc([1, 2, 3], [0, 0, 0]) is None
    with pytest.raises(ScenarioError, match="1-D of one length"):
        roc_auc([1, 2, 3], [0, 1])


def test_bootstrap_score_ci_is_seeded_and_brackets_a_clear_score():
    rng = np.random.default_rng(2)
    y = np.arange(40) % 2 == 0
    x = y + 0.3 * rng.standard_normal(40)
    ci = bootstrap_score_ci(roc_auc, x, y)
    assert ci == bootstrap_score_ci(roc_auc, x, y)
    assert ci[0] <= roc_auc(x, y) <= ci[1] and ci[0] > 0.8
    assert bootstrap_score_ci(roc_auc, x, np.zeros(40, dtype=bool)) is None   # never defined


def test_jacobian_error_is_zero_for_the_truth_and_grows_with_a_wrong_parameter():
    assert jacobian_error(AnalyticModel(), "figure8-fast") <= TOL["exact"]
    e13 = jacobian_error(load_model("analytic:Jxx*1.3"), "figure8-fast")
    e16 = jacobian_error(load_model("analytic:Jxx*1.6"), "figure8-fast")
    assert 0 < e13 < e16
    assert 0 < jacobian_error(OnnxModel(ROOT / "models" / "baseline.onnx"), "figure8-fast") < 1


def test_score_candidates_ranks_a_perfect_and_a_useless_candidate():
    crashed = {"a": True, "b": True, "c": False, "d": False, "e": False}
    rmse = {"a": 0.9, "b": 0.5, "c": 0.3, "d": 0.2, "e": 0.1}
    rows = {r["candidate"]: r for r in score_candidates(
        {"perfect": {"a": 5.0, "b": 4.0, "c": 3.0, "d": 2.0, "e": 1.0},
         "reversed": {"a": 1.0, "b": 2.0, "c": 3.0, "d": 4.0, "e": 5.0}}, crashed, rmse)}
    assert rows["perfect"]["auc"] == 1.0 and rows["perfect"]["spearman"] == pytest.approx(1.0)
    assert rows["reversed"]["auc"] == 0.0 and rows["reversed"]["spearman"] == pytest.approx(-1.0)
    assert rows["perfect"]["crashed"] == 2 and rows["perfect"]["models"] == 5


def test_predictors_of_a_results_folder(tmp_path):
    names = ["baseline", "fourier", "modular", "proposed"]
    mae = {"baseline": 0.01, "fourier": 0.02, "modular": 0.03, "proposed": 0.04}
    evaluation = {"models": [{"name": n, "one_step": {"position": mae[n] / 10},
                              "rollout_100": {"position": mae[n], "n_rollouts": 10, "n_diverged": 0}} for n in names]}
    runs = [{"scenario": "figure8-fast", "controller": "sqp", "model": n, "crashed": n == "proposed",
             "rmse_position_m": 10 * mae[n], "timing": "ideal"} for n in names]
    (tmp_path / "evaluation.json").write_text(json.dumps(evaluation))
    (tmp_path / "results.json").write_text(json.dumps({"runs": runs}))
    out = predictors_of(tmp_path, "sqp", "figure8-fast", ROOT / "models")
    rows = {r["candidate"]: r for r in out["scores"]}
    assert set(rows) == {"one_step_position_mae_m", "rollout_100_position_mae_m", "rollout_100_diverged_fraction",
                         "jacobian_error"}
    assert rows["rollout_100_position_mae_m"]["auc"] == 1.0            # the largest MAE is the one crash
    assert rows["rollout_100_position_mae_m"]["spearman"] == pytest.approx(1.0)   # over the 3 that flew
    assert rows["rollout_100_diverged_fraction"]["auc"] == 0.5          # all zero: a tie everywhere
    assert all(v > 0 for v in out["candidates"]["jacobian_error"].values())
    with pytest.raises(ScenarioError, match="no ideal-timing ltv run"):
        predictors_of(tmp_path, "ltv", "figure8-fast", ROOT / "models")


@pytest.mark.parametrize("b1,b2", [(1.0, 2.0), (0.5, -0.5), (3.0, 3.0)])
def test_chordal_distance_of_two_gains_is_the_closed_form(b1, b2):
    # x+ = b u, y = x: P(z) = b / z, |P| = |b| at every frequency, so the distance is that of two gains.
    d = chordal_distance([[0.0]], [[b1]], [[0.0]], [[b2]])
    assert d == pytest.approx(abs(b2 - b1) / np.sqrt((1 + b1 ** 2) * (1 + b2 ** 2)), abs=TOL["chordal"])


def test_hover_chordal_distance_is_zero_for_the_truth_and_grows_with_a_wrong_inertia():
    from sim import QuadParams
    P = QuadParams()
    assert hover_chordal_distance(AnalyticModel()) < TOL["chordal"]
    d = [hover_chordal_distance(AnalyticModel(QuadParams(Jxx=f * P.Jxx, Jyy=f * P.Jyy))) for f in (1.3, 1.6)]
    assert 0 < d[0] < d[1] < 1
