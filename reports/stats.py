"""Small statistics used in the report text (numpy only)."""

from __future__ import annotations

import numpy as np

from scenarios.studies.stats import rankdata, spearman  # noqa: F401  (the report's correlations)


def median_or_none(values) -> float | None:
    """Median of the finite ``values``, None when there are none."""
    v = np.asarray([float(x) for x in values if x is not None], dtype=float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if len(v) else None
