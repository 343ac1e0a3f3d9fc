"""Data of the headline comparison: open-loop 100-step error against closed-loop error.

x = a model's 100-step open-loop position MAE (``evaluation.json``
``rollout_100.position``, m); y = the closed-loop position RMSE of one run with
that model (m). The oracle has no open-loop error and enters as a reference
level per controller.
"""

from __future__ import annotations

from dataclasses import dataclass

from .labels import ORACLE, controller_key, controller_label
from .stats import median_or_none, spearman


@dataclass(frozen=True)
class Point:
    """One closed-loop run of a learned model.

    Attributes
    ----------
    model, controller, scenario : str
        Names as in ``results.json``.
    open_loop_m : float
        100-step open-loop position MAE of the model, m.
    rmse_m : float
        Closed-loop position RMSE of the run (up to a crash), m.
    crashed : bool
        Whether the run crashed.
    """

    model: str
    controller: str
    scenario: str
    open_loop_m: float
    rmse_m: float
    crashed: bool


@dataclass(frozen=True)
class Headline:
    """Everything the headline figure and its caption show.

    Attributes
    ----------
    points : list of Point
        Runs of learned models with both numbers, in report order.
    oracle_median_m : dict
        Controller -> median RMSE of its non-crashed oracle runs, m.
    correlation : dict
        Controller -> (Spearman rank correlation or None, number of pairs),
        over the non-crashed points of that controller.
    unmatched : list of str
        Models flown in closed loop that ``evaluation.json`` does not list.
    per_scenario : dict
        Controller -> {scenario: Spearman correlation across models}, for the
        scenarios with at least 3 non-crashed learned models (scenario
        difficulty then cancels out of the comparison).
    """

    points: list
    oracle_median_m: dict
    correlation: dict
    unmatched: list
    per_scenario: dict


def headline_data(runs: list[dict], models_by_name: dict) -> Headline:
    """Collect the headline points from ``runs`` (report order) and the open-loop entries by name."""
    points, unmatched = [], set()
    oracle: dict[str, list] = {}
    for r in runs:
        rmse = r.get("rmse_position_m")
        if r.get("error") or rmse is None:
            continue
        if r["model"] == ORACLE:
            if not r.get("crashed"):
                oracle.setdefault(r["controller"], []).append(rmse)
            continue
        pos = ((models_by_name.get(r["model"]) or {}).get("rollout_100") or {}).get("position")
        if pos is None:
            unmatched.add(r["model"])
            continue
        points.append(Point(r["model"], r["controller"], r["scenario"], float(pos), float(rmse),
                            bool(r.get("crashed"))))
    oracle_median = {c: median_or_none(v) for c, v in sorted(oracle.items(), key=lambda kv: controller_key(kv[0]))}
    corr = {}
    for c in sorted({p.controller for p in points}, key=controller_key):
        ok = [p for p in points if p.controller == c and not p.crashed]
        corr[c] = (spearman([p.open_loop_m for p in ok], [p.rmse_m for p in ok]), len(ok))
    per_scenario: dict[str, dict] = {}
    for c in corr:
        for sc in sorted({p.scenario for p in points if p.controller == c}):
            ok = [p for p in points if p.controller == c and p.scenario == sc and not p.crashed]
            rho = spearman([p.open_loop_m for p in ok], [p.rmse_m for p in ok]) if len(ok) >= 3 else None
            if rho is not None:
                per_scenario.setdefault(c, {})[sc] = rho
    return Headline(points, oracle_median, corr, sorted(unmatched), per_scenario)


def correlation_text(h: Headline) -> str:
    """One sentence giving the Spearman correlation per controller (or why there is none)."""
    if not h.correlation:
        return "No closed-loop run of a learned model has both an open-loop and a closed-loop error."
    parts = []
    for c, (rho, n) in h.correlation.items():
        parts.append(f"{controller_label(c)} {rho:+.2f} (n = {n})" if rho is not None
                     else f"{controller_label(c)} undefined (n = {n}; fewer than 3 runs or no spread)")
    text = ("Spearman rank correlation between 100-step open-loop position MAE and closed-loop position RMSE, "
            "over the non-crashed runs of the learned models, all scenarios pooled: " + "; ".join(parts) + ".")
    per = []
    for c, rhos in h.per_scenario.items():
        v = sorted(rhos.values())
        med = v[len(v) // 2] if len(v) % 2 else 0.5 * (v[len(v) // 2 - 1] + v[len(v) // 2])
        per.append(f"{controller_label(c)}: median {med:+.2f} over {len(v)} scenarios, "
                   f"positive in {sum(x > 0 for x in v)}, from {v[0]:+.2f} to {v[-1]:+.2f}")
    if per:
        text += (" Within one scenario (across models, so that scenario difficulty cancels): " + "; ".join(per) + ".")
    return text
