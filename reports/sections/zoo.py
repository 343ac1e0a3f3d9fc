"""The report's lead: the dose-response study of the model zoo (``study.json`` of ``pinnmpc study``).

Figures (open-loop error against crash probability and RMSE, against the
maximum trackable speed), the predictor table, the zoo table and the
sentences that read them, all generated from the study's numbers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..figures import DPI, STYLE, FigureOut, _save, controller_color, log_ticks, plt  # noqa: F401
from ..labels import controller_label
from ..tables import MISSING, fmt, md_table

#: What the sections say when the results folder has no study.
NO_STUDY = ("The zoo study has not been run for this results folder. Train the zoo with `pinnmpc zoo` "
            "(needs `pip install -e \".[train]\"`), fly it with `pinnmpc study`, then run `pinnmpc run` "
            "again: it copies `models/zoo/study.json` here.")
#: Open-loop error bands of the answer's sentences, m: (upper edge of the "accurate" band, lower edge of the "poor").
BANDS_M = (0.035, 0.08)
#: Candidate labels in tables and text.
LABELS = {"one_step_mae_m": "1-step position MAE", "rollout_100_mae_m": "100-step position MAE",
          "envelope_exit_fraction": "envelope exits (1 m, 100 steps)",
          "jacobian_error": "Jacobian error along the reference",
          "closed_loop_kstep_m": "k-step error on the oracle's flight",
          "hover_chordal_distance": "hover chordal distance (nu-gap bound)"}


def _mae(row: dict) -> float:
    return float(row["candidates"]["rollout_100_mae_m"])


def _ci(v, spec=".2f", sep="–") -> str:
    return MISSING if not v else f"{format(v[0], spec)}{sep}{format(v[1], spec)}"


def provenance_text(study: dict) -> str:
    """Where the study's numbers come from (its command, date, runs, wall time)."""
    return (f"From `{study.get('command', 'pinnmpc study')}` ({study.get('date', 'undated')}, "
            f"{study.get('runs', MISSING)} closed-loop runs in {fmt(study.get('wall_time_s', 0) / 60, '.0f')} min), "
            f"copied into this folder by `pinnmpc run`: the study does not fit the main job's time.")


def answer_text(study: dict) -> str:
    """The sentences that read the study, per controller, from its numbers."""
    models = study["models"]
    lo_band, hi_band = BANDS_M
    lines = [f"{len(models)} learned models of the zoo, 100-step open-loop position MAE "
             f"{1e3 * min(map(_mae, models.values())):.1f} mm to {max(map(_mae, models.values())):.2f} m, each flown "
             f"on `{study['scenario']}` from {study['members']} ensemble members per controller; the oracle tracks it "
             f"with {1e3 * study['oracle_rmse_m']:.2f} mm (SQP)."]
    for c in study["controllers"]:
        p = {n: r["ensembles"][c]["crash_probability"] for n, r in models.items()}
        low = [p[n] for n, r in models.items() if _mae(r) < lo_band]
        high = [p[n] for n, r in models.items() if _mae(r) >= hi_band]
        mid = [n for n, r in models.items() if lo_band <= _mae(r) < hi_band]
        s = f"**{controller_label(c)}.** "
        if low:
            s += f"The {_models(len(low))} under {1e3 * lo_band:.0f} mm crashed with probability {_span(low)}; "
        if high:
            s += f"the {_models(len(high))} at {1e3 * hi_band:.0f} mm or more with {_span(high)}; "
        if mid:
            flown = sum(p[n] == 0 for n in mid)
            s += f"in between, {flown} of {_models(len(mid))} flew every member. "
        best = _best(study["scores"][c], "auc")
        base = next((r for r in study["scores"][c] if r["candidate"] == "rollout_100_mae_m"), None)
        if best is None:
            s += "No crash AUC is defined (every model crashed, or none did)."
        else:
            s += (f"The best predictor of a crash is the {LABELS.get(best['candidate'], best['candidate'])}: AUC "
                  f"{best['auc']:.2f} (95 % {_ci(best['auc_ci95'])})")
            if base is not None and base.get("auc") is not None and base is not best:
                s += f", against {base['auc']:.2f} for the 100-step MAE"
            s += "."
            if best.get("auc_ci95") and best["auc_ci95"][0] <= 0.5:
                s += " Its interval includes 0.5: no better than chance at this sample size."
        bs = _best(study["scores"][c], "spearman")
        if bs is not None:
            s += (f" The RMSE of the runs that flew is ranked best by the {LABELS.get(bs['candidate'], bs['candidate'])}"
                  f" (Spearman {bs['spearman']:+.2f}, 95 % {_ci(bs['spearman_ci95'], '+.2f', ' to ')}).")
        lines.append(s)
    return "\n\n".join(lines)


def _models(n: int) -> str:
    return f"{n} model" + ("" if n == 1 else "s")


def _span(values) -> str:
    lo, hi = min(values), max(values)
    return f"{lo:.2f} each" if lo == hi else f"{lo:.2f}–{hi:.2f}"


def _best(scores: list[dict], key: str) -> dict | None:
    rows = [r for r in scores if r.get(key) is not None]
    return max(rows, key=lambda r: r[key]) if rows else None


def predictor_table(study: dict) -> str:
    """One row per controller and candidate: crash AUC and RMSE Spearman with their bootstrap 95 % intervals."""
    rows = []
    for c in study["controllers"]:
        for r in study["scores"][c]:
            auc = "undefined" if r.get("auc") is None else f"{r['auc']:.2f} ({_ci(r.get('auc_ci95'))})"
            sp = ("undefined" if r.get("spearman") is None else
                  f"{r['spearman']:+.2f} ({_ci(r.get('spearman_ci95'), '+.2f', ' to ')})")
            rows.append([controller_label(c), LABELS.get(r["candidate"], r["candidate"]), r.get("models"),
                         r.get("crashed"), auc, sp])
    text = ("A model counts as crashing when its crash probability is above 0.5. AUC: the probability that a "
            "crashing model has the larger value (0.5 is chance). Spearman: rank correlation with the median RMSE "
            "over the models that flew. Intervals: percentile bootstrap over models, 95 %. The candidates: "
            + "; ".join(f"{LABELS.get(k, k)}: {v}" for k, v in study.get("candidates", {}).items()) + ".")
    return text + "\n\n" + md_table(["controller", "candidate", "models", "crashing", "crash AUC (95 %)",
                                     "RMSE Spearman (95 %)"], rows)


def zoo_table(study: dict) -> str:
    """One row per zoo model, by open-loop error: what it is, its open-loop numbers and its closed-loop outcomes."""
    cs = study["controllers"]
    header = ["model", "what it is", "100-step MAE (mm)", "envelope exits"]
    for c in cs:
        header += [f"{controller_label(c)} crash p (Wilson 95 %)", f"{controller_label(c)} RMSE mm (95 %)"]
    header.append(f"max speed, {controller_label(study['ladder']['controller'])} (m/s)")
    rows = []
    for name, r in sorted(study["models"].items(), key=lambda kv: (_mae(kv[1]), kv[0])):
        row = [name, r.get("why") or MISSING, fmt(1e3 * _mae(r), ".1f"),
               fmt(r["candidates"].get("envelope_exit_fraction"), ".2f")]
        for c in cs:
            e = r["ensembles"][c]
            row.append(f"{e['crash_probability']:.1f} ({_ci(e['crash_probability_ci95'])})")
            row.append(MISSING if e["median"] is None else
                       f"{1e3 * e['median']:.0f}" + ("" if not e.get("median_ci95") else
                                                     f" ({_ci([1e3 * v for v in e['median_ci95']], '.0f')})"))
        v = r["max_speed"]["speed_mps"]
        row.append("none" if v is None else f"{v:.2f}")
        rows.append(row)
    text = md_table(header, rows)
    refused = study.get("refused") or {}
    if refused:
        text += (f"\n\nNot flown: {len(refused)} trained models on which no controller can be built (their hover "
                 "linearization is not stabilizable, so the LQR behind every MPC has no solution): "
                 + "; ".join(f"{n} ({r.get('why') or MISSING}, 100-step MAE {fmt(r.get('rollout_100_mae_m'), '.3g')} m)"
                             for n, r in sorted(refused.items())) + ".")
    return text


def dose_response_figure(study: dict, run_dir: Path) -> FigureOut | None:
    """Open-loop 100-step MAE (log) against crash probability (top) and median RMSE (bottom), one column per controller."""
    models = study["models"]
    cs = study["controllers"]
    if not models or not cs:
        return None
    x = np.array([_mae(r) for r in models.values()])
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, axes = plt.subplots(2, len(cs), figsize=(4.6 * len(cs), 7.0), sharex=True, squeeze=False)
        rmses = [r["ensembles"][c]["median"] for r in models.values() for c in cs]
        flown = [v for v in rmses if v is not None] + [study["oracle_rmse_m"]]
        top = max(flown) * 3.0
        for j, c in enumerate(cs):
            col = controller_color(c)
            e = [r["ensembles"][c] for r in models.values()]
            p = np.array([v["crash_probability"] for v in e])
            lo = np.array([v["crash_probability_ci95"][0] for v in e])
            hi = np.array([v["crash_probability_ci95"][1] for v in e])
            ax = axes[0, j]
            ax.errorbar(x, p, yerr=[p - lo, hi - p], fmt="o", color=col, ms=4, capsize=2, lw=0.8)
            ax.set_ylim(-0.05, 1.05)
            ax.set_title(f"{controller_label(c)}, {study['scenario']}")
            if j == 0:
                ax.set_ylabel("crash probability (Wilson 95 %)")
            ax = axes[1, j]
            ok = [i for i, v in enumerate(e) if v["median"] is not None]
            never = [i for i, v in enumerate(e) if v["median"] is None]
            if ok:
                med = np.array([e[i]["median"] for i in ok])
                ci = [e[i].get("median_ci95") or [e[i]["median"]] * 2 for i in ok]
                ax.errorbar(x[ok], med, yerr=[med - np.array([v[0] for v in ci]), np.array([v[1] for v in ci]) - med],
                            fmt="o", color=col, ms=4, capsize=2, lw=0.8, label="median RMSE of the members that flew")
            if never:
                ax.scatter(x[never], [top] * len(never), marker="x", color="red", s=30,
                           label="every member crashed")
            ax.axhline(study["oracle_rmse_m"], color="black", ls="--", lw=1.0, label="oracle")
            ax.set_yscale("log")
            ax.set_ylim(study["oracle_rmse_m"] / 3.0, top * 2.0)
            log_ticks(ax, "y")
            if j == 0:
                ax.set_ylabel("closed-loop position RMSE (m)")
            ax.legend(loc="lower right", fontsize=7)
        for ax in axes[1]:
            ax.set_xscale("log")
            ax.set_xlabel("100-step open-loop position MAE (m)")
            log_ticks(ax, "x")
        fig.tight_layout()
        rel = _save(fig, Path(run_dir), "dose_response")
    cap = (f"{len(models)} zoo models, one point each, {study['members']} ensemble members per model and controller "
           f"on `{study['scenario']}`. Top: crash probability with its Wilson 95 % interval. Bottom: median RMSE of "
           f"the members that did not crash with its bootstrap 95 % interval; red crosses at the top edge: every "
           f"member crashed. Dashed: the oracle (true equations).")
    return FigureOut(rel, "open-loop error against crash probability and closed-loop RMSE", cap)


def max_speed_figure(study: dict, run_dir: Path) -> FigureOut | None:
    """Open-loop 100-step MAE (log) against the maximum trackable speed of each model, rungs as lines."""
    models = study["models"]
    if not models:
        return None
    lad = study["ladder"]
    with plt.style.context("default"), plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(7.5, 4.2))
        col = controller_color(lad["controller"])
        xs = np.array([_mae(r) for r in models.values()])
        v = [r["max_speed"]["speed_mps"] for r in models.values()]
        ok = [i for i, s in enumerate(v) if s is not None]
        no = [i for i, s in enumerate(v) if s is None]
        ax.scatter(xs[ok], [v[i] for i in ok], color=col, s=28, zorder=3, label="fastest lap flown")
        if no:
            ax.scatter(xs[no], [0.0] * len(no), marker="x", color="red", s=30, zorder=3,
                       label="not even the slowest lap")
        for rung, s in lad["speeds_mps"].items():
            ax.axhline(s, color="lightgray", lw=0.8, ls=":")
            ax.text(1.0, s, f" {rung}", transform=ax.get_yaxis_transform(), va="center", fontsize=7)
        ax.set_xscale("log")
        log_ticks(ax, "x")
        ax.set_xlabel("100-step open-loop position MAE (m)")
        ax.set_ylabel("maximum trackable speed (m/s, lap mean)")
        ax.set_ylim(-0.15, max(lad["speeds_mps"].values()) * 1.1)
        ax.legend(loc="upper right", fontsize=7)
        rel = _save(fig, Path(run_dir), "max_speed")
    cap = (f"The fastest figure-8 lap each zoo model flies with the {controller_label(lad['controller'])} without a "
           f"crash and within {lad['rmse_bound_m']:g} m RMSE, climbing the ladder from the slowest lap (one run per "
           f"lap). Dotted: the laps' mean speeds.")
    return FigureOut(rel, "open-loop error against maximum trackable speed", cap)


#: Shown when the results folder has no study flown with the state estimator.
NO_STUDY_EKF = ("No `study_ekf.json` in this folder: `pinnmpc study --estimator ekf` flies the zoo's ensembles with "
                "the state estimator (`--select` for some of its models) and writes a copy into `models/zoo/`, "
                "which the next `pinnmpc run` copies here.")


def _crash_cell(e: dict | None) -> str:
    if not e:
        return MISSING
    return f"{e['crash_probability']:.1f} ({_ci(e['crash_probability_ci95'])})"


def _median_mm(e: dict | None) -> str:
    return MISSING if not e or e.get("median") is None else f"{1e3 * e['median']:.1f}"


def _edges(rows: dict, c: str) -> tuple[float | None, float | None]:
    """(largest open-loop MAE with no crash at or below it, smallest with every crash at or above it), m."""
    pts = sorted((_mae(r), r["ensembles"][c]["crash_probability"]) for r in rows.values())
    safe = None
    for m, p in pts:
        if p > 0:
            break
        safe = m
    doomed = None
    for m, p in reversed(pts):
        if p < 1:
            break
        doomed = m
    return safe, doomed


def estimator_threshold_section(study: dict | None, study_ekf: dict | None) -> str:
    """The dose-response on the same models without and with the state estimator: crash probabilities (Wilson 95 %)
    and median RMSE per controller, and where the threshold's edges fall each way."""
    if study_ekf is None:
        return NO_STUDY_EKF
    base = (study or {}).get("models", {})
    rows = study_ekf["models"]
    cs = [c for c in study_ekf["controllers"]]
    header = ["model", "100-step MAE (mm)"]
    for c in cs:
        lab = controller_label(c)
        header += [f"{lab} crash p without", f"{lab} crash p with", f"{lab} RMSE without (mm)",
                   f"{lab} RMSE with (mm)"]
    body = []
    for name, r in sorted(rows.items(), key=lambda kv: _mae(kv[1])):
        b = base.get(name)
        line = [name, f"{1e3 * _mae(r):.1f}"]
        for c in cs:
            eb = None if b is None else b["ensembles"].get(c)
            e = r["ensembles"][c]
            line += [_crash_cell(eb), _crash_cell(e), _median_mm(eb), _median_mm(e)]
        body.append(line)
    text = [f"{len(rows)} models of the zoo around the threshold, flown on `{study_ekf['scenario']}` from "
            f"{study_ekf['members']} ensemble members per controller with the state estimator (the filter's "
            f"estimate and its disturbance estimate in the controllers' prediction and target), beside the same "
            f"models without it (the study above). From `{study_ekf.get('command', 'pinnmpc study --estimator ekf')}`"
            f" ({study_ekf.get('date', 'undated')}). Crash probabilities with Wilson 95 % intervals."]
    for c in cs:
        sub = {n: base[n] for n in rows if n in base}
        s0, d0 = _edges(sub, c) if sub else (None, None)
        s1, d1 = _edges(rows, c)
        def mm(v):
            return MISSING if v is None else f"{1e3 * v:.0f} mm"
        text.append(f"**{controller_label(c)}.** No crash up to {mm(s0)} of open-loop error without the estimator, "
                    f"{mm(s1)} with it; every member crashes from {mm(d0)} without, {mm(d1)} with.")
    return "\n\n".join(text) + "\n\n" + md_table(header, body)
