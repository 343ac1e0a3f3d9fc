"""Closed-loop scenarios, the runner, metrics and the ``pinnmpc`` command line (DESIGN section 10)."""

from .library import Scenario, get_scenario, scenario_names

__all__ = ["Scenario", "get_scenario", "scenario_names"]
