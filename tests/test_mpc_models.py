"""Prediction models and LQR of mpc/."""

import shutil
import subprocess
import sys
from pathlib import Path

import control
import numpy as np
import pytest

from mpc.errors import ConfigurationError, ModelContractError
from mpc.controllers.lqr import LQRController, default_weights, hover_point
from mpc.prediction.models import AnalyticModel, OnnxModel, load_model
from sim import QuadParams, Simulator
from sim.vehicles.rotors import allocate

ROOT = Path(__file__).resolve().parents[1]
BASELINE = ROOT / "models" / "baseline.onnx"
P = QuadParams()

TOL = {
    "analytic_vs_simulator": 1e-12,   # relative to each state's spread
    "analytic_jacobian_fd": 1e-6,     # CasADi AD vs central differences of the numpy simulator
    "onnx_jacobian_fd": 1e-3,         # derivative graph vs central differences of the ONNX model
    "dlqr_gain": 1e-6,                # K from mpc vs control.dlqr on an independent linearization
    "hover_error_m": 0.01,            # LQR within 1 cm of the setpoint after 2 s
    "single_vs_double": 1e-5,         # float32 derivative graph vs float64 (measured 5e-8 .. 7e-7 near hover)
    "casadi_step_abs": 1e-12,         # ONNX graph rebuilt in CasADi vs onnxruntime (measured 5e-16)
    "casadi_jacobian_rel": 1e-10,     # its AD Jacobian vs the derivative graph (relative to the largest entry)
    "casadi_hessian_rel": 1e-6,       # its AD Hessian vs central differences of the derivative graph (measured 2e-9)
    "rk4_order": (14.0, 18.0),        # one period's error ratio from 1 to 2 RK4 steps: 2^4 = 16 for a 4th-order method
    "points_vs_map": 0.0,             # the point loop against CasADi's map of the same compiled functions: bit for bit
}


def feasible_samples(n, seed=0):
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-2, 2, (n, 3)), np.radians(rng.uniform(-20, 20, (n, 3))),
                         rng.uniform(-1, 1, (n, 3)), rng.uniform(-2, 2, (n, 3))])
    u = np.column_stack([rng.uniform(0.5, 0.8, n), rng.uniform(-1e-3, 1e-3, (n, 3))])
    return x, u


def central_jacobians(step, x, u, h=1e-6):
    """Central differences of a batched ``step`` with respect to x and u, (N, 12, 12) and (N, 12, 4)."""
    A = np.zeros((len(x), 12, 12))
    B = np.zeros((len(x), 12, 4))
    for j in range(12):
        e = np.zeros_like(x)
        e[:, j] = h
        A[:, :, j] = (step(x + e, u) - step(x - e, u)) / (2 * h)
    for j in range(4):
        hj = h * 1e-2 if j > 0 else h
        e = np.zeros_like(u)
        e[:, j] = hj
        B[:, :, j] = (step(x, u + e) - step(x, u - e)) / (2 * hj)
    return A, B


def rel(a, b):
    return np.max(np.linalg.norm(a - b, axis=(1, 2)) / np.linalg.norm(b, axis=(1, 2)))


def test_analytic_model_is_the_simulator_step():
    x, u = feasible_samples(200)
    assert np.all(allocate(u, P) > 0)
    got = AnalyticModel().step(x, u)
    ref = Simulator(P).step(x, u)
    assert np.max(np.abs(got - ref) / np.std(ref - x, axis=0)) < TOL["analytic_vs_simulator"]


def test_fewer_substeps_converge_with_rk4s_fourth_order():
    """The nominal equations with 1 and 2 RK4 steps per period (the model), and 4 (CasADi's own evaluation of the
    same equations), against 64: each halving of the step divides the period's error by about 16 (RK4's local error
    h^5, over n steps n (h / n)^5). The default is 10, the simulator's own."""
    from sim.equations.dynamics_casadi import step_function

    x, u = feasible_samples(20, seed=3)
    x[:, 9:12] *= 3.0                       # body rates up to 6 rad/s: an error well above rounding

    def equations(n):
        return np.asarray(step_function(P, substeps=n).map(len(x))(x.T, u.T)).T
    ref = equations(64)
    steps = [AnalyticModel(substeps=1).step(x, u), AnalyticModel(substeps=2).step(x, u), equations(4)]
    np.testing.assert_allclose(steps[1], equations(2), rtol=0, atol=TOL["analytic_vs_simulator"])
    err = [np.max(np.abs(s - ref)) for s in steps]
    lo, hi = TOL["rk4_order"]
    assert lo <= err[0] / err[1] <= hi and lo <= err[1] / err[2] <= hi, err
    assert AnalyticModel().substeps == 10


@pytest.mark.parametrize("bad,match", [(0, "positive integer; found 0"), (1.5, "positive integer; found 1.5"),
                                       (True, "positive integer; found True")])
def test_a_bad_substep_count_is_refused_by_name(bad, match):
    with pytest.raises(ModelContractError, match=f"substeps must be a {match}"):
        AnalyticModel(substeps=bad)


def test_another_substep_count_is_for_the_nominal_equations_only():
    from sim.params import HIGH_FIDELITY

    with pytest.raises(ModelContractError, match="nominal equations at the wrench level; found substeps=2 with "
                                                 "high-fidelity effects"):
        AnalyticModel(fidelity=HIGH_FIDELITY, substeps=2)


def test_the_point_loop_is_casadis_map_bit_for_bit():
    """The compiled step and Jacobian called at every point in one C call (the default where they compile) against
    CasADi's map of the same compiled functions (the path without it)."""
    x, u = feasible_samples(25, seed=4)
    m = AnalyticModel()
    assert all(p is not None for p in m._points)
    fast = (m.step(x, u), *m.linearize(x, u))
    m._points = (None, None)
    slow = (m.step(x, u), *m.linearize(x, u))
    for a, b in zip(fast, slow):
        assert np.max(np.abs(a - b)) <= TOL["points_vs_map"]


def test_the_analytic_model_pickles_and_copies_with_its_point_loop():
    """Sent to a worker process or deep-copied (a controller's copy of its model), the model makes its point loop
    again from its compiled library: the same numbers, its own work arrays."""
    import copy
    import pickle

    x, u = feasible_samples(5, seed=6)
    m = AnalyticModel()
    for other in (pickle.loads(pickle.dumps(m)), copy.deepcopy(m)):
        assert other._points[1] is not m._points[1] and other._points[1] is not None
        for a, b in zip((other.step(x, u), *other.linearize(x, u)), (m.step(x, u), *m.linearize(x, u))):
            assert np.array_equal(a, b)


def test_analytic_jacobians_match_finite_differences():
    x, u = feasible_samples(10, seed=1)
    xn, A, B = AnalyticModel().linearize(x, u)
    fA, fB = central_jacobians(Simulator(P).step, x, u)
    np.testing.assert_allclose(xn, Simulator(P).step(x, u), rtol=0, atol=1e-12)
    assert rel(A, fA) < TOL["analytic_jacobian_fd"] and rel(B, fB) < TOL["analytic_jacobian_fd"]


def test_onnx_model_jacobians_match_finite_differences():
    m = OnnxModel(BASELINE)
    x, u = feasible_samples(10, seed=2)
    xn, A, B = m.linearize(x, u)
    np.testing.assert_allclose(xn, m.step(x, u), rtol=0, atol=1e-12)
    fA, fB = central_jacobians(m.step, x, u)
    assert rel(A, fA) < TOL["onnx_jacobian_fd"] and rel(B, fB) < TOL["onnx_jacobian_fd"]
    assert m.name == "baseline" and m.theta.shape == (6,)


@pytest.mark.parametrize("name", ["baseline", "fourier", "modular", "proposed"])
def test_single_precision_jacobians_agree_with_the_derivative_graph_and_the_step_stays_exact(name):
    m = OnnxModel(ROOT / "models" / f"{name}.onnx")
    assert m._jac_single is not None, "the float32 copy of a shipped derivative graph was refused"
    x, u = feasible_samples(64, seed=3)       # +-20 deg, +-2 rad/s: wider than the load-time check's probes
    xn, A, B = m.linearize(x, u)
    xs, As, Bs = m.linearize_single(x, u)
    assert np.array_equal(xs, m.step(x, u))
    assert As.dtype == Bs.dtype == np.float64
    assert rel(As, A) < TOL["single_vs_double"] and rel(Bs, B) < TOL["single_vs_double"]
    assert not np.array_equal(As, A)   # it is the float32 graph


def test_a_float32_copy_that_disagrees_is_not_used(tmp_path, monkeypatch):
    from test_contract import build_jacobian, build_model

    import mpc.prediction.contract as contract

    good = build_model(tmp_path / "toy.onnx")
    build_jacobian(good)
    (tmp_path / "wrong").mkdir()
    wrong = build_model(tmp_path / "wrong" / "toy.onnx")
    build_jacobian(wrong, a_scale=1.001)          # A 0.1 % off: what a bad float32 conversion could give
    real = contract.single_precision
    monkeypatch.setattr(contract, "single_precision", lambda path: real(contract.jacobian_path(wrong)))
    with pytest.warns(UserWarning, match="float32 copy differs"):
        m = OnnxModel(good)
    x, u = feasible_samples(5)
    for a, b in zip(m.linearize_single(x, u), m.linearize(x, u)):
        assert np.array_equal(a, b)


def test_a_float32_model_uses_its_own_derivative_graph(tmp_path):
    from test_contract import build_jacobian, build_model

    path = build_model(tmp_path / "toy32.onnx", np.float32)
    build_jacobian(path, np.float32)
    m = OnnxModel(path)
    x, u = feasible_samples(5)
    assert m._jac_single is None
    for a, b in zip(m.linearize_single(x, u), m.linearize(x, u)):
        assert np.array_equal(a, b)


def test_onnx_model_without_derivative_graph_uses_central_differences(tmp_path):
    shutil.copy(BASELINE, tmp_path / "lonely.onnx")
    m = OnnxModel(tmp_path / "lonely.onnx")
    assert m.derivatives == "central differences" and m._jac is None
    x, u = feasible_samples(4)
    for a, b in zip(m.linearize_single(x, u), m.linearize(x, u)):   # no float32 graph to use: the same path
        assert np.array_equal(a, b)


def test_analytic_model_with_identified_parameters():
    m = AnalyticModel.from_onnx_theta(BASELINE)
    from mpc.prediction.contract import check_model
    theta = check_model(BASELINE).theta
    assert m.params.m == theta["m"] and m.params.Jzz == theta["Jzz"] and m.params.g == P.g
    assert load_model("oracle").name == "oracle"


def test_lqr_gain_is_python_controls_dlqr():
    # Independent linearization: central differences of the numpy simulator at hover.
    x, u = hover_point(P)
    fA, fB = central_jacobians(Simulator(P).step, x[None], u[None], h=1e-7)
    Q, R = default_weights(P)
    K_ref, _, _ = control.dlqr(fA[0], fB[0], Q, R)
    K = LQRController().K
    assert np.max(np.abs(K - K_ref)) / np.max(np.abs(K_ref)) < TOL["dlqr_gain"]


def test_lqr_refuses_a_pair_that_is_not_stabilizable():
    # The true hover linearization with the yaw torque removed from B: the yaw rate's integrator (eigenvalue 1)
    # cannot be moved. python-control may return a Riccati solution for it without an error; lqr must not.
    from mpc.errors import ConfigurationError
    from mpc.controllers.lqr import lqr

    x, u = hover_point(P)
    fA, fB = central_jacobians(Simulator(P).step, x[None], u[None], h=1e-7)
    Q, R = default_weights(P)
    B = fB[0].copy()
    B[:, 3] = 0.0
    with pytest.raises(ConfigurationError, match="not stabilizable|no LQR gain"):
        lqr(fA[0], B, Q, R)
    K, Pr = lqr(fA[0], fB[0], Q, R)       # the full pair passes the check
    assert np.max(np.abs(np.linalg.eigvals(fA[0] - fB[0] @ K))) < 1.0


def test_lqr_brings_the_simulator_to_hover_with_feasible_inputs():
    c = LQRController()
    s = Simulator(P)
    x = np.zeros(12)
    x[0:3] = [0.3, -0.2, -0.6]
    x[3] = 0.05
    n_max_sq = P.n_max_sq
    for k in range(200):  # 2 s
        u, info = c(x, k * 0.01)
        n_sq = allocate(u, P)
        assert np.all(n_sq >= -1e-12) and np.all(n_sq <= n_max_sq * (1 + 1e-12))
        assert info.is_optimal() and info.solve_time_s >= 0
        x = s.step(x, u)
    assert np.linalg.norm(x[0:3] - [0, 0, -1]) < TOL["hover_error_m"]


def test_bad_configuration_and_state_are_clear_errors():
    with pytest.raises(ConfigurationError, match="Q must have shape"):
        LQRController(Q=np.eye(11))
    with pytest.raises(ConfigurationError, match="R must be symmetric positive definite"):
        LQRController(R=np.zeros((4, 4)))
    with pytest.raises(ValueError, match="x must be finite"):
        LQRController()(np.full(12, np.nan), 0.0)
    with pytest.raises(ValueError, match="x must have shape"):
        AnalyticModel().step(np.zeros(11), np.zeros(4))


def test_mpc_imports_without_torch():
    code = ("import sys; sys.modules['torch'] = None; import mpc, mpc.prediction.models, mpc.controllers.lqr, "
            "mpc.controllers.controller, mpc.prediction.contract")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("name", ["baseline", "proposed", "baseline_aggressive", "proposed_aggressive"])
def test_the_casadi_rebuild_of_a_dense_pinn_equals_onnxruntime_and_its_derivative_graph(name):
    import casadi as ca

    from mpc.prediction.contract import _probe_batch
    from mpc.prediction.symbolic import casadi_step

    model = OnnxModel(ROOT / "models" / f"{name}.onnx")
    F = casadi_step(model.path)
    x, u = _probe_batch(32, np.float64, seed=4)
    xs, us = ca.MX.sym("x", 12), ca.MX.sym("u", 4)
    y = F(xs, us)
    lin = ca.Function("lin", [xs, us], [y, ca.jacobian(y, xs), ca.jacobian(y, us)]).map(len(x))
    xn, A, B = (np.asarray(v) for v in lin(x.T, u.T))
    xn1, A1, B1 = model.linearize(x, u)
    assert np.max(np.abs(xn.T - xn1)) <= TOL["casadi_step_abs"]
    A = A.reshape(12, len(x), 12).transpose(1, 0, 2)
    B = B.reshape(12, len(x), 4).transpose(1, 0, 2)
    assert np.max(np.abs(A - A1)) / np.max(np.abs(A1)) <= TOL["casadi_jacobian_rel"]
    assert np.max(np.abs(B - B1)) / np.max(np.abs(B1)) <= TOL["casadi_jacobian_rel"]


def test_the_casadi_rebuild_gives_the_second_derivatives_of_the_derivative_graph():
    import casadi as ca

    from mpc.prediction.contract import _probe_batch
    from mpc.prediction.symbolic import casadi_step

    model = OnnxModel(ROOT / "models" / "proposed.onnx")
    xs, us, ys = ca.MX.sym("x", 12), ca.MX.sym("u", 4), ca.MX.sym("y", 12)
    z = ca.vertcat(xs, us)
    hess = ca.Function("h", [xs, us, ys], [ca.hessian(ca.dot(ys, casadi_step(model.path)(xs, us)), z)[0]])
    x, u = _probe_batch(4, np.float64, seed=5)
    y = np.random.default_rng(5).standard_normal((4, 12))
    h = np.concatenate([np.full(12, 1e-5), [1e-6], np.full(3, 1e-8)])     # per variable: state, thrust, torques
    for k in range(len(x)):
        H = np.array(hess(x[k], u[k], y[k]))
        fd = np.zeros((16, 16))
        for j in range(16):
            e = np.zeros(16)
            e[j] = h[j]
            (_, Ap, Bp), (_, Am, Bm) = (model.linearize(x[k] + s * e[:12], u[k] + s * e[12:]) for s in (1, -1))
            fd[j] = y[k] @ (np.concatenate([Ap[0], Bp[0]], axis=1) - np.concatenate([Am[0], Bm[0]], axis=1)) / (2 * h[j])
        fd = (fd + fd.T) / 2
        assert np.linalg.norm(H - fd) / np.linalg.norm(H) <= TOL["casadi_hessian_rel"], k


@pytest.mark.parametrize("name,reason", [("fourier", "Concat with axis=2 not supported"),
                                         ("modular", "Unsupported operation 'GatherND'")])
def test_a_graph_casadi_cannot_rebuild_is_refused_with_its_reason(name, reason):
    from mpc.prediction.symbolic import casadi_step

    with pytest.raises(ModelContractError, match=f"cannot rebuild this graph as an expression \\({reason}"):
        casadi_step(ROOT / "models" / f"{name}.onnx")
