"""A model's derivative computed in numpy from its exported weights: forward-mode differentiation of its ONNX graph.

The SQP linearizes its model at every stage of the horizon each period. The model file's derivative graph
(``<model>.jac.onnx``, run by onnxruntime) is one route; this is another: the model graph's own nodes evaluated
with numpy, each value carried with its tangent, the derivative of that value with respect to the 16 inputs
``(x, u)``, through batched matrix products::

    Gemm      y = a W' + b           dy = W da               (one batched product per layer)
    Tanh      y = tanh a             dy = (1 - y^2) da
    Mul, Div  the product and quotient rules; Add, Sub, Slice, Concat, Reshape, Transpose, Unsqueeze, GatherND
              act on the tangent as on the value

It serves the graphs this project's PINNs export (an input normalization, MLPs, Fourier features, a residual
output); a graph with any other operation is refused (:class:`UnsupportedGraph`), and that model keeps the
derivative graph. The benchmark (``python -m mpc.bench --derivatives``) times it beside the other routes and
checks it against the float64 derivative graph.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ModelContractError

class UnsupportedGraph(ModelContractError):
    """The model's graph has an operation (or a form of one) the numpy route does not differentiate."""


def _axis(axis: int, ndim: int) -> int:
    return axis + ndim if axis < 0 else axis


class WeightDerivative:
    """``(x_next, A, B)`` of an ONNX model in float64 numpy, from its weights (see the module's docstring).

    Parameters
    ----------
    path : str or Path
        The model file (inputs ``x`` (B, nx) and ``u`` (B, 4), output ``x_next`` (B, nx)).

    Raises
    ------
    UnsupportedGraph
        For a graph with an operation outside :data:`SUPPORTED_OPS` (named in the message).
    """

    def __init__(self, path):
        import onnx
        from onnx import numpy_helper

        self.path = Path(path)
        graph = onnx.load(str(self.path)).graph
        self.inputs = [i.name for i in graph.input]
        if self.inputs[:2] != ["x", "u"] or [o.name for o in graph.output][:1] != ["x_next"]:
            raise UnsupportedGraph(f"{self.path}: inputs x, u and output x_next expected; found {self.inputs} and "
                                   f"{[o.name for o in graph.output]}")
        self.consts = {t.name: _constant(numpy_helper.to_array(t)) for t in graph.initializer}
        self.nodes = []
        for n in graph.node:
            if n.op_type not in SUPPORTED_OPS:
                raise UnsupportedGraph(f"{self.path}: the numpy route does not differentiate {n.op_type!r} (node "
                                       f"{n.name or n.output[0]!r}); the model keeps its derivative graph")
            attrs = {a.name: onnx.helper.get_attribute_value(a) for a in n.attribute}
            if n.op_type == "Constant":
                self.consts[n.output[0]] = _constant(numpy_helper.to_array(attrs["value"]))
                continue
            if n.op_type == "Gemm" and (attrs.get("transA", 0) or len(n.input) < 2):
                raise UnsupportedGraph(f"{self.path}: a Gemm with transA is not differentiated here")
            self.nodes.append((n.op_type, list(n.input), list(n.output), attrs))

    def linearize(self, x, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x_next (B, nx), A (B, nx, nx), B (B, nx, 4))`` at states ``x`` (B, nx) and inputs ``u`` (B, 4), float64."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        u = np.atleast_2d(np.asarray(u, dtype=np.float64))
        nb, nx = x.shape
        nz = nx + u.shape[1]
        tx = np.zeros((nb, nx, nz))
        tx[:, np.arange(nx), np.arange(nx)] = 1.0
        tu = np.zeros((nb, u.shape[1], nz))
        tu[:, np.arange(u.shape[1]), nx + np.arange(u.shape[1])] = 1.0
        val = {"x": x, "u": u, **self.consts}
        tan = {"x": tx, "u": tu}
        for op, ins, outs, attrs in self.nodes:
            y, ty = _RULES[op]([val.get(i) if i else None for i in ins], [tan.get(i) for i in ins], attrs)
            val[outs[0]] = y
            if ty is not None:
                tan[outs[0]] = ty
        y, ty = val["x_next"], tan["x_next"]
        return y, ty[:, :, :nx], ty[:, :, nx:]


def _constant(a: np.ndarray) -> np.ndarray:
    """A graph constant as the route computes with it: floating point in float64, integers (indices, shapes) as
    they are."""
    return a.astype(np.float64) if a.dtype.kind == "f" else a


# -- one rule per operation: (values, tangents (None for a constant), attributes) -> (value, tangent or None)

def _bcast(t, shape):
    """A tangent broadcast to the value shape ``shape`` (plus its direction axis)."""
    return np.broadcast_to(t, tuple(shape) + t.shape[-1:])


def _gemm(v, t, a):
    A, W = v[0], v[1]
    alpha, beta = a.get("alpha", 1.0), a.get("beta", 1.0)
    Wm = W.T if a.get("transB", 0) else W          # y = A Wm
    y = alpha * (A @ Wm)
    if len(v) > 2 and v[2] is not None:
        y = y + beta * v[2]
    ty = None if t[0] is None else alpha * np.matmul(Wm.T, t[0])      # (n, k) @ (B, k, d) -> (B, n, d)
    return y, ty


def _matmul(v, t, a):
    if t[1] is not None:
        raise UnsupportedGraph("a MatMul whose right operand depends on the inputs is not differentiated here")
    y = v[0] @ v[1]
    return y, None if t[0] is None else np.matmul(v[1].T, t[0])


def _elementwise(fn, dfn):
    def rule(v, t, a):
        y = fn(v[0])
        return y, None if t[0] is None else dfn(v[0], y)[..., None] * t[0]
    return rule


def _add(sign):
    def rule(v, t, a):
        y = v[0] + sign * v[1]
        if t[0] is None and t[1] is None:
            return y, None
        parts = [_bcast(t[0], y.shape) if t[0] is not None else 0.0,
                 sign * _bcast(t[1], y.shape) if t[1] is not None else 0.0]
        return y, np.asarray(parts[0] + parts[1])
    return rule


def _mul(v, t, a):
    y = v[0] * v[1]
    ty = 0.0
    if t[0] is not None:
        ty = ty + _bcast(t[0], y.shape) * np.broadcast_to(v[1], y.shape)[..., None]
    if t[1] is not None:
        ty = ty + np.broadcast_to(v[0], y.shape)[..., None] * _bcast(t[1], y.shape)
    return y, None if t[0] is None and t[1] is None else ty


def _div(v, t, a):
    y = v[0] / v[1]
    ty = 0.0
    if t[0] is not None:
        ty = ty + _bcast(t[0], y.shape) / np.broadcast_to(v[1], y.shape)[..., None]
    if t[1] is not None:
        ty = ty - np.broadcast_to(y / v[1], y.shape)[..., None] * _bcast(t[1], y.shape)
    return y, None if t[0] is None and t[1] is None else ty


def _slice(v, t, a):
    data = v[0]
    starts, ends = v[1], v[2]
    axes = v[3] if len(v) > 3 and v[3] is not None else np.arange(len(starts))
    steps = v[4] if len(v) > 4 and v[4] is not None else np.ones(len(starts), dtype=np.int64)
    index = [slice(None)] * data.ndim
    for s, e, ax, st in zip(starts, ends, axes, steps):
        index[_axis(int(ax), data.ndim)] = slice(int(s), int(e), int(st))
    index = tuple(index)
    return data[index], None if t[0] is None else t[0][index]


def _concat(v, t, a):
    ax = _axis(a["axis"], v[0].ndim)
    y = np.concatenate(v, axis=ax)
    if all(ti is None for ti in t):
        return y, None
    d = next(ti for ti in t if ti is not None).shape[-1]
    parts = [ti if ti is not None else np.zeros(vi.shape + (d,)) for vi, ti in zip(v, t)]
    return y, np.concatenate(parts, axis=ax)


def _reshape(v, t, a):
    shape = [int(s) for s in v[1]]
    if not a.get("allowzero", 0):
        shape = [v[0].shape[i] if s == 0 else s for i, s in enumerate(shape)]
    y = v[0].reshape(shape)
    return y, None if t[0] is None else t[0].reshape(y.shape + t[0].shape[-1:])


def _transpose(v, t, a):
    perm = list(a.get("perm", range(v[0].ndim - 1, -1, -1)))
    y = np.transpose(v[0], perm)
    return y, None if t[0] is None else np.transpose(t[0], perm + [len(perm)])


def _unsqueeze(v, t, a):
    axes = v[1] if len(v) > 1 and v[1] is not None else a["axes"]
    out_ndim = v[0].ndim + len(axes)
    y, ty = v[0], t[0]
    for ax in sorted(_axis(int(ax), out_ndim) for ax in axes):
        y = np.expand_dims(y, ax)
        ty = None if ty is None else np.expand_dims(ty, ax)
    return y, ty


def _gather_nd(v, t, a):
    if a.get("batch_dims", 0):
        raise UnsupportedGraph("a GatherND with batch_dims is not differentiated here")
    idx = np.asarray(v[1])
    index = tuple(idx[..., i] for i in range(idx.shape[-1]))
    return v[0][index], None if t[0] is None else t[0][index]


def _identity(v, t, a):
    return v[0], t[0]


_RULES = {
    "Gemm": _gemm, "MatMul": _matmul,
    "Tanh": _elementwise(np.tanh, lambda a, y: 1.0 - y * y),
    "Sin": _elementwise(np.sin, lambda a, y: np.cos(a)),
    "Cos": _elementwise(np.cos, lambda a, y: -np.sin(a)),
    "Add": _add(1.0), "Sub": _add(-1.0), "Mul": _mul, "Div": _div, "Slice": _slice, "Concat": _concat,
    "Reshape": _reshape, "Transpose": _transpose, "Unsqueeze": _unsqueeze, "GatherND": _gather_nd,
    "Identity": _identity,
}
#: The operations the numpy route differentiates (``Constant`` nodes are read as constants).
SUPPORTED_OPS = frozenset(_RULES) | {"Constant"}

__all__ = ["SUPPORTED_OPS", "UnsupportedGraph", "WeightDerivative"]
