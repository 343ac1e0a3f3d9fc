"""The derivative in numpy from a model's exported weights (mpc.prediction.weights) against the model file's own
float64 derivative graph (torch's, exported), and against central differences of the model itself; the graphs it
does not differentiate are refused by name."""

from pathlib import Path

import numpy as np
import pytest

from mpc.prediction.contract import _envelope_batch
from mpc.prediction.models import OnnxModel
from mpc.prediction.weights import UnsupportedGraph, WeightDerivative

ROOT = Path(__file__).resolve().parents[1]
TOL = {
    "graph_rel": 1e-9,        # [A B] against the float64 derivative graph, max |error| / max |entry| (measured 1e-15)
    "x_next": 1e-12,          # the value against the model as exported, absolute (measured 9e-16)
    "differences_rel": 1e-6,  # against central differences of the model (step 1e-6 relative), per entry over the largest
}
#: The shipped 12-state PINNs: one plain MLP, one with Fourier features, one with two MLPs gathered (Modular).
MODELS = ("baseline", "proposed_aggressive", "fourier", "modular")


@pytest.mark.parametrize("name", MODELS)
def test_the_numpy_derivative_is_the_derivative_graph(name):
    path = ROOT / "models" / f"{name}.onnx"
    x, u = _envelope_batch(30, np.float64, seed=5)
    xn0, A0, B0 = OnnxModel(path).linearize(x, u)
    xn, A, B = WeightDerivative(path).linearize(x, u)
    assert A.shape == (30, 12, 12) and B.shape == (30, 12, 4)
    assert np.max(np.abs(xn - xn0)) <= TOL["x_next"]
    J0, J = np.concatenate([A0, B0], axis=2), np.concatenate([A, B], axis=2)
    assert np.max(np.abs(J - J0)) / np.max(np.abs(J0)) <= TOL["graph_rel"]


def test_the_numpy_derivative_is_the_models_own_slope():
    """Independent of the derivative graph: central differences of the model as exported (float64)."""
    path = ROOT / "models" / "fourier.onnx"
    model, w = OnnxModel(path), WeightDerivative(path)
    x, u = _envelope_batch(4, np.float64, seed=7)
    _, A, B = w.linearize(x, u)
    J = np.concatenate([A, B], axis=2)
    z = np.concatenate([x, u], axis=1)
    h = 1e-6 * np.maximum(np.abs(z), 1.0)
    for j in range(16):
        zp, zm = z.copy(), z.copy()
        zp[:, j] += h[:, j]
        zm[:, j] -= h[:, j]
        col = (model.step(zp[:, :12], zp[:, 12:]) - model.step(zm[:, :12], zm[:, 12:])) / (2 * h[:, j:j + 1])
        assert np.max(np.abs(col - J[:, :, j])) <= TOL["differences_rel"] * np.max(np.abs(J))


def test_a_graph_with_an_operation_it_does_not_differentiate_is_refused_by_name():
    """The learning studies' 16-state models carry their physics in the graph (Exp, Abs, Clip, ...): they keep the
    derivative graph."""
    with pytest.raises(UnsupportedGraph, match=r"does not differentiate 'Exp'.*keeps its derivative graph"):
        WeightDerivative(ROOT / "models" / "learn" / "rotorpy" / "learn_rotorpy_it3.onnx")
