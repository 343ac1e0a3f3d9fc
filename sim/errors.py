"""Exceptions raised by :mod:`sim`.

Every error a user can provoke with bad input is a :class:`ValueError`
subclass whose message names the offending argument and says what was
expected and what was found.
"""

from __future__ import annotations


class SimInputError(ValueError):
    """Bad argument to a public function of :mod:`sim` (shape, value, name)."""


class DatasetError(ValueError):
    """A dataset file is missing fields or was written by an incompatible version."""


class PlantUnavailableError(SimInputError):
    """A plant needs an optional package that is not installed (the message says how to install it)."""


class FlightLogError(SimInputError):
    """A flight log or its format file cannot be imported (the message names the file and the column or key)."""
