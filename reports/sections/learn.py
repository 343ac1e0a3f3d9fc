"""The report's section on learning from flown flights (``learn_<plant>.json`` of ``pinnmpc learn``)."""

from __future__ import annotations

from pathlib import Path

from scenarios.studies.versus import WIN_FRACTION

from ..figures import STYLE, FigureOut, _save
from ..tables import MISSING, fmt, md_table
from .versus import mm_ci, pct_ci

#: Shown when the results folder has no learning study.
NO_LEARN = ("No `learn_<plant>.json` in this folder: `pinnmpc learn --plant highfi|rotorpy|crazyflie --publish` "
            "flies, learns from its flights and flies again (30-40 minutes per plant on two cores), and writes a copy "
            "into `models/learn/`, which the next `pinnmpc run` copies here.")


def goal_mm(study: dict) -> float | None:
    """The goal's RMSE, mm: the nominal equations' median on the evaluation times one minus the goal fraction."""
    ev = study["evaluation"]
    nominal = ev["models"].get("nominal", {}).get("ensemble", {}).get("median")
    if nominal is None:
        return None
    return 1e3 * (1.0 - (ev.get("verdict") or {}).get("goal", WIN_FRACTION)) * nominal


def verdict_sentence(study: dict) -> str:
    """One sentence on the final model against the goal, with its numbers."""
    ev = study["evaluation"]
    v = ev.get("verdict")
    if v is None:
        return "The final model or the nominal equations lack two members with an RMSE: no verdict."
    nominal = ev["models"]["nominal"]["ensemble"]["median"]
    final = ev["models"][v["model"]]["ensemble"]["median"]
    lo, hi = v["fraction_ci95"]
    ladder = ("its fastest ladder rung is at least the nominal equations'" if v["ladder_ok"] else
              f"it loses speed on the ladder ({fmt(v['max_speed_mps'], '.2f')} against "
              f"{fmt(v['nominal_max_speed_mps'], '.2f')} m/s)")
    return (f"Final model `{v['model']}`: {1e3 * final:.1f} mm against {1e3 * nominal:.1f} mm, "
            f"{100 * v['fraction']:.0f} % better (95 % {100 * lo:.0f} to {100 * hi:.0f} %); the goal, "
            f"{100 * v['goal']:.0f} % or {goal_mm(study):.1f} mm with the intervals apart, is "
            f"{'met' if v['met'] else 'missed'}; the medians' intervals are {'apart' if v['apart'] else 'overlapping'}"
            f"; {ladder}.")


def _members(settings: dict) -> str:
    """How many ensemble members a study flew: the evaluation's, the curve's middle rows' and the ladder's."""
    m = settings["members"]
    between = min(settings.get("curve_members", m), m)
    text = f"{m} members" + (f" ({between} for the models between)" if between < m and settings.get("iterations", 1) > 1
                             else "")
    return text + (f", {settings['ladder_members']} per ladder rung" if "ladder_members" in settings else "")


def learning_figure(studies: dict, run_dir: Path) -> FigureOut | None:
    """Median RMSE on figure8-fast against iteration and against minutes of flight, one line per plant."""
    import matplotlib.pyplot as plt

    if not studies:
        return None
    with plt.rc_context(STYLE):
        fig, axes = plt.subplots(1, 2, figsize=(8.0, 3.2), sharey=True)
        for k, (plant, st) in enumerate(sorted(studies.items())):
            color = f"C{k}"
            rows = [r for r in st["curve"] if r["ensemble"]["median"] is not None]
            for ax, xkey in zip(axes, ("iteration", "flight_minutes")):
                xs = [r[xkey] for r in rows]
                ys = [1e3 * r["ensemble"]["median"] for r in rows]
                lo = [y - 1e3 * (r["ensemble"]["median_ci95"] or [r["ensemble"]["median"]] * 2)[0]
                      for y, r in zip(ys, rows)]
                hi = [1e3 * (r["ensemble"]["median_ci95"] or [r["ensemble"]["median"]] * 2)[1] - y
                      for y, r in zip(ys, rows)]
                ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", color=color, capsize=3, label=plant)
                goal = goal_mm(st)
                if goal is not None:
                    ax.axhline(goal, color=color, ls=":", lw=1)
                best = [m for m, role in st["evaluation"]["roles"].items() if role == "best open-loop model"]
                if best and st["evaluation"]["models"][best[0]]["ensemble"]["median"] is not None:
                    ax.axhline(1e3 * st["evaluation"]["models"][best[0]]["ensemble"]["median"], color=color, ls="--",
                               lw=1)
        axes[0].set_xlabel("iteration (0: the nominal equations)")
        axes[1].set_xlabel("minutes of flight learned from")
        axes[0].set_ylabel("figure8-fast RMSE, mm (median, 95 %)")
        axes[0].legend()
        rel = _save(fig, run_dir, "learning_curve")
    return FigureOut(rel, "learning curve",
                     "Median position RMSE on the held-out `figure8-fast` (ensemble members, bootstrap 95 %) of each "
                     "iteration's model, against the iteration and against the minutes of flown data it learned "
                     "from. Dotted: the goal (half the nominal equations' RMSE, iteration 0); dashed: the plant's "
                     "best model trained on open-loop excitation.")


def learn_section(studies: dict | None, run_dir: Path, figure_md) -> str:
    """Markdown: per plant, the learning curve, the evaluation table and the verdict; the figure."""
    if not studies:
        return NO_LEARN
    parts = ["From `pinnmpc learn` (published into `models/learn/`, copied here by `pinnmpc run`). Each iteration "
             "trains physics plus network with the rotor speeds as states (and, where the study says so below, the "
             "aerodynamic terms its flights select) on every flight flown so far (random "
             "min-snap paths and orbits at 1-3 m/s, perturbed, with input dither; never a figure-8), and its model "
             "flies the next iteration's references. The controls are trained the same way on the same minutes of "
             "open-loop excitation, and (an upper bound only) on the final model's flights plus flights of "
             "`figure8-fast` itself."]
    f = learning_figure(studies, run_dir)
    if f is not None:
        parts.append(figure_md(f))
    for plant, st in sorted(studies.items()):
        ev = st["evaluation"]
        level = st.get("level", "wrench")
        at = "" if level == "wrench" else (f", at the `{level}` level (the level's nominal model plus a network on "
                                           f"the rates and the velocity"
                                           + ("" if "openloop" in (st.get("controls") or {}) else
                                              "; no open-loop control") + ")")
        parts.append(f"**{ev['label']}**{at} (`{ev['scenario']}`; {_members(st['settings'])}, "
                     f"{fmt(st.get('study_seconds', st['wall_time_s']) / 60, '.0f')} min on two cores, "
                     f"{st.get('date', 'undated')})")
        rows = [[r["iteration"], f"`{r['model']}`", r["flights"], fmt(r["flight_minutes"], ".1f"),
                 mm_ci(r["ensemble"]), f"{r['ensemble']['crashes']}/{r['ensemble']['runs']}"] for r in st["curve"]]
        parts.append(md_table(["iteration", "model", "flights learned from", "minutes", "RMSE, mm (95 %)",
                               "crashes"], rows))
        rows = []
        for name, r in ev["models"].items():
            sp = None if r.get("ladder") is None else r["ladder"]["max_speed"]["speed_mps"]
            rows.append([f"`{name}`", ev["roles"].get(name, MISSING), mm_ci(r["ensemble"]),
                         f"{r['ensemble']['crashes']}/{r['ensemble']['runs']}", pct_ci(r.get("versus_nominal")),
                         MISSING if sp is None else f"{sp:.2f}"])
        parts.append(md_table(["model", "role", "RMSE, mm (95 %)", "crashes", "against nominal (95 %)",
                               "max speed, m/s"], rows))
        parts.append(verdict_sentence(st))
        terms = aero_sentence(st)
        if terms:
            parts.append(terms)
    return "\n\n".join(parts)


def aero_sentence(st: dict) -> str | None:
    """The final model's aerodynamic terms (each coefficient trained, and identified with its 95 % interval before
    training), or that the selection claimed none; None for a study trained without the term library."""
    trainings = st.get("trainings", [])
    final = [t for t in trainings if t.get("name") == st.get("final_model")] or trainings[-1:]
    if not final or "aero" not in final[0]:
        return None
    a = final[0]["aero"]
    if not a["terms"]:
        return (f"Aerodynamic terms of `{final[0]['name']}`: the selection claimed none (validation error "
                f"{fmt(a['validation_rmse_none'], '.3f')} m/s² with none).")

    def interval(i):
        if i["low"] is None or i["high"] is None:      # one training flight: the jackknife has no spread
            return "no interval"
        return f"95 % {fmt(i['low'], '.4g')}–{fmt(i['high'], '.4g')}"

    coefs = ", ".join(f"{c} {fmt(v, '.4g')} {a['units'][c]} (identified {fmt(a['identified'][c]['value'], '.4g')}, "
                      f"{interval(a['identified'][c])})" for c, v in a["coefficients"].items())
    return (f"Aerodynamic terms of `{final[0]['name']}` ({', '.join(a['terms'])}; selected on its validation flights, "
            f"one-step acceleration error {fmt(a['validation_rmse_none'], '.3f')} → {fmt(a['validation_rmse'], '.3f')} "
            f"m/s²): {coefs}.")
