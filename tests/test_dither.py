"""Input dither on a controller's output: seeded, of the stated size, and otherwise the controller itself."""

import numpy as np
import pytest

from scenarios.closed_loop.dither import DITHER_THRUST, DITHER_TORQUE, Dithered, dither_std
from scenarios.errors import ScenarioError
from sim.params import QuadParams

#: Tolerances: the sample standard deviation of N draws against the stated one (relative), and the sample mean
#: in standard errors.
TOL = {"std_rel": 0.03, "mean_se": 4.0}
N = 20000


class Constant:
    """A controller that always sends the same input and has a deadline to forward."""

    def __init__(self, u):
        self.u = np.asarray(u, dtype=float)
        self.deadline = None

    def __call__(self, x, t):
        return self.u.copy(), {"t": t}

    def set_deadline(self, when):
        self.deadline = when


def test_the_dither_is_seeded_white_noise_of_the_stated_size():
    p = QuadParams()
    std = dither_std(p)
    w = p.m * p.g
    assert np.array_equal(std, [DITHER_THRUST * w, DITHER_TORQUE * w * p.d, DITHER_TORQUE * w * p.d,
                                DITHER_TORQUE * w * p.kq / p.kt])
    u0 = np.array([w, 0.0, 0.0, 0.0])
    c = Dithered(Constant(u0), std, seed=7)
    out = np.array([c(np.zeros(12), k * 0.01)[0] for k in range(N)])
    again = Dithered(Constant(u0), std, seed=7)
    assert np.array_equal(out[:50], [again(np.zeros(12), 0.0)[0] for _ in range(50)])
    z = np.random.default_rng([7, 0xD17E]).standard_normal((N, 4))
    assert np.array_equal(out, u0 + std * z)
    e = out - u0
    assert np.all(np.abs(e.std(axis=0) / std - 1) <= TOL["std_rel"])
    assert np.all(np.abs(e.mean(axis=0)) <= TOL["mean_se"] * std / np.sqrt(N))
    assert np.array_equal(dither_std(p, 0.0), np.zeros(4))


def test_a_dithered_controller_is_otherwise_the_controller():
    inner = Constant([1.0, 0.0, 0.0, 0.0])
    c = Dithered(inner, np.zeros(4))
    u, info = c(np.zeros(12), 0.5)
    assert np.array_equal(u, inner.u) and info == {"t": 0.5}
    c.set_deadline(3.0)
    assert inner.deadline == 3.0
    assert getattr(c, "applied", None) is None        # what the controller lacks, the wrapper lacks


@pytest.mark.parametrize("std, match", [(np.ones(3), "std must be 4 finite numbers >= 0"),
                                        ([1.0, -1.0, 0.0, 0.0], "std must be 4 finite numbers >= 0")])
def test_bad_dither_is_named(std, match):
    with pytest.raises(ScenarioError, match=match):
        Dithered(Constant(np.zeros(4)), std)
    with pytest.raises(ScenarioError, match="controller must be callable"):
        Dithered(42, np.zeros(4))
    with pytest.raises(ScenarioError, match="scale must be a finite number >= 0"):
        dither_std(QuadParams(), -1.0)
