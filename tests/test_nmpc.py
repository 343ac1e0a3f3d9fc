"""NMPC with CasADi + IPOPT."""

from pathlib import Path

import numpy as np
import pytest

from mpc.errors import ConfigurationError, ModelContractError
from mpc.prediction.models import AnalyticModel, OnnxModel
from mpc.controllers.nmpc import NMPC, NMPCSettings
from mpc.controllers.sqp import SQPMPC, SQPSettings
from sim import QuadParams, Simulator
from sim.vehicles.rotors import allocate

ROOT = Path(__file__).resolve().parents[1]
P = QuadParams()
TOL = {
    "hover_error_m": 0.01,     # oracle NMPC from a 0.5 m offset: within 1 cm from 2 s on
    "rotor_feasible": 1e-9,    # relative slack on 0 <= n^2 <= n_max^2
    "replay_abs": 1e-12,       # replayed plan input vs the stored plan, N and N m
    "hessians_objective": 1e-9,  # exact vs limited-memory Hessian, both to tol 1e-10: same optimum (relative)
    "defect_abs": 1e-9,        # |F(x_k, u_k) - x_{k+1}| of a converged plan
}


def offset_state():
    x = np.zeros(12)
    x[0:3] = [0.5, 0.0, -1.0]
    return x


def fly(controller, steps):
    sim, x = Simulator(P), offset_state()
    xs, us, infos = [x], [], []
    for k in range(steps):
        u, info = controller(x, k * 0.01)
        x = sim.step(x, u)
        xs.append(x), us.append(u), infos.append(info)
    return np.array(xs), np.array(us), infos


@pytest.fixture(scope="module")
def oracle_flight():
    return fly(NMPC(AnalyticModel(), settings=NMPCSettings(horizon=20)), 250)


def test_oracle_nmpc_reaches_hover_within_two_seconds_and_stays(oracle_flight):
    xs, _, infos = oracle_flight
    err = np.linalg.norm(xs[:, 0:3] - [0, 0, -1], axis=1)
    assert np.all(err[200:] < TOL["hover_error_m"]), err[200]
    assert all(i.is_optimal() for i in infos)


def test_every_applied_input_is_rotor_feasible(oracle_flight):
    n_sq = allocate(oracle_flight[1], P)
    assert np.all(n_sq >= -TOL["rotor_feasible"] * P.n_max_sq)
    assert np.all(n_sq <= (1 + TOL["rotor_feasible"]) * P.n_max_sq)


def test_forced_solver_failures_shift_the_plan_then_fall_back_to_lqr():
    mpc = NMPC(AnalyticModel(), settings=NMPCSettings(horizon=10))
    x = offset_state()
    _, i0 = mpc(x, 0.0)
    plan_u = mpc._unpack(mpc._w)[1]
    assert i0.is_optimal()
    mpc.update_settings(time_limit_s=1e-9)
    (u1, i1), (u2, i2), (u3, i3) = (mpc(x, 0.01), mpc(x, 0.02), mpc(x, 0.03))
    assert (i1.fallback, i2.fallback, i3.fallback) == ("shifted_plan", "shifted_plan", "lqr")
    np.testing.assert_allclose(u1, plan_u[1], rtol=0, atol=TOL["replay_abs"])
    np.testing.assert_allclose(u2, plan_u[2], rtol=0, atol=TOL["replay_abs"])
    np.testing.assert_allclose(u3, mpc.lqr.input(x, mpc.reference(np.array([0.03]))[0]), rtol=0,
                               atol=TOL["replay_abs"])
    assert mpc.counts == {"solver_failures": 3, "shifted_plan": 2, "lqr_fallback": 1}
    assert "CpuTime" in i1.extra["ipopt_status"]


def test_onnx_pinn_nmpc_plan_obeys_the_model():
    """The ONNX callback path (one onnxruntime call per horizon, declared block sparsity) solves."""
    nm = NMPC(OnnxModel(ROOT / "models" / "baseline.onnx"), settings=NMPCSettings(horizon=10))
    x = np.zeros(12)
    x[2] = -1.0
    x[0] = 0.05
    u, info = nm(x, 0.0)
    assert info.is_optimal(), info.extra["ipopt_status"]
    assert info.predicted.shape == (11, 12)
    # The plan obeys the model: predicted x_1 is the ONNX step from x_0 with the first input.
    model = nm.model
    np.testing.assert_allclose(info.predicted[1], model.step(x, nm._unpack(nm._w)[1][0])[0], atol=1e-6)


def test_two_runs_give_identical_inputs():
    a = fly(NMPC(AnalyticModel(), settings=NMPCSettings(horizon=10)), 15)[1]
    b = fly(NMPC(AnalyticModel(), settings=NMPCSettings(horizon=10)), 15)[1]
    assert np.array_equal(a, b)


def tight_settings(**kw):
    return NMPCSettings(horizon=10, tol=1e-10, max_iter=3000, time_limit_s=60.0, **kw)


def hold_guess(x):
    return np.tile(x, (11, 1)), np.tile([P.m * P.g, 0.0, 0.0, 0.0], (10, 1))


def test_exact_and_limited_memory_hessians_reach_the_same_optimum_with_the_oracle():
    model, x = AnalyticModel(), offset_state()
    cost = SQPMPC(model, settings=SQPSettings(horizon=10)).cost    # the NMPC's Q, R, P
    ref, u_ref = NMPC(model, settings=tight_settings())._horizon_reference(0.0)
    out = [NMPC(model, settings=tight_settings(hessian=h)).solve_from(x, 0.0, *hold_guess(x))
           for h in ("exact", "limited-memory")]
    assert [o[2] for o in out] == ["Solve_Succeeded"] * 2
    je, jl = (cost(X, U, ref, u_ref) for X, U, _ in out)
    assert abs(je - jl) / je <= TOL["hessians_objective"], (je, jl)


def test_the_exact_hessian_converges_with_a_pinn_to_a_point_the_limited_memory_one_keeps():
    # From a 0.5 m offset the Baseline PINN's problem has several local optima (measured: from the same guess
    # the exact Hessian ends at 1339.1, the limited-memory one at 1332.0 and the SQP at 1342.1, each a KKT point
    # the others stay at), so the check is convergence and agreement at the point, not which optimum.
    model, x = OnnxModel(ROOT / "models" / "baseline.onnx"), offset_state()
    cost = SQPMPC(model, settings=SQPSettings(horizon=10)).cost
    exact, lbfgs = NMPC(model, settings=tight_settings(hessian="exact")), NMPC(model, settings=tight_settings())
    ref, u_ref = exact._horizon_reference(0.0)
    Xe, Ue, status = exact.solve_from(x, 0.0, *hold_guess(x))
    assert status == "Solve_Succeeded", status
    np.testing.assert_allclose(Xe[1:], model.step(Xe[:-1], Ue), rtol=0, atol=TOL["defect_abs"])
    Xl, Ul, _ = lbfgs.solve_from(x, 0.0, Xe, Ue)
    je, jl = cost(Xe, Ue, ref, u_ref), cost(Xl, Ul, ref, u_ref)
    assert abs(je - jl) / je <= TOL["hessians_objective"], (je, jl)


def test_the_exact_hessian_needs_a_graph_casadi_can_rebuild():
    with pytest.raises(ModelContractError, match="GatherND"):
        NMPC(OnnxModel(ROOT / "models" / "modular.onnx"), settings=NMPCSettings(horizon=5, hessian="exact"))


@pytest.mark.parametrize("kwargs,match", [
    (dict(horizon=0), "horizon"), (dict(time_limit_s=-1.0), "time_limit_s"), (dict(max_iter=0), "max_iter"),
    (dict(hessian="bfgs"), "hessian"),
])
def test_bad_settings_are_clear_errors(kwargs, match):
    with pytest.raises(ConfigurationError, match=match):
        NMPCSettings(**kwargs)


def test_no_cpu_time_limit_in_ideal_timing():
    """A period cut by IPOPT's CPU-time limit depends on the machine (measured: the proposed PINN's hardest
    figure-8 period takes about 1 s, so a 1 s limit stopped it in some runs and not others). 0 means no limit, and
    the ideal-timing controller has none; real-time timing keeps it."""
    from mpc.controllers.factory import make_controller

    x = offset_state()
    cut = NMPC(AnalyticModel(), settings=NMPCSettings(horizon=10, time_limit_s=1e-9))
    free = NMPC(AnalyticModel(), settings=NMPCSettings(horizon=10, time_limit_s=0.0))
    assert "CpuTime" in cut(x, 0.0)[1].extra["ipopt_status"]
    assert free(x, 0.0)[1].is_optimal()
    ideal = make_controller("nmpc", AnalyticModel(), None, horizon=10, timing="ideal")
    realtime = make_controller("nmpc", AnalyticModel(), None, horizon=10, timing="realtime")
    assert (ideal.s.time_limit_s, realtime.s.time_limit_s) == (0.0, NMPCSettings().time_limit_s)
