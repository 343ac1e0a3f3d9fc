"""Vehicles as data: the file format, the presets, and a user's own vehicle flown with nothing of the default's."""

import math

import numpy as np
import pytest

from scenarios.closed_loop.runner import RunSpec, fly
from sim import QuadParams
from sim.errors import SimInputError
from sim.params import HIGH_FIDELITY
from sim.vehicles.vehicle import VEHICLE_KEYS, Vehicle, load_vehicle, vehicle_names

TOL = {
    # The nominal equations on their own plant track to rounding and solver tolerance; the acceptance bound is 1 mm.
    "own_vehicle_m": 1e-3,
    "exact": 0.0,
}

#: A user's quadrotor of 1.2 kg (not a preset): its own inertias, arm, rotor coefficients (rad/s) and limit.
USER_VEHICLE = """
name = "user-quad"
m = 1.2
Jxx = 1.1e-2
Jyy = 1.3e-2
Jzz = 2.1e-2
kt = 1.2e-5
kq = 2.0e-7
d = 0.22
n_max = 800.0
c_d = 0.02
motor_tau = 0.02
rotor_drag = 2e-4
rotor_gyro = 0.0
k_z = 2e-4
k_h = 5e-3
k_flap = 0.0
source = "a test vehicle"
"""


@pytest.fixture
def user_file(tmp_path):
    path = tmp_path / "user-quad.toml"
    path.write_text(USER_VEHICLE)
    return path


def test_the_default_vehicle_is_the_reference_values():
    v = load_vehicle()
    assert v.name == "rolling-spider" and v.params == QuadParams()
    assert v.fidelity == HIGH_FIDELITY          # the high-fidelity plant is this vehicle's
    assert v.n_max_value ** 2 == pytest.approx(QuadParams().n_max_sq, rel=1e-15)


def test_the_presets_carry_rotorpys_numbers_and_their_sources():
    assert vehicle_names() == ["cf2x_L250", "crazyflie", "crazyflie-brushless", "hummingbird", "rolling-spider"]
    hb, cf = load_vehicle("hummingbird"), load_vehicle("crazyflie")
    assert (hb.m, hb.kt, hb.kq, hb.d, hb.n_max, hb.motor_tau) == (0.5, 5.57e-6, 1.36e-7, 0.17, 1500.0, 0.005)
    assert (cf.m, cf.kt, cf.d, cf.n_max, cf.motor_tau, cf.c_d) == (0.03, 2.3e-8, 0.043, 2500.0, 0.072, 0.0)
    # The Crazyflie's rotors lift 1.95 times its weight (RotorPy: k_eta 2.3e-8 N/(rad/s)^2 at 2500 rad/s).
    assert 4 * cf.kt * cf.n_max ** 2 / (cf.m * 9.81) == pytest.approx(1.9538, abs=1e-4)
    assert all(load_vehicle(n).source for n in vehicle_names())


def test_the_brushless_crazyflie_carries_the_benchmarks_stated_values():
    cb = load_vehicle("crazyflie-brushless")
    assert (cb.m, cb.Jxx, cb.Jyy, cb.Jzz, cb.kt, cb.kq) == (0.045, 2.3951e-5, 2.3951e-5, 3.2347e-6, 3.72e-8, 7.74e-12)
    assert cb.d / 2 ** 0.5 == pytest.approx(0.0353, abs=1e-6)          # their arm is the lever, d / sqrt(2)
    # n_max gives their thrust-to-weight 2.0
    assert 4 * cb.kt * cb.n_max ** 2 / (cb.m * 9.81) == pytest.approx(2.0, abs=1e-3)


def test_the_drone_models_crazyflie_carries_that_packages_values():
    v = load_vehicle("cf2x_L250")
    assert (v.m, v.Jxx, v.Jzz, v.motor_tau) == (0.0319, 1.68e-5, 2.98e-5, 0.1212)
    # their rpm2thrust quadratic term, 2.4583e-10 N/RPM^2, in rad/s; their thrust_max 0.12 N per rotor
    assert v.kt == pytest.approx(2.4582929831265485e-10 * (60 / (2 * 3.141592653589793)) ** 2, rel=1e-4)
    assert v.kt * v.n_max ** 2 == pytest.approx(0.12, rel=1e-4)
    assert v.d / 2 ** 0.5 == pytest.approx(0.03253, rel=1e-3)        # their L is the lever, d / sqrt(2)
    r = v.inner_loop.response()
    assert r.att_wn[0] ** 2 == pytest.approx(245.67, rel=1e-4)       # their fitted roll: wn^2 and 2 zeta wn
    assert 2 * r.att_zeta[0] * r.att_wn[0] == pytest.approx(17.32, rel=1e-3)


def test_a_key_left_out_takes_its_default_and_n_max_follows_the_weight(tmp_path):
    path = tmp_path / "heavy.toml"
    path.write_text("m = 0.1\n")
    v = load_vehicle(path)
    assert v.name == "heavy" and v.Jxx == QuadParams().Jxx and v.motor_tau == HIGH_FIDELITY.motor_tau
    assert 4 * v.kt * v.n_max_value ** 2 == pytest.approx(2 * 0.1 * 9.81, rel=1e-14)


@pytest.mark.parametrize("text,match", [
    ("mass = 1.0\n", "unknown key 'mass'"),
    ("m = -1.0\n", "m must be finite and > 0"),
    ("Jxx = 'big'\n", "Jxx must be a number"),
    ("c_d = -0.1\n", "c_d must be finite and >= 0"),
    ("n_max = 0\n", "n_max must be finite and > 0"),
    ("m = 1.0\nm = 2.0\n", "not valid TOML"),
    ("name = 3\n", "name must be a string"),
])
def test_a_bad_vehicle_file_is_a_one_line_error_naming_the_key(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SimInputError, match=match) as e:
        load_vehicle(path)
    assert "\n" not in str(e.value) and "bad.toml" in str(e.value)


def test_unknown_names_and_missing_files_are_clear_errors(tmp_path):
    with pytest.raises(SimInputError, match="unknown vehicle 'mavic'; choose from cf2x_L250, crazyflie"):
        load_vehicle("mavic")
    with pytest.raises(SimInputError, match="does not exist"):
        load_vehicle(tmp_path / "none.toml")
    assert set(VEHICLE_KEYS) >= {"m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "c_d", "n_max", "motor_tau"}


def test_a_vehicle_file_round_trips_through_its_description(user_file):
    v = load_vehicle(user_file)
    assert Vehicle(**{k: v.to_dict()[k] for k in VEHICLE_KEYS}) == v


@pytest.fixture
def without_the_default_vehicle(monkeypatch):
    """Make every read of the default vehicle's numbers an error: QuadParams() with its defaults, the default
    vehicle file, and the datasheet behind VehicleSpec()."""
    import sim.vehicles.vehicle

    defaults = QuadParams.__init__.__defaults__
    names = [f for f in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "d", "g", "c_d", "n_max")]
    assert len(defaults) == len(names)
    poisoned = tuple(v if n in ("g", "n_max") else math.nan for n, v in zip(names, defaults))
    monkeypatch.setattr(QuadParams.__init__, "__defaults__", poisoned)
    monkeypatch.setattr(sim.vehicles.vehicle, "DEFAULT_VEHICLE", "no-such-vehicle-the-default-was-read")
    with pytest.raises(ValueError):
        QuadParams()
    with pytest.raises(ValueError):
        load_vehicle()


@pytest.mark.parametrize("scenario,metric", [("hover", "settled_error_m"), ("figure8-slow", "rmse_position_m")])
def test_the_nominal_equations_fly_a_users_vehicle_within_a_millimetre(user_file, without_the_default_vehicle,
                                                                       scenario, metric):
    r, tr = fly(RunSpec(scenario, "sqp", "nominal", vehicle=str(user_file)))
    assert r["error"] is None and not r["crashed"]
    assert r["vehicle"] == "user-quad" and r["vehicle_spec"]["m"] == 1.2 and r["plant"] == "sim"
    assert r[metric] <= TOL["own_vehicle_m"]
    # The controller's thrust is the user's vehicle's: about 1.2 kg x g, not the Rolling Spider's 0.67 N.
    assert np.median(tr["u"][:, 0]) == pytest.approx(1.2 * 9.81, rel=0.05)


def test_the_same_run_with_the_default_vehicle_reads_it():
    r, _ = fly(RunSpec("hover", "lqr", "nominal"))
    assert r["vehicle"] == "rolling-spider" and r["run_id"] == "hover__lqr__nominal"
    assert RunSpec("hover", "lqr", "nominal", vehicle="crazyflie").run_id == "hover__lqr__nominal__crazyflie"
