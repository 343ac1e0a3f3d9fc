"""Intervals and ranks for closed-loop results: Wilson (crash probability), bootstrap (RMSE), Spearman ranks.

One run of a case on the edge of what a model can fly is a sample, not a
number; an ensemble of runs from several seeds gives a distribution, and
these functions summarize it.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ScenarioError

#: Two-sided 95 % standard normal quantile.
Z95 = 1.959963984540054


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval ``(low, high)`` of a probability from ``k`` events in ``n`` trials.

    Unlike the normal approximation it stays inside [0, 1] and is not empty
    at ``k = 0`` or ``k = n`` (0 crashes in 10 runs: 0 to 0.28).
    """
    for name, v in (("k", k), ("n", n)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ScenarioError(f"{name} must be an integer >= 0; found {v!r}")
    if n == 0 or k > n:
        raise ScenarioError(f"need 0 <= k <= n and n >= 1; found k={k}, n={n}")
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # At k = 0 (k = n) the bound is exactly 0 (1); the formula leaves rounding there.
    return (0.0 if k == 0 else max(0.0, centre - half)), (1.0 if k == n else min(1.0, centre + half))


def bootstrap_ci(values, statistic=np.median, n_boot: int = 2000, level: float = 0.95,
                 seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic`` over ``values`` (seeded: the same input gives the same interval).

    Parameters
    ----------
    values : array_like, shape (n,)
        Finite samples (for example the RMSE of each run that did not crash), n >= 2.
    statistic : callable
        Reduces an array (n_boot, n) along axis 1, like ``np.median`` or ``np.mean``.
    """
    v = np.asarray(values, dtype=float).ravel()
    if v.size < 2 or not np.all(np.isfinite(v)):
        raise ScenarioError(f"values must be at least 2 finite numbers; found {v.size} "
                            f"({int(np.sum(~np.isfinite(v)))} not finite)")
    if not 0 < level < 1:
        raise ScenarioError(f"level must be in (0, 1); found {level}")
    rng = np.random.default_rng(seed)
    boot = statistic(v[rng.integers(0, v.size, (n_boot, v.size))], axis=1)
    a = (1 - level) / 2
    return float(np.quantile(boot, a)), float(np.quantile(boot, 1 - a))


def summarize(results: list[dict], metric: str = "rmse_position_m") -> dict:
    """An ensemble's distribution: crash probability with its Wilson interval, the metric's median with a bootstrap CI.

    The metric is taken over the runs that did not crash (a crashed run's
    RMSE covers only its flight up to the crash); with fewer than two of
    those its interval is None.
    """
    n = len(results)
    if n == 0:
        raise ScenarioError("an ensemble needs at least one run")
    crashed = sum(bool(r.get("crashed")) for r in results)
    vals = [r[metric] for r in results if not r.get("crashed") and r.get(metric) is not None]
    out = {"runs": n, "crashes": crashed, "crash_probability": crashed / n,
           "crash_probability_ci95": list(wilson_interval(crashed, n)), "metric": metric,
           "flown": len(vals), "median": float(np.median(vals)) if vals else None,
           "median_ci95": list(bootstrap_ci(vals)) if len(vals) >= 2 else None,
           "min": float(min(vals)) if vals else None, "max": float(max(vals)) if vals else None}
    return out


def rankdata(a) -> np.ndarray:
    """Ranks 1..n of ``a`` (n,), ties given their average rank."""
    a = np.asarray(a, dtype=float)
    order = np.argsort(a, kind="mergesort")
    ranks = np.empty(len(a))
    ranks[order] = np.arange(1, len(a) + 1, dtype=float)
    _, inverse, counts = np.unique(a, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse, weights=ranks)
    return sums[inverse] / counts[inverse]


def spearman(x, y) -> float | None:
    """Spearman rank correlation of ``x`` and ``y`` (n,), or None.

    None when fewer than 3 finite pairs remain or either variable is constant
    (the correlation is undefined).
    """
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 3:
        return None
    rx, ry = rankdata(x), rankdata(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    den = np.sqrt(np.sum(rx * rx) * np.sum(ry * ry))
    if den == 0.0:
        return None
    return float(np.sum(rx * ry) / den)


def improvement(reference, values, n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> dict:
    """How much lower the median of ``values`` is than the median of ``reference``, with a bootstrap interval.

    ``fraction = 1 - median(values) / median(reference)``: 0.5 means half the reference's error, a negative
    number a larger error. The interval resamples the two groups independently (seeded) and takes percentiles
    of the fraction; the two medians' own intervals are :func:`bootstrap_ci`'s.

    Parameters
    ----------
    reference, values : array_like, shape (n,) and (m,)
        Finite positive samples, for example the RMSE (m) of each run that did not crash; n, m >= 2.

    Returns
    -------
    dict
        ``fraction`` and ``fraction_ci95`` (low, high); ``apart``: True when the medians' intervals do not
        overlap.
    """
    r = np.asarray(reference, dtype=float).ravel()
    v = np.asarray(values, dtype=float).ravel()
    for name, a in (("reference", r), ("values", v)):
        if a.size < 2 or not np.all(np.isfinite(a)) or np.any(a <= 0):
            raise ScenarioError(f"{name} must be at least 2 finite positive numbers; found {a.size} of them"
                                f"{'' if a.size < 2 else ' with some not finite or <= 0'}")
    if not 0 < level < 1:
        raise ScenarioError(f"level must be in (0, 1); found {level}")
    rng = np.random.default_rng(seed)
    mr = np.median(r[rng.integers(0, r.size, (n_boot, r.size))], axis=1)
    mv = np.median(v[rng.integers(0, v.size, (n_boot, v.size))], axis=1)
    boot = 1.0 - mv / mr
    a = (1 - level) / 2
    ci_r, ci_v = bootstrap_ci(r, level=level, seed=seed), bootstrap_ci(v, level=level, seed=seed)
    return {"fraction": float(1.0 - np.median(v) / np.median(r)),
            "fraction_ci95": [float(np.quantile(boot, a)), float(np.quantile(boot, 1 - a))],
            "apart": bool(ci_v[1] < ci_r[0] or ci_r[1] < ci_v[0])}
