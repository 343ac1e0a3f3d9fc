"""The generated summary: counts and medians computed from ``results.json`` only."""

from __future__ import annotations

from ..labels import controller_key, controller_label, model_key, scenario_key, sorted_unique
from ..stats import median_or_none
from ..tables import RMSE_FORMAT, fmt


def _names(xs) -> str:
    return ", ".join(xs) if xs else "none"


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def controller_outcomes(runs: list[dict], controller: str) -> dict:
    """Which models flew every scenario of ``controller`` without a crash.

    Parameters
    ----------
    runs : list of dict
        Closed-loop results.
    controller : str
        Controller name.

    Returns
    -------
    dict
        ``scenarios`` (those flown with the controller, report order),
        ``clean`` (models run on every one of them, never crashed, never
        failed to start), ``failed`` (models that crashed or could not start at
        least once), ``partial`` (models neither failed nor run on every
        scenario), ``n_runs``, ``median_rmse_m`` (median RMSE over the runs
        without crash or error, m, or None) and ``n_median``.
    """
    sel = [r for r in runs if r["controller"] == controller]
    scenarios = sorted_unique((r["scenario"] for r in sel), scenario_key)
    models = sorted_unique((r["model"] for r in sel), model_key)
    clean, failed, partial = [], [], []
    for m in models:
        mine = [r for r in sel if r["model"] == m]
        if any(r.get("error") or r.get("crashed") for r in mine):
            failed.append(m)
        elif {r["scenario"] for r in mine} == set(scenarios):
            clean.append(m)
        else:
            partial.append(m)
    ok = [r.get("rmse_position_m") for r in sel if not r.get("error") and not r.get("crashed")]
    ok = [v for v in ok if v is not None]
    return {"scenarios": scenarios, "clean": clean, "failed": failed, "partial": partial, "n_runs": len(sel),
            "median_rmse_m": median_or_none(ok), "n_median": len(ok)}


def summary_text(runs: list[dict], correlation: str | None = None) -> str:
    """The summary section body (Markdown).

    Parameters
    ----------
    runs : list of dict
        Closed-loop results in report order.
    correlation : str, optional
        A sentence on the open-loop / closed-loop rank correlation, appended.
    """
    n = len(runs)
    errors = [r for r in runs if r.get("error")]
    crashed = [r for r in runs if not r.get("error") and r.get("crashed")]
    lines = [f"- Runs: {n} (crashed: {len(crashed)}; could not start: {len(errors)}; "
             f"flew to the end: {n - len(crashed) - len(errors)})."]
    if not runs:
        return lines[0] + "\n\nNo closed-loop runs to summarize."
    scen = sorted_unique((r["scenario"] for r in runs), scenario_key)
    ctrls = sorted_unique((r["controller"] for r in runs), controller_key)
    models = sorted_unique((r["model"] for r in runs), model_key)
    lines.append(f"- Scenarios ({len(scen)}): {_names(scen)}. Controllers: "
                 f"{_names([controller_label(c) for c in ctrls])}. Models: {_names(models)}.")
    for c in ctrls:
        o = controller_outcomes(runs, c)
        s = (f"- {controller_label(c)}: {_count(o['n_runs'], 'run')} over {_count(len(o['scenarios']), 'scenario')}. "
             f"Flew every one of its scenarios without a crash: {_names(o['clean'])}. "
             f"Crashed or could not start at least once: {_names(o['failed'])}.")
        if o["partial"]:
            s += f" Not run on every scenario: {_names(o['partial'])}."
        s += (f" Median RMSE over its {_count(o['n_median'], 'run')} without crash or error: "
              f"{fmt(o['median_rmse_m'], RMSE_FORMAT)} m." if o["n_median"] else
              " No run without crash or error, so no median RMSE.")
        lines.append(s)
    for r in crashed:
        t = r.get("crash_time_s")
        lines.append(f"- Crash: {r['scenario']} / {controller_label(r['controller'])} / {r['model']}"
                     + (f" at {fmt(t, '.2f')} s" if t is not None else "")
                     + (f" ({r['crash_reason']})" if r.get("crash_reason") else "") + ".")
    for r in errors:
        lines.append(f"- Could not start: {r['scenario']} / {controller_label(r['controller'])} / "
                     f"{r['model']}: {' '.join(str(r['error']).split())}")
    text = "\n".join(lines)
    if correlation:
        text += "\n\n" + correlation
    return text
