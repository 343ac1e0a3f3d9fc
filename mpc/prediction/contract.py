"""The ONNX model contract and its checker.

A model file maps one control period of the quadrotor::

    inputs   x  float[B, 12 + E]   state, order sim.params.STATE_NAMES (NED, ZYX Euler), then E extra states
             u  float[B, 4]        wrench command (T, tau_x, tau_y, tau_z), N and N m
    output   x_next float[B, 12 + E]   state after DT = 0.01 s

The ``E`` extra states (none unless declared) are the model's own: actuator
states such as rotor speeds or a lagging wrench, or a window of past states
and inputs. A model that has them names them in the metadata key
``extra_states`` (a JSON list of E names); the controllers carry them from
period to period (:mod:`mpc.prediction.extended`). Their optional ``extra_scale`` (a
JSON list of E positive numbers, in their units) sizes steps and defects.

``B`` is a dynamic batch dimension; ``float`` is float32 or float64, the same
for every tensor. ``metadata_props`` must hold ``dt`` (the only required key);
the keys of :data:`OPTIONAL_METADATA` are used where present (strings; JSON
where the value is structured): ``theta`` feeds the vehicle spec, the training
provenance is shown in reports.

Exact derivatives are optionally shipped beside the model as a *derivative
graph* ``<stem>.jac.onnx`` (see :func:`jacobian_path`) with the same inputs and
the outputs ``x_next`` [B, 12], ``A`` = d x_next / d x [B, 12, 12] and
``B`` = d x_next / d u [B, 12, 4] (12 + E wherever the state appears). Without one, the controllers take A and B
from batched central differences of the model (:func:`central_differences`).

:func:`check_model` validates a file against all of this, runs it with
onnxruntime, and raises :class:`mpc.errors.ModelContractError` (a
``ValueError``) naming the file and the defect. Nothing here imports torch;
``onnx`` and ``onnxruntime`` are imported on first use.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim.levels import DEFAULT_LEVEL, LEVEL_INPUTS, LEVELS
from sim.params import DT, INPUT_NAMES, STATE_NAMES, THETA_NAMES, QuadParams

from ..errors import ModelContractError

#: Version written to the ``pinnmpc.contract`` metadata key: 3 allows extra states; like 2, it requires only ``dt``.
CONTRACT_VERSION = "3"
#: Versions this code reads (1: every key of OPTIONAL_METADATA was required; the shipped models are version 1;
#: 2: only ``dt`` required; 3: extra states). A file of any of them is read by the same rules: a version-1 or -2
#: file simply has no extra states.
READABLE_VERSIONS = ("1", "2", "3")

#: Metadata every model must carry: ``dt`` (float, s; equal to ``sim.params.DT``).
REQUIRED_METADATA = ("dt",)
#: Metadata used where present (all values are strings), each validated when given:
#: ``pinnmpc.contract`` (one of READABLE_VERSIONS), ``architecture`` (name),
#: ``state_names`` / ``input_names`` (JSON lists, must equal the conventions),
#: ``theta`` (JSON object over THETA_NAMES, SI units: the vehicle spec's m, J, kt, kq),
#: ``training_config`` (JSON object), ``config_hash`` (:func:`config_hash` of it),
#: ``dataset_seed`` (int), ``code_version`` (free text), ``test_metrics`` (JSON object),
#: ``extra_states`` (JSON list of the extra states' names), ``extra_scale`` (JSON list of their scales, > 0),
#: ``level`` (the command level of the input ``u``, one of :data:`sim.levels.LEVELS`; ``wrench`` when absent: then
#: ``input_names``, where given, must be that level's, :data:`sim.levels.LEVEL_INPUTS`).
OPTIONAL_METADATA = ("pinnmpc.contract", "architecture", "state_names", "input_names", "theta", "training_config",
                     "config_hash", "dataset_seed", "code_version", "test_metrics", "extra_states", "extra_scale",
                     "level")

NX = len(STATE_NAMES)
NU = len(INPUT_NAMES)

#: Tolerances of the checks: |dt - DT|; derivative-graph x_next vs model
#: (relative, norm-wise per sample); A, B vs central finite differences of the
#: model (relative to the Frobenius norm of the finite-difference matrix, per
#: sample, plus the differences' own rounding noise eps |x_next| / step per
#: column, which only matters for float32).
DT_TOL = 1e-12
JAC_XNEXT_RTOL = {"float64": 1e-9, "float32": 1e-5}
JAC_FD_RTOL = 1e-3
#: Relative central-difference step per model dtype: the step of variable i is FD_STEP * max(|z_i|, FD_SCALE).
FD_STEP = {"float64": 1e-6, "float32": 1e-3}
#: Size below which a variable's step stops shrinking, in its own unit (m, rad, rad/s, m/s, N, N m, and the extra
#: states' own): 1 for all. A smaller torque scale (hover torques are about 1e-3 N m) makes a float32 model's
#: differences noisier than the quantity they measure (tested: a 10 % error of a float32 B then goes unseen);
#: float64 does not need it.
FD_SCALE = 1.0
#: Periods the checker holds a state and input to find a model's extra states at rest, and how still they must be
#: then (largest change in one more period, relative to max(|e|, 1)), per dtype.
SETTLE_PERIODS = 400
SETTLE_RTOL = {"float64": 1e-8, "float32": 1e-4}
#: Batch sizes of the test evaluations.
TEST_BATCH_SIZES = (1, 3)


@dataclass(frozen=True)
class ModelInfo:
    """What :func:`check_model` learned about a valid model file.

    Attributes
    ----------
    path : Path
        The model file.
    architecture : str
        Architecture name from the metadata (e.g. ``"baseline"``), else the file's stem.
    dt : float
        Period of one ``x -> x_next`` step, s (equals ``sim.params.DT``).
    dtype : numpy.dtype
        Element type of every tensor, float32 or float64.
    theta : dict[str, float] or None
        Identified parameters by name (THETA_NAMES order), SI units; None when not given.
    training_config : dict or None
        Training configuration as stored.
    config_hash : str or None
        sha256 hex of the canonical JSON of ``training_config``.
    dataset_seed : int or None
        Seed of the training dataset.
    code_version : str or None
        Version of the code that produced the file.
    test_metrics : dict or None
        Test-set metrics as stored.
    metadata : dict[str, str]
        Every ``metadata_props`` entry, raw strings.
    jacobian : Path or None
        The derivative graph beside the model when present (and valid).
    extra_states : tuple of str
        Names of the states beyond the 12 rigid-body ones (empty for most models).
    extra_scale : tuple of float or None
        Their declared scales, or None.
    level : str
        The command level of the input ``u`` (:data:`sim.levels.LEVELS`): ``wrench`` (thrust and body torques)
        unless the metadata ``level`` says ``ctbr`` (thrust and body rates) or ``ctatt`` (thrust, roll, pitch and
        yaw rate).
    """

    path: Path
    architecture: str
    dt: float
    dtype: np.dtype
    theta: dict | None
    training_config: dict | None
    config_hash: str | None
    dataset_seed: int | None
    code_version: str | None
    test_metrics: dict | None
    metadata: dict
    jacobian: Path | None
    extra_states: tuple = ()
    extra_scale: tuple | None = None
    level: str = DEFAULT_LEVEL

    @property
    def nx(self) -> int:
        """Length of the model's state: 12 plus its extra states."""
        return NX + len(self.extra_states)

    def to_dict(self) -> dict:
        """JSON-ready form: paths as strings, ``dtype`` as its name."""
        return {
            "path": str(self.path), "architecture": self.architecture, "dt": self.dt,
            "dtype": self.dtype.name, "theta": None if self.theta is None else dict(self.theta),
            "training_config": self.training_config,
            "config_hash": self.config_hash, "dataset_seed": self.dataset_seed,
            "code_version": self.code_version, "test_metrics": self.test_metrics,
            "metadata": dict(self.metadata), "jacobian": None if self.jacobian is None else str(self.jacobian),
            "extra_states": list(self.extra_states),
            "extra_scale": None if self.extra_scale is None else list(self.extra_scale), "level": self.level,
        }


def config_hash(config: dict) -> str:
    """sha256 hex digest of the canonical JSON of a training configuration.

    Parameters
    ----------
    config : dict
        JSON-serializable configuration.

    Returns
    -------
    str
        64 hex characters: ``sha256(json.dumps(config, sort_keys=True, separators=(",", ":")))``.
    """
    if not isinstance(config, Mapping):
        raise TypeError(f"config must be a dict; found {type(config).__name__}")
    try:
        text = json.dumps(config, sort_keys=True, separators=(",", ":"))
    except (TypeError, ValueError) as e:
        raise TypeError(f"config must be JSON-serializable; {e}") from e
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def model_files(folder) -> list[Path]:
    """The model files of a folder, sorted: every ``*.onnx`` but the derivative graphs ``*.jac.onnx``."""
    return sorted(p for p in Path(folder).glob("*.onnx") if not p.name.endswith(".jac.onnx"))


def jacobian_path(model_path) -> Path:
    """The derivative graph beside a model: ``models/baseline.onnx -> models/baseline.jac.onnx``."""
    p = Path(model_path)
    return p.with_name(p.stem + ".jac.onnx")


def open_session(path, threads: int = 1, graph: bytes | None = None):
    """An onnxruntime CPU session with ``threads`` intra-op and one inter-op thread.

    Parameters
    ----------
    path : str or Path
        ONNX file.
    threads : int
        Intra-op threads (>= 1). One thread keeps timings reproducible and
        leaves cores to parallel runs.
    graph : bytes, optional
        A serialized graph to load instead of the file (``path`` then only
        names it in errors).

    Returns
    -------
    onnxruntime.InferenceSession

    Raises
    ------
    ModelContractError
        If onnxruntime cannot load the file.
    """
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise ValueError(f"threads must be an integer >= 1; found {threads!r}")
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads)
    so.inter_op_num_threads = 1
    so.log_severity_level = 3  # errors only: warnings about unused initializers etc. are noise here
    source = str(path) if graph is None else graph
    try:
        return ort.InferenceSession(source, sess_options=so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own pybind exception types
        raise ModelContractError(f"{path}: onnxruntime cannot load the model ({_short(str(e), 300)})") from e


def single_precision(path) -> bytes:
    """The ONNX graph of ``path`` with every float64 tensor turned into float32, serialized.

    Initializers, ``Constant`` nodes, ``Cast(to=DOUBLE)`` and the declared
    types of inputs, outputs and intermediate values are converted; the
    graph's structure is unchanged. Used for the derivative graph of the
    QP-based controllers, whose Jacobians need about 7 significant digits
    (onnxruntime evaluates the float32 graph 1.5-2.3x faster on our machines).

    Raises
    ------
    ModelContractError
        If the file cannot be read or converted.
    """
    import onnx
    from onnx import TensorProto, numpy_helper

    double, single = TensorProto.DOUBLE, TensorProto.FLOAT

    def convert_tensor(t):
        if t.data_type == double:
            t.CopyFrom(numpy_helper.from_array(numpy_helper.to_array(t).astype(np.float32), t.name))

    def convert_graph(g):
        for t in g.initializer:
            convert_tensor(t)
        for v in (*g.input, *g.output, *g.value_info):
            if v.type.tensor_type.elem_type == double:
                v.type.tensor_type.elem_type = single
        for node in g.node:
            for a in node.attribute:
                if a.type == onnx.AttributeProto.TENSOR:
                    convert_tensor(a.t)
                elif a.type == onnx.AttributeProto.GRAPH:
                    convert_graph(a.g)
                elif node.op_type == "Cast" and a.name == "to" and a.i == double:
                    a.i = single

    try:
        model = onnx.load(str(path))
        convert_graph(model.graph)
        return model.SerializeToString()
    except Exception as e:  # onnx raises DecodeError, ValueError, ... for bad files
        raise ModelContractError(f"{path}: cannot convert the graph to float32 ({_short(str(e), 300)})") from e


def check_model(path) -> ModelInfo:
    """Validate an ONNX model file against the contract and return what it declares.

    Checks, in order: the file loads and passes ``onnx.checker``; inputs are
    exactly ``x`` [B, 12] and ``u`` [B, 4] with a dynamic batch dimension and
    one element type (float32 or float64); the only output is ``x_next``
    [B, 12] of that type; the metadata of :data:`REQUIRED_METADATA` is present
    and consistent (contract version, ``dt == DT``, state and input names,
    positive finite theta, config hash, where given); onnxruntime evaluates hover-like
    batches of size 1 and 3 to finite (B, 12) outputs. When the derivative
    graph :func:`jacobian_path` exists it is checked too: same inputs, outputs
    ``x_next``, ``A`` [B, 12, 12], ``B`` [B, 12, 4], ``x_next`` equal to the
    model's and ``A``, ``B`` equal to central finite differences of the model,
    on the hover-like batches and on :data:`ENVELOPE_SAMPLES` states across the
    flight envelope (:func:`_envelope_batch`: tilts up to 0.8 rad).

    Parameters
    ----------
    path : str or Path
        The ``.onnx`` model file.

    Returns
    -------
    ModelInfo

    Raises
    ------
    ModelContractError
        Naming the file (the model or its derivative graph) and the defect,
        with what was expected and what was found.
    """
    path = Path(path)
    model = _load(path)
    where = str(path)
    meta = _metadata(model, where)
    extra, extra_scale = _parse_extra_states(meta, where)
    nx = NX + len(extra)
    dtype = _check_io(model, where, {"x_next": (nx,)}, extra)
    fields = _parse_metadata(meta, where, path.stem)

    session = open_session(path)
    batches = []
    for b in TEST_BATCH_SIZES:
        x, u = _probe_batch(b, dtype)
        x = _with_extra_at_rest(session, x, u, extra, where, "hover-like")
        (x_next,) = _run(session, x, u, where, ["x_next"])
        _check_output(x_next, (b, nx), dtype, where, "x_next")
        batches.append((x, u, x_next))

    _check_envelope_finite(session, dtype, extra, where)
    jac = jacobian_path(path)
    if jac.exists():
        x, u = _envelope_batch(ENVELOPE_SAMPLES, dtype)
        try:
            x = _with_extra_at_rest(session, x, u, extra, where, "envelope")
            (x_next,) = _run(session, x, u, where, ["x_next"])
        except ModelContractError:         # a model that is not finite out there is checked where it is
            x_next = None
        if x_next is not None and np.all(np.isfinite(x_next)):
            batches.append((x, u, x_next))
        _check_jacobian(jac, path, session, dtype, batches, extra)
    else:
        jac = None
    return ModelInfo(path=path, dtype=dtype, metadata=meta, jacobian=jac, extra_states=extra,
                     extra_scale=extra_scale, **fields)


def declared_level(path) -> str:
    """The command level the model file ``path`` declares (metadata ``level``; ``wrench`` when absent), read without
    the contract's other checks (:func:`check_model` makes them; an unknown level is one of them).

    Raises
    ------
    ModelContractError
        The file is missing or not a readable ONNX file.
    """
    path = Path(path)
    return _metadata(_load(path), str(path)).get("level", DEFAULT_LEVEL)


def _with_extra_at_rest(session, x: np.ndarray, u: np.ndarray, extra: tuple, where: str, what: str) -> np.ndarray:
    """The test states ``x`` (b, 12) with the model's extra states at rest appended (b, 12 + E).

    The extra states start at zero and the model is stepped with each state
    and input held until they stop changing (:data:`SETTLE_PERIODS`,
    :data:`SETTLE_RTOL`): a lag settles at its command, a shift register fills
    with the held values. Extra states that do not settle are an error.
    """
    if not extra:
        return x
    ne = len(extra)
    dtype = x.dtype
    e = np.zeros((len(x), ne), dtype=dtype)
    tol = SETTLE_RTOL[dtype.name]
    change = np.inf
    for _ in range(SETTLE_PERIODS):
        (z,) = _run(session, np.hstack([x, e]), u, where, ["x_next"])
        e_new = np.asarray(z[:, NX:], dtype=dtype)
        if not np.all(np.isfinite(e_new)):
            raise ModelContractError(f"{where}: its extra states {list(extra)} are not finite on the {what} test "
                                     f"batch with the state and input held")
        change = float(np.max(np.abs(e_new.astype(float) - e.astype(float)) / np.maximum(np.abs(e_new), 1.0)))
        e = e_new
        if change <= tol:
            return np.hstack([x, e])
    raise ModelContractError(f"{where}: its extra states {list(extra)} do not settle with the state and input held "
                             f"on the {what} test batch (relative change {change:.2g} per period after "
                             f"{SETTLE_PERIODS} periods; at most {tol:g} expected); the controllers cannot plan "
                             f"with extra states that never come to rest")


# --------------------------------------------------------------------------- file and graph structure

def _short(text: str, limit: int = 80) -> str:
    text = str(text)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _load(path: Path):
    """Load and ``onnx.checker``-check one file; errors name the file."""
    import onnx

    if not path.exists():
        raise ModelContractError(f"{path}: model file not found")
    if not path.is_file():
        raise ModelContractError(f"{path}: expected an ONNX file; found a directory")
    try:
        model = onnx.load(str(path))
    except Exception as e:  # protobuf DecodeError, OSError, external-data errors
        raise ModelContractError(f"{path}: not a readable ONNX file ({type(e).__name__}: {_short(e, 200)})") from e
    try:
        onnx.checker.check_model(model)
    except Exception as e:  # onnx.checker.ValidationError and friends
        raise ModelContractError(f"{path}: fails onnx.checker ({_short(e, 300)})") from e
    return model


def _type_name(elem_type: int) -> str:
    import onnx

    if elem_type == onnx.TensorProto.FLOAT:
        return "float32"
    if elem_type == onnx.TensorProto.DOUBLE:
        return "float64"
    if elem_type == onnx.TensorProto.UNDEFINED:
        return "undefined"
    try:
        return onnx.TensorProto.DataType.Name(elem_type).lower()
    except ValueError:
        return f"unknown type {elem_type}"


def _dim_str(dim) -> str:
    if dim.HasField("dim_value"):
        return str(dim.dim_value)
    if dim.HasField("dim_param"):
        return dim.dim_param
    return "?"


def _tensor_type(vi, where: str, role: str):
    kind = vi.type.WhichOneof("value")
    if kind != "tensor_type":
        raise ModelContractError(f"{where}: {role} {vi.name!r} must be a tensor; found {kind or 'no type'}")
    return vi.type.tensor_type


def _check_shape(vi, where: str, role: str, dims: tuple[int, ...]) -> None:
    """``vi`` must have shape [batch, *dims] with a dynamic batch dimension."""
    tt = _tensor_type(vi, where, role)
    expected = "[batch, " + ", ".join(map(str, dims)) + "]"
    if not tt.HasField("shape"):
        raise ModelContractError(f"{where}: {role} {vi.name!r} must have rank {1 + len(dims)} "
                                 f"(shape {expected}); found no declared shape")
    d = list(tt.shape.dim)
    found = "[" + ", ".join(_dim_str(k) for k in d) + "]"
    if len(d) != 1 + len(dims):
        raise ModelContractError(f"{where}: {role} {vi.name!r} must have rank {1 + len(dims)} "
                                 f"(shape {expected}); found rank {len(d)}, shape {found}")
    if d[0].HasField("dim_value"):
        raise ModelContractError(f"{where}: {role} {vi.name!r} batch dimension must be dynamic (a named or unset "
                                 f"first dimension, shape {expected}); found fixed size {d[0].dim_value}")
    for k, (dim, want) in enumerate(zip(d[1:], dims), start=1):
        if not dim.HasField("dim_value") or dim.dim_value != want:
            raise ModelContractError(f"{where}: {role} {vi.name!r} must have shape {expected}; found {found} "
                                     f"(dimension {k} is {_dim_str(dim)}, expected {want})")


def _elem_dtype(vi, where: str, role: str) -> np.dtype:
    import onnx

    et = _tensor_type(vi, where, role).elem_type
    if et == onnx.TensorProto.FLOAT:
        return np.dtype(np.float32)
    if et == onnx.TensorProto.DOUBLE:
        return np.dtype(np.float64)
    raise ModelContractError(f"{where}: {role} {vi.name!r} must have element type float32 or float64; "
                             f"found {_type_name(et)}")


def _check_io(model, where: str, outputs: dict, extra: tuple = ()) -> np.dtype:
    """Check inputs ``x``, ``u`` and the named outputs; return the common dtype.

    ``outputs`` maps each required output name to its trailing dimensions; ``extra`` names the declared extra
    states (the state is 12 + len(extra) long).
    """
    graph = model.graph
    initializers = {t.name for t in graph.initializer}
    inputs = [vi for vi in graph.input if vi.name not in initializers]  # IR < 4 lists initializers as inputs
    names = [vi.name for vi in inputs]
    if sorted(names) != ["u", "x"]:
        raise ModelContractError(f"{where}: graph inputs must be exactly ['x', 'u']; found {names}")
    by_name = {vi.name: vi for vi in inputs}
    _check_state_width(by_name["x"], where, "input", extra)
    _check_shape(by_name["x"], where, "input", (NX + len(extra),))
    _check_shape(by_name["u"], where, "input", (NU,))
    tx = _elem_dtype(by_name["x"], where, "input")
    tu = _elem_dtype(by_name["u"], where, "input")
    if tx != tu:
        raise ModelContractError(f"{where}: inputs 'x' and 'u' must have the same element type (float32 or "
                                 f"float64); found x {tx.name}, u {tu.name}")

    out_names = [vi.name for vi in graph.output]
    if sorted(out_names) != sorted(outputs):
        raise ModelContractError(f"{where}: graph outputs must be exactly {list(outputs)}; found {out_names}")
    for vi in graph.output:
        if vi.name == "x_next":
            _check_state_width(vi, where, "output", extra)
        _check_shape(vi, where, "output", outputs[vi.name])
        t = _elem_dtype(vi, where, "output")
        if t != tx:
            raise ModelContractError(f"{where}: output {vi.name!r} must have the element type of the inputs "
                                     f"({tx.name}); found {t.name}")
    return tx


def _check_state_width(vi, where: str, role: str, extra: tuple) -> None:
    """A state tensor whose width does not match the declared extra states: one line that says which is which."""
    tt = _tensor_type(vi, where, role)
    if not tt.HasField("shape") or len(tt.shape.dim) != 2 or not tt.shape.dim[1].HasField("dim_value"):
        return      # the shape check that follows names the defect
    width, want = tt.shape.dim[1].dim_value, NX + len(extra)
    if width == want:
        return
    if not extra:
        if width < NX:
            return  # the shape check that follows names the defect
        raise ModelContractError(f"{where}: {role} {vi.name!r} has {width} states, but the model declares no extra "
                                 f"states: a model with states beyond the 12 rigid-body ones must name them in "
                                 f"metadata 'extra_states' (a JSON list of {width - NX} names)")
    raise ModelContractError(f"{where}: {role} {vi.name!r} must have shape [batch, {want}] (12 rigid-body states "
                             f"and the {len(extra)} extra states of metadata 'extra_states'); found [batch, {width}]")


# --------------------------------------------------------------------------- metadata


def _parse_extra_states(meta: dict, where: str) -> tuple[tuple, tuple | None]:
    """``(extra_states, extra_scale)`` from the metadata, validated: names unique, non-empty, not the rigid body's;
    scales finite, > 0, one per name."""
    if "extra_states" not in meta:
        if "extra_scale" in meta:
            raise ModelContractError(f"{where}: metadata 'extra_scale' is given without the 'extra_states' it scales")
        return (), None
    names = _json(meta, "extra_states", where, list, "a JSON list of the extra states' names")
    if not names or not all(isinstance(n, str) and n.strip() for n in names):
        raise ModelContractError(f"{where}: metadata 'extra_states' must be a non-empty JSON list of non-empty names; "
                                 f"found {_short(meta['extra_states'])!r}")
    dup = sorted({n for n in names if names.count(n) > 1})
    clash = [n for n in names if n in STATE_NAMES]
    if dup or clash:
        raise ModelContractError(f"{where}: metadata 'extra_states' must name each extra state once, and none like a "
                                 f"rigid-body state {list(STATE_NAMES)}; found "
                                 + ", ".join(p for p in (f"repeated {dup}" if dup else "",
                                                         f"rigid-body names {clash}" if clash else "") if p))
    scale = None
    if "extra_scale" in meta:
        scale = _json(meta, "extra_scale", where, list, f"a JSON list of {len(names)} positive numbers")
        ok = len(scale) == len(names) and all(
            not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in scale)
        if not ok:
            raise ModelContractError(f"{where}: metadata 'extra_scale' must be a JSON list of {len(names)} finite "
                                     f"numbers > 0, one per extra state; found {_short(meta['extra_scale'])!r}")
        scale = tuple(float(v) for v in scale)
    return tuple(names), scale

def _metadata(model, where: str) -> dict:
    meta: dict[str, str] = {}
    for entry in model.metadata_props:
        if entry.key in meta:
            raise ModelContractError(f"{where}: metadata key {entry.key!r} must appear once; found it repeated")
        meta[entry.key] = entry.value
    return meta


def _json(meta: dict, key: str, where: str, kind: type, what: str):
    value = meta[key]
    try:
        obj = json.loads(value)
    except ValueError as e:
        raise ModelContractError(f"{where}: metadata {key!r} must be {what}; found invalid JSON "
                                 f"{_short(value)!r} ({e})") from e
    if not isinstance(obj, kind):
        raise ModelContractError(f"{where}: metadata {key!r} must be {what}; found a JSON "
                                 f"{type(obj).__name__}: {_short(value)!r}")
    return obj


def _parse_metadata(meta: dict, where: str, stem: str = "model") -> dict:
    """Validate the contract metadata (``dt`` required, the rest where present); return the ModelInfo fields."""
    missing = [k for k in REQUIRED_METADATA if k not in meta]
    if missing:
        raise ModelContractError(f"{where}: metadata_props is missing required key(s) {missing}; the only "
                                 f"required key is 'dt' (the period of one step, s: {DT!r})")

    version = meta.get("pinnmpc.contract")
    if version is not None and version not in READABLE_VERSIONS:
        raise ModelContractError(f"{where}: metadata 'pinnmpc.contract' must be one of {list(READABLE_VERSIONS)} "
                                 f"(the versions this code reads); found {_short(version)!r}")

    architecture = meta.get("architecture", stem).strip()
    if not architecture:
        raise ModelContractError(f"{where}: metadata 'architecture' must be a non-empty name when given; found "
                                 f"{meta['architecture']!r}")

    try:
        dt = float(meta["dt"])
    except ValueError as e:
        raise ModelContractError(f"{where}: metadata 'dt' must be a number (s); found {_short(meta['dt'])!r}") from e
    if not math.isfinite(dt) or abs(dt - DT) > DT_TOL:
        raise ModelContractError(f"{where}: metadata 'dt' must equal sim.params.DT = {DT!r} s "
                                 f"(within {DT_TOL:g}); found {dt!r}")

    level = meta.get("level", DEFAULT_LEVEL)
    if level not in LEVELS:
        raise ModelContractError(f"{where}: metadata 'level' must be one of {list(LEVELS)}; found {_short(level)!r}")
    for key, want in (("state_names", STATE_NAMES), ("input_names", LEVEL_INPUTS[level])):
        if key in meta:
            names = _json(meta, key, where, list, f"the JSON list {list(want)}")
            if names != list(want):
                at = f" (the inputs of level {level!r})" if key == "input_names" and level != DEFAULT_LEVEL else ""
                raise ModelContractError(f"{where}: metadata {key!r} must be {list(want)}{at}; found {names}")

    theta = None
    if "theta" in meta:
        theta_obj = _json(meta, "theta", where, dict, f"a JSON object with keys {list(THETA_NAMES)}")
        if set(theta_obj) != set(THETA_NAMES):
            lacking = [k for k in THETA_NAMES if k not in theta_obj]
            extra = sorted(k for k in theta_obj if k not in THETA_NAMES)
            found = ", ".join(part for part in (f"missing {lacking}" if lacking else "",
                                                f"unexpected {extra}" if extra else "") if part)
            raise ModelContractError(f"{where}: metadata 'theta' must have exactly the keys {list(THETA_NAMES)}; "
                                     f"found {found}")
        theta = {}
        for name in THETA_NAMES:
            v = theta_obj[name]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ModelContractError(f"{where}: metadata theta[{name!r}] must be a finite number > 0; "
                                         f"found {v!r}")
            theta[name] = float(v)

    training_config = _json(meta, "training_config", where, dict, "a JSON object") \
        if "training_config" in meta else None
    test_metrics = _json(meta, "test_metrics", where, dict, "a JSON object") if "test_metrics" in meta else None

    h = None
    if "config_hash" in meta:
        if training_config is None:
            raise ModelContractError(f"{where}: metadata 'config_hash' is given without the 'training_config' it "
                                     f"hashes")
        h = config_hash(training_config)
        if meta["config_hash"] != h:
            raise ModelContractError(f"{where}: metadata config_hash does not match training_config: expected {h} "
                                     f"(sha256 of its canonical JSON), found {_short(meta['config_hash'])!r}")

    dataset_seed = None
    if "dataset_seed" in meta:
        try:
            dataset_seed = int(meta["dataset_seed"])
        except ValueError as e:
            raise ModelContractError(f"{where}: metadata 'dataset_seed' must be an integer; found "
                                     f"{_short(meta['dataset_seed'])!r}") from e

    return {"architecture": architecture, "dt": dt, "theta": theta, "training_config": training_config,
            "config_hash": h, "dataset_seed": dataset_seed, "code_version": meta.get("code_version"),
            "test_metrics": test_metrics, "level": level}


# --------------------------------------------------------------------------- evaluation

def _probe_batch(batch: int, dtype: np.dtype, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Seeded hover-like test states (batch, 12) and inputs (batch, 4).

    Positions within 0.1 m of (0, 0, -1), angles and body rates within 0.1
    rad(/s), velocities within 0.2 m/s; thrust within 5 % of the reference
    hover thrust (0.667 N), torques within 1e-4 N m.
    """
    rng = np.random.default_rng([seed, batch])
    x = np.zeros((batch, NX))
    x[:, 0:3] = rng.uniform(-0.1, 0.1, (batch, 3))
    x[:, 2] -= 1.0
    x[:, 3:9] = rng.uniform(-0.1, 0.1, (batch, 6))
    x[:, 9:12] = rng.uniform(-0.2, 0.2, (batch, 3))
    u = np.zeros((batch, NU))
    u[:, 0] = QuadParams().hover_thrust * (1.0 + rng.uniform(-0.05, 0.05, batch))
    u[:, 1:] = rng.uniform(-1e-4, 1e-4, (batch, NU - 1))
    return x.astype(dtype), u.astype(dtype)


def _run(session, x: np.ndarray, u: np.ndarray, where: str, names: list[str]) -> list[np.ndarray]:
    try:
        return session.run(names, {"x": x, "u": u})
    except Exception as e:  # onnxruntime's pybind exception types
        raise ModelContractError(f"{where}: evaluation with onnxruntime failed on a test batch of size "
                                 f"{x.shape[0]} ({_short(e, 300)})") from e


def _check_output(value: np.ndarray, shape: tuple, dtype: np.dtype, where: str, name: str) -> None:
    value = np.asarray(value)
    if value.shape != shape:
        raise ModelContractError(f"{where}: output {name!r} must have shape {shape} for a test batch of size "
                                 f"{shape[0]}; found {value.shape}")
    if value.dtype != dtype:
        raise ModelContractError(f"{where}: output {name!r} must be {dtype.name} at run time; found {value.dtype}")
    if not np.all(np.isfinite(value)):
        raise ModelContractError(f"{where}: output {name!r} is not finite on the hover-like test batch of size "
                                 f"{shape[0]} ({int(np.sum(~np.isfinite(value)))} non-finite entries)")


def central_differences(run, x: np.ndarray, u: np.ndarray, dtype=np.float64):
    """``(x_next (b, 12), A (b, 12, 12), B (b, 12, 4))`` of a model by central differences, in one batched call.

    Parameters
    ----------
    run : callable
        ``run(x (n, 12), u (n, 4)) -> x_next (n, 12)`` in the model's dtype (an onnxruntime session's call).
    x, u : ndarray, shape (b, 12) and (b, 4)
        Points of the linearization.
    dtype : numpy dtype
        The model's element type; it sets the step (:data:`FD_STEP`) and the rounding of the perturbed points.

    The step of variable ``i`` is ``FD_STEP * max(|z_i|, FD_SCALE)``; the
    difference is divided by the step the dtype can represent. The ``b``
    centres and ``2 x 16 b`` perturbed points go to ``run`` as one batch.
    Truncation error is O(step^2); rounding error about eps |x_next| / step
    (float64: about 1e-10 relative; float32: about 1e-4).
    """
    dtype = np.dtype(dtype)
    z = np.concatenate([np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)], axis=1)   # (b, n)
    b, n = z.shape
    nx = n - NU
    h = FD_STEP[dtype.name] * np.maximum(np.abs(z), FD_SCALE)                                # (b, n)
    eye = np.eye(n)
    zp = (z[:, None, :] + eye * h[:, None, :]).astype(dtype)                   # (b, n, n): perturb coordinate j
    zm = (z[:, None, :] - eye * h[:, None, :]).astype(dtype)
    step = np.einsum("bjj->bj", zp.astype(np.float64) - zm.astype(np.float64))  # steps actually representable
    zz = np.concatenate([z[:, None, :].astype(dtype), zp, zm], axis=1).reshape(-1, n)   # (b * (1 + 2n), n)
    out = np.asarray(run(np.ascontiguousarray(zz[:, :nx]), np.ascontiguousarray(zz[:, nx:])), dtype=np.float64)
    out = out.reshape(b, 1 + 2 * n, nx)
    jac = ((out[:, 1:n + 1] - out[:, n + 1:]) / step[:, :, None]).transpose(0, 2, 1)   # (b, nx, n)
    return out[:, 0], jac[:, :, :nx], jac[:, :, nx:]


def _fd_jacobians(session, x: np.ndarray, u: np.ndarray, dtype: np.dtype, where: str):
    """Central differences of the model behind ``session``: A (b, 12, 12) and B (b, 12, 4), float64."""
    _, A, B = central_differences(lambda xx, uu: _run(session, xx, uu, where, ["x_next"])[0], x, u, dtype)
    return A, B


def _envelope_batch(batch: int, dtype: np.dtype, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Seeded states and inputs across the flight envelope (batch, 12), (batch, 4), for the derivative check.

    Roll and pitch within 0.8 rad (46 degrees), yaw within pi, body rates within
    3 rad/s, velocities within 3 m/s, thrust from 0.3 to 1.8 times the hover
    thrust, torques within 5e-3 N m: wider than any scenario's reference.
    """
    rng = np.random.default_rng([seed, batch, 1])
    x = np.zeros((batch, NX))
    x[:, 0:3] = rng.uniform(-1.0, 1.0, (batch, 3))
    x[:, 2] -= 1.0
    x[:, 3:5] = rng.uniform(-0.8, 0.8, (batch, 2))
    x[:, 5] = rng.uniform(-np.pi, np.pi, batch)
    x[:, 6:9] = rng.uniform(-3.0, 3.0, (batch, 3))
    x[:, 9:12] = rng.uniform(-3.0, 3.0, (batch, 3))
    u = np.zeros((batch, NU))
    u[:, 0] = QuadParams().hover_thrust * rng.uniform(0.3, 1.8, batch)
    u[:, 1:] = rng.uniform(-5e-3, 5e-3, (batch, NU - 1))
    return x.astype(dtype), u.astype(dtype)


#: Samples of the flight envelope on which a derivative graph is checked (beside the hover-like test batches).
ENVELOPE_SAMPLES = 32
#: Samples of the flight envelope on which the model's output must be finite (one batched call).
ENVELOPE_PROBE_SAMPLES = 1024


def _check_envelope_finite(session, dtype: np.dtype, extra: tuple, where: str) -> None:
    """The model's ``x_next`` must be finite on :data:`ENVELOPE_PROBE_SAMPLES` states and inputs across the flight
    envelope (:func:`_envelope_batch`), not only near hover: the controllers linearize it wherever a reference and
    its tracking error take the vehicle (a fast figure-8 tilts it by 0.6 rad)."""
    x, u = _envelope_batch(ENVELOPE_PROBE_SAMPLES, dtype, seed=2)
    if extra:              # the extra states (actuators, delays) at zero: a valid start, whatever they model
        x = np.hstack([x, np.zeros((len(x), len(extra)), dtype=dtype)])
    (x_next,) = _run(session, x, u, where, ["x_next"])
    bad = ~np.all(np.isfinite(np.asarray(x_next, dtype=np.float64)), axis=1)
    if np.any(bad):
        i = int(np.argmax(bad))
        first = np.abs(x[bad, 3:5]).max(axis=1).min()
        raise ModelContractError(
            f"{where}: output 'x_next' is not finite at {int(bad.sum())} of {len(bad)} states across the flight "
            f"envelope (roll and pitch within 0.8 rad, rates within 3 rad/s, thrust 0.3 to 1.8 times hover), the "
            f"first at roll {float(x[i, 3]):.2f} rad, pitch {float(x[i, 4]):.2f} rad, thrust "
            f"{float(u[i, 0]):.3g} N; the smallest tilt among them is {float(first):.3f} rad. The controllers "
            f"would fail wherever the vehicle goes there")


def _check_jacobian(jac: Path, path: Path, model_session, dtype: np.dtype, batches: list, extra: tuple = ()) -> None:
    """Validate the derivative graph ``jac`` of the model ``path`` on the test batches."""
    where = str(jac)
    jmodel = _load(jac)
    nx = NX + len(extra)
    jdtype = _check_io(jmodel, where, {"x_next": (nx,), "A": (nx, nx), "B": (nx, NU)}, extra)
    if jdtype != dtype:
        raise ModelContractError(f"{where}: derivative graph must use the element type of the model {path.name} "
                                 f"({dtype.name}); found {jdtype.name}")
    session = open_session(jac)
    rtol = JAC_XNEXT_RTOL[dtype.name]
    for x, u, x_next in batches:
        b = x.shape[0]
        xj, a, bm = _run(session, x, u, where, ["x_next", "A", "B"])
        _check_output(xj, (b, nx), dtype, where, "x_next")
        _check_output(a, (b, nx, nx), dtype, where, "A")
        _check_output(bm, (b, nx, NU), dtype, where, "B")
        ref = x_next.astype(np.float64)
        diff = np.linalg.norm(xj.astype(np.float64) - ref, axis=1)
        scale = np.maximum(np.linalg.norm(ref, axis=1), np.finfo(dtype).tiny)
        rel = diff / scale
        if not np.all(rel <= rtol):
            k = int(np.argmax(rel))
            raise ModelContractError(f"{where}: derivative-graph output 'x_next' must equal the output of "
                                     f"{path.name} (relative {rtol:g}); found relative difference {rel[k]:.3g} "
                                     f"at test sample {k} of {b}")
        a_fd, b_fd = _fd_jacobians(model_session, x, u, dtype, str(path))
        # Rounding noise of the differences themselves, eps |x_next| / step per column: it matters for
        # float32 models whose B is small next to |x_next| (e.g. 1e-2 vs 1), never for float64.
        noise = np.finfo(dtype).eps * np.maximum(1.0, np.linalg.norm(ref, axis=1)) / FD_STEP[dtype.name]
        for name, got, fd, what in (("A", a, a_fd, "d x_next / d x"), ("B", bm, b_fd, "d x_next / d u")):
            err = np.linalg.norm(got.astype(np.float64) - fd, axis=(1, 2))
            norm = np.linalg.norm(fd, axis=(1, 2))
            bad = ~(err <= JAC_FD_RTOL * norm + noise * np.sqrt(fd.shape[2]))
            if np.any(bad):
                k = int(np.argmax(bad))
                raise ModelContractError(
                    f"{where}: derivative-graph output {name!r} ({what}) must match central finite differences "
                    f"of {path.name} (relative {JAC_FD_RTOL:g}); found relative error "
                    f"{err[k] / max(norm[k], np.finfo(float).tiny):.3g} at test sample {k} of {b}")
