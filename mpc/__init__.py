"""Model predictive control of the quadrotor from ONNX dynamics models (no torch)."""

import sim  # noqa: F401  (first: it pins the BLAS kernel before numpy loads)
