"""The SQP's partial derivative path (jacobian_refresh="partial") against today's full one.

The partial path keeps each stage's Jacobians and model step from earlier periods and evaluates them again only
where the plan moved. These tests check what it keeps (exactly the model's own values at the recorded points), when
it refreshes every stage, that a deadline cuts a full refresh short, and that it flies as the full path does
within stated tolerances.
"""

from pathlib import Path

import numpy as np
import pytest

from mpc.errors import ConfigurationError
from mpc.prediction.models import AnalyticModel, OnnxModel
from mpc.controllers.sqp import SQPMPC, SQPSettings
from mpc.controllers.timing import PeriodClock
from mpc.references.trajectory import Figure8
from sim import Simulator
from sim.params import DT

ROOT = Path(__file__).resolve().parents[1]
FIG8_FAST = Figure8(0.75, 3.0, 1.0)
IDEAL = dict(time_budget_s=None, cold_start_budget_s=None)

TOL = {
    # The model's steps a period keeps against new ones at the same points: onnxruntime may sum in another order
    # for another batch size (float64 model: a few ulps).
    "kept_step_abs": 1e-12,
    # Closed-loop RMSE of the partial path against the full one (same start, ideal timing): the oracle's and a
    # learned model's, on a figure-8 both fly without drama.
    "oracle_rmse_abs_m": 5e-5,
    "baseline_rmse_rel": 0.02,
}


def fly(model, settings, seconds=1.5, offset=(0.05, -0.03, 0.0)):
    c = SQPMPC(model, FIG8_FAST, settings)
    x = FIG8_FAST(np.array([0.0]))[0].copy()
    x[0:3] += offset
    c.prepare(seconds, x0=x)
    sim, err, infos = Simulator(), [], []
    for k in range(int(round(seconds / DT))):
        u, info = c(x, k * DT)
        infos.append(info)
        x = sim.step(x, u)
        err.append(np.linalg.norm(x[:3] - FIG8_FAST(np.array([(k + 1) * DT]))[0, :3]))
    return c, float(np.sqrt(np.mean(np.square(err)))), infos


def test_what_the_partial_path_keeps_is_the_models_own_steps_and_jacobians_at_the_recorded_points():
    model = OnnxModel(ROOT / "models" / "proposed.onnx")
    c, _, infos = fly(model, SQPSettings(jacobian_refresh="partial", **IDEAL), seconds=0.4)
    assert all(i.is_optimal() for i in infos)
    # Most periods refresh only some stages; the start (the pre-flight plan) refreshed all of them.
    refreshed = [i.extra["refreshed_stages"] for i in infos]
    assert min(refreshed) < c.N and c.counts["full_refreshes"] >= 1
    N = c.N
    A, B = model.jacobians(c._jac_points[:, :c.nx], c._jac_points[:, c.nx:])
    np.testing.assert_array_equal(A, c._jac_A)
    np.testing.assert_array_equal(B, c._jac_B)
    f = model.step(c._f_points[:, :c.nx], c._f_points[:, c.nx:])
    np.testing.assert_allclose(c._f_values, f, rtol=0, atol=TOL["kept_step_abs"])
    # The kept steps are those of the plan the period made.
    np.testing.assert_array_equal(c._f_points, np.hstack([c._plan_x[:N], c._plan_u]))


def test_with_a_zero_tolerance_the_partial_path_is_the_full_one_bit_for_bit():
    """A tolerance of zero refreshes every stage that moved at all, and a kept step is reused only at exactly its
    point: with the oracle (CasADi evaluates each stage on its own) the flight is the full path's, bit for bit."""
    strict = SQPSettings(jacobian_refresh="partial", refresh_tol=0.0, max_refresh_stages=30, full_refresh_above=30,
                         **IDEAL)
    _, r_full, full = fly(AnalyticModel(), SQPSettings(jacobian_refresh="full", **IDEAL), seconds=0.3)
    c, r_part, part = fly(AnalyticModel(), strict, seconds=0.3)
    assert r_full == r_part
    for a, b in zip(full, part):
        np.testing.assert_array_equal(a.predicted, b.predicted)
    # Only the pre-flight plan counts as a full refresh; later periods refreshed the stages that moved, one by one.
    assert c.counts["full_refreshes"] == 1


def _count_steps(model):
    """Record the points of every batched step ``model`` is asked for (in the returned list)."""
    stepped, step = [], model.step

    def counted(x, u):
        stepped.append(np.hstack([np.atleast_2d(x), np.atleast_2d(u)]))
        return step(x, u)

    model.step = counted
    return stepped


def test_an_iteration_after_a_line_search_steps_nothing_the_line_search_stepped():
    """With several iterations per period, the iterate the line search took was stepped by it: the next iteration's
    model step reuses those values instead of asking the model again for the same points."""
    model = OnnxModel(ROOT / "models" / "proposed.onnx")
    stepped = _count_steps(model)
    c, _, infos = fly(model, SQPSettings(jacobian_refresh="partial", max_sqp_iter=4, **IDEAL), seconds=0.3)
    assert sum(i.iterations for i in infos) > len(infos)          # some periods took more than one iteration
    seen, again = set(), 0
    for rows in stepped:
        if len(rows) < c.N:        # the tracker's, the feed-forward's and the shifted plan's few new stages
            continue
        key = rows.tobytes()
        again += key in seen
        seen.add(key)
    assert again == 0


def test_with_a_huge_tolerance_nothing_is_refreshed_after_the_first_plan():
    lax = SQPSettings(jacobian_refresh="partial", refresh_tol=1e9, **IDEAL)
    c, rmse, infos = fly(AnalyticModel(), lax, seconds=0.2)
    assert all(i.extra["refreshed_stages"] == 0 for i in infos) and c.counts["full_refreshes"] == 1
    assert all(i.is_optimal() for i in infos)


def test_a_plan_that_moved_everywhere_gets_a_full_refresh_unless_the_deadline_forbids_it():
    model = AnalyticModel()
    c = SQPMPC(model, FIG8_FAST, SQPSettings(jacobian_refresh="partial", **IDEAL))
    x = FIG8_FAST(np.array([0.0]))[0]
    c.prepare(1.0, x0=x)
    c(x, 0.0)
    before = c.counts["full_refreshes"]
    c._jac_points = c._jac_points + 10.0            # every stage far from where its Jacobians were taken
    _, info = c(x, 0.01)
    assert info.extra["full_refreshes"] == 1 and c.counts["full_refreshes"] == before + 1
    # The same on a fake clock whose deadline leaves no room for a full refresh: the period refreshes at most
    # max_refresh_stages stages and still plans.
    fake = {"t": 0.0}
    c.clock = PeriodClock(lambda: fake["t"])
    c.clock.record("full_derivatives", 1.0)          # a full refresh took 1 s lately (a very slow machine)
    c._jac_points = c._jac_points + 10.0
    c.set_deadline(0.5)                              # the fake clock stands still at 0: 0.5 s are left
    _, info = c(x, 0.02)
    assert info.is_optimal() and info.extra["full_refreshes"] == 0
    assert info.extra["refreshed_stages"] == c.s.max_refresh_stages
    # A full refresh that fits with the least QP time but not with the QP's expected solve is cut too; with a
    # faster solve it is made.
    for qp_s, full in ((0.2, 0), (0.05, 1)):
        c.clock = PeriodClock(lambda: fake["t"])
        c.clock.record("full_derivatives", 0.4)
        c.clock.record("qp", qp_s)
        c._jac_points = c._jac_points + 10.0
        c.set_deadline(0.5)
        _, info = c(x, 0.03)
        assert info.is_optimal() and info.extra["full_refreshes"] == full, qp_s


def test_the_partial_path_flies_as_the_full_one():
    _, full, _ = fly(AnalyticModel(), SQPSettings(jacobian_refresh="full", **IDEAL))
    _, part, _ = fly(AnalyticModel(), SQPSettings(jacobian_refresh="partial", **IDEAL))
    assert abs(part - full) <= TOL["oracle_rmse_abs_m"]
    base = OnnxModel(ROOT / "models" / "baseline.onnx")
    _, full, _ = fly(base, SQPSettings(jacobian_refresh="full", **IDEAL))
    _, part, _ = fly(base, SQPSettings(jacobian_refresh="partial", **IDEAL))
    assert abs(part / full - 1.0) <= TOL["baseline_rmse_rel"]


@pytest.mark.parametrize("field,value", [("jacobian_refresh", "some"), ("refresh_tol", -1.0),
                                         ("max_refresh_stages", 0), ("full_refresh_above", 0)])
def test_bad_refresh_settings_are_refused_by_name(field, value):
    with pytest.raises(ConfigurationError, match=field):
        SQPSettings(**{field: value})


def test_nothing_non_finite_is_kept_and_a_cold_start_evaluates_every_stage(nan_jacobians_after):
    model = nan_jacobians_after(AnalyticModel(), 10 ** 9)
    c = SQPMPC(model, FIG8_FAST, SQPSettings(jacobian_refresh="partial", **IDEAL))
    x = FIG8_FAST(np.array([0.0]))[0]
    c.prepare(1.0, x0=x)
    _, info = c(x, 0.0)
    assert info.is_optimal() and c._jac_points is not None
    model.left = 0                                   # every later evaluation of A is NaN
    c._jac_points = c._jac_points + 10.0             # every stage moved: all are evaluated again
    _, info = c(x, 0.01)
    assert info.status == "non-finite model output" and c._jac_points is None and c._f_points is None
    model.left = 10 ** 9
    _, info = c(x, 0.02)                             # the next Jacobian iteration evaluates every stage
    assert info.is_optimal() and info.extra["full_refreshes"] >= 1
