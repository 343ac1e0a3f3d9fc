"""What the LTV-MPC, the SQP and the NMPC share: model, reference, weights, the LQR, failure bookkeeping."""

from __future__ import annotations

import numpy as np

from sim.params import DT

from .controller import MAX_FAILURES_BEFORE_LQR, ControllerBase
from ..errors import ConfigurationError
from .lqr import LQRController
from ..prediction.models import PredictionModel


def shift_stages(a: np.ndarray) -> np.ndarray:
    """A plan's stages (K, ...) moved on by one period: ``a[1:]`` with its last stage repeated (a new array)."""
    return np.concatenate([a[1:], a[-1:]])


class MPCBase(ControllerBase):
    """What the LTV-MPC and the NMPC share: set-up of model, reference, weights and LQR, and failure bookkeeping.

    After a failed solve, :meth:`_failure` says what to apply: ``"shifted_plan"``
    (the next input of the previous plan) while fewer than
    :data:`MAX_FAILURES_BEFORE_LQR` failures came in a row and a plan exists,
    else ``"lqr"`` (the hover LQR). Both are counted in ``counts``.
    """

    def _setup(self, model, reference, spec, Q, R) -> None:
        if not isinstance(model, PredictionModel):
            raise ConfigurationError(f"model must be a PredictionModel; found {type(model).__name__}")
        self.model = model
        # The LQR (terminal cost, fallback) and the MPC share the spec, the trim and the feed-forward.
        self.lqr = LQRController(reference, model, Q, R, spec)
        self.spec, self.ff = self.lqr.spec, self.lqr.ff
        self.reference = self.ff.states
        self.Q, self.R, self.P = self.lqr.Q, self.lqr.R, self.lqr.P
        self.u_hover = self.lqr.u_hover
        #: Length of the planned state: 12, plus the model's extra states (:mod:`mpc.prediction.extended`).
        self.nx = model.nx
        self.tracker = self.lqr.tracker
        from ..prediction.extended import extra_scale
        from .lqr import DEFAULT_STATE_SCALE

        #: Acceptable deviations of the planned state (nx,): the default weights' for the rigid body, the model's
        #: extra states' own (steps and defects are measured in these).
        self.state_scale = np.concatenate([DEFAULT_STATE_SCALE, extra_scale(model, self.ff.trim_extra)]) \
            if model.n_extra else DEFAULT_STATE_SCALE.copy()
        self.failures_in_a_row = 0
        self.counts = {"solver_failures": 0, "shifted_plan": 0, "lqr_fallback": 0}

    def prepare(self, t_end: float, x0=None) -> None:
        """Before a flight: compute the reference and feed-forward up to ``t_end`` plus one horizon (s).

        ``x0`` (12,): the state the vehicle stands in before take-off, for
        controllers that plan their first period ahead (:class:`mpc.controllers.sqp.SQPMPC`).
        """
        self.ff.prepare(t_end + self.N * self.ff.dt)
        self.tracker.reset()

    def _horizon_reference(self, t: float):
        """Reference states (N + 1, nx) and feed-forward inputs (N, 4) over the horizon from time ``t`` (s)
        (under the disturbance of :meth:`set_disturbance`, the target the disturbed model can fly)."""
        return self.ff.horizon(t + DT * np.arange(self.N + 1))

    def start_extra(self, x: np.ndarray, t: float = 0.0) -> np.ndarray:
        """The model's extra states (n_extra,) at the first period: the LQR's (:meth:`LQRController.start_extra`)."""
        return self.lqr.start_extra(x, t)

    def _set_offset(self, offset) -> None:
        """Add ``offset`` (nx,) or None to every step of the prediction (each MPC's own)."""
        raise NotImplementedError

    def _success(self) -> None:
        self.failures_in_a_row = 0

    def _failure(self, has_plan: bool) -> str:
        self.counts["solver_failures"] += 1
        self.failures_in_a_row += 1
        if self.failures_in_a_row >= MAX_FAILURES_BEFORE_LQR or not has_plan:
            self.counts["lqr_fallback"] += 1
            return "lqr"
        self.counts["shifted_plan"] += 1
        return "shifted_plan"
