"""Rotor layer: wrench allocation, per-rotor saturation, realized wrench.

X layout seen from above with body axes x forward, y right, z down (NED):

====== ================ ========== =========
rotor  position (x, y)   spin sign  position
====== ================ ========== =========
1      (+l, +l)          +1         front right
2      (-l, +l)          -1         rear right
3      (-l, -l)          +1         rear left
4      (+l, -l)          -1         front left
====== ================ ========== =========

with lever ``l = d / sqrt(2)``. Rotor i gives thrust ``kt n_i^2`` along -z_b
and reaction torque ``s_i kq n_i^2`` about z_b, so the wrench is linear in
``n^2``: ``w = M(kt, kq, l) n^2``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..params import QuadParams

#: Rotor positions in units of the lever arm, and spin signs.
ROTOR_X = np.array([1.0, -1.0, -1.0, 1.0])
ROTOR_Y = np.array([1.0, 1.0, -1.0, -1.0])
SPIN = np.array([1.0, -1.0, 1.0, -1.0])


def mixer(kt, kq, lever):
    """Rows of ``M`` with ``w = M n^2`` as nested lists (backend neutral).

    Works for floats and for CasADi symbols alike.
    """
    return [
        [kt * 1.0, kt * 1.0, kt * 1.0, kt * 1.0],
        [-kt * lever * y for y in ROTOR_Y],   # tau_x = sum(-y_i F_i)
        [kt * lever * x for x in ROTOR_X],    # tau_y = sum(x_i F_i)
        [kq * s for s in SPIN],               # tau_z = sum(s_i kq n_i^2)
    ]


def mixer_matrix(p: QuadParams) -> np.ndarray:
    """Mixer ``M`` (4, 4): wrench = M @ n^2."""
    return np.array(mixer(p.kt, p.kq, p.lever), dtype=float)


def load_matrix(p: QuadParams) -> np.ndarray:
    """``L`` (4, 4): each rotor's load ``n_i^2 / n_max^2`` (0 to 1 where it can be flown) per unit of wrench.

    ``L = M^-1 / n_max^2``. Constraints written with it (``0 <= L u <= 1``)
    have entries of the same size whatever the rotor unit: with rotor speeds
    in rad/s (``n_max`` in the thousands) the rows ``M^-1 u <= n_max^2``
    reach 1e7 beside dynamics rows of order one, and a QP solver's
    equilibration cannot undo that.
    """
    return np.linalg.inv(mixer_matrix(p)) / p.n_max_sq


def allocate(w: np.ndarray, p: QuadParams) -> np.ndarray:
    """Unclipped ``n^2`` (..., 4) that produces wrench ``w`` (..., 4)."""
    return w @ np.linalg.inv(mixer_matrix(p)).T


def wrench_from_rotor_sq(n_sq: np.ndarray, p: QuadParams) -> np.ndarray:
    """Wrench (..., 4) in N, N m produced by rotor speeds squared (..., 4)."""
    return n_sq @ mixer_matrix(p).T


class RotorOutput(NamedTuple):
    """What the rotor layer makes of a commanded wrench."""

    n_sq: np.ndarray        # (..., 4) clipped rotor speeds squared, RU^2
    wrench: np.ndarray      # (..., 4) realized wrench, N and N m
    saturated: np.ndarray   # (..., 4) bool, rotor clipped at 0 or at n_max


def realize(w_cmd: np.ndarray, p: QuadParams) -> RotorOutput:
    """Allocate a commanded wrench, clip each rotor, recompute the wrench.

    Each ``n_i^2`` is clipped to ``[0, p.n_max_sq]`` and the wrench is
    recomputed from the clipped values, so below saturation it equals the
    command up to the rounding of ``M @ inv(M)``.
    """
    n_sq = allocate(w_cmd, p)
    lim = p.n_max_sq
    saturated = (n_sq < 0.0) | (n_sq > lim)
    n_sq = np.clip(n_sq, 0.0, lim)
    return RotorOutput(n_sq, wrench_from_rotor_sq(n_sq, p), saturated)
