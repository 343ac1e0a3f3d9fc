"""crazyflow's Crazyflie as a plant: its first-principles model and Mellinger loops behind our frames and levels.

What has a known answer: a vehicle at its hover command stays where it is (any position, yaw, payload); a tilted
vehicle's first millisecond accelerates it as gravity plus its thrust along the tilted body axis (NED); a wind
force's first millisecond accelerates it by the wind's acceleration (crazyflow's drag is zero at rest); a rate
command turns the vehicle about that axis only, with our signs; crazyflow runs in a child process, so two flights
of the same commands are equal bit for bit. The nominal models of each level fly figure8-fast on it.
"""

import numpy as np
import pytest

from scenarios.closed_loop.runner import RunSpec, fly
from sim.errors import SimInputError
from sim.plants.crazyflow_plant import CrazyflowPlant, crazyflow_available
from sim.plants.named import make_plant

pytestmark = pytest.mark.skipif(not crazyflow_available(), reason="the crazyflow extra is not installed")

TOL = {
    "hover": 1e-9,           # m, rad and m/s after 1 s at the hover command (measured below 1e-15)
    "first_ms": 1e-6,        # relative: the first millisecond's acceleration against the closed form
    "decoupled": 1e-12,      # rad and rad/s: the axes a rate command does not turn
}
ACCEPT = {   # RMSE on figure8-fast, m: measured 225 mm (ctbr) and 53 mm (ctatt) with the SQP and the LTV-MPC
    "ctbr": 0.30,
    "ctatt": 0.10,
}
START = np.array([1.0, -2.0, -3.0, 0.0, 0.0, 0.7, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module", params=["ctbr", "ctatt"])
def plant(request):
    p = make_plant("crazyflow", "cf2x_L250", level=request.param)
    yield p
    p.close()


def test_the_hover_command_holds_the_vehicle_where_it_is(plant):
    plant.reset(START)
    for _ in range(100):
        out = plant.step(plant.hover_input)
    assert np.max(np.abs(out.x - START)) <= TOL["hover"]
    assert abs(out.wrench[0] - plant.hover_input[0]) <= 1e-9 * plant.hover_input[0]


def test_a_payload_is_carried_by_its_own_hover_command():
    p = make_plant("crazyflow", "cf2x_L250", level="ctatt", payload_kg=0.005)
    try:
        assert p.hover_input[0] == pytest.approx((p.model_mass + 0.005) * 9.81, rel=1e-12)
        for _ in range(2):                 # a second reset keeps the payload
            p.reset(START)
            for _ in range(100):
                out = p.step(p.hover_input)
            assert np.max(np.abs(out.x - START)) <= TOL["hover"]
    finally:
        p.close()


def test_a_tilted_vehicle_accelerates_along_its_thrust_in_ned(plant):
    """Roll 0.3 rad, pitch -0.2 rad, yaw 1.0 rad: the velocity after 1 ms is (g e3 - T/m R e3) dt, our R."""
    from sim.equations.dynamics import rotation_matrix

    x0 = np.zeros(12)
    x0[3:6] = (0.3, -0.2, 1.0)
    plant.reset(x0)
    out = plant.advance(plant.hover_input, 0.001)
    thrust = plant.hover_input[0]
    expected = (np.array([0.0, 0.0, 9.81]) - thrust / plant.model_mass * np.asarray(rotation_matrix(*x0[3:6])).reshape(3, 3)[:, 2]) * 0.001
    assert np.max(np.abs(out.x[9:12] - expected)) <= TOL["first_ms"] * np.max(np.abs(expected))


def test_a_wind_accelerates_the_vehicle_by_its_acceleration():
    a = np.array([0.5, -0.3, 0.2])
    p = make_plant("crazyflow", "cf2x_L250", level="ctbr", wind=lambda t: a)
    try:
        p.reset(np.zeros(12))
        out = p.advance(p.hover_input, 0.001)
        assert np.max(np.abs(out.x[9:12] / 0.001 - a)) <= TOL["first_ms"] * np.max(np.abs(a))
        assert np.max(np.abs(out.x[3:9])) <= TOL["decoupled"]       # a force at the centre of mass: no turn
    finally:
        p.close()


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_rate_command_turns_the_vehicle_about_that_axis_only_with_our_signs(axis):
    p = make_plant("crazyflow", "cf2x_L250", level="ctbr")
    try:
        p.reset(np.zeros(12))
        u = p.hover_input.copy()
        u[1 + axis] = 0.5
        for _ in range(5):
            out = p.step(u)
        others = [k for k in range(3) if k != axis]
        assert out.x[3 + axis] > 0 and out.x[6 + axis] > 0.2          # measured: 0.48 rad/s (p, q), 0.23 (r)
        assert np.max(np.abs(out.x[3:6][others])) <= TOL["decoupled"]
        assert np.max(np.abs(out.x[6:9][others])) <= TOL["decoupled"]
    finally:
        p.close()


def test_two_flights_of_the_same_commands_are_equal_bit_for_bit():
    rng = np.random.default_rng(3)
    us = rng.normal(0.0, [0.02, 0.5, 0.5, 0.3], (40, 4))
    runs = []
    for _ in range(2):
        p = make_plant("crazyflow", "cf2x_L250", level="ctbr")
        try:
            p.reset(START)
            runs.append(np.array([p.step(p.hover_input + u).x for u in us]))
        finally:
            p.close()
    assert np.array_equal(runs[0], runs[1])


def test_crazyflow_refuses_the_wrench_level_and_other_vehicles_naming_them():
    with pytest.raises(SimInputError, match="'wrench'"):
        CrazyflowPlant("cf2x_L250", "wrench")
    with pytest.raises(SimInputError, match="'crazyflie'"):
        CrazyflowPlant("crazyflie", "ctbr")
    with pytest.raises(SimInputError, match="high fidelity"):
        make_plant("crazyflow", "cf2x_L250", level="ctbr", high_fidelity=True)


@pytest.mark.parametrize("level", ["ctbr", "ctatt"])
def test_the_nominal_model_of_each_level_flies_figure8_fast_on_crazyflow(level):
    r, _ = fly(RunSpec("figure8-fast", "sqp", "nominal", plant="crazyflow", vehicle="cf2x_L250", level=level))
    assert not r["crashed"]
    assert r["rmse_position_m"] <= ACCEPT[level]
