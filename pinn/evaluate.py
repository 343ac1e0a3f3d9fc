"""Tables I and II from exported models, beside the paper's claimed numbers.

Works from ONNX files alone (onnxruntime; no torch): each model's metadata
says which dataset it was trained on, the dataset is regenerated from its
seed and checked against the stored fingerprint, and the metrics of
:mod:`pinn.metrics` are computed on its test split. Identified parameters
are compared with the truth and with the Cramer-Rao standard deviation of
the training split (:mod:`sim.identification.fisher`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mpc.prediction.contract import check_model, model_files, open_session
from sim.params import THETA_NAMES, NoiseModel, QuadParams

from .metrics import one_step_mae, rollout_mae

#: The paper's claims (its Tables I-III); numbers to compare with, not ground truth (the paper's public code had known defects).
PAPER_TABLE1 = {  # 1-step and 100-step MAE: z (m), phi (rad)
    "baseline": {"z_1": 0.087, "phi_1": 0.0008, "z_100": 1.49, "phi_100": 0.018},
    "modular": {"z_1": 0.041, "phi_1": 0.0005, "z_100": 30.0, "phi_100": 0.24},
    "fourier": {"z_1": 0.009, "phi_1": 0.0001, "z_100": 5.2e6, "phi_100": 8596.0},
    "proposed": {"z_1": 0.026, "phi_1": 0.0002, "z_100": 0.029, "phi_100": 0.001},
}
PAPER_TABLE2 = {"m": 0.0, "kt": 0.0, "kq": 0.0, "Jxx": 5.0, "Jyy": 5.0, "Jzz": 5.0}  # error, %
#: Section VI: inertia identification error, %, with small-angle data and with aggressive (45-60 deg) data.
PAPER_TABLE6 = {"small": 5.0, "aggressive": 46.0}
PAPER_TABLE3 = {  # 100-step position MAE, m
    "baseline": 1.49, "baseline+curriculum": 0.82, "baseline+curriculum+ss": 0.45,
    "baseline+curriculum+ss+dropout": 0.12, "proposed": 0.029,
}


def onnx_step(path, threads: int = 1):
    """``step(x, u) -> x_next`` on numpy arrays through onnxruntime (input dtype follows the model)."""
    sess = open_session(path, threads)
    dtype = np.float64 if "double" in sess.get_inputs()[0].type else np.float32

    def step(x, u):
        return sess.run(["x_next"], {"x": np.asarray(x, dtype), "u": np.asarray(u, dtype)})[0].astype(float)
    return step


def data_spec(training_config: dict) -> dict:
    """The dataset description stored in a model's training config (raises if absent)."""
    spec = training_config.get("data")
    if not isinstance(spec, dict) or not {"regime", "n_traj", "duration_s", "seed"} <= spec.keys():
        raise ValueError("the model's training_config has no 'data' entry (regime, n_traj, duration_s, seed); "
                         "pass the dataset with --data")
    return spec


def regenerate(spec: dict, with_clean: bool = False):
    """Rebuild the dataset of ``spec`` and check its fingerprint (with ``with_clean``: and its noise-free twin)."""
    from sim.identification.excitation import make_dataset
    from sim.params import FIDELITIES

    noise = NoiseModel() if spec.get("noise", "default") == "default" else NoiseModel.none()
    fidelity = spec.get("fidelity", "nominal")
    if fidelity not in FIDELITIES:
        raise ValueError(f"the model's data description names fidelity {fidelity!r}; this code knows "
                         f"{', '.join(FIDELITIES)}")
    ds = make_dataset(spec["regime"], int(spec["n_traj"]), float(spec["duration_s"]), int(spec["seed"]), noise=noise,
                      fidelity=FIDELITIES[fidelity], inputs=spec.get("inputs", "commanded"), with_clean=with_clean)
    ds, clean = ds if with_clean else (ds, None)
    fp = spec.get("fingerprint")
    if fp and ds.fingerprint() != fp:
        raise ValueError(f"regenerated {spec['regime']} dataset (seed {spec['seed']}) does not match the "
                         f"fingerprint stored with the model: the data generator has changed since training, or "
                         f"this machine rounds differently from the one that made it (numpy picks its float64 sin, "
                         f"cos and exp by the CPU: with AVX-512 from another library than without)")
    return (ds, clean) if with_clean else ds


def fidelity_name(fidelity: dict) -> str:
    """Name of a dataset's simulator fidelity (``"nominal"``, ``"high"``), or ``"custom"``."""
    import dataclasses

    from sim.params import FIDELITIES

    return next((n for n, f in FIDELITIES.items() if dataclasses.asdict(f) == dict(fidelity)), "custom")


def crlb_train_split(ds, clean=None) -> dict:
    """CRLB standard deviation of each parameter for the training split of ``ds`` (its noise model).

    ``clean``: the same flights without noise, if already at hand (flown again from ``ds``'s description if not).
    """
    from sim.identification.excitation import make_dataset
    from sim.identification.fisher import fisher_from_dataset
    from sim.params import Fidelity

    m = ds.meta
    # The same flights without noise (the bound is evaluated at the true states), through the nominal model.
    if clean is None:
        clean = make_dataset(m["regime"], m["n_traj"], m["duration_s"], m["seed"], noise=NoiseModel.none(),
                             fidelity=Fidelity(**m.get("fidelity", {})), inputs=m.get("inputs", "commanded"))
    res = fisher_from_dataset(clean.subset(clean.split == 0), "wrench", NoiseModel(**m["noise"]))
    return {n: float(v) for n, v in zip(THETA_NAMES, res.crlb_std)}


def _spec_of(info) -> dict:
    """The training data spec recorded in a model's metadata (a model without one needs ``--data``)."""
    if info.training_config is None:
        raise ValueError(f"{info.path}: its metadata has no 'training_config' to regenerate its data from; "
                         f"give the test data with --data FILE.npz")
    return data_spec(info.training_config)


def evaluate_model(path, ds=None, crlb: dict | None = None, n_starts: int = 200, info=None,
                   lag_crlb: dict | None = None) -> dict:
    """Table I and II entries of one ONNX model (``info``: its :func:`check_model` result, if already known).

    A motor-lag model's errors are in σ of the lag model's own bound ``lag_crlb`` (seven parameters, ``tau_m``
    included) where given, as the lag-aware classical fit's.
    """
    info = check_model(path) if info is None else info
    if ds is None:
        ds = regenerate(_spec_of(info))
    step = onnx_step(path)
    truth = QuadParams(**ds.meta["params"]).theta
    extra, tau = model_extra_states(info, ds)
    out = {
        "name": Path(path).stem,
        "architecture": info.architecture,
        "recipe": (info.training_config or {}).get("recipe", info.architecture),
        "regime": ds.meta["regime"],
        "fidelity": fidelity_name(ds.meta.get("fidelity", {})),
        "inputs": ds.meta.get("inputs", "commanded"),
        "one_step": one_step_mae(step, ds, extra=extra),
        "rollout_100": rollout_mae(step, ds, horizon=100, n_starts=n_starts, extra=extra),
        "theta_true": dict(zip(THETA_NAMES, map(float, truth))),
    }
    if tau is not None:
        out["extra_states"] = list(info.extra_states)
        out["tau_m"] = tau
        tau_true = float(ds.meta.get("fidelity", {}).get("motor_tau", 0.0))
        if tau_true > 0:
            out["tau_m_true"] = tau_true
    if info.theta is None:      # a model that identifies no parameters: Table I only
        return out
    theta = np.array([info.theta[n] for n in THETA_NAMES])
    err = 100.0 * (theta - truth) / truth
    out["theta"] = dict(zip(THETA_NAMES, map(float, theta)))
    out["theta_err_pct"] = dict(zip(THETA_NAMES, map(float, err)))
    if tau is not None and "tau_m_true" in out:
        names, theta, truth = THETA_NAMES + ("tau_m",), np.r_[theta, tau], np.r_[truth, out["tau_m_true"]]
        out["theta_err_pct"]["tau_m"] = float(100.0 * (tau - truth[-1]) / truth[-1])
        if lag_crlb is not None:
            out["crlb_std"] = lag_crlb
            out["crlb"] = "lag"
            out["err_over_crlb"] = {n: float(abs(theta[i] - truth[i]) / lag_crlb[n]) for i, n in enumerate(names)}
            return out
    if crlb is not None:
        out["crlb_std"] = crlb
        out["err_over_crlb"] = {n: float(abs(theta[i] - truth[i]) / crlb[n]) for i, n in enumerate(THETA_NAMES)}
    return out


def model_extra_states(info, ds):
    """The extra states of a model along a dataset's flights, and its motor time constant.

    Returns ``(None, None)`` for a model of the rigid body alone. A motor-lag model (rotor speeds ``n1`` .. ``n4``
    as extra states, ``motor_tau`` in its metadata) gets the rotor speeds its own lag gives along the logged
    commands (from the first command's speed; :func:`sim.identification.motor_lag.rotor_trajectory` with its theta-hat
    and
    tau-hat): ``((flights, steps, 4), tau_m)``. Other extra states cannot be reconstructed from a flight log.
    """
    if not info.extra_states:
        return None, None
    from sim.identification.motor_lag import rotor_trajectory

    if tuple(info.extra_states) != ("n1", "n2", "n3", "n4") or "motor_tau" not in info.metadata \
            or info.theta is None:
        raise ValueError(f"{info.path}: its extra states {list(info.extra_states)} cannot be reconstructed from a "
                         "flight log (only a motor-lag model's rotor speeds n1..n4, with metadata 'motor_tau' and "
                         "'theta', can)")
    try:
        tau = float(info.metadata["motor_tau"])
    except ValueError:
        tau = float("nan")
    if not (np.isfinite(tau) and tau > 0):
        raise ValueError(f"{info.path}: metadata 'motor_tau' must be a time constant > 0 s; found "
                         f"{info.metadata['motor_tau']!r}")
    theta7 = np.r_[[info.theta[n] for n in THETA_NAMES], tau]
    n, _ = rotor_trajectory(ds.u, theta7, QuadParams(**ds.meta["params"]))
    return n[:, :-1], tau


def lag_summary(ds, clean=None) -> dict | None:
    """The lag-aware classical fit of a dataset flown with a motor lag, or None (no lag, no noise, realized inputs).

    Seven parameters (:mod:`sim.identification.motor_lag`: the nominal six and the motor time constant, the rotor
    speeds a
    state driven by the logged commands), with the Cramér-Rao bound of the same model on the training split.
    """
    import time

    from sim.identification.excitation import make_dataset
    from sim.identification.motor_lag import LAG_THETA_NAMES, estimate_with_lag, lag_fisher, true_theta7
    from sim.params import Fidelity

    m = ds.meta
    if not m.get("fidelity", {}).get("motor_tau", 0.0) > 0 or m.get("inputs", "commanded") != "commanded" \
            or NoiseModel(**m["noise"]).is_zero:
        return None
    if clean is None:
        clean = make_dataset(m["regime"], m["n_traj"], m["duration_s"], m["seed"], noise=NoiseModel.none(),
                             fidelity=Fidelity(**m.get("fidelity", {})))
    t0 = time.perf_counter()
    bound = lag_fisher(clean, NoiseModel(**m["noise"]))
    est = estimate_with_lag(ds)
    truth = true_theta7(ds)
    err = est.theta - truth
    return {"method": "weighted nonlinear least squares through the nominal model with the motor lag (rotor speeds "
                      "driven by the logged commands, tau_m identified)",
            "theta": est.as_dict(), "theta_true": dict(zip(LAG_THETA_NAMES, map(float, truth))),
            "theta_err_pct": dict(zip(LAG_THETA_NAMES, map(float, 100.0 * err / truth))),
            "crlb_std": dict(zip(LAG_THETA_NAMES, map(float, bound.crlb_std))),
            "err_over_crlb": dict(zip(LAG_THETA_NAMES, map(float, np.abs(err) / bound.crlb_std))),
            "std_pct": dict(zip(LAG_THETA_NAMES, map(float, 100.0 * est.std_rel))),
            "iterations": est.iterations, "converged": est.converged, "n_transitions": est.n_transitions,
            "seconds": round(time.perf_counter() - t0, 1)}


def data_summary(ds, crlb: dict, estimate: bool = True, clean=None) -> dict:
    """What one training dataset allows: its saturation, the CRLB of its training split and the classical fit.

    The classical estimator (:func:`sim.identification.estimate.estimate_theta`) is fitted to the training split, the
    data the
    PINNs train on; its error is given in % and as a multiple of the same CRLB standard deviation as theirs.
    """
    import time

    from sim.identification.estimate import estimate_theta

    tr = ds.split == 0
    out = {"regime": ds.meta["regime"], "fidelity": fidelity_name(ds.meta.get("fidelity", {})),
           "fidelity_detail": dict(ds.meta.get("fidelity", {})), "inputs": ds.meta.get("inputs", "commanded"),
           "n_traj": int(ds.meta["n_traj"]), "duration_s": float(ds.meta["duration_s"]), "seed": int(ds.meta["seed"]),
           "saturated_fraction": float(np.mean(np.any(ds.saturated[tr], axis=-1))),
           "crlb_std": crlb}
    truth = QuadParams(**ds.meta["params"]).theta
    out["theta_true"] = dict(zip(THETA_NAMES, map(float, truth)))
    if estimate:
        t0 = time.perf_counter()
        est = estimate_theta(ds)
        err = est.theta - truth
        out["estimator"] = {
            "method": "weighted nonlinear least squares through the nominal model (Gauss-Newton)",
            "theta": est.as_dict(),
            "theta_err_pct": dict(zip(THETA_NAMES, map(float, 100.0 * err / truth))),
            "err_over_crlb": {n: float(abs(err[i]) / crlb[n]) for i, n in enumerate(THETA_NAMES)},
            "std_pct": dict(zip(THETA_NAMES, map(float, 100.0 * est.std_rel))),
            "iterations": est.iterations, "converged": est.converged,
            "n_transitions": est.n_transitions, "seconds": round(time.perf_counter() - t0, 1)}
        lag = lag_summary(ds, clean)
        if lag is not None:
            out["estimator_lag"] = lag
    return out


#: Datasets the main job studies with the classical estimator although no shipped model is trained on them: the
#: small regime flown with each effect of the high-fidelity simulator alone (which effect moves which parameter).
#: 30 flights (the first 30 of the 100 the models train on; a flight does not depend on how many are made), to
#: keep the main job's time.
EFFECT_SPECS = tuple({"regime": "small", "n_traj": 30, "duration_s": 10.0, "seed": 0, "noise": "default",
                      "fidelity": f} for f in ("motor-lag", "rotor-drag", "rotor-gyro"))


def _spec_task(task) -> tuple[dict, list[dict]]:
    """Worker: one dataset (regenerated from its spec or read from a file), its summary and its models' rows."""
    import sim.identification.fisher   # (the package first: it pins the BLAS kernel and threads in a fresh worker)

    spec, data_path, files, threads = task
    if threads is not None:
        sim.identification.fisher.MAP_THREADS = threads     # a pool's workers share the cores: one thread each
    if data_path is not None:
        from sim.identification.excitation import load_dataset
        ds, clean = load_dataset(data_path), None
    else:
        ds, clean = regenerate(spec, with_clean=True)
    crlb = crlb_train_split(ds, clean)
    # A noise-free dataset gives the weighted fit nothing to weight by: it is summarized without it.
    summary = data_summary(ds, crlb, estimate=not NoiseModel(**ds.meta["noise"]).is_zero, clean=clean)
    if data_path is None:
        summary["spec"] = {k: v for k, v in spec.items() if k != "fingerprint"}
    lag_crlb = (summary.get("estimator_lag") or {}).get("crlb_std")
    rows = [evaluate_model(f, ds, crlb, lag_crlb=lag_crlb) for f in files]
    return summary, rows


#: The code an evaluation depends on besides its models (paths under the project's root): the datasets, the
#: Fisher bounds and the classical estimator (``sim``), the metrics (``pinn``) and the model contract.
EVALUATION_CODE = ("sim", "pinn", "mpc/prediction/contract.py", "mpc/prediction/models.py", "mpc/errors.py")
#: Code under EVALUATION_CODE that neither the evaluation nor the Fisher table imports (the flight-log import and
#: its benchmark, the flight models and the ctbr learner), left out of their keys so that work on it does not call
#: for a recomputation (a test holds that they do not import it).
KEY_EXCLUDES = ("sim/flightlogs", "pinn/flights.py", "pinn/ctbr.py")


def evaluation_key(folder, extra_specs=()) -> str:
    """SHA-256 of everything :func:`evaluate_dir` reads: the model files (``*.onnx``, derivative graphs included)
    of ``folder`` (one or a list), ``extra_specs`` and the source of :data:`EVALUATION_CODE`.

    The evaluation is deterministic, so a result stored with the same key is the one it would compute again.
    """
    from sim.files import source_digest

    h = source_digest(EVALUATION_CODE, Path(__file__).resolve().parents[1], KEY_EXCLUDES)
    for d in [folder] if isinstance(folder, (str, Path)) else folder:
        for f in sorted(Path(d).glob("*.onnx")):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    h.update(json.dumps(list(extra_specs), sort_keys=True).encode())
    return h.hexdigest()


def evaluate_dir(folder, data_path=None, progress: bool = False, jobs: int = 1, extra_specs=()) -> dict:
    """Evaluate every model ``*.onnx`` (not ``*.jac.onnx``) in ``folder`` (a folder or a list of folders).

    Models trained on the same data share one regenerated dataset, one CRLB and one run of the classical
    estimator (``datasets`` in the result). ``extra_specs`` adds datasets (data descriptions as stored with a
    model) that no model was trained on; ``jobs`` datasets are handled in parallel processes.
    """
    folders = [Path(f) for f in ([folder] if isinstance(folder, (str, Path)) else folder)]
    files = [p for d in folders for p in model_files(d)]
    if not files:
        raise ValueError(f"no .onnx models in {', '.join(repr(str(d)) for d in folders)}")
    from mpc.prediction.contract import declared_level

    for f in files:
        if (level := declared_level(f)) != "wrench":
            raise ValueError(f"{f}: the model takes {level} commands; the evaluation's tables are of wrench-level "
                             f"models (a model trained with pinnmpc train --arch ctbr has its open-loop errors in "
                             f"its manifest entry)")
    if data_path is not None:
        from sim.identification.excitation import load_dataset

        if (level := load_dataset(data_path).level) != "wrench":
            raise ValueError(f"--data {str(data_path)!r} holds commands at the {level} level; the evaluation's "
                             f"models take wrenches")
    groups: dict[str, list] = {}
    specs: dict[str, dict] = {}
    for f in files:
        if data_path is not None:
            key, spec = str(data_path), None
        else:
            spec = _spec_of(check_model(f))
            key = json.dumps({k: v for k, v in spec.items() if k != "file"}, sort_keys=True)
        specs.setdefault(key, spec)
        groups.setdefault(key, []).append(f)
    for spec in extra_specs:
        key = json.dumps(spec, sort_keys=True)
        specs.setdefault(key, spec)
        groups.setdefault(key, [])
    threads = 1 if jobs > 1 and len(groups) > 1 else None
    tasks = [(specs[k], data_path, groups[k], threads) for k in groups]
    # Largest groups first, so that the pool's last task is a short one.
    order = sorted(range(len(tasks)), key=lambda i: -len(tasks[i][2]))

    def completed():
        """(task index, result) as the tasks finish, in a pool of ``jobs`` processes or in this one."""
        if jobs > 1 and len(tasks) > 1:
            import concurrent.futures as cf
            import multiprocessing as mp

            from sim.workers import worker_init
            from sim.equations.compiled import precompile
            from sim.identification.fisher import sensitivity_function

            worker_init()      # one BLAS thread per worker, as in the closed-loop sweep (inherited at spawn)
            # Compiled once here, not in every worker at the same time.
            precompile([(sensitivity_function(QuadParams(), "wrench", s), "batch") for s in (True, False)], jobs)
            with cf.ProcessPoolExecutor(min(jobs, len(tasks)), mp_context=mp.get_context("spawn"),
                                        initializer=worker_init) as pool:
                futs = {pool.submit(_spec_task, tasks[i]): i for i in order}
                for fut in cf.as_completed(futs):
                    yield futs[fut], fut.result()
        else:
            for i in order:
                yield i, _spec_task(tasks[i])

    results: dict[int, tuple] = {}
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(files) + len(extra_specs), desc="evaluate", unit="model", leave=False)
    for i, res in completed():
        results[i] = res
        if bar is not None:
            bar.update(max(1, len(tasks[i][2])))
    if bar is not None:
        bar.close()
    by_file = {str(r_f): row for i in results for r_f, row in zip(tasks[i][2], results[i][1])}
    rows = [by_file[str(f)] for f in files]
    datasets = []
    for i in range(len(tasks)):
        summary = results[i][0]
        summary["models"] = [Path(f).stem for f in tasks[i][2]]
        datasets.append(summary)
    return {"models": rows, "datasets": datasets,
            "paper": {"table1": PAPER_TABLE1, "table2_err_pct": PAPER_TABLE2, "table3_position_mae_m": PAPER_TABLE3,
                      "table6_inertia_err_pct": PAPER_TABLE6}}


def _g(v, fmt=".3g"):
    return "-" if v is None else format(v, fmt)


def format_tables(result: dict) -> str:
    """Tables I and II as text, ours beside the paper's."""
    lines = ["Table I: 1-step and 100-step MAE on the test split (ours | paper)", ""]
    head = (f"{'model':<22}{'1-step z (m)':>20}{'1-step phi (rad)':>22}{'100-step z (m)':>22}"
            f"{'100-step phi (rad)':>22}{'100-step pos (m)':>18}{'diverged':>10}")
    lines += [head, "-" * len(head)]
    for r in result["models"]:
        pap = PAPER_TABLE1.get(r["architecture"], {}) if r["regime"] == "small" else {}
        o, k = r["one_step"], r["rollout_100"]
        lines.append(
            f"{r['name']:<22}{_g(o['z']):>10} | {_g(pap.get('z_1')):<7}{_g(o['phi']):>12} | {_g(pap.get('phi_1')):<7}"
            f"{_g(k['z']):>12} | {_g(pap.get('z_100')):<7}{_g(k['phi']):>12} | {_g(pap.get('phi_100')):<7}"
            f"{_g(k['position']):>18}{k['n_diverged']:>6}/{k['n_rollouts']}")
    lines += ["", "Table II: identified parameters (error %, |error| / CRLB std) | paper error %", ""]
    head = f"{'model':<30}" + "".join(f"{n:>22}" for n in THETA_NAMES)
    lines += [head, "-" * len(head)]
    for r in result["models"]:
        if "theta_err_pct" not in r:
            continue
        row = f"{r['name']:<30}"
        for n in THETA_NAMES:
            e = r["theta_err_pct"][n]
            c = r.get("err_over_crlb", {}).get(n)
            row += f"{e:>+9.2f}% {_g(c, '.1f'):>5}σ | {PAPER_TABLE2[n]:>3g}%"
        lines.append(row)
    for d in result.get("datasets", []):
        est = d.get("estimator")
        if not est:
            continue
        row = f"{'classical, ' + data_label(d):<30}"
        for n in THETA_NAMES:
            row += f"{est['theta_err_pct'][n]:>+9.2f}% {est['err_over_crlb'][n]:>5.1f}σ       "
        lines.append(row)
    return "\n".join(lines)


def data_label(d: dict) -> str:
    """Short name of a dataset entry: regime, fidelity off nominal, realized inputs."""
    parts = [d["regime"]]
    if d.get("fidelity", "nominal") != "nominal":
        parts.append("high fidelity" if d["fidelity"] == "high" else d["fidelity"])
    if d.get("inputs", "commanded") != "commanded":
        parts.append(f"{d['inputs']} inputs")
    return ", ".join(parts)


def markdown_tables(result: dict, ablation: dict | None = None) -> str:
    """Tables I, II (and III from an ablation result) in Markdown, ours beside the paper's."""
    L = ["| model | 1-step z (m) | 1-step φ (rad) | 100-step z (m) | 100-step φ (rad) | 100-step position (m) "
         "| diverged | paper 1-step z / φ | paper 100-step z / φ |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["models"]:
        pap = PAPER_TABLE1.get(r["architecture"]) if r["regime"] == "small" else None
        o, k = r["one_step"], r["rollout_100"]
        paper = (f"{pap['z_1']:g} / {pap['phi_1']:g} | {pap['z_100']:g} / {pap['phi_100']:g}" if pap else "– | –")
        L.append(f"| {r['name']} | {o['z']:.2e} | {o['phi']:.2e} | {k['z']:.4f} | {k['phi']:.4f} | "
                 f"{k['position']:.4f} | {k['n_diverged']}/{k['n_rollouts']} | {paper} |")
    L += ["", "| model | " + " | ".join(THETA_NAMES) + " |", "|---|" + "---|" * len(THETA_NAMES)]
    for r in result["models"]:
        cells = [f"{r['theta_err_pct'][n]:+.2f} % ({r['err_over_crlb'][n]:.1f} σ)" if "err_over_crlb" in r
                 else f"{r['theta_err_pct'][n]:+.2f} %" for n in THETA_NAMES]
        L.append(f"| {r['name']} | " + " | ".join(cells) + " |")
    L.append("| paper (Table II) | " + " | ".join(f"{PAPER_TABLE2[n]:g} %" for n in THETA_NAMES) + " |")
    crlb = next((r for r in result["models"] if r["regime"] == "small" and "crlb_std" in r), None)
    if crlb is not None:
        L.append("| CRLB σ, small regime (% of truth) | " + " | ".join(
            f"{100 * crlb['crlb_std'][n] / crlb['theta_true'][n]:.3f} %" for n in THETA_NAMES) + " |")
    if ablation is not None:
        L += ["", "| configuration | 100-step position MAE (m) | improvement | diverged | paper MAE (m) | paper improvement |",
              "|---|---|---|---|---|---|"]
        for r in ablation["rows"]:
            L.append(f"| {r['configuration']} | {r['position_mae_100_m']:.4f} | {r['improvement_pct']:+.0f} % | "
                     f"{r['n_diverged']} | {r['paper_position_mae_100_m']:g} | {r['paper_improvement_pct']:.0f} % |")
    return "\n".join(L)
