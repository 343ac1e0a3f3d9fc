"""Faults a user or a fault tester finds: commands that check their input and outputs before they work, bounds that
never exempt a run that did not fly, a code version that covers code only, a cache keyed by what was flown, sweeps
that outlive their workers and leave none behind, one sweep per folder, check-model over the flight envelope, and
the SQP's budget on a slower machine.

Each section's heading names the fault it covers. Paths that cannot be written are made by putting them under a
file (a folder that cannot exist), which holds for every user, root included.
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import scenarios.closed_loop.record as record
import scenarios.closed_loop.runner as runner
from scenarios.studies.bounds import ORACLE_CASES, Bound, check, generate
from scenarios.cli import main
from scenarios.errors import BoundsError, ScenarioError
from scenarios.closed_loop.runner import MAX_HORIZON, RunSpec

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


# ----------------------------------------------------------------- outputs checked before the work

@pytest.mark.parametrize("option,name", [("--json", "r.json"), ("--trace", "t.npz"), ("--plot", "p.png")])
def test_fly_refuses_an_output_it_cannot_write_before_it_flies(tmp_path, capsys, no_flight, option, name):
    rc = main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover", option,
               str(unwritable(tmp_path, name))])
    err = capsys.readouterr().err
    assert rc == 2 and f"{option} " in err and "cannot be written" in err and "Traceback" not in err


@pytest.mark.parametrize("command", [["run"], ["study"], ["versus"]])
def test_sweeps_refuse_an_output_folder_they_cannot_write_before_they_start(tmp_path, capsys, monkeypatch, command):
    import scenarios.studies.campaign as campaign
    import scenarios.studies.versus as versus
    import scenarios.studies.zoo as zoo

    for mod, fn in ((campaign, "run_main_job"), (zoo, "run_study"), (versus, "run_versus")):
        monkeypatch.setattr(mod, fn, lambda *a, **k: pytest.fail("started before checking --out"))
    rc = main(command + ["--out", str(unwritable(tmp_path, "out"))])
    err = capsys.readouterr().err
    assert rc == 2 and "--out" in err and "cannot be written" in err


# ----------------------------------------------------------------- --horizon checked when the line is read

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


# ----------------------------------------------------------------- --trace writes the path given

def test_trace_is_written_to_exactly_the_path_given(tmp_path, capsys):
    path = tmp_path / "trace-without-suffix"
    assert main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover", "--trace", str(path)]) == 0
    assert f"wrote {path}\n" in capsys.readouterr().out
    assert path.is_file() and not Path(str(path) + ".npz").exists()
    with np.load(path) as tr:
        assert tr["x"].shape[1] == 12 and tr["x"].shape[0] == tr["t"].shape[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]      # no temporary file left


# ----------------------------------------------------------------- bounds

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


# ----------------------------------------------------------------- the code version covers code

def test_the_code_version_covers_python_source_not_the_bounds_file(tmp_path, monkeypatch):
    for pkg in ("sim", "mpc", "scenarios"):
        shutil.copytree(ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(record, "__file__", str(tmp_path / "scenarios" / "closed_loop" / "record.py"))

    def version():
        monkeypatch.setattr(record, "_CODE_VERSION", None)
        return record.code_version()

    before = version()
    with open(tmp_path / "scenarios" / "studies" / "bounds.toml", "a") as f:
        f.write("\n# bounds written again\n")
    assert version() == before
    with open(tmp_path / "mpc" / "controllers" / "ltv.py", "a") as f:
        f.write("\n# a change of code\n")
    assert version() != before


# ----------------------------------------------------------------- a cache keyed by what was flown

def copied_model(tmp_path, name="baseline"):
    d = tmp_path / "models"
    d.mkdir(exist_ok=True)
    for suffix in (".onnx", ".jac.onnx"):
        shutil.copy(ROOT / "models" / f"{name}{suffix}", d / f"baseline{suffix}")
    return d / "baseline.onnx"


def test_the_cache_key_covers_the_derivative_graph(tmp_path):
    from scenarios.closed_loop.record import cache_key

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
    from scenarios.closed_loop.runner import fly
    from scenarios.closed_loop.record import input_hashes
    from scenarios.sweeps.sweep import sweep

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
    from scenarios.sweeps.sweep import sweep

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


# ----------------------------------------------------------------- workers that die, and orphans after a killed sweep

#: Seconds a dead parent's workers may outlive it (they watch for it every half second; Linux kills them at once).
ORPHAN_WAIT_S = 5.0
#: Seconds any one process-level test may take before it is called hung.
PROCESS_TIMEOUT_S = 90.0

MARKERS_ENV = "PINNMPC_TEST_MARKERS"


def fly_or_die(spec):
    """A sweep's unit of work that kills its own worker: always on ``hover+noise``, once on ``figure8-slow`` (a
    marker file in the folder named by the environment says it already did)."""
    import os
    import signal

    marker = Path(os.environ[MARKERS_ENV]) / f"{spec.run_id}.died"
    if spec.scenario == "hover+noise" or (spec.scenario == "figure8-slow" and not marker.exists()):
        marker.write_text("died once")
        os.kill(os.getpid(), signal.SIGKILL)
    return runner.fly_for_sweep(spec)             # in the worker: the real one


@pytest.mark.slow
def test_a_dead_worker_is_replaced_and_a_run_that_kills_it_twice_is_recorded_not_flown(tmp_path, monkeypatch,
                                                                                        capsys):
    from scenarios.sweeps.sweep import sweep

    specs = [RunSpec(sc, "lqr", "oracle") for sc in ("hover", "figure8-slow", "hover+noise", "figure8-fast")]
    monkeypatch.setattr(runner, "fly_for_sweep", fly_or_die)
    monkeypatch.setenv(MARKERS_ENV, str(tmp_path))
    out = tmp_path / "out"
    results = {r["run_id"]: r for r in sweep(specs, out, jobs=2, progress=False)}
    err = capsys.readouterr().err
    monkeypatch.undo()
    dead = results["hover+noise__lqr__oracle"]
    assert dead["error"] == "not flown: its worker process died 2 times on it (last: killed by SIGKILL)"
    assert dead["rmse_position_m"] is None and dead["trace"] is None
    assert err.count("run figure8-slow__lqr__oracle: its worker process died (killed by SIGKILL); flying it again") == 1
    assert "run hover+noise__lqr__oracle: its worker process died (killed by SIGKILL); recorded as not flown" in err
    for s in specs:
        if s.scenario != "hover+noise":
            assert results[s.run_id]["error"] is None
            assert results[s.run_id]["rmse_position_m"] == runner.fly(s)[0]["rmse_position_m"]
    again = []                                  # the run that did not fly is flown by the next resume, alone
    sweep(specs, out, jobs=1, progress=False, on_result=lambda r: again.append(r["run_id"]))
    assert again == ["hover+noise__lqr__oracle"]


def children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is ``pid`` (Linux ``/proc``)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid and fields[0] != "Z":
                out.append(int(d.name))
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


SLOW_SWEEP = """
import sys
from scenarios.closed_loop.runner import RunSpec
from scenarios.sweeps.sweep import sweep
if __name__ == "__main__":
    sweep([RunSpec("figure8-slow", "sqp", "oracle", seed=s) for s in range(6)], sys.argv[1], jobs=2, progress=False)
"""


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table from /proc")
def test_killing_a_sweep_with_sigkill_leaves_no_worker_alive(tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "sweep.py"
    script.write_text(SLOW_SWEEP)
    parent = subprocess.Popen([sys.executable, str(script), str(tmp_path / "out")], cwd=ROOT)
    try:
        t0 = time.monotonic()
        kids = []
        while time.monotonic() - t0 < PROCESS_TIMEOUT_S:
            kids = children(parent.pid)
            workers = [k for k in kids if b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes()]
            if len(workers) == 2:
                break
            time.sleep(0.1)
        assert len(workers) == 2, f"the sweep never started its two workers: {kids}"
        time.sleep(1.0)                             # they are flying now
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)
        t_kill = time.monotonic()
        while any(alive(k) for k in kids) and time.monotonic() - t_kill < ORPHAN_WAIT_S:
            time.sleep(0.1)
        left = [k for k in kids if alive(k)]
        assert not left, f"{len(left)} of the killed sweep's {len(kids)} processes alive after {ORPHAN_WAIT_S} s"
    finally:
        for k in children(parent.pid) + [parent.pid]:
            try:
                os.kill(k, signal.SIGKILL)
            except OSError:
                pass


@pytest.mark.slow
def test_a_sweep_survives_three_random_kills_of_its_workers_with_identical_results(tmp_path, monkeypatch, capsys):
    """The stress run: a worker is SIGKILLed three times, at random moments (seeded), while the sweep flies; it
    ends with the results of an undisturbed sweep, timing aside, and no process of it left."""
    import os
    import random
    import signal
    import threading
    import time

    import scenarios.sweeps.pool as pool
    from scenarios.closed_loop.metrics import TIMING_FIELDS
    from scenarios.sweeps.sweep import sweep

    specs = [RunSpec(sc, c, "oracle", seed=s) for sc in ("hover", "figure8-slow", "figure8-fast")
             for c in ("lqr", "ltv") for s in (0, 1)]
    calm = sweep(specs, tmp_path / "calm", jobs=2, progress=False)
    monkeypatch.setattr(pool, "RETRIES", 3)         # a run may be hit more than once by chance: kills are random
    rng = random.Random(29)
    kills, stop = [], threading.Event()
    me = os.getpid()

    def killer():
        while len(kills) < 3 and not stop.wait(rng.uniform(0.5, 2.0)):
            workers = [k for k in children(me) if b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes()]
            if workers:
                victim = rng.choice(sorted(workers))
                os.kill(victim, signal.SIGKILL)
                kills.append(victim)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    t0 = time.monotonic()
    stormy = sweep(specs, tmp_path / "stormy", jobs=2, progress=False)
    stop.set()
    thread.join(5)
    assert len(kills) == 3, f"only {len(kills)} kills landed in {time.monotonic() - t0:.1f} s"
    assert capsys.readouterr().err.count("its worker process died (killed by SIGKILL)") == 3
    drop = set(TIMING_FIELDS) | {"trace", "cache_key"}
    for a, b in zip(calm, stormy):
        assert {k: v for k, v in a.items() if k not in drop} == {k: v for k, v in b.items() if k not in drop}
    time.sleep(1.0)
    assert not [k for k in children(me) if b"spawn_main" in Path(f"/proc/{k}/cmdline").read_bytes()]


# ----------------------------------------------------------------- one sweep per folder

HOLD_LOCK = """
import sys, time
from scenarios.sweeps.lock import folder_lock
with folder_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(60)
"""


def test_a_second_sweep_on_a_folder_in_use_stops_with_a_line_naming_the_holder(tmp_path, capsys, no_flight):
    import subprocess
    import sys

    from scenarios.sweeps.lock import FolderInUseError
    from scenarios.sweeps.sweep import sweep

    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(out)], stdout=subprocess.PIPE, text=True,
                              cwd=ROOT)
    try:
        assert holder.stdout.readline() == "held\n"
        for command in (["run"], ["study"], ["versus"]):
            rc = main(command + ["--out", str(out)])
            err = capsys.readouterr().err
            assert rc == 2 and len(err.strip().splitlines()) == 1, err
            assert f"is in use by process {holder.pid} on " in err and "`-c " in err
        with pytest.raises(FolderInUseError, match=f"process {holder.pid} "):
            sweep([RunSpec("hover", "lqr", "oracle")], out, progress=False)
        holder.kill()                               # SIGKILL: the lock goes with its holder, the file stays behind
        holder.wait(10)
    finally:
        holder.kill()
        holder.wait(10)
    from scenarios.sweeps.lock import LOCK_NAME, folder_lock

    assert (out / LOCK_NAME).is_file()
    with folder_lock(out):                          # free again
        pass
    assert not (out / LOCK_NAME).exists()


# ----------------------------------------------------------------- check-model over the envelope, fly's causes

#: Roll beyond which the broken model returns NaN, rad (a fast figure-8 reaches 0.58 rad).
NAN_BEYOND_ROLL = 0.3


def nan_beyond_roll(tmp_path, limit=NAN_BEYOND_ROLL, source="baseline"):
    """A shipped model (no derivative graph) whose ``x_next`` is NaN wherever ``|roll| > limit``."""
    import onnx
    from onnx import TensorProto, helper

    m = onnx.load(str(ROOT / "models" / f"{source}.onnx"))
    g = m.graph
    (out,) = g.output
    inner = out.name + "_inner"
    for node in g.node:
        node.output[:] = [inner if o == out.name else o for o in node.output]
    consts = [helper.make_tensor("nb_lo", TensorProto.INT64, [1], [3]),
              helper.make_tensor("nb_hi", TensorProto.INT64, [1], [4]),
              helper.make_tensor("nb_ax", TensorProto.INT64, [1], [1]),
              helper.make_tensor("nb_lim", TensorProto.DOUBLE, [], [limit]),
              helper.make_tensor("nb_nan", TensorProto.DOUBLE, [], [float("nan")]),
              helper.make_tensor("nb_zero", TensorProto.DOUBLE, [], [0.0])]
    g.initializer.extend(consts)
    g.node.extend([helper.make_node("Slice", ["x", "nb_lo", "nb_hi", "nb_ax"], ["nb_roll"]),
                   helper.make_node("Abs", ["nb_roll"], ["nb_abs"]),
                   helper.make_node("Greater", ["nb_abs", "nb_lim"], ["nb_far"]),
                   helper.make_node("Where", ["nb_far", "nb_nan", "nb_zero"], ["nb_add"]),
                   helper.make_node("Add", [inner, "nb_add"], [out.name])])
    path = tmp_path / f"{source}_nan.onnx"
    onnx.save(m, str(path))
    return path


def test_check_model_finds_a_model_that_is_not_finite_away_from_hover(tmp_path, capsys):
    from mpc.prediction.contract import ModelContractError, check_model

    broken = nan_beyond_roll(tmp_path)
    with pytest.raises(ModelContractError, match="not finite at .* states across the flight envelope"):
        check_model(broken)
    assert main(["check-model", str(broken)]) == 2
    err = capsys.readouterr().err
    assert "flight envelope" in err and "Traceback" not in err
    # The smallest tilt named is beyond the model's limit and close to it (1024 samples over +-0.8 rad).
    tilt = float(err.split("smallest tilt among them is ")[1].split(" rad")[0])
    assert NAN_BEYOND_ROLL <= tilt < NAN_BEYOND_ROLL + 0.05
    check_model(nan_beyond_roll(tmp_path, limit=10.0))   # the same graph, NaN beyond any flight: valid


def test_check_model_and_fly_warn_of_a_float32_model_under_the_nmpc(tmp_path, capsys):
    import onnx
    from onnx import TensorProto, helper

    from mpc.controllers.readiness import FLOAT32_NMPC_WARNING

    # A float32 model: the float64 baseline between two casts.
    m = onnx.load(str(ROOT / "models" / "baseline.onnx"))
    g = m.graph
    (out,) = g.output
    for node in g.node:
        node.input[:] = [f"{i}_64" if i in ("x", "u") else i for i in node.input]
        node.output[:] = [f"{out.name}_64" if o == out.name else o for o in node.output]
    g.node.insert(0, helper.make_node("Cast", ["x"], ["x_64"], to=TensorProto.DOUBLE))
    g.node.insert(1, helper.make_node("Cast", ["u"], ["u_64"], to=TensorProto.DOUBLE))
    g.node.append(helper.make_node("Cast", [f"{out.name}_64"], [out.name], to=TensorProto.FLOAT))
    for v in (*g.input, *g.output):
        v.type.tensor_type.elem_type = TensorProto.FLOAT
    path = tmp_path / "baseline32.onnx"
    onnx.save(m, str(path))
    assert main(["check-model", str(path)]) == 0
    out_text = capsys.readouterr().out
    nmpc = out_text.split("    nmpc ")[1]
    assert "flies" in nmpc and f"warning: {FLOAT32_NMPC_WARNING}" in nmpc
    assert out_text.count("warning:") == 1           # the other controllers fly float32 models well
    assert main(["check-model", str(ROOT / "models" / "baseline.onnx")]) == 0
    assert "warning" not in capsys.readouterr().out


class NaNEveryFifth:
    """Made a prediction model by :func:`nan_every_fifth`: its Jacobians are NaN at every fifth linearization once
    the flight has started (the feed-forward fit before it sees the model as it is)."""


def nan_every_fifth(base):
    from mpc.prediction.models import PredictionModel

    class Broken(PredictionModel, NaNEveryFifth):
        def __init__(self):
            self.base, self.armed, self.calls = base, False, 0
            self.name, self.theta, self.extra_names, self.extra_scale = (base.name, base.theta, base.extra_names,
                                                                         base.extra_scale)

        def __getattr__(self, name):
            return getattr(self.base, name)

        def step(self, x, u):
            return self.base.step(x, u)

        def linearize(self, x, u):
            xn, A, B = self.base.linearize(x, u)
            if self.armed:
                self.calls += 1
                if self.calls % 5 == 0:
                    A = np.array(A, copy=True)
                    A[..., 0, 0] = np.nan
            return xn, A, B

        def reference_states(self, trajectory, times):
            return self.base.reference_states(trajectory, times)

    return Broken()


def test_fly_prints_the_settled_error_and_why_the_solver_failed(capsys, monkeypatch):
    assert main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover"]) == 0
    out = capsys.readouterr().out
    r, _ = runner.fly(RunSpec("hover", "lqr", "oracle"))
    assert f"settled_error_m       {r['settled_error_m']:.4g}" in out and "failure_causes" not in out
    # A model whose Jacobians turn NaN at every fifth period of the flight: fly names the cause of each failure.
    import scenarios.closed_loop.loop as loop_module

    real_fly, real_loop, flown = runner.fly, loop_module.fly_loop, []

    def fly(spec, progress=False, model=None):
        flown.append(nan_every_fifth(model))
        return real_fly(spec, progress=progress, model=flown[-1])

    def loop(*a, **k):
        flown[-1].armed = True
        return real_loop(*a, **k)

    monkeypatch.setattr(runner, "fly", fly)
    monkeypatch.setattr(loop_module, "fly_loop", loop)
    assert main(["fly", "--model", "oracle", "--controller", "ltv", "--scenario", "hover"]) == 0
    out = capsys.readouterr().out
    failures = int(out.split("solver_failures")[1].split()[0])
    assert failures == flown[0].calls // 5 > 0
    assert f"failure_causes        non-finite model output {failures}\n" in out


# ----------------------------------------------------------------- budgets on a slower machine

def test_a_line_search_that_would_end_past_the_budget_is_skipped_for_the_full_step():
    """On a slower machine a line search started late ran the period past its deadline (a 2.9 ms line search after
    a QP that ended at 7.4 ms of an 8 ms budget). A period whose longest recent line search would not fit takes the
    QP's full step: bit for bit one full-step iteration; with room for it, the line search runs. (The rest of the
    budget: the evaluation reused, tests/test_evaluation_reuse.py; the slower machine itself,
    python -m mpc.bench --slowdown 2.)"""
    from mpc.prediction.models import OnnxModel
    from mpc.controllers.sqp import SQPMPC, SQPSettings
    from mpc.references.trajectory import Figure8

    model, fig8 = OnnxModel(ROOT / "models" / "proposed.onnx"), Figure8(0.75, 3.0, 1.0)
    budget = 10.0                                   # seconds: no QP here comes near it
    tight = SQPMPC(model, fig8, SQPSettings(time_budget_s=budget, cold_start_budget_s=None, max_sqp_iter=1))
    roomy = SQPMPC(model, fig8, SQPSettings(time_budget_s=budget, cold_start_budget_s=None, max_sqp_iter=1))
    rti = SQPMPC(model, fig8, SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=1,
                                          line_search=False))
    t = 0.5
    X0, U0 = tight._horizon_reference(t)
    x = X0[0] + np.r_[0.05, -0.03, 0.02, np.zeros(9)]
    tight.clock.record("line_search", budget)  # a line search as long as the whole budget, lately
    X1, U1, info = tight.solve_from(x, t, X0, U0)
    X2, U2, _ = rti.solve_from(x, t, X0, U0)
    assert info.extra["late_full_steps"] == 1 and info.extra["merit"] == []
    assert np.array_equal(X1, X2) and np.array_equal(U1, U2)
    info = roomy.solve_from(x, t, X0, U0)[2]
    assert info.extra["late_full_steps"] == 0 and len(info.extra["merit"]) == 1


# ----------------------------------------------------------------- a scenario longer than the limit

@pytest.mark.parametrize("text,what", [
    ("hover = [0, 0, -1]\nduration_s = 1e7\n", "duration_s = 1e+07 s"),
    ("waypoints = [[0, 0, -1], [1, 0, -1]]\npath_duration_s = 900\n", "the reference lasts 900 s"),
])
def test_a_scenario_longer_than_the_limit_is_refused_with_its_reason(tmp_path, capsys, no_flight, text, what):
    from scenarios.closed_loop.scenario import MAX_DURATION_S

    f = tmp_path / "long.toml"
    f.write_text(text)
    out = tmp_path / "r.json"
    rc = main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", str(f), "--json", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "long.toml" in err and what in err and f"at most {MAX_DURATION_S:g} s" in err
    assert "battery" in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_the_duration_limit_holds_for_scenarios_made_in_python_too():
    import dataclasses

    from scenarios.closed_loop.scenario import MAX_DURATION_S
    from sim.params import DT

    with pytest.raises(ScenarioError, match="at most 600 s"):
        dataclasses.replace(runner.get_scenario("hover"), duration_s=MAX_DURATION_S + DT)
    dataclasses.replace(runner.get_scenario("hover"), duration_s=MAX_DURATION_S)


# ----------------------------------------------------------------- datasets a model cannot be trained on

def _dataset(tmp_path):
    from sim.identification.excitation import make_dataset

    path = tmp_path / "d.npz"
    make_dataset("small", 3, 0.5, 0).save(path)
    return path


@pytest.mark.parametrize("damage,says", [
    ("nan", "array x holds 1 non-finite value(s), the first at index (1, 5, 2)"),
    ("inf", "array u holds 1 non-finite value(s)"),
    ("truncated", "is not an .npz archive"),
    ("not-npz", "is not an .npz file"),
    ("text", "is not an .npz archive"),
    ("missing", "missing rotor_speed"),
])
def test_train_refuses_a_dataset_it_cannot_use_in_one_line_and_writes_nothing(tmp_path, capsys, damage, says):
    import dataclasses
    import zipfile

    from sim.identification.excitation import load_dataset

    good = _dataset(tmp_path)
    bad = tmp_path / "bad.npz"
    ds = load_dataset(good)
    if damage == "nan":
        x = ds.x.copy()
        x[1, 5, 2] = np.nan
        dataclasses.replace(ds, x=x).save(bad)
    elif damage == "inf":
        u = ds.u.copy()
        u[0, 0, 0] = np.inf
        dataclasses.replace(ds, u=u).save(bad)
    elif damage == "truncated":
        data = good.read_bytes()
        bad.write_bytes(data[:len(data) // 2])
    elif damage == "not-npz":
        bad = tmp_path / "bad.csv"
        bad.write_text("x,y\n1,2\n")
    elif damage == "text":
        bad.write_text("hello")
    else:
        with zipfile.ZipFile(good) as zin, zipfile.ZipFile(bad, "w") as zout:
            for item in zin.namelist():
                if item != "rotor_speed.npy":
                    zout.writestr(item, zin.read(item))
    out = tmp_path / "models"
    rc = main(["train", "--arch", "baseline", "--profile", "quick", "--data", str(bad), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and bad.name in err and says in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()


# ----------------------------------------------------------------- a study with models that cannot be flown

def _broken_models(folder: Path) -> None:
    """A damaged file and a model of another dt, beside whatever else is in ``folder``."""
    import onnx

    m = onnx.load(str(ROOT / "models" / "zoo" / "baseline_e2.onnx"))
    for p in m.metadata_props:
        if p.key == "dt":
            p.value = "0.02"
    onnx.save(m, str(folder / "wrongdt.onnx"))
    (folder / "corrupt.onnx").write_bytes(np.random.default_rng(0).bytes(2000))


def test_a_folder_of_models_records_those_that_fail_the_contract_instead_of_stopping(tmp_path):
    from scenarios.studies.zoo import zoo_models

    shutil.copy(ROOT / "models" / "zoo" / "baseline_e8.onnx", tmp_path)
    _broken_models(tmp_path)
    models = zoo_models(tmp_path)
    assert sorted(models) == ["baseline_e8", "corrupt", "wrongdt"]
    assert "failed" not in models["baseline_e8"] and models["baseline_e8"]["metrics"]["rollout_100_mae"]
    assert "not a readable ONNX file" in models["corrupt"]["failed"]
    assert "'dt' must equal" in models["wrongdt"]["failed"] and "found 0.02" in models["wrongdt"]["failed"]


def test_study_exits_non_zero_with_one_line_naming_the_models_it_could_not_study(tmp_path, capsys, monkeypatch):
    import scenarios.studies.zoo as zoo

    failed = {"corrupt": "not a readable ONNX file", "wrongdt": "metadata 'dt' must equal 0.01; found 0.02"}
    monkeypatch.setattr(zoo, "run_study", lambda *a, **k: {"failed": failed})
    monkeypatch.setattr(zoo, "format_study", lambda out: "(the study's table)")
    rc = main(["study", "--out", str(tmp_path / "out"), "--no-publish"])
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert rc == 1 and len(lines) == 1
    assert "2 models could not be studied" in lines[0] and "corrupt: not a readable" in lines[0] \
        and "wrongdt: metadata" in lines[0]


@pytest.mark.slow
def test_a_study_with_a_corrupt_and_a_wrong_dt_model_flies_the_others_and_records_both(tmp_path, capsys):
    models = tmp_path / "zoo"
    models.mkdir()
    for f in ("baseline_e8.onnx", "baseline_e8.jac.onnx"):
        shutil.copy(ROOT / "models" / "zoo" / f, models)
    _broken_models(models)
    out = tmp_path / "out"
    rc = main(["study", "--models", str(models), "--out", str(out), "--members", "1", "--no-publish", "--jobs", "1"])
    err = capsys.readouterr().err
    assert rc == 1 and "2 models could not be studied" in err
    study = json.loads((out / "study.json").read_text())
    assert list(study["models"]) == ["baseline_e8"]
    assert set(study["failed"]) == {"corrupt", "wrongdt"} and "found 0.02" in study["failed"]["wrongdt"]
    assert study["models"]["baseline_e8"]["ensembles"]["sqp"]["runs"] == 1


# ----------------------------------------------------------------- messages that say what is true

def test_versus_with_one_member_says_why_it_gives_no_verdict():
    from scenarios.studies.versus import VERSUS_PLANTS, summarize_plant

    key = next(iter(VERSUS_PLANTS))
    sc = VERSUS_PLANTS[key].scenario("figure8-fast")

    from scenarios.closed_loop.library import ladder_names, ladder_speeds

    def run(model, rmse, rung=None):
        return {"_model": model, "_rung": rung, "rmse_position_m": rmse, "crashed": False, "error": None,
                "scenario": sc if rung is None else rung, "solve_ms": {"median": 2.0}}

    models = ["nominal", str(ROOT / "models" / "baseline.onnx")]
    runs = [run(m, rmse) for m, rmse in zip(models, (0.04, 0.03))]
    runs += [run(m, 0.05, rung) for m in models for rung in ladder_names() if rung != "figure8-fast"]
    out = summarize_plant(key, models, dict(enumerate(runs)), ladder_speeds())
    assert out["verdict"] is None
    assert "at least 2 members" in out["no_verdict"] and "found 1" in out["no_verdict"]
    assert "flew every member" not in out["no_verdict"]


def test_bounds_on_results_of_another_plant_say_so():
    runs = [dict(r, plant="rotorpy-ideal") for r in oracle_results()]
    with pytest.raises(BoundsError, match="only on rotorpy-ideal with the rolling-spider") as e:
        generate(runs, [])
    assert "run `pinnmpc run` first" not in str(e.value)


def test_a_high_fidelity_scenario_on_rotorpy_does_not_advise_rotorpy():
    with pytest.raises(ScenarioError, match="already on with --plant rotorpy") as e:
        RunSpec("hover+highfi", "lqr", "nominal", plant="rotorpy")
    assert "fly --plant rotorpy" not in str(e.value)
    with pytest.raises(ScenarioError, match="fly --plant rotorpy for RotorPy's"):
        RunSpec("hover+highfi", "lqr", "nominal", plant="rotorpy-ideal")
