"""LTV-MPC with OSQP."""

from pathlib import Path

import numpy as np
import pytest

from mpc.errors import ConfigurationError
from mpc.controllers.lqr import LQRController, hover_point
from mpc.controllers.ltv import LTVMPC, LTVSettings
from mpc.prediction.models import AnalyticModel, LinearModel, OnnxModel
from sim import QuadParams, Simulator
from sim.vehicles.rotors import allocate

ROOT = Path(__file__).resolve().parents[1]
P = QuadParams()
TOL = {
    "lqr_equivalence": 1e-6,   # relative to the size of u - u_hover
    "hover_error_m": 0.01,     # oracle LTV-MPC after 2 s and until 3 s
    "rotor_feasible": 1e-9,    # relative slack on 0 <= n^2 <= n_max^2
    "replay_abs": 1e-12,       # replayed plan / fallback input vs its source (rotor projection rounding), N and N m
}


def offset_state():
    x = np.zeros(12)
    x[0:3] = [0.5, 0.0, -1.0]
    return x


def fly(controller, x, steps, sim=None):
    sim = Simulator(P) if sim is None else sim
    xs, us, infos = [x], [], []
    for k in range(steps):
        u, info = controller(x, k * 0.01)
        x = sim.step(x, u)
        xs.append(x)
        us.append(u)
        infos.append(info)
    return np.array(xs), np.array(us), infos


def test_unconstrained_ltv_on_the_linear_hover_model_is_lqr():
    lq = LQRController()
    xh, uh = hover_point(P)
    mpc = LTVMPC(LinearModel(lq.A, lq.B, xh, uh),
                 settings=LTVSettings(horizon=20, constraints=False, eps_abs=1e-10, eps_rel=1e-10,
                                      polish=True, max_iter=100000))
    rng = np.random.default_rng(0)
    for _ in range(10):
        # Small enough that the LQR input is rotor-feasible (the controller projects onto that set).
        x = xh + rng.normal(size=12) * np.array([0.05] * 3 + [0.02] * 3 + [0.1] * 3 + [0.05] * 3)
        u, info = mpc(x, 0.0)
        u_lqr = uh - lq.K @ (x - xh)
        assert np.all(allocate(u_lqr, P) > 0) and np.all(allocate(u_lqr, P) < P.n_max_sq)
        assert info.status == "optimal"
        assert np.max(np.abs(u - u_lqr)) <= TOL["lqr_equivalence"] * np.max(np.abs(u_lqr - uh))


def test_oracle_ltv_reaches_hover_with_feasible_inputs():
    xs, us, infos = fly(LTVMPC(AnalyticModel()), offset_state(), 300)
    err = np.linalg.norm(xs[:, 0:3] - [0, 0, -1], axis=1)
    assert np.all(err[200:] < TOL["hover_error_m"]), err[200]
    n_sq = allocate(us, P)
    assert np.all(n_sq >= -TOL["rotor_feasible"] * P.n_max_sq)
    assert np.all(n_sq <= (1 + TOL["rotor_feasible"]) * P.n_max_sq)
    assert all(i.is_optimal() for i in infos)
    assert infos[-1].predicted.shape == (31, 12)


def test_onnx_pinn_ltv_flies_hover():
    xs, _, infos = fly(LTVMPC(OnnxModel(ROOT / "models" / "baseline.onnx")), offset_state(), 300)
    err = np.linalg.norm(xs[:, 0:3] - [0, 0, -1], axis=1)
    assert err[-1] < 0.05 and np.all(np.isfinite(xs))
    assert sum(i.fallback is not None for i in infos) == 0


def test_forced_solver_failures_shift_the_plan_then_fall_back_to_lqr():
    mpc = LTVMPC(AnalyticModel())
    x = offset_state()
    u0, info0 = mpc(x, 0.0)
    plan_u = mpc._plan_u.copy()
    assert info0.is_optimal()
    mpc.update_settings(max_iter=1)
    u1, i1 = mpc(x, 0.01)
    u2, i2 = mpc(x, 0.02)
    u3, i3 = mpc(x, 0.03)
    assert (i1.fallback, i2.fallback, i3.fallback) == ("shifted_plan", "shifted_plan", "lqr")
    np.testing.assert_allclose(u1, plan_u[1], rtol=0, atol=TOL["replay_abs"])
    np.testing.assert_allclose(u2, plan_u[2], rtol=0, atol=TOL["replay_abs"])
    np.testing.assert_allclose(u3, mpc.lqr.input(x, mpc.reference(np.array([0.03]))[0]), rtol=0,
                               atol=TOL["replay_abs"])
    assert mpc.counts == {"solver_failures": 3, "shifted_plan": 2, "lqr_fallback": 1}
    assert not i3.is_optimal()
    mpc.update_settings(max_iter=4000)
    _, i4 = mpc(x, 0.04)
    assert i4.is_optimal() and mpc.failures_in_a_row == 0


def test_two_runs_give_identical_inputs():
    a = fly(LTVMPC(AnalyticModel()), offset_state(), 40)[1]
    b = fly(LTVMPC(AnalyticModel()), offset_state(), 40)[1]
    assert np.array_equal(a, b)


@pytest.mark.parametrize("kwargs,match", [
    (dict(horizon=0), "horizon"),
    (dict(attitude_limit_rad=2.0), "attitude_limit_rad"),
    (dict(max_iter=0), "max_iter"),
])
def test_bad_settings_are_clear_errors(kwargs, match):
    with pytest.raises(ConfigurationError, match=match):
        LTVSettings(**kwargs)


def test_bad_model_and_state_are_clear_errors():
    with pytest.raises(ConfigurationError, match="PredictionModel"):
        LTVMPC("models/baseline.onnx")
    with pytest.raises(ValueError, match="x must be finite"):
        LTVMPC(AnalyticModel())(np.full(12, np.inf), 0.0)


def test_a_model_returning_nan_is_a_counted_failure_not_an_exception(nan_jacobians_after):
    from mpc.controllers.lqr import hover_linearization
    model = nan_jacobians_after(LinearModel(*hover_linearization(), *hover_point()), 2)   # the linear hover model
    mpc = LTVMPC(AnalyticModel())
    mpc.model = model            # the LQR fallback keeps the analytic gain; only the prediction breaks
    x = hover_point()[0].copy()
    x[0] = 0.3
    statuses = [mpc(x, 0.01 * k)[1] for k in range(5)]
    assert [i.status for i in statuses[:2]] == ["optimal", "optimal"]
    assert all(i.status == "non-finite model output" for i in statuses[2:])
    assert [i.fallback for i in statuses[2:]] == ["shifted_plan", "shifted_plan", "lqr"]
    assert mpc.counts == {"solver_failures": 3, "shifted_plan": 2, "lqr_fallback": 1}
