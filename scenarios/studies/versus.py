"""Learned against nominal: on plants whose physics the nominal equations lack, does a learned model fly better?

``pinnmpc versus [--models models] [--out results/versus] [--members 10] [--ladder-members 10]
[--plants highfi,rotorpy] [--jobs 2] [--engine ...]`` flies, on each plant of :data:`VERSUS_PLANTS`:

* the nominal equations (the rigid body with the vehicle's values: what a user has before learning anything);
* every model of the plant's list trained on that plant's own data (those present), with and without actuator
  states where both exist;
* the plant's true equations where this project has them (the high-fidelity plant's oracle, motor lag included);

with the SQP on :data:`VERSUS_SCENARIO` from ``members`` ensemble members (median RMSE with a bootstrap interval,
crash probability with a Wilson interval) and up the figure-8 speed ladder from ``ladder_members`` members per
rung (the fastest rung with no crash and a median RMSE within the ladder's bound is the maximum trackable
speed). For each learned model it gives the improvement over the nominal equations,
``1 - median(model) / median(nominal)``, with a bootstrap interval, and whether the two medians' intervals
are apart; for each plant the best learned model against :data:`WIN_FRACTION`.

It writes ``OUT/versus.json`` and a copy ``MODELS/versus/versus.json`` that the report of ``pinnmpc run`` shows
(the main job does not fly these runs: about an hour of worker time, and the RotorPy models' data cost minutes
to regenerate). The runs are a resumable sweep (:func:`scenarios.sweeps.sweep.sweep`).
"""

from __future__ import annotations

import json

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpc.prediction.contract import declared_level
from mpc.prediction.models import model_name
from sim.files import write_json
from sim.levels import DEFAULT_LEVEL, check_level

from ..errors import ScenarioError
from ..sweeps.lock import locks_out_dir
from ..closed_loop.library import ladder_names, ladder_speeds
from ..closed_loop.metrics import LADDER_RMSE_BOUND_M, max_trackable_speed
from ..closed_loop.record import code_version
from ..closed_loop.runner import RunSpec
from .stats import improvement, summarize
from ..sweeps.sweep import sweep

#: Sub-folder of the models folder with the models only this study flies, and where it publishes versus.json.
VERSUS_DIR = "versus"
VERSUS_SCENARIO = "figure8-fast"
VERSUS_CONTROLLER = "sqp"
#: The goal: the best learned model's median RMSE at most this fraction below the nominal equations' (0.5: half).
WIN_FRACTION = 0.5


@dataclass(frozen=True)
class VersusPlant:
    """One plant of the study: where it flies, what it adds to the nominal equations, which models it flies.

    ``models`` are paths under the models folder, trained on this plant's own data (at any level: a study flies those
    that declare its level); ``suffix`` turns a
    scenario name into this plant's variant (``+highfi`` on the reference simulator); ``oracle``: the plant's
    true equations are known and fly too; ``vehicle`` the vehicle flown (a shipped vehicle's name; None: the
    default vehicle).
    """

    plant: str
    suffix: str
    label: str
    models: tuple
    oracle: bool
    vehicle: str | None = None

    def scenario(self, name: str) -> str:
        return name + self.suffix


#: The plants of the study, in the order of the report.
VERSUS_PLANTS = {
    "highfi": VersusPlant(
        "sim", "+highfi", "our high-fidelity plant (30 ms motor lag, rotor drag, gyroscopic torque)",
        ("identification/baseline_highfi.onnx", "versus/modular_highfi.onnx", "versus/fourier_highfi.onnx",
         "identification/proposed_highfi.onnx", "versus/hybrid_highfi.onnx", "identification/hybrid_lag_highfi.onnx",
         "versus/hybrid_lag_aggressive_highfi.onnx", "versus/hybrid_lag_aero_aggressive_highfi.onnx",
         "versus/ctbr/ctbr_highfi.onnx",
         "versus/ctbr/ctbr_aggressive_highfi.onnx"),
        True),
    "rotorpy": VersusPlant(
        "rotorpy", "", "RotorPy with its motor lag and aerodynamics",
        tuple(f"versus/{a}_rotorpy.onnx" for a in ("baseline", "modular", "fourier", "proposed", "hybrid",
                                                   "hybrid_lag", "hybrid_lag_aero"))
        + ("versus/ctbr/ctbr_rotorpy.onnx", "versus/ctbr/ctbr_aggressive_rotorpy.onnx"),
        False),
    # No open-loop model is trained on it: the learning study (pinnmpc learn) flies it.
    "crazyflie": VersusPlant("rotorpy", "", "RotorPy's Crazyflie 2.0 preset (72 ms motor lag, rotor drag)", (), False,
                             vehicle="crazyflie"),
}
#: The plants flown when none are named: those with models trained on their own open-loop data.
DEFAULT_VERSUS_PLANTS = ("highfi", "rotorpy")


def _count(name: str, v) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ScenarioError(f"{name} must be an integer >= 1; found {v!r}")
    return v


def parse_keys(text: str | None, known, default, name: str = "plants") -> list[str]:
    """Keys of ``known`` from the comma-separated list ``text``, each once, in its order (None: ``default``); else a
    ScenarioError naming ``name`` and the known keys."""
    if text is None:
        return list(default)
    keys = [k.strip() for k in str(text).split(",") if k.strip()]
    bad = [k for k in keys if k not in known]
    if bad or not keys:
        raise ScenarioError(f"{name} must be a comma-separated list of {', '.join(known)}; found {text!r}")
    return list(dict.fromkeys(keys))


def parse_plants(text: str | None) -> list[str]:
    """Plant keys from a comma-separated list (None: :data:`DEFAULT_VERSUS_PLANTS`)."""
    return parse_keys(text, VERSUS_PLANTS, DEFAULT_VERSUS_PLANTS)


def plant_models(key: str, models_dir, level: str = DEFAULT_LEVEL) -> list[str]:
    """The models plant ``key`` flies at ``level``: the equations first (the true ones only at the wrench level: at
    ``ctbr`` and ``ctatt`` this project has no equations of these plants' inner loops with their lag), then the
    learned models present under ``models_dir`` that declare that level."""
    p = VERSUS_PLANTS[key]
    eq = ["nominal"] + (["oracle"] if p.oracle and level == DEFAULT_LEVEL else [])
    files = [str(Path(models_dir) / m) for m in p.models if (Path(models_dir) / m).is_file()]
    return eq + [m for m in files if declared_level(m) == level] + learned_at_level(key, models_dir, level)


#: Where ``pinnmpc learn --level LEVEL --publish`` puts the summary of its study on a plant (under the models folder).
LEARNED_SUMMARY = "learn/{key}_{level}/learn.json"


def learned_at_level(key: str, models_dir, level: str) -> list[str]:
    """The final model of the published learning study on plant ``key`` at ``level`` (``[path]``; ``[]`` at the
    wrench level, whose study's models the main job flies, or where none is published)."""
    if level == DEFAULT_LEVEL:
        return []
    summary = Path(models_dir) / LEARNED_SUMMARY.format(key=key, level=level)
    if not summary.is_file():
        return []
    try:
        stem = json.loads(summary.read_text()).get("final_model")
    except (ValueError, AttributeError, UnicodeDecodeError) as e:
        raise ScenarioError(f"{str(summary)!r} is not the summary of pinnmpc learn ({e})") from None
    if not isinstance(stem, str) or not stem:
        raise ScenarioError(f"{str(summary)!r} is not the summary of pinnmpc learn: 'final_model' must name its "
                            f"final model; found {stem!r}")
    final = summary.parent / f"{stem}.onnx"
    return [str(final)] if final.is_file() and declared_level(str(final)) == level else []


def published_name(level: str = DEFAULT_LEVEL) -> str:
    """The file the study writes and publishes: ``versus.json`` at the wrench level, ``versus_<level>.json`` at
    another."""
    return "versus.json" if level == DEFAULT_LEVEL else f"versus_{level}.json"


def versus_specs(key: str, models: list[str], members: int = 10, ladder_members: int = 10,
                 qp: str = "osqp", level: str = DEFAULT_LEVEL) -> dict:
    """The runs of one plant: ``{"ensemble": {model: [RunSpec]}, "ladder": {model: {rung: [RunSpec]}}}``.

    The ladder's :data:`VERSUS_SCENARIO` rung is the ensemble itself (no run is flown twice). ``qp``: the QP
    solver of every run (:attr:`scenarios.closed_loop.runner.RunSpec.qp`); ``level`` the command level of every run.
    """
    _count("members", members)
    _count("ladder_members", ladder_members)
    p = VERSUS_PLANTS[key]
    ens, lad = {}, {}
    for m in models:
        ens[m] = [RunSpec(p.scenario(VERSUS_SCENARIO), VERSUS_CONTROLLER, m, member=k, plant=p.plant,
                          vehicle=p.vehicle, qp=qp, level=level) for k in range(members)]
        lad[m] = {r: (ens[m] if r == VERSUS_SCENARIO else
                      [RunSpec(p.scenario(r), VERSUS_CONTROLLER, m, member=k, plant=p.plant, vehicle=p.vehicle,
                               qp=qp, level=level)
                       for k in range(ladder_members)]) for r in ladder_names()}
    return {"ensemble": ens, "ladder": lad}


def _model_facts(spec: RunSpec) -> dict:
    """Architecture and actuator-state names of the model of ``spec`` (the oracle's on a plant with motor lag)."""
    if spec.model in ("nominal", "oracle"):
        from ..closed_loop.runner import load_run_model

        return {"architecture": "equations", "extra_states": list(load_run_model(spec).extra_names)}
    from mpc.prediction.contract import check_model

    info = check_model(spec.model)
    return {"architecture": info.architecture, "extra_states": list(info.extra_states)}


def _values(summary_runs: list[dict]) -> list[float]:
    return [r["rmse_position_m"] for r in summary_runs if not r.get("crashed") and not r.get("error")
            and r.get("rmse_position_m") is not None]


def _ladder_row(rungs: dict, speeds: dict) -> dict:
    out, pseudo = {}, []
    for rung, runs in rungs.items():
        s = summarize(runs)
        out[rung] = {"median_m": s["median"], "median_ci95": s["median_ci95"], "crashes": s["crashes"],
                     "runs": s["runs"]}
        pseudo.append({"scenario": rung, "crashed": s["crashes"] > 0 or s["median"] is None,
                       "rmse_position_m": s["median"]})
    return {"rungs": out, "max_speed": max_trackable_speed(pseudo, ladder_names(), speeds)}


def summarize_plant(key: str, models: list[str], results: dict, speeds: dict, level: str = DEFAULT_LEVEL) -> dict:
    """One plant's rows and verdict from its flown runs.

    ``results`` maps any key to a run's result with two more keys: ``_model`` (the model as given in ``models``)
    and ``_rung`` (None for the ensemble on :data:`VERSUS_SCENARIO`, else the ladder rung's base name).
    """
    p = VERSUS_PLANTS[key]
    rows = {}
    nominal_vals = None
    for m in models:
        ens = [results[i] for i in sorted(results) if results[i]["_model"] == m and results[i]["_rung"] is None]
        s = summarize(ens)
        facts = _model_facts(RunSpec(p.scenario(VERSUS_SCENARIO), VERSUS_CONTROLLER, m, plant=p.plant,
                                     vehicle=p.vehicle, level=level))
        solve = [r["solve_ms"]["median"] for r in ens if isinstance(r.get("solve_ms"), dict)
                 and r["solve_ms"].get("median") is not None]
        row = {"model": model_name(m), "path": None if m in ("nominal", "oracle") else m, **facts,
               "ensemble": s, "errors": sum(bool(r.get("error")) for r in ens),
               "members_rmse_m": [None if r.get("crashed") or r.get("error") else r.get("rmse_position_m")
                                  for r in ens],
               "solve_ms_median": float(np.median(solve)) if solve else None}
        rungs = {}
        for rung in ladder_names():
            rungs[rung] = ens if rung == VERSUS_SCENARIO else [
                results[i] for i in sorted(results) if results[i]["_model"] == m and results[i]["_rung"] == rung]
        # A model flown on figure8-fast only (no other rung) has no ladder row.
        row["ladder"] = _ladder_row(rungs, speeds) if all(rungs.values()) else None
        vals = _values(ens)
        if m == "nominal":
            nominal_vals = vals
        row["_vals"] = vals
        rows[row["model"]] = row
    best = None
    for name, row in rows.items():
        vals = row.pop("_vals")
        row["versus_nominal"] = None
        if name != "nominal" and nominal_vals is not None and len(nominal_vals) >= 2 and len(vals) >= 2 \
                and row["ensemble"]["crashes"] == 0:
            row["versus_nominal"] = improvement(nominal_vals, vals)
        if row["path"] is not None and row["ensemble"]["crashes"] == 0 and row["ensemble"]["median"] is not None:
            if best is None or row["ensemble"]["median"] < rows[best]["ensemble"]["median"]:
                best = name
    verdict, no_verdict = None, None
    n_members = max((r["ensemble"]["runs"] for r in rows.values()), default=0)
    if best is None:
        no_verdict = "no learned model flew every member without a crash"
    elif rows[best]["versus_nominal"] is None:
        if n_members < 2:
            no_verdict = (f"no comparison with the nominal equations: their bootstrap intervals need at least 2 "
                          f"members per model (found {n_members}; --members)")
        elif nominal_vals is None or len(nominal_vals) < 2:
            no_verdict = "no comparison: the nominal equations did not fly at least 2 members without a crash"
        else:
            no_verdict = f"no comparison: {best} has fewer than 2 members with an RMSE"
    if best is not None and rows[best]["versus_nominal"] is not None:
        v = rows[best]["versus_nominal"]
        verdict = {"best": best, "fraction": v["fraction"], "fraction_ci95": v["fraction_ci95"], "apart": v["apart"],
                   "goal": WIN_FRACTION, "met": bool(v["fraction"] >= WIN_FRACTION and v["apart"])}
    return {"plant": p.plant, "label": p.label, "scenario": p.scenario(VERSUS_SCENARIO), "models": rows,
            "verdict": verdict, "no_verdict": no_verdict}


@locks_out_dir
def run_versus(models_dir="models", out_dir="results/versus", members: int = 10, ladder_members: int = 10,
               plants=None, jobs: int = 1, progress: bool = True, publish: bool = True, qp: str = "osqp",
               level: str = DEFAULT_LEVEL, **sweep_kwargs) -> dict:
    """Fly the study (a resumable sweep) and write ``versus.json`` (see the module docstring).

    Parameters
    ----------
    models_dir : path
        The models folder (the plants' model lists are paths under it).
    out_dir : path
        Results folder: runs, traces and ``versus.json``.
    members, ladder_members : int
        Ensemble members on :data:`VERSUS_SCENARIO` and on every other rung of the speed ladder.
    plants : list of str, optional
        Keys of :data:`VERSUS_PLANTS` (default all).
    publish : bool
        Also copy ``versus.json`` into ``models_dir/versus`` (where the main job finds it for the report).
    qp : {"osqp", "daqp"}
        The QP solver of every run (:attr:`scenarios.closed_loop.runner.RunSpec.qp`).
    level : str
        The command level of every run (:mod:`sim.levels`); at ``ctbr`` and ``ctatt`` the study writes and publishes
        ``versus_<level>.json`` (:func:`published_name`) beside the wrench level's.
    sweep_kwargs
        ``engine``, ``address``, ``resume`` of :func:`scenarios.sweeps.sweep.sweep`.
    """
    keys = parse_plants(None if plants is None else ",".join(plants))
    check_level(level)
    if not Path(models_dir).is_dir():
        raise ScenarioError(f"models folder {str(models_dir)!r} does not exist")
    if any(VERSUS_PLANTS[k].plant == "rotorpy" for k in keys):
        from sim.plants.named import rotorpy_available

        if not rotorpy_available():
            raise ScenarioError("plants rotorpy and crazyflie need RotorPy (pip install -e '.[rotorpy]'), or fly "
                                "--plants highfi")
    all_specs, tags = [], []
    models = {k: plant_models(k, models_dir, level) for k in keys}
    for k in keys:
        sp = versus_specs(k, models[k], members, ladder_members, qp, level)
        for m, runs in sp["ensemble"].items():
            all_specs += runs
            tags += [(k, m, None)] * len(runs)
        for m, rungs in sp["ladder"].items():
            for rung, runs in rungs.items():
                if rung != VERSUS_SCENARIO:
                    all_specs += runs
                    tags += [(k, m, rung)] * len(runs)
    t0 = time.perf_counter()
    results = sweep(all_specs, out_dir, jobs=jobs, progress=progress, **sweep_kwargs)
    wall = time.perf_counter() - t0
    speeds = ladder_speeds()
    out_plants = {}
    for k in keys:
        mine = {}
        for i, ((kk, m, rung), r) in enumerate(zip(tags, results)):
            if kk == k:
                mine[i] = {**r, "_model": m, "_rung": rung}
        out_plants[k] = summarize_plant(k, models[k], mine, speeds, level)
    out = {"scenario": VERSUS_SCENARIO, "controller": VERSUS_CONTROLLER, "members": members,
           "ladder_members": ladder_members,
           "ladder": {"rungs": ladder_names(), "speeds_mps": speeds, "rmse_bound_m": LADDER_RMSE_BOUND_M},
           "goal": WIN_FRACTION, "plants": out_plants, "runs": len(results), "code_version": code_version(),
           "qp": qp, "level": level,
           "command": f"pinnmpc versus --models {models_dir} --out {out_dir} --members {members} "
                      f"--ladder-members {ladder_members} --plants {','.join(keys)}"
                      + ("" if qp == "osqp" else f" --qp {qp}") + ("" if level == DEFAULT_LEVEL else f" --level {level}"),
           "wall_time_s": wall, "date": time.strftime("%Y-%m-%d")}
    name = published_name(level)
    path = write_json(Path(out_dir) / name, out)
    if publish:
        (Path(models_dir) / VERSUS_DIR).mkdir(exist_ok=True)
        shutil.copyfile(path, Path(models_dir) / VERSUS_DIR / name)
    return out


def _mm(v) -> str:
    return "–" if v is None else f"{1e3 * v:.1f}"


def format_versus(out: dict) -> str:
    """The study as plain text: one block per plant, one line per model."""
    level = out.get("level", DEFAULT_LEVEL)
    lines = [f"{out['scenario']} with the {out['controller'].upper()}, {out['members']} members "
             f"(ladder: {out['ladder_members']} per rung)" + ("" if level == DEFAULT_LEVEL else f", at the {level} level")]
    for k, p in out["plants"].items():
        lines.append(f"\n{p['label']} ({p['scenario']}):")
        for name, row in p["models"].items():
            s = row["ensemble"]
            ci = s["median_ci95"]
            ci_txt = "" if ci is None else f" ({_mm(ci[0])}-{_mm(ci[1])})"
            v = row["versus_nominal"]
            vs = "" if v is None else (f", {100 * v['fraction']:+.0f} % vs nominal "
                                       f"({100 * v['fraction_ci95'][0]:+.0f} to {100 * v['fraction_ci95'][1]:+.0f})")
            sp = row["ladder"]["max_speed"]["speed_mps"]
            extra = f" [{len(row['extra_states'])} extra states]" if row["extra_states"] else ""
            lines.append(f"  {name}{extra}: {_mm(s['median'])} mm{ci_txt}, crashes {s['crashes']}/{s['runs']}{vs}; "
                         f"max speed {'–' if sp is None else f'{sp:.2f} m/s'}")
        v = p["verdict"]
        if v is None:
            lines.append("  " + (p.get("no_verdict") or "no learned model flew every member without a crash"))
        else:
            lines.append(f"  best learned: {v['best']}, {100 * v['fraction']:.0f} % better than nominal "
                         f"(goal {100 * v['goal']:.0f} %, intervals {'apart' if v['apart'] else 'overlap'}): "
                         f"{'met' if v['met'] else 'missed'}")
    return "\n".join(lines)
