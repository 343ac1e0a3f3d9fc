"""Rotor layer (allocation, saturation, telemetry) and parameter validation."""

import math

import numpy as np
import pytest

from sim import Fidelity, NoiseModel, QuadParams, Simulator
from sim.vehicles.rotors import allocate, mixer_matrix, realize

TOL = {
    "realized_equals_command": 1e-12,   # relative to the wrench scale, below saturation
    "limit": 1e-12,                      # relative, clipped rotor at its limit
}

P = QuadParams()
W_SCALE = np.array([P.m * P.g, 0.01, 0.01, 0.02])  # N, N m: size of each wrench component


def feasible_wrenches(rng, n):
    """Random wrenches whose allocation lies strictly inside the rotor limits."""
    n_sq = rng.uniform(0.05, 0.95, (n, 4)) * P.n_max_sq
    return n_sq @ mixer_matrix(P).T


def test_below_saturation_realized_wrench_equals_command(rng):
    w = feasible_wrenches(rng, 1000)
    out = realize(w, P)
    assert not out.saturated.any()
    assert np.max(np.abs(out.wrench - w) / W_SCALE) < TOL["realized_equals_command"]
    # Same through the simulator, whose telemetry is sqrt(n^2) of the allocation.
    res = Simulator(P).step_full(np.zeros((1000, 12)), w)
    assert np.max(np.abs(res.wrench - w) / W_SCALE) < TOL["realized_equals_command"]
    np.testing.assert_allclose(res.rotor_speed ** 2, allocate(w, P), rtol=1e-12)


def test_saturation_clips_each_rotor_and_telemetry_shows_it():
    # Three times hover thrust: every rotor above its limit.
    res = Simulator(P).step_full(np.zeros(12), [3 * P.m * P.g, 0, 0, 0])
    n_max = math.sqrt(P.n_max_sq)
    assert res.saturated.all()
    np.testing.assert_allclose(res.rotor_speed, n_max, rtol=TOL["limit"])
    np.testing.assert_allclose(res.wrench[0], 2 * P.m * P.g, rtol=TOL["limit"])  # total limit 2 m g
    # A large roll torque drives the right rotors (1, 2) to zero and the left ones (3, 4) up.
    res = Simulator(P).step_full(np.zeros(12), [P.m * P.g, 0.05, 0, 0])
    assert res.saturated.all()
    np.testing.assert_array_equal(res.rotor_speed[[0, 1]], 0.0)
    np.testing.assert_allclose(res.rotor_speed[[2, 3]], n_max, rtol=TOL["limit"])
    assert res.wrench[1] < 0.05  # realized roll torque is what the clipped rotors give
    np.testing.assert_allclose(res.wrench, mixer_matrix(P) @ (res.rotor_speed ** 2), rtol=1e-12)


def test_rotor_geometry_signs():
    # More thrust on the left rotors (3, 4; y < 0) rolls right (positive tau_x);
    # more on the front rotors (1, 4) pitches nose up (positive tau_y).
    M = mixer_matrix(P)
    assert M[1] @ [0, 0, 1, 1] > 0 and M[2] @ [1, 0, 0, 1] > 0
    np.testing.assert_allclose(M[0], P.kt)
    np.testing.assert_allclose(np.abs(M[1:3]), P.kt * P.d / math.sqrt(2))


@pytest.mark.parametrize("field", ["m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "g", "c_d", "n_max"])
@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_params_reject_non_positive_or_non_finite(field, bad):
    if field == "c_d" and bad == 0.0:
        assert QuadParams(c_d=0.0).c_d == 0.0     # no drag at all is a valid vehicle (RotorPy's ideal set-up)
        return
    with pytest.raises(ValueError, match=f"QuadParams.{field}"):
        QuadParams(**{field: bad})


def test_params_rotor_limit_given_or_derived():
    assert QuadParams(n_max=5.0).n_max_sq == 25.0
    assert QuadParams(m=0.1).n_max_sq == pytest.approx(2 * 0.1 * 9.81 / (4 * 0.01), rel=1e-15)


def test_params_reference_values_and_overrides():
    p = QuadParams(m=0.08)
    assert p.m == 0.08 and p.Jxx == 6.86e-5 and p.kq == 7.83e-4
    np.testing.assert_allclose(4 * P.kt * P.n_max_sq, 2 * P.m * P.g)
    np.testing.assert_allclose(4 * P.kt * P.n_hover ** 2, P.m * P.g)


def test_fidelity_and_noise_validation():
    with pytest.raises(ValueError, match="Fidelity.motor_tau"):
        Fidelity(motor_tau=-0.1)
    with pytest.raises(ValueError, match="NoiseModel.position"):
        NoiseModel(position=float("nan"))
