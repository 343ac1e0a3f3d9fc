"""Closed-loop metrics of one run.

Definitions (``K`` control periods flown, state ``x_k`` at time ``k dt``):

* position error ``e_k = |p_k - p_ref(k dt)|`` (m) for ``k = 1 .. K``, the
  states the controller produced (the initial offset is not counted);
* ``rmse_position_m = sqrt(mean(e_k^2))``, ``max_position_error_m = max e_k``
  (over finite errors; a non-finite state is a crash);
* crash: the first ``k`` with ``e_k > 2 m``, ``|phi|`` or ``|theta| > 80 deg``,
  a non-finite state, or below ground (``z > 0``, NED). The run ends there;
  ``crash_time_s = k dt`` and the error metrics cover ``1 .. k``;
* ``rmse_yaw_rad``: RMSE of the heading error (wrapped to [0, pi]);
* ``settled_error_m``: the largest position error over the last
  :data:`SETTLE_WINDOW_S` of a run that flew to its end (None after a crash);
* after a gust impulse at ``t_g``: ``gust_peak_error_m``, the largest error
  from ``t_g`` on, and ``recovery_time_s``, the time from ``t_g`` until the
  error is back within ``settled_error_m + RECOVERY_BAND_M`` for good;
* solve time median / p95 / max over the periods flown (ms), deadline misses
  = periods whose solve took longer than ``dt`` (with real-time timing the
  periods a busy controller skipped are counted as ``skipped_periods``);
* ``solver_failures`` = periods whose solve failed (then the shifted plan or
  the LQR flew); ``fallbacks`` = periods flown by the LQR fallback.
"""

from __future__ import annotations

import numpy as np

from sim.params import DT

CRASH_POSITION_ERROR_M = 2.0
#: Window of the settled error at the end of a run, s.
SETTLE_WINDOW_S = 2.0
#: A gust is recovered when the error is back within the settled error plus this band, m.
RECOVERY_BAND_M = 0.005
CRASH_TILT_RAD = np.deg2rad(80.0)

#: Fields that measure this machine's wall time; everything else in a result is reproducible exactly.
TIMING_FIELDS = ("solve_ms", "latency_ms", "deadline_misses", "own_work_misses", "deadline_fallbacks",
                 "wall_time_s", "preflight_ms")
#: Trace arrays that measure wall time (or CPU time).
TRACE_TIMING_FIELDS = ("solve_s", "latency_s", "load_s", "load_cpu_s")


def own_work_misses(load_cpu_s: np.ndarray, called: np.ndarray, dt: float = DT) -> int:
    """Periods whose controller did more than a period's work by its own thread's CPU time (``load_cpu_s`` (K,), s,
    where ``called`` (K,)): the deadline misses it caused itself. A period over the deadline by wall time but not by
    CPU time is one in which the machine gave the core to something else (another process, the kernel, the
    hypervisor)."""
    cpu = np.asarray(load_cpu_s, dtype=float)[np.asarray(called, dtype=bool)]
    return int(np.sum(cpu > dt))



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
                        dt: float = DT, impulse_start_s: float | None = None,
                        planned_steps: int | None = None, called: np.ndarray | None = None) -> dict:
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
    impulse_start_s : float, optional
        Start of a gust impulse, s (adds the gust peak error and recovery time).
    planned_steps : int, optional
        Control periods the run was planned for; a run that stopped earlier has no settled error.
    called : ndarray of bool, shape (K,), optional
        Periods in which the controller was called (real-time timing: a
        controller still busy with an earlier call is not called). The solve
        times and deadline misses cover these periods; ``skipped_periods``
        counts the others.
    """
    x, x_ref = np.asarray(x, dtype=float), np.asarray(x_ref, dtype=float)
    solve_ms = 1e3 * np.asarray(solve_s, dtype=float)
    if x.shape != x_ref.shape or x.shape[0] != solve_ms.shape[0] + 1:
        raise ValueError(f"trace shapes disagree: x {x.shape}, x_ref {x_ref.shape}, solve_s {solve_ms.shape}")
    with np.errstate(invalid="ignore"):
        e = position_errors(x[1:], x_ref[1:])
    finite = np.isfinite(e)
    e_ok = e[finite]
    K = solve_ms.shape[0]
    extra = {}
    if called is not None:
        called = np.asarray(called, dtype=bool)
        extra["skipped_periods"] = int(K - np.sum(called))
        solve_ms = solve_ms[called]
    complete = crash_step is None and (planned_steps is None or K >= planned_steps) and bool(np.all(finite))
    n_settle = int(round(SETTLE_WINDOW_S / dt))
    settled = float(np.max(e[-n_settle:])) if complete and K >= n_settle else None
    gust = {}
    if impulse_start_s is not None:
        k_g = int(round(impulse_start_s / dt))          # e[i] is the error at t = (i + 1) dt
        after = e[k_g - 1:] if K >= k_g else np.array([])
        gust["gust_peak_error_m"] = float(np.max(after)) if after.size and complete else None
        rec = None
        if settled is not None and after.size:
            outside = np.nonzero(after > settled + RECOVERY_BAND_M)[0]
            rec = 0.0 if outside.size == 0 else round(float(outside[-1] + 1) * dt, 10)
        gust["recovery_time_s"] = rec
    with np.errstate(invalid="ignore"):
        e_yaw = np.abs(np.angle(np.exp(1j * (x[1:, 5] - x_ref[1:, 5]))))   # heading error, wrapped to [0, pi]
    e_yaw = e_yaw[np.isfinite(e_yaw)]
    return {**gust, **extra,
        "settled_error_m": settled,
        "rmse_yaw_rad": float(np.sqrt(np.mean(e_yaw ** 2))) if e_yaw.size else None,
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
        "steps": int(K),
    }


#: A speed-ladder rung counts as tracked when the run did not crash and its position RMSE is at most this, m.
LADDER_RMSE_BOUND_M = 0.10


def max_trackable_speed(runs: list[dict], ladder: list[str], speeds: dict[str, float]) -> dict:
    """The fastest figure-8 rung one model/controller pair tracks, climbing the ladder from the slowest.

    Parameters
    ----------
    runs : list of dict
        Results of one model with one controller (``scenario``, ``crashed``, ``rmse_position_m``).
    ladder : list of str
        Rung scenario names from slowest to fastest.
    speeds : dict
        Mean speed of each rung, m/s.

    Returns
    -------
    dict
        ``speed_mps`` (None if even the slowest rung fails), ``scenario`` of that rung, ``failed_at`` (the
        first rung that failed, or None) and ``complete`` (False when a rung was not flown).
    """
    by = {r["scenario"]: r for r in runs}
    best, failed_at, complete = None, None, True
    for name in ladder:
        r = by.get(name)
        if r is None:
            complete = False
            break
        ok = not r.get("crashed") and not r.get("error") and r.get("rmse_position_m") is not None \
            and r["rmse_position_m"] <= LADDER_RMSE_BOUND_M
        if not ok:
            failed_at = name
            break
        best = name
    return {"speed_mps": None if best is None else speeds[best], "scenario": best, "failed_at": failed_at,
            "complete": complete}
