"""Small statistics used in the report text (numpy only)."""

from __future__ import annotations

import numpy as np


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


def median_or_none(values) -> float | None:
    """Median of the finite ``values``, None when there are none."""
    v = np.asarray([float(x) for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if len(v) else None
