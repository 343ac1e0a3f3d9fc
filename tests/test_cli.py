"""The pinnmpc command line: data and fisher commands, clean errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from scenarios.cli import main
from sim.identification.excitation import load_dataset, make_dataset


def test_data_command_writes_dataset_and_summary(tmp_path, capsys):
    out, js = tmp_path / "d.npz", tmp_path / "d.json"
    code = main(["data", "--regime", "small", "--n-traj", "4", "--duration", "2", "--seed", "3",
                 "--out", str(out), "--json", str(js)])
    assert code == 0
    ds = load_dataset(out)
    ref = make_dataset("small", 4, 2.0, 3)
    assert np.array_equal(ds.x, ref.x)
    summary = json.loads(js.read_text())
    assert summary["samples"] == 4 * 200
    assert summary["max_abs_roll_deg"] == pytest.approx(np.degrees(np.abs(ref.x[..., 3])).max())
    text = capsys.readouterr().out
    assert "800 samples" in text and "max |roll|" in text and "saturated" in text


@pytest.mark.parametrize("args,needle", [
    (["--regime", "medium"], "regime"),
    (["--regime", "small", "--duration", "-2"], "duration"),
    (["--regime", "small", "--n-traj", "0"], "n_traj"),
])
def test_data_command_bad_input_is_a_one_line_error(tmp_path, capsys, args, needle):
    code = main(["data", *args, "--out", str(tmp_path / "x.npz")])
    err = capsys.readouterr().err
    assert code == 2
    assert needle in err and "Traceback" not in err
    assert not (tmp_path / "x.npz").exists()


def test_fisher_command_table_and_json(tmp_path, capsys):
    js = tmp_path / "f.json"
    assert main(["fisher", "--n-traj", "2", "--duration", "3", "--json", str(js)]) == 0
    table = json.loads(js.read_text())
    ranks = {(c["regime"], c["inputs"]): c["rank"] for c in table["cases"]}
    assert ranks == {("small", "wrench"): 6, ("small", "motor"): 5,
                     ("aggressive", "wrench"): 6, ("aggressive", "motor"): 5}
    for c in table["cases"]:
        if c["inputs"] == "motor":
            assert c["weakest_vs_scale_direction_abs_cos"] > 0.999
            assert all(v is None for v in c["crlb_pct"].values())
    text = capsys.readouterr().out
    assert "CRLB" in text and "aggressive" in text and "Jxx" in text


def test_console_script_help_runs_without_traceback():
    r = subprocess.run([sys.executable, "-m", "scenarios.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "data" in r.stdout and "fisher" in r.stdout


@pytest.mark.slow
def test_train_check_and_evaluate_round_trip(tmp_path, capsys):
    """Quick training through the CLI, the contract check of its export, and Tables I/II from it."""
    data = make_dataset("small", 10, 5.0, 4).save(tmp_path / "d.npz")
    out = tmp_path / "m"
    assert main(["train", "--arch", "baseline", "--profile", "quick", "--data", str(data), "--out", str(out)]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    entry = manifest["baseline"]
    assert entry["command"].startswith("pinnmpc train --arch baseline --profile quick --seed 0 --data ")
    assert {"onnx", "jacobian", "torch"} == set(entry["files"]) and entry["training_seconds"] > 0
    assert main(["check-model", str(out / "baseline.onnx")]) == 0
    assert main(["evaluate", str(out)]) == 0
    ev = json.loads((out / "evaluation.json").read_text())
    row = ev["models"][0]
    # The ONNX evaluation reproduces the torch metrics stored at training time.
    assert row["rollout_100"]["position"] == pytest.approx(entry["metrics"]["rollout_100_mae"]["position"], rel=1e-9)
    assert set(row["err_over_crlb"]) == {"m", "Jxx", "Jyy", "Jzz", "kt", "kq"}
    text = capsys.readouterr().out
    assert "Table I" in text and "Table II" in text and "paper" in text
    # The classical estimator ran on the same training split, and sits within 3 CRLB sigma of the truth.
    (fit,) = ev["datasets"]
    assert fit["models"] == ["baseline"] and fit["crlb_std"] == row["crlb_std"]
    assert max(fit["estimator"]["err_over_crlb"].values()) < 3.0
    assert "classical, small" in text
    # The ablation can take this run instead of training the same configuration again.
    from pinn.cli import _reusable
    hit = _reusable(out, "baseline", entry["data"], "quick", 0)
    assert hit is not None and hit[2] == entry["metrics"]
    assert _reusable(out, "baseline", entry["data"], "quick", 1) is None
    assert _reusable(out, "baseline+curriculum", entry["data"], "quick", 0) is None


def test_evaluate_rejects_an_empty_folder(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "no .onnx models" in capsys.readouterr().err


@pytest.mark.slow
def test_data_from_another_plant_and_vehicle_trains_unchanged(tmp_path, capsys):
    """`pinnmpc data --plant rotorpy-ideal --vehicle hummingbird` writes the usual format; `pinnmpc train` takes it."""
    from sim.plants.plant import SimPlant
    from sim.vehicles.vehicle import load_vehicle

    pytest.importorskip("rotorpy")
    out = tmp_path / "hb.npz"
    assert main(["data", "--regime", "small", "--n-traj", "6", "--duration", "3", "--seed", "2", "--noise", "none",
                 "--plant", "rotorpy-ideal", "--vehicle", "hummingbird", "--out", str(out)]) == 0
    ds = load_dataset(out)
    assert (ds.meta["plant"], ds.meta["vehicle"], ds.meta["params"]["m"]) == ("rotorpy-ideal", "hummingbird", 0.5)
    assert ds.meta["params"]["c_d"] == 0.0          # RotorPy's ideal set-up has no drag, so its truth has none
    # Each sample is one period of that plant: the same as one of our simulator with the vehicle and no drag.
    sim = SimPlant(load_vehicle("hummingbird").replace(c_d=0.0))
    worst = 0.0
    for i, k in [(0, 0), (2, 150), (5, 299)]:
        sim.reset(ds.x[i, k])
        worst = max(worst, float(np.max(np.abs(sim.step(ds.u[i, k]).x - ds.x_next[i, k]))))
    assert worst < 1e-9
    m = tmp_path / "m"
    assert main(["train", "--arch", "baseline", "--profile", "quick", "--data", str(out), "--out", str(m)]) == 0
    assert main(["check-model", str(m / "baseline.onnx")]) == 0
    # The prior is the data's vehicle biased, not the Rolling Spider: theta-hat is of the Hummingbird's size.
    from mpc.prediction.contract import check_model
    assert 0.3 < check_model(m / "baseline.onnx").theta["m"] < 0.8
    capsys.readouterr()
