"""What every controller shares: the call signature, the info record, references.

A controller is called once per control period::

    u, info = controller(x, t)        # x (12,) measured state, t (s) -> u (4,), ControlInfo

and follows the reference it was built with: a callable ``reference(times)``
returning the desired states (K, 12) at the times (K,) (s).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from sim._validate import as_batch
from sim.params import NX

from .errors import ConfigurationError

Reference = Callable[[np.ndarray], np.ndarray]


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


def hover_reference(position=(0.0, 0.0, -1.0), yaw: float = 0.0) -> Reference:
    """Constant hover reference at ``position`` (m, NED; default 1 m height) and ``yaw`` (rad)."""
    x_ref = np.zeros(NX)
    x_ref[0:3] = as_batch(position, "position", 3)
    x_ref[5] = float(yaw)

    def ref(times):
        return np.tile(x_ref, (np.size(times), 1))
    return ref


def check_state(x, name: str = "x") -> np.ndarray:
    """The measured state as a finite (12,) array, else a clear error (before anything runs)."""
    x = as_batch(x, name, NX)
    if x.shape != (NX,):
        raise ConfigurationError(f"{name} must be one state of shape (12,); found {x.shape}")
    return x


class Timer:
    """Context manager measuring wall time in seconds (``.elapsed``)."""

    def __enter__(self):
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.elapsed = time.perf_counter() - self._t0
        return False
