"""Minimum-snap piecewise-polynomial references through waypoints.

:class:`MinSnap` is a :class:`~mpc.references.trajectory.FlatTrajectory` whose position is,
per axis, a piecewise polynomial of degree 7 that minimizes

.. math:: J = \\int_0^{T} \\lVert p^{(4)}(t) \\rVert^2 \\, dt

subject to passing through every waypoint at its knot time, starting and ending
at rest (velocity, acceleration and jerk zero at both ends). The minimizer is
the complete spline of order 8: on each segment ``p^(8) = 0`` (degree 7), and
at interior knots the admissible set imposes continuity of derivatives 0..3
while the optimality conditions (integration by parts of the first variation)
impose continuity of derivatives 4, 5 and 6. These conditions form a square
linear system of size ``8 (W - 1)`` per axis, which is solved directly, so the
result is exact to rounding::

    traj = MinSnap([[0, 0, -1], [1, 0, -1.5], [1, 1, -1]], [2.0, 2.0])
    f = traj.flat(np.linspace(0.0, traj.duration_s, 401))

:func:`random_minsnap` draws seeded random references inside a box whose peak
speed and acceleration respect given limits. Coordinates are NED (z down; 1 m
height is ``z = -1``), SI units throughout; yaw is held at zero.

Two references built on it take their timing from the user:
:func:`minsnap_through` flies given waypoints in a given total time (each
segment's share proportional to its length), and :class:`FlatTable` passes
through a table of sampled flat outputs (position and yaw) at their times::

    path = minsnap_through([[0, 0, -1], [1, 0, -1.5], [1, 1, -1]], duration_s=4.0, yaw=0.5)
    table = FlatTable([0.0, 1.0, 2.5], [[0, 0, -1], [0.5, 0, -1], [0.5, 0.5, -1.2]], yaw=[0.0, 0.2, 0.0])
"""

from __future__ import annotations

from math import factorial

import numpy as np
import scipy.linalg

from ..errors import ConfigurationError
from .trajectory import FlatOutputs, FlatTrajectory, _times

__all__ = ["MinSnap", "random_minsnap", "DEGREE", "FlatTable", "minsnap_through", "segment_durations"]

#: Polynomial degree of every segment (minimum snap: 2 * 4 - 1).
DEGREE = 7
_NC = DEGREE + 1          # coefficients per segment and axis
_NDER = 5                 # derivatives evaluated by flat(): 0 (pos) .. 4 (snap)
#: Number of grid points per segment on which peak speed / acceleration are measured.
PEAK_SAMPLES = 256

# _FALL[k, j] = j! / (j - k)!  (falling factorial; 0 when j < k): d^k/ds^k s^j = _FALL[k, j] s^(j-k).
_FALL = np.array([[factorial(j) / factorial(j - k) if j >= k else 0.0 for j in range(_NC)]
                  for k in range(_NC)])


def _snap_gram() -> np.ndarray:
    """Gram matrix ``Q`` (8, 8) with ``int_0^1 (d^4/ds^4 sum_j a_j s^j)^2 ds = a^T Q a``."""
    Q = np.zeros((_NC, _NC))
    for j in range(4, _NC):
        for m in range(4, _NC):
            Q[j, m] = _FALL[4, j] * _FALL[4, m] / (j + m - 7)
    return Q


_Q_SNAP = _snap_gram()


def _as_array(value, name: str) -> np.ndarray:
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigurationError(f"{name} must be an array of numbers; found {value!r} ({exc})") from None


class MinSnap(FlatTrajectory):
    """Rest-to-rest minimum-snap trajectory through waypoints (degree-7 piecewise polynomials).

    Parameters
    ----------
    waypoints : array_like, shape (W, 3)
        Positions to pass through, m (NED), ``W >= 2``. ``waypoints[i]`` is
        reached at the knot time ``knot_times[i]``.
    durations : array_like, shape (W - 1,)
        Duration of each segment, s, all finite and ``> 0``.

    Attributes
    ----------
    waypoints : ndarray, shape (W, 3)
        Waypoints, m.
    durations : ndarray, shape (W - 1,)
        Segment durations, s.
    knot_times : ndarray, shape (W,)
        Times at which the waypoints are reached, s (``knot_times[0] = 0``).
    duration_s : float
        Total duration ``sum(durations)``, s.
    normalized_coefficients : ndarray, shape (W - 1, 8, 3)
        ``a[i, j, d]``: on segment ``i``, axis ``d``,
        ``p_d(t) = sum_j a[i, j, d] s^j`` with ``s = (t - knot_times[i]) / durations[i]``
        in ``[0, 1]``; m.

    Raises
    ------
    ConfigurationError
        On a bad shape, a non-finite entry or a non-positive duration.

    Notes
    -----
    The trajectory is continuous with its derivatives 1..6 at the interior
    waypoints; velocity, acceleration and jerk vanish at both ends (snap
    generally does not). Before ``t = 0`` :meth:`flat` holds the first
    waypoint, after ``duration_s`` the last one, with zero derivatives.
    Yaw, yaw rate and yaw acceleration are zero.
    """

    def __init__(self, waypoints, durations):
        w = _as_array(waypoints, "waypoints")
        if w.ndim != 2 or w.shape[1] != 3 or w.shape[0] < 2:
            raise ConfigurationError(f"waypoints must have shape (W, 3) with W >= 2; found shape {w.shape}")
        if not np.all(np.isfinite(w)):
            bad = np.argwhere(~np.isfinite(w))[0]
            raise ConfigurationError(f"waypoints must be finite; found {w[tuple(bad)]} at index {tuple(int(b) for b in bad)}")
        d = _as_array(durations, "durations")
        n_seg = w.shape[0] - 1
        if d.ndim != 1 or d.shape[0] != n_seg:
            raise ConfigurationError(
                f"durations must have shape ({n_seg},) (one per segment between {w.shape[0]} waypoints); "
                f"found shape {d.shape}")
        if not np.all(np.isfinite(d)) or np.any(d <= 0):
            i = int(np.argmax(~(np.isfinite(d) & (d > 0))))
            raise ConfigurationError(f"durations must be finite and > 0 s; found durations[{i}] = {d[i]}")
        self.waypoints = w.copy()
        self.durations = d.copy()
        self.knot_times = np.concatenate([[0.0], np.cumsum(d)])
        self.duration_s = float(self.knot_times[-1])
        self.normalized_coefficients = self._solve()

    # ------------------------------------------------------------------ solve
    def _solve(self) -> np.ndarray:
        """Coefficients (N, 8, 3) of the square system: boundary, interpolation and C^1..C^6 conditions."""
        W = self.waypoints
        T = self.durations
        N = T.size
        n = _NC * N
        A = np.zeros((n, n))
        b = np.zeros((n, 3))
        row = 0
        ones = np.ones(_NC)
        # Start at rest: k! a_{0,k} = (p0, 0, 0, 0) for k = 0..3.
        for k in range(4):
            A[row, k] = _FALL[k, k]
            b[row] = W[0] if k == 0 else 0.0
            row += 1
        # Interior knots m = 1..N-1 between segment i = m-1 (s = 1) and i + 1 (s = 0).
        for m in range(1, N):
            i = m - 1
            left, right = slice(_NC * i, _NC * (i + 1)), slice(_NC * (i + 1), _NC * (i + 2))
            A[row, left] = ones                     # p_i(1) = w_m
            b[row] = W[m]
            row += 1
            A[row, _NC * (i + 1)] = 1.0             # p_{i+1}(0) = w_m
            b[row] = W[m]
            row += 1
            h = min(T[i], T[i + 1])                 # row scaling keeps entries <= 1 in time units
            for k in range(1, 7):
                # d^k/dt^k continuous: _FALL[k] . a_i / T_i^k - k! a_{i+1,k} / T_{i+1}^k = 0, times h^k.
                A[row, left] = _FALL[k] * (h / T[i]) ** k
                A[row, right.start + k] = -_FALL[k, k] * (h / T[i + 1]) ** k
                row += 1
        # End at rest: d^k/ds^k p_{N-1}(1) = (p_N, 0, 0, 0).
        last = slice(_NC * (N - 1), _NC * N)
        for k in range(4):
            A[row, last] = _FALL[k]
            b[row] = W[-1] if k == 0 else 0.0
            row += 1
        assert row == n  # internal invariant, not user input
        # LU solve plus two steps of iterative refinement with the residual in extended precision
        # (long double where the platform has it): the coefficients come out exact to rounding even
        # though the monomial system has a condition number of order 1e4 per segment.
        lu = scipy.linalg.lu_factor(A)
        coef = scipy.linalg.lu_solve(lu, b)
        A_ext, b_ext = A.astype(np.longdouble), b.astype(np.longdouble)
        for _ in range(2):
            resid = b_ext - A_ext @ coef.astype(np.longdouble)
            coef = coef + scipy.linalg.lu_solve(lu, resid.astype(float))
        return coef.reshape(N, _NC, 3)

    # ------------------------------------------------------------- evaluation
    @property
    def coefficients(self) -> np.ndarray:
        """Coefficients in local time, shape (W - 1, 8, 3).

        ``c[i, j, d]`` with ``p_d(t) = sum_j c[i, j, d] tau^j`` and
        ``tau = t - knot_times[i]`` in s; ``c[i, j]`` in m / s^j.
        """
        scale = self.durations[:, None] ** -np.arange(_NC)[None, :]
        return self.normalized_coefficients * scale[:, :, None]

    def derivatives(self, times, order: int = 4) -> np.ndarray:
        """Position and its time derivatives 0..``order`` at ``times``.

        Parameters
        ----------
        times : array_like, shape (K,)
            Times, s (finite). Outside ``[0, duration_s]`` the end points are
            held with zero derivatives.
        order : int
            Highest derivative, ``0 <= order <= 7``.

        Returns
        -------
        ndarray, shape (order + 1, K, 3)
            ``out[k]`` is the k-th time derivative, m / s^k.
        """
        if not (isinstance(order, (int, np.integer)) and 0 <= order <= DEGREE):
            raise ConfigurationError(f"order must be an integer in 0..{DEGREE}; found {order!r}")
        t = _times(times)
        out = np.zeros((order + 1, t.size, 3))
        before, after = t < 0.0, t > self.duration_s
        inside = ~(before | after)
        out[0, before] = self.waypoints[0]
        out[0, after] = self.waypoints[-1]
        ti = t[inside]
        if ti.size:
            seg = np.clip(np.searchsorted(self.knot_times, ti, side="right") - 1, 0, self.durations.size - 1)
            T = self.durations[seg]
            s = (ti - self.knot_times[seg]) / T
            a = self.normalized_coefficients[seg]                      # (Ki, 8, 3)
            powers = s[:, None] ** np.arange(_NC)[None, :]             # (Ki, 8)
            for k in range(order + 1):
                basis = np.zeros((ti.size, _NC))
                basis[:, k:] = _FALL[k, k:] * powers[:, :_NC - k]
                out[k, inside] = np.einsum("kj,kjd->kd", basis, a) / T[:, None] ** k
        return out

    def flat(self, times) -> FlatOutputs:
        """Flat outputs at ``times``.

        Parameters
        ----------
        times : array_like, shape (K,)
            Times, s (finite).

        Returns
        -------
        FlatOutputs
            pos (K, 3) m, vel (K, 3) m/s, acc (K, 3) m/s^2, jerk (K, 3) m/s^3,
            snap (K, 3) m/s^4; yaw, yaw_rate, yaw_acc (K,) all zero.
        """
        d = self.derivatives(times, order=4)
        K = d.shape[1]
        z = np.zeros(K)
        return FlatOutputs(d[0], d[1], d[2], d[3], d[4], z, z.copy(), z.copy())

    # ------------------------------------------------------------- summaries
    def snap_cost(self) -> float:
        """Exact cost ``int_0^T |p''''(t)|^2 dt`` summed over the three axes, m^2 / s^7."""
        a = self.normalized_coefficients
        per_seg = np.einsum("ijd,jm,imd->i", a, _Q_SNAP, a)
        return float(np.sum(per_seg / self.durations ** 7))

    def peaks(self, samples_per_segment: int = PEAK_SAMPLES) -> tuple[float, float]:
        """Peak speed (m/s) and peak acceleration magnitude (m/s^2) on a grid.

        Parameters
        ----------
        samples_per_segment : int
            Grid points per segment (uniform in the segment's normalized time,
            end points included), ``>= 2``.

        Returns
        -------
        (float, float)
            ``max |v|`` in m/s and ``max |a|`` in m/s^2 over the grid.
        """
        if not (isinstance(samples_per_segment, (int, np.integer)) and samples_per_segment >= 2):
            raise ConfigurationError(f"samples_per_segment must be an integer >= 2; found {samples_per_segment!r}")
        s = np.linspace(0.0, 1.0, samples_per_segment)
        t = (self.knot_times[:-1, None] + self.durations[:, None] * s[None, :]).ravel()
        t = np.minimum(t, self.duration_s)   # rounding must not step past the end (held, zero derivatives)
        d = self.derivatives(t, order=2)
        return float(np.max(np.linalg.norm(d[1], axis=1))), float(np.max(np.linalg.norm(d[2], axis=1)))

    def describe(self) -> dict:
        """JSON-ready description: kind, waypoints (m), durations (s), total duration, peaks."""
        v, a = self.peaks()
        return {"kind": "minsnap", "waypoints_m": self.waypoints.tolist(),
                "durations_s": self.durations.tolist(), "duration_s": self.duration_s,
                "peak_speed_mps": v, "peak_accel_mps2": a}


#: Second entry of the seed sequence of :func:`random_minsnap` (separates its stream from other users of ``seed``).
_SEED_TAG = 0x3D5A_0017
#: Minimum distance between consecutive random waypoints, m, and how many draws to try for each.
MIN_SEPARATION_M = 0.3
_MAX_DRAWS = 1000


def random_minsnap(seed: int, n_waypoints: int = 5,
                   box=((-1.0, 1.0), (-1.0, 1.0), (-1.5, -0.5)),
                   v_max: float = 1.5, a_max: float = 4.0,
                   start=(0.0, 0.0, -1.0)) -> MinSnap:
    """Seeded random minimum-snap reference inside a box, within speed and acceleration limits.

    Parameters
    ----------
    seed : int
        Non-negative seed; the generator is ``numpy.random.default_rng([seed, tag])``.
        The same seed gives the identical trajectory.
    n_waypoints : int
        Number of waypoints ``W >= 2`` (the first is ``start``).
    box : array_like, shape (3, 2)
        ``(low, high)`` bounds per NED axis, m, ``low < high``. Waypoints are drawn
        uniformly inside it (the polynomials between them may overshoot it slightly).
    v_max : float
        Speed limit, m/s, ``> 0``.
    a_max : float
        Acceleration magnitude limit, m/s^2, ``> 0``.
    start : array_like, shape (3,)
        First waypoint, m; must lie inside ``box``.

    Returns
    -------
    MinSnap
        Consecutive waypoints are at least 0.3 m apart (each is redrawn until
        so). Segment durations are proportional to the square root of the
        segment length, then all are multiplied by one factor ``k`` so that the
        peak speed (scaling as ``1/k``) and peak acceleration (as ``1/k^2``),
        measured on the :meth:`MinSnap.peaks` grid, are within the limits with
        one of them active.

    Raises
    ------
    ConfigurationError
        On bad arguments, or if no waypoint 0.3 m away from the previous one
        can be drawn inside the box.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigurationError(f"seed must be a non-negative integer; found {seed!r}")
    if isinstance(n_waypoints, bool) or not isinstance(n_waypoints, (int, np.integer)) or n_waypoints < 2:
        raise ConfigurationError(f"n_waypoints must be an integer >= 2; found {n_waypoints!r}")
    bx = _as_array(box, "box")
    if bx.shape != (3, 2) or not np.all(np.isfinite(bx)):
        raise ConfigurationError(f"box must be finite (low, high) pairs for the 3 axes, shape (3, 2); found {box!r}")
    if np.any(bx[:, 0] >= bx[:, 1]):
        ax = int(np.argmax(bx[:, 0] >= bx[:, 1]))
        raise ConfigurationError(f"box[{ax}] must have low < high; found {bx[ax].tolist()}")
    for name, v in (("v_max", v_max), ("a_max", a_max)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not (np.isfinite(v) and v > 0):
            raise ConfigurationError(f"{name} must be finite and > 0; found {v!r}")
    p0 = _as_array(start, "start").reshape(-1)
    if p0.shape != (3,) or not np.all(np.isfinite(p0)):
        raise ConfigurationError(f"start must be 3 finite numbers, shape (3,); found {start!r}")
    if np.any(p0 < bx[:, 0]) or np.any(p0 > bx[:, 1]):
        raise ConfigurationError(f"start must lie inside box {bx.tolist()}; found {p0.tolist()}")

    rng = np.random.default_rng([int(seed), _SEED_TAG])
    pts = [p0]
    for i in range(1, n_waypoints):
        for _ in range(_MAX_DRAWS):
            p = rng.uniform(bx[:, 0], bx[:, 1])
            if np.linalg.norm(p - pts[-1]) >= MIN_SEPARATION_M:
                break
        else:
            raise ConfigurationError(
                f"box {bx.tolist()} is too small: no waypoint {MIN_SEPARATION_M} m away from waypoint {i - 1} "
                f"in {_MAX_DRAWS} draws")
        pts.append(p)
    wp = np.array(pts)
    base = np.sqrt(np.linalg.norm(np.diff(wp, axis=0), axis=1))    # s, for a unit time scale
    v0, a0 = MinSnap(wp, base).peaks()
    # Uniform time scaling by k maps p(t) to p(t / k): the minimizer is scale-invariant, so
    # speeds scale exactly as 1/k and accelerations as 1/k^2 on the same normalized grid.
    k = max(v0 / float(v_max), np.sqrt(a0 / float(a_max)))
    return MinSnap(wp, base * k)


#: Shortest segment between consecutive waypoints of :func:`minsnap_through`, m.
MIN_SEGMENT_M = 1e-3


def segment_durations(waypoints, duration_s: float) -> np.ndarray:
    """Segment durations (W - 1,) proportional to segment length, summing to ``duration_s``.

    Parameters
    ----------
    waypoints : array_like, shape (W, 3)
        Waypoints, m, ``W >= 2``; consecutive ones at least :data:`MIN_SEGMENT_M` apart.
    duration_s : float
        Total duration, s, finite and ``> 0``.

    Raises
    ------
    ConfigurationError
        On a bad shape, a non-finite entry, a non-positive duration, or two
        consecutive waypoints closer than :data:`MIN_SEGMENT_M` (the error
        names the first pair).
    """
    w = _as_array(waypoints, "waypoints")
    if w.ndim != 2 or w.shape[1] != 3 or w.shape[0] < 2:
        raise ConfigurationError(f"waypoints must have shape (W, 3) with W >= 2; found shape {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ConfigurationError("waypoints must be finite")
    if isinstance(duration_s, bool) or not isinstance(duration_s, (int, float, np.integer, np.floating)) \
            or not (np.isfinite(duration_s) and duration_s > 0):
        raise ConfigurationError(f"duration_s must be finite and > 0 s; found {duration_s!r}")
    length = np.linalg.norm(np.diff(w, axis=0), axis=1)
    if np.any(length < MIN_SEGMENT_M):
        i = int(np.argmax(length < MIN_SEGMENT_M))
        raise ConfigurationError(f"waypoints {i} and {i + 1} are {length[i]:.3g} m apart; consecutive waypoints "
                                 f"must be at least {MIN_SEGMENT_M:g} m apart")
    return float(duration_s) * length / np.sum(length)


class FlatTable(FlatTrajectory):
    """Flat outputs given as samples, passed through by rest-to-rest minimum-snap polynomials.

    The position is the :class:`MinSnap` trajectory through ``positions[i]``
    at ``times[i]``; the yaw, when it varies, is the one-dimensional
    minimum-snap trajectory through its samples at the same times. Both are
    smooth to their sixth derivative between the first and last sample and
    at rest (zero velocity, acceleration and jerk; zero yaw rate and yaw
    acceleration) at both ends; before ``times[0]`` the first sample is held,
    after ``times[-1]`` the last.

    Parameters
    ----------
    times : array_like, shape (K,)
        Sample times, s, finite and strictly increasing, ``K >= 2``.
    positions : array_like, shape (K, 3)
        Positions, m (NED).
    yaw : float or array_like of shape (K,), optional
        Yaw, rad: one value held throughout (default 0) or one per sample.
        Taken as given (not wrapped): to turn past +-pi, continue beyond it.

    Attributes
    ----------
    times, positions : ndarray
        The samples.
    yaw : ndarray, shape (K,)
        Yaw samples, rad.
    path : MinSnap
        Position polynomials in time since ``times[0]``.
    duration_s : float
        ``times[-1]``, s: the trajectory is at rest from then on.

    Raises
    ------
    ConfigurationError
        On a bad shape, a non-finite entry or times that do not increase.
    """

    def __init__(self, times, positions, yaw=0.0):
        t = _as_array(times, "times")
        if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)):
            raise ConfigurationError(f"times must be K >= 2 finite numbers; found shape {t.shape}")
        dt = np.diff(t)
        if np.any(dt <= 0):
            i = int(np.argmax(dt <= 0))
            raise ConfigurationError(f"times must increase strictly; found times[{i + 1}] = {t[i + 1]} after "
                                     f"times[{i}] = {t[i]}")
        p = _as_array(positions, "positions")
        if p.shape != (t.size, 3):
            raise ConfigurationError(f"positions must have shape ({t.size}, 3), one row per time; found {p.shape}")
        y = _as_array(yaw, "yaw")
        if y.ndim == 0:
            y = np.full(t.size, float(y))
        if y.shape != (t.size,) or not np.all(np.isfinite(y)):
            raise ConfigurationError(f"yaw must be one finite number or {t.size} of them; found shape {y.shape}")
        self.times, self.positions, self.yaw = t.copy(), p.copy(), y.copy()
        self.path = MinSnap(p, dt)
        self._yaw_path = None if np.all(y == y[0]) else MinSnap(np.column_stack([y, np.zeros((t.size, 2))]), dt)
        self.duration_s = float(t[-1])

    def flat(self, times) -> FlatOutputs:
        """Flat outputs at ``times`` (K,), s: position and derivatives to snap, yaw and two derivatives."""
        tau = _times(times) - self.times[0]
        d = self.path.derivatives(tau, order=4)
        if self._yaw_path is None:
            z = np.zeros(tau.size)
            yaw = (np.full(tau.size, self.yaw[0]), z, z.copy())
        else:
            yaw = tuple(self._yaw_path.derivatives(tau, order=2)[:, :, 0])
        return FlatOutputs(d[0], d[1], d[2], d[3], d[4], *yaw)

    def describe(self) -> dict:
        """JSON-ready description: kind, samples, total duration and the peaks of the path."""
        v, a = self.path.peaks()
        return {"kind": "flat_table", "times_s": self.times.tolist(), "positions_m": self.positions.tolist(),
                "yaw_rad": self.yaw.tolist(), "duration_s": self.duration_s, "peak_speed_mps": v,
                "peak_accel_mps2": a}


def minsnap_through(waypoints, duration_s: float, yaw: float = 0.0) -> FlatTable:
    """Rest-to-rest minimum-snap path through given waypoints in ``duration_s``, at a constant yaw.

    Each segment gets a share of ``duration_s`` proportional to its length
    (:func:`segment_durations`), so the mean speed is the same on every
    segment; the path reaches ``waypoints[i]`` at ``knot_times[i]`` of its
    :attr:`FlatTable.path` and starts at ``t = 0``.

    Parameters
    ----------
    waypoints : array_like, shape (W, 3)
        Waypoints, m (NED), ``W >= 2``, consecutive ones at least :data:`MIN_SEGMENT_M` apart.
    duration_s : float
        Time to fly the whole path, s, ``> 0``.
    yaw : float
        Constant yaw, rad.

    Returns
    -------
    FlatTable
    """
    d = segment_durations(waypoints, duration_s)
    knots = np.concatenate([[0.0], np.cumsum(d)])
    knots[-1] = float(duration_s)
    return FlatTable(knots, waypoints, yaw)
