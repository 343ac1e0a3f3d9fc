"""Identification with the motor lag: the rotor model, its derivatives, its bound and the classical estimator."""

from __future__ import annotations

import numpy as np
import pytest

from sim.identification.excitation import make_dataset
from sim.identification.motor_lag import estimate_with_lag, lag_fisher, rotor_trajectory, true_theta7
from sim.params import HIGH_FIDELITY, Fidelity, QuadParams

#: Tolerances of this module.
TOL = {
    "rotor_vs_simulator": 1e-9,     # relative: the exact one-period lag against the simulator's RK4 substeps
    "rotor_fd": 1e-6,               # relative: d n / d theta against central differences
    "sigma": 3.0,                   # CRLB standard deviations within which every parameter must be identified
    "std_vs_crlb": 0.1,             # the fit's own standard deviations against the bound (relative)
}
LAG_ONLY = Fidelity(motor_tau=0.03)


@pytest.fixture(scope="module")
def data():
    """Ten 10 s small-angle flights on the high-fidelity simulator and on one with the motor lag alone."""
    out = {}
    for name, fid in (("lag", LAG_ONLY), ("high", HIGH_FIDELITY)):
        out[name] = make_dataset("small", 10, 10.0, 0, fidelity=fid, with_clean=True)
    return out


def test_the_rotor_model_reproduces_the_simulators_rotor_speeds(data):
    """Driven by the logged commands from the first command's speed, the rotor model gives the simulator's own rotor
    speeds (the noise-free telemetry), period after period, saturated periods included."""
    _, clean = data["high"]
    p = QuadParams(**clean.meta["params"])
    n, _ = rotor_trajectory(clean.u, true_theta7(clean), p)
    rel = np.abs(n[:, 1:] - clean.rotor_speed) / p.n_hover
    assert np.max(rel) < TOL["rotor_vs_simulator"], np.max(rel)


def test_the_rotor_models_sensitivities_match_central_differences(data):
    _, clean = data["lag"]
    p = QuadParams(**clean.meta["params"])
    u = clean.u[:2, :200]
    theta = true_theta7(clean)
    _, dn = rotor_trajectory(u, theta, p)
    for j in range(7):
        h = 1e-6 * theta[j]
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        fd = (rotor_trajectory(u, tp, p)[0] - rotor_trajectory(u, tm, p)[0]) / (2 * h)
        scale = max(np.max(np.abs(fd)), 1e-12)
        assert np.max(np.abs(dn[..., j] - fd)) < TOL["rotor_fd"] * scale, j


@pytest.mark.parametrize("fidelity", ["lag", "high"])
def test_the_lag_aware_estimator_identifies_all_seven_parameters_within_three_sigma(data, fidelity):
    """With the lag in its model the classical estimator identifies tau_m and the six nominal parameters within
    3 CRLB sigma of the same model, on the motor lag alone and on the whole high-fidelity simulator (rotor drag and
    gyroscopic torque unmodelled). Without the lag, the same flights give inertia errors of about 50 %."""
    ds, clean = data[fidelity]
    bound = lag_fisher(clean)
    est = estimate_with_lag(ds)
    truth = true_theta7(ds)
    sigma = np.abs(est.theta - truth) / bound.crlb_std
    assert est.converged
    assert np.all(sigma < TOL["sigma"]), dict(zip(("m", "Jxx", "Jyy", "Jzz", "kt", "kq", "tau_m"), sigma.round(2)))
    np.testing.assert_allclose(est.std_rel, bound.crlb_rel, rtol=TOL["std_vs_crlb"])


def test_without_the_lag_the_same_flights_give_inertias_tens_of_percent_off(data):
    """The contrast: the nominal six-parameter fit of the same high-fidelity flights absorbs the lag."""
    from sim.identification.estimate import estimate_theta

    ds, _ = data["high"]
    est = estimate_theta(ds)
    err = np.abs(est.theta - QuadParams().theta) / QuadParams().theta
    assert np.max(err[1:4]) > 0.2, err
