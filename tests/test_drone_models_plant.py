"""drone-models' Crazyflie models identified from real flights, as a plant: its equations behind our frames.

The fitted roll and pitch are linear second-order systems, decoupled at hover, so a tilt command's response has a
closed form; our frame conversions (pitch and yaw change sign between NED/FRD and z-up/FLU, Euler-angle rates
become body rates) must give it back with our signs. The yaw rate command is integrated into drone-models' yaw
angle command, so a constant rate turns the vehicle at the fit's steady-state gain times that rate.
"""

import json
import math

import numpy as np
import pytest

from sim.errors import SimInputError
from sim.plants.drone_models_plant import (DroneModelsPlant, body_rates_from_euler_rates, drone_models_available,
                                           euler_rates_from_body_rates)
from sim.plants.named import make_plant

# (importing the package itself after SciPy raises: the plant loads its modules without its __init__)
pytestmark = pytest.mark.skipif(not drone_models_available(), reason="the drone-models extra is not installed")

TOL = {
    "kinematics": 1e-12,     # Euler rates -> body rates -> Euler rates, rad/s
    "step": 1e-8,            # RK4 at 1 ms against the closed-form second-order response, rad (measured ~1e-11)
    "hover": 1e-12,          # m and m/s after 1 s at the hover command
    "yaw_rate": 1e-4,        # rad/s, the steady yaw rate after 4 s
}
ACCEPT = {"nominal_ctatt_rmse_m": 0.10}   # measured 72.6 mm (SQP); the plant's roll gain is 0.8, its thrust lag 121 ms


def _second_order(c_a, c_r, c_c, cmd, t):
    """Response at ``t`` of ``a'' = c_a a + c_r a' + c_c cmd`` from rest (underdamped)."""
    wn = math.sqrt(-c_a)
    zeta = -c_r / (2.0 * wn)
    wd = wn * math.sqrt(1.0 - zeta ** 2)
    final = -c_c / c_a * cmd
    return final * (1.0 - math.exp(-zeta * wn * t) * (math.cos(wd * t) + zeta / math.sqrt(1.0 - zeta ** 2)
                                                       * math.sin(wd * t)))


@pytest.fixture(scope="module")
def plant():
    return make_plant("drone-models", "cf2x_L250", level="ctatt")


def test_euler_rates_and_body_rates_convert_both_ways():
    rng = np.random.default_rng(0)
    for _ in range(100):
        angles = rng.uniform([-1.2, -1.2, -3.0], [1.2, 1.2, 3.0])
        rates = rng.normal(0.0, 2.0, 3)
        back = euler_rates_from_body_rates(angles, body_rates_from_euler_rates(angles, rates))
        assert np.max(np.abs(back - rates)) <= TOL["kinematics"]


def test_hover_holds_the_vehicle_still(plant):
    x0 = np.zeros(12)
    x0[2] = -1.0
    plant.reset(x0)
    for _ in range(100):
        out = plant.step(plant.hover_input)
    assert np.max(np.abs(out.x - x0)) <= TOL["hover"]


@pytest.mark.parametrize("axis, cmd", [(3, 0.2), (4, -0.15)], ids=["roll", "pitch"])
def test_a_tilt_command_gives_the_fitted_second_order_response_with_our_signs(plant, axis, cmd):
    p = plant.model_params
    i = axis - 3
    plant.reset(np.zeros(12))
    u = plant.hover_input.copy()
    u[1 + i] = cmd
    worst = 0.0
    for k in range(1, 31):
        out = plant.step(u)
        want = _second_order(p["rpy_coef"][i], p["rpy_rates_coef"][i], p["cmd_rpy_coef"][i], cmd, 0.01 * k)
        worst = max(worst, abs(out.x[axis] - want))
    assert worst <= TOL["step"], worst
    # the fitted steady-state gain is not one: a roll command of 0.2 rad settles at 0.16 rad
    assert -p["cmd_rpy_coef"][i] / p["rpy_coef"][i] == pytest.approx(0.7986, abs=1e-4)


def test_a_yaw_rate_command_turns_the_vehicle_at_the_fitted_gain_times_that_rate(plant):
    p = plant.model_params
    plant.reset(np.zeros(12))
    for _ in range(400):
        out = plant.step(plant.hover_input + np.array([0.0, 0.0, 0.0, 0.3]))
    gain = -p["cmd_rpy_coef"][2] / p["rpy_coef"][2]
    assert abs(out.x[8] - gain * 0.3) <= TOL["yaw_rate"], (out.x[8], gain)
    assert out.x[5] > 0.0       # a positive yaw rate in NED turns the nose east


def test_other_levels_vehicles_and_physics_are_refused():
    with pytest.raises(SimInputError, match=r"takes commands at the 'ctatt' level only"):
        make_plant("drone-models", "cf2x_L250", level="ctbr")
    with pytest.raises(SimInputError, match=r"flies the drones its models were fitted to .* found vehicle 'crazyflie'"):
        make_plant("drone-models", "crazyflie", level="ctatt")
    with pytest.raises(SimInputError, match=r"physics must be one of"):
        DroneModelsPlant("cf2x_L250", "so_rpy_magic")
    with pytest.raises(SimInputError, match=r"plant must be one of"):
        make_plant("drone-models:so_rpy_magic", "cf2x_L250", level="ctatt")


@pytest.mark.parametrize("name", ["drone-models:so_rpy", "drone-models:so_rpy_rotor"])
def test_every_variant_holds_hover(name):
    p = make_plant(name, "cf2x_L250", level="ctatt")
    p.reset(np.zeros(12))
    for _ in range(50):
        out = p.step(p.hover_input)
    assert np.max(np.abs(out.x)) <= TOL["hover"]
    assert p.describe()["physics"] == name.split(":")[1]


@pytest.mark.slow
def test_the_nominal_model_flies_the_drone_models_plant_at_ctatt(tmp_path):
    from scenarios.cli import main

    out = tmp_path / "r.json"
    assert main(["fly", "--plant", "drone-models", "--vehicle", "cf2x_L250", "--level", "ctatt", "--model",
                 "nominal", "--controller", "sqp", "--scenario", "figure8-fast", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert (r["plant"], r["level"], r["crashed"]) == ("drone-models", "ctatt", False)
    assert r["rmse_position_m"] <= ACCEPT["nominal_ctatt_rmse_m"], r["rmse_position_m"]
