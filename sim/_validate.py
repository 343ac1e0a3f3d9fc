"""Argument checks shared by the public functions of :mod:`sim`.

Each check raises :class:`sim.errors.SimInputError` naming the argument, the
expected form and what was found, so that a user never sees a traceback from
deep inside numpy or CasADi.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from .errors import SimInputError


def as_batch(value, name: str, width: int) -> np.ndarray:
    """Return ``value`` as a finite float64 array of shape ``(..., width)``.

    Parameters
    ----------
    value : array_like
        The user's array.
    name : str
        Argument name used in the error message.
    width : int
        Required size of the last axis.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as e:
        raise SimInputError(f"{name} must be a numeric array of shape (..., {width}); "
                            f"could not convert {type(value).__name__}") from e
    if arr.ndim == 0 or arr.shape[-1] != width:
        raise SimInputError(f"{name} must have shape (..., {width}); found shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise SimInputError(f"{name} must be finite; found {arr[tuple(bad)]} at index {tuple(int(i) for i in bad)}")
    return arr


def _finite_number(value, name: str, positive: bool) -> float:
    bound = "> 0" if positive else ">= 0"
    try:
        v = float(value)
    except (TypeError, ValueError) as e:
        raise SimInputError(f"{name} must be a finite number {bound}; found {value!r}") from e
    if not math.isfinite(v) or v < 0.0 or (positive and v == 0.0):
        raise SimInputError(f"{name} must be finite and {bound}; found {value!r}")
    return v


def positive_finite(value, name: str) -> float:
    """Return ``value`` as a float, raising if it is not finite and > 0."""
    return _finite_number(value, name, positive=True)


def nonnegative_finite(value, name: str) -> float:
    """Return ``value`` as a float, raising if it is not finite and >= 0."""
    return _finite_number(value, name, positive=False)


def positive_int(value, name: str) -> int:
    """Return ``value`` as an int, raising if it is not an integer >= 1."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise SimInputError(f"{name} must be an integer >= 1; found {value!r}")
    if value < 1:
        raise SimInputError(f"{name} must be an integer >= 1; found {value}")
    return int(value)


def choice(value, name: str, options: Iterable[str]) -> str:
    """Return ``value`` if it is one of ``options``, else raise naming them."""
    opts = tuple(options)
    if value not in opts:
        raise SimInputError(f"{name} must be one of {', '.join(map(repr, opts))}; found {value!r}")
    return value


def broadcast_batch(x: np.ndarray, u: np.ndarray, names=("x", "u")) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast the leading (batch) axes of ``x`` (..., nx) and ``u`` (..., nu)."""
    try:
        lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    except ValueError as e:
        raise SimInputError(f"batch axes of {names[0]} {x.shape[:-1]} and {names[1]} {u.shape[:-1]} "
                            f"do not broadcast") from e
    return np.broadcast_to(x, lead + x.shape[-1:]), np.broadcast_to(u, lead + u.shape[-1:])
