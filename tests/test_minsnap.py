"""Minimum-snap waypoint references (mpc.references.minsnap)."""

import json

import numpy as np
import pytest
import scipy.linalg

from mpc.errors import ConfigurationError
from mpc.references.minsnap import MinSnap, random_minsnap

TOL = {
    "closed_form": 1e-12,     # single segment vs closed form, relative to the derivative's peak
    "waypoint_m": 1e-9,       # position at knot times vs waypoints
    "coef_jump": 1e-9,        # derivative jumps 0..6 from coefficients, relative to the derivative's scale
    "side_jump": 1e-9,        # extra allowance (relative) on left/right jumps 0..4 beyond 2 eps |next derivative|
    "finite_diff": 1e-6,      # central differences vs analytic derivatives, relative to the derivative's scale
    "qp_cost_rel": 1e-8,      # snap cost vs generic null-space least-squares QP
    "qp_coef_rel": 1e-6,      # coefficients vs the generic QP, relative to their scale
    "quad_cost_rel": 1e-12,   # snap_cost() vs Gauss-Legendre quadrature of flat().snap
    "limit_rel": 0.01,        # random_minsnap: peak <= limit * (1 + this), fine independent grid
    "active_rel": 0.02,       # random_minsnap: max(peak / limit) >= 1 - this
    "symmetry": 1e-9,         # symmetric knots: derivative that must vanish, relative
}

WP = np.array([[0.0, 0.0, -1.0], [0.8, 0.3, -1.4], [0.2, 0.9, -0.7], [-0.5, 0.4, -1.2], [-0.1, -0.6, -1.0]])
DUR = np.array([1.2, 0.7, 1.6, 0.9])


def _scale(traj, k):
    """Typical size of the k-th derivative: max over the trajectory of |d^k p / dt^k| (> 0)."""
    t = np.linspace(0.0, traj.duration_s, 4001)
    return float(np.max(np.abs(traj.derivatives(t, order=k)[k])))


# ------------------------------------------------------------------ known answers
def test_single_segment_equals_closed_form():
    p0, p1, T = np.array([0.3, -0.2, -1.0]), np.array([1.7, 0.9, -1.6]), 2.3
    traj = MinSnap([p0, p1], [T])
    t = np.linspace(0.0, T, 1001)
    s = t / T
    # p0 + dp (35 s^4 - 84 s^5 + 70 s^6 - 20 s^7) and its s-derivatives.
    c = np.array([0, 0, 0, 0, 35.0, -84.0, 70.0, -20.0])
    f = traj.flat(t)
    dp = p1 - p0
    for k, got in enumerate([f.pos, f.vel, f.acc, f.jerk, f.snap]):
        ck = np.polynomial.polynomial.polyder(c, k)
        want = np.outer(np.polynomial.polynomial.polyval(s, ck), dp) / T ** k + (p0 if k == 0 else 0.0)
        # Relative to the peak of this derivative (|dp| max|d^k/ds^k poly| / T^k): monomial evaluation
        # cancels terms up to ~60 times larger than that peak, so an absolute 1e-12 would be rounding-bound.
        peak = np.max(np.abs(dp)) * np.max(np.abs(np.polynomial.polynomial.polyval(s, ck))) / T ** k
        err = np.max(np.abs(got - want)) / peak
        assert err <= TOL["closed_form"], (k, err)
    np.testing.assert_allclose(traj.normalized_coefficients[0, :, 1], p0[1] * (np.arange(8) == 0) + c * dp[1],
                               rtol=0, atol=TOL["closed_form"])
    assert traj.duration_s == T
    # Rest at both ends; snap does not vanish there (35 * 24 dp / T^4).
    np.testing.assert_allclose(f.snap[0], 840 * dp / T ** 4, rtol=1e-12)
    for arr in (f.vel, f.acc, f.jerk):
        assert np.max(np.abs(arr[[0, -1]])) <= 1e-12


def test_symmetric_knots():
    # Collinear equally spaced waypoints, equal durations: p(2T - t) = 2 - p(t), so at the middle knot
    # acceleration and snap vanish and velocity is the known even part; a 0 -> 1 -> 0 trip stops there.
    traj = MinSnap([[0, 0, 0], [1, 0, -1], [2, 0, 0]], [1.0, 1.0])
    d = traj.derivatives([1.0], order=4)[:, 0, :]
    assert abs(d[2, 0]) <= TOL["symmetry"] * _scale(traj, 2)
    assert abs(d[4, 0]) <= TOL["symmetry"] * _scale(traj, 4)
    assert d[1, 0] > 1.0                        # passes the middle faster than the mean speed
    assert abs(d[1, 2]) <= TOL["symmetry"] * _scale(traj, 1)      # z: 0 -> -1 -> 0 turns around
    assert abs(d[3, 2]) <= TOL["symmetry"] * _scale(traj, 3)


def test_passes_through_waypoints_at_knots():
    traj = MinSnap(WP, DUR)
    np.testing.assert_allclose(traj.knot_times, np.concatenate([[0.0], np.cumsum(DUR)]), rtol=0, atol=1e-15)
    assert traj.duration_s == pytest.approx(DUR.sum(), abs=1e-15)
    err = np.max(np.abs(traj.flat(traj.knot_times).pos - WP))
    assert err <= TOL["waypoint_m"]
    # Rest at both ends.
    d = traj.derivatives([0.0, traj.duration_s], order=3)
    assert np.max(np.abs(d[1:])) <= TOL["waypoint_m"]


def test_holds_outside_and_zero_yaw():
    traj = MinSnap(WP, DUR)
    f = traj.flat([-5.0, -1e-9, traj.duration_s + 1e-9, 100.0])
    np.testing.assert_array_equal(f.pos[:2], WP[[0, 0]])
    np.testing.assert_array_equal(f.pos[2:], WP[[-1, -1]])
    for arr in (f.vel, f.acc, f.jerk, f.snap, f.yaw, f.yaw_rate, f.yaw_acc):
        assert np.all(arr == 0.0)
    g = traj.flat(np.linspace(0, traj.duration_s, 50))
    assert g.pos.shape == (50, 3) and g.snap.shape == (50, 3) and g.yaw.shape == (50,)
    assert np.all(g.yaw == 0) and np.all(g.yaw_rate == 0) and np.all(g.yaw_acc == 0)
    x = traj(np.array([-1.0, 0.5 * traj.duration_s]))            # FlatTrajectory -> reference states
    assert x.shape == (2, 12)
    np.testing.assert_array_equal(x[0, 0:3], WP[0])
    np.testing.assert_allclose(x[0, 3:], 0.0, atol=1e-15)          # at rest, level


def test_describe_is_json_ready():
    traj = MinSnap(WP, DUR)
    d = json.loads(json.dumps(traj.describe()))
    assert d["kind"] == "minsnap"
    np.testing.assert_array_equal(d["waypoints_m"], WP)
    np.testing.assert_array_equal(d["durations_s"], DUR)
    v, a = traj.peaks()
    assert d["peak_speed_mps"] == v and d["peak_accel_mps2"] == a
    t = np.linspace(0, traj.duration_s, 20001)
    f = traj.flat(t)
    assert v == pytest.approx(np.max(np.linalg.norm(f.vel, axis=1)), rel=1e-4)
    assert a == pytest.approx(np.max(np.linalg.norm(f.acc, axis=1)), rel=1e-4)


# -------------------------------------------------------------------- smoothness
def test_continuity_across_interior_knots_from_coefficients():
    traj = MinSnap(WP, DUR)
    c = traj.coefficients                              # (N, 8, 3), local time in s
    j = np.arange(8)
    jumps = []
    for k in range(8):
        fall = np.array([np.prod(np.arange(jj - k + 1, jj + 1)) if jj >= k else 0.0 for jj in j])
        # Left limit at the end of segment i (tau = T_i), right limit at the start of segment i + 1.
        left = np.stack([np.einsum("j,jd->d", fall * np.where(j >= k, DUR[i] ** np.maximum(j - k, 0), 0.0), c[i])
                         for i in range(len(DUR) - 1)])
        right = np.stack([fall[k] * c[i + 1, k] for i in range(len(DUR) - 1)])
        jumps.append(np.max(np.abs(left - right)) / _scale(traj, k))
    assert max(jumps[:7]) <= TOL["coef_jump"], jumps
    # The 7th derivative is piecewise constant and does jump: the check above can see a jump.
    assert jumps[7] > 1e-3


def test_continuity_left_right_of_knots():
    traj = MinSnap(WP, DUR)
    eps = 1e-7
    knots = traj.knot_times[1:-1]
    d = traj.derivatives(np.concatenate([knots - eps, knots + eps]), order=5)
    n = knots.size
    for k in range(5):
        jump = np.max(np.abs(d[k, n:] - d[k, :n]))
        allowed = 2 * eps * _scale(traj, k + 1) * 1.5 + TOL["side_jump"] * _scale(traj, k)
        assert jump <= allowed, (k, jump, allowed)


def test_derivatives_match_finite_differences():
    traj = MinSnap(WP, DUR)
    h = 1e-5
    t = np.linspace(0.01, traj.duration_s - 0.01, 97)         # crosses knots: C^6 there
    dp, dm = traj.derivatives(t + h, order=4), traj.derivatives(t - h, order=4)
    d = traj.derivatives(t, order=4)
    for k in range(1, 5):
        fd = (dp[k - 1] - dm[k - 1]) / (2 * h)
        err = np.max(np.abs(fd - d[k])) / _scale(traj, k)
        assert err <= TOL["finite_diff"], (k, err)
    f = traj.flat(t)
    np.testing.assert_array_equal(np.stack([f.pos, f.vel, f.acc, f.jerk, f.snap]), d)


# ------------------------------------------------------------------- optimality
def _generic_qp(waypoints, durations, extra=()):
    """Minimum snap per axis as a null-space least-squares problem in the monomial basis of local time.

    Only what the problem states is imposed: interpolation, rest at both ends and C^1..C^3 at interior
    knots (C^4..C^6 must come out of the optimization). The cost is the 4-point Gauss-Legendre quadrature
    of snap^2 (exact for degree 6). ``extra``: (knot, order, axis, value) equality constraints.
    Returns coefficients (N, 8, 3) and the cost.
    """
    W, T = np.asarray(waypoints, float), np.asarray(durations, float)
    N = T.size
    j = np.arange(8)

    def row(k, tau):               # d^k/dtau^k of [tau^j]
        fall = np.array([np.prod(np.arange(jj - k + 1, jj + 1)) if jj >= k else 0.0 for jj in j])
        return fall * np.where(j >= k, float(tau) ** np.maximum(j - k, 0), 0.0)

    xg, wg = np.polynomial.legendre.leggauss(4)
    L = np.zeros((4 * N, 8 * N))
    for i in range(N):
        for q in range(4):
            tau = 0.5 * (xg[q] + 1.0) * T[i]
            L[4 * i + q, 8 * i:8 * i + 8] = np.sqrt(0.5 * wg[q] * T[i]) * row(4, tau)
    coefs, cost = np.zeros((N, 8, 3)), 0.0
    for ax in range(3):
        A, b = [], []

        def add(r, v, seg):
            full = np.zeros(8 * N)
            full[8 * seg:8 * seg + 8] = r
            A.append(full)
            b.append(v)
        for k in range(4):
            add(row(k, 0.0), W[0, ax] if k == 0 else 0.0, 0)
            add(row(k, T[-1]), W[-1, ax] if k == 0 else 0.0, N - 1)
        for m in range(1, N):
            add(row(0, T[m - 1]), W[m, ax], m - 1)
            add(row(0, 0.0), W[m, ax], m)
            for k in range(1, 4):
                r = np.zeros(8 * N)
                r[8 * (m - 1):8 * m] = row(k, T[m - 1])
                r[8 * m:8 * m + 8] = -row(k, 0.0)
                A.append(r)
                b.append(0.0)
        for knot, k, axis, value in extra:
            if axis == ax:
                add(row(k, 0.0), value, knot)
        A, b = np.array(A), np.array(b)
        c0 = np.linalg.lstsq(A, b, rcond=None)[0]
        Z = scipy.linalg.null_space(A)
        y = np.linalg.lstsq(L @ Z, -L @ c0, rcond=None)[0]
        c = c0 + Z @ y
        np.testing.assert_allclose(A @ c, b, atol=1e-10)
        coefs[:, :, ax] = c.reshape(N, 8)
        cost += float(np.sum((L @ c) ** 2))
    return coefs, cost


def test_snap_cost_matches_quadrature():
    traj = MinSnap(WP, DUR)
    xg, wg = np.polynomial.legendre.leggauss(4)
    t = (traj.knot_times[:-1, None] + 0.5 * (xg[None, :] + 1) * DUR[:, None]).ravel()
    w = (0.5 * wg[None, :] * DUR[:, None]).ravel()
    quad = float(np.sum(w * np.sum(traj.flat(t).snap ** 2, axis=1)))
    assert traj.snap_cost() == pytest.approx(quad, rel=TOL["quad_cost_rel"])


def test_matches_generic_qp():
    traj = MinSnap(WP, DUR)
    coefs, cost = _generic_qp(WP, DUR)
    assert abs(traj.snap_cost() - cost) <= TOL["qp_cost_rel"] * cost
    scale = np.max(np.abs(coefs), axis=(0, 1))
    assert np.max(np.abs(traj.coefficients - coefs) / scale) <= TOL["qp_coef_rel"]


def test_perturbed_knot_derivative_costs_more():
    traj = MinSnap(WP, DUR)
    d = traj.derivatives(traj.knot_times[2:3], order=2)[:, 0, :]
    base = traj.snap_cost()
    for order, delta in ((1, 0.05), (1, -0.05), (2, 0.2)):
        _, cost = _generic_qp(WP, DUR, extra=[(2, order, 0, d[order, 0] + delta)])
        # Strictly worse, and by a quadratic amount (a first-order gain would mean MinSnap is not optimal).
        assert cost > base * (1 + 1e-6), (order, delta, cost, base)
    _, c_plus = _generic_qp(WP, DUR, extra=[(2, 1, 0, d[1, 0] + 0.05)])
    _, c_minus = _generic_qp(WP, DUR, extra=[(2, 1, 0, d[1, 0] - 0.05)])
    assert abs(c_plus - c_minus) <= 1e-6 * base


# --------------------------------------------------------------- random_minsnap
BOX = np.array([(-1.0, 1.0), (-1.0, 1.0), (-1.5, -0.5)])


def _fine_peaks(traj, n=40001):
    t = np.linspace(0.0, traj.duration_s, n)
    f = traj.flat(t)
    return np.max(np.linalg.norm(f.vel, axis=1)), np.max(np.linalg.norm(f.acc, axis=1))


def test_random_reproducible_and_seed_dependent():
    a, b = random_minsnap(7), random_minsnap(7)
    np.testing.assert_array_equal(a.waypoints, b.waypoints)
    np.testing.assert_array_equal(a.durations, b.durations)
    np.testing.assert_array_equal(a.normalized_coefficients, b.normalized_coefficients)
    others = [random_minsnap(s).waypoints for s in range(5)]
    for i in range(5):
        for j in range(i + 1, 5):
            assert np.max(np.abs(others[i] - others[j])) > 1e-3


@pytest.mark.parametrize("seed, n, v_max, a_max", [(0, 5, 1.5, 4.0), (1, 5, 1.5, 4.0), (2, 8, 0.5, 4.0),
                                                   (3, 4, 3.0, 1.0), (4, 2, 1.5, 4.0)])
def test_random_limits_and_box(seed, n, v_max, a_max):
    traj = random_minsnap(seed, n_waypoints=n, v_max=v_max, a_max=a_max)
    w = traj.waypoints
    assert w.shape == (n, 3)
    np.testing.assert_array_equal(w[0], [0.0, 0.0, -1.0])
    assert np.all(w >= BOX[:, 0]) and np.all(w <= BOX[:, 1])
    seg = np.linalg.norm(np.diff(w, axis=0), axis=1)
    assert np.all(seg >= 0.3)
    ratio = traj.durations / np.sqrt(seg)                # durations proportional to sqrt(length)
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)
    v, a = _fine_peaks(traj)
    assert v <= v_max * (1 + TOL["limit_rel"]) and a <= a_max * (1 + TOL["limit_rel"])
    assert max(v / v_max, a / a_max) >= 1 - TOL["active_rel"]


def test_random_custom_box_and_start():
    box = ((2.0, 3.0), (-0.5, 0.5), (-2.0, -1.0))
    traj = random_minsnap(11, n_waypoints=6, box=box, start=(2.5, 0.0, -1.5))
    b = np.array(box)
    assert np.all(traj.waypoints >= b[:, 0]) and np.all(traj.waypoints <= b[:, 1])
    np.testing.assert_array_equal(traj.waypoints[0], [2.5, 0.0, -1.5])


# ------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("waypoints, durations, match", [
    (np.zeros((1, 3)), np.zeros(0), r"waypoints must have shape \(W, 3\).*found shape \(1, 3\)"),
    (np.zeros((3, 2)), [1.0, 1.0], r"waypoints.*found shape \(3, 2\)"),
    (np.zeros(3), [1.0], r"waypoints.*found shape \(3,\)"),
    ([[0, 0, 0], [1, np.nan, 0]], [1.0], r"waypoints must be finite.*nan"),
    ([[0, 0, 0], [1, np.inf, 0]], [1.0], r"waypoints must be finite"),
    (np.zeros((3, 3)), [1.0], r"durations must have shape \(2,\).*found shape \(1,\)"),
    (np.zeros((3, 3)), [[1.0, 1.0]], r"durations must have shape \(2,\).*found shape \(1, 2\)"),
    (np.zeros((3, 3)), [1.0, 0.0], r"durations must be finite and > 0.*durations\[1\] = 0.0"),
    (np.zeros((3, 3)), [-1.0, 1.0], r"durations\[0\] = -1.0"),
    (np.zeros((3, 3)), [1.0, np.nan], r"durations\[1\] = nan"),
    ([["a", 0, 0], [1, 1, 1]], [1.0], r"waypoints must be an array of numbers"),
])
def test_bad_minsnap_inputs(waypoints, durations, match):
    with pytest.raises(ConfigurationError, match=match):
        MinSnap(waypoints, durations)


@pytest.mark.parametrize("kwargs, match", [
    (dict(seed=-1), r"seed must be a non-negative integer"),
    (dict(seed=1.5), r"seed must be a non-negative integer"),
    (dict(seed=0, n_waypoints=1), r"n_waypoints must be an integer >= 2; found 1"),
    (dict(seed=0, v_max=0.0), r"v_max must be finite and > 0; found 0.0"),
    (dict(seed=0, a_max=np.nan), r"a_max must be finite and > 0"),
    (dict(seed=0, box=((0, 1), (0, 1))), r"box must be .* shape \(3, 2\)"),
    (dict(seed=0, box=((1, 0), (-1, 1), (-1.5, -0.5)), start=(0.5, 0, -1)), r"box\[0\] must have low < high"),
    (dict(seed=0, start=(0.0, 0.0, 0.0)), r"start must lie inside box"),
    (dict(seed=0, start=(0.0, 0.0)), r"start must be 3 finite numbers"),
    (dict(seed=0, box=((0, 0.1), (0, 0.1), (-0.1, 0)), start=(0.05, 0.05, -0.05)), r"box .* is too small"),
])
def test_bad_random_inputs(kwargs, match):
    with pytest.raises(ConfigurationError, match=match):
        random_minsnap(**kwargs)


def test_bad_times_and_order():
    traj = MinSnap(WP, DUR)
    with pytest.raises(ConfigurationError, match="times must be finite"):
        traj.flat([0.0, np.nan])
    with pytest.raises(ConfigurationError, match="order must be an integer in 0..7"):
        traj.derivatives([0.0], order=8)
