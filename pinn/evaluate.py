"""Tables I and II from exported models, beside the paper's claimed numbers.

Works from ONNX files alone (onnxruntime; no torch): each model's metadata
says which dataset it was trained on, the dataset is regenerated from its
seed and checked against the stored fingerprint, and the metrics of
:mod:`pinn.metrics` are computed on its test split. Identified parameters
are compared with the truth and with the Cramer-Rao standard deviation of
the training split (:mod:`sim.fisher`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mpc.contract import check_model, open_session
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


def regenerate(spec: dict):
    """Rebuild the dataset of ``spec`` and check its fingerprint."""
    from sim.excitation import make_dataset
    from sim.params import FIDELITIES

    noise = NoiseModel() if spec.get("noise", "default") == "default" else NoiseModel.none()
    fidelity = spec.get("fidelity", "nominal")
    if fidelity not in FIDELITIES:
        raise ValueError(f"the model's data description names fidelity {fidelity!r}; this code knows "
                         f"{', '.join(FIDELITIES)}")
    ds = make_dataset(spec["regime"], int(spec["n_traj"]), float(spec["duration_s"]), int(spec["seed"]), noise=noise,
                      fidelity=FIDELITIES[fidelity], inputs=spec.get("inputs", "commanded"))
    fp = spec.get("fingerprint")
    if fp and ds.fingerprint() != fp:
        raise ValueError(f"regenerated {spec['regime']} dataset (seed {spec['seed']}) does not match the "
                         f"fingerprint stored with the model; the data generator has changed since training")
    return ds


def crlb_train_split(ds) -> dict:
    """CRLB standard deviation of each parameter for the training split of ``ds`` (default noise)."""
    from sim.excitation import make_dataset
    from sim.fisher import fisher_from_dataset
    from sim.params import Fidelity

    m = ds.meta
    # The same flights without noise (the bound is evaluated at the true states), through the nominal model.
    clean = make_dataset(m["regime"], m["n_traj"], m["duration_s"], m["seed"], noise=NoiseModel.none(),
                         fidelity=Fidelity(**m.get("fidelity", {})))
    res = fisher_from_dataset(clean.subset(clean.split == 0), "wrench", NoiseModel(**m["noise"]))
    return {n: float(v) for n, v in zip(THETA_NAMES, res.crlb_std)}


def _spec_of(info) -> dict:
    """The training data spec recorded in a model's metadata (a model without one needs ``--data``)."""
    if info.training_config is None:
        raise ValueError(f"{info.path}: its metadata has no 'training_config' to regenerate its data from; "
                         f"give the test data with --data FILE.npz")
    return data_spec(info.training_config)


def evaluate_model(path, ds=None, crlb: dict | None = None, n_starts: int = 200, info=None) -> dict:
    """Table I and II entries of one ONNX model (``info``: its :func:`check_model` result, if already known)."""
    info = check_model(path) if info is None else info
    if ds is None:
        ds = regenerate(_spec_of(info))
    step = onnx_step(path)
    truth = QuadParams(**ds.meta["params"]).theta
    out = {
        "name": Path(path).stem,
        "architecture": info.architecture,
        "recipe": (info.training_config or {}).get("recipe", info.architecture),
        "regime": ds.meta["regime"],
        "one_step": one_step_mae(step, ds),
        "rollout_100": rollout_mae(step, ds, horizon=100, n_starts=n_starts),
        "theta_true": dict(zip(THETA_NAMES, map(float, truth))),
    }
    if info.theta is None:      # a model that identifies no parameters: Table I only
        return out
    theta = np.array([info.theta[n] for n in THETA_NAMES])
    err = 100.0 * (theta - truth) / truth
    out["theta"] = dict(zip(THETA_NAMES, map(float, theta)))
    out["theta_err_pct"] = dict(zip(THETA_NAMES, map(float, err)))
    if crlb is not None:
        out["crlb_std"] = crlb
        out["err_over_crlb"] = {n: float(abs(theta[i] - truth[i]) / crlb[n]) for i, n in enumerate(THETA_NAMES)}
    return out


def evaluate_dir(folder, data_path=None, progress: bool = False) -> dict:
    """Evaluate every model ``*.onnx`` (not ``*.jac.onnx``) in ``folder``."""
    folder = Path(folder)
    files = sorted(p for p in folder.glob("*.onnx") if not p.name.endswith(".jac.onnx"))
    if not files:
        raise ValueError(f"no .onnx models in {str(folder)!r}")
    cache: dict = {}
    rows = []
    it = files
    if progress:
        from tqdm import tqdm
        it = tqdm(files, desc="evaluate", unit="model", leave=False)
    for f in it:
        info = check_model(f)
        if data_path is not None:
            key = str(data_path)
            if key not in cache:
                from sim.excitation import load_dataset
                ds = load_dataset(data_path)
                cache[key] = (ds, crlb_train_split(ds))
        else:
            spec = _spec_of(info)
            key = json.dumps(spec, sort_keys=True)
            if key not in cache:
                ds = regenerate(spec)
                cache[key] = (ds, crlb_train_split(ds))
        ds, crlb = cache[key]
        rows.append(evaluate_model(f, ds, crlb, info=info))
    return {"models": rows, "paper": {"table1": PAPER_TABLE1, "table2_err_pct": PAPER_TABLE2,
                                      "table3_position_mae_m": PAPER_TABLE3}}


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
    head = f"{'model':<22}" + "".join(f"{n:>22}" for n in THETA_NAMES)
    lines += [head, "-" * len(head)]
    for r in result["models"]:
        row = f"{r['name']:<22}"
        for n in THETA_NAMES:
            e = r["theta_err_pct"][n]
            c = r.get("err_over_crlb", {}).get(n)
            row += f"{e:>+9.2f}% {_g(c, '.1f'):>5}σ | {PAPER_TABLE2[n]:>3g}%"
        lines.append(row)
    return "\n".join(lines)


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
