"""Identification under model mismatch (Table VI) and the closed loop on the high-fidelity plant.

Reads the ``datasets`` entries of ``evaluation.json`` (one per training dataset: its saturation, the CRLB of its
training split and the classical estimator's fit) and the model rows trained on each; every sentence is computed
from those numbers.
"""

from __future__ import annotations

from collections.abc import Mapping

from scenarios.studies.stats import summarize

from ..tables import MISSING, RMSE_FORMAT, THETA_NAMES, crash_text, fmt, md_table

#: Order of the data cells in Table VI: (regime, fidelity, inputs).
CELL_ORDER = (("small", "nominal", "commanded"), ("small", "high", "commanded"),
              ("aggressive", "nominal", "commanded"), ("aggressive", "high", "commanded"),
              ("aggressive", "nominal", "realized"), ("small", "motor-lag", "commanded"),
              ("small", "rotor-drag", "commanded"), ("small", "rotor-gyro", "commanded"))
INERTIAS = ("Jxx", "Jyy", "Jzz")
#: An error counts as moved by a cause when it changes by more than this many CRLB standard deviations.
MOVED_SIGMA = 3.0
FIDELITY_LABELS = {"nominal": "nominal simulator", "high": "high-fidelity simulator",
                   "motor-lag": "motor lag only", "rotor-drag": "rotor drag only",
                   "rotor-gyro": "rotor gyroscopic torque only"}
NO_DATASETS = ("`evaluation.json` has no `datasets` entries (it predates the classical estimator); run "
               "`pinnmpc run` again for Table VI.")


def cell_key(d: dict) -> tuple:
    """(regime, fidelity, inputs) of a dataset entry or model row (defaults: nominal, commanded)."""
    return (d.get("regime"), d.get("fidelity", "nominal"), d.get("inputs", "commanded"))


def cell_label(key: tuple) -> str:
    regime, fidelity, inputs = key
    text = f"{regime}, {FIDELITY_LABELS.get(fidelity, fidelity)}"
    return text + (", realized inputs (commands inside the rotor limits)" if inputs == "realized" else "")


def datasets(evaluation: dict) -> dict[tuple, dict]:
    """Dataset entries by cell key, in :data:`CELL_ORDER` (then any other)."""
    ds = [d for d in evaluation.get("datasets", []) if isinstance(d, dict) and d.get("crlb_std")]
    by = {cell_key(d): d for d in ds}
    order = [k for k in CELL_ORDER if k in by] + [k for k in by if k not in CELL_ORDER]
    return {k: by[k] for k in order}


def _models_on(evaluation: dict, key: tuple) -> list[dict]:
    return [m for m in evaluation.get("models", []) if isinstance(m, dict) and m.get("theta_err_pct")
            and cell_key(m) == key]


def _entry_cells(err: dict, sig: dict) -> list[str]:
    return [f"{fmt(err.get(n), '+.2f')} % ({fmt(sig.get(n), '.1f')} σ)" if n in err else MISSING
            for n in THETA_NAMES]


def _worst_inertia(err: dict) -> float | None:
    vals = [abs(err[n]) for n in INERTIAS if n in err]
    return max(vals) if vals else None


def table_six(evaluation: dict) -> str:
    """Table VI: identification error per parameter and data cell, classical estimator and PINNs, with CRLB σ."""
    cells = datasets(evaluation)
    if not cells:
        return NO_DATASETS
    paper = ((evaluation.get("paper") or {}).get("table6_inertia_err_pct")) or {}
    rows = []
    for key, d in cells.items():
        label = cell_label(key)
        sat = f"{100 * d['saturated_fraction']:.1f} %" if "saturated_fraction" in d else MISSING
        crlb, true = d["crlb_std"], d.get("theta_true") or {}
        # The paper's claim is per regime (its simulator's fidelity is not stated): beside every cell of that regime.
        claim = f"{fmt(paper.get(key[0]), 'g')} %" if key[0] in paper else ""
        flights = f"{d['n_traj']} × {fmt(d.get('duration_s'), 'g')} s" if "n_traj" in d else MISSING
        rows.append([label, flights, sat, "CRLB σ (% of truth)"]
                    + [f"{fmt(100 * crlb[n] / true[n], '.3f')} %" if n in crlb and true.get(n) else MISSING
                       for n in THETA_NAMES] + ["", claim])
        est = d.get("estimator")
        if est:
            rows.append(["", "", "", "classical estimator"] + _entry_cells(est["theta_err_pct"], est["err_over_crlb"])
                        + [f"{fmt(_worst_inertia(est['theta_err_pct']), '.1f')} %", ""])
        lag = d.get("estimator_lag")
        if lag:
            tau = f"τ_m {fmt(lag['theta_err_pct'].get('tau_m'), '+.2f')} % ({fmt(lag['err_over_crlb'].get('tau_m'), '.1f')} σ)"
            rows.append(["", "", "", f"classical, with the motor lag ({tau}; σ of the lag model's bound)"]
                        + _entry_cells(lag["theta_err_pct"], lag["err_over_crlb"])
                        + [f"{fmt(_worst_inertia(lag['theta_err_pct']), '.2f')} %", ""])
        for m in _models_on(evaluation, key):
            err, sig = m["theta_err_pct"], m.get("err_over_crlb") or {}
            label = m.get("name", MISSING)
            if "tau_m" in err:      # a motor-lag model: tau_m beside its name, σ of the lag model's bound
                label += (f" (motor lag; τ_m {fmt(err['tau_m'], '+.2f')} % ({fmt(sig.get('tau_m'), '.1f')} σ)"
                          + ("; σ of the lag model's bound)" if m.get("crlb") == "lag" else ")"))
            rows.append(["", "", "", label] + _entry_cells(err, sig)
                        + [f"{fmt(_worst_inertia(err), '.1f')} %", ""])
    header = (["training data", "flights (70 % train)", "samples with a saturated rotor", "estimator"] + list(THETA_NAMES)
              + ["largest inertia error", "paper's inertia error (its regime)"])
    text = ("Identification error of each parameter (% of the true value; in brackets |error| in Cramér-Rao "
            "standard deviations of that cell's training split) for the same seeded flights in two regimes "
            "(|roll|, |pitch| up to 20° and 45-60°), flown in the nominal simulator (the models' own equations) "
            "and in the high-fidelity one (motor lag 30 ms, rotor drag, rotor gyroscopic torque), plus the "
            "aggressive flights logged with the wrench the rotors realized instead of the command, and the small "
            "flights with one high-fidelity effect at a time (classical estimator only). The classical estimator "
            "is weighted nonlinear least squares through the nominal model on the same training split, without a "
            "network; where the flights had a motor lag, it is also fitted with the lag in its model (the rotor "
            "speeds a state driven by the logged commands, the rotor telemetry a measurement of them, and the "
            "motor time constant τ_m a seventh parameter), and its errors are then in σ of that model's own "
            "bound. The paper reports 5 % inertia error from small-angle data and 46 % from aggressive data.")
    return text + "\n\n" + md_table(header, rows) + "\n\n" + mismatch_text(evaluation)


def _moved(a: dict, b: dict, crlb: dict, truth: dict) -> list[str]:
    """Parameters whose error differs between entries ``a`` and ``b`` by more than MOVED_SIGMA sigma."""
    out = []
    for n in THETA_NAMES:
        if n in a and n in b and n in crlb and truth.get(n):
            delta = a[n] - b[n]
            if abs(delta) * truth[n] / 100.0 > MOVED_SIGMA * crlb[n]:
                out.append(f"{n} {delta:+.1f} points" if abs(delta) >= 1 else f"{n} {delta:+.2f} points")
    return out


def mismatch_text(evaluation: dict) -> str:
    """Which cause moves which parameter, read off the classical estimator and the PINNs of each cell."""
    cells = datasets(evaluation)
    base = cells.get(("small", "nominal", "commanded"))
    if base is None or not base.get("estimator"):
        return ""
    lines = []
    est0 = base["estimator"]["theta_err_pct"]
    within = max(base["estimator"]["err_over_crlb"].values())
    lines.append(f"- **Reference** (small regime, nominal simulator): the classical estimator is within "
                 f"{within:.1f} σ on every parameter, so the bound and the estimator agree where the model holds.")
    for key in [("small", f, "commanded") for f in ("high", "motor-lag", "rotor-drag", "rotor-gyro")]:
        d = cells.get(key)
        if d is None or not d.get("estimator"):
            continue
        moved = _moved(d["estimator"]["theta_err_pct"], est0, d["crlb_std"], d["theta_true"])
        lines.append(f"- **Fidelity, {FIDELITY_LABELS[key[1]]}** (same small-angle flights): the classical "
                     f"estimator moves " + (", ".join(moved) if moved else f"no parameter by more than "
                                            f"{MOVED_SIGMA:g} σ") + " against the nominal simulator.")
    agg, real = cells.get(("aggressive", "nominal", "commanded")), cells.get(("aggressive", "nominal", "realized"))
    if agg is not None and real is not None:
        sat = 100 * agg.get("saturated_fraction", float("nan"))
        parts = []
        by_arch_real = {m.get("architecture"): m for m in _models_on(evaluation, cell_key(real))}
        for m in _models_on(evaluation, cell_key(agg)):
            r = by_arch_real.get(m.get("architecture"))
            if r is None:
                continue
            moved = _moved(m["theta_err_pct"], r["theta_err_pct"], agg["crlb_std"], agg["theta_true"])
            parts.append(f"{m['name']} against {r['name']}: " + (", ".join(moved) if moved else "nothing beyond "
                                                                 f"{MOVED_SIGMA:g} σ"))
        if parts:
            lines.append(f"- **Saturation** (aggressive flights, {sat:.1f} % of samples with a clipped rotor): "
                         "logging the command instead of the realized wrench moves the PINNs' parameters by "
                         + "; ".join(parts) + ". (The classical estimator drops saturated samples when the "
                         "command is logged, so saturation does not reach it.)")
    if agg is not None:
        ratio = {n: base["crlb_std"][n] / agg["crlb_std"][n] for n in INERTIAS
                 if n in base["crlb_std"] and agg["crlb_std"].get(n)}
        if ratio:
            lines.append("- **Observability**: aggressive flights shrink the inertias' CRLB σ by "
                         + ", ".join(f"{n} {r:.1f}×" for n, r in ratio.items())
                         + " against the small-angle flights.")
    hi_small = cells.get(("small", "high", "commanded"))
    hi_agg = cells.get(("aggressive", "high", "commanded"))
    worst = {k: _worst_inertia(d["estimator"]["theta_err_pct"]) for k, d in cells.items() if d.get("estimator")}
    if hi_small is not None and hi_agg is not None and worst.get(cell_key(hi_small)) is not None:
        lines.append(f"- **Against the paper** (5 % with small angles, 46 % with aggressive ones): the classical "
                     f"estimator's largest inertia error is {worst[cell_key(base)]:.2f} % (small) and "
                     + (f"{worst[cell_key(agg)]:.2f} % (aggressive) " if agg is not None and
                        worst.get(cell_key(agg)) is not None else "")
                     + f"in the nominal simulator, and {worst[cell_key(hi_small)]:.1f} % (small) and "
                     f"{worst[cell_key(hi_agg)]:.1f} % (aggressive) in the high-fidelity one: the error of the "
                     "size the paper reports comes with the simulator's fidelity, at small angles as much as at "
                     "large ones.")
    lagged = {k: d["estimator_lag"] for k, d in cells.items() if d.get("estimator_lag")}
    if lagged:
        parts = [f"{cell_label(k)}: largest inertia error {_worst_inertia(e['theta_err_pct']):.2f} %, every one of "
                 f"the seven parameters within {max(e['err_over_crlb'].values()):.1f} σ (τ_m "
                 f"{e['theta_err_pct']['tau_m']:+.2f} %)" for k, e in lagged.items()]
        worst_sigma = max(max(e["err_over_crlb"].values()) for e in lagged.values())
        verdict = (f"go back to the bound (all within {MOVED_SIGMA:g} σ)" if worst_sigma <= MOVED_SIGMA else
                   f"do not all come back to the bound (up to {worst_sigma:.1f} σ)")
        lines.append("- **The lag modelled**: with the motor lag in the estimator's model the errors on data with a "
                     f"lag {verdict}. " + "; ".join(parts) + ". Rotor drag and gyroscopic torque stay unmodelled.")
    form = physics_form_text(evaluation)
    if form:
        lines.append(form)
    return "\n".join(lines)


#: Architectures whose theta-hat is inside the prediction (physics plus network).
PHYSICS_FORM = ("hybrid", "hybrid_lag")
TARGET = ("m",) + INERTIAS


def _worst_sigma(m: dict, names=TARGET) -> tuple[float, str] | None:
    sig = m.get("err_over_crlb") or {}
    vals = [(sig[n], n) for n in names if n in sig]
    return max(vals) if vals else None


def physics_form_text(evaluation: dict) -> str:
    """θ̂ inside the prediction: how close the physics-plus-network models come to the bound, beside the others."""
    models = [m for m in evaluation.get("models", []) if isinstance(m, dict) and m.get("err_over_crlb")]
    form = [m for m in models if m.get("architecture") in PHYSICS_FORM]
    if not form:
        return ""
    parts = []
    for m in form:
        worst = _worst_sigma(m)
        if worst is None:
            continue
        text = (f"{m['name']} ({cell_label(cell_key(m))}): m and the inertias within {worst[0]:.1f} σ "
                f"(worst {worst[1]})")
        if "tau_m" in m["err_over_crlb"]:
            text += (f", τ_m {m['theta_err_pct']['tau_m']:+.2f} % ({m['err_over_crlb']['tau_m']:.1f} σ of the lag "
                     "model's bound)")
        parts.append(text)
    others = [m for m in models if m.get("architecture") not in PHYSICS_FORM and cell_key(m) ==
              ("small", "nominal", "commanded") and _worst_sigma(m) is not None]
    worst_other = max(others, key=lambda m: _worst_sigma(m)[0]) if others else None
    missed = [m["name"] for m in form if (_worst_sigma(m) or (0.0, ""))[0] > MOVED_SIGMA]
    verdict = (f"every one within {MOVED_SIGMA:g} σ" if not missed else
               "beyond " + f"{MOVED_SIGMA:g} σ: " + ", ".join(missed))
    line = ("- **θ̂ inside the prediction** (physics plus network: the nominal equations under θ̂ integrated over "
            "the period, plus a network residual): " + "; ".join(parts) + f"; {verdict}.")
    if worst_other is not None:
        w = _worst_sigma(worst_other)
        line += (f" The worst model of the four paper architectures on the same data, {worst_other['name']}, is "
                 f"at {w[0]:.1f} σ ({w[1]}).")
    return line


# ------------------------------------------------------------------ closed loop on the high-fidelity plant
def highfi_table(runs: list[dict], evaluation: dict) -> str:
    """RMSE on the ``+highfi`` scenarios of the oracle and of models trained on nominal or high-fidelity data."""
    hf = [r for r in runs if isinstance(r, Mapping) and str(r.get("scenario", "")).endswith("+highfi")]
    if not hf:
        return "No run on a `+highfi` scenario in this results folder."
    trained = {m.get("name"): m for m in evaluation.get("models", []) if isinstance(m, dict)}
    groups: dict[tuple, list] = {}
    for r in hf:
        groups.setdefault((r["scenario"], r.get("controller"), r.get("model")), []).append(r)
    stats = {k: summarize(rs) for k, rs in groups.items()}   # crashes; median, min, max over the runs that flew
    rows = []
    for (sc, ctrl, model), rs in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], _model_order(kv[0][2],
                                                                                                          trained))):
        m, s = trained.get(model), stats[(sc, ctrl, model)]
        data = "true equations (lag, drag, gyro)" if model == "oracle" else \
            "nominal rigid-body equations" if model == "nominal" else (
            "high-fidelity simulator" if m and m.get("fidelity") == "high" else
            "nominal simulator" if m else MISSING)
        if len(rs) == 1:
            value = fmt(s["median"], RMSE_FORMAT) if not rs[0].get("crashed") else crash_text(rs[0])
            spread = ""
        else:
            value = fmt(s["median"], RMSE_FORMAT)
            spread = (f"{fmt(s['min'], RMSE_FORMAT)}–{fmt(s['max'], RMSE_FORMAT)}" if s["flown"] else MISSING)
        rows.append([sc, ctrl, model, data, str(s["runs"]), f"{s['crashes']}/{s['runs']}", value, spread])
    text = ("The plant is the high-fidelity simulator (motor lag, rotor drag, rotor gyroscopic torque). The oracle "
            "is its true equations, with the four rotor speeds as extra states that the controller carries from "
            "period to period, following the reference these equations can fly; `nominal` is the rigid-body "
            "equations with the vehicle's values. Each learned model "
            "predicts with its own network; its parameters θ̂ enter the controller only through its vehicle "
            "description (the rotor limits from kt and kq, the input scaling and first guesses from m). Position "
            "RMSE in m (median over the runs that did not crash when there are several, with their range).")
    return text + "\n\n" + md_table(["scenario", "controller", "model", "trained on data from", "runs", "crashed",
                                     "position RMSE (m)", "range (m)"], rows) + _highfi_answer(stats, trained)


def _model_order(name: str, trained: dict) -> tuple:
    if name in ("oracle", "nominal"):
        return (0, name != "oracle", name)
    m = trained.get(name) or {}
    return (1 if m.get("fidelity", "nominal") == "nominal" else 2, False, name)


def _highfi_answer(stats: dict, trained: dict) -> str:
    """One sentence per scenario and controller: each high-fidelity-trained model against its nominal twin."""
    out = []
    for (sc, ctrl, model), s in sorted(stats.items()):
        m = trained.get(model)
        if not m or m.get("fidelity") != "high":
            continue
        twin = next((n for n, t in trained.items() if t.get("architecture") == m.get("architecture")
                     and t.get("regime") == m.get("regime") and t.get("fidelity", "nominal") == "nominal"
                     and t.get("inputs", "commanded") == "commanded" and (sc, ctrl, n) in stats), None)
        if twin is None:
            continue
        t = stats[(sc, ctrl, twin)]
        a, b = s["median"], t["median"]
        if a is None or b is None:
            out.append(f"- {sc}, {ctrl}: {model} crashed {s['crashes']}/{s['runs']}, {twin} "
                       f"{t['crashes']}/{t['runs']}.")
            continue
        out.append(f"- {sc}, {ctrl}: {model} (θ̂ inertias {_theta_text(m)}) {a:.4f} m against {twin} "
                   f"{b:.4f} m ({100 * (a - b) / b:+.0f} %).")
    out += _against_nominal(stats)
    return ("\n\n" + "\n".join(out)) if out else ""


#: The improvement over the nominal equations that counts as a learned model winning (fraction of their RMSE).
WIN_FRACTION = 0.5


def _against_nominal(stats: dict) -> list[str]:
    """Per scenario and controller: the best learned model against the nominal equations, with the runs' ranges."""
    out = []
    for (sc, ctrl, model), s in sorted(stats.items()):
        if model != "nominal" or s["median"] is None:
            continue
        learned = {k[2]: v for k, v in stats.items() if k[:2] == (sc, ctrl) and k[2] not in ("oracle", "nominal")
                   and v["median"] is not None and not v["crashes"]}
        if not learned:
            continue
        best = min(learned, key=lambda n: learned[n]["median"])
        b = learned[best]
        gain = 1.0 - b["median"] / s["median"]
        if min(b["runs"], s["runs"]) < 2:       # one run: no range to compare
            out.append(f"- {sc}, {ctrl}: the best learned model, {best}, {b['median']:.4f} m against the nominal "
                       f"equations' {s['median']:.4f} m: {100 * gain:+.0f} % better (one run, no range).")
            continue
        apart = b["max"] < s["min"]
        verdict = ("meets" if gain >= WIN_FRACTION and apart else "misses") + \
            f" the {100 * WIN_FRACTION:.0f} % goal"
        out.append(f"- {sc}, {ctrl}: the best learned model, {best}, {b['median']:.4f} m "
                   f"({b['min']:.4f}–{b['max']:.4f}) against the nominal equations' {s['median']:.4f} m "
                   f"({s['min']:.4f}–{s['max']:.4f}): {100 * gain:+.0f} % better, ranges "
                   f"{'apart' if apart else 'overlapping'}; it {verdict}.")
    return out


def _theta_text(m: dict) -> str:
    err = m.get("theta_err_pct") or {}
    return ", ".join(f"{n} {err[n]:+.0f} %" for n in INERTIAS if n in err) or MISSING
