"""Markdown tables of the report: Tables I-III, the Fisher table, closed-loop runs, solve times, provenance.

Every function takes parsed JSON (dicts as saved by the pipeline) and returns
Markdown text. Missing fields show as an en dash; nothing is invented.
"""

from __future__ import annotations

import math

import numpy as np

from .labels import DT_S, controller_key, controller_label, model_key, sorted_unique

#: The identified parameters in table order.
THETA_NAMES = ("m", "Jxx", "Jyy", "Jzz", "kt", "kq")
#: Shown for a missing or non-finite number.
MISSING = "–"
#: Format of a closed-loop position RMSE and maximum error, m.
RMSE_FORMAT = ".4f"
#: Hex digits of a SHA-256 shown in the provenance.
HASH_DIGITS = 12


def fmt(v, spec: str = ".3g") -> str:
    """``format(v, spec)`` for a finite number (rounded to int for a ``d`` spec), else :data:`MISSING`."""
    if v is None or isinstance(v, bool):
        return MISSING
    try:
        f = float(v)
    except (TypeError, ValueError):
        return MISSING
    if not math.isfinite(f):
        return MISSING
    if spec.endswith("d"):
        return format(int(round(f)), spec)
    return format(f, spec)


def cell(text) -> str:
    """``text`` made safe for one Markdown table cell (no newlines, pipes escaped)."""
    return " ".join(str(text).split()).replace("|", "\\|")


def md_table(header: list[str], rows: list[list]) -> str:
    """A Markdown pipe table with ``header`` and ``rows`` (cells escaped)."""
    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def theta_names(*dicts) -> list[str]:
    """Parameter names present in ``dicts``: :data:`THETA_NAMES` order, then others sorted."""
    present = set()
    for d in dicts:
        if isinstance(d, dict):
            present.update(d)
    return [n for n in THETA_NAMES if n in present] + sorted(present - set(THETA_NAMES))


def _paper_table1(evaluation: dict, model: dict) -> dict | None:
    """The paper's Table I entry for ``model`` (small-regime models only), or None."""
    if model.get("regime", "small") != "small":
        return None
    table = (evaluation.get("paper") or {}).get("table1") or {}
    return table.get(model.get("architecture", model.get("name")))


def table_one(evaluation: dict) -> str:
    """Table I: one-step and 100-step MAE of each model beside the paper's claims."""
    models = [m for m in evaluation.get("models", []) if isinstance(m, dict)]
    if not models:
        return "`evaluation.json` lists no models."
    first = models[0].get("rollout_100") or {}
    horizon = first.get("horizon", 100)
    text = (f"Mean absolute error on each model's test split: one step (dt = {DT_S:g} s) and "
            f"{horizon}-step autoregressive rollouts ({fmt(horizon * DT_S, 'g')} s of flight"
            + (f", {first['n_rollouts']} rollouts per model" if "n_rollouts" in first else "")
            + "). Position is the mean of the x, y, z errors. The paper's numbers are its claims; "
              "its \"100 steps\" were 0.1 s at 1 kHz.")
    header = ["model", "regime", "1-step z (m)", "1-step φ (rad)", "1-step position (m)", f"{horizon}-step z (m)",
              f"{horizon}-step φ (rad)", f"{horizon}-step position (m)", "diverged",
              "paper 1-step z (m) / φ (rad)", "paper 100-step z (m) / φ (rad)"]
    rows = []
    for m in models:
        o, k = m.get("one_step") or {}, m.get("rollout_100") or {}
        pap = _paper_table1(evaluation, m)
        div = (f"{k['n_diverged']}/{k['n_rollouts']}" if "n_diverged" in k and "n_rollouts" in k else MISSING)
        rows.append([m.get("name", MISSING), m.get("regime", MISSING), fmt(o.get("z")), fmt(o.get("phi")),
                     fmt(o.get("position")), fmt(k.get("z")), fmt(k.get("phi")), fmt(k.get("position")), div,
                     f"{fmt(pap.get('z_1'), 'g')} / {fmt(pap.get('phi_1'), 'g')}" if pap else MISSING,
                     f"{fmt(pap.get('z_100'), 'g')} / {fmt(pap.get('phi_100'), 'g')}" if pap else MISSING])
    return text + "\n\n" + md_table(header, rows)


def _paper_setting(entry: dict) -> bool:
    """The paper's setting: data from the nominal simulator with the command logged (Table VI has the others)."""
    return entry.get("fidelity", "nominal") == "nominal" and entry.get("inputs", "commanded") == "commanded"


def table_two(evaluation: dict) -> str:
    """Table II: identification error (%) with its multiple of the CRLB std, the paper's row, the CRLB rows."""
    models = [m for m in evaluation.get("models", []) if isinstance(m, dict) and _paper_setting(m)]
    fits = [d for d in evaluation.get("datasets", []) if isinstance(d, dict) and _paper_setting(d)
            and d.get("estimator")]
    paper = (evaluation.get("paper") or {}).get("table2_err_pct") or {}
    names = theta_names(paper, *[m.get("theta_err_pct") for m in models])
    if not names:
        return "`evaluation.json` holds no identified parameters."
    rows = []

    def cells(err, sig):
        return [f"{fmt(err.get(n), '+.2f')} %" + (f" ({fmt(sig.get(n), '.1f')} σ)" if n in sig else "")
                if n in err else MISSING for n in names]
    for m in models:
        rows.append([m.get("name", MISSING)] + cells(m.get("theta_err_pct") or {}, m.get("err_over_crlb") or {}))
    for d in fits:
        est = d["estimator"]
        rows.append([f"classical estimator, {d.get('regime', MISSING)} regime data"]
                    + cells(est.get("theta_err_pct") or {}, est.get("err_over_crlb") or {}))
    if paper:
        rows.append(["paper (Table II)"] + [f"{fmt(paper.get(n), 'g')} %" if n in paper else MISSING for n in names])
    seen = []
    for m in models:
        reg, crlb, true = m.get("regime"), m.get("crlb_std"), m.get("theta_true")
        if reg in seen or not isinstance(crlb, dict) or not isinstance(true, dict):
            continue
        seen.append(reg)
        rows.append([f"CRLB σ, {reg} regime ({m.get('name', MISSING)} training data; % of truth)"] + [
            f"{fmt(100.0 * crlb[n] / true[n], '.3f')} %" if n in crlb and true.get(n) else MISSING for n in names])
    text = ("Identification error of each parameter, % of the true value, and in brackets |error| as a "
            "multiple of the Cramér-Rao standard deviation for that model's training data (σ). Models trained on "
            "data from the nominal simulator with the command logged, as in the paper; the classical estimator "
            "(weighted nonlinear least squares through the nominal model, no network) is fitted to the same "
            "training splits.")
    return text + "\n\n" + md_table(["model"] + names, rows)


def fisher_table(fisher: dict) -> str:
    """The Fisher information table: regime, inputs, samples, rank, condition number, CRLB % per parameter."""
    cases = [c for c in fisher.get("cases", []) if isinstance(c, dict)]
    if not cases:
        return "`fisher.json` lists no cases."
    names = theta_names(*[c.get("crlb_pct") for c in cases])
    cos = any("weakest_vs_scale_direction_abs_cos" in c for c in cases)
    rows = []
    for c in cases:
        n_par = len(c["eigenvalues"]) if isinstance(c.get("eigenvalues"), list) else None
        deficient = c.get("rank") is not None and n_par is not None and c["rank"] < n_par
        pct = c.get("crlb_pct") or {}
        rows.append([c.get("regime", MISSING), c.get("inputs", MISSING), fmt(c.get("n_samples"), "d"),
                     fmt(c.get("rank"), "d") + (f"/{n_par}" if n_par is not None else ""),
                     fmt(c.get("condition_number"), ".3g")]
                    + [f"{fmt(pct[n], '.3g')} %" if fmt(pct.get(n)) != MISSING
                       else ("unbounded" if deficient else MISSING) for n in names]
                    + ([fmt(c.get("weakest_vs_scale_direction_abs_cos"), ".3f")] if cos else []))
    s = fisher.get("settings") or {}
    parts = []
    if "n_traj" in s:
        parts.append(f"{s['n_traj']} trajectories"
                     + (f" of {fmt(s.get('duration_s'), 'g')} s" if "duration_s" in s else ""))
    if "seed" in s:
        parts.append(f"seed {s['seed']}")
    if isinstance(s.get("noise"), dict):
        parts.append("measurement noise std " + ", ".join(f"{k} {fmt(v, 'g')}" for k, v in sorted(s["noise"].items())))
    if "coordinates" in s:
        parts.append(f"coordinates: {s['coordinates']}")
    text = ("Fisher information of the six parameters from simulated flight per regime and input channel, "
            "and the Cramér-Rao standard deviation as % of the true value.")
    if parts:
        text += " Settings: " + "; ".join(parts) + "."
    header = (["regime", "inputs", "samples", "rank", "condition number"] + [f"CRLB σ {n}" for n in names]
              + (["weakest direction vs common scaling (abs cos)"] if cos else []))
    if any("unbounded" in r for r in rows):
        text += (" \"unbounded\": the Fisher information of that case is rank-deficient and `fisher.json` gives "
                 "no finite bound (the parameter is not identifiable from those measurements alone).")
    if cos:
        text += (" Last column: |cos| of the angle between the weakest eigenvector (relative coordinates) and "
                 "the direction scaling all parameters together (1: the weakest direction is that common scaling).")
    return text + "\n\n" + md_table(header, rows)


def table_three(ablation: dict | None, evaluation: dict | None = None) -> str:
    """Table III: the ablation rows, or a sentence when ``ablation.json`` is missing.

    With ``evaluation`` (for the CRLB of the ablation's training data) each row also gives its inertia errors in
    CRLB standard deviations: the step of the recipe that moves them is the cause of a bias.
    """
    if not ablation:
        return "No `ablation.json` in this results folder, so Table III is not shown."
    rows = [r for r in ablation.get("rows", []) if isinstance(r, dict)]
    if not rows:
        return "`ablation.json` holds no rows, so Table III is not shown."
    data = ablation.get("data") or {}
    crlb = _ablation_crlb(evaluation, data)
    inertias = ("Jxx", "Jyy", "Jzz")
    header = (["configuration", "100-step position MAE (m)", "improvement", "diverged", "paper MAE (m)",
               "paper improvement"] + ([f"{n} error" for n in inertias] if crlb else []))

    def theta_cells(r):
        err = r.get("theta_err_pct") or {}
        return [f"{fmt(err.get(n), '+.2f')} % ({fmt(abs(err[n]) / crlb[n], '.1f')} σ)"
                if n in err and crlb.get(n) else MISSING for n in inertias]
    body = [[r.get("configuration", MISSING), fmt(r.get("position_mae_100_m"), ".4f"),
             f"{fmt(r.get('improvement_pct'), '+.0f')} %", fmt(r.get("n_diverged"), "d"),
             fmt(r.get("paper_position_mae_100_m"), "g"), f"{fmt(r.get('paper_improvement_pct'), '.0f')} %"]
            + (theta_cells(r) if crlb else []) for r in rows]
    parts = [f"{k} {ablation[k]}" for k in ("profile", "seed") if k in ablation]
    if data:
        parts.append("data " + ", ".join(f"{k} {data[k]}" for k in ("regime", "n_traj", "duration_s", "seed")
                                         if k in data))
    text = ("100-step position MAE of each training configuration and its improvement over the first row, "
            "beside the paper's claims.")
    if crlb:
        text += (" The last columns give each configuration's inertia errors, % of the truth and in Cramér-Rao "
                 "standard deviations of the training split.")
    if parts:
        text += " Settings: " + "; ".join(parts) + "."
    return text + "\n\n" + md_table(header, body)


def _ablation_crlb(evaluation: dict | None, data: dict) -> dict:
    """CRLB std of each inertia, % of truth, for the ablation's training data (from a matching dataset entry)."""
    for d in (evaluation or {}).get("datasets", []):
        if (isinstance(d.get("crlb_std"), dict) and all(d.get(k) == data.get(k) for k in ("regime", "seed", "n_traj"))
                and _paper_setting(d)):
            true = d.get("theta_true") or {}
            return {n: 100.0 * d["crlb_std"][n] / true[n] for n in ("Jxx", "Jyy", "Jzz")
                    if n in d["crlb_std"] and true.get(n)}
    return {}


def crash_text(run: dict) -> str:
    """The crash cell of a run: ``"no"``, ``"crashed at T s (reason)"`` or ``"could not start: ..."``."""
    if run.get("error"):
        return f"could not start: {run['error']}"
    if not run.get("crashed"):
        return "no"
    t = run.get("crash_time_s")
    why = run.get("crash_reason")
    return ("crashed" + (f" at {fmt(t, '.2f')} s" if t is not None else "") + (f" ({why})" if why else ""))


def closed_loop_table(runs: list[dict]) -> str:
    """One row per closed-loop run (``runs`` already in report order)."""
    if not runs:
        return "`results.json` lists no closed-loop runs."
    header = ["scenario", "controller", "model", "RMSE (m)", "max error (m)", "settled (m)", "crash",
              "solve median / p95 / max (ms)", "deadline misses", "solver failures", "fallbacks"]
    rows = []
    for r in runs:
        err = bool(r.get("error"))
        sm = r.get("solve_ms") or {}
        rows.append([r["scenario"], controller_label(r["controller"]), r["model"],
                     fmt(r.get("rmse_position_m"), RMSE_FORMAT), fmt(r.get("max_position_error_m"), RMSE_FORMAT),
                     fmt(r.get("settled_error_m"), RMSE_FORMAT), crash_text(r),
                     MISSING if err or not sm else
                     f"{fmt(sm.get('median'), '.2f')} / {fmt(sm.get('p95'), '.2f')} / {fmt(sm.get('max'), '.2f')}",
                     MISSING if err else fmt(r.get("deadline_misses"), "d"),
                     MISSING if err else fmt(r.get("solver_failures"), "d"),
                     MISSING if err else fmt(r.get("fallbacks"), "d")])
    text = (f"Position RMSE and maximum position error over the periods flown (up to a crash); settled error: the "
            f"largest position error over the last 2 s of a run that flew to its end; solve time per "
            f"control period; deadline misses are periods whose solve took longer than dt = {DT_S * 1e3:g} ms; "
            f"fallbacks are periods flown by the LQR fallback.")
    return text + "\n\n" + md_table(header, rows)


def solve_time_rows(runs: list[dict]) -> list[dict]:
    """Solve-time statistics per controller x model over the runs that flew.

    Returns
    -------
    list of dict
        In report order, each with ``controller``, ``model``, ``n_runs``,
        ``median_ms`` (median of the per-run medians), ``p95_ms`` (largest
        per-run p95), ``max_ms`` (largest per-run maximum), ``deadline_misses``
        and ``steps`` (sums over the runs).
    """
    out = []
    flown = [r for r in runs if not r.get("error") and isinstance(r.get("solve_ms"), dict)]
    for c in sorted_unique((r["controller"] for r in flown), controller_key):
        for m in sorted_unique((r["model"] for r in flown if r["controller"] == c), model_key):
            sel = [r for r in flown if r["controller"] == c and r["model"] == m]

            def col(key, sel=sel):
                v = np.array([float(r["solve_ms"].get(key)) for r in sel if r["solve_ms"].get(key) is not None])
                return v[np.isfinite(v)]
            med, p95, mx = col("median"), col("p95"), col("max")
            out.append({"controller": c, "model": m, "n_runs": len(sel),
                        "median_ms": float(np.median(med)) if len(med) else None,
                        "p95_ms": float(p95.max()) if len(p95) else None,
                        "max_ms": float(mx.max()) if len(mx) else None,
                        "deadline_misses": int(sum(int(r.get("deadline_misses") or 0) for r in sel)),
                        "steps": int(sum(int(r.get("steps") or 0) for r in sel))})
    return out


def solve_time_table(runs: list[dict]) -> str:
    """Solve time per controller x model (ms) and deadline misses."""
    rows = solve_time_rows(runs)
    if not rows:
        return "No run recorded solve times."
    header = ["controller", "model", "runs", "median of run medians (ms)", "largest run p95 (ms)",
              "largest solve (ms)", "deadline misses / periods"]
    body = [[controller_label(r["controller"]), r["model"], r["n_runs"], fmt(r["median_ms"], ".2f"),
             fmt(r["p95_ms"], ".2f"), fmt(r["max_ms"], ".2f"), f"{r['deadline_misses']} / {r['steps']}"]
            for r in rows]
    return md_table(header, body)


def _bullets(pairs) -> list[str]:
    return [f"- {k}: {v}" for k, v in pairs]


def provenance_section(prov: dict | None, plan: dict | None = None) -> str:
    """Versions, machine, commit, model hashes, training commands and seeds, run command, wall times."""
    if not prov:
        return "No `provenance.json` in this results folder."
    out = []
    top = [(k, f"`{prov[k]}`" if k in ("git_commit", "command") else prov[k])
           for k in ("git_commit", "command", "started", "finished", "jobs", "full", "evaluation", "fisher")
           if prov.get(k) is not None]
    if prov.get("wall_time_s") is not None:
        untimed = isinstance(prov.get("stage_seconds"), dict) and "report" not in prov["stage_seconds"]
        top.append(("wall time" + (" up to the report" if untimed else ""), f"{fmt(prov['wall_time_s'], '.1f')} s"))
    if top:
        out.append("\n".join(_bullets(top)))
    for title, key in (("Versions", "versions"), ("Machine", "machine")):
        d = prov.get(key)
        if isinstance(d, dict) and d:
            out.append(f"{title}:\n\n" + "\n".join(_bullets((k, MISSING if d[k] is None else d[k])
                                                           for k in sorted(d))))
    hashes = prov.get("model_sha256") if isinstance(prov.get("model_sha256"), dict) else {}
    training = prov.get("training") if isinstance(prov.get("training"), dict) else {}
    names = sorted(set(hashes) | set(training))
    if names:
        rows = []
        for n in names:
            t = training.get(n) if isinstance(training.get(n), dict) else {}
            h = hashes.get(n)
            rows.append([n, f"`{h[:HASH_DIGITS]}`" if isinstance(h, str) else MISSING,
                         MISSING if t.get("seed") is None else t["seed"],
                         MISSING if t.get("data_seed") is None else t["data_seed"],
                         f"`{t['command']}`" if t.get("command") else MISSING])
        out.append("Models (SHA-256, first 12 hex digits) and how they were trained:\n\n"
                   + md_table(["model", "sha256", "seed", "data seed", "training command"], rows))
    stages = prov.get("stage_seconds")
    if isinstance(stages, dict) and stages:
        rows = [[k, fmt(v, ".1f")] for k, v in stages.items()]
        if "report" not in stages:
            rows.append(["report", ("not yet timed when this report was built (`pinnmpc report` on this folder "
                                    "shows it)")])
        out.append("Wall time per stage (in the order run):\n\n" + md_table(["stage", "wall time (s)"], rows))
    if plan and plan.get("models_dir") is not None:
        out.append(f"Closed-loop plan: models from `{plan['models_dir']}`"
                   + (f", full = {plan['full']}" if "full" in plan else "")
                   + (f", {len(plan['specs'])} runs planned" if isinstance(plan.get("specs"), list) else "")
                   + (f", every run at the `{plan['level']}` level" if plan.get("level") else "") + ".")
        left = plan.get("left_out")
        if isinstance(left, dict) and left:
            out.append(f"Left out at the `{plan.get('level')}` level (their models take commands at another): "
                       + ", ".join(f"`{m}` ({lv})" for m, lv in left.items()) + ".")
    return "\n\n".join(out) if out else "`provenance.json` is empty."


def hover_table(runs: list[dict]) -> str:
    """Hover runs: settled error, gust peak error and recovery time per controller and model."""
    sel = [r for r in runs if r.get("scenario") == "hover"]
    if not sel:
        return "No `hover` run in `results.json`."
    header = ["controller", "model", "settled error (mm)", "gust peak error (mm)", "recovery (s)", "RMSE (mm)",
              "crash"]
    rows = []
    for r in sel:
        def mm(k, r=r):
            v = r.get(k)
            return fmt(None if v is None else 1e3 * v, ".2f")
        rows.append([controller_label(r["controller"]), r["model"], mm("settled_error_m"), mm("gust_peak_error_m"),
                     fmt(r.get("recovery_time_s"), ".2f"), mm("rmse_position_m"), crash_text(r)])
    from scenarios.closed_loop.library import get_scenario
    from scenarios.closed_loop.metrics import RECOVERY_BAND_M, SETTLE_WINDOW_S

    gust = get_scenario("hover").impulse
    text = (f"The hover starts a few cm and degrees off the set point and takes a gust impulse at {gust.start_s:g} s. "
            f"The settled error (the largest error over the last {SETTLE_WINDOW_S:g} s) measures the model: the true "
            f"equations hold hover to a fraction of a millimetre, so a learned model's settled error is its own bias. "
            f"Recovery is the time from the gust until the error stays within the settled error plus "
            f"{RECOVERY_BAND_M * 1e3:g} mm. The RMSE is dominated by the gust and ranks models poorly.")
    return text + "\n\n" + md_table(header, rows)


def ladder_table(runs: list[dict]) -> str:
    """Maximum trackable speed of each model with each controller, from the figure-8 speed ladder."""
    from scenarios.closed_loop.library import ladder_names, ladder_speeds
    from scenarios.closed_loop.metrics import LADDER_RMSE_BOUND_M, max_trackable_speed

    ladder, speeds = ladder_names(), ladder_speeds()
    sel = [r for r in runs if r.get("scenario") in ladder]
    if not sel:
        return "No run of the figure-8 speed ladder in `results.json`."
    pairs = sorted({(r["controller"], r["model"]) for r in sel}, key=lambda p: (controller_key(p[0]), model_key(p[1])))
    header = ["controller", "model", "max trackable speed (m/s)", "fastest rung tracked", "first rung failed"] + [
        f"{n} RMSE (mm)" for n in ladder]
    rows = []
    for c, m in pairs:
        mine = [r for r in sel if r["controller"] == c and r["model"] == m]
        res = max_trackable_speed(mine, ladder, speeds)
        by = {r["scenario"]: r for r in mine}
        cells = []
        for n in ladder:
            r = by.get(n)
            v = None if r is None else r.get("rmse_position_m")
            cells.append(MISSING if r is None else ("crash" if r.get("crashed") else
                                                    fmt(None if v is None else 1e3 * v, ".2f")))
        speed = fmt(res["speed_mps"], ".2f") if res["complete"] or res["failed_at"] else MISSING
        rows.append([controller_label(c), m, speed, res["scenario"] or "none", res["failed_at"] or "none", *cells])
    text = (f"Two laps of the figure-8 at shorter and shorter periods (mean speeds "
            f"{', '.join(f'{speeds[n]:.2f}' for n in ladder)} m/s; the last is close to the rotor limits). "
            f"A rung is tracked when the run does not crash and its RMSE is at most {LADDER_RMSE_BOUND_M:g} m; the "
            f"maximum trackable speed is the mean speed of the fastest rung below the first one that is not "
            f"(a dash: the ladder was not flown completely).")
    return text + "\n\n" + md_table(header, rows)


def realtime_table(runs: list[dict]) -> str:
    """Each controller x model flown with both timings: RMSE ideal against real time, and what the time cost."""
    from mpc.controllers.sqp import SQPSettings

    budget_ms = 1e3 * SQPSettings().time_budget_s
    rt = [r for r in runs if r.get("timing") == "realtime"]
    if not rt:
        return "No run was flown with real-time timing."
    ideal = {(r["scenario"], r["controller"], r["model"]): r for r in runs if r.get("timing", "ideal") == "ideal"}
    header = ["scenario", "controller", "model", "RMSE ideal (m)", "RMSE real time (m)", "crash (real time)",
              "input latency median / p99 (ms)", "load median / p95 / max (ms)", "deadline misses",
              "deadline fallbacks", "skipped periods", "solver failures", "fallbacks"]
    rows = []
    unflown = False     # a real-time run without its ideal-timing twin in this folder
    for r in sorted(rt, key=lambda r: (r["scenario"], controller_key(r["controller"]), model_key(r["model"]))):
        i = ideal.get((r["scenario"], r["controller"], r["model"]))
        unflown |= i is None
        s, lat = r.get("solve_ms") or {}, r.get("latency_ms") or {}
        label = controller_label(r["controller"]) + (" (real-time iteration)" if r.get("scheme") == "rti" else "")
        rows.append([r["scenario"], label, r["model"],
                     "not flown" if i is None else (crash_text(i) if i.get("crashed") else fmt(i.get("rmse_position_m"))),
                     fmt(r.get("rmse_position_m")), crash_text(r) if r.get("crashed") else "no",
                     " / ".join(fmt(lat.get(k), ".2f") for k in ("median", "p99")) if lat else "-",
                     " / ".join(fmt(s.get(k), ".1f") for k in ("median", "p95", "max")) if s else "-",
                     r.get("deadline_misses"), fmt(r.get("deadline_fallbacks"), "d"), r.get("skipped_periods"),
                     r.get("solver_failures"), r.get("fallbacks")])
    return ("With real-time timing the input computed from the measurement at a period takes effect after the "
            "call's measured wall time, rounded up to the simulator's 1 ms substep; a call that overruns the "
            f"{DT_S * 1e3:.0f} ms period keeps the previous input until it returns, and the periods it overran are "
            "skipped (the controller is not called). Ideal timing applies every input at once. In real time the "
            "SQP flies the real-time iteration: its input waits for one QP (the input latency, from the measurement "
            "to the input out, a state estimator's time included), and the derivatives and the next QP are prepared "
            "after the input is out (the load counts both); in ideal timing it iterates without its "
            f"{budget_ms:g} ms budget (at most its iteration limit). In real time the MPCs on OSQP must send their "
            "input 1 ms before the period ends: a period "
            "whose plan cannot be made by then sends the shifted plan at once (a deadline fallback, counted among "
            "the solver failures too). A sweep flies these runs after all the others, one at a time, so that no "
            "other run of it competes for the cores (and a second sweep cannot use the same folder); other "
            "programs on the machine are not controlled, and a stall of the machine counts against the period."
            + (" \"Not flown\": the case was not flown in ideal timing in this folder (`pinnmpc run` leaves the NMPC's "
               "ideal-timing runs, about 90 s of a core each, to `--full`)." if unflown
               else "")
            + "\n\n" + md_table(header, rows))


def ensemble_table(runs: list[dict]) -> str:
    """Each ensemble's crash probability (Wilson 95 %) and median RMSE (bootstrap 95 %), one row per case."""
    from scenarios.closed_loop.library import ENSEMBLE_X0_SIGMA
    from scenarios.studies.stats import summarize

    members = [r for r in runs if r.get("member") is not None]
    if not members:
        return ("No ensemble in this results folder. `pinnmpc run --full` flies one for every model with the "
                "LTV-MPC and the SQP on `figure8-fast`; `python -m scenarios.studies.ensemble` flies one case.")
    groups: dict[tuple, list[dict]] = {}
    for r in members:
        groups.setdefault((r["scenario"], r["controller"], r["model"], r.get("timing", "ideal")), []).append(r)
    from .labels import scenario_key

    keys = sorted(groups, key=lambda k: (scenario_key(k[0]), controller_key(k[1]), model_key(k[2]), k[3]))
    header = ["scenario", "controller", "model", "timing", "members", "crashes", "crash probability (Wilson 95 %)",
              "median RMSE, mm (bootstrap 95 %)", "RMSE range, mm"]
    rows = []
    for k in keys:
        s = summarize(groups[k])
        lo, hi = s["crash_probability_ci95"]
        if s["median"] is None:
            med, rng = "no run flew to the end", MISSING
        else:
            ci = "" if s["median_ci95"] is None else \
                f" ({1e3 * s['median_ci95'][0]:.1f}–{1e3 * s['median_ci95'][1]:.1f})"
            med, rng = f"{1e3 * s['median']:.1f}{ci}", f"{1e3 * s['min']:.1f}–{1e3 * s['max']:.1f}"
        rows.append([k[0], controller_label(k[1]), k[2], k[3], s["runs"], s["crashes"],
                     f"{s['crash_probability']:.2f} ({lo:.2f}–{hi:.2f})", med, rng])
    sig = ENSEMBLE_X0_SIGMA
    text = (f"Each case flown from several ensemble members: member k has seed k (noise and gusts redrawn) and a "
            f"start moved by a seeded normal draw ({1e2 * sig[0]:g} cm in position, {sig[3]:g} rad in attitude, "
            f"{sig[6]:g} m/s in velocity, {sig[9]:g} rad/s in body rate). The crash probability has a Wilson "
            f"95 % interval; the median RMSE is over the members that did not crash, with a percentile-bootstrap "
            f"95 % interval (2000 resamples, seeded).")
    return text + "\n\n" + md_table(header, rows)
