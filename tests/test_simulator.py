"""Simulator options: high-fidelity effects one at a time, disturbances, input checks."""

import numpy as np
import pytest

from sim import HIGH_FIDELITY, Fidelity, NoiseModel, QuadParams, Simulator, dynamics

P = QuadParams()
HOVER = np.array([P.m * P.g, 0.0, 0.0, 0.0])

TOL = {
    # One 10 ms period from rest: quadratic drag at the reached 1.6 cm/s changes the
    # velocity by about 3e-6 relative, so the constant-acceleration answer holds to 1e-5.
    "one_period_acceleration": 1e-5,
    "noise_std": 0.03,        # sample std of 20,000 draws vs the stated std
    "motor_lag_settled": 1e-4,  # after 10 time constants, exp(-10) = 4.5e-5
    "rotor_drag": 0.05,       # one period, force changes with speed and attitude
    "single_vs_batch": 1e-12,  # one state (CasADi form of the RK4 step) vs a batch of one (numpy), per state
}


def moving_state():
    x = np.zeros(12)
    x[2] = -1.0
    x[6:9] = [0.5, -0.4, 0.3]
    x[9:12] = [2.0, -1.0, 0.0]
    return x


@pytest.mark.parametrize("field,value", [("motor_tau", 0.03), ("rotor_drag", 1.2e-3), ("rotor_gyro", 5e-6)])
def test_each_high_fidelity_effect_switches_alone(field, value):
    x = moving_state()
    u = HOVER + np.array([0.05, 1e-4, -1e-4, 2e-4])
    nominal = Simulator(P).step(x, u)
    one = Simulator(P, Fidelity(**{field: value})).step_full(x, u, rotor_speed=np.full(4, P.n_hover))
    assert np.max(np.abs(one.x - nominal)) > 1e-7  # the effect changes the motion


def test_zero_coefficients_are_the_nominal_simulator():
    x, u = moving_state(), HOVER * 1.1
    np.testing.assert_array_equal(Simulator(P, Fidelity()).step(x, u), Simulator(P).step(x, u))


def test_motor_lag_approaches_commanded_speed():
    s = Simulator(P, Fidelity(motor_tau=0.03))
    u = HOVER * 1.2
    n = np.full(4, P.n_hover)
    x = np.zeros(12)
    for _ in range(30):  # 0.3 s = 10 time constants
        r = s.step_full(x, u, rotor_speed=n)
        x, n = r.x, r.rotor_speed
    np.testing.assert_allclose(n, np.sqrt(1.2) * P.n_hover, rtol=TOL["motor_lag_settled"])


def test_rotor_drag_opposes_horizontal_body_velocity():
    x = np.zeros(12)
    x[9] = 3.0
    s = Simulator(P, Fidelity(rotor_drag=1.2e-3))
    dv_extra = s.step(x, HOVER)[9] - Simulator(P).step(x, HOVER)[9]
    expected = -1.2e-3 * 4 * P.n_hover * 3.0 / P.m * s.dt  # force / m over one period
    np.testing.assert_allclose(dv_extra, expected, rtol=TOL["rotor_drag"])


def test_payload_and_wind_change_the_acceleration():
    x = np.zeros(12)
    heavy = Simulator(P, payload_kg=0.2 * P.m).step(x, HOVER)
    # Hover thrust with 20 % more mass: vz' = g (1 - 1/1.2).
    np.testing.assert_allclose(heavy[11], P.g * (1 - 1 / 1.2) * 0.01, rtol=TOL["one_period_acceleration"])
    windy = Simulator(P, wind=lambda t: np.array([0.5, 0.0, 0.0])).step(x, HOVER)
    np.testing.assert_allclose(windy[9], 0.5 * 0.01, rtol=TOL["one_period_acceleration"])


def test_measure_adds_stated_noise(rng):
    x = np.zeros((20000, 12))
    y = Simulator(P).measure(x, rng)
    np.testing.assert_allclose(np.std(y, axis=0), NoiseModel().state_std, rtol=TOL["noise_std"])


@pytest.mark.parametrize("call,arg", [
    (lambda: dynamics(np.zeros(11), np.zeros(4)), "x"),
    (lambda: dynamics(np.zeros(12), np.zeros((2, 3))), "u"),
    (lambda: Simulator().step(np.zeros((5, 12)), np.zeros((5, 5))), "u"),
    (lambda: Simulator().step(np.zeros((5, 12)), np.zeros((4, 4))), "batch"),
    (lambda: Simulator().step(np.full(12, np.nan), HOVER), "x"),
    (lambda: Simulator().step(np.zeros(12), [np.inf, 0, 0, 0]), "u"),
    (lambda: dynamics(np.zeros(12), "abc"), "u"),
    (lambda: Simulator(dt=-0.01), "dt"),
    (lambda: Simulator(payload_kg=-1.0), "payload_kg"),
    (lambda: Simulator(fidelity="high"), "fidelity"),
    (lambda: Simulator(wind=lambda t: [1.0, 2.0]).step(np.zeros(12), HOVER), "wind"),
])
def test_bad_input_raises_value_error_naming_the_argument(call, arg):
    with pytest.raises(ValueError, match=arg):
        call()


def test_high_fidelity_preset_has_every_effect():
    assert HIGH_FIDELITY.motor_tau > 0 and HIGH_FIDELITY.rotor_drag > 0 and HIGH_FIDELITY.rotor_gyro > 0
    assert Fidelity().is_nominal and not HIGH_FIDELITY.is_nominal


@pytest.mark.parametrize("payload, wind", [(0.0, None), (0.013, lambda t: np.array([0.4, -0.2, 0.1]) * (1 + t))])
def test_one_vehicle_steps_like_a_batch_of_one(payload, wind):
    # A single state takes the compiled CasADi form of the RK4 step; it must equal the numpy batch path.
    rng = np.random.default_rng(5)
    sim = Simulator(payload_kg=payload, wind=wind)
    for _ in range(20):
        x = rng.normal(size=12) * np.array([1, 1, 1, 0.5, 0.5, 1, 2, 2, 2, 2, 2, 2])
        u = np.array([0.6, 1e-3, -1e-3, 5e-4]) + rng.normal(size=4) * np.array([0.1, 1e-3, 1e-3, 5e-4])
        one = sim.step_full(x, u, t=0.37)
        batch = sim.step_full(x[None], u[None], t=0.37)
        np.testing.assert_allclose(one.x, batch.x[0], rtol=0, atol=TOL["single_vs_batch"])
        np.testing.assert_array_equal(one.wrench, batch.wrench[0])
        np.testing.assert_array_equal(one.rotor_speed, batch.rotor_speed[0])


@pytest.mark.parametrize("fidelity", ["high", "motor-lag", "rotor-drag", "rotor-gyro"])
@pytest.mark.parametrize("payload, wind", [(0.0, None), (0.013, lambda t: np.array([0.4, -0.2, 0.1]) * (1 + t))])
def test_one_vehicle_steps_like_a_batch_of_one_with_high_fidelity(fidelity, payload, wind):
    # The high-fidelity effects too: one state goes through their CasADi form, a batch through numpy; with motor
    # lag the rotors start away from the command (as they do between periods) and must end where numpy's end.
    from sim.params import FIDELITIES
    from sim.vehicles.rotors import realize

    rng = np.random.default_rng(7)
    sim = Simulator(fidelity=FIDELITIES[fidelity], payload_kg=payload, wind=wind)
    saturated = 0
    for _ in range(40):
        x = rng.normal(size=12) * np.array([1, 1, 1, 0.3, 0.3, 1, 3, 3, 3, 2, 2, 2])
        u = HOVER + rng.normal(size=4) * np.array([0.5, 2e-3, 2e-3, 1e-3])
        n0 = np.sqrt(realize(u, P).n_sq) * (1.0 + 0.2 * rng.normal(size=4))
        one = sim.step_full(x, u, rotor_speed=n0, t=0.37)
        batch = sim.step_full(x[None], u[None], rotor_speed=n0[None], t=0.37)
        np.testing.assert_allclose(one.x, batch.x[0], rtol=TOL["single_vs_batch"], atol=TOL["single_vs_batch"])
        np.testing.assert_allclose(one.rotor_speed, batch.rotor_speed[0], rtol=TOL["single_vs_batch"], atol=0)
        np.testing.assert_allclose(one.wrench, batch.wrench[0], rtol=TOL["single_vs_batch"], atol=1e-15)
        np.testing.assert_array_equal(one.saturated, batch.saturated[0])
        saturated += bool(one.saturated.any())
    assert saturated > 0     # saturating commands are among the cases
