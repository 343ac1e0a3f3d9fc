"""What every controller shares: the interface the closed loop calls, the info record, references.

A controller is called once per control period::

    u, info = controller(x, t)        # x (12,) measured state, t (s) -> u (4,), ControlInfo

and follows the reference it was built with: a callable ``reference(times)``
returning the desired states (K, 12) at the times (K,) (s). :class:`Controller`
states the whole interface; :class:`ControllerBase` holds the parts the LQR and
the MPCs share.
"""

from __future__ import annotations

import gc
import time
from contextlib import contextmanager
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from sim._validate import as_batch
from sim.params import NX

from ..errors import ConfigurationError

Reference = Callable[[np.ndarray], np.ndarray]

#: Failed solves in a row after which the MPCs fall back to the hover LQR.
MAX_FAILURES_BEFORE_LQR = 3


@dataclass(frozen=True)
class ControlInfo:
    """What a controller did in one period (qpsolvers-style result record)."""

    solve_time_s: float                   # wall time of the call, s
    status: str                           # "optimal", "lqr", "shifted_plan", "lqr_fallback", ...
    iterations: int = 0                   # solver iterations (0 for LQR)
    predicted: np.ndarray | None = None   # (N + 1, 12) predicted states, if any
    fallback: str | None = None           # which fallback produced u, if any
    extra: dict = field(default_factory=dict)

    def is_optimal(self) -> bool:
        """True when the solver reported an optimal solution (LQR counts as optimal)."""
        return self.status in ("optimal", "lqr") and self.fallback is None


class Controller(Protocol):
    """What the closed loop (:func:`scenarios.closed_loop.loop.fly_loop`) and the runner ask of a controller.

    Attributes
    ----------
    preflight : ControlInfo or None
        What the controller did planning before take-off in :meth:`prepare` (the SQP's first plan); None for a
        controller that does not plan ahead.
    """

    preflight: ControlInfo | None

    def __call__(self, x: np.ndarray, t: float) -> tuple[np.ndarray, ControlInfo]:
        """The input (4,) for the measured state ``x`` (12,; the model's whole state from an estimator) at time
        ``t`` (s), and what it did."""

    def prepare(self, t_end: float, x0: np.ndarray | None = None) -> None:
        """Before a flight of ``t_end`` s: compute what the flight will need. ``x0`` (12,): the state before
        take-off, for a controller that plans its first period ahead."""

    def applied(self, u: np.ndarray) -> None:
        """After each period: the input (4,) that was in effect during it (a model with extra states carries
        them with it)."""

    def prepare_next(self, until: float | None = None) -> None:
        """After each call, once its input is out: work for the next period (the real-time iteration's
        preparation), to end by ``until`` (``time.perf_counter``, s: the next measurement; None: no limit). The
        closed loop charges it to the period, not to the input's latency. Most controllers have none."""

    def set_deadline(self, at: float | None) -> None:
        """In real time, before each call: the time (``time.perf_counter``, s) by which the input must be out,
        or None for none. A controller that cannot keep a deadline ignores it."""

    def set_disturbance(self, d: np.ndarray | None, x: np.ndarray | None = None) -> None:
        """With an estimator, before each call: the estimated disturbance ``d`` (6,) (acceleration, m/s^2 NED;
        angular acceleration, rad/s^2 body; None: none) at the estimated state ``x`` (offset-free control)."""

    def start_extra(self, x: np.ndarray, t: float = 0.0) -> np.ndarray:
        """The model's extra states (n_extra,) at the first period, at time ``t`` (s) and state ``x`` (12,)."""


class ControllerBase:
    """The hooks of :class:`Controller` that the LQR and the MPCs share, one definition for all.

    A subclass sets ``model`` (:class:`mpc.prediction.models.PredictionModel`), ``ff``
    (:class:`mpc.references.feedforward.FeedForward`)
    and ``tracker`` (:class:`mpc.prediction.extended.ExtraStateTracker`), and may override :meth:`_set_offset` (a
    prediction
    of its own to offset) and :meth:`set_deadline` (a solver that can stop at a deadline).
    """

    preflight: ControlInfo | None = None

    def applied(self, u) -> None:
        """The input (4,) in effect during the period just flown (to carry the model's extra states)."""
        self.tracker.applied(u)

    def prepare_next(self, until: float | None = None) -> None:
        """Nothing: this controller does all its work in its call."""

    def set_deadline(self, at: float | None) -> None:
        """Ignored: this controller's call has no budget to keep."""

    def set_disturbance(self, d, x=None) -> None:
        """Offset-free control: a disturbance ``d`` (6,) (estimated acceleration, m/s^2 NED, and angular
        acceleration, rad/s^2 body; None or zeros: none) enters the target (and the prediction, see
        :meth:`_set_offset`) from the next call. ``x``: the state whose attitude sets the disturbance's effect on
        the Euler angles (level if None). See :mod:`mpc.controllers.offset_free`."""
        from .offset_free import disturbance_offset

        off = disturbance_offset(d, x, self.model.nx)
        self.ff.set_disturbance(None if off is None else d, off)
        self._set_offset(off)

    def _set_offset(self, offset) -> None:
        """Add ``offset`` (nx,) or None to every step of the controller's own prediction (none here)."""


def hover_reference(position=(0.0, 0.0, -1.0), yaw: float = 0.0):
    """Constant hover reference at ``position`` (m, NED; default 1 m height) and ``yaw`` (rad).

    A :class:`mpc.references.trajectory.Hover`: callable as ``ref(times) -> (K, 12)``.
    """
    from ..references.trajectory import Hover

    return Hover(as_batch(position, "position", 3).reshape(3), float(yaw))


def figure8_reference(amplitude: float = 0.75, period: float = 6.0, height: float = 1.0, center=(0.0, 0.0)):
    """Lemniscate ``x = A sin(wt), y = A sin(wt) cos(wt)`` at ``height`` (m; NED z = -height), w = 2 pi / period.

    A :class:`mpc.references.trajectory.Figure8`: callable as ``ref(times) -> (K, 12)``
    with the full dynamically feasible state (velocity, attitude and body
    rates from the flatness map of the nominal model).
    """
    from ..references.trajectory import Figure8

    return Figure8(amplitude, period, height, center)


def check_state(x, name: str = "x", nx: int = NX) -> np.ndarray:
    """The measured state as a finite (nx,) array (12 unless stated), else a clear error (before anything runs)."""
    x = as_batch(x, name, nx)
    if x.shape != (nx,):
        raise ConfigurationError(f"{name} must be one state of shape ({nx},); found {x.shape}")
    return x


def check_measured(x, model) -> np.ndarray:
    """The state a controller is handed: the rigid body's (12,), or the model's whole state (nx,) from an estimator."""
    n = np.size(np.asarray(x, dtype=object))
    return check_state(x, nx=model.nx if model.n_extra and n == model.nx else NX)


class Timer:
    """Context manager measuring wall time in seconds (``.elapsed``) on ``clock`` (``time.perf_counter`` by
    default; a controller passes the clock its timing rules read)."""

    def __init__(self, clock=time.perf_counter):
        self._clock = clock

    def __enter__(self):
        self.start = self._t0 = self._clock()
        return self

    def now(self) -> float:
        """The clock the timer reads, s."""
        return self._clock()

    def __exit__(self, *exc):
        self.elapsed = self._clock() - self._t0
        return False


@contextmanager
def collector_paused(pause: bool = True):
    """Pause Python's cyclic garbage collector for the block (when ``pause``), then restore its state.

    A controller's call in a real-time loop is charged for its own work; a
    collection triggered by other code's allocations runs after it returns.
    """
    was_enabled = gc.isenabled()
    if pause:
        gc.disable()
    try:
        yield
    finally:
        if pause and was_enabled:
            gc.enable()


def check_common_settings(horizon, attitude_limit_rad, max_iter) -> None:
    """Validate the settings both MPCs have (horizon in steps, attitude bound in rad, iteration limit)."""
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise ConfigurationError(f"horizon must be an integer >= 1; found {horizon!r}")
    if not 0 < attitude_limit_rad < np.pi / 2:
        raise ConfigurationError(f"attitude_limit_rad must lie in (0, pi/2); found {attitude_limit_rad}")
    if max_iter < 1:
        raise ConfigurationError(f"max_iter must be >= 1; found {max_iter}")
