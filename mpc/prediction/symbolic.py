"""An ONNX dynamics model as a CasADi expression, for solvers that need second derivatives.

onnxruntime gives values and (through the derivative graph) first
derivatives. IPOPT with an exact Hessian needs the model's second derivatives
as well, and CasADi takes them from an expression graph. CasADi 3.8 imports an
ONNX file as such a graph (``casadi.GraphBuilder(path).create(name,
{"symbolic": True})``); :func:`casadi_step` wraps that import in the shape the
NMPC uses and turns its failures into a :class:`ModelContractError`.

The import covers dense networks of the usual operations (every MLP-style
PINN exported by this project). Graphs it cannot express are refused with
CasADi's reason: of the shipped models, the Fourier encoding (a concatenation
along a third axis) and the modular network (``GatherND``). Such a model still
flies with every controller, only not with IPOPT's exact Hessian.

>>> F = casadi_step("models/baseline.onnx")      # F(x (12, 1), u (4, 1)) -> x_next (12, 1)
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca

from sim.params import NU, NX

from ..errors import ModelContractError


def casadi_step(path) -> ca.Function:
    """``F(x (12, 1), u (4, 1)) -> x_next (12, 1)``: the ONNX model's graph as a CasADi (MX) function.

    Parameters
    ----------
    path : path
        ONNX model with inputs ``x`` [B, 12], ``u`` [B, 4] and output ``x_next`` [B, 12]
        (the model contract); the batch dimension is fixed to 1.

    Raises
    ------
    ModelContractError
        If CasADi cannot import the graph as an expression (its reason is
        quoted), or the imported function does not map (1, 12), (1, 4) to (1, 12).
    """
    path = Path(path)
    try:
        gb = ca.GraphBuilder(str(path), {})
        gb.bind_dim("batch", 1)
        f = gb.create(f"{path.stem}_onnx", {"symbolic": True})
    except RuntimeError as e:
        reason = str(e).strip().splitlines()[-1].split(": ", 1)[-1]
        raise ModelContractError(f"{path}: CasADi cannot rebuild this graph as an expression ({reason}); the "
                                 f"exact Hessian needs one (the other controllers do not)") from e
    shapes = ([f.size_in(i) for i in range(f.n_in())], [f.size_out(i) for i in range(f.n_out())])
    if shapes != ([(1, NX), (1, NU)], [(1, NX)]):
        raise ModelContractError(f"{path}: the imported graph maps {shapes[0]} to {shapes[1]}; expected "
                                 f"[(1, {NX}), (1, {NU})] to [(1, {NX})]")
    x, u = ca.MX.sym("x", NX), ca.MX.sym("u", NU)
    return ca.Function(f"{path.stem}_step", [x, u], [ca.vec(f(x.T, u.T))], ["x", "u"], ["x_next"])
