"""Bring your own model: the minimal contract, derivatives by central differences, check-model and fly agree.

The linear hover model of ``docs/your-model.md`` is built by running that page's own code (numpy and
onnx only). Other files are built here with onnx.helper, each with one property of interest.
"""

import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from mpc.prediction.contract import _envelope_batch, check_model, jacobian_path
from mpc.errors import ModelContractError
from mpc.prediction.models import DERIVATIVE_PATHS, OnnxModel
from mpc.controllers.readiness import CONTROLLERS, readiness
from scenarios.cli import main

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "your-model.md"
MODELS = REPO / "models"
SHIPPED = ("baseline", "baseline_aggressive", "fourier", "modular", "proposed", "proposed_aggressive")
TOL = {
    "linear_vs_oracle": 1e-6,     # the page's ZOH hover model vs the simulator's hover linearization (abs, per entry)
    "differences": 1e-6,          # central differences vs the derivative graph (relative Frobenius, float64 models)
    "rmse_ratio": 0.02,           # derivative-less model's closed-loop RMSE vs with its graph (relative)
    "doc_model_settled_m": 0.02,  # the page's trained model at hover (the page quotes 8.5 mm)
}
#: Threshold beyond which the faulty derivative graph of the test is wrong, rad (pitch).
FAULT_BEYOND_RAD = 0.3


# ---- the page's model, and variants of it ---------------------------------------------------------
def _doc_code() -> str:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)[0]


@pytest.fixture(scope="module")
def linear(tmp_path_factory) -> Path:
    """``linear.onnx`` written by the code of docs/your-model.md, run as a user would."""
    d = tmp_path_factory.mktemp("doc")
    cwd = os.getcwd()
    os.chdir(d)
    try:
        exec(compile(_doc_code(), str(DOC), "exec"), {"__name__": "your_model"})   # noqa: S102 - our own docs
    finally:
        os.chdir(cwd)
    return d / "linear.onnx"


def _linear_matrices(yaw_torque=True, rates_held=False):
    dt, g, m = 0.01, 9.81, 0.068
    J = np.array([6.86e-5, 9.20e-5, 1.366e-4])
    M = np.zeros((17, 17))
    M[0:3, 9:12] = np.eye(3)
    M[3:6, 6:9] = np.eye(3)
    M[9, 4], M[10, 3] = -g, g
    M[6:9, 13:16] = np.diag(1.0 / J)
    if not yaw_torque:
        M[8, 15] = 0.0
    if rates_held:                      # no torque reaches the body rates: they hold whatever the inputs
        M[6:9, 13:16] = 0.0
    M[11, 12], M[11, 16] = -1.0 / m, g
    E = sum(np.linalg.matrix_power(M * dt, k) / math.factorial(k) for k in range(8))
    return E[:12, :12], E[:12, 12:16], E[:12, 16]


def build_linear(path, *, dtype=np.float64, dt="0.01", nan=False, nx=12, yaw_torque=True, rates_held=False,
                 meta=None) -> Path:
    """The page's model with one change: dtype, dt, a NaN output, the state width, no yaw torque, or no torque at
    all on the body rates (``rates_held``)."""
    Ad, Bd, c = _linear_matrices(yaw_torque, rates_held)
    et = helper.np_dtype_to_tensor_dtype(np.dtype(dtype))
    nodes = [helper.make_node("MatMul", ["x", "AdT"], ["xa"]), helper.make_node("MatMul", ["u", "BdT"], ["ub"]),
             helper.make_node("Add", ["xa", "ub"], ["s"])]
    inits = [numpy_helper.from_array(Ad[:nx, :nx].T.astype(dtype).copy() if nx != 12 else Ad.T.astype(dtype).copy(),
                                     "AdT"),
             numpy_helper.from_array(Bd.T.astype(dtype)[:, :nx].copy(), "BdT"),
             numpy_helper.from_array(c.astype(dtype)[:nx].copy(), "c")]
    if nan:
        inits.append(numpy_helper.from_array(np.array(-1.0, dtype=dtype), "minus_one"))
        nodes += [helper.make_node("Sqrt", ["minus_one"], ["nan"]), helper.make_node("Add", ["s", "nan"], ["s2"]),
                  helper.make_node("Add", ["s2", "c"], ["x_next"])]
    else:
        nodes.append(helper.make_node("Add", ["s", "c"], ["x_next"]))
    graph = helper.make_graph(nodes, "linear", [helper.make_tensor_value_info("x", et, ["batch", nx]),
                                                helper.make_tensor_value_info("u", et, ["batch", 4])],
                              [helper.make_tensor_value_info("x_next", et, ["batch", nx])], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    helper.set_model_props(model, {"dt": dt} if meta is None else meta)
    onnx.save(model, str(path))
    return Path(path)


def build_faulty_jacobian(model_path, beyond_rad: float) -> Path:
    """A derivative graph of the linear model that is exact until |theta| exceeds ``beyond_rad``, then adds 0.5 to
    d vx_next / d theta."""
    Ad, Bd, _ = _linear_matrices()
    D = np.zeros((12, 12))
    D[9, 4] = 0.5
    f = TensorProto.DOUBLE
    inits = [numpy_helper.from_array(a, n) for a, n in ((Ad.T.copy(), "AdT"), (Bd.T.copy(), "BdT"),
                                                         (_linear_matrices()[2], "c"), (Ad, "Ad"), (Bd, "Bd"),
                                                         (D, "D"), (np.zeros((12, 4)), "Z"),
                                                         (np.array(beyond_rad), "limit"))]
    inits += [numpy_helper.from_array(np.array(v, dtype=np.int64), n) for v, n in
              (([4], "i4"), ([5], "i5"), ([1], "ax1"), ([2], "ax2"))]
    nodes = [helper.make_node("MatMul", ["x", "AdT"], ["xa"]), helper.make_node("MatMul", ["u", "BdT"], ["ub"]),
             helper.make_node("Add", ["xa", "ub"], ["s"]), helper.make_node("Add", ["s", "c"], ["x_next"]),
             helper.make_node("Slice", ["x", "i4", "i5", "ax1"], ["th"]),            # (batch, 1)
             helper.make_node("Abs", ["th"], ["ath"]),
             helper.make_node("Greater", ["ath", "limit"], ["far"]),
             helper.make_node("Cast", ["far"], ["farf"], to=f),
             helper.make_node("Unsqueeze", ["farf", "ax2"], ["mask"]),                # (batch, 1, 1)
             helper.make_node("Mul", ["mask", "D"], ["dA"]), helper.make_node("Add", ["Ad", "dA"], ["A"]),
             helper.make_node("Mul", ["mask", "Z"], ["dB"]), helper.make_node("Add", ["Bd", "dB"], ["B"])]
    graph = helper.make_graph(
        nodes, "linear_jac",
        [helper.make_tensor_value_info("x", f, ["batch", 12]), helper.make_tensor_value_info("u", f, ["batch", 4])],
        [helper.make_tensor_value_info("x_next", f, ["batch", 12]),
         helper.make_tensor_value_info("A", f, ["batch", 12, 12]), helper.make_tensor_value_info("B", f, ["batch", 12, 4])],
        initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    path = jacobian_path(model_path)
    onnx.save(model, str(path))
    return path


def _fly_fields(out: str) -> dict:
    return {m.group(1): m.group(2).strip() for m in re.finditer(r"^(\w+)\s{2,}(.*)$", out, re.M)}


# ---- the page's model ---------------------------------------------------------------------------------
def test_the_pages_linear_model_passes_the_minimal_contract_and_is_the_hover_linearization(linear):
    from mpc.controllers.lqr import hover_linearization

    info = check_model(linear)
    assert info.theta is None and info.jacobian is None and info.architecture == "linear"
    assert set(info.metadata) == {"dt"}
    model = OnnxModel(linear)
    assert model.derivatives == DERIVATIVE_PATHS[1]
    A0, B0 = hover_linearization()          # the simulator's own hover linearization
    A, B = hover_linearization(model)
    assert np.max(np.abs(A - A0)) < TOL["linear_vs_oracle"] and np.max(np.abs(B - B0)) < TOL["linear_vs_oracle"]


def test_the_pages_commands_check_and_fly_the_linear_model(linear, capsys):
    assert main(["check-model", str(linear)]) == 0
    out = capsys.readouterr().out
    for c in CONTROLLERS:
        assert re.search(rf"^\s+{c}\s+flies: derivatives by central differences", out, re.M), out
    for scenario in ("hover", "figure8-slow"):
        assert main(["fly", "--model", str(linear), "--controller", "ltv", "--scenario", scenario]) == 0
        f = _fly_fields(capsys.readouterr().out)
        assert f["crashed"] == "False" and "error" not in f, f


# ---- check-model and fly agree ------------------------------------------------------------------------
def _file_set(d: Path) -> dict[str, Path]:
    shutil.copy(MODELS / "baseline.onnx", d / "valid.onnx")
    shutil.copy(MODELS / "baseline.jac.onnx", d / "valid.jac.onnx")
    shutil.copy(MODELS / "baseline.onnx", d / "no_derivative_graph.onnx")
    return {"valid": d / "valid.onnx", "no_derivative_graph": d / "no_derivative_graph.onnx",
            "float32": build_linear(d / "float32.onnx", dtype=np.float32),
            "wrong_dt": build_linear(d / "wrong_dt.onnx", dt="0.02"),
            "nan": build_linear(d / "nan.onnx", nan=True),
            "wrong_shape": build_linear(d / "wrong_shape.onnx", nx=10),
            "no_yaw_torque": build_linear(d / "no_yaw_torque.onnx", yaw_torque=False),
            "rates_held": build_linear(d / "rates_held.onnx", rates_held=True)}


#: What check-model must say of each file of the set: (exit code, controllers that fly, words of the defect). A
#: valid file that no controller flies exits 1; a file that is not valid, 2.
EXPECTED = {"valid": (0, CONTROLLERS, None), "no_derivative_graph": (0, CONTROLLERS, None),
            "float32": (0, CONTROLLERS, None), "wrong_dt": (2, (), "'dt' must equal"),
            "nan": (2, (), "not finite"), "wrong_shape": (2, (), "must have shape"),
            "no_yaw_torque": (1, (), "no LQR"), "rates_held": (1, (), "no input changes the body rates")}


def test_check_model_and_fly_agree_on_every_file(tmp_path, capsys):
    from scenarios.closed_loop.library import get_scenario
    from mpc.controllers.factory import make_controller

    files = _file_set(tmp_path)
    assert set(files) == set(EXPECTED)
    sc = get_scenario("hover")
    for name, path in files.items():
        rc, flying, words = EXPECTED[name]
        assert main(["check-model", str(path)]) == rc, name
        cap = capsys.readouterr()
        said = {c: bool(re.search(rf"^\s+{c}\s+flies:", cap.out, re.M)) for c in CONTROLLERS}
        assert {c for c, v in said.items() if v} == set(flying), (name, cap.out)
        if words:
            assert words in (cap.err if rc else cap.out), (name, cap)
        for c in CONTROLLERS:
            if c in flying:
                # what fly does before the first period: load, build, plan, one call
                from mpc.prediction.models import load_model
                model = load_model(str(path))
                ctrl = make_controller(c, model, sc.reference())
                ctrl.prepare(0.5, x0=np.array(sc.x0, dtype=float))
                u, _ = ctrl(np.array(sc.x0, dtype=float), 0.0)
                assert np.all(np.isfinite(u)), (name, c)
            else:
                assert main(["fly", "--model", str(path), "--controller", c, "--scenario", "hover"]) == 2, (name, c)
                err = capsys.readouterr().err
                assert words in err, (name, c, err)


def test_check_model_exits_1_when_no_controller_can_fly_a_valid_file_and_says_why(linear, tmp_path, capsys):
    """A valid file whose body rates no input changes: every controller's line says it cannot fly and why, the
    JSON is written, and the command ends with exit 1 and one line on stderr naming the file and the reason. The
    page's own model, which they all fly, exits 0 with nothing on stderr."""
    import json

    held = build_linear(tmp_path / "rates_held.onnx", rates_held=True)
    js = tmp_path / "held.json"
    assert main(["check-model", str(held), "--json", str(js)]) == 1
    cap = capsys.readouterr()
    assert f"{held}: valid" in cap.out
    for c in CONTROLLERS:
        assert re.search(rf"^\s+{c}\s+cannot fly: no LQR .*no input changes the body rates", cap.out, re.M), cap.out
    assert cap.err.count("\n") == 1 and cap.err.startswith(f"pinnmpc check-model: no controller can fly {held}: ")
    assert "no input changes the body rates" in cap.err
    assert not any(v["flies"] for v in json.loads(js.read_text())["controllers"].values())
    assert main(["check-model", str(linear)]) == 0
    assert capsys.readouterr().err == ""
    with pytest.raises(SystemExit):                         # and its --help says so
        main(["check-model", "--help"])
    helptext = " ".join(capsys.readouterr().out.split())
    assert "exit 1 when it is valid but no controller can fly it" in helptext and "exit 2" in helptext


# ---- derivatives without a derivative graph -----------------------------------------------------------
@pytest.mark.parametrize("name", SHIPPED)
def test_central_differences_agree_with_the_derivative_graph(name, tmp_path):
    shutil.copy(MODELS / f"{name}.onnx", tmp_path / f"{name}.onnx")
    bare, full = OnnxModel(tmp_path / f"{name}.onnx"), OnnxModel(MODELS / f"{name}.onnx")
    assert (bare.derivatives, full.derivatives) == (DERIVATIVE_PATHS[1], DERIVATIVE_PATHS[0])
    x, u = _envelope_batch(30, np.float64, seed=5)
    xa, A, B = bare.linearize(x, u)
    xb, A0, B0 = full.linearize(x, u)
    assert np.array_equal(xa, bare.step(x, u))
    J, J0 = np.concatenate([A, B], axis=2), np.concatenate([A0, B0], axis=2)
    rel = np.linalg.norm(J - J0, axis=(1, 2)) / np.linalg.norm(J0, axis=(1, 2))
    assert rel.max() < TOL["differences"], rel.max()


def _rmse_pair(name, controller, scenario, tmp_path):
    from scenarios.closed_loop.runner import RunSpec, fly

    shutil.copy(MODELS / f"{name}.onnx", tmp_path / f"{name}.onnx")
    bare = fly(RunSpec(scenario, controller, str(tmp_path / f"{name}.onnx")))[0]
    full = fly(RunSpec(scenario, controller, str(MODELS / f"{name}.onnx")))[0]
    assert not bare["error"] and not full["error"]
    assert bare["crashed"] == full["crashed"]
    return bare["rmse_position_m"], full["rmse_position_m"]


#: One shipped model per architecture (the aggressive-regime models are the same graphs with other weights; their
#: differences are held to the graph's derivatives above, open loop).
ARCHITECTURES = ("baseline", "fourier", "modular", "proposed")
#: Flights per architecture: the Proposed model with every controller that linearizes on hover and figure8-slow; the
#: others (the same finite differences, of other graphs) with the SQP, which uses them most, on figure8-slow.
DIFFERENCE_FLIGHTS = {name: [("sqp", "figure8-slow")] for name in ARCHITECTURES}
DIFFERENCE_FLIGHTS["proposed"] = [(c, s) for c in ("lqr", "ltv", "sqp") for s in ("hover", "figure8-slow")]


@pytest.mark.slow
@pytest.mark.parametrize("name", ARCHITECTURES)
def test_every_derivative_less_architecture_flies_like_with_its_graph(name, tmp_path):
    """A model file without its derivative graph (finite differences) flies as with it: a shipped model of every
    architecture (:data:`DIFFERENCE_FLIGHTS`)."""
    for controller, scenario in DIFFERENCE_FLIGHTS[name]:
        a, b = _rmse_pair(name, controller, scenario, tmp_path)
        assert abs(a - b) <= TOL["rmse_ratio"] * b, (name, controller, scenario, a, b)


# ---- the derivative check covers the flight envelope ----------------------------------------------------
def test_a_derivative_graph_wrong_only_beyond_the_hover_probes_is_caught(tmp_path):
    path = build_linear(tmp_path / "lin.onnx")
    build_faulty_jacobian(path, FAULT_BEYOND_RAD)
    with pytest.raises(ModelContractError, match="'A'.*central finite differences"):
        check_model(path)
    build_faulty_jacobian(path, 2.0)        # wrong only beyond every probe: nothing to see
    assert check_model(path).jacobian is not None
    # and the same fault within the hover probes is caught there too
    build_faulty_jacobian(path, 0.0)
    with pytest.raises(ModelContractError, match="'A'"):
        check_model(path)


def test_readiness_of_the_oracle_and_a_bad_controller_name():
    from mpc.errors import ConfigurationError
    from mpc.prediction.models import AnalyticModel
    from mpc.controllers.readiness import require

    r = readiness(AnalyticModel())
    assert all(v.flies and v.derivatives.startswith("exact") for v in r.values())
    with pytest.raises(ConfigurationError, match="controller must be one of"):
        require(AnalyticModel(), "pid")


def test_the_pages_pytorch_export_gives_a_model_every_controller_takes(tmp_path, monkeypatch):
    torch = pytest.importorskip("torch")
    code = re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)[1]
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(16, 32), torch.nn.Tanh(), torch.nn.Linear(32, 12))
    with torch.no_grad():
        net[2].weight.mul_(1e-3)         # a small correction to "x_next = x": a smooth toy network
    monkeypatch.chdir(tmp_path)
    exec(compile(code, str(DOC), "exec"), {"my_net": net, "__name__": "your_model"})   # noqa: S102 - our own docs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.onnx"]      # one self-contained file
    model = OnnxModel(tmp_path / "mine.onnx")
    assert model.info.metadata == {"dt": "0.01"} or "dt" in model.info.metadata
    x, u = _envelope_batch(4, np.float64)
    with torch.no_grad():
        ref = (torch.as_tensor(x) + net.double()(torch.cat([torch.as_tensor(x), torch.as_tensor(u)], -1))).numpy()
    assert np.allclose(model.step(x, u), ref, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_the_pages_path_from_data_to_a_flown_model(tmp_path, monkeypatch, capsys):
    """The page's section "From data to a flown model", run as written: pinnmpc data, the training code, check-model
    and fly. The model it trains hovers (the page quotes its settled error)."""
    pytest.importorskip("torch")
    text = DOC.read_text(encoding="utf-8")
    section = text.split("## From data to a flown model")[1].split("\n## ")[0]
    commands = [line for block in re.findall(r"```bash\n(.*?)```", section, re.S) for line in block.splitlines()
                if line.startswith("pinnmpc ")]
    assert [c.split()[1] for c in commands] == ["data", "check-model", "fly", "study"]
    monkeypatch.chdir(tmp_path)
    assert main(commands[0].split()[1:]) == 0
    with np.load(tmp_path / "mydata.npz") as z:                # the format table of the page
        n, k = z["x"].shape[:2]
        shapes = {"x": (n, k, 12), "u": (n, k, 4), "x_next": (n, k, 12), "wrench": (n, k, 4),
                  "rotor_speed": (n, k, 4), "saturated": (n, k, 4), "split": (n,), "meta": ()}
        assert {a: z[a].shape for a in z.files} == shapes
        assert z["saturated"].dtype == bool and z["split"].dtype == np.int8 and set(z["split"]) == {0, 1, 2}
        assert np.array_equal(z["x_next"][:, :-1], z["x"][:, 1:])
    code = re.findall(r"```python\n(.*?)```", section, re.S)[0]
    exec(compile(code, str(DOC), "exec"), {"__name__": "your_model"})    # noqa: S102 - our own docs
    capsys.readouterr()
    assert main(commands[1].split()[1:]) == 0
    assert "learned.onnx: valid" in capsys.readouterr().out
    assert main(commands[2].split()[1:]) == 0
    out = capsys.readouterr().out
    settled = float(out.split("settled_error_m")[1].split()[0])
    assert "crashed               False" in out and settled < TOL["doc_model_settled_m"]


def test_the_zoo_refuses_what_check_model_refuses(linear, tmp_path):
    """A trained zoo member that no controller can fly leaves the manifest for refused.json with check-model's
    reason, and its file is removed; one they all fly stays."""
    import json
    import shutil

    from mpc.prediction.models import load_model
    from mpc.controllers.readiness import readiness
    from pinn.zoo import sort_refused

    shutil.copyfile(linear, tmp_path / "flies.onnx")
    build_linear(tmp_path / "held.onnx", rates_held=True)
    entries = {n: {"command": "test", "files": {"onnx": f"{n}.onnx"}} for n in ("flies", "held")}
    (tmp_path / "manifest.json").write_text(json.dumps(entries))
    reason = readiness(load_model(str(tmp_path / "held.onnx")))["lqr"].reason
    refused = sort_refused(tmp_path, ["flies", "held"])
    assert list(refused) == ["held"] and refused["held"]["reason"] == reason
    assert "no input changes the body rates" in reason
    assert json.loads((tmp_path / "refused.json").read_text())["held"]["reason"] == reason
    assert list(json.loads((tmp_path / "manifest.json").read_text())) == ["flies"]
    assert not (tmp_path / "held.onnx").exists() and (tmp_path / "flies.onnx").exists()
