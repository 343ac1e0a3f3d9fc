"""The QP solver chosen on the command line (``--qp osqp|daqp``): carried to every LTV-MPC and SQP a command builds,
named in every run record, part of a saved run's identity, and refused in one line when DAQP is missing."""

import importlib.util
import json
from pathlib import Path

import pytest

from scenarios.cli import main

#: Tolerances. The same short flight (100 periods of figure8-fast) by OSQP (its default 1e-5 tolerances) and by the
#: dense path (exact up to rounding): their position RMSE differed by at most 5e-9 m here without the estimator
#: and 3e-8 m with it, for figures of 1e-5 m (the oracle) to 3e-2 m (Baseline).
TOL = {"rmse_m": 1e-6}
#: Periods flown by the flights of this module (a short case: about a second each).
STEPS = 100

REPO = Path(__file__).resolve().parents[1]
BASELINE = str(REPO / "models" / "baseline.onnx")
HAVE_DAQP = importlib.util.find_spec("daqp") is not None
needs_daqp = pytest.mark.skipif(not HAVE_DAQP, reason='DAQP is not installed (python -m pip install -e ".[dense]")')


@pytest.fixture
def short(monkeypatch):
    """Every scenario lasts :data:`STEPS` periods."""
    monkeypatch.setattr("scenarios.closed_loop.library.Scenario.steps", property(lambda self: STEPS), raising=False)


@pytest.fixture
def dense_calls(monkeypatch):
    """A list that grows by one with every QP the controllers solve by the dense path (DAQP)."""
    from mpc.controllers.ltv import LTVMPC

    calls = []
    real = LTVMPC._solve_dense

    def counted(self, *args, **kwargs):
        calls.append(self.s.qp)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(LTVMPC, "_solve_dense", counted)
    return calls


def _fly_json(tmp_path, capsys, name, argv) -> dict:
    out = tmp_path / f"{name}.json"
    assert main(["fly", *argv, "--json", str(out)]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    return json.loads(out.read_text()), printed


# ------------------------------------------------------------------ fly: the dense path, and the same answer
@needs_daqp
@pytest.mark.parametrize("controller,model,estimator", [("ltv", BASELINE, "none"), ("sqp", "oracle", "none"),
                                                        ("sqp", "oracle", "ekf")],
                         ids=["ltv-baseline", "sqp-oracle", "sqp-oracle-ekf"])
def test_fly_qp_daqp_flies_the_dense_path_and_gives_osqps_answer(controller, model, estimator, short, dense_calls,
                                                                tmp_path, capsys):
    argv = ["--model", model, "--controller", controller, "--scenario", "figure8-fast", "--estimator", estimator]
    sparse, printed = _fly_json(tmp_path, capsys, "osqp", argv)          # the default: OSQP
    assert dense_calls == [] and sparse["qp"] == "osqp"
    assert "qp" in printed.split() and sparse["run_id"].endswith(controller + "__" + Path(model).stem
                                                                  + ("" if estimator == "none" else "__ekf"))
    dense, printed = _fly_json(tmp_path, capsys, "daqp", [*argv, "--qp", "daqp"])
    assert len(dense_calls) >= STEPS and set(dense_calls) == {"daqp"}   # every period's QP went the dense way
    assert dense["qp"] == "daqp" and dense["run_id"].endswith("__daqp")
    assert any(line.split() == ["qp", "daqp"] for line in printed.splitlines())
    assert not sparse["crashed"] and not dense["crashed"] and dense["solver_failures"] == 0
    assert abs(dense["rmse_position_m"] - sparse["rmse_position_m"]) <= TOL["rmse_m"]


def test_a_controller_without_a_qp_is_recorded_without_a_solver_and_refuses_qp_daqp(short, tmp_path, capsys):
    result, _ = _fly_json(tmp_path, capsys, "lqr", ["--model", "oracle", "--controller", "lqr", "--scenario", "hover"])
    assert result["qp"] is None
    rc = main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover", "--qp", "daqp"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert "--qp applies to the controllers that solve a QP (ltv, sqp)" in err and "--controller lqr" in err


@pytest.mark.parametrize("command", ["fly", "run", "study", "versus"])
def test_a_qp_solver_that_does_not_exist_is_refused_by_the_parser(command, capsys):
    argv = {"fly": ["fly", "--model", "oracle", "--controller", "sqp", "--scenario", "hover"]}.get(command, [command])
    with pytest.raises(SystemExit) as e:
        main([*argv, "--qp", "gurobi"])
    assert e.value.code == 2
    assert "argument --qp: invalid choice: 'gurobi' (choose from 'osqp', 'daqp')" in capsys.readouterr().err


# ------------------------------------------------------------------ DAQP missing: one line, before any work
@pytest.mark.parametrize("command", ["fly", "run", "study", "versus"])
def test_qp_daqp_without_daqp_ends_in_one_line_naming_the_option_and_the_install(command, tmp_path, monkeypatch,
                                                                                 capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "daqp" else real(name, *a))

    def no_work(*args, **kwargs):
        raise AssertionError("work started before --qp was checked")

    import scenarios.studies.campaign
    import scenarios.closed_loop.runner
    import scenarios.studies.versus
    import scenarios.studies.zoo

    for module, name in ((scenarios.closed_loop.runner, "fly"), (scenarios.closed_loop.runner, "load_run_model"),
                         (scenarios.studies.campaign, "run_main_job"), (scenarios.studies.zoo, "run_study"),
                         (scenarios.studies.versus, "run_versus")):
        monkeypatch.setattr(module, name, no_work)
    out = tmp_path / "out"
    argv = {"fly": ["fly", "--model", "oracle", "--controller", "sqp", "--scenario", "hover",
                    "--json", str(out / "r.json")]}.get(command, [command, "--out", str(out)])
    assert main([*argv, "--qp", "daqp"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"pinnmpc {command}: error: --qp daqp needs DAQP")
    assert 'python -m pip install -e ".[dense]"' in err
    assert not out.exists()


# ------------------------------------------------------------------ carried to every run a sweep command builds
@pytest.mark.parametrize("command,target", [("run", "scenarios.studies.campaign.run_main_job"),
                                            ("study", "scenarios.studies.zoo.run_study"),
                                            ("versus", "scenarios.studies.versus.run_versus")])
@pytest.mark.parametrize("qp", ["osqp", "daqp"])
def test_the_sweep_commands_hand_their_qp_solver_on(command, target, qp, tmp_path, monkeypatch):
    if qp == "daqp" and not HAVE_DAQP:
        pytest.skip("DAQP is not installed")
    seen = {}

    class Stop(Exception):
        pass

    def capture(*args, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(target, capture)
    with pytest.raises(Stop):
        main([command, "--out", str(tmp_path / "out")] + ([] if command == "run" else ["--no-publish"])
             + ([] if qp == "osqp" else ["--qp", qp]))
    assert seen["qp"] == qp


def test_every_ltv_and_sqp_run_of_the_plans_takes_the_qp_solver():
    """The main job's plan (with and without the estimator), the study's and the versus study's: every LTV-MPC and
    SQP run flies the solver asked for; the NMPC's and the LQR's runs keep their name and identity."""
    from scenarios.studies.campaign import main_plan
    from mpc.controllers.factory import QP_CONTROLLERS
    from scenarios.closed_loop.record import cache_key
    from scenarios.studies.versus import versus_specs
    from scenarios.studies.zoo import study_specs

    for estimator in (None, "ekf"):
        plain = main_plan(scenarios=["hover", "figure8-fast"], estimator=estimator)
        dense = main_plan(scenarios=["hover", "figure8-fast"], estimator=estimator, qp="daqp")
        assert [s.qp for s in plain] == ["osqp"] * len(plain) and [s.qp for s in dense] == ["daqp"] * len(dense)
        assert {s.controller for s in dense} >= {"ltv", "sqp", "lqr"}
        for a, b in zip(plain, dense):
            if b.controller in QP_CONTROLLERS:
                assert b.qp_solver == "daqp" and b.run_id.replace("__daqp", "", 1) == a.run_id != b.run_id
                assert cache_key(b) != cache_key(a)
            else:
                assert b.qp_solver is None and b.run_id == a.run_id and cache_key(b) == cache_key(a)
    models = {"m": {"path": BASELINE}}
    oracle, ens, ladder = study_specs(models, members=2, qp="daqp")
    assert all(s.qp_solver == "daqp" for s in [oracle, *ens, *ladder])
    runs = versus_specs("highfi", ["nominal"], members=2, ladder_members=1, qp="daqp")
    assert all(s.qp_solver == "daqp" for rs in runs["ensemble"].values() for s in rs)
    assert all(s.qp_solver == "daqp" for rungs in runs["ladder"].values() for rs in rungs.values() for s in rs)


# ------------------------------------------------------------------ the sweep's cache
@needs_daqp
def test_a_saved_run_is_reused_only_by_the_solver_it_was_flown_with(short, dense_calls, tmp_path, monkeypatch):
    import scenarios.closed_loop.runner as runner
    from scenarios.closed_loop.runner import RunSpec
    from scenarios.closed_loop.record import cache_key
    from scenarios.sweeps.sweep import sweep

    flown = []
    real = runner.fly

    def counted(spec, *args, **kwargs):
        flown.append(spec.qp)
        return real(spec, *args, **kwargs)

    monkeypatch.setattr(runner, "fly", counted)
    sparse, dense = (RunSpec("hover", "ltv", "oracle", qp=q) for q in ("osqp", "daqp"))
    assert cache_key(sparse) != cache_key(dense) and sparse.run_id != dense.run_id
    (a,) = sweep([sparse], tmp_path, progress=False)
    assert flown == ["osqp"] and a["qp"] == "osqp" and not dense_calls
    (b,) = sweep([dense], tmp_path, progress=False)              # the OSQP run saved there is not reused
    assert flown == ["osqp", "daqp"] and b["qp"] == "daqp" and len(dense_calls) >= STEPS
    saved = json.loads((tmp_path / "runs" / f"{dense.run_id}.json").read_text())
    assert saved["qp"] == "daqp" and saved["cache_key"] == cache_key(dense)
    again = sweep([sparse, dense], tmp_path, progress=False)    # each reused by its own solver
    assert flown == ["osqp", "daqp"] and [r["qp"] for r in again] == ["osqp", "daqp"]
    # A saved OSQP run relabelled as the DAQP run is refused: the key, not the file name, carries the solver.
    (tmp_path / "runs" / f"{dense.run_id}.json").write_text(
        (tmp_path / "runs" / f"{sparse.run_id}.json").read_text().replace(sparse.run_id, dense.run_id))
    sweep([dense], tmp_path, progress=False)
    assert flown == ["osqp", "daqp", "daqp"]
