"""Plants, what a closed loop flies (our simulator, RotorPy), and the sensors that read them."""
