"""Sensors: the IMU reads what a real one reads, motion capture arrives exactly its latency late, seeded reruns agree."""

import dataclasses

import numpy as np
import pytest

from sim.errors import SimInputError
from sim.params import DT
from sim.plants import make_plant
from sim.sensors import ImuConfig, MocapConfig, SensedPlant, SensorSuite, specific_force, wrap_angle

#: Tolerances of this module.
TOL = {
    "accel_sim": 1e-9,          # m/s^2: the reference simulator at hover (exact equilibrium)
    "accel_rotorpy": 1e-6,      # m/s^2: RotorPy at hover (its integrator's tolerance)
    "free_fall": 1e-9,          # m/s^2: no drag, no thrust
    "thrust": 1e-6,             # m/s^2: tilted, hover thrust, first millisecond
    "gyro": 0.0,                # noise-free gyro: the true rates exactly
    "walk_rel": 0.1,            # relative error of the bias random walk's measured standard deviation
}

QUIET_IMU = ImuConfig(gyro_std=0.0, gyro_bias_std=0.0, gyro_bias_walk=0.0, accel_std=0.0, accel_bias_std=0.0,
                      accel_bias_walk=0.0)
HOVER = np.array([0.0, 0.0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0])


def _plant(name):
    if name.startswith("rotorpy"):
        pytest.importorskip("rotorpy")
    return make_plant(name)


@pytest.mark.parametrize("name,tol", [("sim", TOL["accel_sim"]), ("rotorpy", TOL["accel_rotorpy"]),
                                      ("rotorpy-ideal", TOL["accel_rotorpy"])])
def test_accelerometer_reads_minus_g_along_body_z_at_hover(name, tol):
    plant = _plant(name)
    suite = SensorSuite(mocap=None, imu=QUIET_IMU, rng=np.random.default_rng(0))
    sp = SensedPlant(plant, suite)
    sp.reset(HOVER)
    for _ in range(5):
        sp.advance(plant.hover_input, DT)
    r = suite.read(sp.t)
    g = plant.vehicle.params.g
    assert len(r.accel) == 50
    np.testing.assert_allclose(r.accel, np.tile([0.0, 0.0, -g], (50, 1)), rtol=0, atol=tol)
    np.testing.assert_allclose(r.gyro, 0.0, atol=tol)


def test_accelerometer_in_free_fall_reads_zero_and_under_thrust_reads_thrust_over_mass():
    from sim.vehicle import load_vehicle

    v = load_vehicle(None)
    v = dataclasses.replace(v, c_d=0.0)
    plant = make_plant("sim", v)
    suite = SensorSuite(mocap=None, imu=QUIET_IMU, rng=np.random.default_rng(0))
    sp = SensedPlant(plant, suite)
    x0 = HOVER.copy()
    x0[3:6] = [0.3, -0.2, 1.0]
    sp.reset(x0)
    sp.advance(np.zeros(4), DT)
    np.testing.assert_allclose(suite.read(sp.t).accel, 0.0, atol=TOL["free_fall"])
    # Tilted with the hover thrust, no drag: the specific force is the thrust per mass along -z (body), whatever
    # the attitude; the first tick, before the rates build up.
    sp.reset(x0)
    T = plant.hover_input[0]
    sp.advance(np.array([T, 0.0, 0.0, 0.0]), 0.001)
    np.testing.assert_allclose(suite.read(sp.t).accel[0], [0.0, 0.0, -T / v.params.m], atol=TOL["thrust"])


def test_gyro_reads_true_rates_and_bias_walk_has_its_configured_spread():
    plant = make_plant("sim")
    suite = SensorSuite(mocap=None, imu=QUIET_IMU, rng=np.random.default_rng(1))
    sp = SensedPlant(plant, suite)
    x0 = HOVER.copy()
    x0[6:9] = [0.2, -0.1, 0.05]
    sp.reset(x0)
    rates = []
    for _ in range(3):
        for _ in range(10):
            sp.advance(plant.hover_input, 0.001)
            rates.append(sp.x[6:9].copy())
    np.testing.assert_allclose(suite.read(sp.t).gyro, np.array(rates), rtol=0, atol=TOL["gyro"])
    # The bias: a random walk of 1e-3 rad/s per sqrt(s), seen through a noise-free gyro at rest.
    imu = dataclasses.replace(QUIET_IMU, gyro_bias_walk=1e-3)
    suite = SensorSuite(mocap=None, imu=imu, rng=np.random.default_rng(2))
    sp = SensedPlant(make_plant("sim"), suite)
    sp.reset(HOVER)
    for _ in range(200):
        sp.advance(sp.hover_input, DT)
    steps = np.diff(suite.read(sp.t).gyro, axis=0)
    measured = steps.std() / np.sqrt(1e-3)
    assert abs(measured / 1e-3 - 1.0) < TOL["walk_rel"], measured


@pytest.mark.parametrize("rate_hz,latency_ms,shift", [(200.0, 10, 2), (100.0, 30, 3), (1000.0, 7, 7)])
def test_latency_shifts_motion_capture_by_exactly_its_samples(rate_hz, latency_ms, shift):
    """With the same seed, the late system's newest sample is the prompt one's ``shift`` samples back, bit for bit."""
    reads = {}
    for lat in (0, latency_ms):
        suite = SensorSuite(mocap=MocapConfig(rate_hz=rate_hz, latency_s=lat * 1e-3), imu=None,
                            rng=np.random.default_rng(7))
        sp = SensedPlant(make_plant("sim"), suite)
        x0 = HOVER.copy()
        x0[9:12] = [1.0, -0.5, 0.2]        # moving, so that every sample differs
        sp.reset(x0)
        got, newest = [], []
        for _ in range(20):
            sp.advance(sp.hover_input, DT)
            r = suite.read(sp.t)
            got.extend(zip(r.mocap_t, r.mocap))
            newest.append(r.mocap_t[-1] if len(r.mocap_t) else np.nan)
        reads[lat] = got, np.array(newest)
    (prompt, new0), (late, new1) = reads[0], reads[latency_ms]
    # At every period boundary the newest sample is `shift` sample periods older.
    np.testing.assert_allclose((new0 - new1)[5:], shift / rate_hz, rtol=0, atol=1e-12)
    # Every sample arrives, in order, with its own time and value; the late stream ends `shift` samples earlier.
    assert len(prompt) - len(late) == shift
    for (t0, z0), (t1, z1) in zip(prompt, late):
        assert t0 == t1
        np.testing.assert_array_equal(z0, z1)


def test_motion_capture_reports_wrapped_angles_with_its_noise():
    cfg = MocapConfig(rate_hz=250.0, latency_s=0.0, position_std=1e-3, attitude_std=2e-3)
    suite = SensorSuite(mocap=cfg, imu=None, rng=np.random.default_rng(3))
    sp = SensedPlant(make_plant("sim"), suite)
    x0 = HOVER.copy()
    x0[5] = 3.0 * np.pi       # yaw a turn and a half: reported at pi
    sp.reset(x0)
    for _ in range(100):
        sp.advance(sp.hover_input, DT)
    r = suite.read(sp.t)
    assert len(r.mocap) == 251      # 4 ms period over 1 s, and the sample at power-on
    err = r.mocap[:, 0:3] - HOVER[0:3]
    assert abs(err.std() / 1e-3 - 1.0) < TOL["walk_rel"]
    assert np.all(np.abs(r.mocap[:, 3:6]) <= np.pi)
    yaw_err = wrap_angle(r.mocap[:, 5] - np.pi)
    assert abs(yaw_err.std() / 2e-3 - 1.0) < TOL["walk_rel"] * 1.5


def test_a_rate_that_is_not_whole_milliseconds_averages_to_it():
    suite = SensorSuite(mocap=MocapConfig(rate_hz=400.0, latency_s=0.0), imu=None, rng=np.random.default_rng(0))
    sp = SensedPlant(make_plant("sim"), suite)
    sp.reset(HOVER)
    for _ in range(100):
        sp.advance(sp.hover_input, DT)
    assert len(suite.read(sp.t).mocap) == 401


def test_seeded_sensors_read_exactly_the_same():
    out = []
    for _ in range(2):
        suite = SensorSuite(rng=np.random.default_rng(11))
        sp = SensedPlant(make_plant("sim"), suite)
        sp.reset(HOVER)
        for _ in range(10):
            sp.advance(sp.hover_input, DT)
        r = suite.read(sp.t)
        out.append(np.concatenate([r.mocap.ravel(), r.gyro.ravel(), r.accel.ravel()]))
    np.testing.assert_array_equal(out[0], out[1])


def test_specific_force_of_a_known_motion():
    x0, x1 = np.zeros(12), np.zeros(12)
    x1[9:12] = [0.002, 0.0, -0.001]          # 2 m/s^2 north, 1 m/s^2 up in 1 ms
    np.testing.assert_allclose(specific_force(x0, x1, 1e-3, 9.81), [2.0, 0.0, -10.81], atol=1e-12)


@pytest.mark.parametrize("kwargs,word", [({"rate_hz": 2000.0}, "rate_hz"), ({"latency_s": 0.0005}, "latency_s"),
                                         ({"position_std": -1.0}, "position_std"), ({"rate_hz": float("nan")},
                                                                                     "rate_hz")])
def test_bad_motion_capture_settings_name_the_field(kwargs, word):
    with pytest.raises(SimInputError, match=word):
        MocapConfig(**kwargs)


def test_bad_imu_settings_name_the_field():
    with pytest.raises(SimInputError, match="rate_hz"):
        ImuConfig(rate_hz=300.0)
    with pytest.raises(SimInputError, match="gyro_std"):
        ImuConfig(gyro_std=-1.0)
    with pytest.raises(SimInputError, match="sensors"):
        SensedPlant(make_plant("sim"), sensors="mocap")
