"""What every controller shares: the call signature, the info record, references.

A controller is called once per control period::

    u, info = controller(x, t)        # x (12,) measured state, t (s) -> u (4,), ControlInfo

and follows the reference it was built with: a callable ``reference(times)``
returning the desired states (K, 12) at the times (K,) (s).
"""

from __future__ import annotations

import gc
import time
from contextlib import contextmanager
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sim._validate import as_batch
from sim.params import NX

from .errors import ConfigurationError

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


def hover_reference(position=(0.0, 0.0, -1.0), yaw: float = 0.0):
    """Constant hover reference at ``position`` (m, NED; default 1 m height) and ``yaw`` (rad).

    A :class:`mpc.trajectory.Hover`: callable as ``ref(times) -> (K, 12)``.
    """
    from .trajectory import Hover

    return Hover(as_batch(position, "position", 3).reshape(3), float(yaw))


def figure8_reference(amplitude: float = 0.75, period: float = 6.0, height: float = 1.0, center=(0.0, 0.0)):
    """Lemniscate ``x = A sin(wt), y = A sin(wt) cos(wt)`` at ``height`` (m; NED z = -height), w = 2 pi / period.

    A :class:`mpc.trajectory.Figure8`: callable as ``ref(times) -> (K, 12)``
    with the full dynamically feasible state (velocity, attitude and body
    rates from the flatness map of the nominal model).
    """
    from .trajectory import Figure8

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
