"""Exceptions raised by :mod:`mpc`.

Every error a user can provoke with a bad file or argument is a
:class:`ValueError` subclass whose message names the offending file or
argument and says what was expected and what was found; the ``pinnmpc``
command line turns these into a one-line error with exit code 2.
"""

from __future__ import annotations


class ModelContractError(ValueError):
    """An ONNX model file (or its derivative graph) violates the model contract (:mod:`mpc.prediction.contract`)."""


class SolverError(RuntimeError):
    """The MPC optimizer failed in a way the controller cannot recover from."""


class EstimatorError(RuntimeError):
    """The state estimator lost the state in flight (its prediction through the model is not finite).

    An in-flight event, not a bad input: a closed-loop run records it as a
    failed flight with its cause, as it records a crash.
    """


class ConfigurationError(ValueError):
    """An inconsistent controller configuration (weights, horizon, bounds), or a bad measured state."""
