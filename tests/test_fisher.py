"""Fisher information: AD sensitivities vs finite differences, rank and null direction."""

import numpy as np
import pytest

from sim import NoiseModel, QuadParams, THETA_NAMES, rk4_step
from sim.equations.dynamics import rates
from sim.identification.fisher import fisher_from_dataset, fisher_information, rotor_sensitivities, sensitivities
from sim.vehicles.rotors import allocate, wrench_from_rotor_sq

TOL = {
    "fd_relative": 1e-5,     # AD sensitivities vs central differences (column-wise norm)
    "fd_step": 1e-4,         # relative parameter step of the central differences
    "null_cos": 0.999,       # |cos| of the null vector with the scale direction
}
P = QuadParams()


def numpy_step(p, x, u, inputs):
    """One control period with the numpy model (independent of the CasADi code)."""
    w = u if inputs == "wrench" else wrench_from_rotor_sq(u, p)
    return rk4_step(lambda s: rates(s, w, p), x, 1e-3, 10)


def samples(ds, every=23):
    x = ds.x.reshape(-1, 12)[::every]
    w = ds.wrench.reshape(-1, 4)[::every]
    return x, w


@pytest.mark.parametrize("inputs", ["wrench", "motor"])
def test_sensitivities_match_central_differences(clean_aggressive, inputs):
    x, w = samples(clean_aggressive)
    u = w if inputs == "wrench" else np.clip(allocate(w, P), 0, None)
    S, A = sensitivities(x, u, P, inputs)
    theta = P.theta
    nonzero = 0
    for i, name in enumerate(THETA_NAMES):
        h = TOL["fd_step"] * theta[i]
        up, dn = theta.copy(), theta.copy()
        up[i] += h
        dn[i] -= h
        fd = (numpy_step(P.with_theta(up), x, u, inputs) - numpy_step(P.with_theta(dn), x, u, inputs)) / (2 * h)
        scale = np.linalg.norm(fd)
        if scale == 0:  # kt, kq do not enter the rigid body under wrench inputs
            assert inputs == "wrench" and name in ("kt", "kq")
            assert np.all(S[:, :, i] == 0)
            continue
        nonzero += 1
        assert np.linalg.norm(S[:, :, i] - fd) / scale < TOL["fd_relative"], name
    assert nonzero == (4 if inputs == "wrench" else 6)
    # The state Jacobian too (used for the residual covariance).
    k = 5
    e = np.zeros(12)
    e[9] = 1e-6
    fd_a = (numpy_step(P, x[k] + e, u[k], inputs) - numpy_step(P, x[k] - e, u[k], inputs)) / 2e-6
    assert np.linalg.norm(A[k, :, 9] - fd_a) / np.linalg.norm(fd_a) < TOL["fd_relative"]


def test_rotor_telemetry_sensitivities_match_central_differences(clean_aggressive):
    _, w = samples(clean_aggressive)
    n, dn = rotor_sensitivities(w, P)
    np.testing.assert_allclose(n ** 2, allocate(w, P), rtol=1e-12, atol=1e-12)
    theta = P.theta
    for i in (4, 5):
        h = TOL["fd_step"] * theta[i]
        up, lo = theta.copy(), theta.copy()
        up[i] += h
        lo[i] -= h
        fd = (np.sqrt(allocate(w, P.with_theta(up))) - np.sqrt(allocate(w, P.with_theta(lo)))) / (2 * h)
        ok = np.isfinite(fd) & np.isfinite(dn[:, :, i]) & (n > 0.1 * P.n_hover)
        assert np.linalg.norm(dn[:, :, i][ok] - fd[ok]) / np.linalg.norm(fd[ok]) < TOL["fd_relative"]
    assert np.all(dn[:, :, :4] == 0)


@pytest.mark.parametrize("fixture", ["clean_small", "clean_aggressive"])
def test_wrench_inputs_identify_all_six(fixture, request):
    res = fisher_from_dataset(request.getfixturevalue(fixture), "wrench")
    assert res.rank == 6
    assert np.all(np.isfinite(res.crlb_rel)) and np.all(res.crlb_rel > 0)
    # Without the rotor telemetry kt and kq are invisible: rank 4.
    ds = request.getfixturevalue(fixture)
    dyn_only = fisher_information(ds.x.reshape(-1, 12)[::5], ds.wrench.reshape(-1, 4)[::5],
                                  P, inputs="wrench", rotor_telemetry=False)
    assert dyn_only.rank == 4


@pytest.mark.parametrize("fixture", ["clean_small", "clean_aggressive"])
def test_motor_inputs_have_the_scale_direction_as_null_vector(fixture, request):
    res = fisher_from_dataset(request.getfixturevalue(fixture), "motor")
    assert res.rank == 5
    null_abs = res.eigenvectors[:, 0] * P.theta  # back to absolute units
    cos = abs(null_abs @ P.theta) / (np.linalg.norm(null_abs) * np.linalg.norm(P.theta))
    assert cos > TOL["null_cos"]
    assert res.scale_direction_cos > TOL["null_cos"]
    assert np.all(np.isinf(res.crlb_rel))


def test_more_data_tightens_the_bound(clean_small):
    ds = clean_small
    half = fisher_information(ds.x[:5].reshape(-1, 12), ds.wrench[:5].reshape(-1, 4), P,
                              rotor_mask=ds.saturated[:5].reshape(-1, 4))
    full = fisher_from_dataset(ds, "wrench")
    # Twice the data: every bound shrinks, by roughly sqrt(2).
    ratio = half.crlb_rel / full.crlb_rel
    assert np.all(ratio > 1.2) and np.all(ratio < 1.7), ratio


def test_bad_input():
    with pytest.raises(ValueError, match="inputs"):
        sensitivities(np.zeros((2, 12)), np.zeros((2, 4)), P, "torque")
    with pytest.raises(ValueError, match="noise"):
        fisher_information(np.zeros((2, 12)), np.zeros((2, 4)), P, NoiseModel.none())
    with pytest.raises(ValueError, match="same number of samples"):
        fisher_information(np.zeros((3, 12)), np.zeros((2, 4)), P)
