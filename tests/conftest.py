"""Shared fixtures: small seeded datasets, built once per test session."""

import sim  # noqa: F401  (first: it pins the BLAS kernel before numpy loads, as every entry point does)
import numpy as np
import pytest

from sim import NoiseModel
from sim.excitation import make_dataset


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
