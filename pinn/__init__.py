"""Physics-informed neural networks for quadrotor dynamics (training needs torch)."""

import sim  # noqa: F401  (first: it pins the BLAS kernel before numpy loads)
