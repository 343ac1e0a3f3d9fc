"""Flying at the ctbr and ctatt command levels: the per-level models against the plant with its inner loop, the
controllers on them, the refusals.

* The oracle at a level (``sim.equations.levels_casadi.inner_loop_step_function``) is the plant's own inner loop
  stepped inside the period: it must equal the reference simulator flown through
  ``sim.plants.inner_loop.InnerLoopPlant`` to rounding, with the loop's integrals and last error as its extra states.
* The nominal models (first-order rates, second-order attitude) are the continuous-time limit of a P loop: one
  period of them against the plant with that loop differs by a share of the period's change that halves when the
  loop's rate doubles.
* The oracle flown by the SQP and the LTV-MPC tracks ``figure8-fast`` within 1 mm at both levels.
"""

import json

import numpy as np
import pytest

from sim.equations.levels_casadi import inner_loop_extra_names, inner_loop_step_function, level_step_function
from sim.plants.inner_loop import InnerLoopPlant
from sim.plants.named import make_plant
from sim.vehicles.onboard import InnerLoopConfig
from sim.vehicles.vehicle import load_vehicle

TOL = {
    "exact": 1e-12,          # oracle vs plant over 50 periods, any state entry (rounding only)
    "nominal_rel": 0.07,     # nominal vs plant with a matched P loop at 1 kHz: rate error / the period's rate change
    "nominal_angle": 3e-4,   # the same, largest angle error after one period, rad
    "order": (1.8, 2.3),     # the error ratio when the loop's rate doubles (first order in its period: 2)
    "track_m": 1e-3,         # the oracle's RMSE on figure8-fast, m
    # the oracle's RMSE at ctbr and ctatt over the wrench level's, ensemble member 0 (noise): measured 1.04 both
    "oracle_member_ratio": 1.2,
}
SHIPPED = ("crazyflie", "crazyflie-brushless", "hummingbird", "rolling-spider")
LEVELS = ("ctbr", "ctatt")
#: Another rate and other gains than any shipped vehicle's: 100 Hz, a D term (the last error as an extra state).
OTHER_LOOP = InnerLoopConfig(rate_hz=100.0, rate_kp=(50.0, 50.0, 25.0), rate_ki=(100.0, 100.0, 20.0),
                             rate_kd=(0.3, 0.3, 0.0), rate_i_limit=(0.4, 0.4, 1.0), att_kp=(5.0, 5.0),
                             att_ki=(2.0, 2.0), att_i_limit=(0.2, 0.2), max_rate=8.0, max_tilt=0.7,
                             source="a test: 100 Hz with a D term")


def _random_flight(vehicle, level, seed=0, periods=50):
    """Commands (periods, 4) and start state (12,) of a tumbling flight."""
    rng = np.random.default_rng(seed)
    x0 = np.zeros(12)
    x0[2], x0[3], x0[6] = -1.0, 0.1, 0.3
    u = np.column_stack([vehicle.m * 9.81 * rng.uniform(0.9, 1.2, periods), rng.normal(0, 0.5, (periods, 3))])
    if level == "ctatt":
        u[:, 1:3] *= 0.3
    return x0, u


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("name", SHIPPED + ("other",))
def test_the_oracle_at_a_level_is_the_plant_with_its_inner_loop_to_rounding(name, level):
    v = load_vehicle("crazyflie").replace(inner_loop=OTHER_LOOP) if name == "other" else load_vehicle(name)
    c = v.inner_loop
    F = inner_loop_step_function(v.params, level, c)
    extra = inner_loop_extra_names(c, level)
    plant = InnerLoopPlant(make_plant("sim", v), c, level)
    x0, U = _random_flight(v, level)
    plant.reset(x0)
    z = np.concatenate([x0, np.zeros(len(extra))])
    if "e_p" in extra:       # the loop's first period has no last error: its derivative term is zero
        sp = np.clip(U[0, 1:4], -c.max_rate, c.max_rate) if level == "ctbr" else None
        if sp is None:
            e_att = np.clip(U[0, 1:3], -c.max_tilt, c.max_tilt) - x0[3:5]
            sp = np.clip(np.r_[np.asarray(c.att_kp) * e_att + np.asarray(c.att_ki) * e_att * c.period_s, U[0, 3]],
                         -c.max_rate, c.max_rate)
        z[12 + extra.index("e_p"):12 + extra.index("e_p") + 3] = sp - x0[6:9]
    worst = 0.0
    for u in U:
        x = plant.advance(u).x
        z = np.asarray(F(z, u)).ravel()
        worst = max(worst, float(np.max(np.abs(z[:12] - x))))
    assert worst <= TOL["exact"], worst
    assert len(extra) == {("crazyflie", "ctbr"): 3, ("crazyflie", "ctatt"): 5, ("other", "ctbr"): 6,
                          ("other", "ctatt"): 8}.get((name.replace("-brushless", ""), level), 0)


def _nominal_errors(level, rate_hz):
    """Largest one-period errors of the nominal model against the plant with a P loop at ``rate_hz``: rates
    relative to the period's rate change, rates (rad/s) and angles (rad)."""
    c = InnerLoopConfig(rate_hz=rate_hz, rate_kp=(40.0, 40.0, 20.0), att_kp=(5.0, 5.0), max_rate=20.0, max_tilt=1.2)
    v = load_vehicle("crazyflie").replace(inner_loop=c)
    F = level_step_function(v.params, level, c.response())
    rng = np.random.default_rng(1)
    rel, rate, angle = 0.0, 0.0, 0.0
    for _ in range(20):
        x0 = np.zeros(12)
        x0[2] = -1.0
        x0[3:6], x0[6:9], x0[9:12] = rng.normal(0, 0.1, 3), rng.normal(0, 0.5, 3), rng.normal(0, 0.5, 3)
        u = np.r_[v.m * 9.81 * rng.uniform(0.8, 1.2), rng.normal(0, 0.5, 3)]
        if level == "ctatt":
            u[1:3] = rng.normal(0, 0.2, 2)
        plant = InnerLoopPlant(make_plant("sim", v), c, level)
        plant.reset(x0)
        xp = plant.advance(u).x
        xn = np.asarray(F(x0, u)).ravel()
        err = float(np.max(np.abs(xn[6:9] - xp[6:9])))
        rel, rate = max(rel, err / float(np.max(np.abs(xp[6:9] - x0[6:9])))), max(rate, err)
        angle = max(angle, float(np.max(np.abs(xn[3:6] - xp[3:6]))))
    return rel, rate, angle


@pytest.mark.parametrize("level", LEVELS)
def test_the_nominal_model_of_a_level_is_the_continuous_limit_of_the_plant_with_a_matched_loop(level):
    errors = {r: _nominal_errors(level, r) for r in (100, 200, 500, 1000)}
    rel, _, angle = errors[1000]
    assert rel <= TOL["nominal_rel"] and angle <= TOL["nominal_angle"], errors[1000]
    lo, hi = TOL["order"]
    for a, b in ((100, 200), (500, 1000)):
        assert lo <= errors[a][1] / errors[b][1] <= hi, errors
    # The angle error (the rate error integrated) is first order only from 500 Hz (1.78 from 100 to 200 Hz).
    assert lo <= errors[500][2] / errors[1000][2] <= hi, errors


def test_the_response_is_derived_from_the_gains_or_read_with_its_source():
    c = load_vehicle("crazyflie").inner_loop
    r = c.response()
    # A PD rate loop: tau = (1 + kd) / kp + half a period; the attitude P over it: wn = sqrt(kp_att / tau).
    assert r.rate_tau[0] == pytest.approx(1 / 164.45 + 0.001, rel=1e-12)
    assert r.att_wn[0] == pytest.approx(np.sqrt(6.0 / r.rate_tau[0]), rel=1e-12)
    assert r.att_zeta[0] == pytest.approx(1 / (2 * r.att_wn[0] * r.rate_tau[0]), rel=1e-12)
    assert "derived from the loop's gains" in r.source
    given = InnerLoopConfig(rate_kp=(1.0, 1.0, 1.0), rate_tau=(0.02, 0.02, 0.05), att_wn=(15.0, 15.0),
                            att_zeta=(0.5, 0.5), response_source="drone-models so_rpy, cf2x_L250")
    assert given.response().rate_tau == (0.02, 0.02, 0.05) and "cf2x_L250" in given.response().source


# ----------------------------------------------------------------------------- flown

def _fly(tmp_path, vehicle, level, controller, model="oracle"):
    from scenarios.cli import main

    out = tmp_path / f"{vehicle.replace('/', '_')}-{level}-{controller}-{model}.json"
    assert main(["fly", "--model", model, "--controller", controller, "--scenario", "figure8-fast",
                 "--level", level, "--vehicle", vehicle, "--json", str(out)]) == 0
    return json.loads(out.read_text())


#: The oracle's flights the default run makes (on the Crazyflie); the slow grid flies the others.
DEFAULT_RUN_FLIGHTS = (("crazyflie", "ctbr", "sqp"), ("crazyflie", "ctatt", "ltv"))


@pytest.mark.parametrize("level, controller", [(lv, c) for _, lv, c in DEFAULT_RUN_FLIGHTS])
def test_the_oracle_flies_figure8_fast_within_a_millimetre(tmp_path, level, controller):
    r = _fly(tmp_path, "crazyflie", level, controller)
    assert r["level"] == level and r["plant_spec"]["level"] == level and not r["crashed"]
    assert r["rmse_position_m"] <= TOL["track_m"], r["rmse_position_m"]
    assert r["run_id"].endswith(f"__{level}")


@pytest.mark.slow
@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("controller", ("sqp", "ltv"))
@pytest.mark.parametrize("name", SHIPPED + ("other",))
def test_the_oracle_flies_figure8_fast_within_a_millimetre_on_every_vehicle(tmp_path, name, level, controller):
    if (name, level, controller) in DEFAULT_RUN_FLIGHTS:
        pytest.skip("flown by the default run (test_the_oracle_flies_figure8_fast_within_a_millimetre)")
    vehicle = name
    if name == "other":
        path = tmp_path / "other-loop.toml"
        path.write_text(load_vehicle("crazyflie").replace(name="other-loop", inner_loop=OTHER_LOOP).to_toml())
        vehicle = str(path)
    r = _fly(tmp_path, vehicle, level, controller)
    assert not r["crashed"] and r["rmse_position_m"] <= TOL["track_m"], r["rmse_position_m"]


# ----------------------------------------------------------------------------- refused

def _refused(tmp_path, capsys, args, message):
    from scenarios.cli import main

    out = tmp_path / "r.json"
    assert main(args + ["--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and not out.exists(), err


def test_a_vehicle_without_an_inner_loop_is_refused_at_ctbr(tmp_path, capsys):
    path = tmp_path / "bare.toml"
    path.write_text(load_vehicle("crazyflie").replace(name="bare", inner_loop=None).to_toml())
    _refused(tmp_path, capsys, ["fly", "--model", "nominal", "--controller", "lqr", "--scenario", "hover",
                                "--level", "ctbr", "--vehicle", str(path)], "inner_loop.rate_kp is missing")


def test_a_model_file_flown_at_another_level_is_refused(tmp_path, capsys):
    _refused(tmp_path, capsys, ["fly", "--model", "models/baseline.onnx", "--controller", "lqr", "--scenario",
                                "hover", "--level", "ctbr"], "takes commands at the 'wrench' level (metadata 'level')")


def test_the_oracle_at_a_level_is_refused_where_its_loop_is_not_ours(tmp_path, capsys):
    _refused(tmp_path, capsys, ["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "hover+highfi",
                                "--level", "ctbr", "--vehicle", "crazyflie"], "fly --model nominal")


# ----------------------------------------------------------------------------- the main job at a level

def test_the_main_job_at_a_level_flies_each_equations_run_there_and_leaves_out_the_models_of_another():
    from pathlib import Path

    from mpc.prediction.models import is_equation_model
    from scenarios.closed_loop.library import get_scenario
    from scenarios.studies.campaign import left_out_at_level, main_plan, shipped_models

    models = Path(__file__).resolve().parents[1] / "models"
    base, plan = main_plan(models), main_plan(models, level="ctbr")
    assert plan and all(s.level == "ctbr" for s in plan) and len({s.run_id for s in plan}) == len(plan)
    # the shipped model files take wrenches: none flies, and each is named as left out
    assert all(is_equation_model(s.model) for s in plan)
    assert set(left_out_at_level(shipped_models(models), "ctbr").values()) == {"wrench"}
    # the oracle only where it exists at the level: our plant's nominal set-up
    assert all(s.plant == "sim" and not get_scenario(s.scenario).high_fidelity for s in plan if s.model == "oracle")

    def case(s):
        return s.scenario, s.controller, s.timing, s.estimator, s.plant, s.vehicle, s.member

    # every run the wrench plan flies with equations has its twin at the level, and nothing else is flown
    assert {case(s) for s in base if is_equation_model(s.model)} == {case(s) for s in plan}
    assert main_plan(models, level="wrench") == base


# ----------------------------------------------------------------------------- the levels study

def test_the_levels_study_flies_the_oracle_only_where_it_exists_at_a_level():
    from scenarios.studies.levels import levels_specs

    def flown(key):
        return {(lv, m): len(runs) for lv, by_model in levels_specs(key, 3).items() for m, runs in by_model.items()}

    assert flown("sim") == {(lv, m): 3 for lv in LEVELS + ("wrench",) for m in ("nominal", "oracle")}
    assert flown("highfi") == {("wrench", "nominal"): 3, ("wrench", "oracle"): 3, ("ctbr", "nominal"): 3,
                               ("ctatt", "nominal"): 3}
    assert flown("rotorpy") == {(lv, "nominal"): 3 for lv in LEVELS + ("wrench",)}
    assert flown("drone-models") == {("ctatt", "nominal"): 3}
    specs = levels_specs("highfi", 2)
    assert {(s.scenario, s.plant, s.vehicle, s.level, s.member) for s in specs["ctbr"]["nominal"]} == {
        ("figure8-fast+highfi", "sim", "crazyflie", "ctbr", k) for k in range(2)}


def test_the_levels_study_gives_each_level_as_a_multiple_of_the_wrench_level():
    from reports.sections.levels import levels_section
    from scenarios.studies.levels import summarize_levels

    def runs(rmse, solve, crashed=False):
        return [{"rmse_position_m": v, "crashed": crashed, "solve_ms": {"median": t}} for v, t in zip(rmse, solve)]

    out = summarize_levels("sim", {("wrench", "nominal"): runs([0.010, 0.012, 0.011], [4.0, 6.0, 5.0]),
                                   ("ctbr", "nominal"): runs([0.022, 0.020, 0.021], [6.0, 7.0, 8.0]),
                                   ("ctatt", "nominal"): runs([0.5, 0.5, 0.5], [9.0, 9.0, 9.0], crashed=True)})
    rows = {r["level"]: r for r in out["rows"]}
    assert rows["ctbr"]["rmse_vs_wrench"] == pytest.approx(0.021 / 0.011, rel=1e-12)
    assert rows["ctbr"]["solve_vs_wrench"] == pytest.approx(7.0 / 5.0, rel=1e-12)
    assert rows["wrench"]["rmse_vs_wrench"] is None
    assert rows["ctatt"]["ensemble"]["crashes"] == 3 and rows["ctatt"]["rmse_vs_wrench"] is None
    md = levels_section({"scenario": "figure8-fast", "controller": "sqp", "members": 3, "levels": ["wrench"],
                         "plants": {"sim": out}})
    assert "| ctbr | nominal | 21.0 (20.0–22.0) (1.91×) | 0/3 | 7.0 (1.40×) |" in md, md


def test_the_levels_study_refuses_an_unknown_plant_in_one_line(tmp_path, capsys):
    from scenarios.cli import main

    assert main(["levels", "--plants", "sim,mars", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "--plants must be a comma-separated list of sim, highfi, rotorpy, drone-models; found 'sim,mars'" in err
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_the_levels_study_on_our_plant_in_one_run(tmp_path):
    from scenarios.studies.levels import run_levels

    out = run_levels(tmp_path / "models", tmp_path / "out", members=1, plants=["sim"], jobs=2, progress=False,
                     publish=False)
    saved = json.loads((tmp_path / "out" / "levels.json").read_text())
    rows = {(r["level"], r["model"]): r for r in saved["plants"]["sim"]["rows"]}
    assert saved["runs"] == out["runs"] == 6 and len(rows) == 6
    # the oracle tracks at every level: its noise-driven error (member 0) barely grows through the inner loop
    for lv in ("ctbr", "ctatt"):
        assert rows[(lv, "oracle")]["ensemble"]["crashes"] == 0
        assert rows[(lv, "oracle")]["rmse_vs_wrench"] < TOL["oracle_member_ratio"]


def test_versus_at_a_level_flies_the_nominal_model_there_and_its_own_file():
    from pathlib import Path

    from scenarios.studies.versus import plant_models, published_name, versus_specs

    models = Path(__file__).resolve().parents[1] / "models"
    assert plant_models("highfi", models)[:2] == ["nominal", "oracle"] and len(plant_models("highfi", models)) > 2
    # at ctbr: the open-loop models trained at ctbr (not those at the wrench level) and no true equations (none
    # has an inner loop with the plant's lag); the final model of the ctbr learning study published for the plant
    assert plant_models("highfi", models, "ctbr") == ["nominal"] + [str(models / f) for f in (
        "versus/ctbr/ctbr_highfi.onnx", "versus/ctbr/ctbr_aggressive_highfi.onnx",
        "learn/highfi_ctbr/learn_highfi_ctbr_it3.onnx")]
    assert not [m for m in plant_models("highfi", models) if "ctbr" in m]
    assert plant_models("rotorpy", models, "ctatt") == ["nominal"]
    specs = versus_specs("highfi", ["nominal"], members=2, ladder_members=1, level="ctbr")
    assert {s.level for s in specs["ensemble"]["nominal"]} == {"ctbr"}
    assert all(s.level == "ctbr" for runs in specs["ladder"]["nominal"].values() for s in runs)
    assert (published_name(), published_name("ctbr")) == ("versus.json", "versus_ctbr.json")


def test_versus_at_a_level_flies_the_published_learning_study_s_final_model_there(tmp_path):
    """At ctbr a plant flies, after the nominal model, the final model of the learning study published at that level
    (``learn/PLANT_ctbr``); a final model at another level, or none published, adds nothing; the wrench level never
    adds it (the main job flies the wrench study's models)."""
    import json

    from pinn.flights import LaggedCtbrPhysics, export_flight_model
    from scenarios.studies.versus import learned_at_level, plant_models

    theta = {"m": 0.03, "Jxx": 1e-5, "Jyy": 1e-5, "Jzz": 2e-5, "kt": 1e-8, "kq": 1e-10}
    folder = tmp_path / "learn" / "rotorpy_ctbr"
    final = export_flight_model(LaggedCtbrPhysics(0.03, 9.81, 0.0, (0.01,) * 3), folder / "final.onnx", theta, "t",
                                level="ctbr")
    (folder / "learn.json").write_text(json.dumps({"plant": "rotorpy", "level": "ctbr", "final_model": "final"}))
    assert plant_models("rotorpy", tmp_path, "ctbr") == ["nominal", str(final)]
    assert learned_at_level("rotorpy", tmp_path, "wrench") == [] == learned_at_level("highfi", tmp_path, "ctbr")
    assert plant_models("rotorpy", tmp_path, "ctatt") == ["nominal"]
    export_flight_model(LaggedCtbrPhysics(0.03, 9.81, 0.0, (0.01,) * 3), final, theta, "t")    # now a wrench file
    assert plant_models("rotorpy", tmp_path, "ctbr") == ["nominal"]


@pytest.mark.parametrize("content,why", [("", "is not the summary of pinnmpc learn (Expecting value"),
                                         ("[1, 2]", "is not the summary of pinnmpc learn ('list' object"),
                                         ('{"plant": "rotorpy"}', "'final_model' must name its final model; found None"),
                                         ('{"final_model": 3}', "'final_model' must name its final model; found 3")])
def test_a_broken_published_study_summary_is_one_line_naming_the_file(tmp_path, capsys, content, why):
    """pinnmpc versus --level ctbr refuses an unreadable or incomplete published summary before flying or writing
    anything: exit 2, one line naming the file."""
    from scenarios.cli import main

    folder = tmp_path / "models" / "learn" / "highfi_ctbr"
    folder.mkdir(parents=True)
    (folder / "learn.json").write_text(content)
    out = tmp_path / "out"
    assert main(["versus", "--level", "ctbr", "--plants", "highfi", "--models", str(tmp_path / "models"),
                 "--out", str(out), "--members", "1", "--ladder-members", "1"]) == 2
    err = capsys.readouterr().err
    assert str(folder / "learn.json") in err and why in err and err.count("\n") == 1
    assert not out.exists()


def test_a_study_of_a_zoo_with_no_model_at_the_level_is_refused_before_anything_is_written(tmp_path, capsys):
    from scenarios.cli import main

    out = tmp_path / "zoo"
    assert main(["study", "--level", "ctbr", "--no-publish", "--members", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no model can be flown at the 'ctbr' level: every model takes commands at the 'wrench' level" in err
    assert err.count("\n") == 1 and not out.exists()
