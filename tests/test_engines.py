"""Sweep engines (process pool, Ray) and the resumable results cache."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

import scenarios.closed_loop.record as record
import scenarios.closed_loop.runner as runner
from scenarios.errors import ScenarioError
from scenarios.closed_loop.metrics import TIMING_FIELDS, TRACE_TIMING_FIELDS
from scenarios.closed_loop.record import cache_key
from scenarios.closed_loop.runner import RunSpec
from scenarios.sweeps.sweep import sweep

ROOT = Path(__file__).resolve().parents[1]
BASELINE = str(ROOT / "models" / "baseline.onnx")
#: Short runs of three controllers and two models (hover: 5 s).
SPECS = [RunSpec("hover", "lqr", "oracle"), RunSpec("hover", "ltv", "oracle"), RunSpec("hover", "ltv", BASELINE),
         RunSpec("hover", "sqp", BASELINE)]


def reproducible(result):
    return {k: v for k, v in result.items() if k not in TIMING_FIELDS}


def assert_same_runs(a, b, out_a, out_b):
    assert [reproducible(r) for r in a] == [reproducible(r) for r in b]
    for r in a:
        ta, tb = np.load(Path(out_a) / r["trace"]), np.load(Path(out_b) / r["trace"])
        for k in set(ta.files) - set(TRACE_TIMING_FIELDS):
            np.testing.assert_array_equal(ta[k], tb[k], err_msg=f"{r['run_id']}: {k}")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("process")
    return sweep(SPECS, out, jobs=2, progress=False), out


@pytest.mark.slow
def test_a_ray_sweep_gives_the_process_engines_results(reference, tmp_path):
    pytest.importorskip("ray")
    results = sweep(SPECS, tmp_path, jobs=2, progress=False, engine="ray")
    assert_same_runs(reference[0], results, reference[1], tmp_path)


@pytest.mark.slow
def test_an_interrupted_sweep_resumes_without_flying_any_run_twice(reference, tmp_path, monkeypatch):
    flown = []
    fly = runner.fly

    def counting_fly(spec, *args, **kwargs):
        flown.append(spec.run_id)
        return fly(spec, *args, **kwargs)

    monkeypatch.setattr(runner, "fly", counting_fly)

    def interrupt_after_two(result):
        if len(flown) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sweep(SPECS, tmp_path, jobs=1, progress=False, on_result=interrupt_after_two)
    assert len(list((tmp_path / "runs").glob("*.json"))) == 2
    results = sweep(SPECS, tmp_path, jobs=1, progress=False)
    assert sorted(flown) == sorted(s.run_id for s in SPECS)       # each run flown exactly once
    assert_same_runs(reference[0], results, reference[1], tmp_path)
    sweep(SPECS, tmp_path, jobs=1, progress=False)                 # complete: nothing is flown again
    assert len(flown) == len(SPECS)


def test_a_run_is_flown_again_when_its_code_or_its_saved_file_changed(tmp_path, monkeypatch):
    spec = SPECS[0]
    flown = []
    fly = runner.fly
    monkeypatch.setattr(runner, "fly", lambda s, *a, **k: (flown.append(s.run_id), fly(s, *a, **k))[1])
    sweep([spec], tmp_path, progress=False)
    sweep([spec], tmp_path, progress=False)
    assert len(flown) == 1
    monkeypatch.setattr(record, "_CODE_VERSION", "another version")
    sweep([spec], tmp_path, progress=False)
    assert len(flown) == 2
    path = tmp_path / "runs" / f"{spec.run_id}.json"
    path.write_text(path.read_text()[:100])                       # a result cut short
    sweep([spec], tmp_path, progress=False)
    assert len(flown) == 3 and json.loads(path.read_text())["cache_key"] == cache_key(spec)
    sweep([spec], tmp_path, progress=False, resume=False)
    assert len(flown) == 4
    result = json.loads(path.read_text())
    path.write_text(json.dumps({**result, "error": "RuntimeError: could not start"}))   # a run that failed to start
    sweep([spec], tmp_path, progress=False)
    assert len(flown) == 5


def test_the_cache_key_follows_seed_model_content_and_code(tmp_path, monkeypatch):
    import shutil

    a = RunSpec("hover", "ltv", BASELINE)
    copy = tmp_path / "baseline.onnx"
    shutil.copyfile(BASELINE, copy)
    shutil.copyfile(BASELINE.replace(".onnx", ".jac.onnx"), tmp_path / "baseline.jac.onnx")
    assert cache_key(RunSpec("hover", "ltv", str(copy))) == cache_key(a)     # same name and bytes, other folder
    assert cache_key(RunSpec("hover", "ltv", BASELINE, seed=3)) != cache_key(a)
    assert RunSpec("hover", "ltv", BASELINE, seed=3).run_id == "hover__ltv__baseline__s3"
    assert RunSpec("hover", "ltv", BASELINE).run_id == "hover__ltv__baseline"
    before = cache_key(a)
    monkeypatch.setattr(record, "_CODE_VERSION", "another version")
    assert cache_key(a) != before


@pytest.mark.parametrize("kwargs,match", [
    (dict(engine="dask"), "engine must be one of process, ray"),
    (dict(address="localhost:6379"), "address is for the ray engine"),
])
def test_bad_engine_arguments_are_clear_errors(tmp_path, kwargs, match):
    with pytest.raises(ScenarioError, match=match):
        sweep(SPECS[:1], tmp_path, progress=False, **kwargs)


def start_environment(_item) -> dict:
    """In a pool worker: the environment it started with (Linux: ``/proc/<pid>/environ``, which a later change of
    ``os.environ`` does not touch)."""
    raw = Path(f"/proc/{os.getpid()}/environ").read_bytes().decode(errors="replace")
    return dict(kv.split("=", 1) for kv in raw.split("\0") if "=" in kv)


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="reads a process's first environment in /proc")
def test_pool_workers_start_with_one_blas_thread_whatever_the_callers_environment(monkeypatch):
    """Set in the worker by an initializer, the thread counts came too late: numpy, loaded with the worker's
    function, had started its BLAS threads already (two workers ran four threads on two cores)."""
    from scenarios.sweeps.pool import run_pool
    from sim.workers import WORKER_ENV

    for k in WORKER_ENV:
        monkeypatch.delenv(k, raising=False)
    got = {}
    run_pool(start_environment, [0, 1], 2, got.__setitem__, lambda item, reason: pytest.fail(reason))
    assert len(got) == 2
    for env in got.values():
        assert {k: env.get(k) for k in WORKER_ENV} == WORKER_ENV
    assert not any(k in os.environ for k in WORKER_ENV)         # the caller's own environment as it was
