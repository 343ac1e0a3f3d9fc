"""Dynamics and integrator: backend agreement, closed-form solutions, convergence order."""

import casadi as ca
import numpy as np
import pytest

from sim import QuadParams, Simulator, dynamics, rk4_step
from sim.equations.dynamics import rates
from sim.equations.dynamics_casadi import dynamics_casadi, step_function

# Tolerances of this module (all relative unless stated).
TOL = {
    "backend_agreement": 1e-12,     # numpy vs CasADi dynamics
    "step_agreement": 1e-12,        # numpy Simulator.step vs CasADi RK4 step function
    "hover_drift_m": 1e-9,          # absolute, over 10 s
    "free_fall": 1e-9,              # tanh velocity law, log-cosh position
    "spin_up": 1e-10,               # rate linear, angle quadratic in time
    "tumbling_invariants": 1e-9,    # kinetic energy and |J omega| over 5 s
    "rk4_order": 0.3,               # measured order within 4 +/- this
}

P = QuadParams()


def random_envelope(rng, n):
    """States and inputs spread over the flight envelope (roll/pitch up to 60 deg)."""
    x = np.empty((n, 12))
    x[:, 0:3] = rng.uniform(-5, 5, (n, 3))
    x[:, 3:5] = np.radians(rng.uniform(-60, 60, (n, 2)))
    x[:, 5] = rng.uniform(-np.pi, np.pi, n)
    x[:, 6:9] = rng.uniform(-6, 6, (n, 3))
    x[:, 9:12] = rng.uniform(-10, 10, (n, 3))
    u = np.column_stack([rng.uniform(0, 2 * P.m * P.g, n), rng.uniform(-0.01, 0.01, (n, 2)),
                         rng.uniform(-0.02, 0.02, n)])
    return x, u


def close(a, b, rtol):
    """Element-wise |a - b| <= rtol * (column scale), with column scale = max |b| of that column."""
    scale = np.maximum(np.max(np.abs(b), axis=0), 1e-300)
    return np.max(np.abs(a - b) / scale)


def test_numpy_and_casadi_dynamics_agree(rng):
    x, u = random_envelope(rng, 1000)
    xs, us = ca.SX.sym("x", 12), ca.SX.sym("u", 4)
    f = ca.Function("f", [xs, us], [dynamics_casadi(xs, us, P)])
    f_ca = np.asarray(f(x.T, u.T)).T
    f_np = dynamics(x, u, P)
    assert close(f_np, f_ca, 0) <= TOL["backend_agreement"]


def test_numpy_and_casadi_step_agree(rng):
    x, u = random_envelope(rng, 200)
    # Keep rotor commands feasible so the simulator's rotor layer is transparent.
    u[:, 0] = np.clip(u[:, 0], 0.6 * P.m * P.g, 1.4 * P.m * P.g)
    u[:, 1:3] *= 0.3
    u[:, 3] *= 0.3
    F = step_function(P)
    x_ca = np.asarray(F(x.T, u.T)).T
    x_np = Simulator(P).step(x, u)
    assert close(x_np, x_ca, 0) <= TOL["step_agreement"]


def test_hover_stays_put():
    s = Simulator(P)
    x0 = np.zeros(12)
    x0[2] = -1.0
    u = np.array([P.m * P.g, 0.0, 0.0, 0.0])
    x = x0
    for _ in range(1000):  # 10 s
        x = s.step(x, u)
    assert np.max(np.abs(x[0:3] - x0[0:3])) < TOL["hover_drift_m"]


def test_free_fall_with_quadratic_drag_matches_tanh_law():
    s = Simulator(P)
    x = np.zeros(12)
    t_end = 3.0
    for _ in range(300):
        x = s.step(x, np.zeros(4))
    a = np.sqrt(P.g * P.c_d)
    vz = np.sqrt(P.g / P.c_d) * np.tanh(a * t_end)
    z = np.log(np.cosh(a * t_end)) / P.c_d
    assert abs(x[11] - vz) / vz < TOL["free_fall"]
    assert abs(x[2] - z) / z < TOL["free_fall"]
    # It really fell: more than half of terminal velocity.
    assert x[11] > 0.5 * np.sqrt(P.g / P.c_d)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_constant_torque_spin_up(axis):
    s = Simulator(P)
    J = np.array([P.Jxx, P.Jyy, P.Jzz])[axis]
    tau = 2e-5 if axis < 2 else 4e-5
    u = np.array([P.m * P.g, 0.0, 0.0, 0.0])
    u[1 + axis] = tau
    x = np.zeros(12)
    t_end = 1.0
    for _ in range(100):
        x = s.step(x, u)
    rate = tau / J * t_end
    angle = 0.5 * tau / J * t_end ** 2
    assert abs(x[6 + axis] - rate) / rate < TOL["spin_up"]
    assert abs(x[3 + axis] - angle) / angle < TOL["spin_up"]
    others = [i for i in range(3) if i != axis]
    assert np.all(np.abs(x[6 + np.array(others)]) < TOL["spin_up"] * rate)


def test_torque_free_tumbling_conserves_energy_and_angular_momentum():
    s = Simulator(P)
    J = np.array([P.Jxx, P.Jyy, P.Jzz])
    assert len(set(J)) == 3
    x = np.zeros(12)
    x[6:9] = [0.3, 0.2, 2.0]
    w0 = x[6:9].copy()
    E0, L0 = 0.5 * np.sum(J * w0 ** 2), np.linalg.norm(J * w0)
    traj = []
    for _ in range(500):  # 5 s
        x = s.step(x, np.zeros(4))
        traj.append(x[6:9])
    traj = np.array(traj)
    E = 0.5 * np.sum(J * traj ** 2, axis=1)
    L = np.linalg.norm(J * traj, axis=1)
    assert np.max(np.abs(E - E0)) / E0 < TOL["tumbling_invariants"]
    assert np.max(np.abs(L - L0)) / L0 < TOL["tumbling_invariants"]
    # Not trivially constant: the unequal inertias make p and q oscillate.
    assert np.ptp(traj[:, 0]) > 0.5 and np.ptp(traj[:, 1]) > 0.5


def test_rk4_convergence_order_is_four():
    x0 = np.array([0.1, -0.2, -1.0, 0.3, -0.2, 0.5, 1.5, -2.0, 3.0, 2.0, -1.0, 0.5])
    u = np.array([0.9 * P.m * P.g, 2e-5, -3e-5, 1e-5])
    f = lambda s: rates(s, u, P)  # noqa: E731
    t_end = 1.0
    ref = rk4_step(f, x0, t_end / 4096, 4096)
    hs = np.array([t_end / n for n in (16, 32, 64, 128)])
    errs = np.array([np.max(np.abs(rk4_step(f, x0, h, int(round(t_end / h))) - ref)) for h in hs])
    order = np.polyfit(np.log(hs), np.log(errs), 1)[0]
    assert abs(order - 4.0) < TOL["rk4_order"], (order, errs)


@pytest.mark.parametrize("case", ["same shapes", "one state", "input broadcast", "payload masses", "float32 state"])
def test_rates_assembles_its_columns_as_the_general_stack_does(rng, monkeypatch, case):
    """The derivative's columns are written into one array when they share a shape and dtype, and stacked by the
    general broadcasting form otherwise: both give the general form's array, to the last bit."""
    from types import SimpleNamespace

    import sim.equations.dynamics as D

    P = QuadParams()
    x = rng.normal(size=(6, 12)) * 0.5
    u = np.abs(rng.normal(size=(6, 4))) * 0.1
    p, accel = P, None
    if case == "one state":
        x, u = x[0], u[0]
    elif case == "input broadcast":
        u, accel = u[0], rng.normal(size=3)
    elif case == "payload masses":
        p = SimpleNamespace(**{k: getattr(P, k) for k in ("Jxx", "Jyy", "Jzz", "c_d", "g")}, m=P.m * (1 + rng.random(6)))
    elif case == "float32 state":
        x = x.astype(np.float32)
    got = D.rates(x, u, p, accel=accel)
    monkeypatch.setattr(D, "_columns", lambda cols, shape: np.stack(np.broadcast_arrays(*cols), axis=-1))
    want = D.rates(x, u, p, accel=accel)
    assert got.shape == x.shape and got.dtype == want.dtype and np.array_equal(got, want)
