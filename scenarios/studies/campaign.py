"""The main job (``pinnmpc run``): open-loop tables, Fisher bounds, the closed-loop sweep, the report.

Layout of a results folder ``DIR``::

    DIR/provenance.json     versions, machine, git commit, model hashes, seeds, command, wall times
    DIR/fisher.json         Fisher information / CRLB table (as ``pinnmpc fisher --json``, with the SHA-256 of
                            sim/'s code); reused from an earlier run or from models/fisher.json when the code
                            is the same
    DIR/evaluation.json     Tables I, II and VI of the shipped models and the identification study's (as
                            ``pinnmpc evaluate --json``, with the SHA-256 of its inputs); reused from an earlier
                            run or from models/evaluation.json when models and code are the same
    DIR/ablation.json       Table III (copied from models/ablation.json, produced by ``pinnmpc ablation``)
    DIR/study.json          the zoo's dose-response study (copied from models/zoo/study.json, produced by
                            ``pinnmpc study``; it flies 729 runs, more than the main job's time allows)
    DIR/study_ekf.json      the same study's ensembles flown with the state estimator (models/zoo/study_ekf.json,
                            ``pinnmpc study --estimator ekf``)
    DIR/versus.json         learned models against the nominal equations on plants with unmodelled physics
                            (copied from models/versus/versus.json, produced by ``pinnmpc versus``; also too
                            long for the main job)
    DIR/versus_<level>.json the same study at the ctbr or ctatt command level (``pinnmpc versus --level``)
    DIR/levels.json         the three command levels side by side (copied from models/levels/levels.json, produced
                            by ``pinnmpc levels``)
    DIR/learn_<plant>.json  learning from flown flights (copied from models/learn/<plant>/learn.json, produced by
                            ``pinnmpc learn --publish``; its final models fly in the main job's high-fidelity and
                            RotorPy runs)
    DIR/results.json        {"plan": ..., "runs": [one result per closed-loop run, as ``fly --json``]}
    DIR/runs/<id>.json      the same results, one file per run
    DIR/traces/<id>.npz     the trace of each run (t, x, x_ref, x_measured, u, u_command, rotor_speed, solve_s, ...)
    DIR/report.md, DIR/report.html, DIR/figures/*.png

Which runs (``main_plan``): every scenario of :func:`main_scenarios` (hover,
the figure-8 speed ladder, the random paths, the yaw turn, and the variants
of ``figure8-fast`` but ``+highfi``) with the SQP on the oracle, on every
shipped model where :data:`EVERY_MODEL_SCENARIOS` says so and on
:data:`SUBSET_MODELS` where :data:`SUBSET_SCENARIOS` does, and with the LQR
on the oracle; the LTV-MPC on the cases of its CI bounds
(:data:`LTV_SCENARIOS`, every model on ``figure8-fast``); ``figure8-fast``
once more with real-time timing, flown by the SQP with the oracle and
SUBSET_MODELS and by the LTV-MPC and the NMPC with the oracle
(:data:`REALTIME_SCENARIOS`); the high-fidelity plant's runs
(:func:`highfi_plan`) and those on other plants (:func:`plant_plan`); and the
disturbance and noise variants once more with the state estimator
(:func:`estimator_plan`). The plan is sized for the main job's 6 minutes on
the slower of two 2-core machines that differ by up to 2x.
An IPOPT solve takes 100-200 ms per control period on these 2-core machines
(600 periods a run), so the NMPC in ideal timing does not fit the main
job, not even with the oracle alone; ``full=True`` (``pinnmpc run --full``: every scenario,
the NMPC on all of them with every model, and the ensembles of
:data:`ENSEMBLE_SCENARIOS`) takes hours.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

from mpc.prediction.contract import declared_level, model_files
from sim.files import write_json
from sim.levels import DEFAULT_LEVEL, check_level
from sim.plants.named import rotorpy_available

from ..errors import ScenarioError
from ..sweeps.lock import locks_out_dir
from ..closed_loop.library import scenario_names
from ..closed_loop.runner import RunSpec, spec_dict
from ..sweeps.sweep import sweep

#: Scenarios the SQP flies with every shipped model in the default plan; on SUBSET_SCENARIOS it flies the oracle and
#: SUBSET_MODELS, on the plan's other scenarios the oracle alone (with ``full=True``, every model everywhere). These
#: are the cases the report's headline and the CI bounds compare models on; the rest (the speed ladder's middle
#: rungs, the random paths, the yaw turn, figure8-slow, the other variants) show the controller on the true
#: equations, and every model with ``--full`` (the zoo study has every model of its own on the ladder).
EVERY_MODEL_SCENARIOS = ("hover", "figure8-fast")
#: The shipped models (file names) that fly beside the oracle where the default plan does not fly every model but
#: compares a learned model with the true equations: the disturbance variants of SUBSET_SCENARIOS with and without
#: the state estimator, and the real-time runs. The paper's Proposed; a models folder without it uses its first
#: model. With ``full=True`` every model flies there (the main job's 6 minutes do not hold them all: Baseline alone
#: is about 40 s of its 2 cores there).
SUBSET_MODELS = ("proposed.onnx",)
#: Scenarios the SQP flies with the oracle and SUBSET_MODELS (every model with ``full=True``): the disturbances the
#: report's disturbance and estimator sections compare.
SUBSET_SCENARIOS = ("figure8-fast+payload", "figure8-fast+wind")
#: Scenarios the LTV-MPC flies in the main job (every scenario with ``full=True``): those of its CI bounds, with
#: every model on LTV_EVERY_MODEL_SCENARIOS (the headline's case) and the oracle alone on the others. The models'
#: other bound cases fly in the tests (``tests/test_bounds.py``) and with ``--scenarios`` (the bounds' scenarios,
#: :data:`scenarios.studies.bounds.BOUND_SCENARIOS`), from whose results ``pinnmpc bounds`` writes the bounds.
LTV_SCENARIOS = ("hover", "figure8-slow", "figure8-fast", "figure8-2.0s", "yaw-turn")
LTV_EVERY_MODEL_SCENARIOS = ("figure8-fast",)
#: Scenarios flown with real-time timing too, by REALTIME_CONTROLLERS: the SQP with the oracle and SUBSET_MODELS,
#: the LTV-MPC and the NMPC (which cannot meet the period: every call past the deadline) with the oracle alone;
#: every controller with every model with ``full``. Real-time runs fly one at a time after the others (their
#: charged compute time is measured on an idle machine), so each costs the job its whole wall time.
REALTIME_SCENARIOS = ("figure8-fast",)
REALTIME_CONTROLLERS = ("sqp", "ltv", "nmpc")
REALTIME_SUBSET = ("sqp",)
#: Ensembles of ``full=True``: these scenarios, flown by these controllers with every model from ENSEMBLE_MEMBERS
#: members each (:meth:`scenarios.closed_loop.library.Scenario.member`). 6 models x 2 controllers x 10 members on
#: figure8-fast
#: is about 280 worker-seconds, more than the default main job's budget leaves.
ENSEMBLE_SCENARIOS = ("figure8-fast",)
ENSEMBLE_CONTROLLERS = ("ltv", "sqp")
ENSEMBLE_MEMBERS = 10
#: The high-fidelity plant: these scenarios flown by HIGHFI_CONTROLLERS with the oracle and with the models of
#: HIGHFI_MODELS (paths under the models folder; those present), HIGHFI_MEMBERS ensemble members each on
#: figure8-fast+highfi and one run on hover+highfi. The models trained on the plant's own data
#: (``identification/*_highfi``) fly beside their twins trained on the nominal simulator's.
HIGHFI_SCENARIOS = {"hover+highfi": 1, "figure8-fast+highfi": 5}
#: Members per model on a high-fidelity scenario without ``full`` (``pinnmpc versus`` flies ten on each plant).
HIGHFI_DEFAULT_MEMBERS = 1
#: Without ``full``, the high-fidelity scenarios other than this one fly the oracle and the nominal equations only.
HIGHFI_EVERY_MODEL_SCENARIO = "figure8-fast+highfi"
HIGHFI_CONTROLLERS = ("sqp",)
HIGHFI_MODELS = ("proposed.onnx", "identification/proposed_highfi.onnx", "identification/hybrid_lag_highfi.onnx")
#: Sub-folder of the models folder with the models of the identification study (Tables II and VI: other data
#: cells, other seeds, a recipe variant); evaluated by the main job beside the shipped models, flown only on the
#: high-fidelity plant.
IDENTIFICATION_DIR = "identification"
#: Other plants in the main job: this scenario flown by this controller on RotorPy, with the oracle (the rigid-body
#: equations, which are RotorPy's own on ``rotorpy-ideal``), the nominal equations and every shipped model; and the
#: nominal equations flying the other shipped vehicles (RotorPy's presets) on our simulator and on RotorPy.
PLANT_SCENARIO = "figure8-fast"
PLANT_CONTROLLER = "sqp"
#: The shipped models flown on the other plants without ``full`` (all of them with it; ``pinnmpc versus`` has every
#: model trained on RotorPy's data there).
PLANT_DEFAULT_MODELS = ("proposed.onnx",)
PLANT_VEHICLES = ("hummingbird", "crazyflie")
#: With the state estimator as well: the variants of these kinds (disturbances and sensor noise, which the
#: estimator is for) flown by ESTIMATOR_CONTROLLER beside their runs without it, and
#: OFFSET_FREE_SCENARIOS (the hover cases an estimated disturbance should leave without offset) with the oracle
#: both ways (every shipped model's offset-free hover is a test: the main job's 6 minutes do not hold them all).
ESTIMATOR_VARIANTS = ("payload", "wind", "steadywind", "noise")
#: Of those, the ones flown with the models of their twins without the estimator (the oracle and SUBSET_MODELS);
#: the others with the oracle only (the main job's 6 minutes).
ESTIMATOR_VARIANTS_SUBSET = ("payload", "wind")
ESTIMATOR_CONTROLLER = "sqp"
OFFSET_FREE_SCENARIOS = ("hover+payload", "hover+steadywind")
#: Time-dependent provenance fields (excluded when two runs are compared).
PROVENANCE_TIMING = ("started", "finished", "wall_time_s", "stage_seconds")


def shipped_models(models_dir) -> list[str]:
    """Paths of the model files ``*.onnx`` (not ``*.jac.onnx``) in ``models_dir``, sorted."""
    d = Path(models_dir)
    if not d.is_dir():
        raise ScenarioError(f"models folder {str(d)!r} does not exist")
    files = [str(p) for p in model_files(d)]
    if not files:
        raise ScenarioError(f"no .onnx models in {str(d)!r}")
    return files


def identification_models(models_dir) -> list[str]:
    """Paths of the identification study's models (``IDENTIFICATION_DIR`` under ``models_dir``; none if it is absent)."""
    d = Path(models_dir) / IDENTIFICATION_DIR
    return [str(p) for p in model_files(d)] if d.is_dir() else []


def main_scenarios(full: bool = False) -> list[str]:
    """Scenarios of the main job: all but the variants of ``hover`` and ``figure8-slow`` and the ``+highfi`` ones.

    With ``full``, all of them. The disturbance variants of ``figure8-fast`` stay: they show every disturbance
    on the case every section of the report compares. Those of ``hover`` (about 40 s of the main job) and of
    ``figure8-slow`` (twice as long) do not fit its 6 minutes; the ``+highfi`` cases fly in
    :func:`highfi_plan`.
    """
    names = scenario_names()
    if full:
        return names
    return [n for n in names if "+" not in n or (n.startswith("figure8-fast+") and not n.endswith("+highfi"))]


#: The SQP's scheme for the learning studies' final models on RotorPy in :func:`plant_plan`.
LEARNED_PLANT_SCHEME = "rti"


def plant_plan(models_dir="models", full: bool = False) -> list[RunSpec]:
    """The main job's runs on other plants and vehicles (see :data:`PLANT_SCENARIO`); none without RotorPy."""
    if not rotorpy_available():
        return []
    models = shipped_models(models_dir)
    if not full:
        models = [m for m in models if Path(m).name in PLANT_DEFAULT_MODELS]
    sc, c = PLANT_SCENARIO, PLANT_CONTROLLER
    specs = [RunSpec(sc, c, m, plant="rotorpy-ideal") for m in ["oracle", *models]]
    specs += [RunSpec(sc, c, m, plant="rotorpy") for m in ["nominal", *models]]
    specs += [RunSpec(sc, c, "nominal", plant=pl, vehicle=v) for v in PLANT_VEHICLES for pl in ("sim", "rotorpy")]
    # the final model of each shipped learning study on RotorPy, flying that study's vehicle, with the real-time
    # iteration: these 16-state models are the slowest to linearize, and the iterating SQP's periods run past 10 ms
    from .learn import LEARN_PLANTS

    specs += [RunSpec(sc, c, m, plant=lp.plant, vehicle=lp.vehicle, scheme=LEARNED_PLANT_SCHEME)
              for key, lp in LEARN_PLANTS.items() if lp.plant == "rotorpy" for m in learned_models(models_dir, key)]
    return specs


def learned_models(models_dir, plant: str) -> list[str]:
    """The final model of the shipped learning study on ``plant`` (a key of
    :data:`scenarios.studies.learn.LEARN_PLANTS`):
    ``[path]``, or ``[]`` where none is shipped (``models/learn/<plant>/learn.json`` names it; ``pinnmpc learn
    --publish``)."""
    from .learn import LEARN_DIR

    summary = Path(models_dir) / LEARN_DIR / plant / "learn.json"
    if not summary.is_file():
        return []
    path = summary.parent / f"{json.loads(summary.read_text())['final_model']}.onnx"
    return [str(path)] if path.is_file() else []


def _on(spec: RunSpec, plant: str, vehicle: str | None) -> RunSpec | None:
    """``spec`` flown on ``plant`` with ``vehicle``: the oracle becomes the nominal equations where the plant has
    no known equations; a high-fidelity scenario (a set-up of our simulator) is dropped elsewhere."""
    import dataclasses

    from sim.plants.named import KNOWN_EQUATIONS

    from ..closed_loop.library import get_scenario

    if plant != "sim" and get_scenario(spec.scenario).high_fidelity:
        return None
    model = "nominal" if spec.model == "oracle" and plant not in KNOWN_EQUATIONS else spec.model
    return dataclasses.replace(spec, model=model, plant=plant, vehicle=vehicle)


def _variant(name: str) -> str | None:
    return name.split("+", 1)[1] if "+" in name else None


def subset_models(models: list[str]) -> list[str]:
    """Of the model paths ``models``, those named in :data:`SUBSET_MODELS`, or the first one if none is."""
    named = [m for m in models if Path(m).name in SUBSET_MODELS]
    return named or list(models[:1])


def estimator_plan(models: list[str], names: list[str], scenarios_given: bool,
                   subset: list[str] | None = None) -> list[RunSpec]:
    """The runs flown with the state estimator beside their twins without it (see :data:`ESTIMATOR_VARIANTS`).

    ``models`` starts with the oracle; the variants of :data:`ESTIMATOR_VARIANTS_SUBSET` fly with ``subset``
    (default: ``models``), the others with the oracle.
    """
    subset = models if subset is None else subset
    cases = [sc for sc in names if _variant(sc) in ESTIMATOR_VARIANTS]
    specs = [RunSpec(sc, ESTIMATOR_CONTROLLER, m, estimator="ekf") for sc in cases
             for m in (subset if _variant(sc) in ESTIMATOR_VARIANTS_SUBSET else models[:1])]
    if not scenarios_given:       # the offset-free hovers with the oracle, both ways, where the plan has none
        hovers = [sc for sc in OFFSET_FREE_SCENARIOS if sc not in names]
        specs += [RunSpec(sc, ESTIMATOR_CONTROLLER, models[0], estimator=e) for sc in hovers for e in ("ekf", "none")]
    return specs


def at_level(specs: list[RunSpec], level: str) -> list[RunSpec]:
    """``specs`` flown at the command ``level`` (:mod:`sim.levels`): a model file that declares another level is
    left out (:func:`left_out_at_level` names them), the oracle becomes the nominal equations where it does not
    exist at that level (any plant but ``sim``'s nominal set-up), and runs made equal by that are flown once."""
    import dataclasses

    from mpc.prediction.models import is_equation_model, level_oracle_exists

    from ..closed_loop.library import get_scenario

    check_level(level)
    out, seen, levels = [], set(), {}
    for s in specs:
        if not is_equation_model(s.model):
            if s.model not in levels:
                levels[s.model] = declared_level(s.model)
            if levels[s.model] != level:
                continue
        model = s.model
        if model == "oracle" and not level_oracle_exists(s.plant, level, get_scenario(s.scenario).high_fidelity):
            model = "nominal"
        t = dataclasses.replace(s, model=model, level=level)
        if t.run_id not in seen:
            seen.add(t.run_id)
            out.append(t)
    return out


def left_out_at_level(models: list[str], level: str) -> dict[str, str]:
    """Of the model files ``models``, those that declare another level than ``level``: ``{path: their level}``."""
    return {m: lv for m in models if (lv := declared_level(m)) != level}


def main_plan(models_dir="models", full: bool = False, scenarios: list[str] | None = None, plant: str = "sim",
              vehicle: str | None = None, estimator: str | None = None, qp: str = "osqp",
              level: str = DEFAULT_LEVEL) -> list[RunSpec]:
    """The closed-loop runs of the main job (see the module docstring).

    With another ``plant`` or ``vehicle`` the same runs fly there (the oracle becoming the nominal equations
    where the plant has no known equations, without the high-fidelity scenarios), and the runs of
    :func:`plant_plan` are left out. With ``estimator`` (``"none"`` or ``"ekf"``) every run flies with that
    setting; by default (None) every run flies without an estimator and the disturbance and noise cases with
    and without (:func:`estimator_plan`). ``qp``: the QP solver of every run
    (:attr:`scenarios.closed_loop.runner.RunSpec.qp`),
    which the LTV-MPC's and the SQP's runs use and the others leave alone. ``level``: every run flies at that
    command level (:func:`at_level`: the models of another level are left out).
    """
    if level != DEFAULT_LEVEL:
        return at_level(main_plan(models_dir, full, scenarios, plant, vehicle, estimator, qp), level)
    if qp != "osqp":
        import dataclasses

        return [dataclasses.replace(s, qp=qp) for s in main_plan(models_dir, full, scenarios, plant, vehicle,
                                                                   estimator)]
    if estimator is not None:
        from ..closed_loop.runner import ESTIMATORS

        if estimator not in ESTIMATORS:
            raise ScenarioError(f"estimator must be one of {', '.join(ESTIMATORS)}; found {estimator!r}")
        import dataclasses

        out, seen = [], set()
        for s in main_plan(models_dir, full, scenarios, plant, vehicle):
            t = dataclasses.replace(s, estimator=estimator)
            if t.run_id not in seen:
                seen.add(t.run_id)
                out.append(t)
        return out
    if plant != "sim" or vehicle is not None:
        base = main_plan(models_dir, full, scenarios)
        return [t for t in (_on(s, plant, vehicle) for s in base if s.plant == "sim" and s.vehicle is None)
                if t is not None]
    shipped = shipped_models(models_dir)
    models = ["oracle"] + shipped
    # Scenarios asked for by name fly with every model; so does everything with full.
    everything = full or scenarios is not None
    subset = models if everything else ["oracle"] + subset_models(shipped)
    names = main_scenarios(full) if scenarios is None else list(scenarios)
    specs = []
    for sc in names:
        every = everything or sc in EVERY_MODEL_SCENARIOS
        ltv = full or sc in LTV_EVERY_MODEL_SCENARIOS or (scenarios is not None and sc in LTV_SCENARIOS)
        for m in models:
            # The NMPC in ideal timing only with full: an IPOPT run costs about 90 s of a core (the oracle on
            # figure8-fast), a sixth of the default sweep. It flies REALTIME_SCENARIOS in real time.
            if full:
                specs.append(RunSpec(sc, "nmpc", m))
            if every or m == "oracle" or (sc in SUBSET_SCENARIOS and m in subset):
                specs.append(RunSpec(sc, "sqp", m))
            if ltv or (m == "oracle" and sc in LTV_SCENARIOS):
                specs.append(RunSpec(sc, "ltv", m))
        specs.append(RunSpec(sc, "lqr", "oracle"))
    for sc in names:
        if sc in REALTIME_SCENARIOS:
            specs += [RunSpec(sc, c, m, timing="realtime") for c in REALTIME_CONTROLLERS for m in models
                      if everything or m == "oracle" or (c in REALTIME_SUBSET and m in subset)]
    if full:
        specs += [RunSpec(sc, c, m, member=k) for sc in names if sc in ENSEMBLE_SCENARIOS
                  for c in ENSEMBLE_CONTROLLERS for m in models for k in range(ENSEMBLE_MEMBERS)]
    have = {s.run_id for s in specs}
    specs += [s for s in estimator_plan(models, names, scenarios is not None, subset) if s.run_id not in have]
    if scenarios is None:
        have = {s.run_id for s in specs}
        specs += [s for s in highfi_plan(models_dir, full) + plant_plan(models_dir, full) if s.run_id not in have]
    return specs


def highfi_plan(models_dir="models", full: bool = False) -> list[RunSpec]:
    """The high-fidelity plant's runs (see :data:`HIGHFI_SCENARIOS`): ensembles where a scenario has members
    (:data:`HIGHFI_DEFAULT_MEMBERS` without ``full``)."""
    d = Path(models_dir)
    # The oracle is the plant's true equations (lag, drag, gyro); the nominal rigid-body equations fly beside it.
    equations = ["oracle", "nominal"]
    models = equations + [str(d / m) for m in HIGHFI_MODELS if (d / m).is_file()]
    models += learned_models(models_dir, "highfi")    # the learning study's final model (its report's cases)
    specs = []
    for sc, members in HIGHFI_SCENARIOS.items():
        members = members if full else min(members, HIGHFI_DEFAULT_MEMBERS)
        for c in HIGHFI_CONTROLLERS:
            for m in models if full or sc == HIGHFI_EVERY_MODEL_SCENARIO else equations:
                if members == 1:
                    specs.append(RunSpec(sc, c, m))
                else:
                    specs += [RunSpec(sc, c, m, member=k) for k in range(members)]
    return specs


def _versions() -> dict:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for pkg in ("numpy", "scipy", "casadi", "onnx", "onnxruntime", "osqp", "control", "matplotlib"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = None
    return out


def _git_commit() -> str | None:
    try:
        r = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                           cwd=Path(__file__).resolve().parent)
        return r.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def provenance(models_dir) -> dict:
    """Versions, machine, commit, model hashes and the manifest's training seeds."""
    from ..closed_loop.record import file_sha256

    models = {Path(m).stem: file_sha256(m) for m in shipped_models(models_dir) + identification_models(models_dir)}
    seeds = {}
    for manifest in (Path(models_dir) / "manifest.json", Path(models_dir) / IDENTIFICATION_DIR / "manifest.json"):
        if not manifest.is_file():
            continue
        for name, entry in json.loads(manifest.read_text()).items():
            if isinstance(entry, dict):
                seeds[name] = {"seed": entry.get("seed"), "command": entry.get("command"),
                               "data_seed": (entry.get("data") or {}).get("seed")}
    return {"versions": _versions(), "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                                                 "processor": platform.processor() or platform.machine()},
            "git_commit": _git_commit(), "model_sha256": models, "training": seeds,
            "command": " ".join(["pinnmpc"] + sys.argv[1:]) if sys.argv else None}


def precompile_job(jobs: int, evaluation: bool = True, fisher: bool = True) -> int:
    """Compile the CasADi functions the job will need (the sensitivities of the Fisher, evaluation and estimator
    stages, the lag-aware estimator's, the oracles' steps and Jacobians), ``jobs`` compilers at a time; those in
    the cache are skipped. Without ``evaluation`` (a stored evaluation is reused) the evaluation's are left out,
    without ``fisher`` (a stored Fisher table is reused) the Fisher stage's.

    Without this they are compiled one after the other where first used, the oracle's by each sweep worker at
    once. Returns how many were compiled.
    """
    from mpc.prediction.models import numeric_sources
    from sim.equations.compiled import precompile
    from sim.identification.fisher import FISHER_SENSITIVITIES, USED_SENSITIVITIES, sensitivity_function
    from sim.params import QuadParams

    from sim.identification.motor_lag import lag_sensitivity_function
    from sim.vehicles.vehicle import load_vehicle

    p = QuadParams()
    actuated = list(numeric_sources(p, load_vehicle(None).fidelity))     # the oracle of the +highfi scenarios
    used = USED_SENSITIVITIES if evaluation else FISHER_SENSITIVITIES if fisher else ()
    lag = [(lag_sensitivity_function(p, s), "batch") for s in (True, False)] if evaluation else []
    sens = [(sensitivity_function(p, i, s), "batch") for i, s in used]
    return precompile(sens + list(numeric_sources(p)) + actuated + lag, jobs)


def _stored(path) -> dict | None:
    """A stored JSON result that carries the ``inputs_sha256`` it was computed from, or None (absent, unreadable or
    without one)."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and "inputs_sha256" in data else None


#: A stored evaluation of the shipped models (see :func:`reusable_evaluation`), under the models folder.
SHIPPED_EVALUATION = "evaluation.json"
#: A stored Fisher table (see :func:`reusable_fisher`), under the models folder.
SHIPPED_FISHER = "fisher.json"


def fisher_key() -> str:
    """The key of a Fisher table: the digest of ``sim/``'s code, the only code it reads (it reads no file), but the
    flight-log import, which it does not import (:data:`pinn.evaluate.KEY_EXCLUDES`)."""
    from pinn.evaluate import KEY_EXCLUDES
    from sim.files import source_digest

    return source_digest(("sim",), exclude=KEY_EXCLUDES).hexdigest()


def _reusable(paths, key) -> tuple[Path, dict] | None:
    """The first of ``paths`` holding a stored result (:func:`_stored`) whose ``inputs_sha256`` is ``key()``:
    ``(its path, its content)``, or None. ``key`` is computed at most once, and only if a stored result is found."""
    wanted = None
    for path in paths:
        data = _stored(path)
        if data is None:
            continue
        wanted = key() if wanted is None else wanted
        if data["inputs_sha256"] == wanted:
            return path, data
    return None


def reusable_fisher(out_dir, models_dir) -> tuple[Path, dict] | None:
    """A stored Fisher table the main job can reuse: ``(its path, its content)``, or None.

    The table is deterministic: one stored with the key of the same code (:func:`fisher_key`) is what it would
    compute again. Looked for in ``out_dir`` (an earlier run of the job) and then in ``models_dir``
    (:data:`SHIPPED_FISHER`, kept current by a test).
    """
    return _reusable((Path(out_dir) / "fisher.json", Path(models_dir) / SHIPPED_FISHER), fisher_key)


def reusable_evaluation(out_dir, models_dir, folders) -> tuple[Path, dict] | None:
    """A stored evaluation of ``folders`` that the main job can reuse: ``(its path, its content)``, or None.

    The evaluation is deterministic: one stored with the key of the same models and code
    (:func:`pinn.evaluate.evaluation_key`) is what it would compute again. Looked for in ``out_dir`` (an earlier
    run of the job) and then in ``models_dir`` (:data:`SHIPPED_EVALUATION`, kept current by a test).
    """
    from pinn.evaluate import EFFECT_SPECS, evaluation_key

    return _reusable((Path(out_dir) / "evaluation.json", Path(models_dir) / SHIPPED_EVALUATION),
                     lambda: evaluation_key(folders, EFFECT_SPECS))


@locks_out_dir
def run_main_job(out_dir, models_dir="models", jobs: int | None = None, full: bool = False,
                 progress: bool = True, scenarios: list[str] | None = None, engine: str = "process",
                 address: str | None = None, resume: bool = True, plant: str = "sim",
                 vehicle: str | None = None, estimator: str | None = None, qp: str = "osqp",
                 report=None, level: str = DEFAULT_LEVEL) -> dict:
    """Run everything and build the report; returns ``{"results": [...], "report": path}``.

    ``report(out_dir) -> path`` builds the report once the runs are saved (the command line passes
    :func:`reports.build_report`: the reports sit above this layer); without it ``"report"`` is None.

    ``qp``: the QP solver of every LTV-MPC and SQP run (:attr:`scenarios.closed_loop.runner.RunSpec.qp`; ``"osqp"`` or
    ``"daqp"``); the NMPC's and the LQR's runs are the same either way.

    ``engine``, ``address`` and ``resume`` are those of :func:`scenarios.sweeps.sweep.sweep`: closed-loop runs already
    saved in ``out_dir`` with the same spec, seed, model file and code are reused unless ``resume`` is False, and
    so is an open-loop evaluation of the same models by the same code (:func:`reusable_evaluation`).
    """
    out = Path(out_dir)
    jobs = max(1, os.cpu_count() or 1) if jobs is None else jobs
    specs = main_plan(models_dir, full, scenarios, plant, vehicle, estimator, qp, level)   # validates names, files
    left_out = {} if level == DEFAULT_LEVEL else left_out_at_level(shipped_models(models_dir), level)
    if progress and left_out:
        print(f"{len(left_out)} models take commands at another level than {level!r}, so they are left out: "
              + ", ".join(f"{Path(m).stem} ({lv})" for m, lv in left_out.items()), file=sys.stderr)
    if progress and plant == "sim" and vehicle is None and scenarios is None and not rotorpy_available():
        print("RotorPy is not installed: the runs on other plants are left out (pip install -e '.[rotorpy]')",
              file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    stages: dict[str, float] = {}
    t_start = time.time()
    prov = {"started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t_start)), "jobs": jobs, "full": full,
            **provenance(models_dir)}

    def stage(name):
        if progress:
            print(f"[{time.time() - t_start:6.0f} s] {name}", file=sys.stderr, flush=True)
        stages[name] = time.time()

    folders = [models_dir] + ([Path(models_dir) / IDENTIFICATION_DIR] if identification_models(models_dir) else [])
    reused = reusable_evaluation(out, models_dir, folders) if resume else None
    fisher = reusable_fisher(out, models_dir) if resume else None
    stage("compiling the analytic model's derivatives (once per machine)")
    precompile_job(jobs, evaluation=reused is None, fisher=fisher is None)
    if fisher is not None:
        stage(f"Fisher information and Cramer-Rao bounds: reused {fisher[0]} (same code)")
        if fisher[0] != out / "fisher.json":
            write_json(out / "fisher.json", fisher[1])
        prov["fisher"] = f"reused {fisher[0]}"
    else:
        stage("Fisher information and Cramer-Rao bounds")
        from sim.identification.fisher import fisher_table
        write_json(out / "fisher.json", {**fisher_table(progress=False), "inputs_sha256": fisher_key()})
        prov["fisher"] = "computed"
    if reused is None:
        stage("open-loop evaluation and identification (Tables I, II, VI; the classical estimator on each dataset)")
        from pinn.evaluate import EFFECT_SPECS, evaluate_dir, evaluation_key
        result = evaluate_dir(folders, progress=progress, jobs=jobs, extra_specs=EFFECT_SPECS)
        write_json(out / "evaluation.json", {**result, "inputs_sha256": evaluation_key(folders, EFFECT_SPECS)})
        prov["evaluation"] = "computed"
    else:
        source, result = reused
        stage(f"open-loop evaluation and identification: reused {source} (same models and code)")
        if source != out / "evaluation.json":
            write_json(out / "evaluation.json", result)
        prov["evaluation"] = f"reused {source}"
    ablation = Path(models_dir) / "ablation.json"
    if ablation.is_file():
        shutil.copyfile(ablation, out / "ablation.json")
    for src, name in ((Path(models_dir) / "zoo" / "study.json", "study.json"),
                      (Path(models_dir) / "zoo" / "study_ekf.json", "study_ekf.json"),
                      (Path(models_dir) / "versus" / "versus.json", "versus.json"),
                      (Path(models_dir) / "versus" / "versus_ctbr.json", "versus_ctbr.json"),
                      (Path(models_dir) / "versus" / "versus_ctatt.json", "versus_ctatt.json"),
                      (Path(models_dir) / "levels" / "levels.json", "levels.json")):
        if src.is_file():
            shutil.copyfile(src, out / name)
        elif (out / name).is_file():
            (out / name).unlink()     # a stale copy would be reported as this run's
    for stale in out.glob("learn_*.json"):
        stale.unlink()
    for src in sorted((Path(models_dir) / "learn").glob("*/learn.json")):
        shutil.copyfile(src, out / f"learn_{src.parent.name}.json")
    where = (f"the Ray cluster at {address}" if address else f"a local Ray instance with {jobs} CPUs") \
        if engine == "ray" else f"{jobs} processes"
    stage(f"closed-loop sweep: {len(specs)} runs on {where}")
    results = sweep(specs, out, jobs=jobs, progress=progress, engine=engine, address=address, resume=resume)
    from sim.vehicles.vehicle import load_vehicle

    write_json(out / "results.json", {"plan": {"full": full, "models_dir": str(models_dir), "plant": plant, "qp": qp,
                                           **({} if level == DEFAULT_LEVEL else
                                              {"level": level, "left_out": {Path(m).stem: lv
                                                                            for m, lv in left_out.items()}}),
                                           "vehicle": None if vehicle is None else load_vehicle(vehicle).name,
                                           "rotorpy": rotorpy_available(),
                                           "specs": [spec_dict(s) for s in specs]}, "runs": results})
    stage("report")

    def write_provenance(t_end, done):
        """provenance.json with the wall time to ``t_end`` and the seconds of the stages in ``done``."""
        prov.update({"finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t_end)),
                     "wall_time_s": t_end - t_start,
                     "stage_seconds": {n: (stages[done[i + 1]] if i + 1 < len(done) else t_end) - stages[n]
                                       for i, n in enumerate(done)}})
        write_json(out / "provenance.json", prov)

    # The report shows the wall times up to its own build (building it twice to include that would cost its
    # 15 s again); provenance.json then gets the whole job's, and `pinnmpc report` shows those.
    write_provenance(stages["report"], list(stages)[:-1])
    built = None if report is None else report(out)
    write_provenance(time.time(), list(stages))
    return {"results": results, "report": built}
