"""The estimator away from the start of a path, with an input delay, and when it loses the state.

Every earlier estimator test flew a path that ends where it starts; these fly paths that end elsewhere (the
random minimum-snap paths and a scenario file's table), a delayed actuator, and a model that turns non-finite in
flight. The cases that take minutes are marked slow.
"""

from pathlib import Path

import numpy as np
import pytest

from mpc.prediction.models import AnalyticModel, PredictionModel
from mpc.controllers.offset_free import disturbance_offset
from scenarios.closed_loop.library import get_scenario, scenario_names
from scenarios.closed_loop.loop import IdealClock, RealtimeClock
from scenarios.closed_loop.runner import RunSpec, fly, load_run_model
from mpc.controllers.factory import make_controller
from sim.params import DT
from sim.vehicles.vehicle import load_vehicle

ROOT = Path(__file__).resolve().parents[1]
FLAT_TABLE = str(ROOT / "scenarios" / "examples" / "flat-table.toml")

TOL = {
    "settled_m": 5e-3,      # settled error with the estimator on a path that ends away from its start
    "target_m": 1e-9,       # the steady target's position against the path's end point
    "ratio": 2.0,           # a scenario without disturbances: RMSE with the estimator within 2x of without ...
    "floor_m": 5e-3,        # ... or within 5 mm, whichever is larger
    "delay_ratio": 1.5,     # with an input delay: RMSE with the estimator within 1.5x of without
}


def _oracle():
    return AnalyticModel(load_vehicle(None).params)


def settled(spec: RunSpec) -> float:
    result, _ = fly(spec)
    assert result["error"] is None and not result["crashed"], result.get("crash_reason")
    return result["settled_error_m"]


# ----------------------------------------------------------------- the target where the reference is now

def test_the_steady_target_at_the_end_of_a_path_holds_its_end_point_not_its_start():
    sc = get_scenario("random-0")
    ref = sc.reference()
    ctrl = make_controller("sqp", _oracle(), ref)
    ctrl.prepare(sc.duration_s)
    t_end = sc.duration_s - 0.5                       # the path is over: the reference stands still
    end = ref(np.array([t_end]))[0]
    start = ref(np.array([0.0]))[0]
    assert np.linalg.norm(end[:3] - start[:3]) > 0.3  # a path that ends away from its start (0.32 m)
    ctrl.set_disturbance([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    X, U = ctrl.ff.horizon(t_end + DT * np.arange(4))
    assert np.max(np.abs(X[:, :3] - end[:3])) < TOL["target_m"]
    assert abs(X[0, 5] - end[5]) < TOL["target_m"]
    # and it is the model's equilibrium there under the disturbance
    off = disturbance_offset([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], X[0], 12)
    assert np.max(np.abs(ctrl.ff.model.step(X[0], U[0])[0] + off - X[0])) < 1e-8


def test_the_oracle_with_the_estimator_settles_on_a_scenario_file_that_ends_away_from_its_start():
    """flat-table.toml ends 1.95 m from its start and carries a 20 % payload (104 mm without the estimator)."""
    assert settled(RunSpec(FLAT_TABLE, "sqp", "oracle", estimator="ekf")) < TOL["settled_m"]


def test_the_lqr_with_the_estimator_settles_at_the_end_of_a_random_path():
    assert settled(RunSpec("random-0", "lqr", "oracle", estimator="ekf")) < TOL["settled_m"]


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["random-0", "random-1", "random-2"])
def test_the_sqp_with_the_estimator_settles_at_the_end_of_every_random_path(scenario):
    assert settled(RunSpec(scenario, "sqp", "oracle", estimator="ekf")) < TOL["settled_m"]


def _undisturbed():
    return [n for n in scenario_names() if "+" not in n]


@pytest.mark.slow
@pytest.mark.parametrize("scenario", _undisturbed())
def test_every_built_in_scenario_without_disturbances_flies_with_the_estimator_as_without(scenario):
    without, _ = fly(RunSpec(scenario, "sqp", "oracle"))
    with_, _ = fly(RunSpec(scenario, "sqp", "oracle", estimator="ekf"))
    assert not with_["crashed"] and with_["error"] is None
    bound = max(TOL["ratio"] * without["rmse_position_m"], TOL["floor_m"])
    assert with_["rmse_position_m"] < bound, (with_["rmse_position_m"], without["rmse_position_m"])


# ----------------------------------------------------------------- an actuation delay

@pytest.mark.parametrize("delay", [0, 1, 2])
@pytest.mark.parametrize("clock_type", [IdealClock, RealtimeClock])
def test_the_clocks_tell_the_input_in_effect_after_the_delay(clock_type, delay):
    """What the filter is told: the command sent ``delay`` periods earlier (time-averaged as sent); hover before."""
    hover = np.array([1.0, 0.0, 0.0, 0.0])

    class Plant:
        def advance(self, u, duration):
            pass

    clock = clock_type(hover, delay_steps=delay)
    sent, effect = [], []
    for k in range(6):
        clock.command(k, hover * (1.1 + 0.1 * k), 3.5e-3)     # returns after 4 ms in real time
        clock.fly_period(Plant(), k)
        sent.append(clock.sent.copy())
        effect.append(clock.in_effect.copy())
    expect = [hover] * delay + sent[:len(sent) - delay]
    assert np.max(np.abs(np.array(effect) - np.array(expect))) < 1e-14
    if clock_type is RealtimeClock:     # the command arrived 4 ms into its period: a time average
        np.testing.assert_allclose(sent[0], 0.4 * hover + 0.6 * hover * 1.1, rtol=1e-14)


@pytest.mark.parametrize("scenario", ["hover+delay", pytest.param("figure8-fast+delay", marks=pytest.mark.slow)])
def test_the_estimator_with_an_input_delay_flies_as_well_as_the_true_state(scenario):
    """Fed the command as sent, the filter took the delayed response for a disturbance: the oracle's hover+delay
    went into a +-33 deg roll cycle (206 mm) and figure8-fast+delay crashed at 3.9 s."""
    without, _ = fly(RunSpec(scenario, "sqp", "oracle"))
    with_, _ = fly(RunSpec(scenario, "sqp", "oracle", estimator="ekf"))
    assert not with_["crashed"] and with_["error"] is None
    assert with_["rmse_position_m"] < TOL["delay_ratio"] * without["rmse_position_m"]


# ----------------------------------------------------------------- the filter loses the state

class NonFiniteAfter(PredictionModel):
    """A learned model that turns non-finite after ``calls`` evaluations (its step or its linearization)."""

    def __init__(self, base, calls: int):
        self.base, self.left = base, calls
        self.name, self.theta = base.name, base.theta

    def _tick(self, xn):
        self.left -= 1
        return xn * np.nan if self.left < 0 else xn

    def step(self, x, u):
        return self._tick(self.base.step(x, u))

    def linearize(self, x, u):
        xn, A, B = self.base.linearize(x, u)
        return self._tick(xn), A, B


def test_a_model_that_turns_non_finite_under_the_estimator_ends_as_a_recorded_crash():
    spec = RunSpec("hover", "sqp", str(ROOT / "models" / "baseline.onnx"), estimator="ekf")
    model = NonFiniteAfter(load_run_model(spec), 1500)      # a full hover takes about 3700 calls
    result, trace = fly(spec, model=model)
    assert result["error"] is None
    assert result["crashed"] and result["crash_reason"].startswith("estimator failed: ")
    assert "not finite" in result["crash_reason"]
    assert 0.0 < result["crash_time_s"] < get_scenario("hover").duration_s
    assert len(trace["x"]) == round(result["crash_time_s"] / DT) + 1
    assert np.all(np.isfinite(trace["x"]))               # the vehicle itself never left the finite range
