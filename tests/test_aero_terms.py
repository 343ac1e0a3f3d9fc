"""The aerodynamic term library: its forms on both backends, the fit, and a selection that claims only the terms
a plant has."""

import numpy as np
import pytest

from sim import NoiseModel
from sim.errors import SimInputError
from sim.identification.aero import (TERMS, TermSamples, fit_terms, flight_samples, select_terms,
                                     term_acceleration, term_columns)
from sim.identification.excitation import make_dataset
from sim.params import Fidelity
from sim.vehicles.vehicle import load_vehicle

# tolerances of this module
PARITY = 1e-12          # numpy against torch, float64, m/s^2
EXACT = 1e-12           # a term's acceleration against its written form, m/s^2
ROTOR_DRAG_RTOL = 1e-2  # rotor drag identified on our plant's flights (measured 2e-6 without noise, 1e-3 with)
FORM_RTOL = 2e-3        # a coefficient of the test's own plant (measured 6e-4 at most: the Euler steps' bias)

DT = 0.01
RNG_SEED = 7


def _inputs(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(0, 2, (n, 3)), rng.uniform(4000, 9000, n), rng.uniform(5, 15, n)


def test_every_term_is_its_written_form():
    """Each term's acceleration per coefficient against the form in the module's table, written out here again."""
    v, s, t = _inputs()
    vx, vy, vz = v.T
    zero = np.zeros_like(vx)
    k, c, kr, kw, kh, b = (0.3, 0.4, 0.5), (0.1, 0.2, 0.3), 2e-5, 0.05, 0.02, 0.4
    expected = {
        "linear_drag": (k, (-k[0] * vx, -k[1] * vy, -k[2] * vz)),
        "quadratic_drag": (c, (-c[0] * vx * np.abs(vx), -c[1] * vy * np.abs(vy), -c[2] * vz * np.abs(vz))),
        "rotor_drag": ((kr,), (-kr * s * vx, -kr * s * vy, zero)),
        "thrust_loss": ((kw, kh), (zero, zero, t * (-kw * vz + kh * (vx ** 2 + vy ** 2)))),
        "thrust_bias": ((b,), (zero, zero, zero + b)),
    }
    assert set(expected) == set(TERMS)
    for name, (coefs, want) in expected.items():
        got = term_acceleration({name: coefs}, v, s, t)
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, atol=EXACT)
        assert len(term_columns(name, v, s, t)) == len(TERMS[name].coefficients) == len(TERMS[name].units)


def test_the_forms_are_the_same_on_numpy_and_torch():
    torch = pytest.importorskip("torch")
    v, s, t = _inputs(seed=1)
    terms = {n: tuple(np.linspace(0.1, 0.5, len(TERMS[n].coefficients))) for n in TERMS}
    a_np = term_acceleration(terms, v, s, t)
    a_t = term_acceleration(terms, torch.tensor(v), torch.tensor(s), torch.tensor(t))
    for a, b in zip(a_np, a_t):
        assert isinstance(b, torch.Tensor)
        np.testing.assert_allclose(b.numpy(), a, atol=PARITY)


def _plant_flights(drag, n_flights, seed, amplitudes=None, bias=0.0):
    """Flights of the test's own translational plant: a commanded acceleration the rigid body explains, plus
    ``drag(v)`` and a thrust bias ``bias`` (m/s^2 on z); Euler steps of 1 ms, sampled every 10 ms."""
    rng = np.random.default_rng(seed)
    amplitudes = amplitudes or [1.0] * n_flights
    out = []
    for i, amp in enumerate(amplitudes):
        steps = 600
        f = np.cumsum(rng.normal(0, 0.4 * amp, (steps, 3)), axis=0)
        f -= f.mean(axis=0)
        v = np.zeros(3)
        vs, res = [], []
        for k in range(steps):
            v0 = v.copy()
            for _ in range(10):
                v = v + 1e-3 * (f[k] + drag(v) + np.array([0.0, 0.0, bias]))
            vs.append(0.5 * (v0 + v))
            res.append((v - v0) / DT - f[k])
        vs = np.array(vs)
        out.append(TermSamples(f"plant{i}", vs, np.full(steps, 8000.0), np.full(steps, 9.81), np.array(res)))
    return out


@pytest.mark.parametrize("noise", ["none", "default"])
def test_our_plants_rotor_drag_is_found_and_recovered(noise):
    """Our simulator with its rotor drag alone, with and without its measurement noise: the selection claims the
    rotor drag and nothing else, with the plant's coefficient (rotor_drag / m). Without noise it lies inside the
    fit's 95 % interval. With noise the estimate is 0.08 % high and its interval, 0.08 % wide each side, just misses
    it: the attitude noise enters both the body velocity the term reads and the body-frame acceleration it fits."""
    v = load_vehicle("crazyflie")
    p = v.params
    drag = 2e-6
    ds = make_dataset("small", 12, 10.0, 3, noise=NoiseModel.none() if noise == "none" else None,
                      fidelity=Fidelity(rotor_drag=drag), vehicle=v)
    flights = [flight_samples(f"f{i}", np.concatenate([ds.x[i], ds.x_next[i, -1:]]), ds.rotor_speed[i], p)
               for i in range(12)]
    sel = select_terms(flights[:9], flights[9:])
    assert sel.terms == ("rotor_drag",), sel.steps
    if noise == "none":
        assert sel.fit.low["k_r"] <= drag / p.m <= sel.fit.high["k_r"], sel.fit
    assert sel.fit.values["k_r"] == pytest.approx(drag / p.m, rel=ROTOR_DRAG_RTOL)
    assert sel.validation_rmse < sel.validation_rmse_none


def test_a_plant_with_the_library_forms_gets_them_back():
    """Linear and quadratic drag and a thrust bias, set up in the test: each is claimed, with its coefficients."""
    k, c, b = np.array([0.4, 0.3, 0.5]), np.array([0.2, 0.25, 0.1]), 0.3
    fl = _plant_flights(lambda v: -k * v - c * v * np.abs(v), 8, RNG_SEED, amplitudes=[0.5, 0.7, 0.9, 1.1, 1.3,
                                                                                          1.5, 0.8, 1.2], bias=b)
    sel = select_terms(fl[:6], fl[6:])
    assert set(sel.terms) == {"linear_drag", "quadratic_drag", "thrust_bias"}, sel.steps
    got = sel.fit.values
    np.testing.assert_allclose([got["k_x"], got["k_y"], got["k_z"]], k, rtol=FORM_RTOL)
    np.testing.assert_allclose([got["c_x"], got["c_y"], got["c_z"]], c, rtol=FORM_RTOL)
    assert got["b"] == pytest.approx(b, rel=FORM_RTOL)


def test_a_drag_the_library_lacks_is_not_claimed_as_another_term():
    """A cubic drag, set up in the test: the library has no cubic form. Linear and quadratic drag each lower the
    validation error, but the samples below and above the median speed disagree on their coefficients (or give them
    the wrong sign), so neither is claimed; nor is any other term."""
    fl = _plant_flights(lambda v: -0.3 * v ** 3, 8, RNG_SEED, amplitudes=[0.5, 0.7, 0.9, 1.1, 1.3, 1.5, 0.8, 1.2])
    sel = select_terms(fl[:6], fl[6:])
    assert sel.terms == (), sel.steps
    refused = {s.term: s.reason for s in sel.steps}
    assert "changes with the speed" in refused["quadratic_drag"] or "not physical" in refused["quadratic_drag"]
    assert sel.fit.values == {}


def test_bad_input_is_refused_by_name():
    v, s, t = _inputs(5)
    with pytest.raises(SimInputError, match="cubic_drag"):
        term_columns("cubic_drag", v, s, t)
    with pytest.raises(SimInputError, match="linear_drag has 3|term 'linear_drag' has 3"):
        term_acceleration({"linear_drag": (0.1,)}, v, s, t)
    with pytest.raises(SimInputError, match="residual must have shape"):
        TermSamples("x", v, s, t, np.zeros((4, 3)))
    with pytest.raises(SimInputError, match="v holds 1 non-finite"):
        TermSamples("x", np.where(np.arange(15).reshape(5, 3) == 4, np.nan, v), s, t, np.zeros((5, 3)))
    fl = _plant_flights(lambda v: -0.3 * v, 3, 0)
    with pytest.raises(SimInputError, match="needs training samples"):
        select_terms([], fl)
    with pytest.raises(SimInputError, match="needs validation samples"):
        select_terms(fl, [])
    with pytest.raises(SimInputError, match="needs validation samples"):
        select_terms(fl, [fl[0].subset(np.zeros(len(fl[0].v), dtype=bool))])


def test_flight_samples_leave_out_the_periods_they_cannot_use():
    """A state that is NaN though flagged measured, an unmeasured state and a NaN rotor speed each cost the periods
    they touch, and nothing else: the samples kept are those of the clean flight less those."""
    v = load_vehicle("crazyflie")
    ds = make_dataset("small", 1, 2.0, 0, noise=NoiseModel.none(), vehicle=v)
    x = np.concatenate([ds.x[0], ds.x_next[0, -1:]])
    n = ds.rotor_speed[0].copy()
    clean = flight_samples("clean", x, n, v.params)
    x[10, 9] = np.nan                      # periods 9 and 10
    ok = np.ones(len(x), dtype=bool)
    ok[50] = False                         # periods 49 and 50
    n[100, 2] = np.nan                     # period 100
    dirty = flight_samples("dirty", x, n, v.params, ok=ok)
    assert len(dirty.v) == len(clean.v) - 5
    keep = np.setdiff1d(np.arange(len(clean.v)), [9, 10, 49, 50, 100])
    np.testing.assert_array_equal(dirty.residual, clean.residual[keep])
