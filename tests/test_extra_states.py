"""Models with extra states: actuator lags and shift registers, in the contract, the controllers and the oracle.

Two models are built here from scratch with ``onnx.helper``, as a user would:

* a **lag model**: the hover linearization of the nominal equations driven by
  a wrench that follows its command through a first-order lag (four extra
  states, the realized wrench);
* a **history model**: the same linearization driven by the input of three
  periods ago (twelve extra states, a shift register of past inputs), the
  model of the ``+delay`` scenarios' actuator.

Each is checked by ``check-model``, compared with the same equations in
numpy (in the model and in closed loop: the ONNX path must fly exactly like
the numpy one), and flown by the LTV-MPC and the SQP. The high-fidelity
oracle (the plant's own equations, rotor speeds as extra states) is compared
with the simulator and flown within a millimetre.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mpc.prediction.contract import check_model
from mpc.errors import ModelContractError
from mpc.prediction.models import AnalyticModel, OnnxModel, PredictionModel
from sim.params import DT, NU, NX, Fidelity, QuadParams

#: Tolerances of this module.
TOL = {
    "onnx_vs_numpy_step": 1e-12,        # m, rad, ...: the same affine map in float64
    "onnx_vs_numpy_flight": 1e-9,       # m of RMSE: the same model flown through onnxruntime and through numpy
    "oracle_vs_simulator": 1e-10,       # one period of the high-fidelity equations, model against simulator
    "equilibrium": 1e-9,                # RU: rotor speeds at rest against the allocation's square root
    "flatness_residual": 1e-4,          # continuous-time residual of the high-fidelity flatness map, SI units
    "oracle_highfi_rmse": 1e-3,         # m: the acceptance bound of the high-fidelity oracle on figure8-fast
    "history_rmse": 0.01,               # m: the history model on figure8-slow+delay (measured 6.6 mm, LTV and SQP)
}
LAG_TAU = 0.03          # s, the reference vehicle's motor lag
DELAY = 3               # periods, the +delay scenarios' input delay


def _hover_linearization():
    x0 = np.zeros(NX)
    x0[2] = -1.0
    u0 = np.array([QuadParams().hover_thrust, 0.0, 0.0, 0.0])
    _, A, B = AnalyticModel().linearize(x0, u0)
    return x0, u0, A[0], B[0]


def lag_matrices():
    """``(Az, Bz, c)`` of the lag model ``z_next = Az z + Bz u + c`` over ``z = (x, w)`` (16,)."""
    x0, u0, A, B = _hover_linearization()
    alpha = 1.0 - math.exp(-DT / LAG_TAU)            # the lag's step response after one period
    beta = 1.0 - LAG_TAU / DT * alpha                # its mean over the period
    n = NX + NU
    Az, Bz, c = np.zeros((n, n)), np.zeros((n, NU)), np.zeros(n)
    Az[:NX, :NX] = A
    Az[:NX, NX:] = B * (1.0 - beta)
    Bz[:NX] = B * beta
    c[:NX] = x0 - A @ x0 - B @ u0
    Az[NX:, NX:] = (1.0 - alpha) * np.eye(NU)
    Bz[NX:] = alpha * np.eye(NU)
    return Az, Bz, c


def history_matrices():
    """``(Az, Bz, c)`` of the history model over ``z = (x, u_{k-1}, u_{k-2}, u_{k-3})`` (24,)."""
    x0, u0, A, B = _hover_linearization()
    n = NX + NU * DELAY
    Az, Bz, c = np.zeros((n, n)), np.zeros((n, NU)), np.zeros(n)
    Az[:NX, :NX] = A
    Az[:NX, n - NU:] = B                             # the oldest input drives the body
    c[:NX] = x0 - A @ x0 - B @ u0
    Bz[NX:NX + NU] = np.eye(NU)                      # the newest slot takes this period's input
    for k in range(1, DELAY):
        Az[NX + k * NU:NX + (k + 1) * NU, NX + (k - 1) * NU:NX + k * NU] = np.eye(NU)
    return Az, Bz, c


LAG_NAMES = ["T_real", "tau_x_real", "tau_y_real", "tau_z_real"]
HISTORY_NAMES = [f"{name}_{k}" for k in range(1, DELAY + 1) for name in ("T", "tau_x", "tau_y", "tau_z")]
INPUT_SCALES = [0.13, 2e-3, 2e-3, 2e-3]


def write_affine_onnx(path, Az, Bz, c, names, scale=None, jacobian=True, declared=None, extra_meta=None):
    """An affine model ``x_next = x Az' + u Bz' + c`` (float64) built with onnx.helper; with its derivative graph."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    n = Az.shape[0]

    def graph(with_jac):
        nodes = [helper.make_node("MatMul", ["x", "AzT"], ["xa"]), helper.make_node("MatMul", ["u", "BzT"], ["ub"]),
                 helper.make_node("Add", ["xa", "ub"], ["s"]), helper.make_node("Add", ["s", "c"], ["x_next"])]
        inits = [numpy_helper.from_array(Az.T.copy(), "AzT"), numpy_helper.from_array(Bz.T.copy(), "BzT"),
                 numpy_helper.from_array(c.copy(), "c")]
        outputs = [helper.make_tensor_value_info("x_next", TensorProto.DOUBLE, ["batch", n])]
        if with_jac:
            nodes += [helper.make_node("Shape", ["x"], ["shape_x"], start=0, end=1),
                      helper.make_node("Concat", ["shape_x", "dims_a"], ["shape_a"], axis=0),
                      helper.make_node("Concat", ["shape_x", "dims_b"], ["shape_b"], axis=0),
                      helper.make_node("Expand", ["A1", "shape_a"], ["A"]),
                      helper.make_node("Expand", ["B1", "shape_b"], ["B"])]
            inits += [numpy_helper.from_array(np.array([n, n], dtype=np.int64), "dims_a"),
                      numpy_helper.from_array(np.array([n, NU], dtype=np.int64), "dims_b"),
                      numpy_helper.from_array(Az[None].copy(), "A1"), numpy_helper.from_array(Bz[None].copy(), "B1")]
            outputs += [helper.make_tensor_value_info("A", TensorProto.DOUBLE, ["batch", n, n]),
                        helper.make_tensor_value_info("B", TensorProto.DOUBLE, ["batch", n, NU])]
        g = helper.make_graph(nodes, "affine", [helper.make_tensor_value_info("x", TensorProto.DOUBLE, ["batch", n]),
                                                helper.make_tensor_value_info("u", TensorProto.DOUBLE, ["batch", NU])],
                              outputs, inits)
        m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
        m.ir_version = 8
        meta = {"dt": repr(DT), "pinnmpc.contract": "3", "theta": json.dumps(dict(zip(
            ("m", "Jxx", "Jyy", "Jzz", "kt", "kq"), QuadParams().theta.tolist())))}
        if declared is not False:
            meta["extra_states"] = json.dumps(names if declared is None else declared)
        if scale is not None:
            meta["extra_scale"] = json.dumps(scale)
        meta.update(extra_meta or {})
        for k, v in meta.items():
            onnx.helper.set_model_props(m, {**{e.key: e.value for e in m.metadata_props}, k: v})
        return m

    import onnx as _onnx
    _onnx.save(graph(False), str(path))
    if jacobian:
        _onnx.save(graph(True), str(path.with_name(path.stem + ".jac.onnx")))
    return path


class AffineModel(PredictionModel):
    """The same affine map in numpy (the reference the ONNX files are compared with)."""

    def __init__(self, Az, Bz, c, names, scale=None):
        self.Az, self.Bz, self.c = Az, Bz, c
        self.extra_names = tuple(names)
        self.extra_scale = None if scale is None else np.array(scale)
        self.name = "affine"
        self.theta = QuadParams().theta

    def step(self, x, u):
        x, u = np.atleast_2d(np.asarray(x, dtype=float)), np.atleast_2d(np.asarray(u, dtype=float))
        n = max(len(x), len(u))
        x, u = np.broadcast_to(x, (n, x.shape[1])), np.broadcast_to(u, (n, NU))
        return x @ self.Az.T + u @ self.Bz.T + self.c

    def linearize(self, x, u):
        z = self.step(x, u)
        n = len(z)
        return z, np.repeat(self.Az[None], n, 0), np.repeat(self.Bz[None], n, 0)


@pytest.fixture(scope="module")
def lag_file(tmp_path_factory):
    Az, Bz, c = lag_matrices()
    return write_affine_onnx(tmp_path_factory.mktemp("lag") / "lag.onnx", Az, Bz, c, LAG_NAMES, INPUT_SCALES)


@pytest.fixture(scope="module")
def history_file(tmp_path_factory):
    Az, Bz, c = history_matrices()
    return write_affine_onnx(tmp_path_factory.mktemp("hist") / "history.onnx", Az, Bz, c, HISTORY_NAMES,
                             INPUT_SCALES * DELAY, jacobian=False)


# ----------------------------------------------------------------------------------------------- the contract

def test_the_lag_model_passes_the_checker_with_its_extra_states(lag_file, capsys):
    info = check_model(lag_file)
    assert info.extra_states == tuple(LAG_NAMES) and info.nx == 16 and info.jacobian is not None
    from scenarios.cli import main

    assert main(["check-model", str(lag_file)]) == 0
    out = capsys.readouterr().out
    assert "extra states" in out and "T_real" in out


def test_the_onnx_lag_model_steps_like_the_numpy_one(lag_file):
    Az, Bz, c = lag_matrices()
    rng = np.random.default_rng(0)
    z = rng.normal(size=(7, 16)) * 0.1
    u = rng.normal(size=(7, 4)) * 0.01 + [0.667, 0, 0, 0]
    m = OnnxModel(lag_file)
    assert m.nx == 16 and m.extra_names == tuple(LAG_NAMES)
    np.testing.assert_allclose(m.step(z, u), z @ Az.T + u @ Bz.T + c, rtol=0, atol=TOL["onnx_vs_numpy_step"])
    _, A, B = m.linearize(z, u)
    np.testing.assert_allclose(A[3], Az, atol=TOL["onnx_vs_numpy_step"])
    np.testing.assert_allclose(B[3], Bz, atol=TOL["onnx_vs_numpy_step"])


@pytest.mark.parametrize("case, expected", [
    ("three names for four states", "must have shape [batch, 15]"),
    ("no names", "must name them in metadata 'extra_states'"),
    ("rigid-body name", "rigid-body names ['vz']"),
    ("scale of the wrong length", "'extra_scale' must be a JSON list of 4 finite numbers > 0"),
    ("unstable extra states", "do not settle"),
])
def test_a_model_whose_extra_states_do_not_match_gets_one_line(tmp_path, case, expected):
    Az, Bz, c = lag_matrices()
    kwargs = {"jacobian": False}
    names, scale = LAG_NAMES, None
    if case == "three names for four states":
        kwargs["declared"] = LAG_NAMES[:3]
    elif case == "no names":
        kwargs["declared"] = False
    elif case == "rigid-body name":
        kwargs["declared"] = LAG_NAMES[:3] + ["vz"]
    elif case == "scale of the wrong length":
        scale = [1.0, 1.0]
    else:
        Az = Az.copy()
        Az[NX:, NX:] = 1.05 * np.eye(NU)            # a "lag" that grows: no rest
    path = write_affine_onnx(tmp_path / "bad.onnx", Az, Bz, c, names, scale, **kwargs)
    with pytest.raises(ModelContractError) as e:
        check_model(path)
    msg = str(e.value)
    assert expected in msg and "\n" not in msg


# ----------------------------------------------------------------------------------------------- the controllers

def _fly(scenario, controller, model_file, model=None):
    from scenarios.closed_loop.runner import RunSpec, fly

    return fly(RunSpec(scenario, controller, str(model_file)), model=model)[0]


@pytest.mark.parametrize("controller", ["ltv", "sqp"])
def test_the_lag_model_flies_exactly_like_its_numpy_twin(lag_file, controller):
    """Through onnxruntime and through numpy the same equations must fly the same flight, extra states included."""
    Az, Bz, c = lag_matrices()
    onnx_run = _fly("hover+highfi", controller, lag_file)
    twin = AffineModel(Az, Bz, c, LAG_NAMES, INPUT_SCALES)
    numpy_run = _fly("hover+highfi", controller, lag_file, model=twin)
    assert not onnx_run["crashed"] and onnx_run["solver_failures"] == 0
    assert abs(onnx_run["rmse_position_m"] - numpy_run["rmse_position_m"]) < TOL["onnx_vs_numpy_flight"]
    assert abs(onnx_run["settled_error_m"] - numpy_run["settled_error_m"]) < TOL["onnx_vs_numpy_flight"]


def test_the_history_model_passes_and_its_register_holds_the_commands_sent(history_file):
    """A shift register of the last three inputs: the model of a three-period input delay. It passes the checker
    without a derivative graph (central differences), flies figure8-slow+delay with the LTV-MPC, and in flight the
    register the controller plans from holds exactly the last three commands it sent."""
    from mpc.prediction.models import OnnxModel
    from scenarios.closed_loop.library import get_scenario
    from scenarios.closed_loop.loop import IdealClock, StateSensor, fly_loop
    from mpc.controllers.factory import make_controller
    from scenarios.closed_loop.runner import RunSpec, plant_reference
    from sim.plants.named import make_plant

    info = check_model(history_file)
    assert info.nx == NX + NU * DELAY and info.jacobian is None
    model = OnnxModel(history_file)
    spec = RunSpec("figure8-slow+delay", "ltv", str(history_file))
    sc = get_scenario(spec.scenario)
    ctrl = make_controller("ltv", model, sc.reference())
    K = 150
    ctrl.prepare(K * DT)
    x_ref, _ = plant_reference(spec, sc, DT * np.arange(K + 1))
    plant = make_plant("sim", None)
    plant.reset(np.array(sc.x0))
    registers = []

    class Recording:
        def __call__(self, x, t):
            out = ctrl(x, t)
            registers.append(ctrl.tracker.extra)
            return out

        def applied(self, u):
            ctrl.applied(u)

        def prepare_next(self, until=None):
            ctrl.prepare_next(until)

    clock = IdealClock(plant.hover_input, sc.delay_steps)
    tr = fly_loop(plant, StateSensor(), Recording(), clock, x_ref, K)
    assert tr.crash_step is None and not np.any(tr.solver_failed)
    reg = np.array(registers)                     # (K, 12): u_{k-1}, u_{k-2}, u_{k-3} at period k
    sent = tr.u_command
    for k in range(DELAY, K):
        expected = np.concatenate([sent[k - 1], sent[k - 2], sent[k - 3]])
        np.testing.assert_allclose(reg[k], expected, rtol=0, atol=1e-12)
    # and the plant applied the oldest of them
    np.testing.assert_allclose(tr.u[DELAY:], sent[:K - DELAY], rtol=0, atol=0)


@pytest.mark.slow
@pytest.mark.parametrize("controller", ["ltv", "sqp"])
def test_the_history_model_flies_the_delay_scenario(history_file, controller):
    r = _fly("figure8-slow+delay", controller, history_file)
    assert not r["crashed"] and r["solver_failures"] == 0
    assert r["rmse_position_m"] < TOL["history_rmse"], r["rmse_position_m"]


# ----------------------------------------------------------------------------------------------- the oracle

def test_the_high_fidelity_oracle_steps_like_the_simulator():
    from sim import Simulator

    fid = Fidelity(motor_tau=LAG_TAU, rotor_drag=1.2e-3, rotor_gyro=5e-6)
    p = QuadParams()
    m = AnalyticModel(p, fidelity=fid)
    assert m.extra_names == ("n1", "n2", "n3", "n4")
    rng = np.random.default_rng(3)
    x = np.zeros((2, NX))
    x[:, 2] = -1.0
    x[:, 3:12] = rng.normal(scale=[0.3, 0.3, 1.0, 2.0, 2.0, 1.0, 1.5, 1.5, 0.5], size=(2, 9))
    n0 = p.n_hover * rng.uniform(0.7, 1.3, size=(2, 4))
    u = np.array([[0.8, 2e-4, -3e-4, 1e-4], [0.5, -1e-3, 5e-4, -2e-4]])
    out = Simulator(p, fid).step_full(x, u, rotor_speed=n0)       # the numpy batch path
    z = m.step(np.hstack([x, n0]), u)
    np.testing.assert_allclose(z[:, :NX], out.x, rtol=0, atol=TOL["oracle_vs_simulator"])
    np.testing.assert_allclose(z[:, NX:], out.rotor_speed, rtol=0, atol=TOL["oracle_vs_simulator"] * p.n_hover)


def test_the_oracles_rotors_at_rest_turn_at_the_commanded_speeds():
    from mpc.prediction.extended import extra_equilibrium
    from sim.vehicles.rotors import realize

    p = QuadParams()
    m = AnalyticModel(p, fidelity=Fidelity(motor_tau=LAG_TAU))
    x = np.zeros((2, NX))
    u = np.array([[p.hover_thrust, 0, 0, 0], [0.9 * p.hover_thrust, 3e-4, -2e-4, 1e-4]])
    e = extra_equilibrium(m, x, u)
    np.testing.assert_allclose(e, np.sqrt(realize(u, p).n_sq), rtol=0, atol=TOL["equilibrium"])


def test_the_high_fidelity_flatness_map_is_a_solution_of_the_equations():
    """States, rotor speeds and wrench of :func:`actuated_flat_state` satisfy the continuous high-fidelity equations:
    the states' time derivative (central differences of the map) equals the equations' rates at them."""
    from mpc.references.trajectory import actuated_flat_state
    from scenarios.closed_loop.library import get_scenario
    from sim import Simulator
    from sim.vehicles.rotors import wrench_from_rotor_sq

    p, fid = QuadParams(), Fidelity(motor_tau=LAG_TAU, rotor_drag=1.2e-3, rotor_gyro=5e-6)
    traj = get_scenario("figure8-fast").reference()
    t, h = np.linspace(0.5, 5.5, 11), 1e-5
    x, n, w = actuated_flat_state(traj, t, p, fid)
    dx = (actuated_flat_state(traj, t + h, p, fid)[0] - actuated_flat_state(traj, t - h, p, fid)[0]) / (2 * h)
    rates = Simulator(p, fid)._rates_hifi(x, wrench_from_rotor_sq(n * n, p), n, None)
    assert np.max(np.abs(rates - dx)) < TOL["flatness_residual"]
    # Without the drag, the map is the nominal one.
    from mpc.references.trajectory import flat_state
    x0, _, _ = actuated_flat_state(traj, t, p, Fidelity(motor_tau=LAG_TAU))
    np.testing.assert_allclose(x0, flat_state(traj.flat(t), p)[0], rtol=0, atol=1e-12)


@pytest.mark.slow
def test_the_oracle_flies_figure8_fast_highfi_within_a_millimetre():
    """The plant's true equations, lag included, flown by the SQP (the nominal equations get about 39 mm)."""
    from scenarios.closed_loop.runner import RunSpec, fly

    r = fly(RunSpec("figure8-fast+highfi", "sqp", "oracle"))[0]
    assert not r["crashed"] and r["solver_failures"] == 0
    assert r["rmse_position_m"] < TOL["oracle_highfi_rmse"], r["rmse_position_m"]


def test_the_controller_is_told_the_command_sent_averaged_over_the_period_before_the_delay():
    """Under real-time timing a command that arrives 4 ms into a period counts for 6 ms of it; the plant's own
    input delay does not shift what the controller is told (its model's input is the command)."""
    from scenarios.closed_loop.loop import RealtimeClock

    class Plant:
        def advance(self, u, duration):
            pass

    hover, u1 = np.array([0.6, 0, 0, 0]), np.array([0.8, 1e-3, 0, 0])
    clock = RealtimeClock(hover, delay_steps=1)
    clock.command(0, u1, 0.0035)                  # returns after 4 ms (rounded up to the 1 ms substep)
    clock.fly_period(Plant(), 0)
    np.testing.assert_allclose(clock.sent, 0.4 * hover + 0.6 * u1, rtol=0, atol=1e-15)
    np.testing.assert_allclose(clock.u, hover, rtol=0, atol=0)      # the plant still waits for its delay
    clock.fly_period(Plant(), 1)
    np.testing.assert_allclose(clock.sent, u1, rtol=0, atol=1e-15)


def test_evaluation_refuses_extra_states_it_cannot_rebuild_from_a_flight_log(history_file):
    # A shift register of past inputs is not a motor: `pinnmpc evaluate` cannot rebuild it from the logged data
    # and says so in one line, naming the file.
    from pinn.evaluate import model_extra_states
    from sim.identification.excitation import make_dataset
    ds = make_dataset("small", 1, 1.0, 0)
    with pytest.raises(ValueError, match=r"cannot be reconstructed from a flight log") as e:
        model_extra_states(check_model(history_file), ds)
    assert str(history_file) in str(e.value) and "\n" not in str(e.value)
