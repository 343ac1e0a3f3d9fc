"""Errors of :mod:`reports`: bad or missing input raises a ``ValueError`` subclass."""

from __future__ import annotations


class ReportError(ValueError):
    """A results folder that cannot be reported on (a missing or malformed required file).

    The message names the file at fault.
    """
