"""Scenarios, closed-loop metrics, the runner and ``pinnmpc fly``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from mpc.prediction.contract import jacobian_path
from scenarios import get_scenario, scenario_names
from scenarios.errors import ScenarioError
from scenarios.closed_loop.library import VARIANTS
from scenarios.closed_loop.library import DELAY_STEPS, NOISE, PAYLOAD_FRACTION, GustImpulse, WindGusts
from scenarios.closed_loop.metrics import (LADDER_RMSE_BOUND_M, TIMING_FIELDS, TRACE_TIMING_FIELDS, closed_loop_metrics,
                                           crash_reason, max_trackable_speed)
from scenarios.closed_loop.runner import RunSpec, fly
from scenarios.sweeps.sweep import sweep
from sim.params import DT, NX, QuadParams

REPO = Path(__file__).resolve().parents[1]
MODELS = REPO / "models"

TOL = {
    "fd_velocity_abs": 1e-7,     # m/s, central difference (h = 1e-5 s) vs analytic velocity
    "metric_abs": 1e-12,         # synthetic trace metrics vs their closed form
    "noise_std_rel": 0.15,       # sample std of the measurement noise vs NoiseModel (500 samples)
}


# --------------------------------------------------------------------------- scenarios as data

def test_scenario_names_are_the_designs():
    names = scenario_names()
    assert names[:3] == ["hover", "figure8-slow", "figure8-fast"]
    assert names[3:7] == ["figure8-2.7s", "figure8-2.4s", "figure8-2.2s", "figure8-2.0s"]
    assert names[7:11] == ["random-0", "random-1", "random-2", "yaw-turn"]
    assert len(names) == 11 + 3 * 6
    for v in ("highfi", "payload", "wind", "steadywind", "noise", "delay"):
        assert f"figure8-fast+{v}" in names
    assert get_scenario("random-17").path_seed == 17          # any waypoint seed
    with pytest.raises(ScenarioError, match="unknown scenario"):
        get_scenario("figure8-2.0s+wind")


def test_unknown_names_raise_a_value_error_naming_them():
    for bad in ("hovr", "hover+foo", "figure8"):
        with pytest.raises(ScenarioError, match="unknown scenario"):
            get_scenario(bad)
    with pytest.raises(ScenarioError, match="controller"):
        RunSpec("hover", "pid")
    with pytest.raises(ScenarioError, match="does not exist"):
        RunSpec("hover", "ltv", "nowhere.onnx")
    with pytest.raises(ScenarioError, match="seed"):
        get_scenario("hover", seed=-1)


def test_variants_change_only_their_field():
    base = get_scenario("figure8-slow")
    assert base.duration_s == 12.0 and base.period_s == 6.0
    assert get_scenario("figure8-slow+payload").payload_fraction == PAYLOAD_FRACTION
    assert get_scenario("figure8-slow+delay").delay_steps == DELAY_STEPS
    assert get_scenario("figure8-slow+noise").noise == NOISE
    assert get_scenario("figure8-slow+highfi").high_fidelity
    assert get_scenario("figure8-slow+wind").wind is not None
    for v in ("payload", "delay", "noise", "highfi", "wind"):
        s = get_scenario(f"figure8-slow+{v}")
        assert (s.x0, s.duration_s, s.period_s) == (base.x0, base.duration_s, base.period_s)


def test_hover_starts_off_the_setpoint_as_designed():
    s = get_scenario("hover")
    x0 = np.array(s.x0)
    offset = np.linalg.norm(x0[:3] - np.array([0.0, 0.0, -1.0]))
    assert 0.02 <= offset <= 0.06                                # a few cm
    assert 2 <= np.max(np.abs(np.rad2deg(x0[3:6]))) <= 6          # and a few degrees
    assert np.all(x0[6:] == 0.0)
    imp = s.impulse
    assert imp is not None and 0 < imp.start_s < s.duration_s - 2.0 - 1.0   # a settled window after it


def test_gust_impulse_has_its_designed_shape():
    g = GustImpulse(start_s=1.5, duration_s=0.2, peak_mps2=3.0, direction=(0.6, 0.8, 0.0))
    np.testing.assert_array_equal(g(1.49), 0.0)
    np.testing.assert_array_equal(g(1.7), 0.0)
    np.testing.assert_allclose(g(1.6), [1.8, 2.4, 0.0], rtol=0, atol=1e-12)   # midpoint: the full peak
    t = np.arange(1.5, 1.7, 1e-5)
    impulse = np.sum([g(ti) for ti in t], axis=0) * 1e-5
    np.testing.assert_allclose(impulse, 0.5 * 3.0 * 0.2 * np.array([0.6, 0.8, 0.0]), rtol=1e-4)


@pytest.mark.parametrize("name", ["figure8-slow", "figure8-fast"])
def test_figure8_velocities_are_the_derivative_of_positions(name):
    ref = get_scenario(name).reference()
    t = np.linspace(0.0, 12.0, 2401)
    h = 1e-5
    fd = (ref(t + h)[:, 0:3] - ref(t - h)[:, 0:3]) / (2 * h)
    np.testing.assert_allclose(ref(t)[:, 9:12], fd, rtol=0, atol=TOL["fd_velocity_abs"])
    r = ref(t)
    assert np.all(r[:, 2] == -1.0)                       # 1 m altitude, NED
    assert np.max(np.abs(r[:, 0])) == pytest.approx(0.75, abs=1e-3)


def test_figure8_starts_on_its_reference():
    s = get_scenario("figure8-fast")
    np.testing.assert_array_equal(np.array(s.x0), s.reference()(np.array([0.0]))[0])


def test_wind_gusts_have_their_designed_shape():
    w = WindGusts(gust_peak=1.5, gust_duration_s=0.8, n_gusts=3, flight_duration_s=6.0, seed=4)
    mean = np.array(w.mean)
    starts = w.to_dict()["gust_starts_s"]
    assert len(starts) == 3 and all(0 <= s < 6.0 for s in starts)
    np.testing.assert_array_equal(w(starts[0] - 0.01), mean)              # before a gust: the steady part
    mid = w(starts[0] + 0.4) - mean                                       # gust midpoint: the full peak
    assert np.linalg.norm(mid) == pytest.approx(1.5, rel=1e-12)
    assert mid[2] == 0.0                                                  # horizontal
    assert WindGusts(seed=4).to_dict() == WindGusts(seed=4).to_dict()
    assert WindGusts(seed=4).to_dict() != WindGusts(seed=5).to_dict()


# --------------------------------------------------------------------------- metrics

def test_settled_error_recovery_and_heading_on_a_synthetic_trace():
    # 600 periods (6 s): a gust at 1.5 s pushes the error to 0.05 m, which decays linearly to 2 mm at 3.0 s,
    # then stays at 2 mm except one 3 mm sample at 5.5 s. Heading off by 0.1 rad in the first half.
    K = 600
    t = DT * np.arange(1, K + 1)
    e = np.full(K, 0.002)
    gust = (t >= 1.5) & (t < 3.0)
    e[gust] = 0.05 - (0.05 - 0.002) * (t[gust] - 1.5) / 1.5
    e[np.argmin(np.abs(t - 5.5))] = 0.003
    x_ref = np.zeros((K + 1, NX))
    x_ref[:, 2] = -1.0
    x_ref[:, 5] = np.pi - 0.05          # heading error wraps: pi - 0.05 vs -pi + 0.05 is 0.1 rad apart
    x = x_ref.copy()
    x[1:, 0] += e
    x[1:301, 5] = -np.pi + 0.05
    m = closed_loop_metrics(x, x_ref, np.zeros(K), np.zeros(K, bool), np.zeros(K, bool), None,
                            impulse_start_s=1.5, planned_steps=K)
    assert m["settled_error_m"] == pytest.approx(0.003, abs=TOL["metric_abs"])       # max over 4-6 s
    assert m["gust_peak_error_m"] == pytest.approx(0.05, abs=TOL["metric_abs"])
    # back within settled + 5 mm = 8 mm for good once 0.05 - 0.048 (t - 1.5) / 1.5 <= 0.008: t >= 2.8125 s
    t_rec = t[np.nonzero(e > 0.008)[0][-1] + 1] - 1.5
    assert m["recovery_time_s"] == pytest.approx(t_rec, abs=TOL["metric_abs"])
    assert 1.3 - DT <= m["recovery_time_s"] <= 1.32
    assert m["rmse_yaw_rad"] == pytest.approx(np.sqrt(300 * 0.1 ** 2 / K), abs=1e-9)
    crashed = closed_loop_metrics(x[:101], x_ref[:101], np.zeros(100), np.zeros(100, bool), np.zeros(100, bool),
                                  100, "below ground", impulse_start_s=1.5, planned_steps=K)
    assert crashed["settled_error_m"] is None and crashed["recovery_time_s"] is None


def test_max_trackable_speed_climbs_the_ladder_until_the_first_failure():
    ladder = ["a", "b", "c", "d"]
    speeds = {"a": 1.0, "b": 2.0, "c": 3.0, "d": 4.0}

    def run(name, rmse, crashed=False):
        return {"scenario": name, "rmse_position_m": rmse, "crashed": crashed, "error": None}

    good, bad = 0.5 * LADDER_RMSE_BOUND_M, 1.5 * LADDER_RMSE_BOUND_M
    r = max_trackable_speed([run("a", good), run("b", good), run("c", bad), run("d", good)], ladder, speeds)
    assert (r["speed_mps"], r["scenario"], r["failed_at"]) == (2.0, "b", "c")      # d does not count after c
    r = max_trackable_speed([run("a", good), run("b", good, crashed=True)], ladder, speeds)
    assert (r["speed_mps"], r["failed_at"]) == (1.0, "b")
    r = max_trackable_speed([run(n, good) for n in ladder], ladder, speeds)
    assert (r["speed_mps"], r["failed_at"], r["complete"]) == (4.0, None, True)
    r = max_trackable_speed([run("a", bad)], ladder, speeds)
    assert r["speed_mps"] is None and r["failed_at"] == "a"
    assert max_trackable_speed([run("a", good)], ladder, speeds)["complete"] is False


def test_metrics_on_a_synthetic_trace_with_known_answer():
    K = 100
    x_ref = np.zeros((K + 1, NX))
    x_ref[:, 2] = -1.0
    x = x_ref.copy()
    x[1:51, 0] += 0.1            # 50 samples 0.1 m off (north)
    x[51:, 1] += 0.2             # 50 samples 0.2 m off (east)
    solve = np.full(K, 0.002)
    solve[:5] = 0.05             # 5 deadline misses (50 ms > 10 ms)
    failed = np.zeros(K, bool)
    failed[[3, 4, 5, 40]] = True
    lqr = np.zeros(K, bool)
    lqr[5] = True
    m = closed_loop_metrics(x, x_ref, solve, failed, lqr, None)
    assert m["rmse_position_m"] == pytest.approx(np.sqrt((0.01 + 0.04) / 2), abs=TOL["metric_abs"])
    assert m["max_position_error_m"] == pytest.approx(0.2, abs=TOL["metric_abs"])
    assert m["solve_ms"]["median"] == pytest.approx(2.0, abs=TOL["metric_abs"])
    assert m["solve_ms"]["max"] == pytest.approx(50.0, abs=TOL["metric_abs"])
    # p95 of 95 x 2 ms and 5 x 50 ms (linear interpolation at index 94.05 of 0..99): 2 + 0.05 * 48 ms
    assert m["solve_ms"]["p95"] == pytest.approx(2.0 + 0.05 * 48.0, abs=1e-9)
    assert (m["deadline_misses"], m["solver_failures"], m["fallbacks"], m["steps"]) == (5, 4, 1, K)
    assert m["crashed"] is False and m["crash_time_s"] is None


def test_crash_ends_the_metrics_at_the_crash():
    K = 20
    x_ref = np.zeros((K + 1, NX))
    x_ref[:, 2] = -1.0
    x = x_ref.copy()
    x[1:, 0] = 0.3
    m = closed_loop_metrics(x[:13], x_ref[:13], np.zeros(12), np.zeros(12, bool), np.zeros(12, bool), 12, "tilt")
    assert m["crashed"] and m["crash_time_s"] == pytest.approx(0.12)
    assert m["rmse_position_m"] == pytest.approx(0.3) and m["steps"] == 12


def test_crash_conditions():
    ref = np.zeros(NX)
    ref[2] = -1.0
    x = ref.copy()
    assert crash_reason(x, ref) is None
    x[2] = 0.01
    assert crash_reason(x, ref) == "below ground"
    x = ref.copy()
    x[0] = 2.01
    assert crash_reason(x, ref) == "position error > 2 m"
    x = ref.copy()
    x[4] = np.deg2rad(80.5)
    assert crash_reason(x, ref) == "tilt > 80 deg"
    x[4] = np.deg2rad(79.5)
    assert crash_reason(x, ref) is None
    x[7] = np.nan
    assert crash_reason(x, ref) == "non-finite state"


# --------------------------------------------------------------------------- runner

def _scaled_model(src: Path, dst: Path, s: float) -> Path:
    """A copy of ``src`` whose predicted change of state is multiplied by ``s`` (and its derivative graph).

    ``x_next' = x + s (x_next - x)``, ``A' = I + s (A - I)``, ``B' = s B``; with ``s = -1``
    the model predicts time running backwards: a deliberately wrong, contract-valid model.
    """
    for which, path_in, path_out in (("model", src, dst), ("jac", jacobian_path(src), jacobian_path(dst))):
        m = onnx.load(str(path_in))
        g = m.graph
        for node in g.node:                       # rename the graph's outputs to *_raw
            node.output[:] = [o + "_raw" if o in ("x_next", "A", "B") else o for o in node.output]
        g.initializer.extend([numpy_helper.from_array(np.array(s, dtype=np.float64), "scale_s"),
                              numpy_helper.from_array(np.eye(NX), "eye12")])
        g.node.extend([helper.make_node("Sub", ["x_next_raw", "x"], ["d_raw"]),
                       helper.make_node("Mul", ["d_raw", "scale_s"], ["d_s"]),
                       helper.make_node("Add", ["x", "d_s"], ["x_next"])])
        if which == "jac":
            g.node.extend([helper.make_node("Sub", ["A_raw", "eye12"], ["a1"]),
                           helper.make_node("Mul", ["a1", "scale_s"], ["a2"]),
                           helper.make_node("Add", ["a2", "eye12"], ["A"]),
                           helper.make_node("Mul", ["B_raw", "scale_s"], ["B"])])
        onnx.save(m, str(path_out))
    return dst


@pytest.fixture(scope="module")
def reversed_model(tmp_path_factory):
    return _scaled_model(MODELS / "proposed.onnx", tmp_path_factory.mktemp("bad") / "reversed.onnx", -1.0)


def _deterministic(result: dict) -> str:
    return json.dumps({k: v for k, v in result.items() if k not in TIMING_FIELDS}, sort_keys=True)


def test_a_wrong_model_crashes_as_data_and_the_sweep_goes_on(reversed_model, tmp_path):
    specs = [RunSpec("hover", "ltv", str(reversed_model)), RunSpec("hover", "lqr", "oracle")]
    res = sweep(specs, tmp_path, jobs=1, progress=False)
    bad, good = res
    assert bad["crashed"] is True and bad["error"] is None
    assert 0 < bad["crash_time_s"] < 5.0 and bad["crash_reason"]
    assert bad["steps"] == round(bad["crash_time_s"] / DT)
    assert good["crashed"] is False and good["rmse_position_m"] < 0.2
    tr = np.load(tmp_path / bad["trace"])
    assert len(tr["t"]) == bad["steps"] + 1 and crash_reason(tr["x"][-1], tr["x_ref"][-1]) is not None
    saved = json.loads((tmp_path / "runs" / f"{bad['run_id']}.json").read_text())
    assert saved["crashed"] is True


@pytest.mark.slow
def test_same_seed_gives_identical_results_and_another_seed_does_not(tmp_path):
    spec = RunSpec("hover+noise", "ltv", str(MODELS / "proposed.onnx"), seed=3)
    r1, t1 = fly(spec)
    r2, t2 = fly(spec)
    assert _deterministic(r1) == _deterministic(r2)
    assert set(t1) == set(t2)
    for k in set(t1) - set(TRACE_TIMING_FIELDS):
        np.testing.assert_array_equal(t1[k], t2[k])
    r3, t3 = fly(RunSpec("hover+noise", "ltv", str(MODELS / "proposed.onnx"), seed=4))
    assert _deterministic(r3) != _deterministic(r1)
    assert not np.array_equal(t3["x_measured"], t1["x_measured"])


@pytest.mark.slow
def test_a_two_process_sweep_equals_the_serial_one(tmp_path):
    specs = [RunSpec("hover+wind", "lqr", "oracle", seed=2), RunSpec("figure8-fast", "lqr", "oracle"),
             RunSpec("hover+delay", "ltv", str(MODELS / "fourier.onnx"))]
    serial = sweep(specs, tmp_path / "a", jobs=1, progress=False)
    pooled = sweep(specs, tmp_path / "b", jobs=2, progress=False)
    assert [r["run_id"] for r in pooled] == [s.run_id for s in specs]
    assert [_deterministic(r) for r in serial] == [_deterministic(r) for r in pooled]


def test_delay_applies_the_previous_command_and_noise_has_its_std():
    r, tr = fly(RunSpec("hover+delay", "lqr", "oracle"))
    d = DELAY_STEPS
    np.testing.assert_array_equal(tr["u"][d:], tr["u_command"][:-d])
    p = QuadParams()
    for k in range(d):
        np.testing.assert_array_equal(tr["u"][k], [p.m * p.g, 0, 0, 0])
    r, tr = fly(RunSpec("hover+noise", "lqr", "oracle"))
    dev = tr["x_measured"] - tr["x"][:-1]
    np.testing.assert_allclose(dev.std(axis=0), NOISE.state_std, rtol=TOL["noise_std_rel"])


def test_sweep_rejects_duplicates_and_bad_jobs(tmp_path):
    s = RunSpec("hover", "lqr")
    with pytest.raises(ScenarioError, match="duplicate"):
        sweep([s, s], tmp_path, progress=False)
    with pytest.raises(ScenarioError, match="jobs"):
        sweep([s], tmp_path, jobs=0, progress=False)


# --------------------------------------------------------------------------- pinnmpc fly

def test_fly_json_has_the_designs_fields(tmp_path, capsys):
    from scenarios.cli import main

    out = tmp_path / "r.json"
    png = tmp_path / "r.png"
    assert main(["fly", "--model", "oracle", "--controller", "lqr", "--scenario", "figure8-fast",
                 "--json", str(out), "--plot", str(png)]) == 0
    r = json.loads(out.read_text())
    for k in ("scenario", "controller", "model", "rmse_position_m", "max_position_error_m", "crashed",
              "crash_time_s", "deadline_misses", "solver_failures", "fallbacks"):
        assert k in r
    assert set(r["solve_ms"]) == {"median", "p95", "max"}
    assert (r["scenario"], r["controller"], r["model"]) == ("figure8-fast", "lqr", "oracle")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    assert f"{r['rmse_position_m']:.4g}" in printed


def test_fly_bad_input_is_a_one_line_error(tmp_path, capsys):
    from scenarios.cli import main

    assert main(["fly", "--model", "oracle", "--controller", "ltv", "--scenario", "circle"]) == 2
    err = capsys.readouterr().err
    assert "unknown scenario 'circle'" in err and "Traceback" not in err
    assert main(["fly", "--model", str(tmp_path / "m.onnx"), "--controller", "ltv", "--scenario", "hover"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_run_and_report_reject_bad_input_before_anything_runs(tmp_path, capsys):
    from scenarios.studies.campaign import main_plan
    from scenarios.cli import main

    assert main(["report", str(tmp_path / "nothing")]) == 2
    assert "not a folder" in capsys.readouterr().err
    assert main(["run", "--out", str(tmp_path / "r"), "--jobs", "0"]) == 2
    assert "--jobs" in capsys.readouterr().err
    assert main(["run", "--out", str(tmp_path / "r"), "--models", str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    specs = main_plan(MODELS)
    other = [s for s in specs if s.plant != "sim" or s.vehicle is not None]
    specs = [s for s in specs if s.plant == "sim" and s.vehicle is None]
    highfi = [s for s in specs if s.scenario.endswith("+highfi")]
    specs = [s for s in specs if not s.scenario.endswith("+highfi")]
    from scenarios.studies.campaign import ESTIMATOR_VARIANTS, OFFSET_FREE_SCENARIOS

    n_sim = len(specs)
    estimated = [s for s in specs if s.estimator != "none"]
    specs = [s for s in specs if s.estimator == "none" and s.scenario not in OFFSET_FREE_SCENARIOS]
    ideal = [s for s in specs if s.timing == "ideal"]
    nmpc = {(s.scenario, s.model_name) for s in ideal if s.controller == "nmpc"}
    assert nmpc == set()     # IPOPT in ideal timing: --full only (one run is a sixth of the sweep)
    sqp = {(s.scenario, s.model_name) for s in ideal if s.controller == "sqp"}
    # Every base scenario, and the disturbance variants of figure8-fast (those of hover and figure8-slow: --full).
    assert {sc for sc, _ in sqp} == {n for n in scenario_names()
                                     if "+" not in n
                                     or n in {f"figure8-fast+{v}" for v in VARIANTS} - {"figure8-fast+highfi"}}
    assert {s.scenario for s in main_plan(MODELS, full=True) if s.controller == "sqp"} == set(scenario_names())
    models = {m for _, m in sqp}
    assert len(models) == 1 + len(list(MODELS.glob("*.jac.onnx")))
    from scenarios.studies.campaign import (EVERY_MODEL_SCENARIOS, LTV_EVERY_MODEL_SCENARIOS, LTV_SCENARIOS,
                                            SUBSET_MODELS, SUBSET_SCENARIOS)

    # Every model on the cases the report compares models on, the oracle and the paper's Proposed on the
    # disturbances, the oracle alone on the others (all with --full).
    pair = {"oracle"} | {Path(m).stem for m in SUBSET_MODELS}
    assert pair == {"oracle", "proposed"} and pair <= models
    assert sqp == {(sc, m) for sc, _ in sqp for m in (models if sc in EVERY_MODEL_SCENARIOS
                                                      else pair if sc in SUBSET_SCENARIOS else {"oracle"})}
    ltv = {(s.scenario, s.model_name) for s in ideal if s.controller == "ltv"}
    assert ltv == {(sc, m) for sc in LTV_SCENARIOS
                   for m in (models if sc in LTV_EVERY_MODEL_SCENARIOS else {"oracle"})}
    from scenarios.studies.bounds import load_bounds

    from scenarios.studies.bounds import BOUND_SCENARIOS

    # The bounds' scenarios asked for by name fly every CI bound case (pinnmpc bounds writes them from those runs)
    named = [s for s in main_plan(MODELS, scenarios=list(BOUND_SCENARIOS)) if s.timing == "ideal"]
    flown = {(s.scenario, s.controller, s.model_name) for s in named}
    assert {(b.scenario, b.controller, b.model) for b in load_bounds()[1]} <= flown
    full_ideal = {(s.scenario, s.controller, s.model_name) for s in main_plan(MODELS, full=True)
                  if s.timing == "ideal" and s.member is None}
    assert {(sc, c, m) for sc in scenario_names() for c in ("sqp", "ltv", "nmpc") for m in models} <= full_ideal
    realtime = {(s.scenario, s.controller, s.model_name) for s in specs if s.timing == "realtime"}
    assert realtime == {("figure8-fast", "sqp", m) for m in pair} | {
        ("figure8-fast", c, "oracle") for c in ("ltv", "nmpc")}
    assert {(s.controller, s.model_name) for s in main_plan(MODELS, full=True) if s.timing == "realtime"} == {
        (c, m) for c in ("sqp", "ltv", "nmpc") for m in models}
    assert {s.scenario for s in main_plan(MODELS, full=True) if s.controller == "nmpc"} == set(scenario_names())
    # With the state estimator: the disturbance and noise variants of the plan with the models of their twins without
    # it, and the offset-free hover cases with the oracle, both ways.
    cases = {(s.scenario, s.model_name) for s in estimated}
    variants = {sc for sc, _ in sqp if "+" in sc and sc.split("+", 1)[1] in ESTIMATOR_VARIANTS}
    from scenarios.studies.campaign import ESTIMATOR_VARIANTS_SUBSET

    every = {sc for sc in variants if sc.split("+", 1)[1] in ESTIMATOR_VARIANTS_SUBSET}
    assert every and cases == ({(sc, m) for sc in every for m in pair}
                               | {(sc, "oracle") for sc in (variants - every) | set(OFFSET_FREE_SCENARIOS)})
    assert every <= {sc for sc, m in sqp if m == "proposed"}       # each beside its twin without the estimator
    assert {(s.scenario, s.model_name) for s in main_plan(MODELS, full=True) if s.estimator == "ekf"} >= {
        (sc, m) for sc in every for m in models}
    hovers = {(s.scenario, s.model_name, s.estimator) for s in main_plan(MODELS) if s.scenario in OFFSET_FREE_SCENARIOS}
    assert hovers == {(sc, "oracle", e) for sc in OFFSET_FREE_SCENARIOS for e in ("none", "ekf")}
    assert {(s.controller, s.estimator, s.timing) for s in estimated} == {("sqp", "ekf", "ideal")}
    every_ekf = main_plan(MODELS, estimator="ekf")
    assert {s.estimator for s in every_ekf} == {"ekf"} and len({s.run_id for s in every_ekf}) == len(every_ekf)
    with pytest.raises(ScenarioError, match="estimator must be one of none, ekf"):
        main_plan(MODELS, estimator="kalman")
    # The high-fidelity plant: the oracle (its true equations), the nominal equations, the nominal-trained twins and
    # the models trained on its own data, with ensemble members where the scenario has them, and no run twice.
    from scenarios.studies.campaign import HIGHFI_DEFAULT_MEMBERS, HIGHFI_MODELS, HIGHFI_SCENARIOS, learned_models

    # ... and the shipped learning study's final model (models/learn/highfi)
    learned = tuple(learned_models(MODELS, "highfi"))
    assert [Path(m).stem for m in learned] == [json.loads((MODELS / "learn" / "highfi" / "learn.json").read_text())
                                                ["final_model"]]

    from scenarios.studies.campaign import HIGHFI_EVERY_MODEL_SCENARIO

    def expect(full):
        # without full, the learned models fly one high-fidelity scenario, the equations both
        return {(sc, m if m in ("oracle", "nominal") else Path(m).stem, k)
                for sc, n in HIGHFI_SCENARIOS.items()
                for m in ("oracle", "nominal") + ((HIGHFI_MODELS + learned)
                                                  if full or sc == HIGHFI_EVERY_MODEL_SCENARIO else ())
                for k in ([None] if (n if full else min(n, HIGHFI_DEFAULT_MEMBERS)) == 1
                          else range(n if full else HIGHFI_DEFAULT_MEMBERS))}
    assert {(s.scenario, s.model_name, s.member) for s in highfi} == expect(False)
    assert {(s.scenario, s.model_name, s.member) for s in main_plan(MODELS, full=True)
            if s.scenario.endswith("+highfi") and s.plant == "sim"} >= expect(True)
    assert {s.controller for s in highfi} == {"sqp"} and all(s.timing == "ideal" for s in highfi)
    full = main_plan(MODELS, full=True)
    assert len({s.run_id for s in full}) == len(full)
    # Other plants (RotorPy is installed with the test extra): figure8-fast with the SQP, the oracle and every shipped
    # model on the ideal set-up, the nominal equations and every model with motor lag and aerodynamics, and the
    # nominal equations flying RotorPy's two presets on both our simulator and RotorPy.
    from scenarios.studies.campaign import PLANT_DEFAULT_MODELS

    # ... and, with motor lag and aerodynamics, the final model of the shipped learning study on RotorPy
    learned_rp = {Path(m).stem for m in learned_models(MODELS, "rotorpy")}
    assert learned_rp == {json.loads((MODELS / "learn" / "rotorpy" / "learn.json").read_text())["final_model"]}
    # ... and the one on RotorPy's Crazyflie preset, flying the Crazyflie (none where that study is not shipped)
    learned_cf = {Path(m).stem for m in learned_models(MODELS, "crazyflie")}
    cf_summary = MODELS / "learn" / "crazyflie" / "learn.json"
    assert learned_cf == ({json.loads(cf_summary.read_text())["final_model"]} if cf_summary.is_file() else set())

    def on_plants(shipped):
        return ({("rotorpy-ideal", "rolling-spider", m) for m in shipped | {"oracle"}}
                | {("rotorpy", "rolling-spider", m) for m in shipped | {"nominal"} | learned_rp}
                | {(p, v, "nominal") for p in ("sim", "rotorpy") for v in ("hummingbird", "crazyflie")}
                | {("rotorpy", "crazyflie", m) for m in learned_cf})
    assert {(s.scenario, s.controller) for s in other} == {("figure8-fast", "sqp")}
    assert {(s.plant, s.vehicle_data.name, s.model_name) for s in other} == on_plants(
        {Path(m).stem for m in PLANT_DEFAULT_MODELS})
    assert {(s.plant, s.vehicle_data.name, s.model_name) for s in full if s.plant != "sim" or s.vehicle} >= \
        on_plants(models - {"oracle"})                  # with --full, every shipped model
    # The same plan on another plant: every run there, the oracle replaced where the plant has no equations.
    on_rp = main_plan(MODELS, plant="rotorpy")
    assert {s.plant for s in on_rp} == {"rotorpy"} and "oracle" not in {s.model for s in on_rp}
    assert not any("+highfi" in s.scenario for s in on_rp)
    assert len(on_rp) == n_sim and len({s.run_id for s in on_rp}) == len(on_rp)


def test_perturbed_starts_of_a_well_posed_case_agree():
    from scenarios.studies.sensitivity import perturbed_rmse

    rows = perturbed_rmse(RunSpec("figure8-fast", "lqr", "oracle"), trials=3, step_m=1e-9)
    assert [r["offset_m"] for r in rows] == [0.0, 1e-9, 2e-9]
    rm = [r["rmse_position_m"] for r in rows]
    assert max(rm) - min(rm) < 1e-8 and not any(r["crashed"] for r in rows)
    base, _ = fly(RunSpec("figure8-fast", "lqr", "oracle"))
    assert rm[0] == base["rmse_position_m"]          # trial 0 is the scenario itself
