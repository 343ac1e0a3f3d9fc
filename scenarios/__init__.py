"""Closed-loop scenarios, the runner, metrics and the ``pinnmpc`` command line."""

import sim  # noqa: F401  (first: it pins the BLAS kernel before numpy loads)

from .closed_loop.library import Scenario, get_scenario, scenario_names

__all__ = ["Scenario", "get_scenario", "scenario_names"]
