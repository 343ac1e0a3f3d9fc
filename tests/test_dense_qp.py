"""The condensed QP (DAQP) against the sparse one (OSQP, tight tolerances) and against its own KKT conditions."""

import numpy as np
import osqp
import pytest
import scipy.sparse as sp

pytest.importorskip("daqp")

from mpc.controllers.dense_qp import (LTVQP, condense, condense_matrices, kkt_residuals, prepare_ltv_qp,  # noqa: E402
                                     solve_ltv_qp, solve_prepared)
import mpc.controllers.dense_qp as dq  # noqa: E402
from mpc.errors import ConfigurationError  # noqa: E402

#: Tolerances: KKT residuals of the dense solution (it is exact up to rounding); agreement with OSQP solved to
#: 1e-10 and polished, in states and inputs, and in the multipliers (which OSQP gets less accurately).
TOL = {"kkt": 1e-8, "primal": 1e-6, "dual": 1e-5, "controller_inputs": 1e-5,
       "hessian_rel": 1e-12,     # the backward recursion's H against G' W G + R formed in full (rounding)
       # The controllers' own dense QP where its constraints bind: a rotor's load n^2 / n_max^2 and the attitude
       # may pass their bounds by rounding only (measured 4e-16); a constraint within `active` of its bound
       # counts as active; the dense plan against OSQP's polished one of the same controller QP, in inputs
       # (N, N m) and states (measured 1.1e-9 and 6.4e-8).
       "bound": 1e-9, "active": 1e-7, "plan_inputs": 1e-6, "plan_states": 1e-6,
       # the QP prepared for every initial state, then given one, against the QP condensed with it (rounding: the
       # initial state enters through Phi instead of the forward recursion)
       "prepared": 1e-10,
       # the compiled condensing against numpy's, relative to each array's largest entry (the same sums in another
       # order)
       "backends_rel": 1e-12}


def random_qp(seed: int, N: int = 30, nx: int = 12, nu: int = 4, tight: bool = True) -> LTVQP:
    rng = np.random.default_rng(seed)
    A = np.eye(nx) + 0.02 * rng.standard_normal((N, nx, nx))
    B = 0.1 * rng.standard_normal((N, nx, nu))
    c = 0.01 * rng.standard_normal((N, nx))
    Q = np.diag(rng.uniform(0.5, 2.0, nx))
    L = np.abs(rng.standard_normal((nu, nu))) + np.eye(nu)
    S = np.zeros((2, nx))
    S[0, 3] = S[1, 4] = 1.0
    lim = 0.2 if tight else 10.0
    return LTVQP(A=A, B=B, c=c, x0=0.05 * rng.standard_normal(nx), Q=Q, P=5.0 * Q,
                 R=np.diag(rng.uniform(0.1, 1.0, nu)), ref=rng.standard_normal((N + 1, nx)),
                 u_ref=rng.standard_normal((N, nu)), L=L, lo_u=np.full(nu, -0.5 if tight else -50.0),
                 hi_u=np.full(nu, 0.5 if tight else 50.0), S=S, lo_s=np.full(2, -lim), hi_s=np.full(2, lim))


def osqp_solution(qp: LTVQP):
    """The sparse QP (states and inputs) by OSQP to 1e-10: ``(x (N+1, nx), u (N, nu), y)``, y in row order
    initial, dynamics, input constraints, state constraints."""
    N, nx, nu = qp.B.shape
    nX = (N + 1) * nx
    H = sp.block_diag([sp.csc_matrix(qp.Q)] * N + [sp.csc_matrix(qp.P)] + [sp.csc_matrix(qp.R)] * N, format="csc")
    q = np.concatenate([-(qp.ref[:N] @ qp.Q).ravel(), -(qp.P @ qp.ref[N]), -(qp.u_ref @ qp.R).ravel()])
    rows = [sp.hstack([sp.eye(nx), sp.csc_matrix((nx, nX - nx + N * nu))])]
    for k in range(N):
        r = sp.lil_matrix((nx, nX + N * nu))
        r[:, k * nx:(k + 1) * nx] = qp.A[k]
        r[:, (k + 1) * nx:(k + 2) * nx] = -np.eye(nx)
        r[:, nX + k * nu:nX + (k + 1) * nu] = qp.B[k]
        rows.append(r)
    rows.append(sp.hstack([sp.csc_matrix((N * qp.L.shape[0], nX)), sp.kron(sp.eye(N), qp.L)]))
    rows.append(sp.hstack([sp.csc_matrix((N * qp.S.shape[0], nx)), sp.kron(sp.eye(N), qp.S),
                           sp.csc_matrix((N * qp.S.shape[0], N * nu))]))
    Aq = sp.vstack(rows, format="csc")
    lo = np.concatenate([qp.x0, -qp.c.ravel(), np.tile(qp.lo_u, N), np.tile(qp.lo_s, N)])
    hi = np.concatenate([qp.x0, -qp.c.ravel(), np.tile(qp.hi_u, N), np.tile(qp.hi_s, N)])
    s = osqp.OSQP()
    s.setup(sp.triu(H, format="csc"), q, Aq, lo, hi, verbose=False, eps_abs=1e-10, eps_rel=1e-10, max_iter=200000,
            polishing=True)
    res = s.solve(raise_error=False)
    return res.x[:nX].reshape(N + 1, nx), res.x[nX:].reshape(N, nu), res.y


@pytest.mark.parametrize("seed,tight", [(0, True), (1, True), (2, False)])
def test_the_dense_solution_is_the_sparse_qps_and_meets_its_kkt_conditions(seed, tight):
    qp = random_qp(seed, tight=tight)
    sol = solve_ltv_qp(qp)
    assert sol.solved
    res = kkt_residuals(qp, sol)
    assert max(res.values()) <= TOL["kkt"], res
    assert sol.is_optimal(qp, TOL["kkt"])
    x, u, y = osqp_solution(qp)
    N, nx, nu = qp.B.shape
    np.testing.assert_allclose(sol.u, u, atol=TOL["primal"])
    np.testing.assert_allclose(sol.x, x, atol=TOL["primal"])
    m = qp.L.shape[0]
    y_init, y_dyn = y[:nx], y[nx:nx + N * nx].reshape(N, nx)
    y_u = y[nx + N * nx:nx + N * nx + N * m].reshape(N, m)
    y_s = y[nx + N * nx + N * m:].reshape(N, -1)
    # OSQP writes the dynamics row as A_k x_k - x_{k+1} + B_k u_k = -c_k, as the dense solution does
    for mine, its in ((sol.y_dyn, y_dyn), (sol.y_init, y_init), (sol.y_u, y_u), (sol.y_s, y_s)):
        np.testing.assert_allclose(mine, its, atol=TOL["dual"])
    if tight:                                   # the test means something: constraints bind
        assert np.sum(np.abs(sol.y_u) > 1e-6) + np.sum(np.abs(sol.y_s) > 1e-6) >= 5


@pytest.mark.parametrize("seed,tight", [(0, True), (5, True), (2, False)])
def test_a_qp_prepared_for_any_initial_state_solves_as_the_one_condensed_with_it(seed, tight):
    """The real-time iteration's split: condensed before the state is known, then given it. The same inputs and
    states as the QP condensed with the state, for two states (the preparation does not depend on either)."""
    qp = random_qp(seed, tight=tight)
    prep = prepare_ltv_qp(qp)
    for x0 in (qp.x0, qp.x0 + 0.03 * np.random.default_rng(seed).standard_normal(qp.x0.shape)):
        whole = solve_ltv_qp(LTVQP(**{**qp.__dict__, "x0": x0}))
        fb = solve_prepared(prep, x0)
        assert whole.solved and fb.solved
        np.testing.assert_allclose(fb.u, whole.u, rtol=0, atol=TOL["prepared"])
        np.testing.assert_allclose(prep.states(x0, fb.u.ravel()), whole.x, rtol=0, atol=TOL["prepared"])
        if tight:
            assert np.sum(np.abs(fb.lam) > 1e-6) >= 5      # constraints bind: the bounds' shift by x0 matters


def test_a_prepared_qp_takes_a_moved_offset_and_a_new_reference_at_its_feedback():
    """The feedback of offset-free control: every c_k moved by delta, and another reference and feed-forward, as
    the QP condensed with them."""
    qp = random_qp(7)
    rng = np.random.default_rng(8)
    delta = 0.01 * rng.standard_normal(qp.x0.shape)
    ref, u_ref = qp.ref + 0.1 * rng.standard_normal(qp.ref.shape), qp.u_ref + 0.1
    whole = solve_ltv_qp(LTVQP(**{**qp.__dict__, "c": qp.c + delta, "ref": ref, "u_ref": u_ref}))
    prep = prepare_ltv_qp(qp)
    fb = solve_prepared(prep, qp.x0, delta=delta, ref=ref, u_ref=u_ref)
    assert whole.solved and fb.solved
    np.testing.assert_allclose(fb.u, whole.u, rtol=0, atol=TOL["prepared"])
    np.testing.assert_allclose(prep.states(qp.x0, fb.u.ravel(), delta), whole.x, rtol=0, atol=TOL["prepared"])
    assert np.max(np.abs(fb.u - solve_prepared(prep, qp.x0).u)) > 1e-3      # and they matter


def test_condensed_states_follow_the_dynamics():
    qp = random_qp(3)
    H, f, C, lo, hi, G, w = condense(qp)
    u = np.random.default_rng(4).standard_normal(H.shape[0])
    x = (G.reshape(G.shape[0] * G.shape[1], -1) @ u).reshape(G.shape[:2]) + w
    U = u.reshape(qp.u_ref.shape)
    step = np.einsum("kij,kj->ki", qp.A, x[:-1]) + np.einsum("kij,kj->ki", qp.B, U) + qp.c
    np.testing.assert_allclose(x[1:], step, atol=1e-12)
    np.testing.assert_allclose(H, H.T, atol=0.0)
    assert np.min(np.linalg.eigvalsh(H)) > 0.0


def test_an_infeasible_qp_is_reported_not_raised():
    qp = random_qp(5)
    N, nx, nu = qp.B.shape
    # inputs pinned to 0 and the attitude held in a band the free motion leaves at once
    bad = LTVQP(**{**qp.__dict__, "L": np.eye(nu), "lo_u": np.zeros(nu), "hi_u": np.zeros(nu),
                   "x0": np.full(nx, 1.0), "lo_s": np.full(2, -1e-3), "hi_s": np.full(2, 1e-3)})
    sol = solve_ltv_qp(bad)
    assert not sol.solved
    assert not sol.is_optimal(bad)


def test_the_hessian_by_backward_recursion_is_g_w_g_plus_r():
    qp = random_qp(11)
    N, nx, nu = qp.B.shape
    m = condense_matrices(qp)
    Gf = m.G.reshape(-1, N * nu)
    W = np.kron(np.eye(N + 1), np.eye(nx))
    W[:N * nx, :N * nx] = np.kron(np.eye(N), qp.Q)
    W[N * nx:, N * nx:] = qp.P
    H = Gf.T @ W @ Gf + np.kron(np.eye(N), qp.R)
    assert np.max(np.abs(m.H - H)) <= TOL["hessian_rel"] * np.max(np.abs(H))


def test_a_qp_with_the_same_matrices_reuses_them_bit_for_bit():
    """Another c, x0, reference and bounds (a correction's QP, an iteration that keeps its Jacobians): solved with the
    first QP's condensed matrices it gives exactly what condensing it anew gives, and it condenses nothing again."""
    qp = random_qp(12)
    rng = np.random.default_rng(3)
    first = solve_ltv_qp(qp)
    other = LTVQP(**{**qp.__dict__, "c": qp.c + 0.01 * rng.standard_normal(qp.c.shape),
                     "x0": qp.x0 + 0.01, "ref": qp.ref + 0.1, "lo_s": qp.lo_s - 0.01})
    again, fresh = solve_ltv_qp(other, matrices=first.matrices), solve_ltv_qp(other)
    assert again.matrices is first.matrices
    for name in ("x", "u", "y_init", "y_dyn", "y_u", "y_s"):
        assert np.array_equal(getattr(again, name), getattr(fresh, name)), name
    assert again.is_optimal(other, TOL["kkt"])


def test_a_shape_mismatch_names_the_array():
    qp = random_qp(6)
    with pytest.raises(ConfigurationError, match=r"u_ref must have shape \(30, 4\)"):
        LTVQP(**{**qp.__dict__, "u_ref": qp.u_ref[:-1]})


def test_the_sqps_own_qp_solved_densely_gives_osqps_inputs(monkeypatch):
    """One QP of the SQP flying figure8-fast with Baseline, captured in flight, against the SQP's own OSQP answer."""
    from pathlib import Path

    import mpc.controllers.ltv as ltv
    from scenarios.closed_loop.runner import RunSpec, fly

    captured = []
    real = ltv.LTVMPC._solve_qp

    def capture(self, x, ref, u_ref, xb, ub, fx, A, B, warm=None, split=None, hess=None, same_matrices=False):
        res = real(self, x, ref, u_ref, xb, ub, fx, A, B, warm=warm, split=split, hess=hess,
                   same_matrices=same_matrices)
        if len(captured) < 3 and hess is None and res.x is not None:
            c = fx - np.einsum("kij,kj->ki", A, xb) - np.einsum("kij,kj->ki", B, ub)
            S = self._attitude_rows()
            lim = self.s.attitude_limit_rad
            qp = LTVQP(A=A.copy(), B=B.copy(), c=c, x0=np.array(x, dtype=float), Q=self.Q, P=self.P, R=self.R,
                       ref=ref.copy(), u_ref=u_ref.copy(), L=self._load, lo_u=np.zeros(4), hi_u=np.ones(4),
                       S=S, lo_s=np.full(2, -lim), hi_s=np.full(2, lim))
            captured.append((qp, self._unpack(res.x)[1].copy(), self.s.constraints))
        return res

    monkeypatch.setattr(ltv.LTVMPC, "_solve_qp", capture)
    root = Path(__file__).resolve().parents[1]
    spec = RunSpec("figure8-fast", "sqp", str(root / "models" / "baseline.onnx"))
    monkeypatch.setattr("scenarios.closed_loop.library.Scenario.steps", property(lambda self: 5), raising=False)
    fly(spec)
    assert captured and all(constrained for _, _, constrained in captured)
    for qp, u_osqp, _ in captured:
        sol = solve_ltv_qp(qp)
        assert sol.is_optimal(qp, 1e-7)
        np.testing.assert_allclose(sol.u, u_osqp, atol=TOL["controller_inputs"])


# ------------------------------------------------------------------ the controllers on the dense path
#: The issue's same-answers tolerances: the oracle's RMSE within 0.05 mm, a PINN's within 2 %.
ANSWERS = {"oracle_m": 5e-5, "pinn_relative": 0.02}


@pytest.mark.parametrize("controller,model", [("sqp", "oracle"), ("sqp", "baseline"), ("ltv", "baseline")])
def test_a_flight_on_the_dense_qp_path_gives_the_osqp_paths_answer(controller, model, monkeypatch):
    from pathlib import Path

    import scenarios.closed_loop.runner as runner
    from mpc.controllers.ltv import LTVMPC, LTVSettings
    from mpc.prediction.spec import VehicleSpec
    from scenarios.closed_loop.runner import RunSpec, fly

    root = Path(__file__).resolve().parents[1]
    spec = RunSpec("figure8-fast", controller, model if model == "oracle" else str(root / "models" / f"{model}.onnx"))
    dense_qps = []
    real = LTVMPC._solve_dense

    def counted(self, *args):
        dense_qps.append(1)
        return real(self, *args)

    monkeypatch.setattr(LTVMPC, "_solve_dense", counted)
    if controller == "sqp":
        a, _ = fly(spec, sqp={"qp": "osqp"})
        assert not dense_qps
        b, _ = fly(spec, sqp={"qp": "daqp"})
    else:
        a, _ = fly(spec)

        def dense_ltv(kind, model, reference, horizon, timing, vehicle, *rest, **kw):
            return LTVMPC(model, reference, LTVSettings(horizon=horizon, qp="daqp"),
                          spec=VehicleSpec.from_model(model, vehicle))

        monkeypatch.setattr(runner, "make_controller", dense_ltv)
        b, _ = fly(spec)
    assert len(dense_qps) >= spec_steps(spec)          # every period's QP went the dense way
    assert not a["crashed"] and not b["crashed"] and b["solver_failures"] == 0
    if model == "oracle":
        assert abs(a["rmse_position_m"] - b["rmse_position_m"]) <= ANSWERS["oracle_m"]
    else:
        assert abs(b["rmse_position_m"] / a["rmse_position_m"] - 1.0) <= ANSWERS["pinn_relative"]


def test_a_dense_flight_reusing_condensed_matrices_equals_one_that_condenses_every_qp(monkeypatch):
    """The SQP with Proposed (second iterations and corrections: QPs with the same matrices) flies 40 periods of
    figure8-fast the same, bit for bit, whether those QPs reuse the condensed matrices or condense them anew."""
    from pathlib import Path

    from mpc.controllers.ltv import LTVMPC
    from scenarios.closed_loop.runner import RunSpec, fly

    root = Path(__file__).resolve().parents[1]
    spec = RunSpec("figure8-fast", "sqp", str(root / "models" / "proposed.onnx"))
    monkeypatch.setattr("scenarios.closed_loop.library.Scenario.steps", property(lambda self: 40), raising=False)
    real = LTVMPC._solve_dense
    reused = []

    def count(self, x, ref, u_ref, c, A, B, split, t0, same_matrices=False):
        reused.append(same_matrices)
        return real(self, x, ref, u_ref, c, A, B, split, t0, same_matrices)

    monkeypatch.setattr(LTVMPC, "_solve_dense", count)
    a, ta = fly(spec, sqp={"qp": "daqp"})
    assert any(reused)

    def never(self, x, ref, u_ref, c, A, B, split, t0, same_matrices=False):
        return real(self, x, ref, u_ref, c, A, B, split, t0, False)

    monkeypatch.setattr(LTVMPC, "_solve_dense", never)
    b, tb = fly(spec, sqp={"qp": "daqp"})
    assert a["rmse_position_m"] == b["rmse_position_m"]
    for key in ("x", "u"):
        assert np.array_equal(ta[key], tb[key]), key


def spec_steps(spec) -> int:
    from scenarios.closed_loop.library import get_scenario

    return get_scenario(spec.scenario).steps


def test_a_bad_qp_solver_is_refused_by_name():
    from mpc.controllers.ltv import LTVSettings

    with pytest.raises(ConfigurationError, match="qp must be one of osqp, daqp; found 'gurobi'"):
        LTVSettings(qp="gurobi")


# ------------------------------------------------------------------ the controllers' own constraint rows, binding
#: Attitude limit of the binding case, rad: tight enough that the plan from its start reaches it.
BINDING_ATTITUDE_RAD = 0.3
#: Start of the binding case: off the hover point by 3 m in x and 0.5 m in z (below it), moving at 2 m/s in x and
#: 1 m/s upward (NED). The plan back needs full thrust on some rotors, none on others, and the attitude limit.
BINDING_OFFSET = np.array([3.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0, 0.0, -1.0])


def _binding_controller(kind: str, qp: str, **qp_settings):
    from mpc.controllers.ltv import LTVMPC, LTVSettings
    from mpc.prediction.models import AnalyticModel
    from mpc.controllers.sqp import SQPMPC, SQPSettings

    common = dict(qp=qp, attitude_limit_rad=BINDING_ATTITUDE_RAD, **qp_settings)
    if kind == "ltv":
        return LTVMPC(AnalyticModel(), None, LTVSettings(**common))
    # The SQP's first QP alone (one iteration, full step), from its rollout, so that both solvers answer one QP.
    return SQPMPC(AnalyticModel(), None, SQPSettings(max_sqp_iter=1, cold_start_max_iter=1, line_search=False,
                                                     time_budget_s=None, cold_start_budget_s=None, **common))


@pytest.mark.parametrize("kind", ["ltv", "sqp"])
def test_the_controllers_dense_constraints_hold_where_they_bind_and_match_osqp(kind, monkeypatch):
    """The LTV-MPC's and the SQP's own dense QP (the rotor-load and attitude rows they build for DAQP) on a plan
    where the rotor limits (both ends) and the attitude limit are active: the dense plan keeps every rotor's
    n^2 within [0, n_max^2] and the attitude within its limit, touches each bound, and is the plan OSQP gives
    for the same controller's sparse QP (solved to 1e-6 and polished)."""
    import mpc.controllers.ltv as ltv
    from sim.vehicles.rotors import allocate

    polished = []
    real = ltv.LTVMPC._solve_qp

    def spy(self, *args, **kwargs):
        res = real(self, *args, **kwargs)
        if self.s.qp == "osqp":
            polished.append(res.info.status_polish)
        return res

    monkeypatch.setattr(ltv.LTVMPC, "_solve_qp", spy)
    dense = _binding_controller(kind, "daqp")
    x0 = dense._horizon_reference(0.0)[0][0] + BINDING_OFFSET
    _, info = dense(x0, 0.0)
    assert info.status == "optimal" and dense._condensed is not None       # solved, and by the dense path
    U, X = dense._plan_u, dense._plan_x           # the QP's plan (the input sent out is projected onto the rotors)
    load = allocate(U, dense.spec) / dense.spec.n_max_sq     # n^2 / n_max^2 from the mixer, not the QP's rows
    attitude = X[1:, 3:5]
    assert load.min() >= -TOL["bound"] and load.max() <= 1.0 + TOL["bound"], (load.min(), load.max())
    assert np.abs(attitude).max() <= BINDING_ATTITUDE_RAD + TOL["bound"], np.abs(attitude).max()
    assert np.any(load <= TOL["active"]) and np.any(load >= 1.0 - TOL["active"])     # both rotor limits bind
    assert np.any(np.abs(attitude) >= BINDING_ATTITUDE_RAD - TOL["active"])          # and the attitude limit
    sparse = _binding_controller(kind, "osqp", eps_abs=1e-6, eps_rel=1e-6, polish=True, max_iter=100000)
    _, info = sparse(x0, 0.0)
    assert info.status == "optimal" and polished and polished[-1] == 1, polished     # OSQP's answer is polished
    np.testing.assert_allclose(U, sparse._plan_u, rtol=0.0, atol=TOL["plan_inputs"])
    np.testing.assert_allclose(X, sparse._plan_x, rtol=0.0, atol=TOL["plan_states"])


def _close(a, b, what):
    scale = max(float(np.max(np.abs(b))), 1e-300)
    assert np.max(np.abs(a - b)) <= TOL["backends_rel"] * scale, what


@pytest.mark.parametrize("N,nx,nu,weights,state_rows", [(30, 12, 4, "diagonal", 2), (30, 16, 4, "full", 0),
                                                        (1, 12, 4, "diagonal", 0), (7, 3, 2, "full", 1)])
def test_the_compiled_condensing_is_numpys_to_rounding(N, nx, nu, weights, state_rows):
    """Both backends of the condensing on the same QP: G, W G, H, the constraint rows and the free response
    (Phi, v, and Psi made at once or when a feedback first needs it), for the SQP's size, the 16-state models', one
    stage and a small odd one, diagonal and full weights."""
    rng = np.random.default_rng(N * 100 + nx)
    Q = np.diag(rng.uniform(0.5, 2.0, nx))
    if weights == "full":
        M = rng.standard_normal((nx, nx))
        Q = Q + 0.1 * M @ M.T
    S = np.zeros((state_rows, nx))
    S[np.arange(state_rows), np.arange(state_rows)] = 1.0
    qp = LTVQP(A=np.eye(nx) + 0.05 * rng.standard_normal((N, nx, nx)), B=0.1 * rng.standard_normal((N, nx, nu)),
               c=0.01 * rng.standard_normal((N, nx)), x0=np.zeros(nx), Q=Q, P=3.0 * Q,
               R=np.diag(rng.uniform(0.1, 1.0, nu)), ref=np.zeros((N + 1, nx)), u_ref=np.zeros((N, nu)),
               L=np.eye(nu), lo_u=-np.ones(nu), hi_u=np.ones(nu), S=S, lo_s=-np.ones(state_rows),
               hi_s=np.ones(state_rows))
    a, b = condense_matrices(qp, backend="c"), condense_matrices(qp, backend="numpy")
    for name in ("G", "WG", "H", "C"):
        _close(getattr(a, name), getattr(b, name), name)
    assert np.array_equal(a.H, a.H.T)
    for offsets in (True, False):
        pa, pb = prepare_ltv_qp(qp, offsets=offsets, backend="c"), prepare_ltv_qp(qp, offsets=offsets, backend="numpy")
        assert (pa.Psi is None) == (pb.Psi is None) == (not offsets)
        for name in ("G", "WG", "H", "C", "Phi", "v"):
            _close(getattr(pa, name), getattr(pb, name), name)
        x0, delta = rng.standard_normal(nx), 0.01 * rng.standard_normal(nx)
        _close(pa.free(x0, delta), pb.free(x0, delta), "free response with an offset")   # Psi made here if not yet
        _close(pa.Psi, pb.Psi, "Psi")
    # Psi made on demand is the one made at once
    eager, lazy = prepare_ltv_qp(qp, offsets=True, backend="numpy"), prepare_ltv_qp(qp, offsets=False, backend="numpy")
    lazy.free(np.zeros(nx), np.ones(nx))
    _close(lazy.Psi, eager.Psi, "Psi on demand")
    _close(eager.Psi[N], np.sum([np.linalg.multi_dot([np.eye(nx), *qp.A[k + 1:][::-1]]) if k + 1 < N else np.eye(nx)
                                 for k in range(N)], axis=0), "Psi_N = sum of the transition products")


def test_the_compiled_condensing_is_the_default_where_a_compiler_works():
    import shutil

    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler here")
    assert dq._kernel(None) is not None


def test_an_unknown_condensing_backend_is_refused_by_name():
    with pytest.raises(ConfigurationError, match="backend must be one of c, numpy or None; found 'fortran'"):
        condense_matrices(random_qp(1), backend="fortran")
