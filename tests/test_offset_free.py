"""Offset-free control: the target under a known disturbance, no steady offset with an estimated one."""

import numpy as np
import pytest

from mpc.errors import ConfigurationError
from mpc.models import AnalyticModel
from mpc.offset_free import DisturbedModel, ShiftedTrajectory, disturbance_matrix, disturbance_offset
from mpc.trajectory import Figure8, Hover
from scenarios.runner import RunSpec, fly, make_controller
from sim.params import DT
from sim.vehicle import load_vehicle

#: Tolerances of this module.
TOL = {
    "thrust": 1e-6,         # N: the hover thrust under a vertical disturbance, m (g + a)
    "tilt": 1e-6,           # rad: the pitch that cancels a horizontal disturbance, atan(a / g)
    "defect": 1e-3,         # the target's one-period defect through f + G d, in the states' scales
    "defect_velocity": 1e-4,  # m/s: the same, velocity
    "settled": 5e-3,        # m: hover+payload with the estimator, settled error (the acceptance bound)
}


def _oracle():
    return AnalyticModel(load_vehicle(None).params)


def test_the_target_under_a_known_disturbance_is_the_analytic_trim():
    """At hover, a downward 2 m/s^2 needs m (g + 2) of thrust; a 1.5 m/s^2 push north needs atan(1.5 / g) of pitch."""
    model = _oracle()
    p = load_vehicle(None).params
    ctrl = make_controller("lqr", model, Hover())
    ctrl.prepare(1.0)
    t = np.array([0.5, 0.5 + DT])
    ctrl.set_disturbance([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])
    X, U = ctrl.ff.horizon(t)
    assert abs(U[0, 0] - p.m * (p.g + 2.0)) < TOL["thrust"]
    ctrl.set_disturbance([1.5, 0.0, 0.0, 0.0, 0.0, 0.0])
    X, U = ctrl.ff.horizon(t)
    assert abs(X[0, 4] - np.arctan2(1.5, p.g)) < TOL["tilt"]
    assert abs(X[0, 3]) < TOL["tilt"]
    ctrl.set_disturbance(None)
    X0, U0 = ctrl.ff.horizon(t)
    np.testing.assert_array_equal(U0, ctrl.ff.inputs(t[:1]))


def test_the_target_is_flown_exactly_by_the_disturbed_model():
    model = _oracle()
    ctrl = make_controller("sqp", model, Figure8(period=3.0))
    ctrl.prepare(4.0)
    d = np.array([0.4, -0.3, 0.5, 2.0, -1.0, 0.5])
    ctrl.set_disturbance(d)
    X, U = ctrl._horizon_reference(1.0)
    off = disturbance_offset(d, None, 12)
    defect = model.step(X[:-1], U) + off - X[1:]
    scale = ctrl.state_scale
    # A least-squares fit of 4 inputs to 12 residuals; the flatness map's states make it nearly exact.
    assert np.max(np.abs(defect / scale)) < TOL["defect"]
    assert np.max(np.abs(defect[:, 9:12])) < TOL["defect_velocity"]


def test_the_disturbed_model_adds_its_offset_and_nothing_without_one():
    model = _oracle()
    dm = DisturbedModel(model)
    x = np.tile([0.1, 0.2, -1.0, 0.05, -0.02, 0.3, 0.1, 0, 0, 1.0, 0.5, 0.0], (3, 1))
    u = np.tile([0.7, 1e-4, 0.0, 0.0], (3, 1))
    np.testing.assert_array_equal(dm.step(x, u), model.step(x, u))
    d = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    dm.offset = disturbance_offset(d, x[0], 12)
    np.testing.assert_allclose(dm.step(x, u) - model.step(x, u),
                               np.tile(disturbance_matrix(x[0, 3:6], 12) @ d, (3, 1)), atol=1e-15)
    # A constant acceleration over one period: dt^2 / 2 in position, dt in velocity.
    assert dm.offset[0] == pytest.approx(0.5 * DT * DT) and dm.offset[9] == pytest.approx(DT)


def test_shifted_trajectory_changes_only_the_acceleration():
    ref = Figure8(period=3.0)
    sh = ShiftedTrajectory(ref, [0.1, -0.2, 0.3])
    t = np.linspace(0, 3, 7)
    a, b = ref.flat(t), sh.flat(t)
    np.testing.assert_array_equal(a.pos, b.pos)
    np.testing.assert_array_equal(a.jerk, b.jerk)
    np.testing.assert_allclose(a.acc - b.acc, np.tile([0.1, -0.2, 0.3], (7, 1)), atol=1e-15)


def test_a_bad_disturbance_gets_one_line():
    with pytest.raises(ConfigurationError, match="6 finite numbers"):
        disturbance_offset([1.0, 2.0], None, 12)


@pytest.mark.parametrize("controller", ["lqr", "ltv", "sqp"])
def test_a_payload_leaves_no_offset_with_the_estimator(controller):
    """hover+payload (20 % more mass than the model knows): 104 mm settled error on the true state, < 5 mm here."""
    r, _ = fly(RunSpec("hover+payload", controller, "oracle", estimator="ekf"))
    assert not r["crashed"]
    assert r["settled_error_m"] < TOL["settled"], r["settled_error_m"]


@pytest.mark.slow
def test_a_payload_leaves_no_offset_with_the_estimator_nmpc():
    r, _ = fly(RunSpec("hover+payload", "nmpc", "oracle", estimator="ekf"))
    assert not r["crashed"]
    assert r["settled_error_m"] < TOL["settled"], r["settled_error_m"]
