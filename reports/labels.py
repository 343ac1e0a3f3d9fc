"""Names, display labels and the fixed ordering of scenarios, controllers and models.

Every table and figure of the report lists runs in the same order: scenario
(``hover``, ``figure8-slow``, ``figure8-fast``, the speed ladder, the random
paths and the yaw turn, then the variants of each base in the order
``+highfi +payload +wind +noise +delay``, then any other name alphabetically), controller (NMPC, LTV-MPC, LQR, then others), model (the
oracle first, then alphabetically).
"""

from __future__ import annotations

from mpc.controllers.factory import CONTROLLERS
from scenarios.closed_loop.library import BASE, VARIANTS, scenario_names  # noqa: F401  (VARIANTS: the variant order)
from sim.params import DT

#: Scenarios without a variant in report order: the bases, the speed ladder, the random paths, the yaw turn.
BASE_SCENARIOS = tuple(n for n in scenario_names() if "+" not in n)
#: Display names of the controllers.
CONTROLLER_LABELS = {"nmpc": "NMPC", "sqp": "SQP", "ltv": "LTV-MPC", "lqr": "LQR"}
#: The model name of the true (simulator) equations.
ORACLE = "oracle"
#: Control period, s; the deadline of one controller solve.
DT_S = DT


def base_scenario(name: str) -> str:
    """The base scenario of ``name`` (the part before the first ``+``)."""
    return str(name).split("+", 1)[0]


def scenario_key(name: str) -> tuple:
    """Sort key of a scenario name (see the module docstring)."""
    parts = str(name).split("+")
    base, variants = parts[0], parts[1:]
    v = tuple((VARIANTS.index(s), "") if s in VARIANTS else (len(VARIANTS), s) for s in variants)
    if base not in BASE_SCENARIOS:
        return (2, 0, base, v)
    return (1 if variants else 0, BASE_SCENARIOS.index(base), "", v)


def controller_key(name: str) -> tuple:
    """Sort key of a controller name."""
    name = str(name)
    return (CONTROLLERS.index(name), "") if name in CONTROLLERS else (len(CONTROLLERS), name)


def controller_label(name: str) -> str:
    """Display name of a controller (``"ltv"`` -> ``"LTV-MPC"``)."""
    return CONTROLLER_LABELS.get(str(name), str(name))


def model_key(name: str) -> tuple:
    """Sort key of a model name: the oracle first, then alphabetically."""
    name = str(name)
    return (0, "") if name == ORACLE else (1, name)


def run_key(run: dict) -> tuple:
    """Sort key of a closed-loop result: scenario, controller, model, run id."""
    return (scenario_key(run.get("scenario", "")), controller_key(run.get("controller", "")),
            model_key(run.get("model", "")), str(run.get("run_id", "")))


def sorted_unique(values, key) -> list:
    """The distinct ``values`` sorted with ``key``."""
    return sorted(set(values), key=key)
