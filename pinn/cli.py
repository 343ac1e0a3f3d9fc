"""``pinnmpc train``, ``pinnmpc evaluate`` and ``pinnmpc ablation``.

torch is imported inside the handlers only (``evaluate`` needs none of it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from sim.files import check_writable, json_ready, write_json
from sim.identification.aero import AERO_MODES
from sim.params import FIDELITIES, INPUT_LOGS

ARCHS = ("baseline", "modular", "fourier", "proposed", "hybrid", "hybrid_lag")


def register(sub) -> None:
    """Add this package's subcommands to the ``pinnmpc`` parser."""
    p = sub.add_parser("train", help="train one PINN, export it to ONNX and record it in the manifest",
                       description="Physics-informed training with parameter identification; writes "
                                   "NAME.onnx, NAME.jac.onnx, NAME.pt into --out and updates --out/manifest.json.")
    p.add_argument("--arch", required=True, choices=ARCHS + ("ctbr",),
                   help="the architecture; ctbr: the ctbr level's nominal model plus a network with a register, "
                        "from a dataset flown at that level (pinnmpc data --level ctbr; docs/levels.md)")
    p.add_argument("--recipe", default=None, choices=("baseline", "proposed"),
                   help="training recipe, if not the architecture's own (hybrid trains with the baseline recipe; "
                        "--recipe proposed adds curriculum, scheduled sampling, dropout, energy and smoothness)")
    p.add_argument("--profile", default="quick", choices=("quick", "full", "smoke"),
                   help="budget: quick (CI, < 60 s) or full (shipped models); smoke (--arch ctbr only: a few "
                        "seconds, for trying the command)")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--data", type=Path, default=None, help="dataset .npz from `pinnmpc data`")
    src.add_argument("--regime", default="small", choices=("small", "aggressive"),
                     help="without --data: generate the default dataset of this regime (100 x 10 s)")
    p.add_argument("--data-seed", type=int, default=0, help="seed of the generated dataset (default 0)")
    p.add_argument("--fidelity", default="nominal", choices=tuple(FIDELITIES),
                   help="without --data: simulator of the generated dataset (high: motor lag, rotor drag and "
                        "rotor gyroscopic torque, which no model contains; motor-lag, rotor-drag, rotor-gyro: one "
                        "of them)")
    p.add_argument("--inputs", default="commanded", choices=INPUT_LOGS,
                   help="without --data: log the wrench command (default) or the wrench the rotors realized, "
                        "i.e. commands kept inside the rotor limits (not with motor lag)")
    p.add_argument("--dropout-until", type=float, default=1.0, metavar="F",
                   help="recipes with dropout: switch it off after this fraction of the epochs (default 1: on "
                        "throughout, the paper's recipe)")
    p.add_argument("--aero", default="none", choices=AERO_MODES,
                   help="--arch hybrid_lag: aerodynamic terms in the physics (default none; select: the term "
                        "library's selection on the training flights, judged on the validation flights, then "
                        "trained jointly from the identified coefficients; the name gets _aero)")
    p.add_argument("--name", default=None, help="file stem (default: ARCH, then _REGIME off the small regime, "
                                                 "_highfi and _realized off the defaults)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--out", type=Path, required=True, help="output folder, e.g. models/")
    p.set_defaults(handler=cmd_train)

    p = sub.add_parser("evaluate", help="Tables I and II of the ONNX models in a folder",
                       description="1-step and 100-step MAE on the test split and identified parameters "
                                   "against truth and Cramer-Rao bounds, beside the paper's numbers, and the "
                                   "classical estimator fitted to each model's training data.")
    p.add_argument("folder", type=Path, nargs="+", help="folders of models (e.g. models models/identification)")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset .npz (default: regenerate each model's training dataset from its metadata)")
    p.add_argument("--json", type=Path, default=None, help="output JSON (default: evaluation.json in the first "
                                                            "folder)")
    p.add_argument("--jobs", type=int, default=1, help="datasets evaluated in parallel processes (default 1)")
    p.set_defaults(handler=cmd_evaluate)

    p = sub.add_parser("zoo", help="train the model zoo (open-loop quality from millimetres to divergence)",
                       description="Train every run of the zoo (early checkpoints, small networks, scarce or noisy "
                                   "data, the paper's failure modes, unbounded layers) and write OUT/NAME.onnx, "
                                   "OUT/NAME.jac.onnx (float64) and OUT/manifest.json with the command, settings "
                                   "and test metrics of each model. About 5 minutes with 2 jobs.")
    p.add_argument("--out", type=Path, default=Path("models/zoo"), help="output folder (default models/zoo)")
    p.add_argument("--only", nargs="+", default=None, metavar="RUN", help="train only these runs (names as listed "
                   "by --list)")
    p.add_argument("--jobs", type=int, default=1, help="parallel trainings, one torch thread each (default 1)")
    p.add_argument("--list", action="store_true", help="list the runs and the models they yield, train nothing")
    p.set_defaults(handler=cmd_zoo)

    p = sub.add_parser("ablation", help="Table III: train the five ablation configurations",
                       description="Baseline, +curriculum, +scheduled sampling, +dropout, +energy/smoothness "
                                   "(= proposed), same data and budget; 100-step position MAE on the test split.")
    p.add_argument("--profile", default="quick", choices=("quick", "full"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--regime", default="small", choices=("small", "aggressive"))
    p.add_argument("--data-seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=1, help="parallel trainings, one torch thread each (default 1)")
    p.add_argument("--reuse", type=Path, default=None,
                   help="models folder: a configuration already trained there (same training config and "
                        "data fingerprint) is taken from its manifest instead of being trained again")
    p.add_argument("--out", type=Path, required=True, help="output folder (ablation.json)")
    p.set_defaults(handler=cmd_ablation)


# ------------------------------------------------------------------ helpers
def _dataset(args):
    """(dataset, data spec) from --data or the default dataset of --regime."""
    from sim.identification.excitation import load_dataset, make_dataset

    if args.data is not None:
        ds = load_dataset(args.data)
        m = ds.meta
        if ds.valid is not None:
            raise ValueError(f"--data {str(args.data)!r} holds imported flight logs (pinnmpc import); pinnmpc train "
                             f"takes simulated datasets (its test metrics assume every sample was measured): "
                             f"pinnmpc realdata trains and evaluates models on real flight logs")
        noise = "default" if any(m["noise"].values()) else "none"
        spec = {"file": str(args.data), "regime": m["regime"], "n_traj": m["n_traj"], "duration_s": m["duration_s"],
                "seed": m["seed"], "noise": noise, "fingerprint": ds.fingerprint()}
        if ds.level != "wrench":
            spec["level"] = ds.level
        return ds, spec
    fidelity = getattr(args, "fidelity", "nominal")
    inputs = getattr(args, "inputs", "commanded")
    level = "ctbr" if getattr(args, "arch", None) == "ctbr" else "wrench"
    ds = make_dataset(args.regime, 100, 10.0, args.data_seed, fidelity=FIDELITIES[fidelity], inputs=inputs,
                      level=level)
    spec = {"regime": args.regime, "n_traj": 100, "duration_s": 10.0, "seed": args.data_seed, "noise": "default"}
    # Recorded only off their defaults, so that the description (and hash) of older models stays as it was.
    if fidelity != "nominal":
        spec["fidelity"] = fidelity
    if inputs != "commanded":
        spec["inputs"] = inputs
    if level != "wrench":
        spec["level"] = level
    spec["fingerprint"] = ds.fingerprint()
    return ds, spec


def default_name(arch: str, spec: dict) -> str:
    """File stem of a trained model: ARCH, then _REGIME off the small regime, _highfi (or the effect), _realized."""
    name = arch if spec["regime"] == "small" else f"{arch}_{spec['regime']}"
    level = spec.get("level", "wrench")
    if level not in ("wrench", arch):      # a dataset at another level than the architecture's own name
        name += f"_{level}"
    fidelity = spec.get("fidelity", "nominal")
    if fidelity != "nominal":
        name += "_highfi" if fidelity == "high" else "_" + fidelity.replace("-", "_")
    if spec.get("inputs", "commanded") == "realized":
        name += "_realized"
    return name


def _train_one(ds, arch: str, profile: str, seed: int, threads: int, recipe: str | None, progress: bool,
               **overrides):
    from .train import make_config, train

    cfg = make_config(arch, profile, seed, recipe=recipe, threads=threads, **overrides)
    res = train(ds, cfg, progress=progress)
    from .metrics import test_metrics

    return res, test_metrics(res.model, ds)


# ----------------------------------------------------------------- commands
def cmd_train(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc train``."""
    import torch

    from mpc.prediction.contract import config_hash
    from sim.params import THETA_NAMES

    from .export import export_model
    from .train import aero_summary

    if args.threads < 1:
        raise ValueError(f"--threads must be >= 1; found {args.threads}")
    if not 0.0 <= args.dropout_until <= 1.0:
        raise ValueError(f"--dropout-until must lie in [0, 1]; found {args.dropout_until}")
    overrides = {"dropout_until": args.dropout_until} if args.dropout_until != 1.0 else {}
    if args.aero != "none":
        if args.arch != "hybrid_lag":
            raise ValueError(f"--aero {args.aero} needs --arch hybrid_lag (the model that carries the rotor speeds "
                             f"the terms read); found --arch {args.arch}")
        overrides["aero"] = args.aero
    check_writable(args.out, "--out", folder=True)  # before the training, so that its minutes are not lost
    if args.arch == "ctbr":
        for flag, given in (("--recipe", args.recipe is not None), ("--dropout-until", bool(overrides)),
                            ("--inputs", args.inputs != "commanded")):
            if given:
                raise ValueError(f"{flag} applies to the wrench architectures; --arch ctbr has its own recipe")
    elif args.profile == "smoke":
        raise ValueError(f"--profile smoke is --arch ctbr's; --arch {args.arch} takes quick or full")
    ds, spec = _dataset(args)
    if args.arch == "ctbr" and ds.level != "ctbr":
        raise ValueError(f"--arch ctbr learns from a dataset flown at the ctbr level (pinnmpc data --level ctbr); "
                         f"--data {str(args.data)!r} holds commands at the {ds.level} level")
    if args.arch != "ctbr" and ds.level != "wrench":
        raise ValueError(f"--data {str(args.data)!r} holds commands at the {ds.level} level; --arch {args.arch} "
                         f"learns from wrenches (--arch ctbr learns at ctbr)")
    if args.arch == "ctbr":
        return _train_ctbr(args, ds, spec)
    own = args.arch if args.arch in ("baseline", "proposed") else "baseline"
    recipe = None if args.recipe in (None, own) else args.recipe
    name = args.name or default_name(args.arch + ("_aero" if args.aero != "none" else "")
                                     if recipe is None else f"{args.arch}_{recipe}", spec)
    res, metrics = _train_one(ds, args.arch, args.profile, args.seed, args.threads, recipe,
                              progress=sys.stderr.isatty(), **overrides)
    # the terms' record, in the learning study's form
    aero = None if res.aero_selection is None else aero_summary(res.aero_selection, res.model)
    last = res.history[-1]
    if not (np.isfinite(last["val"]) and np.all(np.isfinite(last["theta"]))):
        raise ValueError(f"training {name} ended with a non-finite validation loss ({last['val']}) or parameters; "
                         f"nothing was written to {args.out}")
    training_config = {"name": name, "recipe": args.arch if recipe is None else f"{args.arch}+{recipe}",
                       "train": res.config.to_dict(), "data": spec}
    paths = export_model(res.model, args.out, name, training_config, spec["seed"], metrics, res.stats)
    cmd = (f"pinnmpc train --arch {args.arch} " + (f"--recipe {recipe} " if recipe else "")
           + f"--profile {args.profile} --seed {args.seed} "
           + (f"--data {args.data} " if args.data else f"--regime {spec['regime']} --data-seed {spec['seed']} "
              + (f"--fidelity {spec['fidelity']} " if "fidelity" in spec else "")
              + (f"--inputs {spec['inputs']} " if "inputs" in spec else ""))
           + (f"--dropout-until {args.dropout_until:g} " if args.dropout_until != 1.0 else "")
           + (f"--aero {args.aero} " if args.aero != "none" else "")
           + f"--threads {args.threads} " + (f"--name {args.name} " if args.name else "") + f"--out {args.out}")
    entry = {
        "files": {k: Path(v).name for k, v in paths.items()},
        "command": cmd,
        "seed": args.seed,
        "architecture": args.arch,
        "profile": args.profile,
        "data": spec,
        "config_hash": config_hash(training_config),
        "metrics": metrics,
        "theta": dict(zip(THETA_NAMES, last["theta"])),
        "theta_err_pct": last["theta_err_pct"],
        "final_losses": {k: last[k] for k in ("data", "phys", "theta", "rotor", "energy", "smooth", "val")},
        "training_seconds": round(res.seconds, 1),
        **({"aero": json_ready(aero)} if aero is not None else {}),     # strict JSON (an unknown interval: null)
        "torch_version": torch.__version__,
        "cpu_count": os.cpu_count(),
    }
    from .manifest import update_manifest

    manifest = update_manifest(args.out, name, entry)
    r = metrics["rollout_100_mae"]
    print(f"trained {name} ({args.arch}, {args.profile}) in {res.seconds:.0f} s -> {paths['onnx']}")
    print(f"  1-step MAE z {metrics['one_step_mae']['z']:.2e} m, phi {metrics['one_step_mae']['phi']:.2e} rad; "
          f"100-step MAE position {r['position']:.3g} m, phi {r['phi']:.3g} rad, diverged {r['n_diverged']}/{r['n_rollouts']}")
    print("  theta-hat error %: " + ", ".join(f"{k} {v:+.2f}" for k, v in last["theta_err_pct"].items()))
    print(f"  validation loss {last['val']:.3e} (first epoch {res.history[0]['val']:.3e}); manifest {manifest}")
    if aero is not None:
        def identified(i):
            interval = (f"95 % {i['low']:.4g}-{i['high']:.4g}" if np.isfinite([i["low"], i["high"]]).all()
                        else "no interval: one training flight")
            return f"identified {i['value']:.4g}, {interval}"

        terms = [f"{c} {v:.4g} {aero['units'][c]} ({identified(aero['identified'][c])})"
                 for c, v in aero.get("coefficients", {}).items()]     # none when none was claimed
        print("  aerodynamic terms: " + (", ".join(terms) if terms else "none claimed"))
    return 0


def _train_ctbr(args: argparse.Namespace, ds, spec: dict) -> int:
    """``pinnmpc train --arch ctbr``: :func:`pinn.ctbr.train_ctbr` on the dataset's splits, exported with its
    derivative graph (level ``ctbr``) and recorded in the manifest."""
    import dataclasses

    import torch

    from sim.vehicles.vehicle import load_vehicle

    from .ctbr import CTBR_ARCH, dataset_series, train_ctbr
    from .flights import export_flight_model
    from .manifest import update_manifest

    torch.set_num_threads(args.threads)
    vehicle = load_vehicle(ds.meta.get("vehicle"))
    plant = ds.meta.get("plant", "sim")
    name = args.name or default_name("ctbr", spec)
    say = (lambda line: print(line, file=sys.stderr)) if sys.stderr.isatty() else None
    split = dataset_series(ds)
    t = train_ctbr(split, plant, vehicle, args.seed, args.profile, progress=say)
    res = t.result
    if not np.all(np.isfinite(res.scores)):
        raise ValueError(f"training {name} ended with a non-finite validation score ({res.scores[-1]}); nothing was "
                         f"written to {args.out}")
    path = export_flight_model(res.model, args.out / f"{name}.onnx", t.theta, CTBR_ARCH, level="ctbr")
    cmd = (f"pinnmpc train --arch ctbr --profile {args.profile} --seed {args.seed} "
           + (f"--data {args.data} " if args.data else f"--regime {spec['regime']} --data-seed {spec['seed']} "
              + (f"--fidelity {spec['fidelity']} " if "fidelity" in spec else ""))
           + f"--threads {args.threads} " + (f"--name {args.name} " if args.name else "") + f"--out {args.out}")
    entry = {"files": {"onnx": path.name, "jacobian": f"{name}.jac.onnx"}, "command": cmd, "seed": args.seed,
             "architecture": "ctbr", "recipe": CTBR_ARCH, "level": "ctbr", "profile": args.profile, "data": spec,
             "plant": plant, "vehicle": vehicle.name, "train": dataclasses.asdict(t.config),
             "flights": {k: len(v) for k, v in split.items()}, "best_epoch": res.best_epoch,
             "validation_scores": [float(v) for v in res.scores], "test_errors": t.test_errors,
             "rate_tau_s": t.rate_tau_s, "theta": t.theta, "training_seconds": round(res.seconds, 1),
             "torch_version": torch.__version__, "cpu_count": os.cpu_count()}
    manifest = update_manifest(args.out, name, entry)
    print(f"trained {name} (ctbr, {args.profile}) in {res.seconds:.0f} s -> {path}")
    print(f"  best epoch {res.best_epoch} of {len(res.scores)}, validation score {min(res.scores):.3f} (1 = the goal)")
    print("  test flights' open-loop error at h = 1, 10, 50: "
          + "; ".join(f"{q} " + "/".join(f"{v:.3g}" for v in e) for q, e in t.test_errors.items()))
    print(f"  manifest {manifest}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc evaluate``."""
    from .evaluate import evaluate_dir, format_tables

    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1; found {args.jobs}")
    result = evaluate_dir(args.folder, args.data, progress=sys.stderr.isatty(), jobs=args.jobs)
    print(format_tables(result))
    out = args.json or args.folder[0] / "evaluation.json"
    write_json(out, result)
    print(f"\nwrote {out}")
    return 0


def cmd_zoo(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc zoo``."""
    from .zoo import RUNS, train_zoo

    if args.list:
        for r in RUNS:
            print(f"{r.name:22s} {', '.join(r.model_names()):48s} {r.why}")
        return 0
    runs = RUNS
    if args.only:
        known = {r.name for r in RUNS}
        bad = [n for n in args.only if n not in known]
        if bad:
            raise ValueError(f"--only: unknown zoo runs {bad}; known: {', '.join(sorted(known))}")
        runs = tuple(r for r in RUNS if r.name in args.only)
    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1; found {args.jobs}")
    written = train_zoo(args.out, runs, args.jobs, progress=sys.stderr.isatty())
    secs = written.pop("_seconds")
    for name, e in written.items():
        r = e["metrics"]["rollout_100_mae"]
        print(f"{name:28s} 100-step position MAE {r['position']:10.4g} m, left the envelope "
              f"{r['n_left_envelope']:3d}/{r['n_rollouts']}, diverged {r['n_diverged']}"
              + (f"\n{'':28s} refused (not in the manifest, see refused.json): {e['refused']}" if "refused" in e else ""))
    refused = sum("refused" in e for e in written.values())
    print(f"trained {len(runs)} runs ({len(written)} models, {refused} refused) in {secs:.0f} s; "
          f"manifest {args.out / 'manifest.json'}")
    return 0


def _ablation_arch(recipe: str) -> str:
    return "proposed" if recipe == "proposed" else "baseline"


def _ablation_job(job):
    ds, recipe, profile, seed = job
    res, metrics = _train_one(ds, _ablation_arch(recipe), profile, seed, 1, recipe, progress=False)
    return recipe, res.seconds, metrics, res.history[-1]["theta_err_pct"], res.config.to_dict()


def _reusable(folder: Path, recipe: str, spec: dict, profile: str, seed: int):
    """An already trained model of ``folder`` with exactly this configuration and data, as a job result."""
    from mpc.prediction.contract import check_model

    from .train import make_config

    manifest = folder / "manifest.json"
    if not manifest.exists():
        return None
    cfg = make_config(_ablation_arch(recipe), profile, seed, recipe=recipe, threads=1).to_dict()
    for name, entry in json.loads(manifest.read_text()).items():
        tc = check_model(folder / entry["files"]["onnx"]).training_config
        if tc.get("train") == cfg and tc.get("data", {}).get("fingerprint") == spec["fingerprint"]:
            return recipe, entry["training_seconds"], entry["metrics"], entry["theta_err_pct"], cfg
    return None


def cmd_ablation(args: argparse.Namespace) -> int:
    """Handler of ``pinnmpc ablation``."""
    from concurrent.futures import ProcessPoolExecutor

    from .evaluate import PAPER_TABLE3
    from .train import ABLATION

    if args.jobs < 1:
        raise ValueError(f"--jobs must be >= 1; found {args.jobs}")
    args.data = None
    ds, spec = _dataset(args)
    results = {}
    if args.reuse is not None:
        for r in ABLATION:
            hit = _reusable(args.reuse, r, spec, args.profile, args.seed)
            if hit is not None:
                results[r] = hit
                print(f"{r}: reusing the trained model in {args.reuse} (same config and data)")
    jobs = [(ds, r, args.profile, args.seed) for r in ABLATION if r not in results]
    from tqdm import tqdm
    bar = tqdm(total=len(jobs), desc="ablation", unit="config", disable=not sys.stderr.isatty())
    if args.jobs == 1:
        for j in jobs:
            r = _ablation_job(j)
            results[r[0]] = r
            bar.update()
    else:
        with ProcessPoolExecutor(args.jobs) as ex:
            for r in ex.map(_ablation_job, jobs):
                results[r[0]] = r
                bar.update()
    bar.close()
    base = results["baseline"][2]["rollout_100_mae"]["position"]
    rows = []
    for recipe in ABLATION:
        _, secs, metrics, th_err, cfg = results[recipe]
        reused = args.reuse is not None and recipe not in {j[1] for j in jobs}
        mae = metrics["rollout_100_mae"]["position"]
        rows.append({"configuration": recipe, "position_mae_100_m": mae,
                     "improvement_pct": 100.0 * (base - mae) / base,
                     "n_diverged": metrics["rollout_100_mae"]["n_diverged"],
                     "paper_position_mae_100_m": PAPER_TABLE3[recipe],
                     "paper_improvement_pct": 100.0 * (PAPER_TABLE3["baseline"] - PAPER_TABLE3[recipe])
                     / PAPER_TABLE3["baseline"],
                     "one_step_mae": metrics["one_step_mae"], "theta_err_pct": th_err,
                     "training_seconds": round(secs, 1), "config": cfg, "reused_from_models": reused})
    out = {"profile": args.profile, "seed": args.seed, "data": spec, "rows": rows}
    path = write_json(args.out / "ablation.json", out)
    print("Table III: 100-step position MAE on the test split (ours | paper)\n")
    print(f"{'configuration':<34}{'MAE (m)':>10}{'improvement':>13} | {'paper MAE':>9}{'paper impr.':>12}")
    for r in rows:
        print(f"{r['configuration']:<34}{r['position_mae_100_m']:>10.4f}{r['improvement_pct']:>12.0f}% | "
              f"{r['paper_position_mae_100_m']:>9.3g}{r['paper_improvement_pct']:>11.0f}%")
    print(f"\nwrote {path}")
    return 0
