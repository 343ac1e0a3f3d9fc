"""Rotor units: a vehicle described in rad/s or RPM flies exactly as the same vehicle in normalized units.

The rotor-limit constraints of the MPCs are written as rotor loads ``n^2 / n_max^2``
(``sim.vehicles.rotors.load_matrix``),
so the QP a controller solves does not depend on the unit its vehicle file gives rotor speeds in. Written as
``M^-1 u <= n_max^2`` they reached 1e7 beside dynamics rows of order one, and the SQP took ten times as long on
RotorPy's Crazyflie (2500 rad/s) as on the same vehicle with n_max = 1.
"""

import dataclasses
import math

import numpy as np
import pytest

from scenarios.cli import main
from scenarios.closed_loop.library import get_scenario
from scenarios.closed_loop.runner import RunSpec, fly
from sim.params import GRAVITY
from sim.vehicles.rotors import load_matrix, mixer_matrix
from sim.vehicles.vehicle import MIN_THRUST_TO_WEIGHT, Vehicle, load_vehicle

TOL = {
    "load_rel": 1e-12,          # L M n^2 = n^2 / n_max^2, relative to the largest load
    "flight_m": 1e-9,           # the same flight in three rotor units: largest state difference (measured 3e-14)
}
#: Rotor units relative to rad/s: one unit is this many rad/s.
UNITS = {"rad/s": 1.0, "rpm": 2.0 * math.pi / 60.0}


def in_unit(v: Vehicle, rad_per_unit: float | None) -> Vehicle:
    """``v`` with its rotor speeds in another unit (None: normalized, n_max = 1); the same physical vehicle."""
    return v.normalized() if rad_per_unit is None else v.in_rotor_unit(rad_per_unit, name=f"{v.name}-{rad_per_unit}")


def write_vehicle(path, v: Vehicle):
    path.write_text(v.to_toml())
    return path


def test_a_vehicle_in_another_rotor_unit_has_the_same_thrusts_and_forces():
    v = load_vehicle("hummingbird")
    for s in (*UNITS.values(), None):
        w = in_unit(v, s)
        n_old = 0.7 * v.n_max_value
        n_new = n_old * w.n_max_value / v.n_max_value
        assert w.kt * n_new ** 2 == pytest.approx(v.kt * n_old ** 2, rel=1e-14)
        assert w.kq * n_new ** 2 == pytest.approx(v.kq * n_old ** 2, rel=1e-14)
        assert w.rotor_drag * n_new == pytest.approx(v.rotor_drag * n_old, rel=1e-14)
        assert w.k_z * n_new == pytest.approx(v.k_z * n_old, rel=1e-14)
    assert v.normalized().n_max_value == 1.0


def test_a_vehicle_file_written_by_to_toml_reads_back_the_same(tmp_path):
    for name in ("crazyflie", "hummingbird", "rolling-spider"):
        v = load_vehicle(name)
        back = load_vehicle(write_vehicle(tmp_path / f"{name}.toml", v))
        assert back == v.replace(n_max=v.n_max_value)


def test_the_load_matrix_gives_each_rotor_its_share_of_n_max_squared():
    rng = np.random.default_rng(3)
    for name in ("crazyflie", "hummingbird", "rolling-spider"):
        p = load_vehicle(name).params
        n_sq = rng.uniform(0.0, p.n_max_sq, size=(20, 4))
        w = n_sq @ mixer_matrix(p).T
        load = w @ load_matrix(p).T
        assert np.max(np.abs(load - n_sq / p.n_max_sq)) <= TOL["load_rel"]


def test_the_load_matrix_is_the_same_in_every_rotor_unit():
    v = load_vehicle("crazyflie")
    ref = load_matrix(in_unit(v, None).params)
    for s in UNITS.values():
        L = load_matrix(in_unit(v, s).params)
        assert np.max(np.abs(L - ref)) <= TOL["load_rel"] * np.max(np.abs(ref))
    # Written as M^-1 (the old rows) the entries differ by n_max^2 = 6.25e6 between rad/s and normalized units.
    old_rad = np.linalg.inv(mixer_matrix(v.params))
    assert np.max(np.abs(old_rad)) / np.max(np.abs(ref)) == pytest.approx(v.params.n_max_sq, rel=1e-9)


@pytest.mark.parametrize("controller", ["sqp", "ltv"])
def test_a_crazyflie_in_rad_s_and_rpm_flies_exactly_as_in_normalized_units(tmp_path, controller):
    v = load_vehicle("crazyflie")
    sc = dataclasses.replace(get_scenario("figure8-fast"), duration_s=1.0)
    flown = {}
    for label, s in (("normalized", None), *UNITS.items()):
        path = write_vehicle(tmp_path / f"cf-{label.replace('/', '-')}.toml", in_unit(v, s))
        result, trace = fly(RunSpec("figure8-fast", controller, "nominal", vehicle=str(path)), scenario=sc)
        assert result["error"] is None and not result["crashed"] and result["solver_failures"] == 0
        flown[label] = trace
    ref = flown["normalized"]
    for label in UNITS:
        assert np.max(np.abs(flown[label]["x"] - ref["x"])) <= TOL["flight_m"], label
        # The same QP in every unit: the same number of iterations in every period.
        assert np.array_equal(flown[label]["iterations"], ref["iterations"]), label


def test_a_vehicle_that_cannot_lift_1_2_times_its_weight_is_refused():
    with pytest.raises(ValueError, match=r"lift 0\.102 times its weight .* at least 1\.2"):
        Vehicle(name="weak", m=1.0, kt=1e-6, n_max=500.0)
    # Just enough: 1.2 times the weight.
    kt = MIN_THRUST_TO_WEIGHT * 1.0 * GRAVITY / 4.0
    Vehicle(name="enough", m=1.0, kt=kt * (1 + 1e-12), n_max=1.0)
    with pytest.raises(ValueError, match="at least 1.2"):
        Vehicle(name="short", m=1.0, kt=kt * (1 - 1e-9), n_max=1.0)


WEAK = "m = 1.0\nkt = 1e-6\nn_max = 500\n"


@pytest.mark.parametrize("command", [
    ["fly", "--model", "nominal", "--controller", "lqr", "--scenario", "hover", "--json", "{out}/r.json"],
    ["data", "--regime", "small", "--n-traj", "2", "--duration", "1", "--out", "{out}/d.npz"],
    ["run", "--out", "{out}/run"],
    ["study", "--out", "{out}/study", "--no-publish"],
])
def test_every_command_refuses_a_vehicle_that_cannot_hover_and_writes_nothing(tmp_path, capsys, monkeypatch, command):
    import scenarios.studies.campaign as campaign
    import scenarios.closed_loop.runner as runner
    import scenarios.studies.zoo as zoo

    for mod, fn in ((campaign, "run_main_job"), (zoo, "run_study"), (runner, "fly")):
        monkeypatch.setattr(mod, fn, lambda *a, **k: pytest.fail("started before reading the vehicle"))
    weak = tmp_path / "weak.toml"
    weak.write_text(WEAK)
    out = tmp_path / "out"
    out.mkdir()
    rc = main([c.format(out=out) for c in command] + ["--vehicle", str(weak)])
    err = capsys.readouterr().err
    assert rc == 2 and "weak.toml" in err and "times its weight" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert list(out.iterdir()) == []
