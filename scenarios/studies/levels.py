"""The three command levels side by side: what flying through an inner loop does to the nominal model's tracking
and to the controller's time.

``pinnmpc levels [--models models] [--out results/levels] [--members 5] [--plants sim,highfi,rotorpy,drone-models]
[--jobs 2] [--engine ...]`` flies, on each plant of :data:`LEVELS_PLANTS` and at each level of
:data:`sim.levels.LEVELS`, the nominal model of that level (the rigid body with the vehicle's values; at ``ctbr``
and ``ctatt`` with the inner loop's assumed response) and, where it exists, the oracle (the plant's own
equations; at ``ctbr`` and ``ctatt`` with its exact inner loop, which only our plant's nominal set-up has), with
the SQP on :data:`LEVELS_SCENARIO` from ``members`` ensemble members (drone-models' plant, identified from
attitude commands, at ``ctatt`` only). Each row gives the median RMSE with its
bootstrap interval, the crash count and the SQP's median solve time, and at ``ctbr`` and ``ctatt`` the ratio of
both to the wrench level's, all measured in one run.

It writes ``OUT/levels.json`` and a copy ``MODELS/levels/levels.json`` that the report of ``pinnmpc run`` shows.
The runs are a resumable sweep (:func:`scenarios.sweeps.sweep.sweep`).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mpc.prediction.models import level_oracle_exists
from sim.files import write_json
from sim.levels import DEFAULT_LEVEL, LEVELS

from ..closed_loop.record import code_version
from ..closed_loop.runner import RunSpec
from ..errors import ScenarioError
from ..sweeps.lock import locks_out_dir
from ..sweeps.sweep import sweep
from .stats import summarize
from .versus import parse_keys

#: Sub-folder of the models folder where the study publishes levels.json.
LEVELS_DIR = "levels"
LEVELS_SCENARIO = "figure8-fast"
LEVELS_CONTROLLER = "sqp"


@dataclass(frozen=True)
class LevelsPlant:
    """One plant of the study: where it flies (``plant``, ``vehicle``, the scenario ``suffix`` of its set-up), its
    label, whether its equations are known at the wrench level (``oracle``), and the levels it takes."""

    plant: str
    vehicle: str
    suffix: str
    label: str
    oracle: bool
    levels: tuple = LEVELS

    def scenario(self) -> str:
        return LEVELS_SCENARIO + self.suffix

    def models(self, level: str) -> list[str]:
        """The models flown at ``level``: the nominal one, and the oracle where it exists there (at ``ctbr`` and
        ``ctatt`` only on our plant's nominal set-up, whose inner loop the oracle steps exactly)."""
        oracle = self.oracle and level_oracle_exists(self.plant, level, bool(self.suffix))
        return ["nominal"] + (["oracle"] if oracle else [])


#: The plants of the study, in the order of the report: the Crazyflie on each.
LEVELS_PLANTS = {
    "sim": LevelsPlant("sim", "crazyflie", "", "our plant, nominal set-up", True),
    "highfi": LevelsPlant("sim", "crazyflie", "+highfi",
                          "our high-fidelity plant (72 ms motor lag, rotor drag)", True),
    "rotorpy": LevelsPlant("rotorpy", "crazyflie", "",
                           "RotorPy (72 ms motor lag, aerodynamics), through its own onboard controllers", False),
    "drone-models": LevelsPlant("drone-models", "cf2x_L250", "",
                                "drone-models' so_rpy_rotor_drag, identified from real flights (attitude level only)",
                                False, ("ctatt",)),
}
DEFAULT_LEVELS_PLANTS = tuple(LEVELS_PLANTS)


def parse_level_plants(text: str | None) -> list[str]:
    """Plant keys from a comma-separated list (None: :data:`DEFAULT_LEVELS_PLANTS`)."""
    return parse_keys(text, LEVELS_PLANTS, DEFAULT_LEVELS_PLANTS, "--plants")


def levels_specs(key: str, members: int, qp: str = "osqp") -> dict:
    """The runs of one plant: ``{level: {model: [RunSpec] (one per member)}}``."""
    p = LEVELS_PLANTS[key]
    return {lv: {m: [RunSpec(p.scenario(), LEVELS_CONTROLLER, m, member=k, plant=p.plant, vehicle=p.vehicle, qp=qp,
                             level=lv) for k in range(members)] for m in p.models(lv)} for lv in p.levels}


def _solve_median(runs: list[dict]) -> float | None:
    """Median over the members of each run's median solve time, ms (None without one)."""
    vals = [r["solve_ms"]["median"] for r in runs if isinstance(r.get("solve_ms"), dict)
            and r["solve_ms"].get("median") is not None]
    return float(np.median(vals)) if vals else None


def _ratio(a, b) -> float | None:
    return None if a is None or b is None or b == 0 else a / b


def summarize_levels(key: str, results: dict) -> dict:
    """One plant's rows from its flown runs: ``results`` maps ``(level, model)`` to the members' results."""
    p = LEVELS_PLANTS[key]
    rows = []
    for (level, model), runs in results.items():
        s = summarize(runs)
        rows.append({"level": level, "model": model, "ensemble": s, "errors": sum(bool(r.get("error")) for r in runs),
                     "solve_ms_median": _solve_median(runs)})
    wrench = {r["model"]: r for r in rows if r["level"] == DEFAULT_LEVEL}
    for r in rows:
        w = None if r["level"] == DEFAULT_LEVEL else wrench.get(r["model"])
        r["rmse_vs_wrench"] = None if w is None else _ratio(r["ensemble"]["median"], w["ensemble"]["median"])
        r["solve_vs_wrench"] = None if w is None else _ratio(r["solve_ms_median"], w["solve_ms_median"])
    return {"plant": p.plant, "vehicle": p.vehicle, "label": p.label, "scenario": p.scenario(), "rows": rows}


@locks_out_dir
def run_levels(models_dir="models", out_dir="results/levels", members: int = 5, plants=None, jobs: int = 1,
               progress: bool = True, publish: bool = True, qp: str = "osqp", **sweep_kwargs) -> dict:
    """Fly the study (a resumable sweep) and write ``levels.json`` (see the module docstring).

    Parameters
    ----------
    models_dir : path
        The models folder, where ``levels/levels.json`` is published.
    out_dir : path
        Results folder: runs, traces and ``levels.json``.
    members : int
        Ensemble members of every (plant, level, model).
    plants : list of str, optional
        Keys of :data:`LEVELS_PLANTS` (default all).
    publish : bool
        Also copy ``levels.json`` into ``models_dir/levels`` (where the main job finds it for the report).
    qp : {"osqp", "daqp"}
        The QP solver of every run.
    sweep_kwargs
        ``engine``, ``address``, ``resume`` of :func:`scenarios.sweeps.sweep.sweep`.
    """
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ScenarioError(f"--members must be an integer >= 1; found {members!r}")
    keys = parse_level_plants(None if plants is None else ",".join(plants))
    if publish and not Path(models_dir).is_dir():
        raise ScenarioError(f"models folder {str(models_dir)!r} does not exist")
    if any(LEVELS_PLANTS[k].plant == "rotorpy" for k in keys):
        from sim.plants.named import rotorpy_available

        if not rotorpy_available():
            raise ScenarioError("plant rotorpy needs RotorPy (pip install -e '.[rotorpy]'), or fly --plants sim,highfi")
    if "drone-models" in keys:
        from sim.plants.drone_models_plant import drone_models_available

        if not drone_models_available():
            raise ScenarioError("plant drone-models needs the drone-models extra (pip install -e '.[drone-models]'), "
                                "or leave it out of --plants")
    specs, tags = [], []
    for k in keys:
        for lv, by_model in levels_specs(k, members, qp).items():
            for m, runs in by_model.items():
                specs += runs
                tags += [(k, lv, m)] * len(runs)
    t0 = time.perf_counter()
    results = sweep(specs, out_dir, jobs=jobs, progress=progress, **sweep_kwargs)
    wall = time.perf_counter() - t0
    grouped: dict = {k: {} for k in keys}
    for (k, lv, m), r in zip(tags, results):
        grouped[k].setdefault((lv, m), []).append(r)
    out = {"scenario": LEVELS_SCENARIO, "controller": LEVELS_CONTROLLER, "members": members, "levels": list(LEVELS),
           "plants": {k: summarize_levels(k, grouped[k]) for k in keys}, "runs": len(results),
           "code_version": code_version(), "qp": qp,
           "command": f"pinnmpc levels --out {out_dir} --members {members} --plants {','.join(keys)}"
                      + ("" if qp == "osqp" else f" --qp {qp}"),
           "wall_time_s": wall, "date": time.strftime("%Y-%m-%d")}
    path = write_json(Path(out_dir) / "levels.json", out)
    if publish:
        (Path(models_dir) / LEVELS_DIR).mkdir(exist_ok=True)
        shutil.copyfile(path, Path(models_dir) / LEVELS_DIR / "levels.json")
    return out


def _mm(v) -> str:
    return "–" if v is None else f"{1e3 * v:.1f}"


def _x(v) -> str:
    return "" if v is None else f" ({v:.2f}x)"


def format_levels(out: dict) -> str:
    """The study as plain text: one block per plant, one line per level and model."""
    lines = [f"{out['scenario']} with the {out['controller'].upper()}, {out['members']} members per row"]
    for p in out["plants"].values():
        lines.append(f"\n{p['label']} ({p['vehicle']}, {p['scenario']}):")
        for r in p["rows"]:
            s = r["ensemble"]
            ci = s["median_ci95"]
            ci_txt = "" if ci is None else f" ({_mm(ci[0])}-{_mm(ci[1])})"
            solve = r["solve_ms_median"]
            lines.append(f"  {r['level']:6s} {r['model']:8s} {_mm(s['median'])} mm{ci_txt}{_x(r['rmse_vs_wrench'])}, "
                          f"crashes {s['crashes']}/{s['runs']}, solve {'–' if solve is None else f'{solve:.1f}'} ms"
                          f"{_x(r['solve_vs_wrench'])}")
    return "\n".join(lines)
