"""Model predictive control of the quadrotor from ONNX dynamics models (no torch)."""
