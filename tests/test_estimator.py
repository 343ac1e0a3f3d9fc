"""The extended Kalman filter: known disturbances and actuator states recovered, exact seeded reruns, clear errors."""

import numpy as np
import pytest

from mpc.errors import ConfigurationError
from mpc.estimators.estimator import DisturbanceEKF, EKFConfig, euler_rate_matrix
from mpc.prediction.models import AnalyticModel
from scenarios.errors import ScenarioError
from scenarios.closed_loop.runner import RunSpec, fly
from sim.params import DT
from sim.plants.plant import SimPlant
from sim.plants.sensors import ImuConfig, MocapConfig, SensedPlant, SensorSuite
from sim.vehicles.vehicle import load_vehicle

#: Tolerances of this module.
TOL = {
    "wind": 0.03,           # m/s^2: a constant wind, the estimate's mean over the last 2 s of 4
    "torque": 0.3,          # rad/s^2: no torque disturbance, estimated near zero
    "rotor_rel": 2e-3,      # relative error of the estimated rotor speeds after 1 s, started 5 % off
    "bias": 1e-3,           # rad/s: the gyroscope bias after 4 s
    "accel_bias": 0.02,     # m/s^2: the accelerometer bias after 4 s (told from the wind by motion capture)
    "euler_fd": 1e-6,       # W(eta) against finite differences of the rotation
    "nees_prob": 0.95,      # the chi-square band of the time-averaged NEES
    "highfi_rmse": 2e-3,    # m: the high-fidelity oracle (rotor speeds estimated) on figure8-fast+highfi
}

#: Seeded oracle flights of the consistency test.
NEES_FLIGHTS = 20

HOVER = np.array([0.0, 0.0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0])


def _fly_open_loop(model, plant, suite, ekf, u, seconds, x0=HOVER, guess=None):
    """Fly ``u`` held for ``seconds``; the sensed plant, the last estimate and every estimate's disturbance."""
    sp = SensedPlant(plant, suite)
    sp.reset(x0)
    est = ekf.step(suite.read(0.0), 0.0, guess=guess)
    d = []
    for k in range(int(round(seconds / DT))):
        sp.advance(u, DT)
        est = ekf.step(suite.read(sp.t), sp.t, u)
        d.append(est.disturbance)
    return sp, est, np.array(d)


def test_a_constant_wind_and_the_gyro_bias_are_estimated():
    v = load_vehicle(None)
    wind = np.array([0.3, -0.2, 0.1])
    plant = SimPlant(v, wind=lambda t: wind)
    suite = SensorSuite(rng=np.random.default_rng(0))
    model = AnalyticModel(v.params)
    ekf = DisturbanceEKF(model, suite.mocap, suite.imu)
    _, est, d = _fly_open_loop(model, plant, suite, ekf, plant.hover_input, 4.0)
    # The estimate wanders about the truth (its random walk); its mean over the last 2 s is the wind.
    np.testing.assert_allclose(d[200:, 0:3].mean(axis=0), wind, atol=TOL["wind"])
    np.testing.assert_allclose(d[200:, 3:6].mean(axis=0), 0.0, atol=TOL["torque"])
    np.testing.assert_allclose(est.gyro_bias, suite.gyro_bias, atol=TOL["bias"])
    np.testing.assert_allclose(est.accel_bias, suite.accel_bias, atol=TOL["accel_bias"])


def test_the_rotor_speeds_of_a_lagging_motor_are_estimated():
    from mpc.prediction.extended import extra_equilibrium

    v = load_vehicle(None)
    plant = SimPlant(v, fidelity=v.fidelity)
    suite = SensorSuite(rng=np.random.default_rng(1))
    model = AnalyticModel(v.params, fidelity=v.fidelity)
    u_hover = plant.hover_input

    def start(x):
        return 1.05 * extra_equilibrium(model, x[None], u_hover[None])[0]     # 5 % off

    ekf = DisturbanceEKF(model, suite.mocap, suite.imu, extra_start=start)
    u = u_hover * np.array([1.1, 1.0, 1.0, 1.0]) + np.array([0.0, 2e-4, -1e-4, 0.0])
    sp, est, _ = _fly_open_loop(model, plant, suite, ekf, u, 1.0)
    truth = sp.plant._n
    np.testing.assert_allclose(est.x[12:], truth, rtol=TOL["rotor_rel"])


@pytest.mark.slow
def test_seeded_flights_with_the_estimator_are_exactly_equal():
    a = fly(RunSpec("hover", "lqr", "oracle", estimator="ekf"))[1]
    b = fly(RunSpec("hover", "lqr", "oracle", estimator="ekf"))[1]
    for name in ("x", "x_estimate", "disturbance", "nees"):
        np.testing.assert_array_equal(a[name], b[name])


def test_the_controller_sees_the_estimate_and_the_clock_charges_the_filter():
    r, tr = fly(RunSpec("figure8-fast", "sqp", "oracle", timing="realtime", estimator="ekf"))
    called = tr["called"]
    np.testing.assert_array_equal(tr["x_measured"][called], tr["x_estimate"][called][:, :12])
    assert np.all(tr["latency_s"][called] >= tr["estimator_s"][called])
    assert r["estimator"] == "ekf" and r["estimator_ms"]["median"] > 0.0
    assert r["run_id"] == "figure8-fast__sqp__oracle__ekf__realtime"


@pytest.mark.slow
def test_a_model_with_actuator_states_flies_on_its_estimate():
    """The high-fidelity oracle's controllers get its 16-state estimate (rotor speeds included) and track."""
    r, tr = fly(RunSpec("figure8-fast+highfi", "sqp", "oracle", estimator="ekf"))
    assert tr["x_estimate"].shape[1] == 16
    assert not r["crashed"] and r["rmse_position_m"] < TOL["highfi_rmse"], r["rmse_position_m"]


def test_euler_rate_matrix_against_finite_differences():
    from sim.equations.dynamics import rotation_matrix

    eta = np.array([0.3, -0.4, 1.2])
    omega = np.array([0.5, -0.2, 0.8])
    h = 1e-7
    R = rotation_matrix(*eta)
    R_next = R @ (np.eye(3) + h * np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]],
                                             [-omega[1], omega[0], 0]]))
    # Euler angles of R_next (ZYX)
    phi = np.arctan2(R_next[2, 1], R_next[2, 2])
    theta = -np.arcsin(R_next[2, 0])
    psi = np.arctan2(R_next[1, 0], R_next[0, 0])
    fd = (np.array([phi, theta, psi]) - eta) / h
    np.testing.assert_allclose(euler_rate_matrix(eta) @ omega, fd, atol=TOL["euler_fd"])


def test_bad_estimator_set_ups_get_one_line_errors():
    v = load_vehicle(None)
    with pytest.raises(ConfigurationError, match="motion capture"):
        DisturbanceEKF(AnalyticModel(v.params), None, ImuConfig())
    with pytest.raises(ConfigurationError, match="extra_start"):
        DisturbanceEKF(AnalyticModel(v.params, fidelity=v.fidelity), MocapConfig(), ImuConfig())
    with pytest.raises(ConfigurationError, match="force_walk"):
        EKFConfig(force_walk=-1.0)
    with pytest.raises(ScenarioError, match="estimator must be one of none, ekf"):
        RunSpec("hover", "lqr", "oracle", estimator="kalman")
    ekf = DisturbanceEKF(AnalyticModel(v.params), MocapConfig(latency_s=0.02), None)
    from sim.plants.sensors import Readings

    with pytest.raises(ConfigurationError, match="no motion-capture sample"):
        ekf.step(Readings.empty(), 0.0)


def integrated_autocorrelation_time(x: np.ndarray, cutoff: float = 0.05) -> float:
    """``1 + 2 sum rho_k`` over the lags until the autocorrelation ``rho_k`` first falls below ``cutoff``."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    n = len(x)
    c = np.correlate(x, x, "full")[n - 1:] / np.arange(n, 0, -1)
    rho = c / c[0]
    tau = 1.0
    for k in range(1, n // 4):
        if rho[k] < cutoff:
            break
        tau += 2.0 * rho[k]
    return tau


@pytest.mark.slow
def test_the_filter_is_consistent_on_the_plant_its_model_is_exact_for():
    """Time-averaged NEES of the 12 rigid-body states over 20 seeded oracle flights on the nominal plant.

    The flights have no disturbance and the model is exact, so the filter's noise model matches them with its
    disturbance walks and its model-error noise at zero. Consecutive NEES values are correlated: the band is the
    chi-square band of N K_eff n degrees of freedom, K_eff = K / tau with tau the NEES series' integrated
    autocorrelation time (Bar-Shalom's time-average test with the samples counted honestly).
    """
    from scipy.stats import chi2

    cfg = EKFConfig(force_walk=0.0, torque_walk=0.0, position=0.0, attitude=0.0, rate=0.0, velocity=0.0)
    series = np.array([fly(RunSpec("figure8-fast", "lqr", "oracle", seed=s, estimator="ekf"), ekf_config=cfg)[1]
                       ["nees"] for s in range(NEES_FLIGHTS)])
    n, (N, K) = 12, series.shape
    tau = float(np.mean([integrated_autocorrelation_time(e) for e in series]))
    dof = N * (K / tau) * n
    a = (1.0 - TOL["nees_prob"]) / 2.0
    lo, hi = chi2.ppf(a, dof) * n / dof, chi2.ppf(1.0 - a, dof) * n / dof
    mean = float(series.mean())
    print(f"time-averaged NEES {mean:.3f} (n = 12), 95 % band {lo:.3f}-{hi:.3f} (tau {tau:.1f} periods)")
    assert lo <= mean <= hi, (mean, lo, hi)
