"""The report's figures (matplotlib, Agg backend), written as PNG to ``run_dir/figures``.

Each function draws one figure from parsed results and returns a
:class:`FigureOut` (file path relative to the results folder, alt text,
generated caption), or None when there is nothing to draw.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)
import numpy as np  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402

from scenarios.closed_loop.metrics import position_errors  # noqa: E402

from .headline import Headline  # noqa: E402
from .labels import (BASE_SCENARIOS, DT_S, ORACLE, base_scenario, controller_key,  # noqa: E402
                     controller_label, model_key, sorted_unique)
from .tables import fmt, solve_time_rows  # noqa: E402

#: Resolution of the PNG files, dots per inch.
DPI = 110
#: Folder of the figures inside the results folder.
FIG_DIR = "figures"
#: Marker per base scenario in the headline figure (others: diamond).
SCENARIO_MARKERS = {"hover": "o", "figure8-slow": "s", "figure8-fast": "^"}
#: Colour per controller (others: grey).
CONTROLLER_COLORS = {"nmpc": "tab:blue", "sqp": "tab:purple", "ltv": "tab:orange", "lqr": "tab:green"}
#: Floor of log-scaled errors, m (an error of exactly 0 is drawn here).
LOG_FLOOR_M = 1e-5
#: rc settings of every figure.
STYLE = {"font.size": 9, "axes.titlesize": 10, "axes.labelsize": 9, "legend.fontsize": 8,
         "axes.grid": True, "grid.alpha": 0.3, "figure.dpi": DPI}


@dataclass(frozen=True)
class FigureOut:
    """A written figure.

    Attributes
    ----------
    path : str
        Path relative to the results folder, ``figures/<name>.png``.
    alt : str
        Short description (Markdown alt text).
    caption : str
        Generated caption (Markdown).
    """

    path: str
    alt: str
    caption: str


def _save(fig, run_dir: Path, name: str) -> str:
    rel = f"{FIG_DIR}/{name}.png"
    (run_dir / FIG_DIR).mkdir(parents=True, exist_ok=True)
    fig.savefig(run_dir / rel, dpi=DPI, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    return rel


def log_ticks(ax, which: str = "y") -> None:
    """Readable ticks on a log axis: 1..9, or 1, 2, 5, or 1 per decade by the span; plain numbers."""
    axis = ax.yaxis if which == "y" else ax.xaxis
    lo, hi = (ax.get_ylim() if which == "y" else ax.get_xlim())
    decades = np.log10(max(hi, 1e-300) / max(lo, 1e-300))
    subs = tuple(float(k) for k in range(1, 10)) if decades < 1.2 else (1.0, 2.0, 5.0) if decades < 4 else (1.0,)
    axis.set_major_locator(LogLocator(base=10.0, subs=subs))
    axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def _log_limits(values, pad: float = 1.6) -> tuple[float, float]:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x) and x > 0], dtype=float)
    return float(v.min() / pad), float(v.max() * pad)


def controller_color(c: str) -> str:
    """Colour of a controller."""
    return CONTROLLER_COLORS.get(c, "tab:gray")


def model_colors(models) -> dict:
    """Colour per model name: the oracle black, the others from ``tab10`` in sorted order."""
    names = sorted({str(m) for m in models}, key=model_key)
    cmap = plt.get_cmap("tab10" if len(names) <= 11 else "tab20")
    out, i = {}, 0
    for m in names:
        if m == ORACLE:
            out[m] = "black"
        else:
            out[m] = cmap(i % cmap.N)
            i += 1
    return out


def safe_name(text: str) -> str:
    """``text`` reduced to a file-name-safe slug."""
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in str(text))


def headline_figure(h: Headline, run_dir: Path) -> FigureOut | None:
    """Log-log scatter of 100-step open-loop position MAE (m) against closed-loop RMSE (m)."""
    if not h.points:
        return None
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(8.0, 5.2))
        any_variant = any_crash = False
        for p in h.points:
            if p.crashed:
                any_crash = True
                ax.scatter(p.open_loop_m, p.rmse_m, marker="x", s=60, color="red", linewidths=2, zorder=4)
                continue
            variant = p.scenario != base_scenario(p.scenario)
            any_variant |= variant
            col = controller_color(p.controller)
            ax.scatter(p.open_loop_m, p.rmse_m, marker=SCENARIO_MARKERS.get(base_scenario(p.scenario), "D"), s=36,
                       facecolors="none" if variant else col, edgecolors=col, linewidths=1.2, zorder=3)
        handles = []
        for c in sorted({p.controller for p in h.points if not p.crashed}, key=controller_key):
            col = controller_color(c)
            handles.append(Line2D([], [], ls="", marker="o", color=col, label=controller_label(c)))
        for c, med in h.oracle_median_m.items():
            if med is not None:
                ax.axhline(med, color=controller_color(c), ls="--", lw=1.2, zorder=2)
                handles.append(Line2D([], [], color=controller_color(c), ls="--",
                                      label=f"oracle, {controller_label(c)}: median RMSE {med:.3g} m"))
        bases = sorted({base_scenario(p.scenario) for p in h.points if not p.crashed},
                       key=lambda b: (BASE_SCENARIOS.index(b) if b in BASE_SCENARIOS else len(BASE_SCENARIOS), b))
        for b in bases:
            handles.append(Line2D([], [], ls="", marker=SCENARIO_MARKERS.get(b, "D"), color="dimgray", label=b))
        if any_variant:
            handles.append(Line2D([], [], ls="", marker="o", markerfacecolor="none", color="dimgray",
                                  label="variant (+highfi, +wind, ...)"))
        if any_crash:
            handles.append(Line2D([], [], ls="", marker="x", color="red", markeredgewidth=2, markersize=7,
                                  label="crashed (RMSE up to the crash)"))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(*_log_limits([p.open_loop_m for p in h.points]))
        ax.set_ylim(*_log_limits([p.rmse_m for p in h.points] + list(h.oracle_median_m.values()), 1.3))
        log_ticks(ax, "x")
        log_ticks(ax, "y")
        for m in sorted({p.model for p in h.points}, key=model_key):
            x = next(p.open_loop_m for p in h.points if p.model == m)
            ax.axvline(x, color="lightgray", lw=0.8, ls=":", zorder=1)
            ax.text(x, 1.01, m, transform=ax.get_xaxis_transform(), rotation=45, ha="left", va="bottom", fontsize=8)
        ax.set_xlabel("100-step (1 s) open-loop position MAE of the model (m)")
        ax.set_ylabel("closed-loop position RMSE of the run (m)")
        ax.set_title("Open-loop error against closed-loop error", pad=42)
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
        rel = _save(fig, run_dir, "headline")
    n_crash = sum(p.crashed for p in h.points)
    cap = (f"{len(h.points)} closed-loop runs of learned models ({n_crash} crashed, drawn as red crosses at the "
           f"RMSE up to the crash). Colour: controller; marker: base scenario (hollow: a variant). "
           f"Dashed lines: median RMSE of the oracle (true equations) per controller.")
    if h.unmatched:
        cap += f" Not drawn (not in `evaluation.json`): {', '.join(h.unmatched)}."
    return FigureOut(rel, "open-loop 100-step position MAE against closed-loop position RMSE", cap)


def _position_error(tr: dict) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        e = position_errors(tr["x"], tr["x_ref"])
    return np.where(np.isfinite(e), np.maximum(e, LOG_FLOOR_M), np.nan)


def trajectory_figures(inputs, run_dir: Path, colors: dict | None = None,
                       jobs: int | None = None) -> tuple[list[FigureOut], list[str]]:
    """One figure per base scenario: horizontal path, height and position error of every run.

    Rows are controllers; columns the path (east y against north x, m, equal
    aspect), the height h = -z (m) against time (s) and the position error
    (m, log) against time (s) from the first control period on. Only runs of
    the base scenario itself are drawn. ``colors`` maps model name to colour
    (default: :func:`model_colors` of the runs' models). The figures are
    drawn by ``jobs`` processes (default: up to 2, by the CPUs; 1: in this
    process); each is the same file either way.

    Returns
    -------
    figures : list of FigureOut
    notes : list of str
        Sentences about what could not be drawn.
    """
    figs, notes, skipped = [], [], []
    present = sorted_unique((r["scenario"] for r in inputs.runs), lambda s: (s not in BASE_SCENARIOS, s))
    bases = [b for b in BASE_SCENARIOS if b in present]
    colors = colors or model_colors([r["model"] for r in inputs.runs])
    todo = []
    for base in bases:
        rows = {}
        for r in inputs.runs:
            if r["scenario"] != base:
                continue
            tr, why = (None, "could not start") if r.get("error") else inputs.trace(r)
            if tr is None:
                skipped.append(f"{r['scenario']} / {controller_label(r['controller'])} / {r['model']} ({why})")
                continue
            rows.setdefault(r["controller"], []).append((r, tr))
        if rows:
            todo.append((base, rows))
    for (base, rows), rel in zip(todo, _draw_all(todo, run_dir, colors, jobs)):
        ctrls = sorted(rows, key=controller_key)
        n = sum(len(v) for v in rows.values())
        cap = (f"Scenario {base}: {n} runs, one row per controller ({', '.join(controller_label(c) for c in ctrls)}). "
               f"Left: horizontal path (north x against east y, NED); middle: height h = -z; right: position "
               f"error (errors below {LOG_FLOOR_M * 1e6:g} µm drawn at {LOG_FLOOR_M * 1e6:g} µm). "
               f"Dashed grey: reference; "
               f"grey plus: its final point. A red cross marks the last state of a crashed run.")
        figs.append(FigureOut(rel, f"trajectories, height and position error, {base}", cap))
    if skipped:
        notes.append("Runs without a usable trace are not drawn: " + "; ".join(skipped) + ".")
    others = [s for s in present if s not in BASE_SCENARIOS]
    if others:
        notes.append("Variant scenarios are not drawn here (their numbers are in the closed-loop table): "
                     + ", ".join(sorted_unique(others, lambda s: s)) + ".")
    if not figs:
        notes.insert(0, "No run of a base scenario (" + ", ".join(BASE_SCENARIOS) + ") has a usable trace, "
                     "so there are no trajectory figures.")
    return figs, notes


#: Fewest trajectory figures worth a process pool (starting one costs about 0.5 s; a figure about 1 s).
POOL_MIN_FIGURES = 4


def _draw_all(todo, run_dir: Path, colors: dict, jobs: int | None) -> list[str]:
    """The relative paths of the trajectory figures of ``todo`` (``(base, rows)`` pairs), drawn in order."""
    import os

    jobs = min(2, os.cpu_count() or 1) if jobs is None else jobs
    if jobs < 2 or len(todo) < POOL_MIN_FIGURES:
        return [_trajectory_figure(base, rows, run_dir, colors) for base, rows in todo]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # Forked workers: the figures' data are already in memory, and nothing here holds a lock a child could need.
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("fork")) as pool:
        return list(pool.map(_trajectory_figure, *zip(*todo), [run_dir] * len(todo), [colors] * len(todo)))


def _trajectory_figure(base: str, rows: dict, run_dir: Path, colors: dict) -> str:
    """Draw and save one scenario's trajectory figure (see :func:`trajectory_figures`); its relative path."""
    ctrls = sorted(rows, key=controller_key)
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, axes = plt.subplots(len(ctrls), 3, figsize=(14.0, 3.9 * len(ctrls)), squeeze=False,
                                 gridspec_kw={"width_ratios": [1.0, 1.3, 1.3]})
        for i, c in enumerate(ctrls):
            ax_p, ax_h, ax_e = axes[i]
            ref = max(rows[c], key=lambda rt: len(rt[1]["t"]))[1]
            ax_p.plot(ref["x_ref"][:, 1], ref["x_ref"][:, 0], color="gray", ls="--", lw=1.5, label="reference")
            ax_p.plot(ref["x_ref"][-1, 1], ref["x_ref"][-1, 0], "P", color="gray", ms=8, mfc="none", zorder=5)
            ax_h.plot(ref["t"], -ref["x_ref"][:, 2], color="gray", ls="--", lw=1.5, label="reference")
            for r, tr in rows[c]:
                col, t, x = colors[r["model"]], tr["t"], tr["x"]
                crashed = bool(r.get("crashed"))
                lab = r["model"] + (" (crashed)" if crashed else "")
                ax_p.plot(x[:, 1], x[:, 0], color=col, lw=1.1, label=lab)
                ax_h.plot(t, -x[:, 2], color=col, lw=1.1, label=lab)
                ax_e.plot(t[1:], _position_error(tr)[1:], color=col, lw=1.1, label=lab)
                if crashed:
                    fin = np.flatnonzero(np.all(np.isfinite(x[:, 0:3]), axis=1))
                    if len(fin):
                        k = fin[-1]
                        ax_p.plot(x[k, 1], x[k, 0], "x", color="red", ms=9, mew=2)
                        ax_h.plot(t[k], -x[k, 2], "x", color="red", ms=9, mew=2)
                        ax_e.plot(t[k], _position_error(tr)[k], "x", color="red", ms=9, mew=2)
            ax_p.set_aspect("equal", adjustable="datalim")
            ax_p.set_xlabel("east y (m)")
            ax_p.set_ylabel("north x (m)")
            ax_p.set_title(f"{base}, {controller_label(c)}: horizontal path")
            ax_h.set_xlabel("time (s)")
            ax_h.set_ylabel("height h = -z (m)")
            ax_h.set_title(f"{base}, {controller_label(c)}: height")
            ax_e.set_yscale("log")
            ax_e.set_xlabel("time (s)")
            ax_e.set_ylabel("position error |p - p_ref| (m)")
            ax_e.set_title(f"{base}, {controller_label(c)}: position error")
            ax_h.legend(loc="best")
        fig.tight_layout()
        return _save(fig, run_dir, f"trajectories_{safe_name(base)}")


def rollout_figure(evaluation: dict, run_dir: Path, colors: dict | None = None) -> FigureOut | None:
    """Position MAE (m, log) against rollout step, one line per model (``position_by_step``).

    ``colors`` maps model name to colour (default: :func:`model_colors` of the models).
    """
    models = [m for m in evaluation.get("models", [])
              if isinstance(m, dict) and isinstance((m.get("rollout_100") or {}).get("position_by_step"), list)
              and len(m["rollout_100"]["position_by_step"]) > 0]
    if not models:
        return None
    colors = colors or model_colors([m.get("name", "?") for m in models])
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(7.5, 4.6))
        horizon = 0
        for m in sorted(models, key=lambda m: model_key(m.get("name", "?"))):
            y = np.asarray(m["rollout_100"]["position_by_step"], dtype=float)
            k = np.arange(1, len(y) + 1)
            horizon = max(horizon, len(y))
            ax.plot(k, np.maximum(y, LOG_FLOOR_M), color=colors[m.get("name", "?")],
                    ls="--" if m.get("regime") == "aggressive" else "-", lw=1.5,
                    label=f"{m.get('name', '?')} ({m.get('regime', '?')} regime)")
        ax.set_yscale("log")
        ax.set_xlim(0, horizon + 1)
        log_ticks(ax, "y")
        ax.set_xlabel(f"rollout step k (1 step = dt = {DT_S:g} s; step {horizon} = {horizon * DT_S:g} s)")
        ax.set_ylabel("position MAE (m)")
        top = ax.secondary_xaxis("top", functions=(lambda k: k * DT_S, lambda t: t / DT_S))
        top.set_xlabel("time since the rollout start (s)")
        ax.set_title("Open-loop rollout error growth", y=1.14)
        ax.legend(loc="best")
        rel = _save(fig, run_dir, "rollout_growth")
    return FigureOut(rel, "open-loop position MAE against rollout step",
                     f"Mean absolute position error of {len(models)} models' autoregressive rollouts on their test "
                     f"split, by step (dashed: trained on the aggressive regime).")


def fisher_figure(fisher: dict, run_dir: Path) -> FigureOut | None:
    """Eigenvalues of the Fisher information (log) per case, ascending."""
    cases = [c for c in fisher.get("cases", []) if isinstance(c, dict) and isinstance(c.get("eigenvalues"), list)
             and len(c["eigenvalues"]) > 0]
    if not cases:
        return None
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(7.5, 4.6))
        markers = ("o", "s", "^", "D", "v", "P", "X", "*")
        cmap = plt.get_cmap("tab10")
        dropped, parts = [], []
        for i, c in enumerate(cases):
            ev = np.sort(np.asarray(c["eigenvalues"], dtype=float))
            name = f"{c.get('regime', '?')} / {c.get('inputs', '?')}"
            if np.any(~(ev > 0)):
                dropped.append(f"{name} ({int(np.sum(~(ev > 0)))})")
            k = np.arange(1, len(ev) + 1)
            lab = f"{name}: rank {fmt(c.get('rank'), 'd')}/{len(ev)}, condition {fmt(c.get('condition_number'), '.2g')}"
            ax.plot(k + 0.06 * (i - (len(cases) - 1) / 2), np.where(ev > 0, ev, np.nan), marker=markers[i % 8],
                    color=cmap(i % 10), lw=1.0, label=lab)
            parts.append(f"{name}: rank {fmt(c.get('rank'), 'd')} of {len(ev)}, condition number "
                         f"{fmt(c.get('condition_number'), '.3g')}")
        ax.set_yscale("log")
        n = max(len(c["eigenvalues"]) for c in cases)
        ax.set_xticks(np.arange(1, n + 1))
        ax.set_xlabel("eigenvalue index (ascending)")
        coords = (fisher.get("settings") or {}).get("coordinates")
        ax.set_ylabel("Fisher information eigenvalue" + (" (relative coordinates)" if coords else ""))
        ax.set_title("Fisher information spectrum per regime and input channel")
        ax.legend(loc="best")
        rel = _save(fig, run_dir, "fisher_spectrum")
    cap = "Eigenvalues of the Fisher information of the six parameters. " + "; ".join(parts) + "."
    if dropped:
        cap += " Eigenvalues <= 0 are not drawn: " + ", ".join(dropped) + "."
    return FigureOut(rel, "Fisher information eigenvalues per case", cap)


def solve_time_figure(runs: list[dict], run_dir: Path) -> FigureOut | None:
    """Per-run median and p95 solve time (ms, log) per controller x model, with the 10 ms period."""
    rows = solve_time_rows(runs)
    if not rows:
        return None
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(max(6.0, 0.75 * len(rows) + 2.5), 4.6))
        for i, row in enumerate(rows):
            col = controller_color(row["controller"])
            sel = [r for r in runs if r["controller"] == row["controller"] and r["model"] == row["model"]
                   and not r.get("error") and isinstance(r.get("solve_ms"), dict)]
            med = np.array([float(r["solve_ms"]["median"]) for r in sel if r["solve_ms"].get("median") is not None])
            p95 = np.array([float(r["solve_ms"]["p95"]) for r in sel if r["solve_ms"].get("p95") is not None])
            ax.scatter(np.full(len(med), i - 0.12), med, marker="o", color=col, s=22, zorder=3)
            ax.scatter(np.full(len(p95), i + 0.12), p95, marker="^", facecolors="none", edgecolors=col, s=30,
                       zorder=3)
        ax.axhline(DT_S * 1e3, color="red", ls="--", lw=1.2)
        ax.set_yscale("log")
        ax.set_xticks(np.arange(len(rows)))
        ax.set_xticklabels([f"{controller_label(r['controller'])}\n{r['model']}" for r in rows], rotation=45,
                           ha="right")
        ax.set_xlim(-0.6, len(rows) - 0.4)
        log_ticks(ax, "y")
        ax.set_ylabel("solve time per control period (ms)")
        ax.set_xlabel("controller / model")
        ax.set_title("Controller solve time (one marker per run)")
        handles = [Line2D([], [], ls="", marker="o", color="dimgray", label="run median"),
                   Line2D([], [], ls="", marker="^", markerfacecolor="none", color="dimgray", label="run p95"),
                   Line2D([], [], color="red", ls="--", label=f"control period dt = {DT_S * 1e3:g} ms")]
        handles += [Line2D([], [], ls="", marker="s", color=controller_color(c), label=controller_label(c))
                    for c in sorted({r["controller"] for r in rows}, key=controller_key)]
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
        rel = _save(fig, run_dir, "solve_time")
    return FigureOut(rel, "solve time per controller and model",
                     f"Median (filled) and 95th-percentile (hollow) solve time of each run, by controller and model; "
                     f"the red line is the {DT_S * 1e3:g} ms control period (a solve above it is a deadline miss).")


__all__ = ["FigureOut", "headline_figure", "trajectory_figures", "rollout_figure", "fisher_figure",
           "solve_time_figure"]
