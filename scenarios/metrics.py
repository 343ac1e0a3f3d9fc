"""Closed-loop metrics of one run (DESIGN section 10).

Definitions (``K`` control periods flown, state ``x_k`` at time ``k dt``):

* position error ``e_k = |p_k - p_ref(k dt)|`` (m) for ``k = 1 .. K``, the
  states the controller produced (the initial offset is not counted);
* ``rmse_position_m = sqrt(mean(e_k^2))``, ``max_position_error_m = max e_k``
  (over finite errors; a non-finite state is a crash);
* crash: the first ``k`` with ``e_k > 2 m``, ``|phi|`` or ``|theta| > 80 deg``,
  a non-finite state, or below ground (``z > 0``, NED). The run ends there;
  ``crash_time_s = k dt`` and the error metrics cover ``1 .. k``;
* solve time median / p95 / max over the periods flown (ms), deadline misses
  = periods whose solve took longer than ``dt``;
* ``solver_failures`` = periods whose solve failed (then the shifted plan or
  the LQR flew); ``fallbacks`` = periods flown by the LQR fallback.
"""

from __future__ import annotations

import numpy as np

from sim.params import DT

CRASH_POSITION_ERROR_M = 2.0
CRASH_TILT_RAD = np.deg2rad(80.0)

#: Fields that measure this machine's wall time; everything else in a result is reproducible exactly.
TIMING_FIELDS = ("solve_ms", "deadline_misses", "wall_time_s")
#: Trace arrays that measure wall time.
TRACE_TIMING_FIELDS = ("solve_s",)


def crash_reason(x: np.ndarray, x_ref: np.ndarray) -> str | None:
    """Why the state ``x`` (12,) counts as a crash against ``x_ref`` (12,), or None."""
    if not np.all(np.isfinite(x)):
        return "non-finite state"
    if x[2] > 0.0:
        return "below ground"
    if np.linalg.norm(x[0:3] - x_ref[0:3]) > CRASH_POSITION_ERROR_M:
        return "position error > 2 m"
    if abs(x[3]) > CRASH_TILT_RAD or abs(x[4]) > CRASH_TILT_RAD:
        return "tilt > 80 deg"
    return None


def position_errors(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """``|p_k - p_ref,k|`` (K,) for states (K, 12) and references (K, 12), m."""
    return np.linalg.norm(np.asarray(x)[:, 0:3] - np.asarray(x_ref)[:, 0:3], axis=1)


def closed_loop_metrics(x: np.ndarray, x_ref: np.ndarray, solve_s: np.ndarray, failed: np.ndarray,
                        lqr_fallback: np.ndarray, crash_step: int | None, crash_why: str | None = None,
                        dt: float = DT) -> dict:
    """Metrics of one run from its trace.

    Parameters
    ----------
    x, x_ref : ndarray, shape (K + 1, 12)
        True states and references at ``t = 0, dt, ..., K dt``.
    solve_s : ndarray, shape (K,)
        Controller wall time per period, s.
    failed, lqr_fallback : ndarray of bool, shape (K,)
        Failed solve / LQR fallback flew, per period.
    crash_step : int or None
        Index ``k`` of the crash state in ``x``, if the run crashed.
    """
    x, x_ref = np.asarray(x, dtype=float), np.asarray(x_ref, dtype=float)
    solve_ms = 1e3 * np.asarray(solve_s, dtype=float)
    if x.shape != x_ref.shape or x.shape[0] != solve_ms.shape[0] + 1:
        raise ValueError(f"trace shapes disagree: x {x.shape}, x_ref {x_ref.shape}, solve_s {solve_ms.shape}")
    with np.errstate(invalid="ignore"):
        e = position_errors(x[1:], x_ref[1:])
    finite = np.isfinite(e)
    e_ok = e[finite]
    return {
        "rmse_position_m": float(np.sqrt(np.mean(e_ok ** 2))) if e_ok.size else None,
        "max_position_error_m": float(np.max(e_ok)) if e_ok.size else None,
        "crashed": crash_step is not None,
        "crash_time_s": None if crash_step is None else round(crash_step * dt, 10),
        "crash_reason": crash_why,
        "solve_ms": {"median": float(np.median(solve_ms)), "p95": float(np.percentile(solve_ms, 95)),
                     "max": float(np.max(solve_ms))} if solve_ms.size else None,
        "deadline_misses": int(np.sum(solve_ms > 1e3 * dt)),
        "solver_failures": int(np.sum(failed)),
        "fallbacks": int(np.sum(lqr_fallback)),
        "steps": int(solve_ms.size),
    }
