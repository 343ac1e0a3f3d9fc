"""Closed-loop error bounds checked in CI (``scenarios/bounds.toml``).

Each ``[[case]]`` names a scenario, a controller and a model (``oracle`` or a
file name in ``models/``), the largest position RMSE allowed (m) and whether a
crash is expected::

    [[case]]
    scenario = "hover"
    controller = "ltv"
    model = "proposed"
    rmse_max_m = 0.14
    crash_expected = false
    measured_rmse_m = 0.123     # what set the bound (informational)

:func:`check` compares results with the bounds and :func:`format_table` prints
the comparison, so a failing CI job shows every case at once.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from .errors import BoundsError
from .library import get_scenario
from .runner import CONTROLLERS, RunSpec

BOUNDS_FILE = Path(__file__).with_name("bounds.toml")


@dataclass(frozen=True)
class Bound:
    """One CI case: where to fly and what is allowed."""

    scenario: str
    controller: str
    model: str                  # "oracle" or a model name in the models folder
    rmse_max_m: float           # largest position RMSE allowed, m
    crash_expected: bool = False
    measured_rmse_m: float | None = None   # the measurement that set the bound, m (informational)

    def spec(self, models_dir="models") -> RunSpec:
        model = "oracle" if self.model == "oracle" else str(Path(models_dir) / f"{self.model}.onnx")
        return RunSpec(self.scenario, self.controller, model)


def load_bounds(path=BOUNDS_FILE) -> tuple[dict, list[Bound]]:
    """``(settings, bounds)`` from a bounds file; a :class:`BoundsError` naming the defect otherwise."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError as e:
        raise BoundsError(f"bounds file {str(path)!r} does not exist") from e
    except tomllib.TOMLDecodeError as e:
        raise BoundsError(f"{path}: not valid TOML: {e}") from e
    cases = data.get("case")
    if not isinstance(cases, list) or not cases:
        raise BoundsError(f"{path}: no [[case]] entries")
    out = []
    for i, c in enumerate(cases):
        where = f"{path}: case {i + 1}"
        missing = {"scenario", "controller", "model", "rmse_max_m"} - set(c)
        if missing:
            raise BoundsError(f"{where}: missing {sorted(missing)}")
        if c["controller"] not in CONTROLLERS:
            raise BoundsError(f"{where}: controller must be one of {CONTROLLERS}; found {c['controller']!r}")
        try:
            get_scenario(c["scenario"])
        except ValueError as e:
            raise BoundsError(f"{where}: {e}") from e
        rmse = c["rmse_max_m"]
        if isinstance(rmse, bool) or not isinstance(rmse, (int, float)) or not rmse > 0:
            raise BoundsError(f"{where}: rmse_max_m must be a number > 0; found {rmse!r}")
        crash = c.get("crash_expected", False)
        if not isinstance(crash, bool):
            raise BoundsError(f"{where}: crash_expected must be true or false; found {crash!r}")
        measured = c.get("measured_rmse_m")
        if measured is not None and (isinstance(measured, bool) or not isinstance(measured, (int, float))):
            raise BoundsError(f"{where}: measured_rmse_m must be a number; found {measured!r}")
        out.append(Bound(c["scenario"], c["controller"], str(c["model"]), float(rmse), crash,
                         None if measured is None else float(measured)))
    keys = [(b.scenario, b.controller, b.model) for b in out]
    if len(set(keys)) != len(keys):
        raise BoundsError(f"{path}: a case appears twice")
    return {k: v for k, v in data.items() if k != "case"}, out


def check(bounds: list[Bound], results: list[dict]) -> list[dict]:
    """One row per bound: measured RMSE, crash, and whether the bound holds."""
    by_key = {(r["scenario"], r["controller"], r["model"]): r for r in results}
    rows = []
    for b in bounds:
        r = by_key.get((b.scenario, b.controller, b.model))
        if r is None:
            rows.append({"bound": b, "rmse": None, "crashed": None, "ok": False, "why": "not run"})
            continue
        rmse, crashed = r.get("rmse_position_m"), bool(r.get("crashed"))
        why = []
        if r.get("error"):
            why.append(f"error: {r['error']}")
        if crashed != b.crash_expected:
            why.append(f"crash {'expected' if b.crash_expected else 'not expected'}, "
                       f"{'crashed at %.2f s (%s)' % (r['crash_time_s'], r['crash_reason']) if crashed else 'flew'}")
        if not b.crash_expected and (rmse is None or rmse > b.rmse_max_m):
            why.append("RMSE above bound")
        rows.append({"bound": b, "rmse": rmse, "crashed": crashed, "ok": not why, "why": "; ".join(why)})
    return rows


def format_table(rows: list[dict]) -> str:
    """The comparison as a fixed-width text table."""
    head = f"{'scenario':<22}{'controller':<11}{'model':<22}{'RMSE (m)':>10}{'bound (m)':>11}{'crash':>7}  result"
    lines = [head, "-" * len(head)]
    for r in rows:
        b = r["bound"]
        rmse = "-" if r["rmse"] is None else f"{r['rmse']:.4f}"
        crash = "-" if r["crashed"] is None else ("yes" if r["crashed"] else "no")
        verdict = "ok" if r["ok"] else f"FAIL ({r['why']})"
        lines.append(f"{b.scenario:<22}{b.controller:<11}{b.model:<22}{rmse:>10}{b.rmse_max_m:>11.4f}{crash:>7}  {verdict}")
    return "\n".join(lines)
