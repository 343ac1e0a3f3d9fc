"""Closed-loop error bounds checked in CI (``scenarios/studies/bounds.toml``), generated from a measured run.

A bound is stated against the oracle (the true equations) flown on the same
scenario with the same controller in the same check:

* a learned model's case: ``value <= oracle value + tolerance_m``, with the
  tolerance set from a measured run: ``(model - oracle) * (1 + margin) + floor``;
* the oracle's own cases are absolute (``value <= tolerance_m``, set as
  ``oracle * (1 + margin) + floor``): the true model tracks a feasible
  reference to a fraction of a millimetre, so these bounds are tight enough
  that the true equations with one wrong parameter fail them
  (the negative controls of ``tests/test_bounds.py``).

``value`` is the case's ``metric``: ``rmse_position_m`` (m), ``settled_error_m``
(m; the largest error over the last 2 s) or ``rmse_yaw_rad`` (rad). A case
that crashed in the measured run is written as a known failure: it is flown
and reported, but it neither passes nor fails the check, so a fix that makes
it fly is not blocked. A run that never flew (its ``error`` set) measured
nothing: no bounds are written from it.

The file is written by ``pinnmpc bounds DIR`` from the results folder of
``pinnmpc run``; :func:`check` compares a new set of results with it and
:func:`format_table` prints the comparison, so a failing CI job shows every
case at once.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from mpc.controllers.factory import CONTROLLERS
from mpc.prediction.models import model_name
from sim.vehicles.vehicle import DEFAULT_VEHICLE

from ..errors import BoundsError
from ..closed_loop.library import get_scenario
from ..closed_loop.record import RunRecord
from ..closed_loop.runner import RunSpec

BOUNDS_FILE = Path(__file__).with_name("bounds.toml")
METRICS = ("rmse_position_m", "settled_error_m", "rmse_yaw_rad")

#: Tolerance rules (see the module docstring); written into the generated file with their reasons.
MARGIN = 0.25
FLOOR = {"rmse_position_m": 1e-4, "settled_error_m": 1e-4, "rmse_yaw_rad": 1e-3}
MODEL_FLOOR = {"rmse_position_m": 1e-3, "settled_error_m": 1e-3, "rmse_yaw_rad": 1e-2}

#: The oracle's cases: (scenario, controller, metric).
ORACLE_CASES = (
    ("hover", "ltv", "settled_error_m"),
    ("figure8-slow", "ltv", "rmse_position_m"),
    ("figure8-fast", "ltv", "rmse_position_m"),
    ("figure8-2.0s", "ltv", "rmse_position_m"),
    ("yaw-turn", "ltv", "rmse_yaw_rad"),
    ("figure8-fast", "sqp", "rmse_position_m"),
    ("hover", "lqr", "settled_error_m"),
    ("figure8-slow", "lqr", "rmse_position_m"),
)
#: Every shipped model's cases (the last rung of the speed ladder is where the gentle-flight models crash:
#: there it is a known failure, kept in view).
MODEL_CASES = (
    ("hover", "ltv", "settled_error_m"),
    ("figure8-slow", "ltv", "rmse_position_m"),
    ("figure8-fast", "ltv", "rmse_position_m"),
    ("figure8-2.0s", "ltv", "rmse_position_m"),
    ("figure8-fast", "sqp", "rmse_position_m"),
)
#: The scenarios of every case, in order: ``pinnmpc run --scenarios`` these flies every case with every model.
BOUND_SCENARIOS = tuple(dict.fromkeys(sc for sc, _, _ in ORACLE_CASES + MODEL_CASES))


@dataclass(frozen=True)
class Bound:
    """One CI case: where to fly, what to measure and what is allowed."""

    scenario: str
    controller: str
    model: str                  # "oracle", "analytic:..." or a model name in the models folder
    metric: str                 # one of METRICS
    tolerance_m: float          # oracle: the bound itself; other models: allowed excess over the oracle
    known_failure: bool = False
    measured: float | None = None          # the model's value in the run that set the bound
    oracle_measured: float | None = None   # the oracle's value in that run
    # True: the bound is the oracle's value plus the tolerance; False: the tolerance itself.
    # None (default): relative for every model but the oracle.
    relative: bool | None = None

    def __post_init__(self):
        if self.relative is None:
            object.__setattr__(self, "relative", self.model != "oracle")

    def spec(self, models_dir="models") -> RunSpec:
        if self.model == "oracle" or self.model.startswith("analytic:"):
            model = self.model
        else:
            model = str(Path(models_dir) / f"{self.model}.onnx")
        return RunSpec(self.scenario, self.controller, model)

    def oracle_spec(self) -> RunSpec:
        return RunSpec(self.scenario, self.controller, "oracle")


def _number(c, key, where, required=True):
    v = c.get(key)
    if v is None and not required:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BoundsError(f"{where}: {key} must be a number; found {v!r}")
    return float(v)


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
        missing = {"scenario", "controller", "model", "metric", "tolerance_m"} - set(c)
        if missing:
            raise BoundsError(f"{where}: missing {sorted(missing)}")
        if c["controller"] not in CONTROLLERS:
            raise BoundsError(f"{where}: controller must be one of {CONTROLLERS}; found {c['controller']!r}")
        if c["metric"] not in METRICS:
            raise BoundsError(f"{where}: metric must be one of {METRICS}; found {c['metric']!r}")
        try:
            get_scenario(c["scenario"])
        except ValueError as e:
            raise BoundsError(f"{where}: {e}") from e
        tol = _number(c, "tolerance_m", where)
        if not tol > 0:
            raise BoundsError(f"{where}: tolerance_m must be > 0; found {tol!r}")
        known = c.get("known_failure", False)
        if not isinstance(known, bool):
            raise BoundsError(f"{where}: known_failure must be true or false; found {known!r}")
        out.append(Bound(c["scenario"], c["controller"], str(c["model"]), c["metric"], tol, known,
                         _number(c, "measured", where, False), _number(c, "oracle_measured", where, False)))
    keys = [(b.scenario, b.controller, b.model, b.metric) for b in out]
    if len(set(keys)) != len(keys):
        raise BoundsError(f"{path}: a case appears twice")
    return {k: v for k, v in data.items() if k != "case"}, out


def specs_to_fly(bounds: list[Bound], models_dir="models") -> list[RunSpec]:
    """Every run the check needs: each case's model and the oracle on the same scenario and controller."""
    seen, out = set(), []
    for b in bounds:
        for s in (b.spec(models_dir), b.oracle_spec()):
            if s.run_id not in seen:
                seen.add(s.run_id)
                out.append(s)
    return out


def _key(r: RunRecord) -> tuple:
    return r.scenario, r.controller, r.model


def _records(results) -> list[RunRecord]:
    return [RunRecord.from_dict(r, f"run {i} of the results") for i, r in enumerate(results)]


def check(bounds: list[Bound], results: list[dict]) -> list[dict]:
    """One row per bound: measured value, the bound, crash, and whether it holds (known failures: ``ok`` None)."""
    results = _records(results)
    # The bounds are of our simulator flying the default vehicle (the cases the tests fly): runs on other plants or
    # vehicles in the same results folder are not theirs.
    by_key = {_key(r): r for r in results if r.get("timing", "ideal") == "ideal"
              and r.get("plant", "sim") == "sim" and r.get("vehicle", DEFAULT_VEHICLE) == DEFAULT_VEHICLE}
    rows = []
    for b in bounds:
        r = by_key.get((b.scenario, b.controller, model_name(b.model)))
        o = by_key.get((b.scenario, b.controller, "oracle"))
        row = {"bound": b, "value": None, "limit": None, "crashed": None, "ok": False, "why": ""}
        if r is None or (b.relative and o is None):
            row["why"] = "not run" if r is None else "oracle not run"
            rows.append(row)
            continue
        value, crashed = r.get(b.metric), bool(r.get("crashed"))
        row.update(value=value, crashed=crashed)
        ref = o.get(b.metric) if b.relative else 0.0
        if b.relative and ref is None:
            row["why"] = f"oracle has no {b.metric} ({'crashed' if o.get('crashed') else o.get('error')})"
            # A known failure is exempt from a crash, never from a run that did not fly.
            row["ok"] = None if b.known_failure and not o.get("error") and not r.get("error") else False
            rows.append(row)
            continue
        row["limit"] = ref + b.tolerance_m
        why = []
        if r.get("error"):
            why.append(f"error: {r['error']}")
        if crashed:
            why.append(f"crashed at {r['crash_time_s']:.2f} s ({r['crash_reason']})")
        if value is None or value > row["limit"]:
            why.append(f"{b.metric} above bound")
        row["why"] = "; ".join(why)
        row["ok"] = None if b.known_failure and not r.get("error") else not why
        rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    """The comparison as a fixed-width text table."""
    head = (f"{'scenario':<16}{'controller':<11}{'model':<34}{'metric':<17}{'value':>10}{'bound':>10}"
            f"{'crash':>7}  result")
    lines = [head, "-" * len(head)]
    for r in rows:
        b = r["bound"]
        value = "-" if r["value"] is None else f"{r['value']:.5f}"
        limit = "-" if r["limit"] is None else f"{r['limit']:.5f}"
        crash = "-" if r["crashed"] is None else ("yes" if r["crashed"] else "no")
        if r["ok"] is None:
            verdict = "known failure" + (f" ({r['why']})" if r["why"] else " (now passes)")
        else:
            verdict = "ok" if r["ok"] else f"FAIL ({r['why']})"
        lines.append(f"{b.scenario:<16}{b.controller:<11}{b.model:<34}{b.metric:<17}{value:>10}{limit:>10}"
                     f"{crash:>7}  {verdict}")
    return "\n".join(lines)


def generate(results: list[dict], models: list[str], source: str = "") -> str:
    """The text of a bounds file from measured ``results`` (as ``pinnmpc run`` saves them).

    ``models`` are the shipped model names that get :data:`MODEL_CASES`; the
    oracle gets :data:`ORACLE_CASES`. Only runs on our simulator with the
    default vehicle count (a results folder also holds runs on other plants). A case whose run is missing raises a
    :class:`BoundsError` naming it.
    """
    results = _records(results)
    # The bounds are of our simulator flying the default vehicle (the cases the tests fly): runs on other plants or
    # vehicles in the same results folder are not theirs.
    by_key = {_key(r): r for r in results if r.get("timing", "ideal") == "ideal"
              and r.get("plant", "sim") == "sim" and r.get("vehicle", DEFAULT_VEHICLE) == DEFAULT_VEHICLE}
    lines = [
        "# Closed-loop error bounds checked by the tests (tests/test_bounds.py).",
        f"# Generated by `pinnmpc bounds` from {source or 'a measured run'}; do not edit by hand.",
        "#",
        "# model = \"oracle\": the bound is tolerance_m itself, set to the measured value * (1 + margin) + floor.",
        "#   The true equations track a feasible reference to a fraction of a millimetre; these bounds are tight",
        "#   enough that the true equations with one wrong parameter (inertias x1.3 or x0.7, mass x1.1, kq x1.3)",
        "#   fail at least one of them. The margin absorbs rounding differences between machines and library",
        "#   versions (the runs are deterministic on one machine); the floor keeps a bound of zero from failing",
        "#   on rounding alone.",
        "# other models: the bound is the oracle's value on the same case, flown in the same check, plus",
        "#   tolerance_m = (measured - oracle_measured) * (1 + margin) + model_floor. A learned model is allowed",
        "#   its measured excess over the true model and a quarter more, no more.",
        "# known_failure = true: crashed when measured; flown and reported, but outside the pass/fail set.",
        "",
        f"margin = {MARGIN}",
        "floor = { " + ", ".join(f"{k} = {v:g}" for k, v in FLOOR.items()) + " }",
        "model_floor = { " + ", ".join(f"{k} = {v:g}" for k, v in MODEL_FLOOR.items()) + " }",
    ]
    cases = [("oracle", *c) for c in ORACLE_CASES] + [(m, *c) for m in models for c in MODEL_CASES]
    for model, scenario, controller, metric in cases:
        r = by_key.get((scenario, controller, model))
        o = by_key.get((scenario, controller, "oracle"))
        if r is None or o is None:
            missing = [k for k, run in (((scenario, controller, model), r), ((scenario, controller, "oracle"), o))
                       if run is None]
            elsewhere = sorted({f"{x.get('plant', 'sim')} with the {x.get('vehicle', DEFAULT_VEHICLE)}"
                                for x in results if _key(x) in missing and x.get("timing", "ideal") == "ideal"})
            if elsewhere:
                raise BoundsError(f"the results have runs of {model} on {scenario} with {controller} only on "
                                  f"{', '.join(elsewhere)}; bounds are of our simulator with the {DEFAULT_VEHICLE} "
                                  f"(the tests' cases): give the results of a `pinnmpc run` without --plant and "
                                  f"--vehicle")
            raise BoundsError(f"the results have no run of {model} on {scenario} with {controller} "
                              f"(or of the oracle there); give the results of `pinnmpc run --scenarios "
                              f"{' '.join(BOUND_SCENARIOS)}`, which flies every case with every model")
        for run, who in ((r, model), (o, "the oracle")):
            if run.get("error") is not None:    # never flew: nothing was measured, so nothing to exempt
                raise BoundsError(f"the run of {who} on {scenario} with {controller} never flew "
                                  f"({run['error']}); fix it and fly it again before writing bounds")
        value, ref = r.get(metric), o.get(metric)
        if value is None and not r.get("crashed"):
            raise BoundsError(f"the run of {model} on {scenario} with {controller} has no {metric}")
        known = bool(r.get("crashed"))
        if model == "oracle":
            if known:
                raise BoundsError(f"the oracle did not fly {scenario} with {controller}: cannot set a bound")
            tol = value * (1 + MARGIN) + FLOOR[metric]
        elif known or ref is None:
            tol = MODEL_FLOOR[metric]
            known = True
        else:
            tol = max(value - ref, 0.0) * (1 + MARGIN) + MODEL_FLOOR[metric]
        lines += ["", "[[case]]", f'scenario = "{scenario}"', f'controller = "{controller}"', f'model = "{model}"',
                  f'metric = "{metric}"', f"tolerance_m = {tol:.6g}", f"known_failure = {'true' if known else 'false'}"]
        if value is not None:
            lines.append(f"measured = {value:.6g}")
        if ref is not None:
            lines.append(f"oracle_measured = {ref:.6g}")
        if known and r.get("crashed"):
            lines.append(f"# crashed at {r['crash_time_s']} s ({r['crash_reason']})")
    return "\n".join(lines) + "\n"
