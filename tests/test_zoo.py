"""The model zoo: its variant architectures, its settings' bookkeeping, its metrics, and the study's pieces.

The variants' forward-mode Jacobians are checked against autograd with the four architectures' in test_pinn.py.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from pinn.metrics import ENVELOPE_POSITION_M, rollout_mae
from pinn.models import VARIANT_DEFAULTS, build_model
from pinn.train import make_config, train
from pinn.zoo import RUNS, zoo_names
from test_pinn import fake_stats as stats   # the same synthetic normalization statistics
from scenarios.errors import ScenarioError
from sim import NoiseModel, QuadParams

TOL = {
    "kstep_oracle": 1e-9,   # k-step error of the true model along its own noise-free flight, m
}
#: Acceptance of the zoo's size: at least this many models.
MIN_ZOO = 24
ZOO_DIR = Path(__file__).resolve().parents[1] / "models" / "zoo"
P = QuadParams()

torch.set_num_threads(1)


def random_xu(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(n, 12, generator=g, dtype=torch.float64) * 0.3,
            torch.randn(n, 4, generator=g, dtype=torch.float64) * 0.3)


def test_decoupled_modular_translation_does_not_see_the_attitude():
    m = build_model("modular", stats(), P.theta, hidden=16, layers=2, variant={"coupled": False}).double().eval()
    x, u = random_xu(8)
    tilted = x.clone()
    tilted[:, 3:9] += 0.2          # angles and body rates
    d = m(tilted, u) - tilted - (m(x, u) - x)
    trans = [0, 1, 2, 9, 10, 11]
    assert torch.all(d[:, trans] == 0)
    assert torch.all(d[:, 3:9].abs().sum(1) > 0)     # the rotation module does see them
    coupled = build_model("modular", stats(), P.theta, hidden=16, layers=2).double().eval()
    dc = coupled(tilted, u) - tilted - (coupled(x, u) - x)
    assert torch.all(dc[:, trans].abs().sum(1) > 0)


def test_fourier_frequencies_and_softplus_is_unbounded():
    f = build_model("fourier", stats(), P.theta, hidden=8, layers=1, variant={"fourier_max": 12})
    assert f.freqs.tolist() == [2.0 ** k for k in range(13)]
    assert build_model("fourier", stats(), P.theta, hidden=8, layers=1).freqs.tolist()[-1] == 256.0
    out = {}
    for act in ("tanh", "softplus"):
        m = build_model("baseline", stats(), P.theta, hidden=8, layers=1, variant={"activation": act}).double()
        with torch.no_grad():
            m.mlp.out.weight.fill_(1.0)
            m.mlp.hidden[0].weight.fill_(1.0)
            m.mlp.hidden[0].bias.fill_(0.0)
            out[act] = [m.mlp(torch.full((1, 13), s, dtype=torch.float64))[0, 0].item() for s in (1.0, 1e3)]
    # 8 units of 13 s each: tanh saturates at 8, softplus(13 s) = 13 s for large s
    assert out["tanh"][1] == pytest.approx(8.0) and out["softplus"][1] == pytest.approx(8 * 13e3)


def test_variant_settings_stay_out_of_the_shipped_configs():
    shipped = json.loads((ZOO_DIR.parent / "manifest.json").read_text())
    for name in ("baseline", "proposed"):
        cfg = make_config(name, "full", 0, threads=1).to_dict()
        assert not set(VARIANT_DEFAULTS) & set(cfg)
        assert shipped[name]["profile"] == "full"
    cfg = make_config("baseline", "quick", 0, activation="softplus", gain=10.0).to_dict()
    assert cfg["activation"] == "softplus" and cfg["gain"] == 10.0 and "coupled" not in cfg
    with pytest.raises(ValueError, match="variant keys"):
        build_model("baseline", stats(), P.theta, variant={"width": 3})
    with pytest.raises(ValueError, match="activation"):
        build_model("baseline", stats(), P.theta, variant={"activation": "relu"})


def test_checkpoints_are_the_model_after_that_many_epochs():
    from sim.identification.excitation import make_dataset
    ds = make_dataset("small", 6, 3.0, 0)
    cfg = make_config("baseline", "quick", 0, epochs=3, steps_per_epoch=4, batch=64, n_colloc=16, hidden=16, layers=2)
    full = train(ds, cfg, checkpoints=(1, 3))
    short = train(ds, make_config("baseline", "quick", 0, epochs=3, steps_per_epoch=4, batch=64, n_colloc=16,
                                  hidden=16, layers=2), checkpoints=(3,))
    assert sorted(full.checkpoints) == [1, 3]
    x, u = random_xu(4)
    m3, m1 = full.checkpoints[3].double(), full.checkpoints[1].double()
    torch.testing.assert_close(m3(x, u), short.model.double()(x, u), rtol=0, atol=0)
    assert not torch.equal(m1(x, u), m3(x, u))
    with pytest.raises(ValueError, match="checkpoints"):
        train(ds, cfg, checkpoints=(4,))


def test_envelope_exits_are_counted():
    from sim.identification.excitation import make_dataset
    ds = make_dataset("small", 10, 3.0, 1, noise=NoiseModel.none())

    from sim import Simulator
    sim = Simulator(P)

    def drifts(x, u):          # the true step plus 2 cm in x: 1 m of error after 50 steps, never diverged
        y = sim.step(x, u)
        y[:, 0] += 0.02
        return y
    r = rollout_mae(drifts, ds, horizon=100, n_starts=30)
    assert r["n_diverged"] == 0 and r["n_left_envelope"] == 30
    r = rollout_mae(drifts, ds, horizon=40, n_starts=30)     # 0.8 m at most: inside
    assert 0.02 * 40 < ENVELOPE_POSITION_M and r["n_left_envelope"] == 0


def test_zoo_definition():
    names = zoo_names()
    assert len(names) == len(set(names)) >= MIN_ZOO
    assert len({r.name for r in RUNS}) == len(RUNS)
    for r in RUNS:
        cfg = make_config(r.arch, r.profile, 0, **r.overrides)
        assert r.checkpoints[-1] == cfg.epochs, r.name
        assert r.data_seed != 0 or (r.n_traj == 100 and r.noise_mult == 1.0), \
            f"{r.name}: reduced or noisier data must not be drawn from the test data's seed"


def test_closed_loop_kstep_error_of_the_true_model_is_zero():
    from mpc.prediction.models import AnalyticModel
    from scenarios.studies.zoo import closed_loop_kstep_error
    from sim import Simulator

    sim = Simulator(P)
    rng = np.random.default_rng(0)
    X = [np.array([0, 0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0])]
    U = P.m * P.g * np.array([1.0, 0, 0, 0]) + 0.01 * rng.standard_normal((80, 4)) * [1, 0.01, 0.01, 0.01]
    for u in U:
        X.append(sim.step(X[-1], u))
    trace = {"x": np.array(X), "u": U}
    assert closed_loop_kstep_error(AnalyticModel(), trace, k=30) < TOL["kstep_oracle"]
    biased = AnalyticModel(QuadParams(m=1.2 * P.m))          # 20 % heavier: it sinks in 0.3 s
    e = closed_loop_kstep_error(biased, trace, k=30)
    # free-fall share g/6 for 0.3 s: 0.5 * (g - g / 1.2) * 0.3^2, to the RK4 step's accuracy
    assert e == pytest.approx(0.5 * (P.g - P.g / 1.2) * 0.3 ** 2, rel=0.02)


@pytest.mark.skipif(not (ZOO_DIR / "manifest.json").is_file(), reason="the zoo is not trained here")
def test_shipped_zoo_spans_the_required_range_and_passes_the_contract():
    from mpc.prediction.contract import check_model

    manifest = json.loads((ZOO_DIR / "manifest.json").read_text())
    refused = json.loads((ZOO_DIR / "refused.json").read_text()) if (ZOO_DIR / "refused.json").is_file() else {}
    assert set(manifest) | set(refused) == set(zoo_names()) and not set(manifest) & set(refused)
    assert len(manifest) >= MIN_ZOO
    assert all("LQR" in e["reason"] and not (ZOO_DIR / f"{n}.onnx").exists() for n, e in refused.items())
    mae = {n: e["metrics"]["rollout_100_mae"]["position"] for n, e in manifest.items()}
    left = {n: e["metrics"]["rollout_100_mae"]["n_left_envelope"] / e["metrics"]["rollout_100_mae"]["n_rollouts"]
            for n, e in manifest.items()}
    assert min(mae.values()) <= 0.01 and max(mae.values()) >= 1.0
    assert sum(0.01 <= v < 0.1 for v in mae.values()) >= 3 and sum(0.1 <= v < 1.0 for v in mae.values()) >= 3
    assert sum(v >= 0.1 for v in left.values()) >= 3
    size = sum(p.stat().st_size for p in ZOO_DIR.iterdir())
    assert size < 40e6
    for n, e in manifest.items():
        info = check_model(ZOO_DIR / e["files"]["onnx"])
        assert info.jacobian is not None, n


CONTROLLERS = ("lqr", "ltv", "sqp", "nmpc")


def _first_inputs(name: str) -> dict:
    from mpc.prediction.models import load_model
    from scenarios.closed_loop.library import get_scenario
    from mpc.controllers.factory import make_controller

    sc = get_scenario("figure8-fast")
    model = load_model(str(ZOO_DIR / f"{name}.onnx"))
    out = {}
    for kind in CONTROLLERS:
        ctrl = make_controller(kind, model, sc.reference())
        ctrl.prepare(1.0, x0=np.array(sc.x0, dtype=float))
        u, _ = ctrl(np.array(sc.x0, dtype=float), 0.0)
        out[kind] = np.asarray(u)
    return out


def _assert_flyable(name: str):
    for kind, u in _first_inputs(name).items():
        assert u.shape == (4,) and np.all(np.isfinite(u)), f"{name} / {kind}: {u}"


@pytest.mark.slow
@pytest.mark.skipif(not (ZOO_DIR / "manifest.json").is_file(), reason="the zoo is not trained here")
def test_every_controller_takes_every_zoo_model():
    """LQR, LTV-MPC, SQP and IPOPT are built on every zoo model and return a finite first input (about 20 s)."""
    for name in json.loads((ZOO_DIR / "manifest.json").read_text()):
        _assert_flyable(name)


@pytest.mark.slow
@pytest.mark.skipif(not (ZOO_DIR / "manifest.json").is_file(), reason="the zoo is not trained here")
def test_study_of_a_two_model_zoo(tmp_path):
    """The most and one of the least accurate zoo models, 2 members, LTV-MPC: outcomes, scores, rescoring, resume."""
    import shutil

    from scenarios.studies.zoo import CANDIDATES, rescore_study, run_study

    manifest = json.loads((ZOO_DIR / "manifest.json").read_text())
    zoo = tmp_path / "zoo"
    zoo.mkdir()
    keep = {k: manifest[k] for k in ("baseline_long", "absolute_e8")}
    for e in keep.values():
        for f in e["files"].values():
            shutil.copy(ZOO_DIR / f, zoo / f)
    (zoo / "manifest.json").write_text(json.dumps(keep))
    out = run_study(zoo, tmp_path / "res", members=2, jobs=1, controllers=("ltv",), progress=False)
    assert out["runs"] == 1 + 2 * 2 + 2 * 6      # oracle, ensembles, ladder
    assert json.loads((zoo / "study.json").read_text()) == json.loads((tmp_path / "res" / "study.json").read_text())
    good, bad = out["models"]["baseline_long"], out["models"]["absolute_e8"]
    assert good["ensembles"]["ltv"]["crash_probability"] == 0.0 and bad["ensembles"]["ltv"]["crash_probability"] == 1.0
    assert bad["max_speed"]["speed_mps"] is None and good["max_speed"]["speed_mps"] > 0
    # Every candidate ranks the 1.2 m model above the 9 mm one: AUC 1 over these two models.
    assert {s["candidate"]: s["auc"] for s in out["scores"]["ltv"]} == {c: 1.0 for c in CANDIDATES}
    again = rescore_study(zoo, tmp_path / "res")
    assert again["scores"] == out["scores"] and again["models"] == out["models"]
    runs_before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "res" / "runs").iterdir()}
    run_study(zoo, tmp_path / "res", members=2, jobs=1, controllers=("ltv",), progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "res" / "runs").iterdir()} == runs_before


def test_the_study_flies_on_the_plant_and_vehicle_it_is_given(tmp_path, capsys):
    from scenarios.cli import main
    from scenarios.studies.zoo import study_specs

    models = {"a": {"path": str(Path(__file__).resolve().parents[1] / "models" / "baseline.onnx")}}
    ref, ens, ladder = study_specs(models, 2, ("sqp",), plant="rotorpy", vehicle="hummingbird")
    every = [ref, *ens, *ladder]
    assert {(s.plant, s.vehicle_data.name) for s in every} == {("rotorpy", "hummingbird")}
    assert ref.model == "nominal"          # RotorPy with aerodynamics has no oracle: the reference is the nominal one
    assert study_specs(models, 2, ("sqp",))[0].model == "oracle"
    # Publishing a study flown elsewhere over the shipped zoo's study.json is refused before anything flies.
    assert main(["study", "--plant", "rotorpy", "--members", "1", "--out", str(tmp_path / "z")]) == 2
    assert "--no-publish" in capsys.readouterr().err and not (tmp_path / "z").exists()


def test_the_study_with_the_estimator_flies_its_ensembles_with_it_and_selects_models(tmp_path, capsys):
    from scenarios.cli import main
    from scenarios.studies.zoo import select_models, study_file, study_specs

    path = str(Path(__file__).resolve().parents[1] / "models" / "baseline.onnx")
    models = {"a": {"path": path}, "b": {"path": path}, "c": {"path": path}}
    ref, ens, ladder = study_specs(models, 3, ("sqp", "ltv"), estimator="ekf")
    assert ref.estimator == "none" and ladder == []       # the reference flight scores the open-loop candidates
    assert len(ens) == 3 * 3 * 2 and {s.estimator for s in ens} == {"ekf"}
    assert all(s.run_id.endswith("__ekf") for s in ens)
    assert len(study_specs(models, 3, ("sqp",))[2]) > 0   # without it, the ladder flies
    assert list(select_models(models, ["c", "a"])) == ["a", "c"]
    with pytest.raises(ScenarioError, match="no model 'z' in the zoo"):
        select_models(models, ["a", "z"])
    assert (study_file("none"), study_file("ekf")) == ("study.json", "study_ekf.json")
    # A partial study without the estimator would replace the zoo's study.json: refused before anything flies.
    assert main(["study", "--select", "baseline_e1", "--out", str(tmp_path / "z")]) == 2
    assert "--no-publish" in capsys.readouterr().err and not (tmp_path / "z").exists()


@pytest.mark.slow
def test_a_folder_without_a_manifest_is_studied_from_its_model_files(tmp_path, capsys):
    """Its models are checked and evaluated open loop on the zoo's test data: the same errors as the zoo's manifest
    recorded from the training run's torch model (onnxruntime on the exported file)."""
    import shutil

    from scenarios.studies.zoo import zoo_models

    manifest = json.loads((ZOO_DIR / "manifest.json").read_text())
    names = list(manifest)[:2]
    for n in names:
        shutil.copy(ZOO_DIR / manifest[n]["files"]["onnx"], tmp_path / f"{n}.onnx")
    models = zoo_models(tmp_path, progress=True)
    assert "has no manifest.json: evaluating its 2 models" in capsys.readouterr().err
    assert list(models) == sorted(names)
    for n in names:
        got, want = models[n]["metrics"], manifest[n]["metrics"]
        for metric in ("one_step_mae", "rollout_100_mae"):
            assert got[metric]["position"] == pytest.approx(want[metric]["position"], rel=1e-9, abs=0)
        assert got["rollout_100_mae"]["n_rollouts"] == want["rollout_100_mae"]["n_rollouts"]
        assert models[n]["path"] == str(tmp_path / f"{n}.onnx")
    # A file that fails the contract is recorded with its reason; the others are studied.
    (tmp_path / "broken.onnx").write_bytes(b"not a model")
    again = zoo_models(tmp_path)
    assert "broken.onnx" in again["broken"]["failed"] and "metrics" not in again["broken"]
    assert all("failed" not in again[n] for n in names)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ScenarioError, match="no manifest.json and no .onnx model"):
        zoo_models(empty)
