"""Which controller can fly a prediction model, and how it gets its derivatives.

``pinnmpc check-model`` prints :func:`readiness` for every controller and
``pinnmpc fly`` refuses a controller it marks as unable, with the same
reason, so the two never disagree.

Every controller here needs the LQR about the model's own hover trim: the
LQR controller is it, and the MPCs use its Riccati solution as their terminal
cost and its gain as their fallback. A model whose hover linearization is not
stabilizable (a mode at hover that the inputs cannot move) can be flown by
none of them. Beyond that, each controller needs the model's derivatives:

* ``lqr``: one linearization at hover;
* ``ltv``, ``sqp``: a linearization at every stage of the horizon, every period;
* ``nmpc``: the same inside IPOPT, with a limited-memory Hessian.

An ONNX model gives them through its derivative graph when it ships one,
else through central differences (:data:`mpc.prediction.models.DERIVATIVE_PATHS`).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigurationError

#: The controllers, in the order they are reported.
CONTROLLERS = ("lqr", "ltv", "sqp", "nmpc")
#: What each controller asks of the model's derivatives.
NEEDS = {"lqr": "one hover linearization", "ltv": "a linearization along the horizon every period",
         "sqp": "linearizations along the horizon, one per iteration", "nmpc": "IPOPT's constraint Jacobian"}


@dataclass(frozen=True)
class Readiness:
    """Whether one controller can fly a model.

    Attributes
    ----------
    controller : str
    flies : bool
    derivatives : str or None
        How the controller gets the model's A and B (None when it cannot fly).
    reason : str
        What it needs when it flies; why not when it cannot.
    warning : str or None
        Why it may fly badly although it can fly (a float32 model under the
        NMPC: :data:`FLOAT32_NMPC_WARNING`).
    """

    controller: str
    flies: bool
    derivatives: str | None
    reason: str
    warning: str | None = None


#: Said of a float32 model under the NMPC.
FLOAT32_NMPC_WARNING = ("the model is float32: IPOPT needs model values and derivatives more exact than float32's "
                        "7 digits (a float32 copy of the shipped Baseline failed all 1200 solves of figure8-slow, "
                        "its float64 original none); export it in float64 for the NMPC")


def readiness(model) -> dict[str, Readiness]:
    """:class:`Readiness` of every controller of :data:`CONTROLLERS` for a loaded prediction model.

    Parameters
    ----------
    model : mpc.prediction.models.PredictionModel
        Oracle, analytic or ONNX model (already past the contract check).
    """
    from .lqr import LQRController

    try:
        LQRController(None, model)
    except ConfigurationError as e:
        why = f"no LQR about the model's hover trim ({e})"
        return {c: Readiness(c, False, None, why) for c in CONTROLLERS}
    deriv = getattr(model, "derivatives", "exact (analytic equations)")
    info = getattr(model, "info", None)
    single = info is not None and info.dtype.name == "float32"
    return {c: Readiness(c, True, deriv, NEEDS[c], FLOAT32_NMPC_WARNING if single and c == "nmpc" else None)
            for c in CONTROLLERS}


def require(model, controller: str) -> Readiness:
    """The controller's :class:`Readiness`; raises :class:`ConfigurationError` with its reason when it cannot fly."""
    if controller not in CONTROLLERS:
        raise ConfigurationError(f"controller must be one of {', '.join(CONTROLLERS)}; found {controller!r}")
    r = readiness(model)[controller]
    if not r.flies:
        raise ConfigurationError(f"{getattr(model, 'name', 'model')} cannot be flown by {controller}: {r.reason}")
    return r
