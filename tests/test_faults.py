"""Faults a user or a fault tester finds: commands that check their input and outputs before they work, bounds that
never exempt a run that did not fly, a code version that covers code only.

Each test names the defect it covers. Paths that cannot be written are made by putting them under a file (a folder
that cannot exist), which holds for every user, root included.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import scenarios.runner as runner
from scenarios.bounds import ORACLE_CASES, Bound, check, generate
from scenarios.cli import main
from scenarios.errors import BoundsError, ScenarioError
from scenarios.runner import MAX_HORIZON, RunSpec

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def no_flight(monkeypatch):
    """Any flight fails the test: the command must stop before it."""
    def fly(*a, **k):
        raise AssertionError("flew before checking its input")
    monkeypatch.setattr(runner, "fly", fly)


def unwritable(tmp_path, name):
    """A path under a plain file: no folder can be made there."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    return blocker / name


# ----------------------------------------------------------------- outputs checked before the work (defect 5)

@pytest.mark.parametrize("option,name", [("--json", "r.json"), ("--trace", "t.npz"), ("--plot", "p.png")])
def test_fly_refuses_an_output_it_cannot_write_before_it_flies(tmp_path, capsys, no_flight, option, name):
    rc = main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover", option,
               str(unwritable(tmp_path, name))])
    err = capsys.readouterr().err
    assert rc == 2 and f"{option} " in err and "cannot be written" in err and "Traceback" not in err


@pytest.mark.parametrize("command", [["run"], ["study"], ["versus"]])
def test_sweeps_refuse_an_output_folder_they_cannot_write_before_they_start(tmp_path, capsys, monkeypatch, command):
    import scenarios.campaign as campaign
    import scenarios.versus as versus
    import scenarios.zoo as zoo

    for mod, fn in ((campaign, "run_main_job"), (zoo, "run_study"), (versus, "run_versus")):
        monkeypatch.setattr(mod, fn, lambda *a, **k: pytest.fail("started before checking --out"))
    rc = main(command + ["--out", str(unwritable(tmp_path, "out"))])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "cannot be written" in err


# ----------------------------------------------------------------- --horizon checked when the line is read (defect 9)

@pytest.mark.parametrize("value", ["0", "-5", str(MAX_HORIZON + 1), "100000", "ten"])
@pytest.mark.parametrize("controller", ["lqr", "sqp"])
def test_a_bad_horizon_is_refused_when_the_command_line_is_read(capsys, no_flight, value, controller):
    with pytest.raises(SystemExit) as e:
        main(["fly", "--model", "oracle", "--controller", controller, "--scenario", "hover", "--horizon", value])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--horizon" in err and "Traceback" not in err
    if value != "ten":
        assert f"1 to {MAX_HORIZON}" in err


def test_the_horizon_bound_holds_for_runs_made_in_python_too():
    assert RunSpec("hover", "sqp", horizon=MAX_HORIZON).horizon == MAX_HORIZON
    for bad in (0, MAX_HORIZON + 1, 2.5, True):
        with pytest.raises(ScenarioError, match="horizon must be an integer"):
            RunSpec("hover", "sqp", horizon=bad)


# ----------------------------------------------------------------- --trace writes the path given (defect 10)

def test_trace_is_written_to_exactly_the_path_given(tmp_path, capsys):
    path = tmp_path / "trace-without-suffix"
    assert main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover", "--trace", str(path)]) == 0
    assert f"wrote {path}\n" in capsys.readouterr().out
    assert path.is_file() and not Path(str(path) + ".npz").exists()
    with np.load(path) as tr:
        assert tr["x"].shape[1] == 12 and tr["x"].shape[0] == tr["t"].shape[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]      # no temporary file left


# ----------------------------------------------------------------- bounds (defects 6 and 11)

def oracle_results(changes=None):
    """A measured result for each of the oracle's bound cases; ``changes`` ({(scenario, controller): fields})
    update some."""
    out = []
    for scenario, controller, metric in ORACLE_CASES:
        r = {"scenario": scenario, "controller": controller, "model": "oracle", "timing": "ideal", "plant": "sim",
             "crashed": False, "error": None, metric: 1e-3}
        r.update((changes or {}).get((scenario, controller), {}))
        out.append(r)
    return out


def test_bounds_are_not_written_from_a_run_that_never_flew():
    assert "known_failure = false" in generate(oracle_results(), [])
    never = {("hover", "lqr"): {"error": "ConfigurationError: no LQR gain", "settled_error_m": None}}
    with pytest.raises(BoundsError, match="never flew"):
        generate(oracle_results(never), [])


def test_a_known_failure_is_exempt_from_a_crash_but_not_from_a_run_that_never_flew():
    b = Bound("hover", "lqr", "oracle", "settled_error_m", 1e-3, known_failure=True)
    crashed = oracle_results({("hover", "lqr"): {"crashed": True, "settled_error_m": None, "crash_time_s": 1.0,
                                                 "crash_reason": "below ground"}})
    assert check([b], crashed)[0]["ok"] is None
    never = oracle_results({("hover", "lqr"): {"error": "ModelContractError: bad file", "settled_error_m": None}})
    row = check([b], never)[0]
    assert row["ok"] is False and "error" in row["why"]


def results_folder(tmp_path, text):
    d = tmp_path / "results"
    d.mkdir()
    (d / "results.json").write_text(text)
    return d


@pytest.mark.parametrize("text,why", [('{"plan": {}}', "list of runs"), ('{"runs": [', "not a readable JSON"),
                                      ('[1, 2]', "list of runs")])
def test_bounds_errors_name_the_results_file(tmp_path, capsys, text, why):
    d = results_folder(tmp_path, text)
    rc = main(["bounds", str(d), "--out", str(tmp_path / "b.toml")])
    err = capsys.readouterr().err
    assert rc == 2 and str(d / "results.json") in err and why in err and "Traceback" not in err
    assert not (tmp_path / "b.toml").exists()


def test_bounds_refuse_an_output_they_cannot_write_before_reading_the_results(tmp_path, capsys):
    d = results_folder(tmp_path, json.dumps({"runs": oracle_results()}))
    rc = main(["bounds", str(d), "--out", str(unwritable(tmp_path, "b.toml"))])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "cannot be written" in err


# ----------------------------------------------------------------- the code version covers code (defect 12)

def test_the_code_version_covers_python_source_not_the_bounds_file(tmp_path, monkeypatch):
    for pkg in ("sim", "mpc", "scenarios"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(runner, "__file__", str(tmp_path / "scenarios" / "runner.py"))

    def version():
        monkeypatch.setattr(runner, "_CODE_VERSION", None)
        return runner.code_version()

    before = version()
    with open(tmp_path / "scenarios" / "bounds.toml", "a") as f:
        f.write("\n# bounds written again\n")
    assert version() == before
    with open(tmp_path / "mpc" / "ltv.py", "a") as f:
        f.write("\n# a change of code\n")
    assert version() != before


# ----------------------------------------------------------------- a cache keyed by what was flown (defects 1, 2, 8)

def copied_model(tmp_path, name="baseline"):
    d = tmp_path / "models"
    d.mkdir(exist_ok=True)
    for suffix in (".onnx", ".jac.onnx"):
        shutil.copy(ROOT / "models" / f"{name}{suffix}", d / f"baseline{suffix}")
    return d / "baseline.onnx"


def test_the_cache_key_covers_the_derivative_graph(tmp_path):
    from scenarios.runner import cache_key

    model = copied_model(tmp_path)
    spec = RunSpec("hover", "lqr", str(model))
    with_graph = cache_key(spec)
    jac = model.with_name("baseline.jac.onnx")
    jac.unlink()                                       # the controllers now take central differences
    without = cache_key(spec)
    shutil.copy(ROOT / "models" / "proposed.jac.onnx", jac)
    assert len({with_graph, without, cache_key(spec)}) == 3


def test_a_model_swapped_mid_sweep_leaves_each_result_with_the_hash_of_what_it_flew(tmp_path):
    """The swap test: after the first run returns, the model file is replaced; every result carries the hash of the
    file it flew (its RMSE is that file's), and once the original is back a resume flies exactly the others."""
    from scenarios.runner import fly, input_hashes
    from scenarios.sweep import sweep

    model = copied_model(tmp_path)
    specs = [RunSpec(sc, "lqr", str(model)) for sc in ("hover", "hover+noise", "figure8-slow")]
    original = input_hashes(specs[0])
    flown = []

    def swap_after_first(result):
        flown.append(result["run_id"])
        if len(flown) == 1:
            copied_model(tmp_path, "proposed")

    out = tmp_path / "out"
    results = sweep(specs, out, jobs=1, progress=False, on_result=swap_after_first)
    swapped = input_hashes(specs[0])
    assert swapped["model"] != original["model"]
    first = flown[0]
    for s, r in zip(specs, results):
        assert r["inputs_sha256"] == (original if s.run_id == first else swapped)
        if s.run_id != first:                          # flown with the replacement: its numbers are the replacement's
            assert r["rmse_position_m"] == fly(s)[0]["rmse_position_m"]
    copied_model(tmp_path, "baseline")                 # the original back
    (s1, r1), = [(s, r) for s, r in zip(specs, results) if s.run_id == first]
    assert r1["rmse_position_m"] == fly(s1)[0]["rmse_position_m"]
    again = []
    sweep(specs, out, jobs=1, progress=False, on_result=lambda r: again.append(r["run_id"]))
    assert sorted(again) == sorted(set(flown) - {first})


def test_a_torn_trace_is_flown_again_with_a_line_saying_so(tmp_path, capsys):
    from scenarios.sweep import sweep

    spec = RunSpec("hover", "lqr", "oracle")
    out = tmp_path / "out"
    (r,) = sweep([spec], out, jobs=1, progress=False)
    trace = out / r["trace"]
    data = trace.read_bytes()
    trace.write_bytes(data[: len(data) // 2])
    again = []
    (r2,) = sweep([spec], out, jobs=1, progress=False, on_result=lambda res: again.append(res["run_id"]))
    assert again == [spec.run_id] and "flying hover__lqr__oracle again" in capsys.readouterr().err
    assert r2["rmse_position_m"] == r["rmse_position_m"]
    with np.load(out / r2["trace"]) as tr:
        assert tr["x"].shape[0] == tr["t"].shape[0]
    (runs_json,) = (out / "runs").iterdir()
    runs_json.write_text('{"run_id": ')          # a torn result: flown again too, not a traceback
    again.clear()
    sweep([spec], out, jobs=1, progress=False, on_result=lambda res: again.append(res["run_id"]))
    assert again == [spec.run_id] and "damaged" in capsys.readouterr().err
