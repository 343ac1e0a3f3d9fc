"""Sensors: the IMU reads what a real one reads, motion capture arrives exactly its latency late, seeded reruns agree."""

import dataclasses

import numpy as np
import pytest

from sim.errors import SimInputError
from sim.params import DT
from sim.plants.plant import Plant, SimPlant
from sim.plants.named import make_plant
from sim.plants.sensors import ImuConfig, MocapConfig, SensedPlant, SensorSuite, specific_force, wrap_angle
from sim.vehicles.vehicle import load_vehicle

#: Tolerances of this module.
TOL = {
    "accel_sim": 1e-9,          # m/s^2: the reference simulator at hover (exact equilibrium)
    "accel_rotorpy": 1e-6,      # m/s^2: RotorPy at hover (its integrator's tolerance)
    "free_fall": 1e-9,          # m/s^2: no drag, no thrust
    "thrust": 1e-6,             # m/s^2: tilted, hover thrust, first millisecond
    "gyro": 0.0,                # noise-free gyro: the true rates exactly
    "walk_rel": 0.1,            # relative error of the bias random walk's measured standard deviation
    "fast_path": 0.0,           # a period flown and sampled at once against one call per millisecond: bit for bit
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
    from sim.vehicles.vehicle import load_vehicle

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


# ---------------------------------------------------------------- a period at once against one call per millisecond

def _same(a, b, what):
    """``a`` and ``b`` equal within TOL["fast_path"] (zero: bit for bit, NaN where NaN)."""
    assert TOL["fast_path"] == 0.0
    np.testing.assert_array_equal(a, b, err_msg=what)


def _gusts(t):
    return np.array([0.8 * np.sin(2.3 * t), -0.5 * np.cos(1.1 * t), 0.3 * np.sin(5.0 * t)])


def _setup(name):
    v = load_vehicle(None)
    m = v.params.m
    return {"nominal": lambda: SimPlant(v),
            "motor lag": lambda: SimPlant(v, v.fidelity),
            "payload": lambda: SimPlant(v, payload_kg=0.2 * m),
            "wind": lambda: SimPlant(v, wind=_gusts),
            "all": lambda: SimPlant(v, v.fidelity, payload_kg=0.2 * m, wind=_gusts)}[name]()


#: Sensor set-ups: the default lab, and rates whose samples fall unevenly on the ticks, with a late mocap.
SUITES = {"default": {}, "uneven": {"mocap": MocapConfig(rate_hz=400.0, latency_s=0.003),
                                    "imu": ImuConfig(rate_hz=500.0)}}
X0 = np.array([0.0, 0.0, -1.0, 0.1, -0.05, 0.4, 0.3, -0.2, 0.1, 0.5, -0.3, 0.2])


def _command(k, hover):
    """A command that changes every period (thrust +-30 %, torques that tilt the vehicle back and forth)."""
    return hover * np.array([1.0 + 0.3 * np.sin(0.05 * k), 0, 0, 0]) + np.array(
        [0.0, 2e-4 * np.sin(0.1 * k), 2e-4 * np.cos(0.13 * k), 5e-5 * np.sin(0.07 * k)])


def _per_tick(plant, suite, u, duration_s):
    """The reference: one plant call and one sensor tick per millisecond."""
    out = None
    for _ in range(int(round(duration_s / 1e-3))):
        x0 = plant.x
        out = plant.advance(u, 1e-3)
        suite.tick(x0, out.x)
    return out


def _flight(plant, suite, fast, periods, pieces=None):
    """Per period: plant state, rotor speeds, time and last output; every third period a read; the end."""
    sp = SensedPlant(plant, suite)
    sp.reset(X0)
    log, reads = [], []
    for k in range(periods):
        u = _command(k, plant.hover_input)
        d = DT if pieces is None else pieces[k % len(pieces)]
        out = sp.advance(u, d) if fast else _per_tick(plant, suite, u, d)
        log.append(np.concatenate([plant.x, plant._n if plant._n is not None else np.full(4, -1.0), [plant.t],
                                   out.x, out.rotor_speed, out.wrench, out.saturated]))
        if k % 3 == 2:
            r = suite.read(plant.t)
            reads.append([r.mocap_t, r.mocap, r.imu_t, r.gyro, r.accel, suite.gyro_bias, suite.accel_bias])
    return np.array(log), reads, suite.rng.bit_generator.state


@pytest.mark.parametrize("setup,suite,pieces", [("nominal", "default", None), ("motor lag", "default", None),
                                                ("payload", "default", None), ("wind", "uneven", None),
                                                ("all", "uneven", (0.003, 0.007, 0.01, 0.001, 0.009))])
def test_a_period_at_once_flies_and_reads_bit_for_bit_as_one_call_per_millisecond(setup, suite, pieces):
    """Several hundred periods of a changing command (some in pieces, as the real-time clock flies them): every
    period's state, rotor speeds and time, every reading, the biases and the random stream are the reference's."""
    runs = [_flight(_setup(setup), SensorSuite(rng=np.random.default_rng(17), **SUITES[suite]), fast, 300, pieces)
            for fast in (False, True)]
    (log0, reads0, rng0), (log1, reads1, rng1) = runs
    assert np.all(np.isfinite(log0)) and np.ptp(log0[:, 3]) > 0.1      # a flight that tilts, not a hover
    _same(log0, log1, "plant after each period")
    assert len(reads0) == len(reads1)
    for k, (r0, r1) in enumerate(zip(reads0, reads1)):
        assert len(r0[0]) > 0 and len(r0[2]) > 0
        for name, a, b in zip(("mocap_t", "mocap", "imu_t", "gyro", "accel", "gyro_bias", "accel_bias"), r0, r1):
            _same(a, b, f"read {k}: {name}")
    assert rng0 == rng1


def test_the_reference_simulator_flies_a_period_in_one_call(monkeypatch):
    """The fast path is taken: the sensed plant never calls the simulator's one-tick advance."""
    plant = _setup("all")
    sp = SensedPlant(plant, SensorSuite(rng=np.random.default_rng(0)))
    sp.reset(X0)

    def refuse(u, duration_s=DT):
        raise AssertionError("advance called")
    monkeypatch.setattr(plant, "advance", refuse)
    out = sp.advance(plant.hover_input, DT)
    assert plant.t == DT and out.x is plant.x


class _OwnPlant(Plant):
    """A user's plant with only ``_reset`` and ``_advance`` (the reference simulator inside)."""

    name = "own"

    def __init__(self):
        super().__init__(None, wind=_gusts)
        self._inner = SimPlant(None, load_vehicle(None).fidelity, wind=_gusts)

    _n = property(lambda self: self._inner._n)

    def _reset(self, x0, rotor_speed):
        return self._inner.reset(x0, rotor_speed)

    def _advance(self, u, ticks):
        return self._inner.advance(u, ticks * 1e-3)


class _DuckPlant:
    """A plant that is not a :class:`sim.plants.plant.Plant`, only shaped like one."""

    def __init__(self):
        self._inner = _OwnPlant()
        self.vehicle, self.hover_input = self._inner.vehicle, self._inner.hover_input

    x = property(lambda self: self._inner.x)
    t = property(lambda self: self._inner.t)
    _n = property(lambda self: self._inner._n)

    def reset(self, x0, rotor_speed=None):
        return self._inner.reset(x0, rotor_speed)

    def advance(self, u, duration_s):
        return self._inner.advance(u, duration_s)


@pytest.mark.parametrize("make", [_OwnPlant, _DuckPlant])
def test_other_plants_are_flown_one_tick_at_a_time_with_the_same_numbers(make):
    runs = [_flight(make(), SensorSuite(rng=np.random.default_rng(3), **SUITES["uneven"]), fast, 30)
            for fast in (False, True)]
    _same(runs[0][0], runs[1][0], "plant after each period")
    for r0, r1 in zip(runs[0][1], runs[1][1]):
        for a, b in zip(r0, r1):
            _same(a, b, "reading")
    assert runs[0][2] == runs[1][2]


def _failing_flight(fast, wind):
    plant = SimPlant(load_vehicle(None), wind=wind)
    suite = SensorSuite(rng=np.random.default_rng(0))
    sp = SensedPlant(plant, suite)
    sp.reset(HOVER)
    sp.advance(plant.hover_input, DT)
    with pytest.raises(SimInputError) as e:
        sp.advance(plant.hover_input, DT) if fast else _per_tick(plant, suite, plant.hover_input, DT)
    return str(e.value), plant.x.copy(), plant.t


@pytest.mark.parametrize("wind", [lambda t: np.array([np.nan if t >= 0.0135 else 0.0, 0.0, 0.0]),
                                  lambda t: np.array([1e306 if t >= 0.0125 else 0.0, 0.0, 0.0])],
                         ids=["wind fails", "state not finite"])
def test_a_period_that_fails_partway_fails_where_one_call_per_millisecond_fails(wind):
    """The same error, at the same tick, with the plant where the calls one per millisecond left it."""
    (msg0, x0, t0), (msg1, x1, t1) = _failing_flight(False, wind), _failing_flight(True, wind)
    assert msg0 == msg1 and t0 == t1 and 0.012 <= t0 < 0.02
    _same(x0, x1, "plant at the error")


def test_one_draw_of_normals_is_the_consecutive_draws_and_a_stack_of_ticks_each_tick_alone():
    """What a period at once rests on: numpy's generator and the sensors' arithmetic, on this machine."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        seed, sizes = int(rng.integers(2**31)), 3 * rng.integers(0, 7, size=int(rng.integers(1, 12)))
        g1, g2 = np.random.default_rng(seed), np.random.default_rng(seed)
        _same(np.concatenate([g1.standard_normal(int(n)) for n in sizes]), g2.standard_normal(int(sizes.sum())),
              "normals")
        assert g1.bit_generator.state == g2.bit_generator.state
    x0 = rng.standard_normal((2000, 12)) * 3.0
    x1 = x0 + 1e-3 * rng.standard_normal((2000, 12))
    _same(specific_force(x0, x1, 1e-3, 9.81), np.array([specific_force(a, b, 1e-3, 9.81) for a, b in zip(x0, x1)]),
          "specific force")
    c = MocapConfig(rate_hz=400.0)
    t = np.arange(1, 200)
    _same(c.due(t), [c.due(int(i)) for i in t], "motion capture due")


def test_tick_all_refuses_states_of_the_wrong_shape():
    suite = SensorSuite(rng=np.random.default_rng(0))
    with pytest.raises(SimInputError, match="states must have shape"):
        suite.tick_all(np.zeros((3, 11)))
