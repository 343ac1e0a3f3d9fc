"""The ONNX model contract checker (mpc.prediction.contract) and ``pinnmpc check-model``.

The models are built here with onnx.helper (no torch): a small residual tanh
network x_next = x + tanh([x, u] W1) W2s and its exact derivative graph
A = I + W2s^T diag(1 - a^2) W1x^T, B = W2s^T diag(1 - a^2) W1u^T.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from mpc.prediction.contract import (CONTRACT_VERSION, OPTIONAL_METADATA, REQUIRED_METADATA, ModelInfo, _fd_jacobians,
                                     _probe_batch, check_model, config_hash, jacobian_path, open_session)
from mpc.errors import ModelContractError
from scenarios.cli import main
from sim.params import INPUT_NAMES, STATE_NAMES, THETA_NAMES, QuadParams

TOL = {
    "analytic_jacobian": 1e-12,   # ONNX derivative graph vs the numpy formula (float64)
    "fd_float64": 1e-6,           # checker's finite differences vs the analytic Jacobian, relative
    "fd_float32": 1e-3,
}

REPO = Path(__file__).resolve().parents[1]
NX, NU, H = 12, 4, 8
OPSET = [helper.make_opsetid("", 17)]
TRAINING_CONFIG = {"arch": "toy", "hidden": [H], "lr": 1e-3, "epochs": 3, "profile": "quick"}
TEST_METRICS = {"one_step_rmse": 1.2e-4, "rollout_rmse_m": 0.01}


def _weights():
    rng = np.random.default_rng(7)
    w1 = rng.normal(0.0, 0.3, (NX + NU, H))
    w2s = 0.01 * rng.normal(0.0, 1.0, (H, NX))
    return w1, w2s


def _metadata(**changes):
    theta = {n: getattr(QuadParams(), n) for n in THETA_NAMES}
    meta = {
        "pinnmpc.contract": CONTRACT_VERSION,
        "architecture": "toy",
        "dt": "0.01",
        "state_names": json.dumps(list(STATE_NAMES)),
        "input_names": json.dumps(list(INPUT_NAMES)),
        "theta": json.dumps(theta),
        "training_config": json.dumps(TRAINING_CONFIG),
        "config_hash": config_hash(TRAINING_CONFIG),
        "dataset_seed": "3",
        "code_version": "0.1.0+test",
        "test_metrics": json.dumps(TEST_METRICS),
        "level": "wrench",
    }
    for k, v in changes.items():
        if v is None:
            del meta[k]
        else:
            meta[k] = v
    return meta


def _save(graph, path, meta=None):
    model = helper.make_model(graph, opset_imports=OPSET, producer_name="test_contract")
    model.ir_version = 9
    if meta:
        helper.set_model_props(model, meta)
    onnx.save(model, str(path))
    return path


def _forward_nodes(dtype, x="x", u="u"):
    """Nodes and initializers computing a = tanh([x, u] W1) and x_next = x + a W2s."""
    w1, w2s = _weights()
    inits = [numpy_helper.from_array(w1.astype(dtype), "W1"), numpy_helper.from_array(w2s.astype(dtype), "W2s")]
    nodes = [
        helper.make_node("Concat", [x, u], ["z"], axis=1),
        helper.make_node("MatMul", ["z", "W1"], ["pre"]),
        helper.make_node("Tanh", ["pre"], ["a"]),
        helper.make_node("MatMul", ["a", "W2s"], ["dx"]),
        helper.make_node("Add", [x, "dx"], ["x_next"]),
    ]
    return nodes, inits


def build_model(path, dtype=np.float64, *, input_names=("x", "u"), nx=NX, batch="B", output_name="x_next",
                u_dtype=None, meta=None):
    """Write the toy model; keyword arguments inject one defect each."""
    et = helper.np_dtype_to_tensor_dtype(np.dtype(dtype))
    ut = helper.np_dtype_to_tensor_dtype(np.dtype(u_dtype or dtype))
    xn, un = input_names
    nodes, inits = _forward_nodes(dtype, xn, un)
    if output_name != "x_next":
        nodes.append(helper.make_node("Identity", ["x_next"], [output_name]))
    graph = helper.make_graph(
        nodes, "toy",
        [helper.make_tensor_value_info(xn, et, [batch, nx]), helper.make_tensor_value_info(un, ut, [batch, NU])],
        [helper.make_tensor_value_info(output_name, et, [batch, NX])],
        initializer=inits)
    return _save(graph, path, _metadata() if meta is None else meta)


def build_jacobian(model_path, dtype=np.float64, *, a_scale=1.0, b_scale=1.0):
    """Write the exact derivative graph beside ``model_path`` (A or B optionally scaled: a defect)."""
    w1, w2s = _weights()
    et = helper.np_dtype_to_tensor_dtype(np.dtype(dtype))
    nodes, inits = _forward_nodes(dtype)
    e = np.hstack([np.eye(NX), np.zeros((NX, NU))])
    inits += [numpy_helper.from_array(a.astype(dtype), n) for a, n in [
        (np.array(1.0), "one"), (w2s.T.copy(), "W2sT"), (w1.T.copy(), "W1T"), (e, "E"), (np.array(a_scale), "a_scale"),
        (np.array(b_scale), "b_scale")]]
    inits += [numpy_helper.from_array(np.array(v, dtype=np.int64), n) for v, n in [
        ([1], "ax1"), ([2], "ax2"), ([0], "i0"), ([NX], "i12"), ([NX + NU], "i16")]]
    nodes += [
        helper.make_node("Mul", ["a", "a"], ["a2"]),
        helper.make_node("Sub", ["one", "a2"], ["s"]),                 # (B, H)
        helper.make_node("Unsqueeze", ["s", "ax1"], ["s3"]),           # (B, 1, H)
        helper.make_node("Mul", ["s3", "W2sT"], ["M"]),                # (B, 12, H)
        helper.make_node("MatMul", ["M", "W1T"], ["Jn"]),              # (B, 12, 16)
        helper.make_node("Add", ["Jn", "E"], ["J"]),
        helper.make_node("Slice", ["J", "i0", "i12", "ax2"], ["A0"]),
        helper.make_node("Mul", ["A0", "a_scale"], ["A"]),
        helper.make_node("Slice", ["J", "i12", "i16", "ax2"], ["B0"]),
        helper.make_node("Mul", ["B0", "b_scale"], ["B"]),
    ]
    graph = helper.make_graph(
        nodes, "toy_jac",
        [helper.make_tensor_value_info("x", et, ["B", NX]), helper.make_tensor_value_info("u", et, ["B", NU])],
        [helper.make_tensor_value_info("x_next", et, ["B", NX]), helper.make_tensor_value_info("A", et, ["B", NX, NX]),
         helper.make_tensor_value_info("B", et, ["B", NX, NU])],
        initializer=inits)
    return _save(graph, jacobian_path(model_path))


def analytic_jacobian(x, u):
    """Numpy A (b, 12, 12) and B (b, 12, 4) of the toy model."""
    w1, w2s = _weights()
    a = np.tanh(np.concatenate([x, u], axis=1) @ w1)
    j = np.einsum("hi,bh,kh->bik", w2s, 1.0 - a**2, w1) + np.hstack([np.eye(NX), np.zeros((NX, NU))])
    return j[:, :, :NX], j[:, :, NX:]


@pytest.fixture
def valid(tmp_path):
    """A valid float64 model with its derivative graph."""
    path = build_model(tmp_path / "toy.onnx")
    build_jacobian(path)
    return path


# --------------------------------------------------------------------------- helpers of the contract

def test_jacobian_path_and_config_hash():
    assert jacobian_path("models/baseline.onnx") == Path("models/baseline.jac.onnx")
    assert jacobian_path(Path("/a/b.c/m.onnx")) == Path("/a/b.c/m.jac.onnx")
    assert config_hash({}) == "44136fa355b3678a1146ad16f7e8649e94fb4fc21fe77e8310c060f61caaff8a"
    assert config_hash({"b": 1, "a": [1, 2]}) == config_hash({"a": [1, 2], "b": 1})
    assert config_hash({"a": 1}) != config_hash({"a": 2})
    assert REQUIRED_METADATA == ("dt",)


def test_open_session_rejects_bad_thread_count(valid):
    assert open_session(valid, threads=2).get_inputs()[0].name in ("x", "u")
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        open_session(valid, threads=0)


def test_test_fixture_jacobian_graph_is_exact_and_fd_agrees(valid):
    x, u = _probe_batch(3, np.dtype(np.float64))
    _, a, b = open_session(jacobian_path(valid)).run(["x_next", "A", "B"], {"x": x, "u": u})
    a_ref, b_ref = analytic_jacobian(x, u)
    assert np.abs(a - a_ref).max() <= TOL["analytic_jacobian"]
    assert np.abs(b - b_ref).max() <= TOL["analytic_jacobian"]
    a_fd, b_fd = _fd_jacobians(open_session(valid), x, u, np.dtype(np.float64), str(valid))
    assert np.linalg.norm(a_fd - a_ref) <= TOL["fd_float64"] * np.linalg.norm(a_ref)
    assert np.linalg.norm(b_fd - b_ref) <= TOL["fd_float64"] * np.linalg.norm(b_ref)


# --------------------------------------------------------------------------- valid models

def test_valid_model_passes_and_reports_its_metadata(valid):
    info = check_model(valid)
    assert isinstance(info, ModelInfo)
    assert info.path == valid and info.jacobian == valid.with_name("toy.jac.onnx")
    assert info.architecture == "toy" and info.dt == 0.01 and info.dtype == np.float64
    assert info.theta == {n: getattr(QuadParams(), n) for n in THETA_NAMES}
    assert list(info.theta) == list(THETA_NAMES)
    assert info.training_config == TRAINING_CONFIG and info.config_hash == config_hash(TRAINING_CONFIG)
    assert info.dataset_seed == 3 and info.code_version == "0.1.0+test" and info.test_metrics == TEST_METRICS
    # every key but the extra states' (a 12-state model has none)
    assert set(info.metadata) == set(REQUIRED_METADATA) | set(OPTIONAL_METADATA) - {"extra_states", "extra_scale"}
    assert info.extra_states == () and info.nx == 12
    d = info.to_dict()
    assert json.loads(json.dumps(d)) == d and d["dtype"] == "float64" and d["jacobian"].endswith("toy.jac.onnx")


def test_valid_model_without_jacobian_graph(tmp_path):
    info = check_model(build_model(tmp_path / "m.onnx"))
    assert info.jacobian is None


def test_valid_float32_model_with_jacobian_graph(tmp_path):
    path = build_model(tmp_path / "m32.onnx", np.float32)
    build_jacobian(path, np.float32)
    info = check_model(str(path))
    assert info.dtype == np.float32 and info.jacobian is not None
    x, u = _probe_batch(3, np.dtype(np.float32))
    a_fd, b_fd = _fd_jacobians(open_session(path), x, u, np.dtype(np.float32), str(path))
    a_ref, b_ref = analytic_jacobian(x.astype(float), u.astype(float))
    assert np.linalg.norm(a_fd - a_ref) <= TOL["fd_float32"] * np.linalg.norm(a_ref)


def test_only_dt_is_required_and_each_optional_key_may_be_left_out(tmp_path):
    info = check_model(build_model(tmp_path / "min.onnx", meta={"dt": "0.01"}))
    assert (info.theta, info.training_config, info.config_hash, info.dataset_seed, info.code_version,
            info.test_metrics) == (None,) * 6
    assert info.architecture == "min"       # the file's stem
    assert json.loads(json.dumps(info.to_dict()))["theta"] is None
    for i, key in enumerate(k for k in OPTIONAL_METADATA if not k.startswith("extra_")):   # the toy has no extras
        meta = _metadata(**{key: None})
        if key == "training_config":
            del meta["config_hash"]          # a hash needs the configuration it hashes
        check_model(build_model(tmp_path / f"m{i}.onnx", meta=meta))
    # the shipped models are contract version 1, still read
    assert check_model(REPO / "models" / "baseline.onnx").metadata["pinnmpc.contract"] == "1"


def test_extra_metadata_keys_are_allowed(tmp_path):
    info = check_model(build_model(tmp_path / "m.onnx", meta={**_metadata(), "note": "hello"}))
    assert info.metadata["note"] == "hello"


# --------------------------------------------------------------------------- defects, one message each

def _swapped_state_names():
    names = list(STATE_NAMES)
    names[0], names[1] = names[1], names[0]
    return json.dumps(names)


def _theta(**changes):
    theta = {n: getattr(QuadParams(), n) for n in THETA_NAMES}
    theta.update(changes)
    return json.dumps(theta)


DEFECTS = {
    "input names": (dict(input_names=("state", "u")), "graph inputs must be exactly ['x', 'u']; found ['state', 'u']"),
    "x width 11": (dict(nx=11), "input 'x' must have shape [batch, 12]; found [B, 11]"),
    "fixed batch": (dict(batch=1), "batch dimension must be dynamic"),
    "output name": (dict(output_name="y"), "graph outputs must be exactly ['x_next']; found ['y']"),
    "x/u dtype": (dict(u_dtype=np.float32), "must have the same element type (float32 or float64); found x float64, "
                                            "u float32"),
    "integer dtype": (dict(dtype=np.int64), "must have element type float32 or float64; found int64"),
    "missing dt": (dict(meta=_metadata(dt=None)), "missing required key(s) ['dt']"),
    "contract version": (dict(meta=_metadata(**{"pinnmpc.contract": "4"})),
                         "'pinnmpc.contract' must be one of ['1', '2', '3']"),
    "hash without config": (dict(meta=_metadata(training_config=None)), "'config_hash' is given without the "
                                                                         "'training_config'"),
    "dt": (dict(meta=_metadata(dt="0.02")), "metadata 'dt' must equal sim.params.DT = 0.01 s"),
    "dt not a number": (dict(meta=_metadata(dt="fast")), "metadata 'dt' must be a number"),
    "state names": (dict(meta=_metadata(state_names=_swapped_state_names())), "metadata 'state_names' must be"),
    "input names json": (dict(meta=_metadata(input_names="T,tau_x")), "metadata 'input_names' must be the JSON list"),
    "theta keys": (dict(meta=_metadata(theta=json.dumps({"m": 0.07}))),
                   "found missing ['Jxx', 'Jyy', 'Jzz', 'kt', 'kq']"),
    "theta extra key": (dict(meta=_metadata(theta=_theta(g=9.81))), "keys ['m', 'Jxx', 'Jyy', 'Jzz', 'kt', 'kq']; "
                                                                  "found unexpected ['g']"),
    "theta nonpositive": (dict(meta=_metadata(theta=_theta(m=-0.068))), "theta['m'] must be a finite number > 0"),
    "theta zero": (dict(meta=_metadata(theta=_theta(kq=0))), "theta['kq'] must be a finite number > 0; found 0"),
    "config hash": (dict(meta=_metadata(config_hash=config_hash({"other": 1}))),
                    "config_hash does not match training_config"),
    "training config": (dict(meta=_metadata(training_config="[1, 2]")), "'training_config' must be a JSON object"),
    "dataset seed": (dict(meta=_metadata(dataset_seed="3.5")), "'dataset_seed' must be an integer"),
}


@pytest.mark.parametrize("defect", list(DEFECTS))
def test_each_defect_has_its_own_message(tmp_path, defect):
    kwargs, needle = DEFECTS[defect]
    path = build_model(tmp_path / "bad.onnx", **kwargs)
    with pytest.raises(ModelContractError) as exc:
        check_model(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: ")
    assert needle in msg


def test_defect_messages_are_distinct(tmp_path):
    messages = set()
    for i, (kwargs, _) in enumerate(DEFECTS.values()):
        with pytest.raises(ModelContractError) as exc:
            check_model(build_model(tmp_path / f"m{i}.onnx", **kwargs))
        messages.add(str(exc.value).split(": ", 1)[1])
    assert len(messages) == len(DEFECTS)


def test_model_error_is_a_value_error():
    assert issubclass(ModelContractError, ValueError)


def test_missing_file(tmp_path):
    with pytest.raises(ModelContractError, match="model file not found"):
        check_model(tmp_path / "nope.onnx")


def test_not_an_onnx_file(tmp_path):
    path = tmp_path / "junk.onnx"
    path.write_bytes(b"\x00\xffnot a protobuf" * 10)
    with pytest.raises(ModelContractError, match="junk.onnx: (not a readable ONNX file|fails onnx.checker)"):
        check_model(path)


def test_non_finite_output_is_rejected(tmp_path):
    path = build_model(tmp_path / "nan.onnx")
    model = onnx.load(str(path))
    w1 = numpy_helper.to_array(model.graph.initializer[0]).copy()
    w1[0, 0] = np.nan
    model.graph.initializer[0].CopyFrom(numpy_helper.from_array(w1, "W1"))
    onnx.save(model, str(path))
    with pytest.raises(ModelContractError, match="output 'x_next' is not finite"):
        check_model(path)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("matrix", ["A", "B"])
def test_jacobian_graph_with_a_wrong_matrix_is_rejected(tmp_path, dtype, matrix):
    path = build_model(tmp_path / "toy.onnx", dtype)
    jac = build_jacobian(path, dtype, **{f"{matrix.lower()}_scale": 1.1})
    with pytest.raises(ModelContractError) as exc:
        check_model(path)
    msg = str(exc.value)
    assert msg.startswith(f"{jac}: ")
    assert f"'{matrix}' (d x_next / d {'x' if matrix == 'A' else 'u'}) must match central finite differences " \
           f"of toy.onnx" in msg


def test_jacobian_graph_with_wrong_x_next_is_rejected(tmp_path):
    path = build_model(tmp_path / "toy.onnx")
    jac = build_jacobian(path)
    model = onnx.load(str(jac))
    w2s = numpy_helper.to_array(model.graph.initializer[1]).copy()
    model.graph.initializer[1].CopyFrom(numpy_helper.from_array(w2s * (1 + 1e-6), "W2s"))
    onnx.save(model, str(jac))
    with pytest.raises(ModelContractError, match=r"toy\.jac\.onnx: derivative-graph output 'x_next' must equal "
                                                 r"the output of toy\.onnx"):
        check_model(path)


def test_jacobian_graph_with_wrong_outputs_is_rejected(tmp_path):
    path = build_model(tmp_path / "toy.onnx")
    build_model(jacobian_path(path))  # a plain model where the derivative graph should be
    with pytest.raises(ModelContractError, match=r"toy\.jac\.onnx: graph outputs must be exactly "
                                                 r"\['x_next', 'A', 'B'\]; found \['x_next'\]"):
        check_model(path)


# --------------------------------------------------------------------------- command line

def test_cli_valid_model(valid, tmp_path, capsys):
    js = tmp_path / "out" / "info.json"
    # Valid, but the toy network has no LQR about its hover trim, so no controller flies it: exit 1, saying why.
    assert main(["check-model", str(valid), "--json", str(js)]) == 1
    cap = capsys.readouterr()
    out = cap.out
    assert cap.err.startswith(f"pinnmpc check-model: no controller can fly {valid}: no LQR about the model's hover trim")
    assert "valid" in out and "architecture    toy" in out and "float64" in out and "toy.jac.onnx" in out
    assert "one_step_rmse" in out
    d = json.loads(js.read_text())
    assert d["architecture"] == "toy" and d["theta"]["m"] == QuadParams().m and d["jacobian"].endswith(".jac.onnx")


def test_cli_broken_model_is_a_one_line_error(tmp_path, capsys):
    path = build_model(tmp_path / "bad.onnx", batch=1)
    assert main(["check-model", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pinnmpc check-model: error: {path}: ")
    assert "batch dimension must be dynamic" in err and "Traceback" not in err
    assert err.count("\n") == 1


def test_cli_missing_file(tmp_path, capsys):
    assert main(["check-model", str(tmp_path / "none.onnx")]) == 2
    err = capsys.readouterr().err
    assert "model file not found" in err and "Traceback" not in err


def test_works_without_torch_and_cli_import_stays_light(valid):
    code = (
        "import sys; sys.modules['torch'] = None\n"
        "import scenarios.cli\n"
        "assert 'onnx' not in sys.modules and 'onnxruntime' not in sys.modules, 'heavy import at CLI load'\n"
        "import mpc.prediction.contract, mpc.cli\n"
        "info = mpc.prediction.contract.check_model(sys.argv[1])\n"
        "assert info.jacobian is not None\n"
        "assert sys.modules['torch'] is None\n"
    )
    r = subprocess.run([sys.executable, "-c", code, str(valid)], cwd=REPO, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr


# --------------------------------------------------------------------------- command levels

CTBR_INPUTS = ["T", "p_cmd", "q_cmd", "r_cmd"]
CTATT_INPUTS = ["T", "phi_cmd", "theta_cmd", "r_cmd"]


@pytest.mark.parametrize("level, names", [("ctbr", CTBR_INPUTS), ("ctatt", CTATT_INPUTS)])
def test_a_model_states_its_command_level_and_it_round_trips(tmp_path, level, names):
    from mpc.prediction.models import OnnxModel

    path = build_model(tmp_path / f"{level}.onnx", meta=_metadata(level=level, input_names=json.dumps(names)))
    info = check_model(path)
    assert info.level == level and info.to_dict()["level"] == level
    assert OnnxModel(path).level == level


def test_a_model_without_a_level_is_at_the_wrench_level(tmp_path):
    path = build_model(tmp_path / "plain.onnx", meta=_metadata(level=None))
    assert check_model(path).level == "wrench"
    assert check_model(REPO / "models" / "proposed.onnx").level == "wrench"       # the shipped files name none


@pytest.mark.parametrize("meta, message", [
    (dict(level="rates"), "metadata 'level' must be one of ['wrench', 'ctbr', 'ctatt']; found 'rates'"),
    (dict(level="ctbr"), "metadata 'input_names' must be ['T', 'p_cmd', 'q_cmd', 'r_cmd'] (the inputs of level "
                         "'ctbr'); found ['T', 'tau_x', 'tau_y', 'tau_z']"),
    (dict(input_names=json.dumps(CTATT_INPUTS)), "metadata 'input_names' must be ['T', 'tau_x', 'tau_y', 'tau_z']; "
                                                 "found ['T', 'phi_cmd', 'theta_cmd', 'r_cmd']"),
])
def test_a_level_and_input_names_that_disagree_are_refused(tmp_path, meta, message):
    path = build_model(tmp_path / "m.onnx", meta=_metadata(**meta))
    with pytest.raises(ModelContractError) as e:
        check_model(path)
    assert message in str(e.value)


def test_a_model_at_another_level_is_judged_with_that_level_s_inputs(tmp_path):
    from mpc.controllers.readiness import readiness
    from mpc.prediction.models import OnnxModel
    from mpc.prediction.spec import VehicleSpec

    # A wrench model's graph declared at ctbr: its "rates" move the body as torques would, a million times too
    # little for a rate command of 1 rad/s. Readiness now judges it as any model (by its LQR), not by its level.
    path = build_model(tmp_path / "ctbr.onnx", meta=_metadata(level="ctbr", input_names=json.dumps(CTBR_INPUTS)))
    ready = readiness(OnnxModel(path))
    assert len(ready) == 4 and all("level" not in r.reason for r in ready.values())
    # The controllers bound and weigh a ctbr input's rates by the vehicle's largest rate command and 1 rad/s.
    inputs = VehicleSpec().inputs("ctbr")
    assert np.allclose(inputs.matrix[1:, 1:], np.eye(3) / VehicleSpec().max_rate) and np.allclose(inputs.scale[1:], 1)
    assert np.allclose(inputs.project([1.0, 20.0, -20.0, 0.5]), [1.0, 10.0, -10.0, 0.5])


def test_check_model_refuses_a_level_the_model_does_not_declare(tmp_path, valid, capsys):
    js = tmp_path / "info.json"
    assert main(["check-model", str(valid), "--level", "ctbr", "--json", str(js)]) == 2
    err = capsys.readouterr().err
    assert "metadata 'level'" in err and "--level ctbr" in err and err.count("\n") == 1 and "Traceback" not in err
    assert not js.exists()
    assert main(["check-model", str(REPO / "models" / "baseline.onnx"), "--level", "wrench"]) == 0
    assert "level           wrench (u = T, tau_x, tau_y, tau_z)" in capsys.readouterr().out


def test_fly_refuses_a_model_at_another_level_in_one_line(tmp_path, capsys):
    path = build_model(tmp_path / "ctbr.onnx", meta=_metadata(level="ctbr", input_names=json.dumps(CTBR_INPUTS)))
    js = tmp_path / "r.json"
    assert main(["fly", "--scenario", "hover", "--controller", "lqr", "--model", str(path), "--json", str(js)]) == 2
    err = capsys.readouterr().err
    assert "'ctbr' level (metadata 'level')" in err and "--level ctbr" in err and err.count("\n") == 1
    assert not js.exists()
