"""PINN models, physics losses, schedules, training and metrics."""

import numpy as np
import pytest
import torch

from pinn.metrics import one_step_mae, rollout_mae
from pinn.models import ALL_ARCHITECTURES, ARCHITECTURES, build_model
from pinn.physics import (dynamics_torch, mechanical_energy, power_balance, rk4_increment, rk4_increment_tangent,
                          rotor_sq_from_wrench)
from pinn.train import (CURRICULUM_HORIZONS, SS_MAX, curriculum_horizon, make_config, physics_residual,
                        sampling_probability, train, training_stats)
from sim import NoiseModel, QuadParams, Simulator, dynamics
from sim.vehicles.rotors import allocate

TOL = {
    "backend": 1e-12,          # torch (float64) vs numpy dynamics, relative to column scale
    "residual_truth": 1e-6,    # physics residual with the true step and theta-hat = truth
    "residual_biased": 1e-2,   # ... and at least this with the +30 % guess
    "jacobian": 1e-10,         # forward-mode Jacobian vs autograd (float64, absolute)
    "energy_rate": 1e-6,       # d/dt mechanical energy vs power balance (relative)
    "rk4_order": 0.25,         # measured convergence order of the physics-plus-network RK4 step vs 4
    "one_step_rk4": 5e-8,      # one 10 ms RK4 step vs the simulator's ten of 1 ms (absolute, small-regime states)
    "hybrid_theta_pct": 1.0,   # quick physics-plus-network training: every |theta-hat error| below this, %
    "lag_one_step": 5e-6,      # motor-lag physics, one RK4 step vs the estimator's ten (rates up to 2e-6 off)
    "lag_ten_steps": 1e-8,     # ... ten steps vs ten steps (exact rotors against RK4 ones)
    "lag_quick_inertia_pct": 5.0,   # quick motor-lag training on high-fidelity data: largest |inertia error|, %
    "lag_quick_tau_pct": 30.0,      # ... and |tau_m error|, %
    "export_rel": 1e-12,       # exported step and derivative graphs vs torch, relative to each output's largest entry
}
P = QuadParams()

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def small_ds():
    from sim.identification.excitation import make_dataset
    return make_dataset("small", 20, 10.0, 0)


@pytest.fixture(scope="module")
def small_ds_highfi():
    from sim.identification.excitation import make_dataset
    from sim.params import FIDELITIES
    return make_dataset("small", 20, 10.0, 0, fidelity=FIDELITIES["high"])


def fake_stats():
    g = torch.Generator().manual_seed(0)
    return {"in_mean": torch.randn(13, generator=g) * 0.1, "in_std": torch.rand(13, generator=g) + 0.5,
            "out_scale": torch.rand(12, generator=g) * 0.1 + 0.01,
            # the zoo's absolute-state variant: every state and input, and the next state
            "abs_in_mean": torch.randn(16, generator=g) * 0.1, "abs_in_std": torch.rand(16, generator=g) + 0.5,
            "abs_out_mean": torch.randn(12, generator=g) * 0.1, "abs_out_std": torch.rand(12, generator=g) + 0.5,
            # the physics-plus-network model's constants: gravity and the drag coefficient
            "physics": torch.tensor([P.g, P.c_d], dtype=torch.float64)}


def built(arch, theta=None, variant=None):
    """A float64 model in evaluation mode; the physics-plus-network model's residual (started at zero) is given
    random output weights, so that its network part is tested too."""
    m = build_model(arch, fake_stats(), P.theta if theta is None else theta, variant=variant)
    if arch == "hybrid":
        with torch.no_grad():
            m.mlp.out.weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(7))
    return m.double().eval()


#: The four architectures, and the model zoo's variants of them (pinn.models.VARIANT_DEFAULTS).
JACOBIAN_CASES = [(a, None) for a in ARCHITECTURES] + [
    ("baseline", {"activation": "softplus"}), ("baseline", {"activation": "softplus", "gain": 10.0}),
    ("fourier", {"fourier_max": 12}), ("fourier", {"fourier_max": 12, "activation": "softplus"}),
    ("modular", {"coupled": False}), ("absolute", None), ("absolute", {"activation": "softplus"}), ("hybrid", None)]


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
    from sim.equations.dynamics import rates, rk4_step
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
    m = built(arch, variant=variant)
    x, u = random_xu(5, seed=4)
    xn, A, B = m.forward_jacobian(x, u)
    Jx, Ju = torch.autograd.functional.jacobian(lambda a, b: m(a, b), (x, u))
    idx = torch.arange(5)
    torch.testing.assert_close(xn, m(x, u))
    torch.testing.assert_close(A, Jx[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])
    torch.testing.assert_close(B, Ju[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])


def test_rk4_tangent_equals_autograd_at_large_angles():
    # Roll and pitch near 60 degrees, fast rates and velocities: every partial derivative is far from zero.
    g = torch.Generator().manual_seed(11)
    x = torch.randn(6, 12, generator=g, dtype=torch.float64) * torch.tensor([1.0] * 3 + [0.9] * 3 + [3.0] * 6,
                                                                              dtype=torch.float64)
    u = torch.tensor([0.8, 2e-3, -1e-3, 5e-4], dtype=torch.float64) + 0.1 * torch.randn(6, 4, generator=g,
                                                                                         dtype=torch.float64)
    th = torch.tensor(P.theta * 1.1)
    for substeps in (1, 3):
        inc, A, B = rk4_increment_tangent(x, u, th, P.g, P.c_d, substeps=substeps)
        Jx, Ju = torch.autograd.functional.jacobian(lambda a, b: rk4_increment(a, b, th, P, substeps=substeps), (x, u))
        idx = torch.arange(6)
        torch.testing.assert_close(inc, rk4_increment(x, u, th, P, substeps=substeps), rtol=1e-14, atol=1e-15)
        torch.testing.assert_close(A, Jx[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])
        torch.testing.assert_close(B, Ju[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])


def test_hybrid_is_the_nominal_step_under_theta_hat_plus_the_residual():
    m = built("hybrid", theta=P.theta * 1.2)
    x, u = random_xu(16, seed=5)
    u[:, 0] = 0.6 + 0.1 * u[:, 0]
    u[:, 1:] *= 1e-3
    with torch.no_grad():
        y = m(x, u)
        physics = rk4_increment(x, u, m.theta, P, substeps=1)
        torch.testing.assert_close(y - x, physics + m.out_scale * m.network(m.features(x, u)), rtol=0, atol=1e-15)
        # translation invariance, as the other architectures
        shifted = x.clone()
        shifted[:, 0:3] += 5.0
        torch.testing.assert_close(m(shifted, u) - shifted, y - x, rtol=0, atol=1e-12)
        # theta-hat enters the prediction: with the network silent and theta-hat the truth it is the simulator's step
        m.mlp.out.weight.zero_()
        m.log_theta.copy_(torch.tensor(np.log(P.theta)))
        small = x * 0.3 / x.abs().max()
        step = m(small, u) - small
    ref = Simulator(P).step(small.numpy(), u.numpy()) - small.numpy()
    assert np.max(np.abs(step.numpy() - ref)) < TOL["one_step_rk4"]


def test_the_physics_step_converges_with_order_four():
    x, u = random_xu(32, seed=6)
    u[:, 0] = 0.6 + 0.1 * u[:, 0]
    u[:, 1:] *= 1e-3
    th = torch.tensor(P.theta)
    ref = rk4_increment(x, u, th, P, substeps=64)
    err = [float((rk4_increment(x, u, th, P, substeps=n) - ref).abs().max()) for n in (1, 2, 4)]
    orders = np.log2(np.array(err[:-1]) / np.array(err[1:]))
    assert np.all(np.abs(orders - 4.0) < TOL["rk4_order"]), orders


def test_hybrid_physics_loss_trains_the_network_only(small_ds):
    # theta-hat sits inside the prediction; the physics residual (the network's own output) must not move it,
    # while the identification term must.
    from pinn.train import step_losses
    cfg = make_config("hybrid", "quick", 0)
    st = training_stats(small_ds)
    m = build_model("hybrid", st, P.theta * 1.3)
    with torch.no_grad():
        m.mlp.out.weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(1))
    states = torch.as_tensor(small_ds.x[0, :9], dtype=torch.float32)[None]
    states = torch.cat([states, torch.as_tensor(small_ds.x_next[0, 8:9], dtype=torch.float32)[None]], dim=1)
    us = torch.as_tensor(small_ds.u[0, :9], dtype=torch.float32)[None]
    ns = torch.as_tensor(small_ds.rotor_speed[0, :9], dtype=torch.float32)[None]
    colloc = torch.as_tensor(np.concatenate([small_ds.x[0, :4, 3:12], small_ds.u[0, :4]], axis=1), dtype=torch.float32)
    scales = {"n_sq": torch.ones(4), "rate_max": torch.ones(12), "power": 1.0}
    losses = step_losses(m, states[:, :2], us[:, :1], ns[:, :1], 0.0, colloc, P, scales, cfg, torch.Generator())
    g_phys = torch.autograd.grad(losses["phys"], [m.log_theta, m.mlp.out.weight], allow_unused=True)
    g_theta = torch.autograd.grad(losses["theta"], m.log_theta)[0]
    g_data = torch.autograd.grad(losses["data"], m.log_theta)[0]
    assert g_phys[0] is None or float(g_phys[0].abs().max()) == 0.0
    assert float(g_phys[1].abs().max()) > 0.0
    assert float(g_theta.abs().max()) > 0.0 and float(g_data.abs().max()) > 0.0


def lag_stats():
    """Training statistics of a motor-lag model, without data."""
    return {**fake_stats(), "n_mean": torch.full((4,), 4.0), "n_std": torch.full((4,), 0.1),
            "rotor": torch.tensor([P.n_max_sq, P.lever], dtype=torch.float64)}


def lag_inputs(n, seed=0, spread=0.05):
    """Rigid-body states, rotor speeds off their commands by ``spread`` (relative), and hover-like wrenches."""
    from sim.vehicles.rotors import allocate
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 12)) * 0.3
    u = np.tile([P.m * P.g, 0, 0, 0], (n, 1)) + rng.normal(size=(n, 4)) * [0.05, 2e-4, 2e-4, 1e-4]
    rotors = np.sqrt(allocate(u, P)) * (1 + spread * rng.normal(size=(n, 4)))
    return torch.tensor(np.c_[x, rotors]), torch.tensor(u)


def test_lag_model_jacobian_equals_autograd():
    m = build_model("hybrid_lag", lag_stats(), P.theta * 1.1)
    with torch.no_grad():
        m.mlp.out.weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(3))
    m = m.double().eval()
    z, u = lag_inputs(5, seed=1)
    zn, A, B = m.forward_jacobian(z, u)
    Jz, Ju = torch.autograd.functional.jacobian(lambda a, b: m(a, b), (z, u))
    idx = torch.arange(5)
    torch.testing.assert_close(zn, m(z, u), rtol=1e-14, atol=1e-15)
    torch.testing.assert_close(A, Jz[idx, :, idx, :], rtol=0, atol=TOL["jacobian"])
    torch.testing.assert_close(B, Ju[idx, :, idx, :], rtol=0, atol=1e-9)    # B's entries reach 1e3 (1/Jxx)


def test_lag_physics_is_the_lag_aware_estimators_model():
    # The same equations as sim.identification.motor_lag's CasADi model (RK4 of the rigid body and the rotors, 10 x 1
    # ms): the
    # rotors here are solved exactly, the rigid body by RK4 at the rotors' speeds at each stage's time.
    from pinn.physics import lagged_rotor_increment
    from sim.identification.motor_lag import lag_sensitivity_function
    from sim.vehicles.rotors import mixer
    z, u = lag_inputs(6, seed=2)
    f64 = torch.float64
    consts = {"g": torch.tensor(P.g, dtype=f64), "c_d": torch.tensor(P.c_d, dtype=f64),
              "mixer_unit": torch.tensor(mixer(1.0, 1.0, P.lever), dtype=f64),
              "mixer_unit_inv": torch.linalg.inv(torch.tensor(mixer(1.0, 1.0, P.lever), dtype=f64)),
              "n_max_sq": torch.tensor(P.n_max_sq, dtype=f64)}
    F = lag_sensitivity_function(P, state=False)
    ref = np.array([np.asarray(F(z[i].numpy(), u[i].numpy(), np.r_[P.theta, 0.03])[2]).ravel() for i in range(6)])
    for substeps, tol in ((1, TOL["lag_one_step"]), (10, TOL["lag_ten_steps"])):
        ix, inn = lagged_rotor_increment(z[:, :12], z[:, 12:], u, torch.tensor(P.theta), torch.tensor(0.03, dtype=f64),
                                         consts, substeps=substeps)
        assert np.max(np.abs(ref[:, :12] - z[:, :12].numpy() - ix.numpy())) < tol
        # the rotors: exact exponential here, RK4 there (relative error of its step, (h / tau)^5 / 120 per substep)
        np.testing.assert_allclose(inn.numpy(), ref[:, 12:] - z[:, 12:].numpy(), rtol=1e-7)


def test_lag_model_rotor_speeds_follow_the_commands_as_the_estimators():
    from sim.identification.excitation import make_dataset
    from sim.identification.motor_lag import rotor_trajectory
    from sim.params import FIDELITIES
    ds = make_dataset("small", 2, 2.0, 0, fidelity=FIDELITIES["high"])
    m = build_model("hybrid_lag", training_stats(ds), P.theta).double()
    theta7 = np.r_[m.theta.detach().numpy(), float(m.tau.detach())]
    n, _ = rotor_trajectory(ds.u, theta7, QuadParams(**ds.meta["params"]))
    with torch.no_grad():
        got = m.rotor_speeds_after(torch.tensor(ds.u[:, :120]))
    np.testing.assert_allclose(got.numpy(), n[:, 120], rtol=1e-12)


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
@pytest.mark.parametrize("arch", [a if a == "baseline" else pytest.param(a, marks=pytest.mark.slow)
                                  for a in ARCHITECTURES])      # one architecture by default, all four on demand
def test_quick_training_moves_theta_toward_truth_and_lowers_validation_loss(small_ds, arch):
    # (Its wall time, under 60 s on 2 cores, is measured by `python -m pinn.bench`, not asserted here.)
    res = train(small_ds, make_config(arch, "quick", 0))
    init_err = np.abs(np.full(6, 100 * 0.3))
    final_err = np.abs([res.history[-1]["theta_err_pct"][n] for n in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")])
    assert np.all(final_err < init_err), final_err
    assert res.history[-1]["val"] < res.history[0]["val"]


@pytest.mark.slow
def test_quick_hybrid_training_identifies_every_parameter_within_a_percent(small_ds):
    # theta-hat inside the prediction: the quick budget already brings the +30 % guess within 1 % (the Baseline's
    # inertias, identified through the physics loss only, are still 9 % off after the same budget).
    res = train(small_ds, make_config("hybrid", "quick", 0))
    err = np.abs([res.history[-1]["theta_err_pct"][n] for n in ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")])
    assert np.all(err < TOL["hybrid_theta_pct"]), err


@pytest.mark.slow
def test_quick_lag_model_training_finds_the_lag_and_the_inertias(small_ds_highfi):
    # On data with a 30 ms motor lag the rigid-body forms read the lag as 30-50 % more inertia; with the rotors as
    # states and tau_m learnable, the quick budget brings the inertias within a few % and tau_m (from 50 ms,
    # +67 %) within 30 %.
    res = train(small_ds_highfi, make_config("hybrid_lag", "quick", 0))
    err = res.history[-1]["theta_err_pct"]
    assert max(abs(err[n]) for n in ("Jxx", "Jyy", "Jzz")) < TOL["lag_quick_inertia_pct"], err
    assert abs(err["tau_m"]) < TOL["lag_quick_tau_pct"], err


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
    from sim.identification.excitation import make_dataset
    ds = make_dataset("small", 10, 3.0, 1, noise=NoiseModel.none())
    sim = Simulator(P)
    one = one_step_mae(sim.step, ds)
    roll = rollout_mae(sim.step, ds, horizon=100, n_starts=50)
    assert one["position"] == 0.0 and max(v for k, v in roll.items() if k in ("x", "phi", "vz")) < 1e-12
    assert roll["n_diverged"] == 0


def test_diverging_rollouts_are_counted_not_dropped():
    from sim.identification.excitation import make_dataset
    ds = make_dataset("small", 10, 3.0, 1, noise=NoiseModel.none())

    def blows_up(x, u):
        return 10.0 * x + 1.0  # leaves the finite range within a few steps
    roll = rollout_mae(blows_up, ds, horizon=100, n_starts=40)
    assert roll["n_diverged"] == 40 and roll["n_rollouts"] == 40
    assert all(1 <= s <= 10 for s in roll["divergence_steps"])
    assert np.isfinite(roll["position"]) and roll["position"] > 10.0


@pytest.mark.parametrize("arch", ALL_ARCHITECTURES)
def test_every_architecture_exports_to_graphs_equal_to_torch_that_the_contract_takes(tmp_path, arch):
    """The ONNX files of :func:`pinn.export.export_model` compute what the float64 torch model computes, to rounding
    (an operation the exporter took in float32 shows as 1e-7 to 1e-5 relative), and state every output dimension."""
    import onnxruntime as ort

    from mpc.prediction.contract import check_model
    from pinn.export import export_model

    if arch == "hybrid_lag":
        m = build_model(arch, lag_stats(), P.theta * 1.1)
        with torch.no_grad():
            m.mlp.out.weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(3))
        x, u = lag_inputs(20, seed=2)
    else:
        m = built(arch, P.theta * 1.1)
        x, u = lag_inputs(20, seed=2)
        x = x[:, :12]
    m = m.double().eval()
    paths = export_model(m, tmp_path, arch, {"arch": arch}, 0, {}, torch_file=False)
    check_model(paths["onnx"])      # the derivative graph beside it too
    feeds = {"x": x.numpy(), "u": u.numpy()}
    with torch.no_grad():
        want = (m(x, u), *m.forward_jacobian(x, u)[1:])
    found = (ort.InferenceSession(str(paths["onnx"])).run(None, feeds)[0],
             *ort.InferenceSession(str(paths["jacobian"])).run(None, feeds)[1:])
    for name, a, b in zip(("x_next", "A", "B"), found, want):
        b = b.numpy()
        assert np.max(np.abs(a - b)) <= TOL["export_rel"] * np.max(np.abs(b)), (name, np.max(np.abs(a - b)))
