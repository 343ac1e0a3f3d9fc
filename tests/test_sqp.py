"""Real-time SQP NMPC: convergence to IPOPT's optimum, the LTV-MPC as its one-iteration case, line search,
cold start and failure handling."""

import functools
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from mpc.errors import ConfigurationError
from mpc.controllers.lqr import hover_point
from mpc.controllers.ltv import LTVMPC
from mpc.prediction.models import AnalyticModel, OnnxModel
from mpc.controllers.nmpc import NMPC, NMPCSettings
from mpc.controllers.sqp import SQPMPC, SQPSettings
from mpc.references.trajectory import Figure8
from sim import QuadParams, Simulator
from sim.params import NU, NX

ROOT = Path(__file__).resolve().parents[1]
PROPOSED = str(ROOT / "models" / "proposed.onnx")
FIG8_FAST = Figure8(0.75, 3.0, 1.0)
TOL = {
    "objective_rel": 1e-4,      # |J_sqp - J_ipopt| / J_ipopt at the converged solutions
    "defect_abs": 1e-7,         # largest dynamics defect |f(X_k, U_k) - X_{k+1}| of the SQP's plan
    "merit_rel": 1e-12,         # an accepted step never raises the merit by more than rounding
    "proposed_min_within": 0.76,  # share of states within objective_rel with the Proposed PINN (measured 0.78-0.88)
    "exact_hessian_rel": 1e-6,  # central-difference Hessian vs CasADi's symbolic one (measured 7e-9)
    "fixed_point_rel": 1e-9,    # converged objective with Jacobians every iteration vs every other (measured 1e-15)
    "stationarity": 1e-6,       # Lagrangian gradient / cost gradient at a plan called converged (measured 1.3e-9)
    "curvature_min": 1e-2,      # reduced Hessian's smallest eigenvalue / the cost's own there (measured 0.27)
    "at_bound": 1e-9,           # an inequality this close to its bound counts as active
}
#: Perturbed reference states (for the line-search check): the reference plus seeded errors of these sizes.
ERROR_SCALE = np.array([0.02, 0.02, 0.02, 0.03, 0.03, 0.03, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1])
#: No budget, tight QPs (polished), a small step tolerance; the exact Hessian and float64 Jacobians (float32 ones
#: leave steps of about 1e-7 that never pass the step tolerance).
CONVERGED = SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=400, step_tol=1e-7, defect_tol=0.0,
                        eps_abs=1e-10, eps_rel=1e-10, max_iter=100000, polish=True, hessian="exact",
                        jacobians="float64")
#: States along figure8-fast: every EVERY-th period of the SQP's own two-lap flight (600 periods). Every 24th (25
#: states) keeps the slow run's time; ``PINNMPC_SQP_EVERY=12`` compares the 50 states the documentation's figures
#: were measured on (twice as long).
_EVERY = os.environ.get("PINNMPC_SQP_EVERY", "24")
if not _EVERY.isdigit() or not 1 <= int(_EVERY) <= 600:
    raise ValueError(f"PINNMPC_SQP_EVERY must be a whole number of periods from 1 to 600; found {_EVERY!r}")
EVERY = int(_EVERY)
N_STATES = 600 // EVERY


def sampled_states(n, seed):
    rng = np.random.default_rng(seed)
    times = np.round(np.linspace(0.0, 3.0, n, endpoint=False), 2)
    return [(t, FIG8_FAST(np.array([t]))[0] + ERROR_SCALE * rng.standard_normal(12)) for t in times]


def flown_states(model):
    """``(t, x, warm)`` per sampled period; ``warm`` is the first iterate the flying controller itself started that
    period from (its shifted plan, ``(X (N + 1, 12), U (N, 4))``), ``None`` at take-off."""
    sqp = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    sim, x, out = Simulator(QuadParams()), FIG8_FAST(np.array([0.0]))[0], []
    for k in range(N_STATES * EVERY):
        t = 0.01 * k
        if k % EVERY == 0:
            warm = None if sqp._plan_x is None else sqp._initial_iterate(x, *sqp._horizon_reference(t))
            out.append((round(t, 2), x.copy(), warm))
        u, _ = sqp(x, t)
        x = sim.step(x, u)
    return out


def optimality(sqp, x, t, X, U):
    """First- and second-order optimality of the plan ``(X (N + 1, 12), U (N, 4))`` for the period at ``(x, t)``.

    Multipliers by least squares for the initial state, the dynamics and every inequality at its bound. Returns
    ``(stationarity, curvature, sign)``: the Lagrangian's gradient relative to the cost's (zero at a KKT point); the
    smallest eigenvalue of the Lagrangian's Hessian (the model's curvature from ``sqp._lagrangian_curvature``) on the
    null space of those constraints, relative to the cost Hessian's own smallest eigenvalue there (positive: a strict
    local minimum); the largest multiplier of an inequality with the wrong sign (zero when none is at its bound).
    """
    from scipy.linalg import block_diag, null_space

    N = sqp.N
    ref, u_ref = sqp._horizon_reference(t)
    fx, A, B = sqp.model.linearize(X[:N], U)
    M = sqp._A0.copy()
    M.data = sqp._constraint_values(A, B)
    M = M.toarray()
    z = np.concatenate([X.ravel(), U.ravel()])
    Mz, n_eq = M @ z, sqp._n_eq
    inequalities = np.arange(n_eq, len(Mz))
    at_upper = inequalities[(sqp._u0 - Mz)[n_eq:] <= TOL["at_bound"]]
    at_lower = inequalities[(Mz - sqp._l0)[n_eq:] <= TOL["at_bound"]]
    rows = np.r_[np.arange(n_eq), at_upper, at_lower]
    C = M[rows]
    P = block_diag(*[sqp.Q] * N, sqp.P, *[sqp.R] * N)             # the QP's scaling: the cost is z' P z / 2 + q' z
    g = P @ z + sqp._linear_cost(ref, u_ref)
    lam = np.linalg.lstsq(C.T, -g, rcond=None)[0]
    stationarity = np.max(np.abs(g + C.T @ lam)) / np.max(np.abs(g))
    n_up = len(at_upper)
    sign = max([0.0, *-lam[n_eq:n_eq + n_up], *lam[n_eq + n_up:]]) / np.max(np.abs(g))
    H = P.copy()
    curvature = sqp._lagrangian_curvature(X[:N], U, lam[NX:n_eq].reshape(N, NX))
    for k in range(N):
        idx = np.r_[sqp._xi(k) + np.arange(NX), sqp._ui(k) + np.arange(NU)]
        H[np.ix_(idx, idx)] += curvature[k]
    Z = null_space(C)
    smallest = np.linalg.eigvalsh(Z.T @ H @ Z)[0] / np.linalg.eigvalsh(Z.T @ P @ Z)[0]
    return stationarity, smallest, sign


def objective_gaps(model, hessian="limited-memory", guess="cold"):
    """The SQP against IPOPT per state, both started from the same guess: ``"cold"``, the cold-start rollout, or
    ``"warm"``, the flying controller's own first iterate of that period (the rollout at take-off).

    Returns a dict of arrays over the states: ``gap``, the relative objective gap SQP - IPOPT (inf where the SQP's
    plan still violates the model); ``sqp``, the SQP plan's :func:`optimality` (n, 3); ``ipopt``, the same of IPOPT's
    plan where the two differ (NaN elsewhere).
    """
    return gaps_by_hessian(model, (hessian,), guess)[hessian]


def gaps_by_hessian(model, hessians, guess="cold"):
    """:func:`objective_gaps` against IPOPT with each of ``hessians``, the SQP solved once: ``{hessian: {"gap",
    "sqp", "ipopt"}, "cost": {hessian: IPOPT's objective per state}}``."""
    def ipopt_with(h):
        return NMPC(model, FIG8_FAST, NMPCSettings(tol=1e-10, max_iter=3000, time_limit_s=60.0, hessian=h))

    sqp = SQPMPC(model, FIG8_FAST, CONVERGED)
    ipopts = {h: ipopt_with(h) for h in hessians}
    N = sqp.N
    out = {h: {"gap": [], "sqp": [], "ipopt": []} for h in hessians}
    cost = {h: [] for h in hessians}
    for t, x, warm in flown_states(model):
        ref, u_ref = sqp._horizon_reference(t)
        X0, U0 = warm if guess == "warm" and warm is not None else sqp.rollout(x, ref, u_ref)
        Xs, Us, _ = sqp.solve_from(x, t, X0, U0)
        defect = np.max(np.abs(model.step(Xs[:N], Us) - Xs[1:]))
        js, mine = sqp.cost(Xs, Us, ref, u_ref), optimality(sqp, x, t, Xs, Us)
        for h, ipopt in ipopts.items():
            accepted = ("Solve_Succeeded",) if h == "exact" else ("Solve_Succeeded", "Solved_To_Acceptable_Level")
            Xn, Un, status = ipopt.solve_from(x, t, X0, U0)
            assert status in accepted, f"t={t}: IPOPT ({h} Hessian) {status}"
            jn = sqp.cost(Xn, Un, ref, u_ref)
            cost[h].append(jn)
            # A plan that still violates the dynamics has not reached anything: count it as a miss.
            out[h]["gap"].append((js - jn) / jn if defect <= TOL["defect_abs"] else np.inf)
            out[h]["sqp"].append(mine)
            differ = not abs(out[h]["gap"][-1]) <= TOL["objective_rel"]
            out[h]["ipopt"].append(optimality(sqp, x, t, Xn, Un) if differ else (np.nan,) * 3)
    result = {h: {k: np.array(v) for k, v in out[h].items()} for h in hessians}
    result["cost"] = {h: np.array(v) for h, v in cost.items()}
    return result


@functools.lru_cache(maxsize=1)
def proposed_from_the_cold_guess():
    """The Proposed PINN's comparison from the cold guess against both IPOPTs (limited-memory and exact Hessian),
    computed once for the two tests that read it (the SQP's and the limited-memory IPOPT's solves were made twice)."""
    return gaps_by_hessian(OnnxModel(PROPOSED), ("exact", "limited-memory"))


def assert_strict_local_minima(plans, which):
    """Every plan (rows of :func:`optimality`, NaN rows skipped) is a KKT point and a strict local minimum."""
    plans = plans[~np.isnan(plans[:, 0])]
    assert np.all(plans[:, 0] <= TOL["stationarity"]), f"{which}: stationarity {np.max(plans[:, 0]):.1e}"
    assert np.all(plans[:, 2] <= TOL["stationarity"]), f"{which}: multiplier of wrong sign {np.max(plans[:, 2]):.1e}"
    assert np.all(plans[:, 1] >= TOL["curvature_min"]), f"{which}: reduced Hessian {np.min(plans[:, 1]):.2e}"


@pytest.mark.slow
def test_sqp_reaches_ipopts_optimal_objective_with_the_oracle():
    found = objective_gaps(AnalyticModel())
    gaps = np.abs(found["gap"])
    assert np.max(gaps) <= TOL["objective_rel"], f"worst relative objective gap {np.max(gaps):.2e}"
    assert_strict_local_minima(found["sqp"], "SQP")


def test_the_optimality_check_tells_a_converged_plan_from_one_two_iterations_short():
    model = AnalyticModel()
    t, x = sampled_states(1, 4)[0]
    sqp = SQPMPC(model, FIG8_FAST, CONVERGED)
    short = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=2,
                                                 hessian="exact", jacobians="float64"))
    ref, u_ref = sqp._horizon_reference(t)
    X0, U0 = sqp.rollout(x, ref, u_ref)
    for solver, converged in ((sqp, True), (short, False)):
        X, U, _ = solver.solve_from(x, t, X0, U0)
        stationarity = optimality(sqp, x, t, X, U)[0]
        assert (stationarity <= TOL["stationarity"]) == converged, (converged, stationarity)


def differing(found):
    """Counts and sizes of the states where the SQP and IPOPT end at different objectives, for a message."""
    signed = found["gap"]
    lower, higher = int(np.sum(signed < -TOL["objective_rel"])), int(np.sum(signed > TOL["objective_rel"]))
    return (f"{lower} lower and {higher} higher (worst gap {np.max(np.abs(signed)):.1e}); where they differ, both "
            f"plans are strict local minima (reduced Hessian's smallest eigenvalue at least "
            f"{np.nanmin(np.r_[found['sqp'][:, 1], found['ipopt'][:, 1]]):.2f} of the cost's own)")


def checked_within(found):
    """The checks every Proposed comparison makes; returns how many states end within 1e-4 of IPOPT's objective.

    Every state ends with a plan that satisfies the model (with the exact Hessian; the Gauss-Newton one left 7 of 50
    infeasible after 400 iterations). Every plan the SQP calls converged is a strict local minimum, and where the two
    differ IPOPT's plan is one too: two different local minima of a non-convex problem, not a solver stopped early or
    parked on a saddle. And the regression guard on what is reached (measured 39 to 44 of 50).
    """
    gaps = np.abs(found["gap"])
    assert np.all(np.isfinite(gaps)), f"{int(np.sum(~np.isfinite(gaps)))} states end with an infeasible plan"
    assert_strict_local_minima(found["sqp"], "SQP")
    assert_strict_local_minima(found["ipopt"], "IPOPT")
    within = int(np.sum(gaps <= TOL["objective_rel"]))
    assert within >= math.ceil(TOL["proposed_min_within"] * N_STATES), (within, N_STATES)
    return within


@pytest.mark.slow
def test_sqp_reaches_ipopts_optimal_objective_with_the_proposed_pinn():
    """About 5 minutes (25 states, each solved by the SQP and by IPOPT with both Hessians): in the slow run."""
    found = proposed_from_the_cold_guess()["limited-memory"]
    within = checked_within(found)
    if within < N_STATES:
        # The target is every state. The network's problem has more than one local minimum, and from the same guess
        # the SQP and IPOPT (whose limited-memory Hessian stops these states at its "acceptable" level) end at
        # different ones: measured 3 states with a lower objective than IPOPT's, 3 with a higher one.
        pytest.xfail(f"{N_STATES - within} of {N_STATES} states not within 1e-4 of IPOPT's objective: "
                     + differing(found))


@pytest.mark.slow
def test_sqp_against_ipopt_from_the_controllers_own_warm_start_on_the_proposed_pinn():
    """The same comparison from the guess the flying controller started each period from (its shifted plan), not
    the cold-start rollout: is the miss an artefact of a guess far from the plan the controller carries?

    About 2.5 minutes. Measured (50 states): no; 43 of 50 within 1e-4 (4 lower, 3 higher, worst 2.9e-2), against
    44 of 50 from the cold guess, and the differing states are mostly other states than the cold guess's.
    """
    found = objective_gaps(OnnxModel(PROPOSED), guess="warm")
    within = checked_within(found)
    if within < N_STATES:
        pytest.xfail(f"from the controller's own warm start, {N_STATES - within} of {N_STATES} states not within "
                     f"1e-4 of IPOPT's objective: " + differing(found))


@pytest.mark.slow
def test_sqp_against_ipopt_with_the_exact_hessian_on_the_proposed_pinn():
    """The same comparison with IPOPT converged properly: exact Hessian (the PINN rebuilt in CasADi), tol 1e-10.

    Shares its solves with the limited-memory check above. Measured (50 states): IPOPT converges on all 50; the SQP
    ends at IPOPT's point on 39 of them (objectives equal to about 1e-14) and at other local minima on 11 (6 lower,
    5 higher, worst 1.7e-2). For scale, IPOPT with its limited-memory Hessian, from the same guess, ends at the
    exact-Hessian IPOPT's point on 42.
    """
    both = proposed_from_the_cold_guess()
    found = both["exact"]
    between = (both["cost"]["limited-memory"] - both["cost"]["exact"]) / both["cost"]["exact"]
    signed = found["gap"]
    within = checked_within(found)
    if within < N_STATES:
        ipopts = int(np.sum(np.abs(between) <= TOL["objective_rel"]))
        # Objectives relative to the exact-Hessian IPOPT's: which of the three solvers reaches the lowest per state.
        rel = np.stack([signed, between, np.zeros_like(signed)])
        at_lowest = np.sum((rel - rel.min(axis=0)) / (1 + rel.min(axis=0)) <= TOL["objective_rel"], axis=1)
        pytest.xfail(f"{N_STATES - within} of {N_STATES} states at other local minima than IPOPT's (exact Hessian, "
                     f"converged): {differing(found)}; IPOPT with its limited-memory Hessian is within 1e-4 of it "
                     f"on {ipopts} of {N_STATES}; the lowest of the three objectives is reached by the SQP on "
                     f"{at_lowest[0]}, the limited-memory IPOPT on {at_lowest[1]} and the exact-Hessian one on "
                     f"{at_lowest[2]}")


def test_the_exact_hessian_is_the_models_curvature_weighted_by_the_multipliers():
    import casadi as ca

    model = AnalyticModel()
    sqp = SQPMPC(model, FIG8_FAST, SQPSettings(hessian="exact"))
    N, rng = sqp.N, np.random.default_rng(0)
    t = 0.01 * np.arange(N)
    X = sqp.ff.states(t) + 0.02 * rng.standard_normal((N, 12))
    U = sqp.ff.inputs(t) * (1 + 0.05 * rng.standard_normal((N, 4)))
    y = rng.standard_normal((N, 12))
    H = sqp._lagrangian_curvature(X, U, y)
    xs, us, ys = ca.SX.sym("x", 12), ca.SX.sym("u", 4), ca.SX.sym("y", 12)
    hess = ca.Function("h", [xs, us, ys], [ca.hessian(ca.dot(ys, model.casadi_step(xs, us)), ca.vertcat(xs, us))[0]])
    exact = np.array([np.array(hess(X[k], U[k], y[k])) for k in range(N)])
    err = np.linalg.norm(H - exact, axis=(1, 2)) / np.linalg.norm(exact, axis=(1, 2))
    assert np.max(err) <= TOL["exact_hessian_rel"], np.max(err)


def test_the_ltv_mpc_is_the_one_iteration_full_step_case():
    model = OnnxModel(PROPOSED)
    one = SQPSettings(max_sqp_iter=1, line_search=False, time_budget_s=None, cold_start_budget_s=None,
                      cold_start_max_iter=1, cold_start="hold", tail="hold", jacobian_refresh="full")
    ltv, sqp = LTVMPC(model, FIG8_FAST), SQPMPC(model, FIG8_FAST, one)
    sim = Simulator(QuadParams())
    x = FIG8_FAST(np.array([0.0]))[0]
    for k in range(60):
        u1, _ = ltv(x, 0.01 * k)
        u2, info = sqp(x, 0.01 * k)
        assert np.array_equal(u1, u2), f"period {k}"
        assert info.iterations == 1
        x = sim.step(x, u1)


def test_a_shifted_plan_ends_on_the_models_own_prediction():
    """With tail="model" the first iterate of a period is the last plan shifted, its new last input the
    feed-forward plus LQR, and its new last state the model's step under that input (not the old one repeated)."""
    model = OnnxModel(PROPOSED)
    sqp = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    sim = Simulator(QuadParams())
    x = FIG8_FAST(np.array([0.0]))[0]
    sqp.prepare(1.0, x0=x)
    u, _ = sqp(x, 0.0)
    old_x, old_u = sqp._plan_x.copy(), sqp._plan_u.copy()
    x = sim.step(x, u)
    ref, u_ref = sqp._horizon_reference(0.01)
    X, U = sqp._initial_iterate(x, ref, u_ref)
    assert np.array_equal(X[0], x) and np.array_equal(X[1:-1], old_x[2:]) and np.array_equal(U[:-1], old_u[1:])
    assert np.allclose(U[-1], u_ref[-1] - sqp.lqr.K @ (old_x[-1] - ref[-2]), rtol=0, atol=1e-12)
    fx = model.step(X[:-1], U)
    warm = sqp._close_tail(X, U, fx, None)
    assert np.array_equal(X[-1], model.step(old_x[-1], U[-1])[0])
    assert np.array_equal(warm, np.concatenate([X.ravel(), U.ravel()]))
    # The LTV-MPC's shift (tail="hold") repeats the last state and input.
    hold = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None, tail="hold"))
    hold._plan_x, hold._plan_u = old_x, old_u
    Xh, Uh = hold._initial_iterate(x, ref, u_ref)
    assert np.array_equal(Xh[-1], old_x[-1]) and np.array_equal(Uh[-1], old_u[-1])
    assert hold._close_tail(Xh, Uh, fx, "kept") == "kept" and np.array_equal(Xh[-1], old_x[-1])


@pytest.mark.parametrize("every,expected", [(1, 5), (2, 3), (3, 2), (10, 1)])
def test_iterations_between_jacobian_evaluations_do_not_linearize_the_model(every, expected, nan_jacobians_after):
    model = nan_jacobians_after(AnalyticModel(), 10 ** 9)     # the oracle, its linearizations counted
    sqp = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=5,
                                               step_tol=0.0, defect_tol=0.0, jacobians="float64",
                                               jacobian_every=every, jacobian_refresh="full"))
    t, x = sampled_states(1, seed=2)[0]
    sqp.prepare(1.0, x0=x)          # the feed-forward fit and the pre-flight plan linearize too: not counted
    model.linearizations = 0
    _, info = sqp(x, t)
    assert info.iterations == 5 and info.is_optimal()
    assert model.linearizations == expected     # iterations 0, every, 2 every, ... of the five


def test_iterations_between_jacobian_evaluations_leave_the_converged_plan_unchanged():
    """Reusing the Jacobians changes the path, not the fixed points: with the oracle (where Gauss-Newton converges
    in a few iterations) every other evaluation reaches the same objective, in about twice the iterations."""
    def converged(every):
        s = SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=100, step_tol=1e-7,
                        defect_tol=0.0, eps_abs=1e-10, eps_rel=1e-10, max_iter=100000, polish=True,
                        jacobians="float64", jacobian_every=every, jacobian_refresh="full")
        sqp, out = SQPMPC(AnalyticModel(), FIG8_FAST, s), []
        for t, x in sampled_states(8, seed=3):
            ref, u_ref = sqp._horizon_reference(t)
            Xs, Us, info = sqp.solve_from(x, t, *sqp.rollout(x, ref, u_ref))
            assert info.extra["converged"], f"t={t}: not converged in {info.iterations} iterations"
            out.append((sqp.cost(Xs, Us, ref, u_ref), info.iterations))
        return np.array(out)
    every, each = converged(2), converged(1)
    np.testing.assert_allclose(every[:, 0], each[:, 0], rtol=TOL["fixed_point_rel"], atol=0)
    assert np.all(every[:, 1] > each[:, 1])     # the reuse iterations did happen


def test_the_time_split_counts_each_part_of_a_period_once():
    sqp = SQPMPC(OnnxModel(PROPOSED), FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    sim, x = Simulator(QuadParams()), FIG8_FAST(np.array([0.0]))[0]
    sqp.prepare(1.5, x0=x)
    corrected = 0
    for k in range(150):
        u, info = sqp(x, 0.01 * k)
        split = info.extra["time_split_s"]
        assert min(split.values()) >= 0.0, split
        assert sum(split.values()) <= info.solve_time_s, (split, info.solve_time_s)
        corrected += -1.0 in info.extra["step_lengths"]
        x = sim.step(x, u)
    assert corrected > 0, "no second-order correction: the test does not exercise the correction's QP"


def test_accepted_steps_never_raise_the_merit_and_some_are_shortened():
    sqp = SQPMPC(OnnxModel(PROPOSED), FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None,
                                                             max_sqp_iter=10))
    accepted = shortened = 0
    for t, x in sampled_states(10, seed=1):
        ref, u_ref = sqp._horizon_reference(t)
        _, _, info = sqp.solve_from(x, t, *sqp.rollout(x, ref, u_ref))
        assert len(info.extra["merit"]) == len(info.extra["step_lengths"]) == info.iterations
        for (before, after, ok), alpha in zip(info.extra["merit"], info.extra["step_lengths"]):
            if ok:
                accepted += 1
                assert after <= before * (1 + TOL["merit_rel"])
            shortened += alpha != 1.0        # halved (0 < alpha < 1) or second-order corrected (alpha = -1)
    assert accepted > 0
    assert shortened > 0, "every full step was taken: the test case does not exercise the line search"


def test_cold_start_from_a_standing_start_is_counted_and_does_not_fail():
    x = hover_point()[0].copy()
    x[0:2] = [0.3, -0.2]
    sqp = SQPMPC(OnnxModel(PROPOSED))
    infos = []
    sim = Simulator(QuadParams())
    for k in range(30):
        u, info = sqp(x, 0.01 * k)
        infos.append(info)
        x = sim.step(x, u)
    assert infos[0].extra["cold_start"] and not any(i.extra["cold_start"] for i in infos[1:])
    assert all(i.is_optimal() for i in infos)
    assert sqp.counts["cold_starts"] == 1 and sqp.counts["solver_failures"] == 0
    # The first iterate of a cold start is the model flown under the feed-forward and the LQR.
    X, U = sqp.rollout(x, *sqp._horizon_reference(0.0))
    np.testing.assert_array_equal(X[1:], sqp.model.step(X[:-1], U))


def test_a_plan_made_before_take_off_starts_the_first_period_unshifted():
    x0 = hover_point()[0].copy()
    x0[0:2] = [0.3, -0.2]
    sqp = SQPMPC(OnnxModel(PROPOSED))
    sqp.prepare(0.5, x0=x0)
    pre = sqp.preflight
    assert pre.is_optimal() and pre.extra["cold_start"] and pre.iterations >= 1
    assert sqp.counts["cold_starts"] == 1
    X, U = sqp._plan_x.copy(), sqp._plan_u.copy()
    Xi, Ui = sqp._initial_iterate(x0, *sqp._horizon_reference(0.0))   # made for t = 0: the first period starts from it
    assert np.array_equal(Xi[1:], X[1:]) and np.array_equal(Xi[0], x0) and np.array_equal(Ui, U)
    u, info = sqp(x0, 0.0)
    assert info.is_optimal() and not info.extra["cold_start"] and sqp.counts["cold_starts"] == 1
    Xi, _ = sqp._initial_iterate(x0, *sqp._horizon_reference(0.01))   # later periods shift the plan by one step
    np.testing.assert_array_equal(Xi[1:-1], sqp._plan_x[2:])


def test_failures_shift_the_plan_then_fall_back_to_lqr_and_the_next_plan_is_a_counted_cold_start(
        nan_jacobians_after):
    model = nan_jacobians_after(AnalyticModel(), 10 ** 9)   # the oracle
    sqp = SQPMPC(model, settings=SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=1,
                                             cold_start_max_iter=1))
    sqp.prepare(1.0)       # the feed-forward fit linearizes the model too: done before the count starts
    model.left = 2
    x = hover_point()[0].copy()
    x[0] = 0.3
    infos = [sqp(x, 0.01 * k)[1] for k in range(5)]
    assert [i.status for i in infos[:2]] == ["optimal", "optimal"]
    assert [i.fallback for i in infos[2:]] == ["shifted_plan", "shifted_plan", "lqr"]
    assert sqp.counts["solver_failures"] == 3 and sqp.counts["lqr_fallback"] == 1
    model.left = 10
    _, info = sqp(x, 0.05)
    assert info.is_optimal() and info.extra["cold_start"] and sqp.counts["cold_starts"] == 2


def test_a_period_past_its_budget_takes_the_qps_full_step_without_a_line_search():
    """After its first QP a period past its budget stops there with the full step: the same plan, bit for bit, as
    one full-step iteration with no budget from the same first iterate, and no line search (which, in time, runs)."""
    model = OnnxModel(PROPOSED)
    late = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=1e-9, cold_start_budget_s=None))
    rti = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=1,
                                               line_search=False))
    searched = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None, max_sqp_iter=1))
    for t, x in sampled_states(6, seed=4):
        X0, U0 = late._horizon_reference(t)
        X1, U1, info = late.solve_from(x, t, X0, U0)
        X2, U2, _ = rti.solve_from(x, t, X0, U0)
        info3 = searched.solve_from(x, t, X0, U0)[2]
        assert info.iterations == 1 and info.extra["late_full_steps"] == 1 and info.extra["merit"] == []
        assert np.array_equal(U1, U2) and np.array_equal(X1, X2)
        assert len(info3.extra["merit"]) == 1 and info3.extra["late_full_steps"] == 0


def test_a_line_search_shortens_its_step_only_while_another_trial_fits_the_budget():
    """A full step that raises the merit, no correction: without a clock the step is halved up to four times (five
    model steps); on a fake clock whose budget is spent it stops after the first trial and takes the best one tried;
    with a budget for three and a half trials of the fake clock's length it makes three."""
    from mpc.controllers.sqp import MAX_BACKTRACKS
    from mpc.controllers.timing import PeriodClock

    class Counted(AnalyticModel):
        calls = 0
        tick = 0.0

        def step(self, x, u):
            Counted.calls += 1
            fake["t"] += Counted.tick          # each model step takes `tick` s of the fake clock
            return super().step(x, u)

    fake = {"t": 0.0}
    sqp = SQPMPC(Counted(), FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    x = FIG8_FAST(np.array([0.0]))[0]
    X, U = sqp._horizon_reference(0.0)
    X = X.copy()
    X[0] = x
    fx = sqp.model.step(X[:sqp.N], U)
    Xq, Uq = X + 0.5, U + 0.5 * np.abs(U).max()          # far off: the merit rises at every step length tried
    ref, u_ref = sqp._horizon_reference(0.0)
    args = (X, U, Xq, Uq, fx, ref, u_ref, 1.0, lambda shift: None)
    for budget, tick, trials in ((None, 0.0, 1 + MAX_BACKTRACKS), (-1.0, 0.0, 1), (3.5e-3, 1e-3, 3)):
        clock = None if budget is None else PeriodClock(lambda: fake["t"]).begin(fake["t"], budget)
        Counted.calls, Counted.tick = 0, tick
        Xn, Un, alpha, accepted, phi0, phi, _, _ = sqp._line_search(*args, clock=clock)
        assert Counted.calls == trials and not accepted, (budget, Counted.calls)
        assert phi > phi0 and alpha in (1.0, 0.5, 0.25, 0.125, 0.0625)
        # The best trial is taken: its merit is the lowest of those tried.
        assert phi == pytest.approx(sqp._merit(Xn, Un, sqp.model.step(Xn[:sqp.N], Un), ref, u_ref, 1.0),
                                    rel=TOL["merit_rel"])


def test_a_period_that_cannot_plan_before_its_deadline_sends_the_shifted_plan_at_once(nan_jacobians_after):
    model = nan_jacobians_after(AnalyticModel(), 10 ** 9)     # the oracle, its linearizations counted
    sqp = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    twin = SQPMPC(AnalyticModel(), FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    x = FIG8_FAST(np.array([0.0]))[0]
    sim = Simulator(QuadParams())
    for c in (sqp, twin):
        c.prepare(1.0, x0=x)
    for k in range(3):      # a deadline that is met changes nothing
        sqp.set_deadline(time.perf_counter() + 100.0)
        u, info = sqp(x, 0.01 * k)
        assert info.is_optimal() and np.array_equal(u, twin(x, 0.01 * k)[0])
        x = sim.step(x, u)
    plan = sqp._plan_u.copy()
    model.linearizations = 0
    sqp.set_deadline(time.perf_counter() - 1e-3)     # already past: no derivatives, no QP
    u, info = sqp(x, 0.03)
    assert info.status == "deadline" and info.fallback == "shifted_plan" and model.linearizations == 0
    assert np.array_equal(u, plan[1])
    _, info = sqp(x, 0.04)                     # the deadline was for that call only
    assert info.is_optimal() and model.linearizations == 1
    # A cold start with no earlier one to judge it by plans whatever the deadline.
    cold = SQPMPC(AnalyticModel(), FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    cold.set_deadline(time.perf_counter() - 1e-3)
    _, info = cold(FIG8_FAST(np.array([0.0]))[0], 0.0)
    assert info.is_optimal() and info.extra["cold_start"]


def prepared_on_a_still_clock(model, cold_start_s: float):
    """An ideal-timing SQP on ``model`` whose clock stands still at 0, prepared at the start of figure8-fast, with a
    cold start's time to its first plan of ``cold_start_s`` recorded; ``(sqp, x0)``."""
    from mpc.controllers.timing import PeriodClock

    sqp = SQPMPC(model, FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
    sqp.clock = PeriodClock(lambda: 0.0)
    x = FIG8_FAST(np.array([0.0]))[0]
    sqp.prepare(1.0, x0=x)
    sqp.clock.record("cold_start", cold_start_s)
    return sqp, x


def test_a_cold_start_in_flight_that_would_end_past_the_deadline_is_put_off_and_the_lqr_flies(nan_jacobians_after):
    """On a fake clock: the pre-flight plan took 1 s to its first plan (a very slow machine). A cold start in flight
    (after the LQR took over) with 0.5 s to its deadline makes no model call and sends the LQR's input; with 2 s
    it plans, and its deadline is kept."""
    model = nan_jacobians_after(AnalyticModel(), 10 ** 9)     # the oracle, its linearizations counted
    sqp, x = prepared_on_a_still_clock(model, cold_start_s=1.0)
    sqp._plan_x = sqp._plan_u = sqp._z = None       # what a hand-over to the LQR leaves
    ref, u_ref = sqp._horizon_reference(0.01)
    model.linearizations = 0
    sqp.set_deadline(0.5)
    u, info = sqp(x, 0.01)
    assert info.status == "deadline" and info.fallback == "lqr" and model.linearizations == 0
    assert np.array_equal(u, sqp._rotor_feasible(sqp.lqr.input(x, ref[0], u_ref[0])))
    assert sqp.counts["cold_starts_deferred"] == 1 and not info.extra["cold_start"]
    sqp.set_deadline(2.0)
    _, info = sqp(x, 0.02)
    assert info.is_optimal() and info.extra["cold_start"] and model.linearizations >= 1
    assert sqp.counts["cold_starts_deferred"] == 1


def test_a_cold_start_in_flight_with_no_time_for_its_rollout_starts_from_the_reference(nan_jacobians_after):
    """On a fake clock: a cold start's rollout and first plan took 1 s lately, a full refresh 0.1 s. With 0.5 s to
    the deadline the cold start in flight plans from the reference states (no single-state model step: no rollout);
    with 0.05 s it is put off."""
    class Counted(nan_jacobians_after):
        singles = 0

        def step(self, x, u):
            Counted.singles += np.ndim(x) == 1 or len(x) == 1
            return super().step(x, u)

    sqp, x = prepared_on_a_still_clock(Counted(AnalyticModel(), 10 ** 9), cold_start_s=1.0)
    sqp.clock.record("full_derivatives", 0.1)
    for deadline, planned in ((0.5, True), (0.05, False)):
        sqp._plan_x = sqp._plan_u = sqp._z = None   # what a hand-over to the LQR leaves
        Counted.singles = 0
        sqp.set_deadline(deadline)
        _, info = sqp(x, 0.01)
        assert Counted.singles == 0 and info.extra["cold_start"] == planned, deadline
        assert info.is_optimal() == planned and (planned or info.fallback == "lqr")
    assert sqp.counts["cold_starts_from_reference"] == 1 and sqp.counts["cold_starts_deferred"] == 1
    # With a full refresh too slow for the deadline but the last plan's Jacobians kept, a partial refresh (its
    # median time) plans from the reference.
    sqp.clock.record("full_derivatives", 1.0)
    sqp.clock.record("derivatives", 0.05)
    sqp._plan_x = sqp._plan_u = sqp._z = None
    sqp.set_deadline(0.5)
    _, info = sqp(x, 0.02)
    assert info.is_optimal() and info.extra["cold_start"] and info.extra["full_refreshes"] == 0
    assert 0 < info.extra["refreshed_stages"] <= sqp.s.max_refresh_stages
    assert sqp.counts["cold_starts_from_reference"] == 2


def test_two_ideal_runs_are_identical():
    def run():
        sqp = SQPMPC(OnnxModel(PROPOSED), FIG8_FAST, SQPSettings(time_budget_s=None, cold_start_budget_s=None))
        sim, x, us = Simulator(QuadParams()), FIG8_FAST(np.array([0.0]))[0], []
        for k in range(40):
            u, _ = sqp(x, 0.01 * k)
            us.append(u)
            x = sim.step(x, u)
        return np.array(us)
    assert np.array_equal(run(), run())


@pytest.mark.parametrize("kwargs,match", [
    (dict(max_sqp_iter=0), "max_sqp_iter"),
    (dict(time_budget_s=0.0), "time_budget_s"),
    (dict(cold_start_budget_s=-1.0), "cold_start_budget_s"),
    (dict(step_tol=-1.0), "step_tol"),
    (dict(cold_start="zeros"), "cold_start"),
    (dict(jacobians="float16"), "jacobians"),
    (dict(hessian="bfgs"), "hessian"),
    (dict(tail="zero"), "tail"),
    (dict(jacobian_every=0), "jacobian_every"),
])
def test_bad_settings_are_clear_errors(kwargs, match):
    with pytest.raises(ConfigurationError, match=match):
        SQPSettings(**kwargs)


def test_ltv_settings_are_refused_and_guesses_must_have_the_horizons_shape():
    from mpc.controllers.ltv import LTVSettings
    with pytest.raises(ConfigurationError, match="SQPSettings"):
        SQPMPC(AnalyticModel(), settings=LTVSettings())
    sqp = SQPMPC(AnalyticModel())
    with pytest.raises(ConfigurationError, match="X0 must be"):
        sqp.solve_from(hover_point()[0], 0.0, np.zeros((5, 12)), np.zeros((30, 4)))
