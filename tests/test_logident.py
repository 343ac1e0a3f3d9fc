"""Real-flight identification and the benchmark's prediction protocol, on flights with known answers."""

import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from sim import NoiseModel
from sim.identification.excitation import make_dataset
from sim.files import json_ready
from sim.flightlogs.logbench import (HORIZONS, ctbr_inputs, ctbr_physics_step, physics_step,
                                     prediction_errors, rotation_angle)
from sim.flightlogs.attitudeloop import AttitudeLoop, heading_velocity
from sim.flightlogs.logident import _bounds, fisher_table, fit_attitude_loop, identify
from sim.params import DT
from sim.vehicles.rotors import wrench_from_rotor_sq
from sim.vehicles.vehicle import load_vehicle

# tolerances of this module
EXACT = 1e-9          # the plant's own equations predict its noise-free flight (RK4, same substeps)
RATIO_RTOL = 2e-3     # identified ratios against the true ones (forward differences bias them by O(dt))
SCALE_TOL = 1e-6      # the Fisher information's null direction against the common scale
GAIN_TOL_M = 1e-4     # h=50 position error of the identified physics on a wrench logged with a 10 % wrong kt
JACKKNIFE_RTOL = 1e-6 # interval half-width against the jackknife recomputed from refits (normal equations vs lstsq)
BOUND_RTOL = 1e-9    # Cramer-Rao bounds against the inverse computed directly
CTBR_EXACT = 1e-12    # a ctbr model predicts a flight it generated itself (same RK4)
CTBR_H1_M = 1e-5      # the plant's own equations at ctbr, given the achieved rates: position error after one period, m
T95 = {3: 3.18}       # Student t, two-sided 95 %, by degrees of freedom (4 flights)
LOOP_EXACT = 1e-8     # the attitude loop's roll against the damped oscillator's closed form (RK4, 10 substeps), rad
LOOP_RTOL = 0.02      # fitted attitude-loop coefficients against those that made the flights (measured 0.6 %)


def _flights(ds):
    """The dataset's trajectories as imported flights: every sample measured, no delay."""
    out = []
    for i in range(ds.n_traj):
        x = np.concatenate([ds.x[i], ds.x_next[i, -1:]])
        n = np.concatenate([ds.rotor_speed[i], ds.rotor_speed[i, -1:]])
        ok = np.ones(len(x), dtype=bool)
        out.append(SimpleNamespace(name=f"f{i}", x=x, rotor_speed=n, u=np.concatenate([ds.wrench[i], ds.wrench[i, -1:]]),
                                   x_ok=ok, rotor_ok=ok, report=SimpleNamespace(delay_samples=0)))
    return out


@pytest.fixture(scope="module")
def crazyflie_flights():
    vehicle = load_vehicle("crazyflie")
    ds = make_dataset("small", 4, 8.0, 5, noise=NoiseModel.none(), vehicle=vehicle)
    return vehicle, _flights(ds)


@pytest.fixture(scope="module")
def noisy_flights():
    """The same flights with the stated measurement noise (the Fisher information needs residuals of a real size)."""
    vehicle = load_vehicle("crazyflie")
    return vehicle, _flights(make_dataset("small", 4, 8.0, 5, noise=NoiseModel(), vehicle=vehicle))


def test_rotation_angle_of_a_known_rotation():
    e0 = np.array([[0.1, -0.2, 0.3]])
    e1 = e0 + np.array([[0.0, 0.0, 0.25]])          # 0.25 rad more yaw: a rotation of 0.25 rad about world z
    assert rotation_angle(e1, e0)[0] == pytest.approx(0.25, abs=1e-12)
    assert rotation_angle(e0, e0)[0] == pytest.approx(0.0, abs=1e-7)


def test_the_true_equations_predict_the_plants_flight_exactly(crazyflie_flights):
    vehicle, flights = crazyflie_flights
    e = prediction_errors(physics_step(vehicle.params), flights)
    for q in ("position", "velocity", "rotation", "angular_velocity"):
        assert max(getattr(e, q)) <= EXACT, q
    assert e.windows[0] == sum(len(f.x) - max(HORIZONS) for f in flights)


def test_holding_the_state_gives_the_mean_displacement(crazyflie_flights):
    """A model that predicts no motion errs by exactly the logged displacement over h steps."""
    _, flights = crazyflie_flights
    e = prediction_errors(lambda x, u: x, flights)
    H = max(HORIZONS)
    for j, h in enumerate(HORIZONS):
        d = np.concatenate([np.linalg.norm(f.x[h:len(f.x) - H + h, 0:3] - f.x[:len(f.x) - H, 0:3], axis=1)
                            for f in flights])
        assert e.position[j] == pytest.approx(d.mean(), rel=1e-12)


def test_identified_ratios_are_the_vehicles(crazyflie_flights):
    vehicle, flights = crazyflie_flights
    ident = identify(flights, vehicle)
    assert ident.value("kt/m") == pytest.approx(vehicle.kt / vehicle.m, rel=RATIO_RTOL)
    assert ident.value("kt/Jxx") == pytest.approx(vehicle.kt / vehicle.Jxx, rel=RATIO_RTOL)
    assert ident.value("kt/Jyy") == pytest.approx(vehicle.kt / vehicle.Jyy, rel=RATIO_RTOL)
    assert ident.value("kq/Jzz") == pytest.approx(vehicle.kq / vehicle.Jzz, rel=RATIO_RTOL)
    for c in ("k_x", "k_y", "k_z"):                 # the plant has no drag (c_d = 0 for this vehicle)
        assert abs(ident.value(c)) < 1e-2
    # with the midpoint regressors the equations hold to second order in the period (x and y carry no force at all)
    assert min(ident.explained[e] for e in ("a_z", "p_dot", "q_dot", "r_dot")) > 1 - 1e-6
    assert all(len(c.per_flight) == 4 for c in ident.coefficients.values())


def test_each_interval_is_the_jackknife_over_flights_around_the_pooled_value(noisy_flights):
    """Every coefficient's interval holds its own pooled value (an interval of the per-flight mean once showed a
    value outside it), and its half-width is t(n - 1) times the jackknife standard error of the pooled fit with each
    flight left out in turn, computed here by fitting every subset again."""
    vehicle, flights = noisy_flights
    ident = identify(flights, vehicle)
    n = len(flights)
    loo = [identify(flights[:i] + flights[i + 1:], vehicle) for i in range(n)]
    for name, c in ident.coefficients.items():
        assert c.low <= c.value <= c.high, name
        vals = np.array([r.value(name) for r in loo])
        se = np.sqrt((n - 1) / n * np.sum((vals - vals.mean()) ** 2))
        assert (c.high - c.low) / 2 == pytest.approx(T95[n - 1] * se, rel=JACKKNIFE_RTOL), name
        assert c.value == pytest.approx((c.high + c.low) / 2, rel=JACKKNIFE_RTOL, abs=1e-300)
    one = identify(flights[:1], vehicle).coefficients["kt/m"]
    assert np.isnan(one.low) and np.isnan(one.high)


def test_fisher_information_has_the_common_scale_as_its_null_direction(noisy_flights):
    vehicle, flights = noisy_flights
    table = fisher_table(flights, vehicle, identify(flights, vehicle))
    ev = table["eigenvalues"]
    assert abs(ev[0]) <= 1e-9 * ev[-1]
    assert np.allclose(table["weakest_direction"], 1 / np.sqrt(6), atol=SCALE_TOL)
    assert all(v > 0 for v in table["crlb_relative_with_m_fixed"].values())


def test_a_parameter_the_information_does_not_see_has_no_finite_bound():
    """On a positive-definite information the bounds are the square roots of the inverse's diagonal; with a
    parameter it holds no information about, that one is unbounded and the others are the bounds of the rest."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 5))
    info = a @ a.T + 0.1 * np.eye(5)
    assert np.allclose(_bounds(info), np.sqrt(np.diag(np.linalg.inv(info))), rtol=BOUND_RTOL, atol=0)
    info[2, :] = info[:, 2] = 0.0
    b = _bounds(info)
    rest = np.delete(np.delete(info, 2, 0), 2, 1)
    assert np.isinf(b[2])
    assert np.allclose(np.delete(b, 2), np.sqrt(np.diag(np.linalg.inv(rest))), rtol=BOUND_RTOL, atol=0)


def test_flights_without_a_torque_leave_the_inertias_unbounded_instead_of_a_traceback(noisy_flights):
    """Flights whose four rotors always turn alike (same total thrust, no torque) once stopped the Fisher table
    with 'Singular matrix'. The inertias and kq have no bound then; kt keeps the bound the z equation gives it,
    which is the whole of its bound in the excited flights too (there kt/Jxx leaves kt to the z equation)."""
    vehicle, flights = noisy_flights
    level = [SimpleNamespace(**{**vars(f), "rotor_speed": np.repeat(
        np.sqrt((f.rotor_speed ** 2).mean(axis=1, keepdims=True)), 4, axis=1)}) for f in flights]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bound = fisher_table(level, vehicle, identify(level, vehicle))["crlb_relative_with_m_fixed"]
    excited = fisher_table(flights, vehicle, identify(flights, vehicle))["crlb_relative_with_m_fixed"]
    assert all(np.isinf(bound[p]) for p in ("Jxx", "Jyy", "Jzz", "kq"))
    assert bound["kt"] == pytest.approx(excited["kt"], rel=BOUND_RTOL)
    assert json_ready(bound)["Jxx"] is None


def test_the_wrench_of_the_flights_is_the_rotor_speeds_through_the_mixer(crazyflie_flights):
    """The helper's flights are consistent: u is the wrench of the logged rotor speeds (so the identification sees
    the same rotor speeds that flew)."""
    vehicle, flights = crazyflie_flights
    f = flights[0]
    assert np.allclose(wrench_from_rotor_sq(f.rotor_speed ** 2, vehicle.params), f.u, rtol=1e-12, atol=1e-15)
    assert DT == 0.01


def test_identified_physics_rescales_a_wrench_logged_with_a_wrong_thrust_coefficient(crazyflie_flights):
    """The wrench of a log is computed with the vehicle file's kt: when the file's kt is 10 % off, the identified
    model rescales it (``wrench_gain``) and predicts the flight as the true equations do, while the file's kt
    inside the same equations errs by the 10 %."""
    from sim.flightlogs.logident import identified_model

    vehicle, flights = crazyflie_flights
    wrong = vehicle.replace(kt=1.1 * vehicle.kt)
    logged = [SimpleNamespace(**{**vars(f), "u": f.u * np.array([1.1, 1.1, 1.1, 1.0])}) for f in flights]
    kw = identified_model(identify(logged, wrong), wrong, hold_rates=False)
    assert kw["wrench_gain"][0] == pytest.approx(1 / 1.1, rel=RATIO_RTOL)
    good = prediction_errors(physics_step(**kw), logged)
    bad = prediction_errors(physics_step(**{**kw, "wrench_gain": (1.0, 1.0, 1.0, 1.0)}), logged)
    assert good.position[-1] < GAIN_TOL_M < 0.1 * bad.position[-1]


def _ctbr_flight(step, n=400, seed=3):
    """A flight generated by a ctbr ``step`` from smooth thrust and rate commands: the rates reached at each
    period's end are the commanded ones, so the log's next-sample rates are the commands."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    phase = rng.uniform(0, 2 * np.pi, 4)
    cmd = np.stack([0.30 + 0.05 * np.sin(2.1 * t + phase[0])] + [0.8 * np.sin(f * t + ph)
                   for f, ph in zip((3.0, 2.3, 1.1), phase[1:])], -1)
    x = np.zeros((n + 1, 12))
    x[0, 2] = -1.0
    for k in range(n):
        x[k + 1] = step(x[k:k + 1], cmd[k:k + 1])[0]
    u = np.concatenate([cmd, cmd[-1:]])
    u[:, 1:] = 0.0                  # a log's torques: not what a ctbr model reads
    ok = np.ones(n + 1, dtype=bool)
    return SimpleNamespace(name="ctbr", x=x, u=u, x_ok=ok, rotor_ok=ok), cmd


def test_a_ctbr_model_predicts_the_flight_it_generated_and_the_inputs_are_aligned():
    """The thrust and the next sample's rates are the inputs: with the generating parameters (drags, bias, a thrust
    gain) every error is rounding; the rates of the same sample instead (one period late) are not."""
    vehicle = load_vehicle("crazyflie")
    kw = dict(p=vehicle.params, linear_drag=(0.3, 0.35, 0.1), quadratic_drag=(0.02, 0.02, 0.05),
              accel_bias=(0.05, -0.03, 0.2), thrust_gain=1.07)
    step = ctbr_physics_step(**kw)
    flight, cmd = _ctbr_flight(step)
    u = ctbr_inputs(flight)
    np.testing.assert_array_equal(u[:-1], np.c_[cmd[:, :1], flight.x[1:, 6:9]])
    aligned = SimpleNamespace(**{**vars(flight), "u": u})
    e = prediction_errors(step, [aligned])
    for q in ("position", "velocity", "rotation", "angular_velocity"):
        assert max(getattr(e, q)) <= CTBR_EXACT, (q, getattr(e, q))
    late = u.copy()
    late[:, 1:] = flight.x[:, 6:9]
    e_late = prediction_errors(step, [SimpleNamespace(**{**vars(flight), "u": late})])
    assert e_late.angular_velocity[0] > 1e3 * CTBR_EXACT and e_late.position[-1] > 1e3 * CTBR_EXACT


def test_at_ctbr_the_plants_equations_are_given_the_rates_it_reached(crazyflie_flights):
    vehicle, flights = crazyflie_flights
    at_ctbr = [SimpleNamespace(**{**vars(f), "u": ctbr_inputs(f)}) for f in flights]
    e = prediction_errors(ctbr_physics_step(vehicle.params), at_ctbr)
    assert max(e.angular_velocity) <= EXACT
    assert e.position[0] <= CTBR_H1_M, e.position


def test_the_attitude_loop_rolls_as_a_damped_oscillator_about_its_held_setpoint():
    """Roll alone (no pitch, yaw, torque or velocity loop): phi'' = -D phi' - K (phi - phi_sp), in closed form."""
    p = load_vehicle("crazyflie").params
    D, K, lead = 3.0, 40.0, 0.05
    loop = AttitudeLoop(damping=(D, 1.0, 1.0), stiffness=(K, 10.0), lead=lead, torque_gain=(0.0, 0.0, 0.0))
    x0 = np.zeros((1, 12))
    x0[0, 3], x0[0, 6] = 0.2, -0.5
    z = loop.start(x0)
    assert z.shape == (1, 16) and z[0, 12] == pytest.approx(0.2 - 0.5 * lead, abs=1e-15)
    step = physics_step(p, attitude_loop=loop)
    u = np.array([[p.m * 9.81, 0.0, 0.0, 0.0]])
    for _ in range(50):
        z = step(z, u)
    sp, a, w = 0.2 - 0.5 * lead, 0.5 * lead, np.sqrt(K - D * D / 4)
    t = 50 * DT                                          # phi - sp = e^{-D t / 2} (a cos wt + (phi'0 + D a / 2)/w sin wt)
    phi = sp + np.exp(-D * t / 2) * (a * np.cos(w * t) + (-0.5 + D * a / 2) / w * np.sin(w * t))
    assert z[0, 3] == pytest.approx(phi, abs=LOOP_EXACT)
    assert np.abs(z[0, [4, 5, 7, 8]]).max() == 0.0       # nothing turned pitch or yaw


def test_an_attitude_loop_with_no_loop_is_the_rigid_body(crazyflie_flights):
    """No damping, stiffness, bias or velocity gain and torque gains of 1: Euler's equations, state for state."""
    vehicle, flights = crazyflie_flights
    f = flights[0]
    loop = AttitudeLoop(lead=0.3)                        # the setpoint it starts from is then never used
    plain = physics_step(vehicle.params)(f.x[:200], f.u[:200])
    looped = physics_step(vehicle.params, attitude_loop=loop)(loop.start(f.x[:200]), f.u[:200])
    assert np.abs(looped[:, :12] - plain).max() <= EXACT
    assert np.array_equal(looped[:, 12:], loop.start(f.x[:200])[:, 12:])    # the extra states are held


def test_the_attitude_loops_velocity_loop_pitches_up_against_a_forward_gain_in_speed():
    """Facing east (yaw pi/2), a world velocity to the north is to the left; a gain in forward speed since the
    window's start pulls the pitch setpoint up (FRD: nose up brakes), one to the right rolls the setpoint left."""
    x = np.zeros((1, 16))
    x[0, 5], x[0, 9] = np.pi / 2, 1.0
    assert heading_velocity(x)[0] == pytest.approx([0.0, -1.0], abs=1e-15)
    loop = AttitudeLoop(stiffness=(10.0, 20.0), velocity_gain=0.1, torque_gain=(0.0, 0.0, 0.0))
    fwd = np.zeros((1, 16))
    fwd[0, 9] = 1.0                                       # yaw 0: north is forward; the start velocity is 0
    assert loop.angular_acceleration(fwd, np.zeros((1, 3)), np.ones(3))[0] == pytest.approx([0.0, 20.0 * 0.1, 0.0])
    right = np.zeros((1, 16))
    right[0, 10] = 1.0
    assert loop.angular_acceleration(right, np.zeros((1, 3)), np.ones(3))[0] == pytest.approx([-10.0 * 0.1, 0.0, 0.0])


def test_the_attitude_loop_fit_recovers_the_loop_that_made_the_flights():
    """Flights of one 50-step window each, made by a known loop (so each window's held setpoint is the one the
    model assumes): the fit from its default start recovers every coefficient."""
    p = load_vehicle("crazyflie").params
    true = AttitudeLoop(damping=(3.0, 4.0, 6.0), stiffness=(20.0, 15.0), lead=-0.1, torque_gain=(0.3, 0.2, 1.5),
                        bias=(0.2, -0.1, 0.05), velocity_gain=0.08)
    rng = np.random.default_rng(0)
    step = physics_step(p, substeps=1, attitude_loop=true)
    flights = []
    for _ in range(20):
        x = np.zeros(12)
        x[3:5], x[5] = rng.normal(0, 0.1, 2), rng.uniform(-3, 3)
        x[6:9], x[9:12] = rng.normal(0, 0.5, 3), rng.normal(0, 1.0, 3)
        u = np.zeros((51, 4))
        u[:, 0] = p.m * 9.81 * (1 + 0.1 * rng.normal(size=51))
        u[:, 1:4] = 5.0 * rng.normal(size=(51, 3)) * np.array([p.Jxx, p.Jyy, p.Jzz])
        z, xs = true.start(x[None]), [x]
        for k in range(50):
            z = step(z, u[k:k + 1])
            xs.append(z[0, :12])
        flights.append(SimpleNamespace(x=np.array(xs), u=u, x_ok=np.ones(51, dtype=bool)))
    fit = fit_attitude_loop(flights, {"p": p}, stride=1)
    assert fit.windows == 20 and fit.converged
    assert fit.cost < 1e-4 * fit.initial_cost
    assert fit.loop.vector() == pytest.approx(true.vector(), rel=LOOP_RTOL, abs=1e-3)
