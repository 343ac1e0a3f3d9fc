"""One controller by name: the LQR, the LTV-MPC, the SQP or the NMPC on a prediction model and a reference.

::

    from mpc.controllers.factory import make_controller
    ctrl = make_controller("sqp", model, reference, horizon=30, timing="ideal", vehicle=vehicle)

The closed loop (:func:`scenarios.closed_loop.runner.fly`) builds every run's controller here, and so do the
benchmarks and the studies that fly without it.
"""

from __future__ import annotations

from ..errors import ConfigurationError

#: The controllers by name.
CONTROLLERS = ("nmpc", "sqp", "ltv", "lqr")
#: The controllers that solve a QP each period, and so take a QP solver.
QP_CONTROLLERS = ("ltv", "sqp")
#: MPC horizon of every run unless stated, steps of 10 ms.
HORIZON = 30
#: The QP solver of a run unless stated (the solver of a run's record and cache key before the choice existed).
DEFAULT_QP = "osqp"
#: With the state estimator in real time, the SQP's wall-clock budget (8 ms per period alone) leaves this much of the
#: period to the filter (its time, median 0.4-0.9 ms, spikes to 2-6 ms, is charged to the same deadline).
ESTIMATOR_RESERVE_S = 0.003


#: The SQP's iteration scheme in real-time timing (:attr:`mpc.controllers.sqp.SQPSettings.scheme`) unless ``sqp``
#: names one: the real-time iteration, whose input waits for one QP (in ideal timing the SQP iterates).
REALTIME_SCHEME = "rti"


def timing_scheme(timing: str) -> str:
    """The SQP's scheme :func:`make_controller` gives it in ``timing`` when ``sqp`` names none: :data:`REALTIME_SCHEME`
    in real time, :class:`mpc.controllers.sqp.SQPSettings`' own (the iterating SQP) in ideal timing."""
    from .sqp import SQPSettings

    return REALTIME_SCHEME if timing == "realtime" else SQPSettings.scheme


def make_controller(kind: str, model, reference, horizon: int = HORIZON, timing: str = "ideal", vehicle=None,
                    estimator: str = "none", sqp: dict | None = None, qp: str = DEFAULT_QP):
    """The controller ``kind`` (``nmpc``, ``sqp``, ``ltv``, ``lqr``) on prediction ``model`` following ``reference``.

    The controller gets the model, the reference and the vehicle's datasheet
    only: its vehicle spec comes from the model and the datasheet of
    ``vehicle`` (:meth:`mpc.prediction.spec.VehicleSpec.from_model`; the default vehicle
    when None), never from the plant. With ``ideal`` timing the SQP runs
    without its wall-clock budget and the NMPC without IPOPT's CPU-time limit (each at most its iteration
    limit), so that the run is reproducible bit for bit; with ``realtime`` timing the budget applies, less
    :data:`ESTIMATOR_RESERVE_S` with a state ``estimator`` (its time counts against the same period), and the SQP
    flies the real-time iteration (:data:`REALTIME_SCHEME`).
    ``sqp``: other :class:`mpc.controllers.sqp.SQPSettings` values for the SQP (for example ``{"jacobian_refresh":
    "full"}``, or ``{"scheme": "sqp"}`` for the iterating SQP in real time; a ``"qp"`` there wins over ``qp``).
    ``qp``: the QP solver of the LTV-MPC and the SQP (``"osqp"`` or ``"daqp"``,
    :attr:`mpc.controllers.ltv.LTVSettings.qp`); the NMPC and the LQR have none.
    """
    from ..prediction.spec import VehicleSpec
    from .lqr import LQRController
    from .ltv import LTVMPC, LTVSettings
    from .nmpc import NMPC, NMPCSettings

    spec = VehicleSpec.from_model(model, vehicle)
    if kind == "nmpc":
        # Ideal timing: no CPU-time limit (a period cut by it would depend on the machine), as the SQP's budget.
        limit = {} if timing != "ideal" else {"time_limit_s": 0.0}
        return NMPC(model, reference, NMPCSettings(horizon=horizon, **limit), spec=spec)
    if kind == "sqp":
        import dataclasses

        from .sqp import SQPMPC, SQPSettings
        other = {"qp": qp, **(sqp or {})}
        if timing == "ideal":
            return SQPMPC(model, reference, SQPSettings(horizon=horizon, time_budget_s=None, cold_start_budget_s=None,
                                                        **other), spec=spec)
        # in real time the input waits for one QP only, unless ``sqp`` names the scheme
        st = SQPSettings(horizon=horizon, **{"scheme": timing_scheme(timing), **other})
        if estimator != "none":
            st = dataclasses.replace(st, time_budget_s=st.time_budget_s - ESTIMATOR_RESERVE_S,
                                     cold_start_budget_s=st.cold_start_budget_s - ESTIMATOR_RESERVE_S)
        return SQPMPC(model, reference, st, spec=spec)
    if kind == "ltv":
        return LTVMPC(model, reference, LTVSettings(horizon=horizon, qp=qp), spec=spec)
    if kind == "lqr":
        return LQRController(reference, model, spec=spec)
    raise ConfigurationError(f"controller must be one of {', '.join(CONTROLLERS)}; found {kind!r}")
