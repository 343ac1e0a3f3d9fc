"""Dynamically feasible references (flatness map), the model's own feed-forward, and the vehicle spec."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpc.errors import ConfigurationError
from mpc.references.feedforward import FeedForward
from mpc.controllers.lqr import DEFAULT_STATE_SCALE, input_scale
from mpc.controllers.ltv import LTVMPC
from mpc.references.minsnap import random_minsnap
from mpc.prediction.models import AnalyticModel, LinearModel, OnnxModel, load_model
from mpc.prediction.spec import VehicleSpec, datasheet
from mpc.references.trajectory import Figure8, Hover, YawTurn, flat_state, held_wrench
from scenarios import get_scenario
from scenarios.closed_loop.library import LADDER
from sim import QuadParams, Simulator, dynamics
from sim.params import DT

ROOT = Path(__file__).resolve().parents[1]
P = QuadParams()

TOL = {
    "round_trip_m": 2e-3,          # open-loop feed-forward vs reference positions over 0.5 s (figure8-fast)
    "fd_rel": 1e-6,                # dynamics(x_ref, u_ff) vs central difference of x_ref, relative to its size
    "trim_rel": 1e-9,              # the oracle's trim vs m g
    "fit_residual": 1e-4,          # one-period residual of the oracle's feed-forward, in state scales (O(dt^3))
    "oracle_ladder_rmse_m": 5e-3,  # the oracle on the 2 s rung
}

TRAJECTORIES = {
    "figure8-fast": Figure8(period=3.0),
    "figure8-2.0s": Figure8(period=2.0),
    "yaw-turn": YawTurn(),
    "random-3": random_minsnap(3),
}


def test_feed_forward_of_figure8_fast_flies_the_reference_open_loop():
    traj = get_scenario("figure8-fast").reference()
    t = DT * np.arange(51)
    x_ref = traj(t)
    u = held_wrench(traj, t[:-1], P)
    sim, x = Simulator(P), x_ref[0].copy()
    err = []
    for k in range(50):
        x = sim.step(x, u[k])
        err.append(np.linalg.norm(x[:3] - x_ref[k + 1, :3]))
    assert max(err) <= TOL["round_trip_m"], max(err)


@pytest.mark.parametrize("name", list(TRAJECTORIES))
def test_flatness_map_satisfies_the_equations_of_motion(name):
    traj = TRAJECTORIES[name]
    # Off the instants where a velocity component crosses zero: there the drag v|v| is not twice
    # differentiable and the torque jumps (figure-8 at t = period / 4, for example).
    t = np.linspace(0.05, (traj.duration_s or 2.9) - 0.05, 37) + 0.0123
    x, u = flat_state(traj.flat(t), P)
    h = 1e-5
    fd = (traj(t + h) - traj(t - h)) / (2 * h)
    lhs = dynamics(x, u, P)
    scale = np.maximum(np.abs(fd).max(axis=0), 1e-3)
    assert np.max(np.abs(lhs - fd) / scale) <= TOL["fd_rel"]


def test_hover_maps_to_level_attitude_and_the_weight():
    x, u = flat_state(Hover((1.0, 2.0, -3.0), yaw=0.4).flat(np.array([0.0, 1.0])), P)
    np.testing.assert_array_equal(x[:, 0:3], [[1.0, 2.0, -3.0]] * 2)
    np.testing.assert_array_equal(x[:, 5], 0.4)
    assert np.all(x[:, [3, 4, 6, 7, 8, 9, 10, 11]] == 0.0)
    np.testing.assert_allclose(u, [[P.m * P.g, 0, 0, 0]] * 2, rtol=1e-15, atol=0)


def test_the_speed_ladder_reaches_the_rotor_limit_but_stays_inside_it():
    from sim.vehicles.rotors import allocate

    peaks = []
    for name, period in [("figure8-fast", 3.0), *LADDER.items()]:
        t = np.arange(0.0, period, 0.002)
        n_sq = allocate(held_wrench(Figure8(period=period), t, P), P)
        peaks.append(n_sq.max() / P.n_max_sq)
        assert n_sq.min() > 0
    assert peaks == sorted(peaks)               # faster rungs need more
    assert 0.9 < peaks[-1] < 1.0                # the last rung is within 10 % of the rotor limit


# --------------------------------------------------------------------------- the model's own trim and feed-forward

def _ff(model, reference=None):
    spec = VehicleSpec.from_model(model)
    return FeedForward(model, reference, spec, 1.0 / DEFAULT_STATE_SCALE ** 2, input_scale(spec))


def test_trim_is_each_models_own_equilibrium():
    assert _ff(AnalyticModel()).trim == pytest.approx([P.m * P.g, 0, 0, 0], rel=TOL["trim_rel"], abs=1e-12)
    heavy = load_model("analytic:m*1.1")
    assert _ff(heavy).trim[0] == pytest.approx(1.1 * P.m * P.g, rel=TOL["trim_rel"])
    # A learned model's trim is the input that keeps its own prediction closest to hover (a minimum of the
    # weighted one-period drift: any small change of any input makes it larger).
    model = OnnxModel(ROOT / "models" / "baseline.onnx")
    ff = _ff(model)
    x, u = ff.linearization_point()

    def drift(v):
        return np.sum(((model.step(x, v)[0] - x) / DEFAULT_STATE_SCALE) ** 2)

    best = drift(u)
    for i, step in enumerate(1e-3 * input_scale(VehicleSpec.from_model(model))):
        for sign in (-1, 1):
            assert drift(u + sign * step * np.eye(4)[i]) > best
    assert abs(u[0] - P.m * P.g) < 0.01 * P.m * P.g           # close to, but not taken from, the true weight


def test_feed_forward_inverts_the_model_along_the_reference():
    model = AnalyticModel()
    ff = _ff(model, Figure8(period=3.0))
    t = DT * np.arange(40)
    u = ff.inputs(t)
    x0, x1 = ff.states(t), ff.states(t + DT)
    r = (model.step(x0, u) - x1) / DEFAULT_STATE_SCALE
    # A constant input cannot carry all 12 states exactly through a period (the reference's wrench varies
    # within it), but it comes within O(dt^3) and far closer than the wrench at the period's start.
    _, u_start = flat_state(Figure8(period=3.0).flat(t), P)
    r_start = (model.step(x0, u_start) - x1) / DEFAULT_STATE_SCALE
    assert np.max(np.abs(r)) <= TOL["fit_residual"]
    assert np.max(np.abs(r)) <= 0.1 * np.max(np.abs(r_start))
    # The fit is a least-squares minimum: the weighted residual is orthogonal to the input directions.
    _, _, B = model.linearize(x0, u)
    grad = np.einsum("kij,ki->kj", B / DEFAULT_STATE_SCALE[None, :, None], r)
    assert np.max(np.abs(grad)) <= 1e-6 * np.max(np.abs(B / DEFAULT_STATE_SCALE[None, :, None]))
    # A linear model is inverted exactly: its input offset comes back.
    lin = LinearModel(np.eye(12), np.vstack([np.zeros((9, 4)), np.eye(3, 4)]), np.zeros(12), np.ones(4))
    assert np.allclose(_ff(lin).trim[:3], 1.0)


def test_feed_forward_is_cached_per_time():
    calls = []

    class Counting(AnalyticModel):
        def linearize(self, x, u):
            calls.append(len(x))
            return super().linearize(x, u)

    ff = _ff(Counting(), Figure8(period=3.0))
    calls.clear()
    a = ff.inputs(DT * np.arange(30))
    n_first = sum(calls)
    b = ff.inputs(DT * np.arange(1, 31))          # the next period: one new input
    assert np.array_equal(a[1:], b[:-1])
    assert sum(calls) - n_first <= 2              # at most two Gauss-Newton iterations of one input


# --------------------------------------------------------------------------- the vehicle spec

def test_spec_comes_from_the_models_theta_or_the_datasheet():
    model = OnnxModel(ROOT / "models" / "proposed.onnx")
    spec = VehicleSpec.from_model(model)
    assert (spec.m, spec.Jxx, spec.kt, spec.kq) == tuple(model.theta[[0, 1, 4, 5]])
    assert (spec.d, spec.n_max) == (datasheet()["d"], datasheet()["n_max"])
    lin = LinearModel(np.eye(12), np.zeros((12, 4)), np.zeros(12), np.zeros(4))
    assert VehicleSpec.from_model(lin) == VehicleSpec()
    assert VehicleSpec().n_max_sq == pytest.approx(P.n_max_sq, rel=1e-14)   # the datasheet's top speed
    # Another vehicle's datasheet: its own arm and rotor limit, the model's theta where it has one.
    hb = VehicleSpec.from_model(model, "hummingbird")
    assert (hb.d, hb.n_max, hb.m, hb.vehicle) == (0.17, 1500.0, model.theta[0], "hummingbird")
    assert VehicleSpec.from_model(lin, "hummingbird").m == 0.5
    with pytest.raises(ConfigurationError, match="VehicleSpec.m"):
        VehicleSpec(m=-1.0)
    with pytest.raises(ConfigurationError, match="VehicleSpec.n_max"):
        VehicleSpec(n_max=float("nan"))


@pytest.mark.parametrize("bad,match", [
    ("analytic:J*1.3", "NAME\\*FACTOR"), ("analytic:m*0", "factor > 0"), ("analytic:m*1.1,m*1.2", "one factor"),
])
def test_bad_analytic_model_names_are_clear_errors(bad, match):
    with pytest.raises(ValueError, match=match):
        load_model(bad)


@pytest.mark.slow
def test_the_oracle_flies_every_rung_of_the_speed_ladder():
    from scenarios.closed_loop.runner import RunSpec, fly

    for name in LADDER:
        r, _ = fly(RunSpec(name, "ltv", "oracle"))
        assert not r["crashed"], (name, r["crash_reason"])
        if name == "figure8-2.0s":
            assert r["rmse_position_m"] <= TOL["oracle_ladder_rmse_m"]


def test_a_pinn_controller_follows_a_reference_with_its_own_inputs():
    model = OnnxModel(ROOT / "models" / "baseline.onnx")
    ctrl = LTVMPC(model, Figure8(period=6.0))
    u_ref = ctrl.ff.inputs(np.array([0.0]))[0]
    oracle_ff = held_wrench(Figure8(period=6.0), np.array([0.0]), P)[0]
    assert not np.array_equal(u_ref, oracle_ff)                 # not the plant's inverse...
    assert np.abs(u_ref[0] - oracle_ff[0]) < 0.05 * oracle_ff[0]  # ...but the same thrust to a few %
