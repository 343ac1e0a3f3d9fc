"""Training on imported flight logs: samples a log did not measure never enter a model."""

import dataclasses

import numpy as np
import pytest
import torch

from pinn.train import _TrainData, make_config, train, training_stats
from sim.excitation import make_dataset

torch.set_num_threads(1)

# tolerances of this module
STATS_RTOL = 1e-12     # statistics of the masked dataset against those of its measured samples alone
UNMEASURED = 0.15      # share of states marked as not measured


@pytest.fixture(scope="module")
def masked():
    """(clean, corrupted): one simulated dataset with 15 % of its states marked unmeasured; in the second copy those
    states are NaN."""
    ds = make_dataset("small", 6, 4.0, 2)
    rng = np.random.default_rng(0)
    x_ok = rng.random((ds.n_traj, ds.x.shape[1] + 1)) > UNMEASURED
    valid = np.stack([x_ok[:, :-1], np.ones_like(x_ok[:, :-1]), x_ok[:, 1:]], axis=-1)
    clean = dataclasses.replace(ds, valid=valid)
    x, xn = ds.x.copy(), ds.x_next.copy()
    x[~valid[..., 0]] = np.nan
    xn[~valid[..., 2]] = np.nan
    return clean, dataclasses.replace(clean, x=x, x_next=xn)


def _tiny(arch, **kw):
    return make_config(arch, "quick", 1, epochs=2, steps_per_epoch=4, batch=128, n_colloc=32, hidden=16, layers=2,
                       **kw)


@pytest.mark.parametrize("arch,recipe", [("baseline", None), ("proposed", None), ("hybrid", None)])
def test_unmeasured_states_never_reach_the_model(masked, arch, recipe):
    """Training on the clean and on the NaN-corrupted copy gives the same weights, bit for bit, and finite ones:
    a masked state is neither an input, nor a target, nor in the normalization."""
    clean, corrupted = masked
    a, b = train(clean, _tiny(arch)), train(corrupted, _tiny(arch))
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(va, vb), k
        assert bool(torch.all(torch.isfinite(va))), k
    assert np.isfinite(b.history[-1]["val"]) and b.history[-1]["val"] == a.history[-1]["val"]


def test_windows_start_at_measured_samples_and_carry_the_mask(masked):
    _, ds = masked
    data = _TrainData(ds, torch.Generator().manual_seed(0))
    states, us, ns, hist, ok = data.windows(500, 10)
    assert states.shape == (500, 11, 12) and ok.shape == (500, 11) and hist is None
    assert bool(ok[:, 0].all()) and not bool(ok.all())
    assert bool(torch.isfinite(states[ok]).all()) and bool(torch.isnan(states[~ok]).all())


def test_training_statistics_come_from_the_measured_pairs(masked):
    clean, corrupted = masked
    st = training_stats(corrupted)
    pairs = clean.pairs("train")
    dx = pairs["x_next"] - pairs["x"]
    np.testing.assert_allclose(st["out_scale"], dx.std(0) + 1e-8, rtol=STATS_RTOL)
    feats = np.concatenate([pairs["x"][:, 3:12], pairs["u"]], axis=1)
    np.testing.assert_allclose(st["in_mean"], feats.mean(0), rtol=STATS_RTOL)


def test_the_motor_lag_model_refuses_imported_logs(masked):
    with pytest.raises(ValueError, match="simulated datasets only"):
        train(masked[0], _tiny("hybrid_lag"))
