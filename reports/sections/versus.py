"""The report's section on learned models against the nominal equations (``versus.json`` of ``pinnmpc versus``)."""

from __future__ import annotations

from ..tables import MISSING, fmt, md_table

#: Shown when the results folder has no versus.json.
NO_VERSUS = ("No `versus.json` in this folder: `pinnmpc versus` flies the models trained on plants with unmodelled "
             "physics against the nominal equations (about an hour on two cores) and writes a copy into "
             "`models/versus/`, which the next `pinnmpc run` copies here.")


def mm_ci(s: dict) -> str:
    """An ensemble's median RMSE in mm with its bootstrap interval (``–`` without a median)."""
    if s.get("median") is None:
        return MISSING
    ci = s.get("median_ci95")
    return f"{1e3 * s['median']:.1f}" + ("" if not ci else f" ({1e3 * ci[0]:.1f}–{1e3 * ci[1]:.1f})")


def pct_ci(v: dict | None) -> str:
    """An improvement over the nominal equations in % with its interval (``–`` without one)."""
    if v is None:
        return MISSING
    lo, hi = v["fraction_ci95"]
    return f"{100 * v['fraction']:+.0f} % ({100 * lo:+.0f} to {100 * hi:+.0f})"


def verdict_text(p: dict, goal: float) -> str:
    """One sentence on a plant's best learned model against the goal."""
    v = p.get("verdict")
    if v is None:
        return "No learned model flew every member without a crash, so none is weighed against the nominal equations."
    lo, hi = v["fraction_ci95"]
    apart = "the two medians' intervals are apart" if v["apart"] else "the two medians' intervals overlap"
    if v["met"]:
        tail = f"the {100 * goal:.0f} % goal is met"
    else:
        tail = (f"the {100 * goal:.0f} % goal is missed" +
                (f" by {100 * (goal - v['fraction']):.0f} points" if v["fraction"] < goal else ""))
    return (f"Best learned model: `{v['best']}`, {100 * v['fraction']:.0f} % below the nominal equations' RMSE "
            f"(bootstrap 95 % {100 * lo:.0f} to {100 * hi:.0f} %); {apart}; {tail}.")


def study_head(study: dict, command: str) -> str:
    """The opening of a flown study's section: its command, date, runs and minutes, its scenario, controller and
    members ("... from N ensemble members"; the caller goes on)."""
    return (f"From `{study.get('command', command)}` ({study.get('date', 'undated')}, "
            f"{study.get('runs', MISSING)} closed-loop runs in {fmt(study.get('wall_time_s', 0) / 60, '.0f')} min), "
            f"copied into this folder by `pinnmpc run`. `{study['scenario']}` with the "
            f"{study['controller'].upper()} from {study['members']} ensemble members")


def versus_section(versus: dict | None) -> str:
    """Markdown: where the numbers come from, one table and one verdict per plant."""
    if versus is None:
        return NO_VERSUS
    head = (study_head(versus, "pinnmpc versus") + ": median position RMSE in mm "
            f"with its bootstrap 95 % interval, and the improvement over the nominal equations "
            f"(1 − median / nominal median) with its own. The maximum trackable speed climbs the figure-8 speed "
            f"ladder ({versus['ladder_members']} members per rung): the fastest rung without a crash and with a "
            f"median RMSE within {fmt(1e3 * versus['ladder']['rmse_bound_m'], '.0f')} mm.")
    parts = [head]
    for p in versus["plants"].values():
        rows = []
        for name, r in p["models"].items():
            s = r["ensemble"]
            sp = r["ladder"]["max_speed"]["speed_mps"]
            rows.append([f"`{name}`", r.get("architecture") or MISSING,
                         ", ".join(r.get("extra_states") or []) or "none", mm_ci(s),
                         f"{s['crashes']}/{s['runs']}", pct_ci(r.get("versus_nominal")),
                         MISSING if sp is None else f"{sp:.2f}"])
        parts.append(f"**{p['label']}** (`{p['scenario']}`)")
        parts.append(md_table(["model", "architecture", "extra states", "RMSE, mm (95 %)", "crashes",
                               "against nominal (95 %)", "max speed, m/s"], rows))
        parts.append(verdict_text(p, versus["goal"]))
    return "\n\n".join(parts)
