"""95 % intervals of a pooled least-squares fit from a jackknife over flights.

The pooled fit is repeated with each flight left out in turn; the spread of those fits gives the jackknife standard
error, and the interval is the pooled value plus or minus Student's t (two-sided 95 %, one degree of freedom fewer
than the flights) times it. It stays honest when a flight's residuals are correlated in time, which the textbook
least-squares interval does not.
"""

from __future__ import annotations

import math

import numpy as np

#: Student t quantiles (two-sided 95 %) by degrees of freedom; 1.96 beyond the table, and a number of degrees of
#: freedom between two entries takes the smaller one's (the wider interval).
T95 = {1: 12.71, 2: 4.30, 3: 3.18, 4: 2.78, 5: 2.57, 6: 2.45, 7: 2.36, 8: 2.31, 9: 2.26, 10: 2.23, 12: 2.18,
       15: 2.13, 20: 2.09, 30: 2.04}


def t95(dof: int) -> float:
    """Two-sided 95 % Student t quantile for ``dof`` degrees of freedom (:data:`T95`)."""
    keys = [k for k in sorted(T95) if k <= dof]
    return T95[keys[-1]] if keys and dof <= 30 else 1.96


def half_width(blocks) -> np.ndarray:
    """Half-width (p,) of the 95 % interval of each coefficient of the pooled least-squares fit of ``blocks``.

    Parameters
    ----------
    blocks : list of (A, y)
        Per flight, its regressor rows ``A`` (n_i, p) and targets ``y`` (n_i,).

    Returns
    -------
    numpy.ndarray
        ``t95(n - 1) * se`` with ``se`` the jackknife standard error over the ``n`` flights; NaN with one flight.
    """
    n = len(blocks)
    p = np.shape(blocks[0][0])[1]
    if n < 2 or p == 0:
        return np.full(p, math.nan)
    # each refit on the stacked rows (normal equations would square the regressors' condition, 1e7 against 1)
    loo = np.array([np.linalg.lstsq(np.concatenate([a for j, (a, _) in enumerate(blocks) if j != i]),
                                    np.concatenate([y for j, (_, y) in enumerate(blocks) if j != i]), rcond=None)[0]
                    for i in range(n)])
    se = np.sqrt((n - 1) / n * np.sum((loo - loo.mean(axis=0)) ** 2, axis=0))
    return t95(n - 1) * se
