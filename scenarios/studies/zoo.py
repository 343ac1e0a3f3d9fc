"""The dose-response study: every model of the zoo flown as an ensemble, and which open-loop number predicts failure.

``pinnmpc study [--models models/zoo] [--out results/zoo] [--members 10] [--jobs 2] [--engine ...]`` flies:

* every zoo model with each controller of :data:`STUDY_CONTROLLERS` on
  :data:`STUDY_SCENARIO`, from ``members`` ensemble members (crash
  probability with a Wilson interval, median RMSE with a bootstrap interval);
* every zoo model with the LTV-MPC up the figure-8 speed ladder (single
  runs; the fastest rung flown without crash within the ladder's error bound
  is the model's maximum trackable speed);
* the oracle once on :data:`STUDY_SCENARIO` with the SQP: the states and
  inputs a closed loop visits, on which each model's k-step error is measured.

It then scores the open-loop candidates (:data:`CANDIDATES`) of every model
as predictors of crash (ROC AUC) and of RMSE (Spearman), with bootstrap
intervals over models, per controller, and writes ``OUT/study.json`` and a
copy ``MODELS/study.json`` that the report of ``pinnmpc run`` shows. The runs
are a resumable sweep (:func:`scenarios.sweeps.sweep.sweep`).
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from mpc.controllers.factory import HORIZON
from sim.files import write_json

from ..errors import ScenarioError
from ..sweeps.lock import locks_out_dir
from ..closed_loop.library import ladder_names, ladder_speeds
from ..closed_loop.metrics import LADDER_RMSE_BOUND_M, max_trackable_speed
from .predictors import hover_chordal_distance, jacobian_error, score_candidates
from ..closed_loop.record import code_version
from ..closed_loop.runner import RunSpec
from ..sweeps.sweep import sweep
from .stats import summarize

STUDY_SCENARIO = "figure8-fast"
STUDY_CONTROLLERS = ("ltv", "sqp")
LADDER_CONTROLLER = "ltv"
#: Steps of the closed-loop k-step error: the MPC's horizon.
KSTEP = HORIZON
#: Open-loop candidates (larger = worse), with what each measures.
CANDIDATES = {
    "one_step_mae_m": "1-step position MAE on the test split, m",
    "rollout_100_mae_m": "100-step position MAE on the test split, m",
    "envelope_exit_fraction": "fraction of 100-step test rollouts whose position error exceeds 1 m (or diverge)",
    "jacobian_error": "relative error of [A B] against the true model along the figure-8 reference",
    "closed_loop_kstep_m": f"{KSTEP}-step position error along the oracle's closed-loop flight of the figure-8, m",
    "hover_chordal_distance": "largest chordal distance over frequency between the model's and the true hover "
                              "transfer matrices (a lower bound of the nu-gap), 0 to 1",
}


def zoo_models(models_dir, progress: bool = False) -> dict[str, dict]:
    """``{name: manifest entry}`` of the zoo in ``models_dir`` (its manifest.json), in manifest order.

    A folder without a ``manifest.json`` is a study of its own model files (:func:`manifest_of_files`): every
    ``*.onnx`` in it (not ``*.jac.onnx``), by name, with the open-loop errors the study's predictors need measured
    on the zoo's test data.
    """
    d = Path(models_dir)
    if not d.is_dir():
        raise ScenarioError(f"models folder {str(d)!r} does not exist")
    if not (d / "manifest.json").exists():
        return manifest_of_files(d, progress)
    try:
        manifest = json.loads((d / "manifest.json").read_text())
    except (OSError, ValueError) as e:
        raise ScenarioError(f"{d / 'manifest.json'}: not a readable manifest ({e})") from e
    out = {}
    for name, entry in manifest.items():
        path = d / entry.get("files", {}).get("onnx", f"{name}.onnx")
        if not path.is_file():
            raise ScenarioError(f"{d}: the manifest lists {name} but {path.name} is missing")
        out[name] = {**entry, "path": str(path)}
    if not out:
        raise ScenarioError(f"{d}: the manifest lists no model")
    return out


def manifest_of_files(models_dir, progress: bool = False) -> dict[str, dict]:
    """Manifest entries for the model files of a folder that has no manifest: ``{name: entry}``, sorted by name.

    Each model is checked against the contract and evaluated open loop on the
    zoo's test data (:data:`pinn.zoo.TEST_DATA`, generated in a few seconds): its one-step and 100-step position
    errors are the entry's ``metrics``, as ``pinnmpc zoo`` records them when it trains a model (the same numbers:
    onnxruntime on the exported file agrees with the training run's torch to 1e-15 m). A model that fails the
    check or the evaluation gets an entry with ``failed``, the reason, instead of metrics.
    """
    from mpc.prediction.contract import ModelContractError, check_model, model_files
    from pinn.evaluate import evaluate_model, regenerate
    from pinn.zoo import TEST_DATA

    d = Path(models_dir)
    files = model_files(d)
    if not files:
        raise ScenarioError(f"{d}: no manifest.json and no .onnx model to study")
    if progress:
        print(f"{d} has no manifest.json: evaluating its {len(files)} models open loop on the zoo's test data "
              f"(the study's predictors need their one-step and 100-step errors)", file=sys.stderr, flush=True)
    ds = regenerate(TEST_DATA)
    out = {}
    for f in files:
        entry = {"files": {"onnx": f.name}, "why": "a model of your own", "test_data": TEST_DATA, "path": str(f)}
        try:
            info = check_model(f)
            r = evaluate_model(f, ds=ds, info=info)
        except (ModelContractError, ValueError) as e:   # recorded; the study goes on with the other models
            out[f.stem] = {**entry, "failed": " ".join(str(e).split())}
            continue
        out[f.stem] = {**entry, "architecture": info.architecture,
                       "metrics": {"one_step_mae": r["one_step"], "rollout_100_mae": r["rollout_100"]}}
    return out


def refused_models(models_dir) -> dict[str, dict]:
    """The zoo's refused models (``refused.json`` of ``pinnmpc zoo``): what each is, its open-loop error, the reason."""
    path = Path(models_dir) / "refused.json"
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text())
    except ValueError as e:
        raise ScenarioError(f"{path}: not valid JSON ({e})") from e
    return {n: {"why": e.get("why"), "reason": e.get("reason"),
                "rollout_100_mae_m": e.get("metrics", {}).get("rollout_100_mae", {}).get("position")}
            for n, e in data.items()}


def study_specs(models: dict[str, dict], members: int = 10, controllers=STUDY_CONTROLLERS, plant: str = "sim",
                vehicle: str | None = None, estimator: str = "none",
                qp: str = "osqp", level: str = "wrench") -> tuple[RunSpec, list[RunSpec], list[RunSpec]]:
    """(oracle reference run, ensemble runs, speed-ladder runs) of the study, on ``plant`` flying ``vehicle``.

    The reference run is the oracle's, or on a plant without known equations (``rotorpy``) the nominal
    equations', without an estimator (its trace scores the open-loop candidates). With ``estimator``
    (``"ekf"``) the ensembles fly with the state estimator and there is no ladder (the study of the threshold).
    ``qp``: the QP solver of every run (:attr:`scenarios.closed_loop.runner.RunSpec.qp`); ``level`` the command level
    of every run (the reference run is the oracle's at that level only on our plant's nominal set-up).
    """
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ScenarioError(f"members must be an integer >= 1; found {members!r}")
    from mpc.prediction.models import level_oracle_exists
    from sim.plants.named import KNOWN_EQUATIONS

    where = {"plant": plant, "vehicle": vehicle, "qp": qp, "level": level}
    known = plant in KNOWN_EQUATIONS and level_oracle_exists(plant, level)
    oracle = RunSpec(STUDY_SCENARIO, "sqp", "oracle" if known else "nominal", **where)
    ens = [RunSpec(STUDY_SCENARIO, c, m["path"], member=k, estimator=estimator, **where) for m in models.values()
           for c in controllers for k in range(members)]
    ladder = [] if estimator != "none" else \
        [RunSpec(s, LADDER_CONTROLLER, m["path"], **where) for m in models.values() for s in ladder_names()]
    return oracle, ens, ladder


def study_file(estimator: str = "none") -> str:
    """Name of a study's JSON file: ``study.json``, or ``study_<estimator>.json`` with a state estimator."""
    return "study.json" if estimator == "none" else f"study_{estimator}.json"


def select_models(models: dict[str, dict], select) -> dict[str, dict]:
    """The models named in ``select`` (a list of names, or None for all), in the manifest's order."""
    if select is None:
        return models
    unknown = [n for n in select if n not in models]
    if unknown:
        raise ScenarioError(f"--select: no model {', '.join(map(repr, unknown))} in the zoo; it has "
                            f"{', '.join(models)}")
    if not select:
        raise ScenarioError("--select names no model")
    return {n: e for n, e in models.items() if n in select}


def closed_loop_kstep_error(model, trace: dict, k: int = KSTEP, every: int = 5) -> float:
    """Mean position error (m) of ``k``-step predictions along a flown trace, with the trace's own inputs.

    From every ``every``-th period ``i`` of the trace, the model is rolled out
    ``k`` steps from the true state ``x[i]`` with the applied inputs
    ``u[i .. i+k-1]`` and compared with ``x[i+k]`` (Euclidean norm). A
    non-finite prediction counts as an error of 1e3 m.
    """
    X = np.asarray(trace["x"], dtype=float)
    U = np.asarray(trace["u"], dtype=float)
    starts = np.arange(0, len(U) - k + 1, every)
    if starts.size == 0:
        raise ScenarioError(f"the trace has {len(U)} periods, fewer than k = {k}")
    x = X[starts].copy()
    with np.errstate(all="ignore"):
        for j in range(k):
            x = model.step(x, U[starts + j])
            x = np.where(np.isfinite(x), x, 1e3)
        err = np.linalg.norm(x[:, :3] - X[starts + k, :3], axis=1)
    return float(np.mean(np.minimum(err, 1e3)))


def _candidates(name: str, entry: dict, oracle_trace: dict) -> dict:
    from mpc.prediction.models import load_model

    r = entry["metrics"]["rollout_100_mae"]
    model = load_model(entry["path"])
    left = r.get("n_left_envelope")
    return {"one_step_mae_m": entry["metrics"]["one_step_mae"]["position"],
            "rollout_100_mae_m": r["position"],
            "envelope_exit_fraction": None if left is None else left / r["n_rollouts"],
            "jacobian_error": jacobian_error(model, STUDY_SCENARIO),
            "closed_loop_kstep_m": closed_loop_kstep_error(model, oracle_trace),
            "hover_chordal_distance": hover_chordal_distance(model)}


@locks_out_dir
def run_study(models_dir="models/zoo", out_dir="results/zoo", members: int = 10, jobs: int = 1,
              controllers=STUDY_CONTROLLERS, progress: bool = True, publish: bool = True, plant: str = "sim",
              vehicle: str | None = None, estimator: str = "none", select=None, qp: str = "osqp",
              level: str = "wrench", **sweep_kwargs) -> dict:
    """Fly the study (a resumable sweep), score the predictors and write ``study.json``.

    Parameters
    ----------
    models_dir : path
        The zoo (``manifest.json`` and its ONNX files).
    out_dir : path
        Results folder: runs, traces and ``study.json``.
    members : int
        Ensemble members per model and controller.
    publish : bool
        Also copy ``study.json`` into ``models_dir`` (where the report reads it).
    plant, vehicle
        Where the study flies (:class:`scenarios.closed_loop.runner.RunSpec`); the reference simulator and the default
        vehicle by default.
    estimator : {"none", "ekf"}
        With ``"ekf"`` the ensembles fly with the state estimator, without the speed ladder, and the study is
        written to ``study_ekf.json`` (:func:`study_file`) beside the one without.
    select : list of str, optional
        Fly only these models of the zoo (default: all).
    qp : {"osqp", "daqp"}
        The QP solver of every LTV-MPC and SQP run (:attr:`scenarios.closed_loop.runner.RunSpec.qp`).
    level : str
        The command level of every run (:mod:`sim.levels`); a model of the zoo that declares another is recorded as
        not flown, and a zoo with none at that level is refused.
    sweep_kwargs
        ``engine``, ``address``, ``resume`` of :func:`scenarios.sweeps.sweep.sweep`.
    """
    from mpc.prediction.contract import declared_level
    from sim.levels import check_level

    from ..closed_loop.runner import ESTIMATORS

    check_level(level)

    if estimator not in ESTIMATORS:
        raise ScenarioError(f"estimator must be one of {', '.join(ESTIMATORS)}; found {estimator!r}")
    from mpc.prediction.models import load_model

    models = select_models(zoo_models(models_dir, progress), select)
    # A model that cannot be loaded (a damaged file, another dt, ...) is recorded with its reason and not flown;
    # the study goes on with the others.
    failed = {n: e["failed"] for n, e in models.items() if e.get("failed")}
    for name, entry in models.items():
        if name not in failed:
            try:
                load_model(entry["path"])
                other = declared_level(entry["path"])
                if other != level:
                    failed[name] = f"takes commands at the {other!r} level, not {level!r}"
            except ValueError as e:
                failed[name] = " ".join(str(e).split())
    models = {n: e for n, e in models.items() if n not in failed}
    if not models:
        why = sorted(set(failed.values()))
        raise ScenarioError(f"{models_dir}: no model can be flown" + (f" at the {level!r} level" if level != "wrench"
                                                                      else "") + ": "
                            + ("; ".join(f"{n}: {w}" for n, w in failed.items()) if len(why) > 1
                               else f"every model {why[0]}" if why else "the zoo is empty"))
    oracle, ens, ladder = study_specs(models, members, controllers, plant, vehicle, estimator, qp, level)
    t0 = time.perf_counter()
    results = sweep([oracle, *ens, *ladder], out_dir, jobs=jobs, progress=progress, **sweep_kwargs)
    wall = time.perf_counter() - t0
    by_id = {r["run_id"]: r for r in results}
    ref = by_id[oracle.run_id]
    if ref.get("error") or ref.get("crashed") or not ref.get("trace"):
        raise ScenarioError(f"the oracle's reference flight did not complete: {ref.get('error') or 'crashed'}")
    oracle_trace = _oracle_trace(out_dir, ref)
    speeds = ladder_speeds()
    rows = {}
    for name, entry in models.items():
        try:
            candidates = _candidates(name, entry, oracle_trace)
        except ValueError as e:      # the model changed or broke after its flights: recorded, not scored
            failed[name] = " ".join(str(e).split())
            continue
        row = {"run": entry.get("run"), "why": entry.get("why"), "epochs": entry.get("epochs"),
               "architecture": entry.get("architecture"), "candidates": candidates, "ensembles": {}}
        for c in controllers:
            runs = [by_id[s.run_id] for s in ens if s.model == entry["path"] and s.controller == c]
            row["ensembles"][c] = summarize(runs)
            row["ensembles"][c]["errors"] = sum(bool(r.get("error")) for r in runs)
        lad = [by_id[s.run_id] for s in ladder if s.model == entry["path"]]
        row["max_speed"] = None if not ladder else \
            {"controller": LADDER_CONTROLLER, **max_trackable_speed(lad, ladder_names(), speeds),
             "rungs": {r["scenario"]: {"crashed": r.get("crashed"), "rmse_m": r.get("rmse_position_m")} for r in lad}}
        rows[name] = row
    scores = _scores(rows, controllers)
    out = {"scenario": STUDY_SCENARIO, "members": members, "controllers": list(controllers),
           "ladder": {"controller": LADDER_CONTROLLER, "rungs": ladder_names(), "speeds_mps": speeds,
                      "rmse_bound_m": LADDER_RMSE_BOUND_M},
           "candidates": CANDIDATES, "kstep": KSTEP, "oracle_run": oracle.run_id,
           "oracle_rmse_m": ref.get("rmse_position_m"), "models": rows, "scores": scores,
           "refused": refused_models(models_dir), "failed": failed,
           "runs": len(results), "code_version": code_version(), "plant": plant,
           "vehicle": oracle.vehicle_data.name,
           "estimator": estimator, "qp": qp, "level": level,
           "command": f"pinnmpc study --models {models_dir} --out {out_dir} --members {members}"
                      + ("" if plant == "sim" else f" --plant {plant}") + ("" if vehicle is None else f" --vehicle {vehicle}")
                      + ("" if estimator == "none" else f" --estimator {estimator}")
                      + ("" if select is None else f" --select {','.join(models)}")
                      + ("" if qp == "osqp" else f" --qp {qp}") + ("" if level == "wrench" else f" --level {level}"),
           "wall_time_s": wall, "date": time.strftime("%Y-%m-%d")}
    path = write_json(Path(out_dir) / study_file(estimator), out)
    if publish:
        shutil.copyfile(path, Path(models_dir) / study_file(estimator))
    return out


def _oracle_trace(out_dir, ref: dict) -> dict:
    with np.load(Path(out_dir) / ref["trace"]) as z:
        return {"x": z["x"], "u": z["u"]}


def _scores(rows: dict, controllers) -> dict:
    scores = {}
    for c in controllers:
        cands = {k: {m: rows[m]["candidates"].get(k) for m in rows} for k in CANDIDATES}
        crash = {m: rows[m]["ensembles"][c]["crash_probability"] for m in rows}
        rmse = {m: rows[m]["ensembles"][c]["median"] for m in rows}
        scores[c] = score_candidates(cands, crash, rmse)
        for row in scores[c]:
            row["description"] = CANDIDATES[row["candidate"]]
    return scores


def rescore_study(models_dir="models/zoo", out_dir="results/zoo", publish: bool = True) -> dict:
    """Recompute every model's open-loop candidates and the scores of a flown study, flying nothing.

    The closed-loop outcomes (ensembles, speed ladder) are read from
    ``OUT/study.json``; the oracle's flight from its saved trace. Use it
    after adding a candidate: the outcomes do not depend on it.
    """
    path = Path(out_dir) / "study.json"
    try:
        out = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ScenarioError(f"{path}: needs the study.json of pinnmpc study ({e})") from e
    models = zoo_models(models_dir)
    missing = sorted(set(out["models"]) - set(models))
    if missing:
        raise ScenarioError(f"{models_dir}: the study flew models that are not in its manifest: {missing}")
    ref = json.loads((Path(out_dir) / "runs" / f"{out['oracle_run']}.json").read_text())
    oracle_trace = _oracle_trace(out_dir, ref)
    for name, row in out["models"].items():
        row["candidates"] = _candidates(name, models[name], oracle_trace)
    out["candidates"] = CANDIDATES
    out["scores"] = _scores(out["models"], out["controllers"])
    out["refused"] = refused_models(models_dir)
    out["rescored"] = time.strftime("%Y-%m-%d")
    write_json(path, out)
    if publish:
        shutil.copyfile(path, Path(models_dir) / "study.json")
    return out


def best_predictor(scores: list[dict], key: str = "auc") -> dict | None:
    """The candidate with the highest ``key`` (``auc`` or ``spearman``) among those defined."""
    rows = [s for s in scores if s.get(key) is not None]
    return max(rows, key=lambda s: s[key]) if rows else None


def format_study(out: dict) -> str:
    """Plain-text tables of a study: one row per model, then the predictor scores per controller."""
    cs = out["controllers"]
    lines = [f"{out['scenario']}, {out['members']} members per model and controller; "
             f"oracle (SQP) RMSE {1e3 * out['oracle_rmse_m']:.2f} mm"]
    head = f"{'model':26s}{'100-step MAE':>13}" + "".join(f"{c + ' crash p (95 %)':>26}{c + ' RMSE':>10}"
                                                          for c in cs) + f"{'max speed':>11}"
    lines.append(head)
    for name, r in sorted(out["models"].items(), key=lambda kv: kv[1]["candidates"]["rollout_100_mae_m"]):
        s = f"{name:26s}{r['candidates']['rollout_100_mae_m']:>13.4g}"
        for c in cs:
            e = r["ensembles"][c]
            lo, hi = e["crash_probability_ci95"]
            s += f"{e['crash_probability']:>12.2f} ({lo:.2f}-{hi:.2f})"
            s += f"{'-' if e['median'] is None else format(e['median'], '.4f'):>10}"
        v = (r.get("max_speed") or {}).get("speed_mps")
        s += f"{'-' if r.get('max_speed') is None else 'none' if v is None else format(v, '.2f') + ' m/s':>11}"
        lines.append(s)
    for c in cs:
        lines.append(f"\npredictors, {c}:")
        for p in out["scores"][c]:
            auc = "undefined" if p["auc"] is None else f"{p['auc']:.2f}"
            if p.get("auc_ci95"):
                auc += f" ({p['auc_ci95'][0]:.2f}-{p['auc_ci95'][1]:.2f})"
            sp = "undefined" if p["spearman"] is None else f"{p['spearman']:+.2f}"
            if p.get("spearman_ci95"):
                sp += f" ({p['spearman_ci95'][0]:+.2f} to {p['spearman_ci95'][1]:+.2f})"
            lines.append(f"  {p['candidate']:26s} crash AUC {auc:20s} RMSE Spearman {sp}")
    return "\n".join(lines)
