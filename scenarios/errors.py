"""Errors of :mod:`scenarios` (user-input errors subclass ``ValueError``)."""

from __future__ import annotations


class ScenarioError(ValueError):
    """Unknown scenario, controller or model name, or an inconsistent scenario."""


class BoundsError(ValueError):
    """A malformed ``bounds.toml``."""
