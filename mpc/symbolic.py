"""An ONNX dynamics model as a CasADi expression, for solvers that need second derivatives.

onnxruntime gives values and (through the derivative graph) first
derivatives. IPOPT with an exact Hessian needs the second derivatives of the
model as well, and CasADi can take them from an expression graph. This module
rebuilds that graph from the ONNX file for models made of dense layers and
elementwise operations (every MLP-style PINN exported by this project, and
most small networks exported from PyTorch):

``Gemm``, ``MatMul`` (by a constant), ``Add``, ``Sub``, ``Mul``, ``Div``,
``Neg``, ``Tanh``, ``Sigmoid``, ``Relu``, ``Sin``, ``Cos``, ``Exp``,
``Identity``, ``Slice`` and ``Concat`` along the last axis.

Each tensor is one sample's feature vector (the batch axis is dropped), so a
graph that reshapes samples into matrices (a Fourier encoding over several
frequencies, per-module gathers) is refused with a :class:`ModelContractError`
that names the operation; such a model still flies with every controller, only
not with IPOPT's exact Hessian.

>>> F = casadi_step("models/baseline.onnx")      # F(x (12, 1), u (4, 1)) -> x_next (12, 1)
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from sim.params import NU, NX

from .errors import ModelContractError

#: Operations the translation supports (see the module docstring).
SUPPORTED_OPS = ("Gemm", "MatMul", "Add", "Sub", "Mul", "Div", "Neg", "Tanh", "Sigmoid", "Relu", "Sin", "Cos",
                 "Exp", "Identity", "Slice", "Concat")

_UNARY = {"Tanh": ca.tanh, "Sin": ca.sin, "Cos": ca.cos, "Exp": ca.exp, "Neg": lambda v: -v,
          "Identity": lambda v: v, "Sigmoid": lambda v: 1.0 / (1.0 + ca.exp(-v)), "Relu": lambda v: ca.fmax(v, 0.0)}


def casadi_step(path, sym=ca.SX) -> ca.Function:
    """``F(x (12, 1), u (4, 1)) -> x_next (12, 1)``: the ONNX model's graph as a CasADi function.

    Parameters
    ----------
    path : path
        ONNX model with inputs ``x``, ``u`` and output ``x_next`` (the model contract).
    sym : casadi.SX or casadi.MX
        Symbol type of the graph (``SX``: scalar expressions, fastest to differentiate for small networks).

    Raises
    ------
    ModelContractError
        If the graph uses an operation outside :data:`SUPPORTED_OPS`, or one
        the per-sample translation cannot express (for example a slice of the
        batch axis).
    """
    import onnx
    from onnx import numpy_helper

    path = Path(path)
    try:
        graph = onnx.load(str(path)).graph
    except Exception as e:  # noqa: BLE001 - any parse failure is the file's fault
        raise ModelContractError(f"{path}: not a readable ONNX file ({e})") from e
    consts = {t.name: numpy_helper.to_array(t).astype(float) for t in graph.initializer}
    x, u = sym.sym("x", NX), sym.sym("u", NU)
    env: dict = {"x": x, "u": u}

    def refuse(node, why):
        return ModelContractError(f"{path}: node {node.name or node.op_type!r} ({node.op_type}) {why}; the exact "
                                  f"Hessian needs a graph of {', '.join(SUPPORTED_OPS)} on per-sample vectors")

    def value(name, node):
        if name in env:
            return env[name]
        if name in consts:
            c = consts[name]
            if c.ndim > 1 and c.shape[0] != 1:
                raise refuse(node, f"uses the matrix {name!r} outside a Gemm/MatMul")
            return ca.DM(c.reshape(-1, 1))
        raise refuse(node, f"reads {name!r}, which is neither an input, a constant nor an earlier result")

    def last_axis(node, axis):
        if int(axis) not in (1, -1):
            raise refuse(node, f"works on axis {int(axis)}, not the feature axis")

    for node in graph.node:
        op, ins = node.op_type, list(node.input)
        att = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        if op in _UNARY:
            out = _UNARY[op](value(ins[0], node))
        elif op in ("Add", "Sub", "Mul", "Div"):
            a, b = value(ins[0], node), value(ins[1], node)
            out = {"Add": a + b, "Sub": a - b, "Mul": a * b, "Div": a / b}[op]
        elif op == "Gemm":
            if att.get("transA", 0):
                raise refuse(node, "transposes its input")
            if ins[1] not in consts:
                raise refuse(node, "multiplies by a computed matrix")
            W = consts[ins[1]] if att.get("transB", 0) else consts[ins[1]].T
            out = att.get("alpha", 1.0) * ca.mtimes(ca.DM(W), value(ins[0], node))
            if len(ins) > 2 and ins[2]:
                out = out + att.get("beta", 1.0) * ca.DM(np.reshape(consts[ins[2]], (-1, 1)))
        elif op == "MatMul":
            if ins[1] not in consts or consts[ins[1]].ndim != 2:
                raise refuse(node, "multiplies by something other than a constant matrix")
            out = ca.mtimes(ca.DM(consts[ins[1]].T), value(ins[0], node))
        elif op == "Concat":
            last_axis(node, att.get("axis", 0))
            out = ca.vertcat(*[value(i, node) for i in ins])
        elif op == "Slice":
            if any(i not in consts for i in ins[1:]):
                raise refuse(node, "has computed slice bounds")
            axes = consts[ins[3]] if len(ins) > 3 and ins[3] else np.array([0])
            if len(axes) != 1:
                raise refuse(node, "slices more than one axis")
            last_axis(node, axes[0])
            v = value(ins[0], node)
            n = v.shape[0]
            start, stop = int(consts[ins[1]][0]), int(consts[ins[2]][0])
            step = int(consts[ins[4]][0]) if len(ins) > 4 and ins[4] else 1
            idx = list(range(n))[slice(start, min(stop, n) if stop >= 0 else stop, step)]
            out = v[idx]
        else:
            raise refuse(node, "is not supported")
        env[node.output[0]] = out
    try:
        out = env[graph.output[0].name]
    except KeyError as e:
        raise ModelContractError(f"{path}: the graph's output {graph.output[0].name!r} is never computed") from e
    if out.shape != (NX, 1):
        raise ModelContractError(f"{path}: the translated output has shape {out.shape}; expected ({NX}, 1)")
    return ca.Function(f"{path.stem}_step", [x, u], [out], ["x", "u"], ["x_next"])
