"""Prediction models: the ONNX contract, the models behind one interface, what a controller knows of the vehicle."""
