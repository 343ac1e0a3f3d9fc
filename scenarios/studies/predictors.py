"""Which open-loop number predicts closed-loop failure? Candidates, and how to score them as predictors.

Candidates for one prediction model (each a number, larger = worse):

* the open-loop errors of the evaluation (``pinnmpc evaluate``): 1-step
  position MAE, 100-step position MAE, the fraction of 100-step rollouts
  that diverged;
* :func:`jacobian_error`: how far the model's linearization ``[A B]`` is
  from the true model's along a scenario's reference (states and the true
  feed-forward wrench), the quantity an MPC actually uses;
* :func:`hover_chordal_distance`: the identification-for-control measure,
  the largest chordal distance over frequency between the model's and the
  true model's hover transfer matrices (Vinnicombe's nu-gap without its
  winding-number condition, so a lower bound of it).

Scores of a candidate over a set of models:

* against crashes (a yes/no outcome): the ROC AUC (:func:`roc_auc`, the
  probability that a model that crashed has the larger candidate value; 0.5
  is chance), with a bootstrap interval over models;
* against the RMSE: the Spearman rank correlation, with a bootstrap interval.

``python -m scenarios.studies.predictors DIR [--controller sqp] [--scenario figure8-fast] [--json FILE]`` scores
the candidates on a results folder of ``pinnmpc run`` (its ``evaluation.json`` and its runs; ensemble
members are used when the folder has them, else the single runs). It asserts nothing.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..errors import ScenarioError
from .stats import spearman

#: Candidates taken from ``evaluation.json`` (name -> path in a model's entry).
EVALUATION_CANDIDATES = {"one_step_position_mae_m": ("one_step", "position"),
                         "rollout_100_position_mae_m": ("rollout_100", "position"),
                         "rollout_100_diverged_fraction": None}


def roc_auc(scores, labels) -> float | None:
    """ROC AUC of ``scores`` (n,) for the binary ``labels`` (n,): P(score of a positive > score of a negative).

    Ties count one half (the Mann-Whitney statistic). None when either class is empty.
    """
    s = np.asarray(scores, dtype=float)
    y = np.asarray(labels, dtype=bool)
    if s.shape != y.shape or s.ndim != 1:
        raise ScenarioError(f"scores and labels must be 1-D of one length; found {s.shape} and {y.shape}")
    pos, neg = s[y], s[~y]
    if pos.size == 0 or neg.size == 0:
        return None
    diff = pos[:, None] - neg[None, :]
    return float((np.sum(diff > 0) + 0.5 * np.sum(diff == 0)) / diff.size)


def bootstrap_score_ci(score, x, y, n_boot: int = 2000, level: float = 0.95,
                       seed: int = 0) -> tuple[float, float] | None:
    """Percentile bootstrap interval of ``score(x, y)`` over resampled (x, y) pairs (seeded).

    Resamples where the score is undefined (None: one class only, constant
    ranks) are skipped; None when fewer than half are defined.
    """
    x, y = np.asarray(x), np.asarray(y)
    rng = np.random.default_rng(seed)
    vals = []
    for _ in range(n_boot):
        i = rng.integers(0, len(x), len(x))
        v = score(x[i], y[i])
        if v is not None:
            vals.append(v)
    if len(vals) < n_boot / 2:
        return None
    a = (1 - level) / 2
    return float(np.quantile(vals, a)), float(np.quantile(vals, 1 - a))


def jacobian_error(model, scenario: str, samples: int = 50) -> float:
    """Mean relative error of the model's ``[A B]`` against the true model's along ``scenario``'s reference.

    ``samples`` times evenly spread over the scenario; at each, the
    reference state and the true feed-forward wrench (held over the period);
    the error is ``||[A B] - [A* B*]||_F / ||[A* B*]||_F`` with each column
    scaled by the acceptable deviation of its variable (so that metres,
    radians and newton-metres weigh alike), averaged over the samples.
    """
    from mpc.controllers.lqr import DEFAULT_STATE_SCALE, input_scale
    from mpc.prediction.models import AnalyticModel
    from mpc.prediction.spec import VehicleSpec
    from mpc.references.trajectory import held_wrench

    from ..closed_loop.library import get_scenario

    sc = get_scenario(scenario)
    t = np.linspace(0.0, sc.duration_s - 0.01, samples)
    ref = sc.reference()
    x = ref(t)
    u = held_wrench(ref, t)
    truth = AnalyticModel()
    _, A0, B0 = truth.linearize(x, u)
    _, A, B = model.linearize(x, u)
    col = np.concatenate([DEFAULT_STATE_SCALE, input_scale(VehicleSpec.from_model(truth))])
    J0 = np.concatenate([A0, B0], axis=2) * col
    J = np.concatenate([A, B], axis=2) * col
    return float(np.mean(np.linalg.norm(J - J0, axis=(1, 2)) / np.linalg.norm(J0, axis=(1, 2))))


#: Frequencies of the chordal distance, rad per control period (log-spaced up to Nyquist).
CHORDAL_FREQUENCIES = np.logspace(-3, np.log10(np.pi), 200)


def _inv_sqrt(M: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(M)
    return (V / np.sqrt(w)) @ V.conj().T


def chordal_distance(A1, B1, A2, B2, out_scale=None, in_scale=None, freqs=CHORDAL_FREQUENCIES) -> float:
    """Largest chordal distance over ``freqs`` between two discrete systems ``(A, B)`` with full-state output.

    ``kappa(w) = sigma_max((I + P2 P2^H)^-1/2 (P2 - P1) (I + P1^H P1)^-1/2)`` with ``P_i = diag(1/out_scale)
    (e^{jw} I - A_i)^-1 B_i diag(in_scale)``: each output in units of its acceptable deviation, each input in units
    of its acceptable change. Between 0 (same frequency response) and 1. Without the winding-number condition of
    the nu-gap it is a lower bound of it (they are equal when that condition holds).
    """
    A1, B1, A2, B2 = (np.asarray(a, dtype=float) for a in (A1, B1, A2, B2))
    n, m = B1.shape
    so = np.ones(n) if out_scale is None else np.asarray(out_scale, dtype=float)
    si = np.ones(m) if in_scale is None else np.asarray(in_scale, dtype=float)
    eye_n, eye_p = np.eye(n), np.eye(n)
    worst = 0.0
    for w in freqs:
        z = np.exp(1j * w)
        P1 = (np.linalg.solve(z * eye_n - A1, B1) * si) / so[:, None]
        P2 = (np.linalg.solve(z * eye_n - A2, B2) * si) / so[:, None]
        M = _inv_sqrt(eye_p + P2 @ P2.conj().T) @ (P2 - P1) @ _inv_sqrt(np.eye(m) + P1.conj().T @ P1)
        worst = max(worst, float(np.linalg.norm(M, 2)))
    return worst


def hover_chordal_distance(model) -> float:
    """:func:`chordal_distance` between the model's hover linearization and the true model's (scaled as the LQR's)."""
    from mpc.controllers.lqr import DEFAULT_STATE_SCALE, hover_linearization, input_scale
    from mpc.prediction.models import AnalyticModel
    from mpc.prediction.spec import VehicleSpec

    truth = AnalyticModel()
    A0, B0 = hover_linearization(truth)
    A, B = hover_linearization(model)
    return chordal_distance(A0, B0, A, B, DEFAULT_STATE_SCALE, input_scale(VehicleSpec.from_model(truth)))


def _evaluation_value(entry: dict, name: str) -> float | None:
    if name == "rollout_100_diverged_fraction":
        r = entry.get("rollout_100") or {}
        n, d = r.get("n_rollouts"), r.get("n_diverged")
        return None if not n else float(d) / float(n)
    a, b = EVALUATION_CANDIDATES[name]
    v = (entry.get(a) or {}).get(b)
    return None if v is None else float(v)


def score_candidates(candidates: dict[str, dict[str, float]], crashed: dict[str, float],
                     rmse: dict[str, float]) -> list[dict]:
    """One row per candidate: AUC against crash and Spearman against RMSE, with bootstrap intervals.

    ``candidates``: name -> {model: value}; ``crashed``: model -> crashed (bool, or a crash probability, then
    > 0.5 counts as a crash); ``rmse``: model -> RMSE (m) of the runs that flew.
    """
    rows = []
    for name, values in candidates.items():
        ms = [m for m in values if values[m] is not None and m in crashed]
        x = np.array([values[m] for m in ms], dtype=float)
        y = np.array([float(crashed[m]) > 0.5 for m in ms])
        mr = [m for m in ms if rmse.get(m) is not None]
        xr = np.array([values[m] for m in mr], dtype=float)
        yr = np.array([rmse[m] for m in mr], dtype=float)
        rows.append({"candidate": name, "models": len(ms), "crashed": int(y.sum()),
                     "auc": roc_auc(x, y) if len(ms) else None,
                     "auc_ci95": bootstrap_score_ci(roc_auc, x, y) if len(ms) >= 3 else None,
                     "spearman": spearman(xr, yr), "spearman_ci95": bootstrap_score_ci(spearman, xr, yr)
                     if len(mr) >= 4 else None})
    return rows


def predictors_of(run_dir, controller: str = "sqp", scenario: str = "figure8-fast", models_dir="models") -> dict:
    """The candidates of every learned model in a results folder, scored against its runs of one case."""
    from mpc.prediction.models import load_model

    from .stats import summarize

    d = Path(run_dir)
    try:
        evaluation = json.loads((d / "evaluation.json").read_text())
        runs = json.loads((d / "results.json").read_text())["runs"]
    except (OSError, ValueError, KeyError) as e:
        raise ScenarioError(f"{d}: needs evaluation.json and results.json of pinnmpc run ({e})") from e
    entries = {m["name"]: m for m in evaluation.get("models", [])}
    mine = [r for r in runs if r.get("controller") == controller and r.get("scenario") == scenario
            and r.get("timing", "ideal") == "ideal" and r.get("model") in entries]
    if not mine:
        raise ScenarioError(f"{d}: no ideal-timing {controller} run of {scenario} with a model of evaluation.json")
    members = [r for r in mine if r.get("member") is not None]
    use = members or mine
    crashed, rmse = {}, {}
    for m in sorted({r["model"] for r in use}):
        s = summarize([r for r in use if r["model"] == m])
        crashed[m], rmse[m] = s["crash_probability"], s["median"]
    candidates = {n: {m: _evaluation_value(entries[m], n) for m in crashed} for n in EVALUATION_CANDIDATES}
    candidates["jacobian_error"] = {m: jacobian_error(load_model(str(Path(models_dir) / f"{m}.onnx")), scenario)
                                    for m in crashed}
    return {"controller": controller, "scenario": scenario, "outcome_runs": "ensembles" if members else "single runs",
            "candidates": candidates, "crash_probability": crashed, "rmse_m": rmse,
            "scores": score_candidates(candidates, crashed, rmse)}


def main(argv=None) -> int:
    """Score the candidates on a results folder and print the table."""
    ap = argparse.ArgumentParser(prog="python -m scenarios.studies.predictors", description=__doc__.splitlines()[0])
    ap.add_argument("dir", type=Path, help="results folder of pinnmpc run")
    ap.add_argument("--controller", default="sqp")
    ap.add_argument("--scenario", default="figure8-fast")
    ap.add_argument("--models", type=Path, default=Path("models"))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    try:
        out = predictors_of(args.dir, args.controller, args.scenario, args.models)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None

    def ci(v):
        return "undefined" if v is None else f"{v[0]:+.2f} to {v[1]:+.2f}"

    print(f"{args.scenario} / {args.controller}: {len(out['rmse_m'])} learned models, outcomes from "
          f"{out['outcome_runs']}")
    for r in out["scores"]:
        auc = "undefined (one class)" if r["auc"] is None else f"{r['auc']:.2f} ({ci(r['auc_ci95'])})"
        sp = "undefined" if r["spearman"] is None else f"{r['spearman']:+.2f} ({ci(r['spearman_ci95'])})"
        print(f"  {r['candidate']:32s} crash AUC {auc:28s} RMSE Spearman {sp}")
    if args.json:
        from sim.files import write_json
        write_json(args.json, out)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
