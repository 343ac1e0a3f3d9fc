"""The theta refit of pinn.refit: it recovers known parameters from an exact physics target."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pinn.physics import rk4_increment  # noqa: E402
from pinn.refit import _fit  # noqa: E402
from sim import QuadParams  # noqa: E402
from sim.identification.excitation import make_dataset  # noqa: E402

TOL = {"relative": 1e-6}   # refit parameters against the ones that made the target


def test_refit_recovers_the_parameters_that_made_its_target():
    ds = make_dataset("small", 2, 2.0, 3)
    X = torch.as_tensor(ds.x.reshape(-1, 12)[::2])
    U = torch.as_tensor(ds.u.reshape(-1, 4)[::2])
    p = QuadParams()
    made = p.theta * np.array([1.01, 0.97, 1.03, 1.02, 1.0, 1.0])
    target = rk4_increment(X, U, torch.as_tensor(made), p)
    start = p.theta * 1.05
    scale = torch.as_tensor(np.std(ds.x_next - ds.x, axis=(0, 1)) + 1e-8)
    got = _fit(target, X, U, start, scale, p)
    assert np.allclose(got, made[:4], rtol=TOL["relative"]), (got / made[:4] - 1)
