"""Shared fixtures: small seeded datasets, built once per test session."""

import sim  # noqa: F401  (first: it pins the BLAS kernel before numpy loads, as every entry point does)
import numpy as np
import pytest

from mpc.prediction.models import PredictionModel
from sim import NoiseModel
from sim.identification.excitation import make_dataset


@pytest.fixture(scope="session")
def clean_small():
    """Noise-free small-regime dataset (10 trajectories x 10 s)."""
    return make_dataset("small", 10, 10.0, 3, noise=NoiseModel.none())


@pytest.fixture(scope="session")
def clean_aggressive():
    """Noise-free aggressive-regime dataset (10 trajectories x 10 s)."""
    return make_dataset("aggressive", 10, 10.0, 3, noise=NoiseModel.none())


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


class NaNJacobiansAfter(PredictionModel):
    """A prediction model that forwards to ``base`` and returns NaN Jacobians after ``left`` more linearizations.

    ``left`` can be set again at any time (for example after a controller's
    feed-forward fit, which linearizes the model too). ``linearizations``
    counts the calls (and can be reset the same way).
    """

    def __init__(self, base, left: int):
        self.base, self.left, self.linearizations = base, left, 0
        self.name, self.theta = base.name, base.theta

    def step(self, x, u):
        return self.base.step(x, u)

    def linearize(self, x, u):
        xn, A, B = self.base.linearize(x, u)
        self.linearizations += 1
        self.left -= 1
        if self.left < 0:
            A = A.copy()
            A[:, 0, 0] = np.nan
        return xn, A, B


@pytest.fixture
def nan_jacobians_after():
    """``nan_jacobians_after(base, n)``: ``base`` wrapped so that its Jacobians turn NaN after ``n`` calls."""
    return NaNJacobiansAfter


# ---- the slower checks' order on two processes ------------------------------------------------------------
#: Files of the slower checks that hold a test of several minutes, longest first. `pytest -m slow -n 2 --dist
#: loadfile` hands whole files to the two processes; by default pytest-xdist sends the files with the most tests
#: first, which left the 11-minute learning test to start last, alone on one process while the other idled (35.1 min
#: for the slower checks, measured). Started first, it runs beside the rest.
LONG_SLOW_FILES = ("test_learn.py", "test_sqp.py", "test_evaluation_reuse.py", "test_your_model.py")


def _slow_run(config) -> bool:
    """True for a run of the slower checks (``-m slow``)."""
    expr = config.getoption("markexpr", default="") or ""
    return "slow" in expr and "not slow" not in expr


def pytest_configure(config):
    if _slow_run(config) and hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False      # keep the order below


def pytest_collection_modifyitems(config, items):
    if _slow_run(config):
        rank = {name: i for i, name in enumerate(LONG_SLOW_FILES)}
        items.sort(key=lambda item: rank.get(item.path.name, len(rank)))    # stable: the rest keep their order
