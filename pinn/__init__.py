"""Physics-informed neural networks for quadrotor dynamics (training needs torch)."""
