"""The report's section on the three command levels side by side (``levels.json`` of ``pinnmpc levels``)."""

from __future__ import annotations

from ..tables import MISSING, md_table
from .versus import mm_ci, study_head

#: Shown when the results folder has no levels.json.
NO_LEVELS = ("No `levels.json` in this folder: `pinnmpc levels` flies the nominal model (and the oracle where it "
             "exists) at the wrench, ctbr and ctatt levels on each plant (about 10 minutes on two cores) and "
             "writes a copy into `models/levels/`, which the next `pinnmpc run` copies here.")


def _times(v) -> str:
    return "" if v is None else f" ({v:.2f}×)"


def levels_section(levels: dict | None) -> str:
    """Markdown: where the numbers come from, then one table per plant with a row per level and model."""
    if levels is None:
        return NO_LEVELS
    head = (study_head(levels, "pinnmpc levels") + " per row: median position RMSE "
            f"in mm with its bootstrap 95 % interval, crashes, and the median over the members of each run's median "
            f"solve time; at ctbr and ctatt, in brackets, each as a multiple of the wrench level's. At ctbr the "
            f"controller sends thrust and body rates, at ctatt thrust, roll, pitch and a yaw rate; the vehicle's "
            f"inner loop turns them into torques. The oracle exists at those levels only on our plant's nominal "
            f"set-up, whose inner loop it steps exactly.")
    parts = [head]
    for p in levels["plants"].values():
        rows = []
        for r in p["rows"]:
            s = r["ensemble"]
            solve = r.get("solve_ms_median")
            rows.append([r["level"], r["model"], mm_ci(s) + _times(r.get("rmse_vs_wrench")),
                         f"{s['crashes']}/{s['runs']}",
                         (MISSING if solve is None else f"{solve:.1f}") + _times(r.get("solve_vs_wrench"))])
        parts.append(f"**{p['label']}** (`{p['vehicle']}`, `{p['scenario']}`):\n\n"
                     + md_table(["level", "model", "RMSE (mm)", "crashes", "SQP median solve (ms)"], rows))
    return "\n\n".join(parts)
