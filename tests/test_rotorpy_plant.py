"""RotorPy as a plant: frames, rotor order and set-ups checked against the reference simulator."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rotorpy")

from sim.plants import rotorpy_plant
from sim.errors import PlantUnavailableError, SimInputError
from sim.params import DT, Fidelity
from sim.plants.plant import SimPlant
from sim.plants.named import make_plant
from sim.plants.rotorpy_plant import (FLIP, INTEGRATORS, ROTORPY_INDEX, RotorPyPlant, from_rotorpy_state,
                                      rotorpy_params, to_rotorpy_state)
from sim.vehicles.onboard import InnerLoopConfig
from sim.vehicles.rotors import ROTOR_X, ROTOR_Y, SPIN, mixer_matrix
from sim.vehicles.vehicle import load_vehicle

TOL = {
    # Ideal set-up vs the reference simulator (RK4 at 1 ms), one 10 ms period from 240 random states; measured
    # 1.6e-12 m and 2e-10 (rad, rad/s, m/s): the reference's RK4 error.
    "ideal_position": 1e-8,     # m
    "ideal_state": 1e-8,        # every state, in its unit
    # Instant motors: both run at the clipped command of their own allocation (the rotors placed at our lever
    # d / sqrt(2) exactly); they differ by the rounding of two inversions of the mixer.
    "rotor_speed": 1e-12,       # RU
    "wrench": 1e-12,            # N, N m
    # Motor lag alone, 5 periods from given rotor speeds; measured 2e-10 m, 8e-8 rad/s, 2e-8 RU (RK4's error on
    # the 30 ms lag at 1 ms steps).
    "lag_position": 1e-8,       # m
    "lag_state": 1e-6,          # every state, in its unit
    "lag_rotor_speed": 1e-6,    # RU
    "round_trip": 1e-14,        # our state -> RotorPy -> ours (rad, m, m/s, rad/s)
    "hover_drift": 1e-12,       # m and m/s, one period at hover
    "geometry": 1e-15,          # relative: the rotor positions against our lever d / sqrt(2)
    "mixer": 1e-14,             # relative, RotorPy's allocation vs ours
    "yaw_spin": 1e-8,           # rad, psi through pi, RotorPy vs reference
    "wind": 1e-8,               # m and m/s, constant wind over 3 periods
    "payload": 1e-8,            # m, sink at hover thrust
    # ctbr: RotorPy's cmd_ctbr against our plant with the same P loop (instant motors, no drag), 100 periods;
    # measured 4.6e-11 (any state, in its unit), also with calls that end inside a loop period.
    "ctbr_state": 1e-8,
    # ctatt, instant motors, no drag: the PD attitude loop's steady state after 2 s of a constant command; its slow
    # pole is near att_kp (5-6 1/s), so the error left is about 1e-6.
    "ctatt_steady": 1e-4,       # rad (roll, pitch) and rad/s (yaw rate)
}

VEHICLE = load_vehicle()
NO_DRAG = VEHICLE.replace(c_d=0.0)       # the ideal set-up has no drag at all
P = NO_DRAG.params
M = mixer_matrix(P)
HOVER = np.array([P.m * P.g, 0.0, 0.0, 0.0])


def hover_state():
    x = np.zeros(12)
    x[2] = -1.0
    return x


def random_state(rng, yaw):
    x = np.zeros(12)
    x[0:3] = rng.uniform(-3.0, 3.0, 3)
    x[3:5] = rng.uniform(-1.0, 1.0, 2)
    x[5] = yaw
    x[6:9] = rng.uniform(-4.0, 4.0, 3)
    x[9:12] = rng.uniform(-4.0, 4.0, 3)
    return x


def random_yaws(rng, n):
    """Yaw angles: anywhere in [-pi, pi], within 0.05 rad of +-pi, and beyond +-pi (continuous angles)."""
    k = n // 4
    near = np.pi - rng.uniform(0.0, 0.05, k)
    return np.concatenate([rng.uniform(-np.pi, np.pi, n - 3 * k), near, -near, rng.uniform(-4 * np.pi, 4 * np.pi, k)])


@pytest.fixture(scope="module")
def ideal():
    return RotorPyPlant(NO_DRAG, motor_lag=False, aero=False)


@pytest.fixture(scope="module")
def full():
    return RotorPyPlant(VEHICLE, motor_lag=True, aero=True)


# ---------------------------------------------------------------- set-ups


def test_names_and_make_plant():
    assert make_plant("rotorpy").name == "rotorpy"
    ideal = make_plant("rotorpy-ideal")
    assert ideal.name == "rotorpy-ideal" and not ideal.motor_lag and not ideal.aero
    assert RotorPyPlant(motor_lag=True, aero=False).name == "rotorpy-custom"
    d = make_plant("rotorpy", payload_kg=0.01).describe()
    assert d["plant"] == "rotorpy" and d["motor_lag"] and d["aero"] and d["payload_kg"] == 0.01


# ------------------------------------------------------------ equivalence


def test_ideal_set_up_agrees_with_the_reference_simulator(ideal):
    rng = np.random.default_rng(20240611)
    ref = SimPlant(NO_DRAG)
    n = 240
    err = np.zeros(12)
    low = high = clean = 0
    for yaw in random_yaws(rng, n):
        x = random_state(rng, yaw)
        u = M @ (rng.uniform(-0.25, 1.25, 4) * P.n_max_sq)   # a good share of rotors clipped at 0 or at n_max
        ideal.reset(x)
        ref.reset(x)
        a, b = ideal.advance(u), ref.advance(u)
        err = np.maximum(err, np.abs(a.x - b.x))
        np.testing.assert_array_equal(a.saturated, b.saturated)
        np.testing.assert_allclose(a.rotor_speed, b.rotor_speed, rtol=0, atol=TOL["rotor_speed"])
        np.testing.assert_allclose(a.wrench, b.wrench, rtol=0, atol=TOL["wrench"])
        n_sq = np.linalg.solve(M, u)
        low += np.any(n_sq < 0.0)
        high += np.any(n_sq > P.n_max_sq)
        clean += not np.any(b.saturated)
    assert low > n / 4 and high > n / 4 and clean > n / 10   # both limits, and unclipped commands, exercised
    assert np.max(err[0:3]) < TOL["ideal_position"], err
    assert np.max(err) < TOL["ideal_state"], err


def test_motor_lag_alone_agrees_with_the_reference_simulator():
    rng = np.random.default_rng(7)
    lag = RotorPyPlant(NO_DRAG, motor_lag=True, aero=False)
    ref = SimPlant(NO_DRAG, Fidelity(motor_tau=NO_DRAG.motor_tau))
    for _ in range(8):
        x = random_state(rng, rng.uniform(-4.0, 4.0))
        n0 = rng.uniform(0.2, 1.0, 4) * NO_DRAG.n_max_value
        lag.reset(x, rotor_speed=n0)
        ref.reset(x, rotor_speed=n0)
        for _ in range(5):
            u = M @ (rng.uniform(-0.2, 1.2, 4) * P.n_max_sq)
            a, b = lag.advance(u), ref.advance(u)
            np.testing.assert_array_equal(a.saturated, b.saturated)
            np.testing.assert_allclose(a.x[0:3], b.x[0:3], rtol=0, atol=TOL["lag_position"])
            np.testing.assert_allclose(a.x, b.x, rtol=0, atol=TOL["lag_state"])
            np.testing.assert_allclose(a.rotor_speed, b.rotor_speed, rtol=0, atol=TOL["lag_rotor_speed"])


def test_motor_lag_starts_at_hover_and_carries_rotor_speeds():
    lag = RotorPyPlant(NO_DRAG, motor_lag=True, aero=False)
    out = lag.reset(hover_state())
    np.testing.assert_allclose(out.rotor_speed, P.n_hover)
    out = lag.advance(1.2 * HOVER)
    np.testing.assert_allclose(out.wrench, HOVER, rtol=1e-12, atol=1e-15)   # the wrench at the start: hover
    assert np.all(out.rotor_speed > P.n_hover) and np.all(out.rotor_speed < np.sqrt(1.2) * P.n_hover)
    again = lag.advance(1.2 * HOVER)
    np.testing.assert_allclose(again.wrench, M @ out.rotor_speed ** 2, rtol=1e-12)


# ------------------------------------------------------------------ signs


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("plant", ["ideal", "full", "sim"])
def test_positive_torque_gives_positive_rate(plant, axis, request):
    pl = SimPlant(VEHICLE) if plant == "sim" else request.getfixturevalue(plant)
    u = HOVER.copy()
    u[1 + axis] = 2e-4
    pl.reset(hover_state())
    x = pl.advance(u).x
    assert x[6 + axis] > 0.0
    others = [i for i in range(3) if i != axis]
    assert np.all(np.abs(x[6 + np.array(others)]) < 1e-3 * x[6 + axis])


@pytest.mark.parametrize("plant", ["ideal", "full"])
def test_hover_is_an_equilibrium(plant, request):
    pl = request.getfixturevalue(plant)
    x0 = hover_state()
    x0[5] = 2.0
    pl.reset(x0)
    out = pl.advance(pl.hover_input)
    assert np.max(np.abs(out.x - x0)) < TOL["hover_drift"]
    np.testing.assert_allclose(out.rotor_speed, P.n_hover, rtol=1e-12)


def test_flying_leaves_numpys_global_generator_alone(full):
    np.random.seed(5)
    expected = np.random.random()
    np.random.seed(5)
    full.reset(hover_state())
    full.advance(full.hover_input)
    assert np.random.random() == expected


# ------------------------------------------------------------ conversions


def test_state_round_trip_is_exact():
    rng = np.random.default_rng(3)
    for i in range(500):
        x = random_state(rng, rng.uniform(-10.0, 10.0))
        x[3] = rng.uniform(-3.0, 3.0)
        if i % 5 == 0:                    # pitch past 90 degrees: the other Euler representation of the attitude
            x[4] = rng.choice([-1.0, 1.0]) * rng.uniform(1.6, 3.0)
        n = rng.uniform(0.0, 5.0, 4)
        s = to_rotorpy_state(x, n)
        back, n_back = from_rotorpy_state(s, x)
        np.testing.assert_allclose(back, x, rtol=0, atol=TOL["round_trip"])
        np.testing.assert_array_equal(n_back, n)
        # The angles come back from any previous state within a fraction of a turn.
        prev = x.copy()
        prev[3:6] += rng.uniform(-0.4, 0.4, 3)
        np.testing.assert_allclose(from_rotorpy_state(s, prev)[0], x, rtol=0, atol=TOL["round_trip"])


def test_rotorpy_frames_are_flipped_y_and_z():
    x = np.zeros(12)
    x[0:3] = [1.0, 2.0, -3.0]          # 3 m up
    x[5] = np.pi / 2                   # nose east
    x[6:9] = [0.1, 0.2, 0.3]
    x[9:12] = [4.0, 5.0, 6.0]
    s = to_rotorpy_state(x, np.arange(1.0, 5.0))
    np.testing.assert_allclose(s["x"], [1.0, -2.0, 3.0])
    np.testing.assert_allclose(s["v"], [4.0, -5.0, -6.0])
    np.testing.assert_allclose(s["w"], [0.1, -0.2, -0.3])
    np.testing.assert_array_equal(s["rotor_speeds"], [4.0, 1.0, 2.0, 3.0])   # RotorPy r1..r4 = our 4, 1, 2, 3
    from scipy.spatial.transform import Rotation

    # Nose east in NED is nose at -y in the z-up frame: the body x axis is (0, -1, 0).
    np.testing.assert_allclose(Rotation.from_quat(s["q"]).as_matrix()[:, 0], [0.0, -1.0, 0.0], atol=1e-15)


@pytest.mark.parametrize("rate", [2.0, -2.0])
def test_yaw_spin_through_pi_is_continuous(ideal, rate):
    ref = SimPlant(NO_DRAG)
    x0 = hover_state()
    x0[5] = np.sign(rate) * (np.pi - 0.1)
    x0[8] = rate
    ideal.reset(x0)
    ref.reset(x0)
    psi = [x0[5]]
    for _ in range(10):
        a, b = ideal.advance(HOVER), ref.advance(HOVER)
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=TOL["yaw_spin"])
        psi.append(a.x[5])
    np.testing.assert_allclose(np.diff(psi), rate * DT, rtol=1e-9)
    assert abs(psi[-1]) > np.pi


# ------------------------------------------------------------ rotor order


def test_rotor_geometry_and_spins_match_ours(ideal):
    mr = ideal._mr
    keys = list(mr.rotor_pos)
    for i in range(4):
        j = ROTORPY_INDEX[i]
        pos = FLIP * mr.rotor_pos[keys[j]]
        np.testing.assert_allclose(pos, [ROTOR_X[i] * P.lever, ROTOR_Y[i] * P.lever, 0.0], rtol=TOL["geometry"])
        assert SPIN[i] == -mr.rotor_dir[j]   # RotorPy's yaw moment is about z up, ours about z down
    # RotorPy's allocation: rotor thrusts -> [T, M] (FLU); in our frame, our mixer.
    for i in range(4):
        tm = mr.f_to_TM[:, ROTORPY_INDEX[i]] * P.kt
        ours = np.concatenate([[tm[0]], FLIP * tm[1:]])
        np.testing.assert_allclose(ours, M[:, i], rtol=TOL["mixer"], atol=1e-18)
    assert rotorpy_params(VEHICLE)["rotor_speed_max"] == VEHICLE.n_max_value


@pytest.mark.parametrize("rotor", [0, 1, 2, 3])
def test_one_rotor_faster_gives_the_same_torque_signs(ideal, full, rotor):
    n_sq = np.full(4, P.n_hover ** 2)
    n_sq[rotor] *= 1.1
    u = M @ n_sq
    ref = SimPlant(NO_DRAG)
    ref.reset(hover_state())
    b = ref.advance(u)
    for pl in (ideal, full):
        pl.reset(hover_state())
        a = pl.advance(u)
        np.testing.assert_array_equal(np.sign(a.x[6:9]), np.sign(b.x[6:9]))
        assert np.all(a.x[6:9] != 0.0)
        assert np.argmax(a.rotor_speed) == rotor
    np.testing.assert_allclose(ideal.advance(u).wrench, u, rtol=TOL["mixer"])


# -------------------------------------------------------- wind and payload


def test_constant_wind_acceleration_agrees(ideal):
    wind = np.array([0.5, -0.3, 0.2])
    rp = RotorPyPlant(NO_DRAG, motor_lag=False, aero=False, wind=lambda t: wind)
    ref = SimPlant(NO_DRAG, wind=lambda t: wind)
    x0 = random_state(np.random.default_rng(11), 1.0)
    for pl in (rp, ref, ideal):
        pl.reset(x0)
    for _ in range(3):
        u = HOVER + np.array([0.05, 1e-5, -2e-5, 1e-5])
        a, b, calm = rp.advance(u), ref.advance(u), ideal.advance(u)
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=TOL["wind"])
    dv = a.x[9:12] - calm.x[9:12]
    np.testing.assert_allclose(dv, wind * 3 * DT, rtol=1e-6)   # the wind adds its acceleration, in NED


def test_wind_is_read_at_the_start_of_each_call():
    times = []
    pl = RotorPyPlant(NO_DRAG, motor_lag=False, aero=False, wind=lambda t: times.append(t) or np.zeros(3))
    pl.reset(hover_state())
    pl.advance(HOVER, 0.004)
    pl.advance(HOVER, DT)
    assert times == pytest.approx([0.0, 0.004])


def test_payload_sinks_both_plants_alike():
    payload = 0.2 * P.m
    rp = RotorPyPlant(NO_DRAG, motor_lag=False, aero=False, payload_kg=payload)
    ref = SimPlant(NO_DRAG, payload_kg=payload)
    x0 = hover_state()
    rp.reset(x0)
    ref.reset(x0)
    a, b = rp.advance(rp.hover_input), ref.advance(ref.hover_input)
    sink = a.x[2] - x0[2]
    assert sink > 0.0   # NED: z grows downwards
    np.testing.assert_allclose(sink, b.x[2] - x0[2], rtol=0, atol=TOL["payload"])
    np.testing.assert_allclose(sink, 0.5 * P.g * (1 - P.m / (P.m + payload)) * DT ** 2, rtol=1e-9)
    assert rp._mr.rotor_speed_max == NO_DRAG.n_max_value   # limits stay the vehicle's


# ------------------------------------------------------ the full set-up


def test_full_set_up_slows_a_moving_vehicle(full):
    ideal = RotorPyPlant(VEHICLE, motor_lag=False, aero=False)
    x0 = hover_state()
    x0[9:12] = [3.0, -1.0, 0.0]
    speeds = []
    for pl in (full, ideal):
        pl.reset(x0)
        speeds.append(np.linalg.norm(pl.advance(pl.hover_input).x[9:12]))
    assert speeds[1] == pytest.approx(np.hypot(3.0, 1.0), rel=1e-12)   # ideal: no drag at all
    assert speeds[0] < speeds[1] - 1e-3                                   # rotor and parasitic drag


# ---------------------------------------------------------------- errors


def test_bad_calls_raise_clear_errors(ideal):
    fresh = RotorPyPlant(NO_DRAG, motor_lag=False, aero=False)
    with pytest.raises(SimInputError, match="reset"):
        fresh.advance(HOVER)
    ideal.reset(hover_state())
    with pytest.raises(SimInputError, match="whole number"):
        ideal.advance(HOVER, 0.0105)
    with pytest.raises(SimInputError, match="motor_lag"):
        RotorPyPlant(NO_DRAG, motor_lag="yes")
    with pytest.raises(SimInputError, match="wind"):
        bad = RotorPyPlant(NO_DRAG, motor_lag=False, aero=False, wind=lambda t: np.zeros(2))
        bad.reset(hover_state())
        bad.advance(HOVER)


def test_gravity_other_than_rotorpys_is_refused(monkeypatch):
    monkeypatch.setattr(rotorpy_plant, "ROTORPY_G", 9.80665)
    with pytest.raises(SimInputError, match="gravity"):
        RotorPyPlant(NO_DRAG)


def test_missing_rotorpy_is_a_one_line_error(monkeypatch):
    monkeypatch.setattr(rotorpy_plant, "_WindMultirotor", None)
    monkeypatch.setitem(sys.modules, "rotorpy.vehicles.multirotor", None)   # import fails
    with pytest.raises(PlantUnavailableError) as e:
        make_plant("rotorpy")
    assert isinstance(e.value, ValueError)
    assert str(e.value) == "plant 'rotorpy' needs RotorPy: pip install -e '.[rotorpy]'"
    # The main job then leaves its RotorPy runs out instead of failing them.
    from scenarios.studies import campaign
    monkeypatch.setattr(campaign, "rotorpy_available", lambda: False)
    plan = campaign.main_plan(Path(__file__).resolve().parents[1] / "models")
    assert campaign.plant_plan() == [] and {s.plant for s in plan} == {"sim"}


def test_flying_rotorpy_does_not_import_torch():
    # RotorPy's module tries torch for its batched vehicle; the plant imports it without, so that a flight on
    # RotorPy stays as light as one on our simulator (torch alone costs 2 s and 660 MB per process).
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from sim.plants.named import make_plant\n"
            "p = make_plant('rotorpy')\n"
            "x0 = np.zeros(12); x0[2] = -1.0\n"
            "p.reset(x0); p.step(p.hover_input)\n"
            "assert 'torch' not in sys.modules, 'torch was imported'\n"
            "import importlib.util; print(importlib.util.find_spec('torch') is not None)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


ACCEPT = {
    "oracle_rmse_m": 1e-3,          # the oracle on RotorPy's ideal set-up: within 1 mm of the figure-8
    "nominal_level_rmse_m": 0.05,   # the per-level nominal model on RotorPy's Crazyflie: no crash, within 50 mm
}


def test_the_oracle_flies_rotorpy_within_a_millimetre(tmp_path, capsys):
    import json

    from scenarios.cli import main

    out = tmp_path / "r.json"
    assert main(["fly", "--plant", "rotorpy-ideal", "--model", "oracle", "--controller", "sqp", "--scenario",
                 "figure8-fast", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert (r["plant"], r["vehicle"], r["model"], r["crashed"]) == ("rotorpy-ideal", "rolling-spider", "oracle", False)
    assert r["rmse_position_m"] <= ACCEPT["oracle_rmse_m"]
    assert r["plant_spec"]["integrator"]["rtol"] == INTEGRATORS["ideal"]["rtol"]
    assert "rotorpy-ideal" in capsys.readouterr().out


def test_rotorpy_with_aerodynamics_has_no_oracle_and_says_so(capsys):
    from scenarios.cli import main

    assert main(["fly", "--plant", "rotorpy", "--model", "oracle", "--controller", "lqr", "--scenario", "hover"]) == 2
    err = capsys.readouterr().err
    assert "has no known equations" in err and "--model nominal" in err and err.count("\n") == 1
    # The high-fidelity set-up belongs to our simulator.
    assert main(["fly", "--plant", "rotorpy-ideal", "--model", "nominal", "--controller", "lqr", "--scenario",
                 "hover+highfi"]) == 2
    assert "high-fidelity" in capsys.readouterr().err


def test_a_rotorpy_dataset_flown_in_two_processes_equals_one_flown_in_one():
    """Each trajectory has its own random stream and plant: slicing them over processes changes no bit."""
    from sim.identification.excitation import make_dataset

    one = make_dataset("small", 3, 0.5, 4, plant="rotorpy", vehicle="crazyflie")
    two = make_dataset("small", 3, 0.5, 4, plant="rotorpy", vehicle="crazyflie", workers=2)
    for k in ("x", "u", "rotor_speed", "x_next", "wrench", "saturated", "split"):
        np.testing.assert_array_equal(getattr(one, k), getattr(two, k))
    assert one.meta == two.meta


# ---------------------------------------------------------------- command levels: RotorPy's own onboard loops

#: A P-only rate loop (RotorPy's cmd_ctbr has no integral or derivative) at 500 Hz: a loop period of 2 ms, so a
#: call of 3 ms ends inside one.
P_LOOP = InnerLoopConfig(rate_hz=500.0, rate_kp=(120.0, 100.0, 60.0), att_kp=(6.0, 5.0), max_rate=6.0,
                         max_tilt=0.8, source="a test: a P loop")


@pytest.mark.parametrize("split", [False, True], ids=["whole periods", "calls ending inside a loop period"])
def test_rotorpy_at_ctbr_is_our_plant_with_the_same_p_loop(split):
    v = NO_DRAG.replace(inner_loop=P_LOOP)
    ours = make_plant("sim", v, level="ctbr")
    rp = make_plant("rotorpy-ideal", v, level="ctbr")
    rng = np.random.default_rng(4)
    x0 = hover_state()
    x0[3], x0[6] = 0.1, 0.3
    ours.reset(x0)
    rp.reset(x0)
    worst = 0.0
    for _ in range(100):
        u = np.r_[P.m * P.g * rng.uniform(0.9, 1.2), rng.normal(0.0, 2.0, 3)]   # some rates beyond max_rate
        if split:
            rp.advance(u, 0.003)
            a = rp.advance(u, DT - 0.003)
        else:
            a = rp.advance(u)
        b = ours.advance(u)
        worst = max(worst, float(np.max(np.abs(a.x - b.x))))
    assert worst <= TOL["ctbr_state"], worst
    d = rp.describe()
    assert (d["level"], d["inner_loop"]["rotorpy_abstraction"], d["inner_loop"]["k_w"]) == (
        "ctbr", "cmd_ctbr", list(P_LOOP.rate_kp))


def test_rotorpy_at_ctatt_holds_the_commanded_tilt_and_yaw_rate():
    """RotorPy's PD attitude loop reaches a constant roll and pitch command, and the yaw setpoint integrated from a
    yaw-rate command turns the vehicle at that rate (instant motors, no drag: nothing disturbs the steady state)."""
    v = NO_DRAG.replace(inner_loop=P_LOOP)
    rp = make_plant("rotorpy-ideal", v, level="ctatt")
    rp.reset(hover_state())
    for _ in range(200):
        out = rp.advance([P.m * P.g, 0.2, -0.1, 0.0])
    np.testing.assert_allclose(out.x[3:5], [0.2, -0.1], atol=TOL["ctatt_steady"])
    for _ in range(200):
        out = rp.advance([P.m * P.g, 0.0, 0.0, 0.3])
    np.testing.assert_allclose(out.x[[3, 4, 8]], [0.0, 0.0, 0.3], atol=TOL["ctatt_steady"])
    # Commands beyond the vehicle's limits are clipped, as our loop clips them: a 2 rad roll holds at max_tilt.
    for _ in range(200):
        out = rp.advance([P.m * P.g, 2.0, 0.0, 0.0])
    assert abs(out.x[3] - P_LOOP.max_tilt) <= TOL["ctatt_steady"]


def test_rotorpy_at_a_level_needs_the_vehicles_inner_loop():
    with pytest.raises(SimInputError, match=r"inner_loop.rate_kp is missing"):
        make_plant("rotorpy", NO_DRAG.replace(inner_loop=None), level="ctbr")


@pytest.mark.slow
@pytest.mark.parametrize("level", ["ctbr", "ctatt"])
def test_the_nominal_model_flies_rotorpys_crazyflie_at_a_level(tmp_path, level):
    """The acceptance flight: the per-level nominal model, SQP, figure8-fast, RotorPy with motor lag and
    aerodynamics. Measured 32.9 mm (ctbr) and 25.0 mm (ctatt); the wrench level's is 31.0 mm."""
    from scenarios.cli import main

    out = tmp_path / "r.json"
    assert main(["fly", "--plant", "rotorpy", "--vehicle", "crazyflie", "--level", level, "--model", "nominal",
                 "--controller", "sqp", "--scenario", "figure8-fast", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert (r["level"], r["plant_spec"]["level"], r["crashed"]) == (level, level, False)
    assert r["rmse_position_m"] <= ACCEPT["nominal_level_rmse_m"], r["rmse_position_m"]
