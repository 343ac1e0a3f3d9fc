"""``pinnmpc fly``, ``pinnmpc run`` and ``pinnmpc report``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sim.cli import add_plant_options
from sim.files import check_writable, write_json, write_npz, write_text

from .sweeps.engines import ENGINES

#: Fields printed by ``pinnmpc fly``, in order (names other tools rely on).
FLY_FIELDS = ("scenario", "controller", "qp", "model", "plant", "vehicle", "level", "timing", "estimator", "rmse_position_m", "max_position_error_m", "crashed",
              "crash_time_s", "solve_ms", "deadline_misses", "deadline_fallbacks", "solver_failures",
              "fallbacks")


#: How to install the dense QP solver (the optional extra ``dense``).
DENSE_INSTALL = 'python -m pip install -e ".[dense]"'


def _qp_option(p, what: str) -> None:
    """``--qp``: the QP solver of every LTV-MPC and SQP the command builds (``what`` says which those are)."""
    from mpc.controllers.dense_qp import QP_SOLVERS

    p.add_argument("--qp", choices=QP_SOLVERS, default="osqp",
                   help=f"QP solver of {what}: osqp (sparse, the default) or daqp (the QP condensed onto the "
                        f"inputs and solved by a dense active-set solver, usually faster; the optional extra "
                        f"dense: {DENSE_INSTALL}). A run records it, and a saved run is reused only by the same "
                        f"solver")


def _level_option(p, every: str = "") -> None:
    """``--level``: the command level the controllers send and the plants take (``every``: what the option does to
    a command that flies many runs)."""
    from sim.levels import DEFAULT_LEVEL, LEVELS

    p.add_argument("--level", choices=LEVELS, default=DEFAULT_LEVEL,
                   help="command level: wrench (thrust and body torques, the default); ctbr (thrust and body rates) "
                        "or ctatt (thrust, roll, pitch and yaw rate), flown through the vehicle's inner loop (its "
                        "[inner_loop] table, docs/levels.md); a model file must declare the level it takes" + every)


def _check_qp(qp: str) -> None:
    """``--qp daqp`` without DAQP installed: a user-input error naming the option and the install command, raised
    before anything is loaded, written or flown."""
    if qp == "daqp":
        from mpc.controllers.dense_qp import daqp_installed

        if not daqp_installed():
            raise ValueError(f"--qp daqp needs DAQP, which is not installed (the optional extra dense): "
                             f"{DENSE_INSTALL}; or give --qp osqp")


def _sweep_options(p, published: str, where: str) -> None:
    """The options of a study that flies a resumable sweep and publishes its JSON file next to its models."""
    p.add_argument("--jobs", type=int, default=None, help="worker processes (default: number of CPUs)")
    p.add_argument("--engine", choices=ENGINES, default="process")
    p.add_argument("--address", default=None, metavar="ADDR", help="Ray cluster (with --engine ray)")
    p.add_argument("--fresh", action="store_true", help="fly every run again instead of reusing saved ones")
    p.add_argument("--no-publish", action="store_true", help=f"do not copy {published} into {where}")


def register(sub) -> None:
    """Add this package's subcommands to the ``pinnmpc`` parser."""
    from mpc.controllers.factory import CONTROLLERS, HORIZON

    from .closed_loop.library import scenario_names
    from .closed_loop.runner import ESTIMATORS, MAX_HORIZON, TIMINGS

    names = scenario_names()
    p = sub.add_parser("realdata", help="the real-data study on a copy of the nano-drone benchmark",
                       description="Import the benchmark's raw flights, hold the melon flights out, identify the "
                                   "vehicle and train the learned models on the training flights, choose on the "
                                   "validation flights, evaluate every model under the benchmark's protocol and fly "
                                   "the best flyable learned model (docs/real-flights.md).")
    p.add_argument("--logs", required=True, type=Path, metavar="DIR",
                   help="the benchmark's root (branch model_export), a copy with its data/real/ layout, or a folder "
                        "of your own logs (.parquet, .csv; see --format)")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (realdata.json, .md)")
    p.add_argument("--vehicle", default="crazyflie-brushless", metavar="NAME|FILE.toml",
                   help="the vehicle (default crazyflie-brushless, the benchmark's stated values)")
    p.add_argument("--plants", default="sim,rotorpy", metavar="LIST",
                   help="plants of the closed-loop check, comma-separated (default sim,rotorpy; 'none': no flight)")
    p.add_argument("--format", default="nanodrone-raw", metavar="NAME|FILE.toml",
                   help="format of the logs (default nanodrone-raw, the benchmark's raw Parquet files)")
    p.add_argument("--test", default="melon*", metavar="PATTERNS",
                   help="name patterns of the held-out test flights, comma-separated (default melon*)")
    p.add_argument("--val", default=None, metavar="PATTERNS",
                   help="name patterns of the validation flights, where every choice is made (default: run 4 of "
                        "multisine, random1 and random2 and square run 5); the other flights train")
    p.add_argument("--learn", default="full", choices=("full", "quick", "none"),
                   help="training budget of the learned models (default full, about 10 minutes on 2 cores; quick: "
                        "seconds, for a trial run; none: physics models only)")
    p.set_defaults(handler=cmd_realdata)

    p = sub.add_parser("fly", help="fly one closed-loop run and print its metrics",
                       description="One closed-loop run: a scenario flown on a plant (by default this project's "
                                   "simulator) by a controller using a prediction model. Scenarios: "
                                   + ", ".join(names) + ", or a scenario file (docs/scenario-files.md).")
    p.add_argument("--model", required=True, metavar="{oracle,nominal,FILE.onnx}",
                   help="'oracle' (the plant's own equations, where known), 'nominal' (the rigid-body equations "
                        "with the vehicle's values) or an ONNX model that passes check-model")
    p.add_argument("--controller", required=True, choices=CONTROLLERS)
    p.add_argument("--scenario", required=True, metavar="NAME|FILE.toml", help="scenario name (see above) or file")
    add_plant_options(p)
    p.add_argument("--seed", type=int, default=None, help="seed of noise and gusts (default: the scenario's, 0)")
    p.add_argument("--horizon", type=_horizon_arg, default=HORIZON,
                   help=f"MPC horizon in steps of 10 ms, 1 to {MAX_HORIZON} (default {HORIZON})")
    p.add_argument("--timing", choices=TIMINGS, default="ideal",
                   help="ideal: each input applies at once (deterministic, default); realtime: it applies after "
                        "the call's measured wall time, rounded up to 1 ms, and a call that overruns the 10 ms "
                        "period keeps the previous input until it returns")
    p.add_argument("--estimator", choices=ESTIMATORS, default="none",
                   help="none: the controller sees the true state (plus the scenario's noise; default); ekf: it "
                        "sees an extended Kalman filter's estimate from motion capture and an IMU, on its own "
                        "model, with a disturbance estimate (docs/estimation.md)")
    _qp_option(p, "the ltv and sqp controllers (the others solve no QP)")
    _level_option(p)
    p.add_argument("--scheme", choices=("sqp", "rti"), default=None,
                   help="the sqp controller's scheme: sqp (it iterates) or rti (the real-time iteration: one "
                        "prepared QP a period, the next one prepared after the input is out; docs/realtime.md); "
                        "default: rti with --timing realtime, sqp in ideal timing")
    p.add_argument("--json", metavar="FILE", type=Path, default=None, help="write the result as JSON")
    p.add_argument("--trace", metavar="FILE.npz", type=Path, default=None, help="write the trace arrays")
    p.add_argument("--plot", metavar="FILE.png", type=Path, default=None, help="plot path, height, error, inputs")
    p.set_defaults(handler=cmd_fly)

    p = sub.add_parser("run", help="the main job: Tables I-III, every closed-loop run, the report",
                       description="Evaluates the shipped models (Tables I-III, Fisher bounds), flies every "
                                   "base scenario (hover, the figure-8 speed ladder, random paths, the yaw turn) "
                                   "and the disturbance variants of figure8-fast with the real-time SQP (oracle "
                                   "and every shipped model) and the LQR, the LTV-MPC on its CI-bound cases, "
                                   "figure8-fast with real-time timing (SQP, LTV-MPC and NMPC, every model), the "
                                   "high-fidelity plant and, with RotorPy installed, other plants and vehicles; "
                                   "then writes DIR/report.md and DIR/report.html. About 8 minutes on 2 cores "
                                   "(--full: hours).")
    p.add_argument("--out", type=Path, default=Path("results/main"), help="results folder (default results/main)")
    p.add_argument("--jobs", type=int, default=None, help="worker processes (default: number of CPUs)")
    p.add_argument("--models", type=Path, default=Path("models"), help="folder of ONNX models (default models)")
    p.add_argument("--full", action="store_true",
                   help="fly the figure8-slow and +highfi variants too, the LTV-MPC everywhere, and the NMPC "
                        "on every scenario with every model")
    p.add_argument("--engine", choices=ENGINES, default="process",
                   help="where the closed-loop runs fly: a process pool here (default) or Ray tasks "
                        "(pip install -e '.[ray]')")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="Ray cluster to send the runs to, e.g. HEAD:6379 (default: a local Ray instance)")
    p.add_argument("--fresh", action="store_true",
                   help="fly every run again and evaluate the models again; by default runs saved in --out with "
                        "the same spec, seed, model file and code are reused, so an interrupted run resumes where "
                        "it stopped, and so is an evaluation of the same models by the same code (in --out or "
                        "models/evaluation.json)")
    add_plant_options(p, "; with another plant or vehicle every run flies there (the oracle becomes the nominal "
                         "equations where the plant has none)")
    p.add_argument("--estimator", choices=ESTIMATORS, default=None,
                   help="fly every run with this setting (none: the true state plus noise; ekf: the state "
                        "estimator's estimate, docs/estimation.md). Default: every run without, and the "
                        "disturbance and noise cases with the SQP both ways")
    _qp_option(p, "every LTV-MPC and SQP run (the NMPC's and the LQR's runs are unchanged)")
    _level_option(p, ". Every run flies at it: models of another level are left out (and named), the oracle "
                     "becomes the nominal model where it has no equations at that level")
    p.set_defaults(handler=cmd_run)

    p = sub.add_parser("study", help="dose-response: fly every zoo model as an ensemble and score the predictors",
                       description="Fly every model of the zoo (pinnmpc zoo) on figure8-fast with the LTV-MPC and "
                                   "the SQP from --members ensemble members, and up the figure-8 speed ladder with "
                                   "the LTV-MPC; score the open-loop candidates (1-step and 100-step MAE, envelope "
                                   "exits, Jacobian error, closed-loop k-step error) as predictors of crash (ROC AUC) "
                                   "and RMSE (Spearman) with bootstrap intervals. Writes OUT/study.json and a copy "
                                   "MODELS/study.json, which the report of pinnmpc run shows. Resumable like run. "
                                   "About 30 minutes on 2 cores for 31 models and 10 members.")
    p.add_argument("--models", type=Path, default=Path("models/zoo"), help="the zoo (default models/zoo)")
    p.add_argument("--out", type=Path, default=Path("results/zoo"), help="results folder (default results/zoo)")
    p.add_argument("--members", type=int, default=10, help="ensemble members per model and controller (default 10)")
    _sweep_options(p, "study.json", "--models")
    add_plant_options(p)
    p.add_argument("--score-only", action="store_true",
                   help="fly nothing: recompute the open-loop candidates and their scores of the study already in "
                        "--out (after adding a candidate)")
    p.add_argument("--estimator", choices=ESTIMATORS, default="none",
                   help="ekf: fly the ensembles with the state estimator (no speed ladder) and write "
                        "study_ekf.json beside study.json, for the report's threshold with and without it")
    p.add_argument("--select", default=None, metavar="NAMES",
                   help="comma-separated zoo models to fly (default: all)")
    _qp_option(p, "every LTV-MPC and SQP run")
    _level_option(p, ". The zoo's models that declare another level are recorded as not flown; a zoo with none at "
                     "it is refused (the shipped zoo takes wrenches)")
    p.set_defaults(handler=cmd_study)

    p = sub.add_parser("versus", help="learned against nominal: fly the models trained on plants with unmodelled "
                                      "physics against the nominal equations, as ensembles",
                       description="On the high-fidelity plant and on RotorPy (motor lag, aerodynamics), fly the "
                                   "nominal equations, the models trained on that plant's own data and, where known, "
                                   "the plant's true equations with the SQP: figure8-fast from --members ensemble "
                                   "members and the figure-8 speed ladder from --ladder-members per rung. Gives each "
                                   "model's median RMSE with a bootstrap interval and its improvement over the "
                                   "nominal equations. Writes OUT/versus.json and a copy MODELS/versus/versus.json, "
                                   "which the report of pinnmpc run shows. Resumable like run. About 35 minutes on 2 "
                                   "cores for 16 models and 10 members.")
    p.add_argument("--models", type=Path, default=Path("models"), help="models folder (default models)")
    p.add_argument("--out", type=Path, default=Path("results/versus"), help="results folder (default results/versus)")
    p.add_argument("--members", type=int, default=10, help="ensemble members on figure8-fast (default 10)")
    p.add_argument("--ladder-members", type=int, default=10,
                   help="ensemble members on every other rung of the speed ladder (default 10)")
    p.add_argument("--plants", default=None, metavar="LIST",
                   help="comma-separated plants: highfi, rotorpy (default both; rotorpy needs the rotorpy extra), "
                        "crazyflie (RotorPy's Crazyflie preset: no open-loop model is trained on it)")
    _sweep_options(p, "versus.json", "--models/versus")
    _qp_option(p, "every SQP run")
    _level_option(p, ". At ctbr and ctatt: the nominal model of that level, the learned models that declare it and "
                     "the final model of the learning study published at that level (MODELS/learn/PLANT_LEVEL) (no "
                     "true equations: they would need the inner loop with the plant's lag); writes and publishes "
                     "versus_LEVEL.json beside the wrench level's versus.json, and the report shows both")
    p.set_defaults(handler=cmd_versus)

    p = sub.add_parser("levels", help="the three command levels side by side: the nominal model (and the oracle) "
                                      "at wrench, ctbr and ctatt on each plant",
                       description="On our plant (nominal and high-fidelity set-ups) and on RotorPy, each flying the "
                                   "Crazyflie, and on drone-models' Crazyflie identified from real flights (ctatt "
                                   "only), fly figure8-fast with the SQP at the wrench, ctbr and ctatt levels: the "
                                   "nominal model of each level and, where it exists, the oracle, from --members "
                                   "ensemble members. Gives each row's median RMSE with a bootstrap interval, its "
                                   "crashes and the SQP's median solve time, and their ratios to the wrench level's. "
                                   "Writes OUT/levels.json and a copy MODELS/levels/levels.json, which the report of "
                                   "pinnmpc run shows. Resumable like run. About 10 minutes on 2 cores with 5 "
                                   "members (docs/levels.md).")
    p.add_argument("--models", type=Path, default=Path("models"),
                   help="models folder, where levels/levels.json is published (default models)")
    p.add_argument("--out", type=Path, default=Path("results/levels"), help="results folder (default results/levels)")
    p.add_argument("--members", type=int, default=5, help="ensemble members per plant, level and model (default 5)")
    p.add_argument("--plants", default=None, metavar="LIST",
                   help="comma-separated plants: sim, highfi, rotorpy, drone-models (default all; rotorpy and "
                        "drone-models need their extras)")
    _sweep_options(p, "levels.json", "--models/levels")
    _qp_option(p, "every SQP run")
    p.set_defaults(handler=cmd_levels)

    from sim.identification.aero import AERO_MODES

    from .studies.learn import LEARN_LEVELS, LEARN_PLANTS, LearnSettings, upper_flights
    from .studies.training_refs import references_per_iteration

    per_level = LearnSettings.per_level
    p = sub.add_parser("learn", help="learn from the flights it flies: fly, train on the flights, fly the new model",
                       description="On one plant with physics the nominal equations lack, fly the nominal equations "
                                   "with the SQP on random training references (perturbed, with input dither; never "
                                   "a figure-8), train physics plus network with the rotor speeds as states and the "
                                   "aerodynamic terms the flights select on every flight so far, fly the new model on "
                                   "fresh references, and repeat. Each "
                                   "iteration's model flies the held-out figure8-fast: the learning curve. Then two "
                                   "controls (the same minutes of open-loop excitation, and an upper bound trained "
                                   "on the flights plus flights of figure8-fast itself, "
                                   f"as many as an iteration flies, {upper_flights(per_level)} at the default "
                                   f"--per-level {per_level}) and the "
                                   "evaluation on "
                                   "figure8-fast and the speed ladder against the nominal equations. Writes "
                                   "OUT/PLANT/learn.json; "
                                   "resumable: a rerun reuses every stage already written (docs/learning.md).")
    p.add_argument("--plant", required=True, choices=tuple(LEARN_PLANTS),
                   help="highfi: our simulator's high-fidelity set-up; rotorpy: RotorPy with its motor lag and "
                        "aerodynamics; crazyflie: RotorPy's Crazyflie 2.0 preset, 72 ms motor lag (both need the "
                        "rotorpy extra)")
    p.add_argument("--out", type=Path, default=Path("results/learn"), help="results folder (default results/learn)")
    p.add_argument("--models", type=Path, default=Path("models"),
                   help="models folder, for the plant's best open-loop model (default models)")
    p.add_argument("--iterations", type=int, default=3, help="models trained on flown data (default 3)")
    p.add_argument("--per-level", type=int, default=per_level,
                   help=f"training references per family and speed level in each iteration (default {per_level}: "
                        f"{references_per_iteration(per_level)} flights)")
    p.add_argument("--members", type=int, default=10,
                   help="ensemble members on figure8-fast for the nominal equations, the final model and the "
                        "controls (default 10)")
    p.add_argument("--curve-members", type=int, default=5,
                   help="ensemble members on figure8-fast for the learning curve's other iterations (default 5)")
    p.add_argument("--ladder-members", type=int, default=3, help="members per other rung of the ladder (default 3)")
    p.add_argument("--profile", choices=("scaled", "full", "quick", "smoke"), default="scaled",
                   help="training budget (default scaled: 60 passes over the flights; full: the shipped models' "
                        "fixed budget; smoke: seconds, for tests of the loop)")
    p.add_argument("--seed", type=int, default=0, help="seed of the references, dither and noise (default 0)")
    p.add_argument("--no-controls", action="store_true", help="skip the two controls")
    p.add_argument("--level", choices=LEARN_LEVELS, default="wrench",
                   help="command level flown and learned (default wrench: physics plus network with the rotor "
                        "speeds as states; ctbr: collective thrust and body rates through the plant's inner loop, "
                        "the level's nominal model plus a network with a register of the last 2 periods, no "
                        "open-loop control; the study goes in OUT/PLANT_ctbr)")
    p.add_argument("--aero", choices=AERO_MODES, default=None,
                   help="aerodynamic terms in the physics, at the wrench level: select (the default there): the "
                        "term library's selection on each training's flights, then the network trained on what the "
                        "identified terms leave, their coefficients learned beside the physical parameters; none: "
                        "no terms (the default at ctbr, whose model has no rotor speeds for them)")
    p.add_argument("--jobs", type=int, default=None, help="worker processes (default: number of CPUs)")
    p.add_argument("--publish", action="store_true",
                   help="copy the study's summary, learning curve and models into MODELS/learn/PLANT (PLANT_ctbr at "
                        "ctbr), where the report of pinnmpc run finds them")
    p.set_defaults(handler=cmd_learn)

    p = sub.add_parser("bounds", help="write the CI bounds file from the results of pinnmpc run",
                       description="Write the closed-loop CI bounds (scenarios/studies/bounds.toml) from a results "
                                   "folder of pinnmpc run: the oracle's cases bounded by its measured error, every "
                                   "shipped model's cases by its measured excess over the oracle, crashed cases as "
                                   "known failures. Nothing is flown.")
    p.add_argument("dir", metavar="DIR", type=Path, help="results folder of pinnmpc run")
    p.add_argument("--out", type=Path, default=None,
                   help="bounds file to write (default: scenarios/studies/bounds.toml)")
    p.add_argument("--models", type=Path, default=Path("models"),
                   help="folder of the shipped models that get bounds (default models)")
    p.set_defaults(handler=cmd_bounds)

    p = sub.add_parser("report", help="rebuild report.md and report.html from a saved results folder",
                       description="Rebuild DIR/report.md, DIR/report.html and DIR/figures from the files "
                                   "pinnmpc run saved in DIR (nothing is flown again).")
    p.add_argument("dir", metavar="DIR", type=Path)
    p.set_defaults(handler=cmd_report)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_fmt(x)}" for k, x in v.items())
    return "null" if v is None else str(v)


def _horizon_arg(text: str) -> int:
    """``--horizon``, checked when the command line is read (before anything is loaded or flown)."""
    from .closed_loop.runner import check_horizon

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    try:
        return check_horizon(value, "--horizon")
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def cmd_realdata(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc realdata``."""
    from .studies.realdata import run_realdata, summary_lines

    from sim.plants.named import PLANTS

    check_writable(args.out, "--out", folder=True)
    plants = () if args.plants == "none" else tuple(p.strip() for p in args.plants.split(",") if p.strip())
    bad = [p for p in plants if p not in PLANTS]
    if bad:
        raise ValueError(f"--plants: unknown plant {bad[0]!r}; choose from {', '.join(PLANTS)}, or none")
    if args.learn != "none":
        import importlib.util

        if importlib.util.find_spec("torch") is None:
            raise ValueError(f"--learn {args.learn}: training the learned models needs torch "
                             f"(pip install -e '.[train]'); --learn none evaluates the physics models only")
    from .studies.realdata import VALIDATION

    test, val = ([x.strip() for x in v.split(",") if x.strip()] for v in (args.test, args.val or ",".join(VALIDATION)))
    r = run_realdata(args.logs, args.out, args.vehicle, plants=plants, learn=args.learn, fmt=args.format,
                     test=test, val=val,
                     progress=(lambda line: print(line, file=sys.stderr, flush=True)))
    print("\n".join(summary_lines(r)))
    print(f"wrote {args.out / 'realdata.json'} and {args.out / 'realdata.md'}")
    return 0


def cmd_fly(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc fly``."""
    from .closed_loop.metrics import SETTLE_WINDOW_S
    from mpc.controllers.factory import DEFAULT_QP, QP_CONTROLLERS

    from .closed_loop.runner import RunSpec, fly

    _check_qp(args.qp)
    if args.qp != DEFAULT_QP and args.controller not in QP_CONTROLLERS:
        raise ValueError(f"--qp applies to the controllers that solve a QP ({', '.join(QP_CONTROLLERS)}); found "
                         f"--qp {args.qp} with --controller {args.controller}")
    if args.scheme is not None and args.controller != "sqp":
        raise ValueError(f"--scheme applies to the sqp controller; found --scheme {args.scheme} with --controller "
                         f"{args.controller}")

    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise ValueError(f"--plot must name a .png file; found {str(args.plot)!r}")
    for name in ("json", "trace", "plot"):      # before the flight, not after it
        if getattr(args, name) is not None:
            check_writable(getattr(args, name), f"--{name}")
    from mpc.controllers.readiness import require

    from .closed_loop.runner import load_run_model

    spec = RunSpec(args.scenario, args.controller, args.model, args.seed, args.horizon, args.timing,
                   plant=args.plant, vehicle=args.vehicle, estimator=args.estimator, qp=args.qp, level=args.level,
                   scheme=args.scheme)
    model = load_run_model(spec)
    ready = require(model, spec.controller)     # the same verdict as pinnmpc check-model prints
    if ready.warning:
        print(f"warning: {spec.controller} with {spec.model_name}: {ready.warning}", file=sys.stderr, flush=True)
    result, trace = fly(spec, progress=sys.stderr.isatty(), model=model)
    for k in FLY_FIELDS:
        print(f"{k:<22}{_fmt(result[k])}")
        if k == "max_position_error_m" and result["settled_error_m"] is not None:
            print(f"{'settled_error_m':<22}{_fmt(result['settled_error_m'])}   (largest error over the last "
                  f"{SETTLE_WINDOW_S:g} s)")
    if result.get("scheme"):
        print(f"{'scheme':<22}{result['scheme']}   (the input waits for one QP; the derivatives follow it)")
    if result.get("latency_ms") is not None:
        print(f"{'latency_ms':<22}{_fmt(result['latency_ms'])}   (from the measurement to the input out)")
    if result.get("failure_causes"):
        print(f"{'failure_causes':<22}" + ", ".join(f"{c} {n}" for c, n in result["failure_causes"].items()))
    if result.get("estimator_ms") is not None:
        print(f"{'estimator_ms':<22}{_fmt(result['estimator_ms'])}")
        print(f"{'nees_mean':<22}{_fmt(result['nees_mean'])}")
    if result["crashed"]:
        print(f"{'crash_reason':<22}{result['crash_reason']}")
    if result["error"]:
        print(f"{'error':<22}{result['error']}")
    if args.json:
        write_json(args.json, result)
        print(f"wrote {args.json}")
    if args.trace:
        write_npz(args.trace, trace)
        print(f"wrote {args.trace}")
    if args.plot:
        from .plot import plot_run
        plot_run(result, trace, args.plot)
        print(f"wrote {args.plot}")
    return 2 if result["error"] else 0     # a run that could not start is a failure of the command


def _check_vehicle(vehicle) -> None:
    """A sweep's --vehicle is read (and refused, naming the file and key) before anything is written or flown."""
    if vehicle is not None:
        from sim.vehicles.vehicle import load_vehicle

        load_vehicle(vehicle)


def cmd_run(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc run``."""
    from reports import build_report

    from .studies.campaign import run_main_job

    _check_qp(args.qp)
    if args.jobs is not None and args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1; found {args.jobs}")
    if args.address is not None and args.engine != "ray":
        raise ValueError("--address needs --engine ray")
    _check_vehicle(args.vehicle)
    check_writable(args.out, "--out", folder=True)
    out = run_main_job(args.out, args.models, args.jobs, args.full, progress=True, engine=args.engine,
                       address=args.address, resume=not args.fresh, plant=args.plant, vehicle=args.vehicle,
                       estimator=args.estimator, qp=args.qp, report=build_report, level=args.level)
    runs = out["results"]
    crashed = [r["run_id"] for r in runs if r.get("crashed")]
    errors = [r["run_id"] for r in runs if r.get("error")]
    print(f"{len(runs)} closed-loop runs, {len(crashed)} crashed, {len(errors)} could not start")
    for rid in crashed:
        print(f"  crashed: {rid}")
    for rid in errors:
        print(f"  error:   {rid}")
    print(f"wrote {out['report']} and {Path(out['report']).with_suffix('.html')}")
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc study``."""
    import os

    from .studies.zoo import format_study, rescore_study, run_study

    if args.score_only:
        if args.estimator != "none" or args.select is not None:
            raise ValueError("--score-only rescores the study without an estimator; drop --estimator and --select")
        if args.qp != "osqp":
            raise ValueError(f"--score-only flies nothing, so it has no QP solver; drop --qp {args.qp}")
        out = rescore_study(args.models, args.out, publish=not args.no_publish)
        print(format_study(out))
        return 0
    _check_qp(args.qp)
    jobs = args.jobs if args.jobs is not None else (os.cpu_count() or 1)
    if jobs < 1 or args.members < 1:
        raise ValueError(f"--jobs and --members must be >= 1; found {jobs} and {args.members}")
    if args.address is not None and args.engine != "ray":
        raise ValueError("--address needs --engine ray")
    if (args.plant != "sim" or args.vehicle is not None or args.level != "wrench") and not args.no_publish \
            and args.models == Path("models/zoo"):
        raise ValueError("a study on another plant, vehicle or level would replace the shipped zoo's study.json; give "
                         "--no-publish (or another --models folder)")
    from .studies.zoo import study_file

    _check_vehicle(args.vehicle)
    check_writable(args.out, "--out", folder=True)
    select = None if args.select is None else [n.strip() for n in args.select.split(",") if n.strip()]
    if select is not None and args.estimator == "none" and not args.no_publish:
        raise ValueError("a study of some models would replace the zoo's study.json; give --no-publish")
    out = run_study(args.models, args.out, args.members, jobs, progress=True, publish=not args.no_publish,
                    engine=args.engine, address=args.address, resume=not args.fresh, plant=args.plant,
                    vehicle=args.vehicle, estimator=args.estimator, select=select, qp=args.qp, level=args.level)
    print(format_study(out))
    name = study_file(args.estimator)
    print(f"wrote {args.out / name}" + ("" if args.no_publish else f" and {args.models / name}"))
    failed = out.get("failed") or {}
    if failed:
        print(f"pinnmpc study: {len(failed)} model{'s' if len(failed) > 1 else ''} could not be studied (recorded in "
              f"{name}): " + "; ".join(f"{n}: {why}" for n, why in failed.items()), file=sys.stderr)
        return 1
    return 0


def cmd_versus(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc versus``."""
    import os

    from .studies.versus import format_versus, parse_plants, published_name, run_versus

    _check_qp(args.qp)
    jobs = args.jobs if args.jobs is not None else (os.cpu_count() or 1)
    for name, v in (("--jobs", jobs), ("--members", args.members), ("--ladder-members", args.ladder_members)):
        if v < 1:
            raise ValueError(f"{name} must be >= 1; found {v}")
    if args.address is not None and args.engine != "ray":
        raise ValueError("--address needs --engine ray")
    check_writable(args.out, "--out", folder=True)
    out = run_versus(args.models, args.out, args.members, args.ladder_members, parse_plants(args.plants), jobs,
                     progress=True, publish=not args.no_publish, engine=args.engine, address=args.address,
                     resume=not args.fresh, qp=args.qp, level=args.level)
    print(format_versus(out))
    name = published_name(args.level)
    print(f"wrote {args.out / name}" + ("" if args.no_publish else f" and {args.models / 'versus' / name}"))
    return 0


def cmd_levels(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc levels``."""
    import os

    from .studies.levels import format_levels, parse_level_plants, run_levels

    _check_qp(args.qp)
    jobs = args.jobs if args.jobs is not None else (os.cpu_count() or 1)
    for name, v in (("--jobs", jobs), ("--members", args.members)):
        if v < 1:
            raise ValueError(f"{name} must be >= 1; found {v}")
    if args.address is not None and args.engine != "ray":
        raise ValueError("--address needs --engine ray")
    plants = parse_level_plants(args.plants)
    check_writable(args.out, "--out", folder=True)
    out = run_levels(args.models, args.out, args.members, plants, jobs, progress=True, publish=not args.no_publish,
                     engine=args.engine, address=args.address, resume=not args.fresh, qp=args.qp)
    print(format_levels(out))
    print(f"wrote {args.out / 'levels.json'}"
          + ("" if args.no_publish else f" and {args.models / 'levels' / 'levels.json'}"))
    return 0


def cmd_learn(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc learn``."""
    import os

    from .studies.learn import LearnSettings, format_learn, publish_learn, run_learn

    jobs = args.jobs if args.jobs is not None else (os.cpu_count() or 1)
    if jobs < 1:
        raise ValueError(f"--jobs must be >= 1; found {jobs}")
    from .studies.learn import LEARN_PLANTS

    if LEARN_PLANTS[args.plant].plant == "rotorpy":
        from sim.plants.named import rotorpy_available

        if not rotorpy_available():
            raise ValueError(f"plant {args.plant} needs RotorPy: python -m pip install -e '.[rotorpy]'")
    settings = LearnSettings(plant=args.plant, iterations=args.iterations, per_level=args.per_level, seed=args.seed,
                             profile=args.profile, members=args.members, curve_members=args.curve_members,
                             ladder_members=args.ladder_members, controls=not args.no_controls, level=args.level,
                             aero=args.aero)
    check_writable(args.out, "--out", folder=True)
    out = run_learn(settings, args.out, args.models, jobs)
    print(format_learn(out))
    print(f"wrote {args.out / settings.tag / 'learn.json'}")
    if args.publish:
        print(f"published into {publish_learn(args.out / settings.tag, args.models)}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc report``."""
    from reports import build_report

    if not args.dir.is_dir():
        raise ValueError(f"DIR {str(args.dir)!r} is not a folder of saved results")
    path = build_report(args.dir)
    print(f"wrote {path} and {Path(path).with_suffix('.html')}")
    return 0


def cmd_bounds(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc bounds``."""
    import json

    from .studies.bounds import BOUNDS_FILE, generate, load_bounds
    from .studies.campaign import shipped_models
    from .errors import BoundsError

    results = args.dir / "results.json"
    if not results.is_file():
        raise ValueError(f"DIR {str(args.dir)!r} has no results.json; give the results folder of pinnmpc run")
    out = check_writable(BOUNDS_FILE if args.out is None else args.out, "--out")
    try:
        data = json.loads(results.read_text())
    except (OSError, ValueError) as e:
        raise BoundsError(f"{results}: not a readable JSON file ({e})") from e
    runs = data.get("runs") if isinstance(data, dict) else None
    if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
        raise BoundsError(f"{results}: expected an object with a list of runs under \"runs\" (as pinnmpc run "
                          f"writes it)")
    models = [Path(m).stem for m in shipped_models(args.models)]
    try:
        text = generate(runs, models, f"`pinnmpc run` ({args.dir.name}/results.json)")
    except BoundsError as e:
        raise BoundsError(f"{results}: {e}") from e
    write_text(out, text)
    _, bounds = load_bounds(out)
    known = [b for b in bounds if b.known_failure]
    print(f"wrote {out}: {len(bounds)} cases, {len(known)} known failures")
    for b in known:
        print(f"  known failure: {b.scenario} / {b.controller} / {b.model}")
    return 0
