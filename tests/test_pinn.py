"""PINN models, physics losses, schedules, training and metrics."""

import numpy as np
import pytest
import torch

from pinn.metrics import one_step_mae, rollout_mae
from pinn.models import ARCHITECTURES, build_model
from pinn.physics import dynamics_torch, mechanical_energy, power_balance, rk4_increment, rotor_sq_from_wrench
from pinn.train import (CURRICULUM_HORIZONS, SS_MAX, curriculum_horizon, make_config, physics_residual,
                        sampling_probability, train, training_stats)
from sim import NoiseModel, QuadParams, Simulator, dynamics
from sim.rotors import allocate

TOL = {
    "backend": 1e-12,          # torch (float64) vs numpy dynamics, relative to column scale
    "residual_truth": 1e-6,    # physics residual with the true step and theta-hat = truth
    "residual_biased": 1e-2,   # ... and at least this with the +30 % guess
    "jacobian": 1e-10,         # forward-mode Jacobian vs autograd (float64, absolute)
    "energy_rate": 1e-6,       # d/dt mechanical energy vs power balance (relative)
}
P = QuadParams()

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def small_ds():
    from sim.excitation import make_dataset
    return make_dataset("small", 20, 10.0, 0)


def fake_stats():
    g = torch.Generator().manual_seed(0)
    return {"in_mean": torch.randn(13, generator=g) * 0.1, "in_std": torch.rand(13, generator=g) + 0.5,
            "out_scale": torch.rand(12, generator=g) * 0.1 + 0.01,
            # the zoo's absolute-state variant: every state and input, and the next state
            "abs_in_mean": torch.randn(16, generator=g) * 0.1, "abs_in_std": torch.rand(16, generator=g) + 0.5,
            "abs_out_mean": torch.randn(12, generator=g) * 0.1, "abs_out_std": torch.rand(12, generator=g) + 0.5}


#: The four architectures, and the model zoo's variants of them (pinn.models.VARIANT_DEFAULTS).
JACOBIAN_CASES = [(a, None) for a in ARCHITECTURES] + [
    ("baseline", {"activation": "softplus"}), ("baseline", {"activation": "softplus", "gain": 10.0}),
    ("fourier", {"fourier_max": 12}), ("fourier", {"fourier_max": 12, "activation": "softplus"}),
    ("modular", {"coupled": False}), ("absolute", None), ("absolute", {"activation": "softplus"})]


def random_xu(n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 12, generator=g, dtype=dtype) * 0.3
    u = torch.randn(n, 4, generator=g, dtype=dtype) * 0.3
    return x, u


# ------------------------------------------------------------------ physics
def test_torch_dynamics_equals_numpy(rng):
    x = np.column_stack([rng.uniform(-3, 3, (500, 3)), np.radians(rng.uniform(-60, 60, (500, 3))),
                         rng.uniform(-5, 5, (500, 3)), rng.uniform(-8, 8, (500, 3))])
    u = np.column_stack([rng.uniform(0, 1.3, 500), rng.uniform(-0.01, 0.01, (500, 3))])
    ref = dynamics(x, u, P)
    got = dynamics_torch(torch.tensor(x), torch.tensor(u), torch.tensor(P.theta), P.g, P.c_d).numpy()
    scale = np.abs(ref).max(axis=0)
    assert np.max(np.abs(got - ref) / scale) < TOL["backend"]


def test_physics_residual_vanishes_for_the_true_step_at_the_truth(small_ds):
    pairs = small_ds.pairs("train")
    x, u = pairs["x"][:2000], pairs["u"][:2000]
    true_inc = torch.tensor(Simulator(P).step(x, u) - x)
    xt, ut = torch.tensor(x), torch.tensor(u)
    scale = torch.tensor(np.abs(true_inc.numpy()).std(axis=0))
    r_truth = physics_residual(true_inc, xt, ut, torch.tensor(P.theta), P, scale)
    r_biased = physics_residual(true_inc, xt, ut, torch.tensor(P.theta * 1.3), P, scale)
    assert r_truth.abs().max() < TOL["residual_truth"]
    assert r_biased.pow(2).mean().sqrt() > TOL["residual_biased"]


def test_physics_loss_gradcheck():
    x, u = random_xu(4, seed=1)
    x[:, 3:6] *= 0.5
    u[:, 0] = 0.5 + 0.1 * u[:, 0]
    u[:, 1:] *= 1e-3
    inc = torch.randn(4, 12, dtype=torch.float64) * 1e-3
    scale = torch.full((12,), 1e-2, dtype=torch.float64)
    log_theta = torch.tensor(np.log(P.theta * 1.3), requires_grad=True)
    xr = x.clone().requires_grad_(True)

    def loss(lt, xx):
        return physics_residual(inc, xx, u, lt.exp(), P, scale).pow(2).mean()
    assert torch.autograd.gradcheck(loss, (log_theta, xr), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_rotor_side_allocation_matches_numpy(rng):
    w = np.column_stack([rng.uniform(0.3, 1.0, 50), rng.uniform(-3e-3, 3e-3, (50, 3))])
    got = rotor_sq_from_wrench(torch.tensor(w), torch.tensor(P.theta), P).numpy()
    np.testing.assert_allclose(got, allocate(w, P), rtol=1e-12)


def test_power_balance_is_the_energy_rate():
    x, u = random_xu(64, seed=2)
    u[:, 0] = u[:, 0].abs() + 0.3
    th = torch.tensor(P.theta)
    h = 1e-6
    xd = dynamics_torch(x, u, th, P.g, P.c_d)
    dE = (mechanical_energy(x + h * xd, th, P.g) - mechanical_energy(x - h * xd, th, P.g)) / (2 * h)
    pw = power_balance(x, u, th, P.g, P.c_d)
    assert torch.max((dE - pw).abs()) / torch.max(pw.abs()) < TOL["energy_rate"]


def test_rk4_increment_is_the_simulator_step():
    x, u = random_xu(32, seed=3)
    u[:, 0] = 0.6
    u[:, 1:] *= 1e-3
    inc = rk4_increment(x, u, torch.tensor(P.theta), P).numpy()
    from sim.dynamics import rates, rk4_step
    ref = rk4_step(lambda s: rates(s, u.numpy(), P), x.numpy(), 1e-3, 10) - x.numpy()
    np.testing.assert_allclose(inc, ref, rtol=1e-12, atol=1e-15)


# ------------------------------------------------------------------- models
@pytest.mark.parametrize("arch", ARCHITECTURES)
def test_forward_residual_form_and_positive_parameters(arch):
    m = build_model(arch, fake_stats(), P.theta * 1.3).double().eval()
    x, u = random_xu(16)
    y = m(x, u)
    assert y.shape == (16, 12)
    # Residual form: x_next - x is the scaled network output, independent of position.
    shifted = x.clone()
    shifted[:, 0:3] += 5.0
    torch.testing.assert_close(m(shifted, u) - shifted, y - x, rtol=0, atol=1e-12)
    torch.testing.assert_close(y - x, m.out_scale * m.network(m.features(x, u)))
    with torch.no_grad():
        m.log_theta.fill_(-50.0)
    assert torch.all(m.theta > 0)
    np.testing.assert_allclose(build_model(arch, fake_stats(), P.theta * 1.3).theta.detach().numpy(),
                               P.theta * 1.3, rtol=1e-6)


@pytest.mark.parametrize("arch,variant", JACOBIAN_CASES)
def test_forward_jacobian_equals_autograd(arch, variant):
    m = build_model(arch, fake_stats(), P.theta, variant=variant).double().eval()
    x, u = random_xu(5, seed=4)
    xn, A, B = m.forward_jacobian(x, u)
    Jx, Ju = torch.autograd.functional.jacobian(lambda a, b: m(a, b), (x, u))
    idx = torch.arange(5)
    torch.testing.assert_close(xn, m(x, u))
    torch.testing.assert_close(A, Jx[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])
    torch.testing.assert_close(B, Ju[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])


def test_bad_architecture_and_theta_are_rejected():
    with pytest.raises(ValueError, match="arch"):
        build_model("transformer", fake_stats(), P.theta)
    with pytest.raises(ValueError, match="theta_init"):
        build_model("baseline", fake_stats(), -P.theta)
    with pytest.raises(ValueError, match="profile"):
        make_config("baseline", "slow")


# ---------------------------------------------------------------- schedules
@pytest.mark.parametrize("epochs", [4, 8, 40, 200])
def test_curriculum_and_sampling_schedules(epochs):
    ks = [curriculum_horizon(e, epochs) for e in range(epochs)]
    ps = [sampling_probability(e, epochs) for e in range(epochs)]
    # Four equal quarters of 5, 10, 25, 50 (paper Eq. 11 scaled to the budget).
    for e, k in enumerate(ks):
        assert k == CURRICULUM_HORIZONS[min(3, 4 * e // epochs)]
    assert ks[0] == 5 and ks[-1] == 50 and ks == sorted(ks)
    assert ps[0] == 0.0 and ps[-1] == pytest.approx(SS_MAX)
    assert np.allclose(np.diff(ps), SS_MAX / (epochs - 1))


def test_training_history_follows_the_schedules(small_ds):
    cfg = make_config("proposed", "quick", 0, epochs=4, steps_per_epoch=2, batch=200, n_colloc=32)
    res = train(small_ds, cfg)
    assert [h["horizon"] for h in res.history] == [5, 10, 25, 50]
    assert [h["sampling_p"] for h in res.history] == pytest.approx([0.0, 0.1, 0.2, 0.3])
    base = train(small_ds, make_config("baseline", "quick", 0, epochs=2, steps_per_epoch=2, batch=200, n_colloc=32))
    assert [h["horizon"] for h in base.history] == [1, 1] and [h["sampling_p"] for h in base.history] == [0, 0]


# ----------------------------------------------------------------- training
@pytest.mark.parametrize("arch", ARCHITECTURES)
def test_quick_training_moves_theta_toward_truth_and_lowers_validation_loss(small_ds, arch):
    # (Its wall time, under 60 s on 2 cores, is measured by `python -m pinn.bench`, not asserted here.)
    res = train(small_ds, make_config(arch, "quick", 0))
    init_err = np.abs(np.full(6, 100 * 0.3))
    final_err = np.abs([res.history[-1]["theta_err_pct"][n] for n in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")])
    assert np.all(final_err < init_err), final_err
    assert res.history[-1]["val"] < res.history[0]["val"]


def test_same_seed_reproduces_training_exactly(small_ds):
    cfg = make_config("baseline", "quick", 3, epochs=2, steps_per_epoch=3)
    a, b = train(small_ds, cfg), train(small_ds, cfg)
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(va, vb), k


def test_training_stats_come_from_the_training_split(small_ds):
    st = training_stats(small_ds)
    tr = small_ds.split == 0
    np.testing.assert_allclose(st["out_scale"], (small_ds.x_next[tr] - small_ds.x[tr]).reshape(-1, 12).std(0) + 1e-8)


# ------------------------------------------------------------------ metrics
def test_metrics_of_the_exact_model_are_the_noise_floor():
    from sim.excitation import make_dataset
    ds = make_dataset("small", 10, 3.0, 1, noise=NoiseModel.none())
    sim = Simulator(P)
    one = one_step_mae(sim.step, ds)
    roll = rollout_mae(sim.step, ds, horizon=100, n_starts=50)
    assert one["position"] == 0.0 and max(v for k, v in roll.items() if k in ("x", "phi", "vz")) < 1e-12
    assert roll["n_diverged"] == 0


def test_diverging_rollouts_are_counted_not_dropped():
    from sim.excitation import make_dataset
    ds = make_dataset("small", 10, 3.0, 1, noise=NoiseModel.none())

    def blows_up(x, u):
        return 10.0 * x + 1.0  # leaves the finite range within a few steps
    roll = rollout_mae(blows_up, ds, horizon=100, n_starts=40)
    assert roll["n_diverged"] == 40 and roll["n_rollouts"] == 40
    assert all(1 <= s <= 10 for s in roll["divergence_steps"])
    assert np.isfinite(roll["position"]) and roll["position"] > 10.0
