"""Training on imported flight logs: samples a log did not measure never enter a model."""

import dataclasses
import json

import numpy as np
import pytest
import torch

from pinn.flights import (AttitudeLoopPhysics, FlightModel, FlightTrainConfig, HeldRatesPhysics, flight_stats,
                          flight_step, register, train_flight_model)
from sim.flightlogs.attitudeloop import EXTRA_STATES, AttitudeLoop
from pinn.train import _TrainData, make_config, train, training_stats
from scenarios.studies.realdata import why_not_flyable
from sim.identification.excitation import make_dataset
from sim.flightlogs.logbench import ctbr_physics_step, physics_step, prediction_errors
from sim.params import DT, QuadParams

torch.set_num_threads(1)

# tolerances of this module
STATS_RTOL = 1e-12     # statistics of the masked dataset against those of its measured samples alone
LEARNED_GAIN = 0.8     # the trained model's validation score against the held-rates physics alone (at most)
ONNX_TOL = 1e-12       # onnxruntime against torch, float64
JACOBIAN_TOL = 1e-10   # forward_jacobian against torch.func.jacfwd, float64 (entries of A and B up to about 1)
PHYSICS_TOL = 1e-12    # torch held-rates physics against the numpy protocol's, float64, one RK4 step
LAG_EXACT_TOL = 1e-14  # the lagged-rates physics' next rates against the lag's closed form (rad/s, about 1)
LAG_NOMINAL_TOL = 3e-5  # the lagged-rates physics (1 substep) against the CasADi ctbr nominal model (10 RK4 substeps)
LAG_ORDER = (3.6, 4.4)  # observed order of the lagged-rates physics' RK4 in its substeps (4, the method's)
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


# ------------------------------------------------------------------ the flight model (identified physics + network)
DRAGS = {"linear_drag": (0.5, 0.4, 0.7), "quadratic_drag": (0.1, -0.05, 0.02), "accel_bias": (0.01, -0.02, 0.3)}
P = QuadParams(m=0.045, Jxx=1e-4, Jyy=2e-4, Jzz=5e-6, kt=4e-8, kq=7.7e-12, d=0.05, c_d=0.03)


def _physics():
    return HeldRatesPhysics(P.m, P.g, P.c_d, **DRAGS)


#: An attitude loop with every coefficient nonzero (the velocity loop too), torque gains of both signs.
LOOP = AttitudeLoop(damping=(1.8, 2.2, 40.0), stiffness=(14.0, 15.0), lead=-0.1, torque_gain=(0.6, -0.4, 3.0),
                    bias=(0.1, -0.1, 0.05), velocity_gain=0.08)


def _loop_physics(substeps=1):
    return AttitudeLoopPhysics(P.m, P.g, P.c_d, **DRAGS, loop=LOOP, inertia=(P.Jxx, P.Jyy, P.Jzz), substeps=substeps)


def test_torch_attitude_loop_physics_is_the_protocols(rng=np.random.default_rng(5)):
    """One period of the torch loop physics from random states (with a random setpoint and start velocity) is
    ``physics_step`` with the same loop, at one and at three substeps; a window's extra states are the loop's."""
    x = rng.normal(size=(64, 16)) * np.r_[1, 1, 1, 0.4, 0.4, 3, 2, 2, 2, 2, 2, 2, 0.3, 0.3, 1, 1]
    u = np.c_[rng.uniform(0.2, 0.8, 64), rng.normal(size=(64, 3)) * 1e-3]
    for substeps in (1, 3):
        want = physics_step(P, substeps=substeps, **DRAGS, attitude_loop=LOOP)(x, u)
        got = _loop_physics(substeps).double()(torch.as_tensor(x), torch.as_tensor(u)).numpy()
        np.testing.assert_allclose(got, want, rtol=0, atol=PHYSICS_TOL)
    np.testing.assert_array_equal(_loop_physics().start(x[:, :12]), LOOP.start(x[:, :12])[:, 12:])


def test_torch_held_rates_physics_is_the_protocols(rng=np.random.default_rng(3)):
    x = rng.normal(size=(64, 12)) * np.r_[1, 1, 1, 0.4, 0.4, 3, 2, 2, 2, 2, 2, 2]
    u = np.c_[rng.uniform(0.2, 0.8, 64), rng.normal(size=(64, 3)) * 1e-3]
    want = physics_step(P, hold_rates=True, substeps=1, **DRAGS)(x, u)
    got = _physics().double()(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=PHYSICS_TOL)


def _flights(n=3, steps=400, seed=0):
    """Flights of our plant (the stated Crazyflie), every sample measured."""
    from types import SimpleNamespace

    ds = make_dataset("small", n, steps / 100, seed)
    out = []
    for i in range(n):
        x = np.concatenate([ds.x[i], ds.x_next[i, -1:]])
        u = np.concatenate([ds.wrench[i], ds.wrench[i, -1:]])
        out.append(SimpleNamespace(name=f"f{i}", x=x, u=u, x_ok=np.ones(len(x), bool)))
    return out


def test_the_untrained_model_is_its_physics_and_its_register_shifts_exactly():
    flights = _flights(1)
    f = flights[0]
    m = FlightModel(_physics(), flight_stats(flights, np.ones(4), 3), history=3).double()
    idx = np.arange(5, 40)
    z = np.concatenate([f.x[idx], register(f.x, f.u, idx, 3)], axis=1)
    nxt = m(torch.as_tensor(z), torch.as_tensor(f.u[idx])).detach().numpy()
    np.testing.assert_allclose(nxt[:, :12], physics_step(P, hold_rates=True, substeps=1, **DRAGS)(f.x[idx], f.u[idx]),
                               rtol=0, atol=PHYSICS_TOL)
    np.testing.assert_array_equal(nxt[:, 12:], register(f.x, f.u, idx + 1, 3))
    assert why_not_flyable(*flight_step(m, np.ones(4)), f.u.mean(0), 0.1 * f.u.std(0)) == \
        "holds the body rates: no input turns it"


def test_training_keeps_the_best_validation_epoch_and_reruns_exactly():
    """On our plant's flights (whose rates do follow the torques) the network learns what the held-rates physics
    misses: the kept epoch scores below the physics alone on the validation flights, responds to every input, and
    a second run with the same seed is identical."""
    flights = _flights(4)
    train_f, val_f = flights[:3], flights[3:]
    kw = {"p": QuadParams(), "hold_rates": True, "linear_drag": (0.0, 0.0, 0.0), "quadratic_drag": (0.0, 0.0, 0.0),
          "accel_bias": (0.0, 0.0, 0.0)}      # the plant's own equations, but with the rates held
    cfg = FlightTrainConfig(history=2, epochs=3, steps_per_epoch=30, windows=64, hidden=32, layers=2,
                            validation_stride=5)
    tiny = FlightTrainConfig(history=2, epochs=1, steps_per_epoch=3, windows=16, hidden=8, layers=1,
                             validation_stride=50)
    a, b = train_flight_model(train_f, val_f, kw, tiny), train_flight_model(train_f, val_f, kw, tiny)
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(va, vb), k
    a = train_flight_model(train_f, val_f, kw, cfg)
    assert a.best_epoch == int(np.argmin(a.scores)) + 1
    from sim.flightlogs.logbench import goal_score as score
    physics = score(prediction_errors(physics_step(**kw), val_f, stride=5).to_dict())
    assert min(a.scores) < LEARNED_GAIN * physics, (a.scores, physics)
    step, start = flight_step(a.model, np.ones(4))
    assert why_not_flyable(step, start, train_f[0].u.mean(0), 0.1 * train_f[0].u.std(0)) == ""


def test_the_exported_model_is_the_torch_model(tmp_path):
    """onnxruntime runs the exported flight model (with its register) as torch does, in float64, and check-model
    finds its extra states."""
    import onnxruntime as ort

    from mpc.prediction.contract import check_model
    from pinn.flights import export_flight_model

    flights = _flights(1)
    torch.manual_seed(0)
    m = FlightModel(_physics(), flight_stats(flights, np.ones(4), 2), history=2, hidden=16, layers=2)
    with torch.no_grad():
        m.out.weight.normal_(0.0, 0.3)
    theta = {"m": P.m, "Jxx": P.Jxx, "Jyy": P.Jyy, "Jzz": P.Jzz, "kt": P.kt, "kq": P.kq}
    path = export_flight_model(m, tmp_path / "f.onnx", theta, "test")
    f = flights[0]
    idx = np.arange(3, 60)
    z = np.concatenate([f.x[idx], register(f.x, f.u, idx, 2)], axis=1)
    got = ort.InferenceSession(str(path)).run(None, {"x": z, "u": f.u[idx]})[0]
    want = m.double()(torch.as_tensor(z), torch.as_tensor(f.u[idx])).detach().numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=ONNX_TOL)
    assert check_model(path).extra_states == m.extra_states


def test_torch_ctbr_physics_is_the_protocols(rng=np.random.default_rng(4)):
    from pinn.flights import CtbrPhysics

    x = rng.normal(size=(64, 12)) * np.r_[1, 1, 1, 0.4, 0.4, 3, 2, 2, 2, 2, 2, 2]
    u = np.c_[rng.uniform(0.2, 0.8, 64), rng.normal(size=(64, 3))]
    want = ctbr_physics_step(P, thrust_gain=1.1, **DRAGS)(x, u)
    got = CtbrPhysics(P.m, P.g, P.c_d, thrust_gain=1.1, **DRAGS).double()(torch.as_tensor(x),
                                                                            torch.as_tensor(u)).numpy()
    np.testing.assert_allclose(got, want, rtol=0, atol=PHYSICS_TOL)
    np.testing.assert_allclose(got[:, 6:9], u[:, 1:], rtol=0, atol=PHYSICS_TOL)    # the rates reached


def test_a_ctbr_model_round_trips_through_the_contract_at_its_level(tmp_path):
    """Exported at ctbr, the file declares the level and its inputs, the contract's loader finds them, and the
    model that the controllers load predicts as the protocol's numpy step does."""
    from mpc.prediction.contract import check_model, declared_level
    from mpc.prediction.models import OnnxModel
    from pinn.flights import CtbrPhysics, export_flight_model
    from sim.levels import LEVEL_INPUTS

    theta = {"m": P.m, "Jxx": P.Jxx, "Jyy": P.Jyy, "Jzz": P.Jzz, "kt": P.kt, "kq": P.kq}
    path = export_flight_model(CtbrPhysics(P.m, P.g, P.c_d, thrust_gain=0.9, **DRAGS), tmp_path / "c.onnx", theta,
                               "identified physics, ctbr", level="ctbr")
    info = check_model(path)
    assert declared_level(path) == "ctbr" and info.level == "ctbr"
    assert info.jacobian is None      # the physics alone: central differences cost less than its derivative graph
    assert tuple(json.loads(info.metadata["input_names"])) == LEVEL_INPUTS["ctbr"]
    model = OnnxModel(path)
    assert model.level == "ctbr"
    rng = np.random.default_rng(5)
    x = rng.normal(size=(32, 12)) * np.r_[1, 1, 1, 0.3, 0.3, 3, 1, 1, 1, 1, 1, 1]
    u = np.c_[rng.uniform(0.3, 0.6, 32), rng.normal(size=(32, 3))]
    np.testing.assert_allclose(model.step(x, u), ctbr_physics_step(P, thrust_gain=0.9, **DRAGS)(x, u), rtol=0,
                               atol=ONNX_TOL)


# ---- the ctbr level: a network on the translational dynamics, given the rates reached
def _ctbr_flights(n, seed=0):
    """Our plant's flights with the ctbr inputs (the thrust and the body rates reached)."""
    from sim.flightlogs.logbench import ctbr_inputs

    flights = _flights(n, seed=seed)
    for f in flights:
        f.u = ctbr_inputs(f)
    return flights


def test_a_ctbr_flight_model_corrects_the_velocity_alone_and_names_its_register():
    from pinn.flights import CtbrPhysics

    flights = _ctbr_flights(1)
    f = flights[0]
    physics = CtbrPhysics(P.m, P.g, P.c_d, thrust_gain=0.9, **DRAGS)
    m = FlightModel(physics, flight_stats(flights, np.ones(4), 2), history=2, hidden=16, layers=2).double()
    assert m.extra_states == ("u1_T", "u1_p", "u1_q", "u1_r", "u2_T", "u2_p", "u2_q", "u2_r", "p1", "q1", "r1",
                              "p2", "q2", "r2")
    idx = np.arange(5, 60)
    z = torch.as_tensor(np.concatenate([f.x[idx], register(f.x, f.u, idx, 2)], axis=1))
    u = torch.as_tensor(f.u[idx])
    want = ctbr_physics_step(P, thrust_gain=0.9, **DRAGS)(f.x[idx], f.u[idx])
    np.testing.assert_allclose(m(z, u).detach().numpy()[:, :12], want, rtol=0, atol=PHYSICS_TOL)   # untrained
    torch.manual_seed(1)
    with torch.no_grad():
        m.out.weight.normal_(0.0, 0.3)
    nxt = m(z, u).detach().numpy()
    np.testing.assert_array_equal(nxt[:, :9], (physics.double()(z[:, :12], u)).numpy()[:, :9])  # rates, attitude
    assert np.max(np.abs(nxt[:, 9:12] - want[:, 9:12])) > 1e-3                                   # the velocity moves
    np.testing.assert_array_equal(nxt[:, 12:], register(f.x, f.u, idx + 1, 2))


def test_a_ctbr_flight_model_learns_a_thrust_its_physics_has_wrong_and_exports_at_ctbr(tmp_path):
    """The physics given 10 % too little thrust: the network, on the translational dynamics alone, makes up for it
    (validation score below the physics'), and the file written at ctbr runs as torch does."""
    import onnxruntime as ort

    from mpc.prediction.contract import check_model
    from pinn.flights import ctbr_learned_models
    from sim.flightlogs.logbench import goal_score as score

    flights = _ctbr_flights(4)
    kw = {"p": QuadParams(), "thrust_gain": 0.9}          # the plant's own equations but for the thrust
    cfg = FlightTrainConfig(history=0, epochs=3, steps_per_epoch=30, windows=64, hidden=32, layers=2,
                            validation_stride=5)
    res = train_flight_model(flights[:3], flights[3:], kw, cfg, level="ctbr")
    physics = score(prediction_errors(ctbr_physics_step(**kw), flights[3:], stride=5).to_dict())
    assert min(res.scores) < LEARNED_GAIN * physics, (res.scores, physics)
    theta = {"m": P.m, "Jxx": P.Jxx, "Jyy": P.Jyy, "Jzz": P.Jzz, "kt": P.kt, "kq": P.kq}
    models = ctbr_learned_models({"train": flights[:3], "val": flights[3:]}, kw, theta, "quick", progress=None)
    assert [m.name for m in models] == ["identified physics, ctbr + network",
                                        "identified physics, ctbr + network, history 4"]
    path = models[1].export(tmp_path / "c.onnx")
    info = check_model(path)
    assert info.level == "ctbr" and len(info.extra_states) == 28
    f, idx = flights[0], np.arange(6, 50)
    z = models[1].start(f, idx)
    got = ort.InferenceSession(str(path)).run(None, {"x": z, "u": f.u[idx]})[0]
    np.testing.assert_allclose(got, models[1].step(z, f.u[idx]), rtol=0, atol=ONNX_TOL)


# ---- exact derivatives: forward_jacobian and the derivative graph written beside the model file
def _jacobian_states(n, nz, level, seed=7):
    """Random states (n, nz) with tilts up to 0.6 rad, any heading and velocities of 0.3 to 2 m/s per axis (away
    from the drags' kink), a random register, and inputs (n, 4) at ``level``, as float64 tensors."""
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(n, nz))
    z[:, 3:5] = rng.uniform(-0.6, 0.6, (n, 2))
    z[:, 5] = rng.uniform(-np.pi, np.pi, n)
    z[:, 9:12] = rng.uniform(0.3, 2.0, (n, 3)) * rng.choice([-1.0, 1.0], (n, 3))
    turn = rng.normal(size=(n, 3)) * (1.0 if level == "ctbr" else 1e-3)       # rates reached, or torques
    return torch.as_tensor(z), torch.as_tensor(np.c_[rng.uniform(0.2, 0.8, n), turn])


def _jacobian_model(kind, level="wrench", history=0, substeps=1):
    """``(model, nz, level)``: float64 physics (``kind`` ``"held"`` or ``"ctbr"``, with ``substeps``) or a
    :class:`FlightModel` (``"flight"``) at ``level`` with ``history``, its network's weights all random and nonzero
    and its statistics random (so that every feature's normalization and every output's scale matters)."""
    from pinn.flights import CtbrPhysics, LaggedCtbrPhysics

    def ctbr():
        if kind.startswith("lagged"):
            return LaggedCtbrPhysics(P.m, P.g, P.c_d, (0.007, 0.009, 0.0125), substeps=substeps)
        return CtbrPhysics(P.m, P.g, P.c_d, thrust_gain=1.1, substeps=substeps, **DRAGS)

    if kind == "held":
        return _physics().double(), 12, "wrench"
    if kind == "loop":
        return _loop_physics(substeps).double(), 16, "wrench"
    if kind in ("ctbr", "lagged"):
        return ctbr().double(), 12, "ctbr"
    rng = np.random.default_rng(11)
    n_in = 12 + 7 * history
    stats = {"in_mean": rng.normal(size=n_in) * 0.3, "in_std": rng.uniform(0.5, 2.0, n_in),
             "out_scale": rng.uniform(0.05, 0.5, 6)}
    torch.manual_seed(2)
    physics = _loop_physics(substeps) if kind == "loop-flight" else _physics() if level == "wrench" else ctbr()
    m = FlightModel(physics, stats, history=history, hidden=16, layers=2)
    if kind.startswith("lagged"):
        assert m.corrects_rates and m.out.out_features == 6
    with torch.no_grad():
        m.out.weight.normal_(0.0, 0.3)
        m.out.bias.normal_(0.0, 0.3)
    return m.double().eval(), 12 + len(physics.extra_states) + 7 * history, level


def _jacfwd(model, z, u):
    """Per-sample ``dz_next/dz`` (B, nz, nz) and ``dz_next/du`` (B, nz, 4) of ``model`` by
    :func:`torch.func.jacfwd` of the batched model (the diagonal blocks of its batch-by-batch Jacobian)."""
    jz = torch.func.jacfwd(lambda a: model(a, u))(z)           # (B, nz, B, nz)
    ju = torch.func.jacfwd(lambda b: model(z, b))(u)           # (B, nz, B, 4)
    return (torch.diagonal(jz, dim1=0, dim2=2).permute(2, 0, 1).detach(),
            torch.diagonal(ju, dim1=0, dim2=2).permute(2, 0, 1).detach())


# (torch's forward-mode differentiation loads its decompositions with torch.jit.script, which warns once)
@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
@pytest.mark.parametrize("kind,level,history,substeps", [
    pytest.param("held", "wrench", 0, 1, id="held-rates physics"),
    pytest.param("loop", "wrench", 0, 1, id="attitude-loop physics, 1 substep"),
    pytest.param("loop", "wrench", 0, 2, id="attitude-loop physics, 2 substeps"),
    pytest.param("loop-flight", "wrench", 0, 1, id="flight model on the attitude loop"),
    pytest.param("loop-flight", "wrench", 3, 1, id="flight model on the attitude loop, history 3"),
    pytest.param("ctbr", "ctbr", 0, 1, id="ctbr physics, 1 substep"),
    pytest.param("ctbr", "ctbr", 0, 10, id="ctbr physics, 10 substeps"),
    pytest.param("flight", "wrench", 0, 1, id="flight model, wrench"),
    pytest.param("flight", "wrench", 4, 1, id="flight model, wrench, history 4"),
    pytest.param("flight", "ctbr", 0, 2, id="flight model, ctbr"),
    pytest.param("flight", "ctbr", 4, 2, id="flight model, ctbr, history 4"),
    pytest.param("lagged", "ctbr", 0, 1, id="lagged-rates physics, 1 substep"),
    pytest.param("lagged", "ctbr", 0, 3, id="lagged-rates physics, 3 substeps"),
    pytest.param("lagged-flight", "ctbr", 2, 1, id="flight model on lagged rates, history 2"),
])
def test_forward_jacobian_is_the_derivative_of_forward(kind, level, history, substeps):
    """``forward_jacobian`` gives ``forward``'s next state bit for bit and its A, B as torch's forward-mode automatic
    differentiation of ``forward`` does, in float64: the physics' RK4 stages (any number of substeps), the network
    (through the body-frame velocity of its features) and the register's shift."""
    model, nz, level = _jacobian_model(kind, level, history, substeps)
    z, u = _jacobian_states(16, nz, level)
    with torch.no_grad():
        nxt, A, B = model.forward_jacobian(z, u)
        assert torch.equal(nxt, model(z, u))
    assert A.shape == (16, nz, nz) and B.shape == (16, nz, 4)
    A_ad, B_ad = _jacfwd(model, z, u)
    np.testing.assert_allclose(A.numpy(), A_ad.numpy(), rtol=0, atol=JACOBIAN_TOL)
    np.testing.assert_allclose(B.numpy(), B_ad.numpy(), rtol=0, atol=JACOBIAN_TOL)


def test_an_exported_ctbr_history_model_has_its_exact_derivative_graph(tmp_path):
    """The file written at ctbr for a model with a register has its derivative graph beside it: the contract finds it
    and checks it against central differences of the model, and onnxruntime's x_next, A and B are torch's
    ``forward_jacobian``'s."""
    import onnxruntime as ort

    from mpc.prediction.contract import check_model, jacobian_path
    from pinn.flights import HISTORY, export_flight_model

    model, nz, level = _jacobian_model("flight", "ctbr", HISTORY, substeps=2)
    theta = {"m": P.m, "Jxx": P.Jxx, "Jyy": P.Jyy, "Jzz": P.Jzz, "kt": P.kt, "kq": P.kq}
    path = export_flight_model(model, tmp_path / "h.onnx", theta, "test", level=level)
    info = check_model(path)
    assert info.jacobian == jacobian_path(path) and info.jacobian.is_file()
    z, u = _jacobian_states(32, nz, level, seed=8)
    got = ort.InferenceSession(str(info.jacobian)).run(["x_next", "A", "B"], {"x": z.numpy(), "u": u.numpy()})
    with torch.no_grad():
        want = model.forward_jacobian(z, u)
    for name, g, w in zip(("x_next", "A", "B"), got, want):
        np.testing.assert_allclose(g, w.numpy(), rtol=0, atol=ONNX_TOL, err_msg=name)


def test_a_model_on_the_attitude_loop_carries_its_states_and_exports_with_its_derivative_graph(tmp_path):
    """A flight model on the attitude loop: untrained, it is its physics (16 states, the loop's extra states held)
    with the register after them, shifting exactly; its file names the loop's states then the register's, and
    onnxruntime's x_next, A and B are torch's."""
    import onnxruntime as ort

    from mpc.prediction.contract import check_model
    from pinn.flights import export_flight_model, register_names

    flights = _flights(1)
    f = flights[0]
    m = FlightModel(_loop_physics(), flight_stats(flights, np.ones(4), 2), history=2).double()
    _, start = flight_step(m, np.ones(4))
    idx = np.arange(5, 40)
    z = start(f, idx)
    assert z.shape == (len(idx), 16 + 14)
    np.testing.assert_array_equal(z[:, 12:16], LOOP.start(f.x[idx])[:, 12:])
    nxt = m(torch.as_tensor(z), torch.as_tensor(f.u[idx])).detach().numpy()
    want = physics_step(P, substeps=1, **DRAGS, attitude_loop=LOOP)(z[:, :16], f.u[idx])
    np.testing.assert_allclose(nxt[:, :16], want, rtol=0, atol=PHYSICS_TOL)
    np.testing.assert_array_equal(nxt[:, 16:], register(f.x, f.u, idx + 1, 2))
    assert m.extra_states == EXTRA_STATES + register_names(2)
    model, nz, _ = _jacobian_model("loop-flight", "wrench", 2)
    theta = {"m": P.m, "Jxx": P.Jxx, "Jyy": P.Jyy, "Jzz": P.Jzz, "kt": P.kt, "kq": P.kq}
    path = export_flight_model(model, tmp_path / "loop.onnx", theta, "test")
    info = check_model(path)
    assert info.extra_states == model.extra_states and info.jacobian is not None
    zz, u = _jacobian_states(32, nz, "wrench", seed=9)
    got = ort.InferenceSession(str(info.jacobian)).run(["x_next", "A", "B"], {"x": zz.numpy(), "u": u.numpy()})
    with torch.no_grad():
        want = model.forward_jacobian(zz, u)
    for name, g, w in zip(("x_next", "A", "B"), got, want):
        np.testing.assert_allclose(g, w.numpy(), rtol=0, atol=ONNX_TOL, err_msg=name)


# ------------------------------------------------------------------ the ctbr level's nominal model in torch
def _lag_states(n, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 12)) * 0.3
    u = np.c_[np.full(n, 0.3) * (1.0 + 0.1 * rng.normal(size=n)), rng.normal(size=(n, 3))]
    return x, u


@pytest.mark.parametrize("vehicle,plant", [("crazyflie", "rotorpy"), (None, "rotorpy"), ("crazyflie", "sim")])
def test_the_lagged_rates_physics_is_the_ctbr_nominal_model(vehicle, plant):
    """One period of :class:`LaggedCtbrPhysics` from random states and commands: the rates are the lag's closed form
    exactly, and the whole state is the CasADi nominal model of the level (ten RK4 substeps) within
    LAG_NOMINAL_TOL, for the vehicle's own response (the Crazyflie's 7 ms lag is the fastest shipped)."""
    from mpc.prediction.models import model_params
    from pinn.flights import LaggedCtbrPhysics
    from sim.equations.levels_casadi import level_step_function
    from sim.vehicles.vehicle import load_vehicle

    v = load_vehicle(vehicle)
    response = v.inner_loop_at("ctbr").response()
    p = model_params("nominal", plant, v)
    x, u = _lag_states(40, 5)
    u[:, 0] *= p.m * p.g / 0.3
    with torch.no_grad():
        got = LaggedCtbrPhysics(p.m, p.g, p.c_d, response.rate_tau).double()(torch.as_tensor(x),
                                                                             torch.as_tensor(u)).numpy()
    decay = np.exp(-DT / np.asarray(response.rate_tau))
    np.testing.assert_allclose(got[:, 6:9], u[:, 1:] + (x[:, 6:9] - u[:, 1:]) * decay, rtol=0, atol=LAG_EXACT_TOL)
    F = level_step_function(p, "ctbr", response)
    want = np.stack([np.asarray(F(x[i], u[i])).ravel() for i in range(len(x))])
    np.testing.assert_allclose(got, want, rtol=0, atol=LAG_NOMINAL_TOL)


def test_the_lagged_rates_physics_converges_at_fourth_order():
    """Along the lag's exact rates, the attitude and velocity are RK4's: halving the substep divides the error
    (against 64 substeps) by about 16."""
    from pinn.flights import LaggedCtbrPhysics

    x, u = _lag_states(20, 6)
    x, u = torch.as_tensor(x), torch.as_tensor(u * np.r_[1.0, 8.0, 8.0, 8.0])       # fast turns: a visible error
    with torch.no_grad():
        run = {n: LaggedCtbrPhysics(P.m, P.g, P.c_d, (0.007, 0.009, 0.0125), substeps=n).double()(x, u).numpy()
               for n in (1, 2, 4, 64)}
    err = {n: np.abs(run[n] - run[64]).max() for n in (1, 2, 4)}
    for a, b in ((1, 2), (2, 4)):
        order = np.log2(err[a] / err[b])
        assert LAG_ORDER[0] < order < LAG_ORDER[1], (a, b, err)


def test_the_lagged_rates_physics_refuses_a_time_constant_that_is_not_positive():
    from pinn.flights import LaggedCtbrPhysics

    for tau in ((0.0, 0.01, 0.01), (0.01, -1.0, 0.01), (0.01, 0.01), (0.01, 0.01, float("nan"))):
        with pytest.raises(ValueError, match="^rate_tau must be 3 finite numbers > 0"):
            LaggedCtbrPhysics(P.m, P.g, P.c_d, tau)
    with pytest.raises(ValueError, match="^substeps must be an integer >= 1"):
        LaggedCtbrPhysics(P.m, P.g, P.c_d, (0.01,) * 3, substeps=0)


# ------------------------------------------------------------------ learning at ctbr from an excitation dataset
def test_a_ctbr_excitation_becomes_flights_of_its_own_splits():
    from pinn.ctbr import dataset_series

    ds = make_dataset("small", 7, 1.0, 3, level="ctbr")
    series = dataset_series(ds)
    assert {k: len(v) for k, v in series.items()} == {"train": 5, "val": 1, "test": 1}
    for split, flights in series.items():
        for f in flights:
            i = int(f.name[4:])
            assert ("train", "val", "test")[int(ds.split[i])] == split
            np.testing.assert_array_equal(f.x[:-1], ds.x[i])
            np.testing.assert_array_equal(f.x[1:], ds.x_next[i])
            np.testing.assert_array_equal(f.u[:-1], ds.u[i])
            assert f.x_ok.all() and len(f.x_ok) == ds.x.shape[1] + 1


def test_the_ctbr_learner_beats_its_physics_on_a_plant_with_motor_lag():
    """On our high-fidelity plant at ctbr (a 30 ms motor lag and rotor drag, neither in the level's nominal model),
    the network trained on the excitation's training flights scores below the nominal physics alone on its
    validation flights."""
    from pinn.ctbr import CTBR_HISTORY, ctbr_physics, dataset_series
    from pinn.flights import FlightModel
    from sim.flightlogs.logbench import goal_score as score
    from sim.vehicles.vehicle import load_vehicle

    veh = load_vehicle(None)
    series = dataset_series(make_dataset("aggressive", 8, 4.0, 0, level="ctbr", fidelity=veh.fidelity))
    physics, _ = ctbr_physics("sim", veh)
    cfg = FlightTrainConfig(history=CTBR_HISTORY, epochs=3, steps_per_epoch=30, windows=64, hidden=32, layers=2,
                            validation_stride=5)
    res = train_flight_model(series["train"], series["val"], None, cfg, physics=physics)
    alone = FlightModel(physics, flight_stats(series["train"], np.ones(4), CTBR_HISTORY), CTBR_HISTORY, 32, 2)
    step, start = flight_step(alone, np.ones(4))
    physics_score = score(prediction_errors(step, series["val"], start=start, stride=5).to_dict())
    assert min(res.scores) < LEARNED_GAIN * physics_score, (res.scores, physics_score)


def test_train_arch_ctbr_writes_a_ctbr_model_reruns_exactly_and_refuses_the_other_level(tmp_path, capsys):
    import onnxruntime as ort

    from mpc.prediction.contract import check_model
    from scenarios.cli import main
    from sim.vehicles.vehicle import load_vehicle

    ctbr, wrench = tmp_path / "ctbr.npz", tmp_path / "wrench.npz"
    make_dataset("small", 8, 3.0, 0, level="ctbr").save(ctbr)
    make_dataset("small", 8, 3.0, 0).save(wrench)
    outs = []
    for run in ("a", "b"):
        assert main(["train", "--arch", "ctbr", "--profile", "smoke", "--data", str(ctbr), "--out",
                     str(tmp_path / run)]) == 0
        info = check_model(tmp_path / run / "ctbr.onnx")
        assert info.level == "ctbr" and info.jacobian is not None
        sess = ort.InferenceSession(str(tmp_path / run / "ctbr.onnx"), providers=["CPUExecutionProvider"])
        z = np.random.default_rng(0).normal(0.0, 0.1, (5, sess.get_inputs()[0].shape[-1]))
        outs.append(sess.run(None, {sess.get_inputs()[0].name: z, sess.get_inputs()[1].name: np.ones((5, 4))})[0])
    np.testing.assert_array_equal(outs[0], outs[1])
    entry = json.loads((tmp_path / "a" / "manifest.json").read_text())["ctbr"]
    assert entry["level"] == "ctbr" and entry["data"]["level"] == "ctbr" and entry["data"]["n_traj"] == 8
    assert entry["flights"] == {"train": 6, "val": 1, "test": 1}
    assert entry["rate_tau_s"] == pytest.approx(list(load_vehicle(None).inner_loop_at("ctbr").response().rate_tau),
                                                rel=1e-12)
    capsys.readouterr()
    for args, message in ((["--arch", "ctbr", "--data", str(wrench)], "--arch ctbr learns from a dataset flown at"),
                          (["--arch", "hybrid", "--data", str(ctbr)], "holds commands at the ctbr level"),
                          (["--arch", "ctbr", "--recipe", "proposed", "--data", str(ctbr)], "--recipe applies to"),
                          (["--arch", "hybrid", "--profile", "smoke", "--data", str(wrench)], "--profile smoke is"),
                          (["--arch", "hybrid", "--aero", "select", "--data", str(wrench)],
                           "--aero select needs --arch hybrid_lag")):
        assert main(["train", *args, "--out", str(tmp_path / "c")]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
        assert not (tmp_path / "c").exists()
