"""The onboard controller (sim.plants.inner_loop) against the step responses of its continuous-time loops.

On a pure inertia (no drag, no motors) the loops have closed forms:

* rate loop, PI: w/w_cmd = (kp s + ki) / (s^2 + kp s + ki), whose unit step is
  ``1 - exp(-a t) (cos(b t) - a/b sin(b t))`` with ``a = kp/2``, ``b = sqrt(ki - a^2)``;
* attitude loop P over a rate loop P: phi/phi_cmd = kr ka / (s^2 + kr s + kr ka), unit step
  ``1 - exp(-a t) (cos(b t) + a/b sin(b t))`` with ``a = kr/2``, ``b = sqrt(kr ka - a^2)``.

The loops run at a fixed rate and hold their torque over a period, so they follow the closed forms to first order
in the period: halving the period (100 to 200 Hz, 500 to 1000 Hz) halves the largest error.
"""

import math

import numpy as np
import pytest

from sim.errors import SimInputError
from sim.plants.inner_loop import InnerLoop, InnerLoopConfig

TOL = {
    "order": (1.8, 2.3),        # ratio of the largest errors when the rate doubles (first order: 2)
    "overshoot": 0.01,          # |discrete - continuous| peak of the unit step at 500 Hz
    "rise_s": 0.004,            # |discrete - continuous| 10-90 % rise time at 500 Hz, s (two periods)
    "exact": 1e-12,             # known values computed two ways
}
J = np.array([1.43e-5, 1.43e-5, 2.89e-5])     # kg m^2, the Crazyflie 2.0's
RATES = (100, 200, 500, 1000)     # the rates a vehicle file may give (a whole number of runs per 10 ms)


def fly_inertia(loop: InnerLoop, command, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """States after each period (n, 12) of a pure inertia (small angles: the Euler rates are the body rates) under
    ``loop`` holding ``command``, integrated exactly for the held torque; and their times (n,)."""
    x, dt = np.zeros(12), loop.config.period_s
    out = []
    for _ in range(int(round(seconds / dt))):
        a = loop.update(command, x)[1:] / J
        x[3:6] += x[6:9] * dt + 0.5 * a * dt * dt
        x[6:9] += a * dt
        out.append(x.copy())
    return np.array(out), dt * np.arange(1, len(out) + 1)


def pi_step(t, kp, ki):
    a = kp / 2
    b = math.sqrt(ki - a * a)
    return 1 - np.exp(-a * t) * (np.cos(b * t) - a / b * np.sin(b * t))


def cascade_step(t, kr, ka):
    a = kr / 2
    b = math.sqrt(kr * ka - a * a)
    return 1 - np.exp(-a * t) * (np.cos(b * t) + a / b * np.sin(b * t))


def rise_time(t, y):
    return t[np.argmax(y >= 0.9)] - t[np.argmax(y >= 0.1)]


def rate_loop(rate_hz, kp=50.0, ki=1000.0):
    c = InnerLoopConfig(rate_hz=rate_hz, rate_kp=(kp, kp, kp), rate_ki=(ki, ki, ki), rate_i_limit=(10, 10, 10))
    return InnerLoop(c, "ctbr", J)


def test_the_rate_loop_follows_its_closed_form_to_first_order_in_the_period():
    errors = {}
    for r in RATES:
        x, t = fly_inertia(rate_loop(r), [0.3, 1.0, 0.0, 0.0], 1.0)
        errors[r] = np.max(np.abs(x[:, 6] - pi_step(t, 50.0, 1000.0)))
        assert np.all(x[:, 7:9] == 0.0)                  # the other axes were not commanded
    lo, hi = TOL["order"]
    assert lo <= errors[100] / errors[200] <= hi and lo <= errors[500] / errors[1000] <= hi, errors


def test_the_rate_loop_overshoot_and_rise_time_match_the_continuous_loop():
    x, t = fly_inertia(rate_loop(500), [0.3, 0.0, 1.0, 0.0], 1.0)
    fine = np.linspace(0.0, 1.0, 200001)
    exact = pi_step(fine, 50.0, 1000.0)
    assert abs(x[:, 7].max() - exact.max()) <= TOL["overshoot"]
    assert exact.max() - 1 == pytest.approx(0.1824, abs=1e-3)           # an 18 % overshoot, from the zero
    assert abs(rise_time(t, x[:, 7]) - rise_time(fine, exact)) <= TOL["rise_s"]


def test_the_attitude_loop_over_the_rate_loop_follows_its_closed_form():
    errors = {}
    for r in RATES:
        c = InnerLoopConfig(rate_hz=r, rate_kp=(30.0, 30.0, 30.0), att_kp=(15.0, 15.0))
        x, t = fly_inertia(InnerLoop(c, "ctatt", J), [0.3, 0.2, -0.1, 0.0], 1.0)
        errors[r] = max(np.max(np.abs(x[:, 3] - 0.2 * cascade_step(t, 30.0, 15.0))),
                        np.max(np.abs(x[:, 4] + 0.1 * cascade_step(t, 30.0, 15.0))))
    lo, hi = TOL["order"]
    assert lo <= errors[100] / errors[200] <= hi and lo <= errors[500] / errors[1000] <= hi, errors
    assert errors[500] < 0.02 * 0.2                                     # within 2 % of the step


def test_the_integral_stops_at_its_limit():
    c = InnerLoopConfig(rate_hz=500, rate_kp=(0.0, 0.0, 0.0), rate_ki=(100.0, 100.0, 100.0),
                        rate_i_limit=(0.05, 0.05, 0.05))
    loop, x = InnerLoop(c, "ctbr", J), np.zeros(12)
    taus = [loop.update([0.3, 1.0, -1.0, 0.0], x) for _ in range(100)]     # an error of 1 rad/s held 0.2 s
    assert taus[9][1] == pytest.approx(J[0] * 100.0 * 0.02, rel=TOL["exact"])   # 10 periods of 2 ms
    assert taus[-1][1] == pytest.approx(J[0] * 100.0 * 0.05, rel=TOL["exact"])  # clamped at 0.05 rad
    assert taus[-1][2] == pytest.approx(-J[1] * 100.0 * 0.05, rel=TOL["exact"])
    assert all(t[0] == 0.3 for t in taus)                                   # the thrust passes through


def test_commands_beyond_the_limits_are_clipped():
    c = InnerLoopConfig(max_rate=4.0, max_tilt=0.5)
    assert np.array_equal(InnerLoop(c, "ctbr", J).rate_setpoint(np.array([0.3, 9.0, -9.0, 1.0]), np.zeros(12)),
                          [4.0, -4.0, 1.0])
    w = InnerLoop(c, "ctatt", J).rate_setpoint(np.array([0.3, 0.9, 0.0, 0.0]), np.zeros(12))
    assert w[0] == pytest.approx(min(c.att_kp[0] * 0.5, 4.0), rel=TOL["exact"])


@pytest.mark.parametrize("changes, message", [
    (dict(rate_hz=0.0), "inner_loop.rate_hz must be a number of Hz > 0; found 0.0"),
    (dict(rate_hz=-500.0), "inner_loop.rate_hz must be a number of Hz > 0; found -500.0"),
    (dict(rate_hz=300.0), "inner_loop.rate_hz must run the loop a whole number of times in each 10 ms"),
    (dict(rate_hz=250.0), "one of 1000, 500, 200, 100 Hz; found 250.0"),
    (dict(rate_tau=(0.01, 0.0, 0.02)), "inner_loop.rate_tau must be 3 numbers > 0"),
    (dict(rate_kp=(1.0, 2.0)), "inner_loop.rate_kp must be 3 finite numbers >= 0"),
    (dict(att_ki=(1.0, -1.0)), "inner_loop.att_ki must be 2 finite numbers >= 0"),
    (dict(max_tilt=2.0), "inner_loop.max_tilt must be below pi/2 rad"),
])
def test_bad_settings_are_refused_naming_the_key(changes, message):
    with pytest.raises(SimInputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        InnerLoopConfig(**changes)


def test_the_wrench_level_has_no_inner_loop():
    with pytest.raises(SimInputError, match="the wrench level has no inner loop"):
        InnerLoop(InnerLoopConfig(), "wrench", J)
    with pytest.raises(SimInputError, match="level must be one of wrench, ctbr, ctatt; found 'rates'"):
        InnerLoop(InnerLoopConfig(), "rates", J)


# ----------------------------------------------------------------------------- the loop in the plant

def test_the_plant_with_its_inner_loop_flies_the_loop_on_the_rigid_body():
    """A roll-rate step on the reference simulator (nominal: the wrench is realized as commanded, and a roll about
    the hover attitude has no gyroscopic or kinematic coupling) is the loop on the pure inertia, period by period,
    however the periods are cut into calls."""
    from sim.plants.inner_loop import InnerLoopPlant
    from sim.plants.named import make_plant
    from sim.vehicles.vehicle import load_vehicle

    v = load_vehicle("crazyflie")
    J_v = np.array([v.Jxx, v.Jyy, v.Jzz])
    c = InnerLoopConfig(rate_hz=500, rate_kp=(50.0, 50.0, 50.0), rate_ki=(1000.0, 1000.0, 1000.0),
                        rate_i_limit=(10, 10, 10))
    command = np.array([v.m * 9.81, 0.5, 0.0, 0.0])
    rolls = []
    for pieces in ((10,), (3, 7), (1, 1, 1, 1, 1, 1, 1, 1, 1, 1)):       # one period of 10 ms in 1, 2, 10 calls
        plant = InnerLoopPlant(make_plant("sim", v), c, "ctbr")
        plant.reset(np.zeros(12))
        p = []
        for _ in range(30):
            for ms in pieces:
                out = plant.advance(command, ms * 1e-3)
            p.append(out.x[6])
        rolls.append(np.array(p))
    assert np.array_equal(rolls[0], rolls[1]) and np.array_equal(rolls[0], rolls[2])

    loop, w, ref = InnerLoop(c, "ctbr", J_v), np.zeros(12), []
    for k in range(150):                                  # 0.3 s at 500 Hz
        w[6] += loop.update(command, w)[1] / J_v[0] * c.period_s
        if k % 5 == 4:
            ref.append(w[6])
    assert np.max(np.abs(rolls[0] - np.array(ref))) <= 1e-9
    d = plant.describe()
    assert d["level"] == "ctbr" and d["inner_loop"]["rate_hz"] == 500 and d["plant"] == "sim"


# ----------------------------------------------------------------------------- the vehicle file's table

def test_a_vehicle_file_carries_its_inner_loop_and_reads_back_the_same(tmp_path):
    from sim.vehicles.vehicle import load_vehicle

    v = load_vehicle("crazyflie").replace(
        name="cf-loop", inner_loop=InnerLoopConfig(rate_hz=200.0, rate_kp=(70.0, 71.0, 30.0), max_tilt=0.4,
                                                   source="a test", att_wn=(20.0, 21.0), att_zeta=(0.7, 0.8)))
    path = tmp_path / "cf-loop.toml"
    path.write_text(v.to_toml())
    back = load_vehicle(str(path))
    assert back == v and back.inner_loop.rate_kp == (70.0, 71.0, 30.0) and back.inner_loop.ticks == 5
    assert back.to_dict()["inner_loop"]["rate_hz"] == 200.0 and "rate_tau" not in back.to_dict()["inner_loop"]
    assert back.inner_loop.att_wn == (20.0, 21.0)
    bare = v.replace(inner_loop=None)
    assert "inner_loop" not in bare.to_dict() and "[inner_loop]" not in bare.to_toml()   # none: none recorded


@pytest.mark.parametrize("table, message", [
    ("rate_hz = 0.0\nrate_kp = [60.0, 60.0, 30.0]", "inner_loop.rate_hz must be a number of Hz > 0; found 0.0"),
    ("rate_hz = -500.0\nrate_kp = [60.0, 60.0, 30.0]", "inner_loop.rate_hz must be a number of Hz > 0; found -500.0"),
    ("rate_hz = 500.0\nrate_kp = [60.0, 60.0]", "inner_loop.rate_kp must be 3 finite numbers >= 0"),
    ("rate_gain = 3.0", "unknown key 'inner_loop.rate_gain'"),
    ("", "inner_loop.rate_hz is missing"),                                   # an empty table: no gains
    ("rate_hz = 500.0", "inner_loop.rate_kp is missing"),
])
def test_a_bad_inner_loop_in_a_vehicle_file_is_one_line_exit_2_and_nothing_written(tmp_path, capsys, table,
                                                                                      message):
    from scenarios.cli import main

    path = tmp_path / "bad.toml"
    path.write_text(f'name = "bad"\n\n[inner_loop]\n{table}\n')
    out = tmp_path / "r.json"
    assert main(["fly", "--scenario", "hover", "--controller", "lqr", "--model", "nominal", "--vehicle", str(path),
                 "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and str(path) in err and err.count("\n") == 1 and not out.exists()
