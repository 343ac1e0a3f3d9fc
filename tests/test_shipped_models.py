"""The shipped ONNX models: contract, torch/onnxruntime parity, exact derivatives, reproducibility."""

import json
import shlex
from pathlib import Path

import numpy as np
import pytest

from mpc.prediction.contract import check_model, jacobian_path, open_session

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "models"
MANIFEST = json.loads((MODELS / "manifest.json").read_text())
NAMES = sorted(MANIFEST)
#: The identification study's models (models/identification), with their own manifest.
IDENT = MODELS / "identification"
IDENT_MANIFEST = json.loads((IDENT / "manifest.json").read_text())
#: The models only ``pinnmpc versus`` flies (models/versus): the other architectures on the high-fidelity data, and
#: every architecture on RotorPy's data (its motor lag and aerodynamics).
VERSUS = MODELS / "versus"
VERSUS_MANIFEST = json.loads((VERSUS / "manifest.json").read_text())
#: Every shipped model as (folder, name).
ALL = ([(MODELS, n) for n in NAMES] + [(IDENT, n) for n in sorted(IDENT_MANIFEST)]
       + [(VERSUS, n) for n in sorted(VERSUS_MANIFEST)])
IDS = [f"{d.name}/{n}" for d, n in ALL]

TOL = {
    "parity": 1e-5,        # torch vs onnxruntime, relative to each state's spread of x_next - x
    "fd": 1e-3,            # exported A, B vs central differences of the model (relative, per sample)
    "reproduce": 0.05,     # retrained metrics vs the manifest's
    "reproduce_theta": 0.05,   # retrained theta-hat error vs the manifest's (relative, plus 0.01 point)
}
REQUIRED = {"baseline", "modular", "fourier", "proposed", "baseline_aggressive", "proposed_aggressive"}
#: The identification study: Baseline and Proposed on each data cell off the shipped ones, both with two more
#: training seeds, and the Proposed recipe with dropout switched off for the last quarter of the epochs.
#: The physics-plus-network form: with both recipes on the shipped data, and with the motor lag on the small
#: high-fidelity data.
REQUIRED_IDENT = {f"{a}_{c}" for a in ("baseline", "proposed")
                     for c in ("highfi", "aggressive_highfi", "aggressive_realized", "seed1", "seed2")} | {
    "proposed_dropout75", "hybrid", "hybrid_proposed", "hybrid_lag_highfi"}
#: Learned against nominal: the other architectures on the small high-fidelity data, the lag model on the
#: aggressive one, every architecture on RotorPy's data; the lag model with the aerodynamic term library on both.
ARCHS = ("baseline", "modular", "fourier", "proposed", "hybrid", "hybrid_lag", "hybrid_lag_aero")
REQUIRED_VERSUS = {"modular_highfi", "fourier_highfi", "hybrid_highfi", "hybrid_lag_aggressive_highfi",
                   "hybrid_lag_aero_aggressive_highfi"} | {f"{a}_rotorpy" for a in ARCHS}
#: The open-loop models at the ctbr level (models/versus/ctbr, their own manifest): ``pinnmpc train --arch ctbr`` on
#: ``pinnmpc data --level ctbr`` of each plant of the study, small and aggressive.
VERSUS_CTBR = VERSUS / "ctbr"
VERSUS_CTBR_MANIFEST = json.loads((VERSUS_CTBR / "manifest.json").read_text())
REQUIRED_VERSUS_CTBR = {f"ctbr{r}_{p}" for r in ("", "_aggressive") for p in ("highfi", "rotorpy")}


def envelope_inputs(n, seed=0):
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-3, 3, (n, 3)), np.radians(rng.uniform(-20, 20, (n, 2))),
                         np.radians(rng.uniform(-60, 60, n)), rng.uniform(-2, 2, (n, 3)), rng.uniform(-4, 4, (n, 3))])
    u = np.column_stack([rng.uniform(0.3, 1.0, n), rng.uniform(-3e-3, 3e-3, (n, 2)), rng.uniform(-2e-3, 2e-3, n)])
    return x, u


def model_inputs(path, n, seed=0):
    """Envelope states and inputs for a shipped model: a model with extra states gets them at rest for each input
    (held state and input), then moved 5 % off it, so that they are exercised away from equilibrium. A model at
    ``ctbr`` gets body-rate commands within 2 rad/s instead of torques."""
    from mpc.prediction.contract import _with_extra_at_rest
    x, u = envelope_inputs(n, seed)
    info = check_model(path)
    if info.level == "ctbr":
        u[:, 1:] = np.random.default_rng(seed + 2).uniform(-2.0, 2.0, (n, 3))
    if not info.extra_states:
        return x, u
    z = _with_extra_at_rest(open_session(path), x, u, info.extra_states, str(path), "test")
    z[:, 12:] *= 1.0 + 0.05 * np.random.default_rng(seed + 1).standard_normal(z[:, 12:].shape)
    return z, u


def _manifest(folder):
    return {MODELS: MANIFEST, IDENT: IDENT_MANIFEST, VERSUS: VERSUS_MANIFEST}[folder]


def test_every_required_model_is_shipped():
    assert REQUIRED <= set(NAMES)
    assert REQUIRED_IDENT <= set(IDENT_MANIFEST)
    assert REQUIRED_VERSUS <= set(VERSUS_MANIFEST)
    for folder, name in ALL:
        for f in _manifest(folder)[name]["files"].values():
            assert (folder / f).is_file(), f


@pytest.mark.parametrize("folder, name", ALL, ids=IDS)
def test_shipped_model_passes_the_contract_and_matches_its_manifest(folder, name):
    info = check_model(folder / f"{name}.onnx")
    assert info.jacobian == jacobian_path(folder / f"{name}.onnx")
    assert info.config_hash == _manifest(folder)[name]["config_hash"]
    assert info.test_metrics["rollout_100_mae"] == _manifest(folder)[name]["metrics"]["rollout_100_mae"]


@pytest.mark.parametrize("folder, name", ALL, ids=IDS)
def test_torch_and_onnxruntime_agree(folder, name):
    import torch

    from pinn.export import load_torch_model

    model, _ = load_torch_model(folder / f"{name}.pt")
    x, u = model_inputs(folder / f"{name}.onnx", 1000)
    with torch.no_grad():
        ref = model.double()(torch.tensor(x), torch.tensor(u)).numpy()
    got = open_session(folder / f"{name}.onnx").run(["x_next"], {"x": x, "u": u})[0]
    scale = np.std(ref - x, axis=0) + 1e-12
    assert np.max(np.abs(got - ref) / scale) < TOL["parity"]


@pytest.mark.parametrize("folder, name", ALL + [(VERSUS_CTBR, n) for n in sorted(VERSUS_CTBR_MANIFEST)],
                         ids=IDS + [f"versus/ctbr/{n}" for n in sorted(VERSUS_CTBR_MANIFEST)])
def test_exported_derivatives_match_central_differences(folder, name):
    x, u = model_inputs(folder / f"{name}.onnx", 20, seed=1)
    model = open_session(folder / f"{name}.onnx")
    _, A, B = open_session(jacobian_path(folder / f"{name}.onnx")).run(["x_next", "A", "B"], {"x": x, "u": u})

    def f(xx, uu):
        return model.run(["x_next"], {"x": xx, "u": uu})[0]
    fd_A = np.zeros_like(A)
    fd_B = np.zeros_like(B)
    for j in range(x.shape[1]):
        h = 1e-6 * np.maximum(1.0, np.abs(x[:, j]))
        e = np.zeros_like(x)
        e[:, j] = h
        fd_A[:, :, j] = (f(x + e, u) - f(x - e, u)) / (2 * h[:, None])
    for j in range(4):
        h = 1e-6 * np.maximum(1e-3, np.abs(u[:, j]))
        e = np.zeros_like(u)
        e[:, j] = h
        fd_B[:, :, j] = (f(x, u + e) - f(x, u - e)) / (2 * h[:, None])
    for got, fd in ((A, fd_A), (B, fd_B)):
        rel = np.linalg.norm(got - fd, axis=(1, 2)) / np.linalg.norm(fd, axis=(1, 2))
        assert np.max(rel) < TOL["fd"]


@pytest.mark.retrain
def test_retraining_reproduces_the_shipped_metrics(tmp_path):
    """Run the manifest command of the shipped baseline into a temporary folder (about 5 minutes)."""
    from scenarios.cli import main

    entry = MANIFEST["baseline"]
    args = shlex.split(entry["command"])[1:]
    args[args.index("--out") + 1] = str(tmp_path)
    assert main(args) == 0
    new = json.loads((tmp_path / "manifest.json").read_text())["baseline"]["metrics"]
    for group in ("one_step_mae", "rollout_100_mae"):
        for key in ("position", "z", "phi", "vz"):
            old, now = entry["metrics"][group][key], new[group][key]
            assert abs(now - old) <= TOL["reproduce"] * old, (group, key, old, now)


def _retrain(entry: dict, name: str, tmp_path) -> dict:
    """Run a manifest entry's command into ``tmp_path`` (its dataset first when it has a ``data_command``); the
    new entry, after checking its data fingerprint and metrics against ``entry``."""
    from scenarios.cli import main

    args = shlex.split(entry["command"])[1:]
    if "data_command" in entry:
        data = shlex.split(entry["data_command"])[1:]
        data[data.index("--out") + 1] = str(tmp_path / "data.npz")
        assert main(data) == 0
        args[args.index("--data") + 1] = str(tmp_path / "data.npz")
    args[args.index("--out") + 1] = str(tmp_path)
    assert main(args) == 0
    new = json.loads((tmp_path / "manifest.json").read_text())[name]
    assert new["data"]["fingerprint"] == entry["data"]["fingerprint"]
    for group in ("one_step_mae", "rollout_100_mae"):
        for key in ("position", "z", "phi", "vz"):
            old, now = entry["metrics"][group][key], new["metrics"][group][key]
            assert abs(now - old) <= TOL["reproduce"] * old, (group, key, old, now)
    return new


@pytest.mark.retrain
@pytest.mark.parametrize("name", sorted(IDENT_MANIFEST))
def test_retraining_an_identification_model_reproduces_it(tmp_path, name):
    """Run a models/identification manifest command into a temporary folder (5-8 minutes each)."""
    entry = IDENT_MANIFEST[name]
    new = _retrain(entry, name, tmp_path)
    for key, old in entry["theta_err_pct"].items():
        now = new["theta_err_pct"][key]
        assert abs(now - old) <= TOL["reproduce_theta"] * abs(old) + 0.01, (key, old, now)


@pytest.mark.retrain
@pytest.mark.parametrize("name", sorted(VERSUS_MANIFEST))
def test_retraining_a_versus_model_reproduces_it(tmp_path, name):
    """Retrain a models/versus model (5-10 minutes); RotorPy's dataset first, with the manifest's data command
    (about 4 minutes)."""
    _retrain(VERSUS_MANIFEST[name], name, tmp_path)


def test_the_open_loop_models_with_the_term_library_record_their_terms():
    """Each model trained with ``--aero select`` states its terms in its metadata as in its manifest entry; on our
    high-fidelity plant the one term is the plant's rotor drag, identified with ``rotor_drag / m`` inside its 95 %
    interval."""
    import onnx

    from sim.params import FIDELITIES, QuadParams

    for name in ("hybrid_lag_aero_aggressive_highfi", "hybrid_lag_aero_rotorpy"):
        entry = VERSUS_MANIFEST[name]
        meta = {p.key: p.value for p in onnx.load(str(VERSUS / entry["files"]["onnx"])).metadata_props}
        record = json.loads(meta["aero_terms"])
        assert record["terms"] and record["terms"] == entry["aero"]["terms"]
        # the file's from the float64 export, the manifest's from the float32 model that was trained
        assert record["coefficients"] == pytest.approx(entry["aero"]["coefficients"], rel=1e-6)
        assert "--aero select" in entry["command"]
    got = VERSUS_MANIFEST["hybrid_lag_aero_aggressive_highfi"]["aero"]
    truth = FIDELITIES["high"].rotor_drag / QuadParams().m
    assert got["terms"] == ["rotor_drag"]
    assert got["identified"]["k_r"]["low"] <= truth <= got["identified"]["k_r"]["high"]


def test_the_open_loop_models_at_ctbr_are_shipped_at_their_level_with_their_record():
    """Each declares ctbr with its derivative graph and the register of its history, and its manifest entry names
    its data (flown at ctbr on its plant) and the rate time constants of its physics (the vehicle file's)."""
    from pinn.ctbr import CTBR_ARCH, CTBR_HISTORY
    from pinn.flights import register_names
    from sim.vehicles.vehicle import load_vehicle

    assert set(VERSUS_CTBR_MANIFEST) == REQUIRED_VERSUS_CTBR
    tau = list(load_vehicle(None).inner_loop_at("ctbr").response().rate_tau)
    for name, entry in VERSUS_CTBR_MANIFEST.items():
        info = check_model(VERSUS_CTBR / entry["files"]["onnx"])
        assert info.level == "ctbr" and info.jacobian == jacobian_path(VERSUS_CTBR / f"{name}.onnx")
        assert info.architecture == CTBR_ARCH and tuple(info.extra_states) == register_names(CTBR_HISTORY, "ctbr")
        assert entry["data"]["level"] == "ctbr" and entry["plant"] == name.rsplit("_", 1)[1].replace("highfi", "sim")
        assert ("aggressive" in name) == (entry["data"]["regime"] == "aggressive")
        assert entry["rate_tau_s"] == pytest.approx(tau, rel=1e-12)


@pytest.mark.retrain
@pytest.mark.parametrize("name", sorted(VERSUS_CTBR_MANIFEST))
def test_retraining_a_ctbr_versus_model_reproduces_it(tmp_path, name):
    """Fly its dataset again at ctbr (the manifest's data command: 20 s on our plant, 2 minutes on RotorPy) and
    retrain it (about 2 minutes): the same data, test errors within 5 %."""
    from scenarios.cli import main

    entry = VERSUS_CTBR_MANIFEST[name]
    data = shlex.split(entry["data_command"])[1:]
    data[data.index("--out") + 1] = str(tmp_path / "data.npz")
    assert main(data) == 0
    args = shlex.split(entry["command"])[1:]
    args[args.index("--data") + 1] = str(tmp_path / "data.npz")
    args[args.index("--out") + 1] = str(tmp_path)
    assert main(args) == 0
    new = json.loads((tmp_path / "manifest.json").read_text())[name]
    assert new["data"]["fingerprint"] == entry["data"]["fingerprint"]
    for q, old in entry["test_errors"].items():
        assert np.allclose(new["test_errors"][q], old, rtol=TOL["reproduce"], atol=0), (q, old, new["test_errors"][q])
