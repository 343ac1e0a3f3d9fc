"""The classical estimator (weighted nonlinear least squares) against the Cramér-Rao bound of the same data."""

import numpy as np
import pytest

from sim import NoiseModel, QuadParams
from sim.errors import SimInputError
from sim.identification.estimate import estimate_theta
from sim.identification.excitation import make_dataset
from sim.identification.fisher import fisher_from_dataset

TOL = {
    "sigma": 3.0,            # |theta-hat - theta| within this many CRLB standard deviations, every parameter
    "own_vs_crlb": 0.25,     # the estimator's own standard deviation within 25 % of the CRLB's
    "pilot_vs_direct": 0.1,  # pilot-then-full and direct fits agree within 0.1 of a CRLB sigma
}
P = QuadParams()
SEED = 11


@pytest.fixture(scope="module")
def small_pair():
    """A small nominal dataset (10 flights x 5 s, default noise) and its noise-free twin."""
    noisy = make_dataset("small", 10, 5.0, SEED)
    clean = make_dataset("small", 10, 5.0, SEED, noise=NoiseModel.none())
    return noisy, clean


@pytest.fixture(scope="module")
def small_fit(small_pair):
    noisy, clean = small_pair
    est = estimate_theta(noisy)
    fim = fisher_from_dataset(clean.subset(clean.split == 0), "wrench", NoiseModel())
    return est, fim


def test_recovers_theta_within_three_crlb_sigma(small_fit):
    est, fim = small_fit
    assert est.converged
    z = (est.theta - P.theta) / fim.crlb_std
    assert np.all(np.abs(z) <= TOL["sigma"]), f"|error| / CRLB sigma = {np.round(z, 2)}"


def test_its_own_standard_deviation_is_the_crlb(small_fit):
    """The Gauss-Newton covariance at the estimate and the Fisher information of the same samples agree."""
    est, fim = small_fit
    assert est.n_transitions == fim.n_samples
    assert np.allclose(est.std_rel, fim.crlb_rel, rtol=TOL["own_vs_crlb"]), (est.std_rel, fim.crlb_rel)


def test_the_pilot_stage_reaches_the_direct_fit(small_pair, monkeypatch):
    """A pilot on every 3rd transition, then fixed weights, ends where the fit on all transitions does."""
    noisy, clean = small_pair
    direct = estimate_theta(noisy)
    import sim.identification.estimate as est_mod

    monkeypatch.setattr(est_mod, "PILOT_SIZE", direct.n_transitions // 3)
    piloted = estimate_theta(noisy)
    gap = np.abs(piloted.theta - direct.theta) / (direct.std_rel * direct.theta)
    assert np.all(gap <= TOL["pilot_vs_direct"]), gap


def test_saturated_samples_are_dropped_only_when_the_command_is_logged():
    commanded = make_dataset("aggressive", 4, 5.0, 1)
    realized = make_dataset("aggressive", 4, 5.0, 1, inputs="realized")
    sat = np.any(commanded.saturated[commanded.split == 0], axis=-1).sum()
    assert sat > 0, "the test needs saturated samples"
    a, b = estimate_theta(commanded, max_iter=1), estimate_theta(realized, max_iter=1)
    assert b.n_transitions - a.n_transitions == sat


@pytest.mark.parametrize("kwargs, message", [
    ({"theta0": [1.0, 2.0]}, "theta0 must be 6 positive"),
    ({"theta0": -P.theta}, "theta0 must be 6 positive"),
    ({"split": "training"}, "split must be one of"),
    ({"noise": NoiseModel.none()}, "weights residuals by the noise"),
])
def test_bad_arguments_are_named(small_pair, kwargs, message):
    with pytest.raises(SimInputError, match=message):
        estimate_theta(small_pair[0], **kwargs)


def test_realized_inputs_need_a_simulator_without_motor_lag():
    from sim.params import HIGH_FIDELITY

    with pytest.raises(SimInputError, match="without motor lag"):
        make_dataset("small", 1, 0.1, 0, fidelity=HIGH_FIDELITY, inputs="realized")
