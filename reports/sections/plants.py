"""Other plants and vehicles: the same flights on RotorPy, and the nominal equations on other vehicles.

Reads the runs whose ``plant`` or ``vehicle`` is not the results folder's own
(see :func:`split_by_plant`) and sets them beside that plant's runs of the
same case. Every sentence is computed from the runs.
"""

from __future__ import annotations

from ..tables import MISSING, crash_text, fmt, md_table

#: The plant and vehicle of a result that predates them.
DEFAULT_PLANT = "sim"
DEFAULT_VEHICLE = "rolling-spider"
PLANT_LABELS = {"sim": "our simulator", "rotorpy-ideal": "RotorPy, ideal (instant motors, no drag)",
                "rotorpy": "RotorPy, motor lag and aerodynamics"}
PLANT_ORDER = ("sim", "rotorpy-ideal", "rotorpy")
NO_RUNS = ("No run on another plant or vehicle in this results folder (the main job flies them when RotorPy is "
           "installed: `pip install -e '.[rotorpy]'`).")
#: Columns of the compute-time table (:func:`timing_table`).
TIMING_HEADER = ["plant", "vehicle", "scenario", "controller", "model", "RMSE (mm)", "load median (ms)",
                 "worst load (ms)", "periods over 10 ms / periods (by its own work)",
                 "input latency median / p99 (ms)"]


def where(run: dict) -> tuple[str, str]:
    """(plant, vehicle) of a result (the defaults for results written before plants existed)."""
    return run.get("plant") or DEFAULT_PLANT, run.get("vehicle") or DEFAULT_VEHICLE


def plant_label(plant: str) -> str:
    """How the report names a plant."""
    return PLANT_LABELS.get(plant, plant)


def _plant_rank(plant: str) -> int:
    """A plant's place in the report's order (:data:`PLANT_ORDER`; unknown plants last)."""
    return PLANT_ORDER.index(plant) if plant in PLANT_ORDER else len(PLANT_ORDER)


def where_sentence(runs: list[dict]) -> str:
    """One sentence naming the plant and vehicle of every run in ``runs`` (with counts when there are several)."""
    counts: dict[tuple[str, str], int] = {}
    for r in runs:
        counts[where(r)] = counts.get(where(r), 0) + 1
    if not counts:
        return ""
    if len(counts) == 1:
        (plant, vehicle), n = next(iter(counts.items()))
        return f"All {n} run{'s' if n > 1 else ''} here flew on {plant_label(plant)} with the {vehicle}."
    order = sorted(counts, key=lambda k: (_plant_rank(k[0]), k[1]))
    return ("The runs here flew on " + "; ".join(f"{plant_label(p)} with the {v} ({counts[(p, v)]} run"
                                                f"{'s' if counts[(p, v)] > 1 else ''})" for p, v in order) + ".")


def timing_table(runs: list[dict]) -> str:
    """Each run's RMSE beside its median and worst load, its periods over 10 ms and its input latency, with its plant
    and vehicle."""
    rows = []
    def key(r):
        plant, vehicle = where(r)
        return _plant_rank(plant), vehicle, str(r.get("scenario")), str(r.get("controller")), str(r.get("model"))

    for r in sorted(runs, key=key):
        sm, lat = r.get("solve_ms") or {}, r.get("latency_ms") or {}
        flown = not r.get("error") and bool(sm)
        rows.append([plant_label(where(r)[0]), where(r)[1], r.get("scenario"),
                     str(r.get("controller")).upper() + (" (real-time iteration)" if r.get("scheme") == "rti" else ""),
                     r.get("model"), _cell(r),
                     fmt(sm.get("median"), ".2f") if flown else MISSING,
                     fmt(sm.get("max"), ".2f") if flown else MISSING,
                     _misses(r) if flown else MISSING,
                     f"{fmt(lat.get('median'), '.2f')} / {fmt(lat.get('p99'), '.2f')}" if flown and lat else MISSING])
    return ("**Compute time on each plant and vehicle.** Per run: position RMSE (mm, or the crash), the "
            "controller's median and largest load per 10 ms period (all its work of the period; with the real-time "
            "iteration the next period's preparation too), the periods whose load was longer than the period (and "
            "in brackets those whose controller's own work, its thread's CPU time, was: the others are periods in "
            "which the machine gave the core to something else), and the input latency (from the measurement to the "
            "input out).\n\n" + md_table(TIMING_HEADER, rows))


def _misses(run: dict) -> str:
    """``"over / periods (own)"``: the periods whose load passed 10 ms, and of them those the controller's own work
    made so (records from before the CPU time was measured: without the brackets)."""
    own = run.get("own_work_misses")
    return f"{run.get('deadline_misses')} / {run.get('steps')}" + ("" if own is None else f" ({own})")


def split_by_plant(runs: list[dict], plan: dict | None) -> tuple[list[dict], list[dict]]:
    """(runs on the folder's own plant and vehicle, the others). The folder's own: the plan's (its vehicle by name),
    else the defaults."""
    plan = plan or {}
    own = (plan.get("plant") or DEFAULT_PLANT, plan.get("vehicle") or DEFAULT_VEHICLE)
    mine = [r for r in runs if where(r) == own]
    return mine, [r for r in runs if where(r) != own]


def _cell(run: dict | None) -> str:
    if run is None:
        return MISSING
    if run.get("error") or run.get("crashed"):
        return crash_text(run)
    return fmt(1e3 * run["rmse_position_m"], ".3g") if run.get("rmse_position_m") is not None else MISSING


def plants_section(own: list[dict], others: list[dict]) -> str:
    """The tables and sentences of the report's section on other plants and vehicles."""
    single = [r for r in own + others if r.get("member") is None and r.get("timing", "ideal") == "ideal"]
    ext = [r for r in others if r.get("member") is None and r.get("timing", "ideal") == "ideal"]
    if not ext:
        return where_sentence(own) + (" " if own else "") + NO_RUNS
    by = {(r.get("scenario"), r.get("controller"), r.get("model"), *where(r)): r for r in single}
    parts = []
    # 1. The Rolling Spider (or the folder's vehicle) on every plant: one row per model.
    vehicles = sorted({where(r)[1] for r in ext})
    own_vehicle = where(own[0])[1] if own else DEFAULT_VEHICLE
    cases = sorted({(r.get("scenario"), r.get("controller")) for r in ext if where(r)[1] == own_vehicle})
    for sc, ctrl in cases:
        plants = [p for p in PLANT_ORDER if any(k[:2] == (sc, ctrl) and k[3] == p and k[4] == own_vehicle
                                                for k in by)]
        models = sorted({k[2] for k in by if k[:2] == (sc, ctrl) and k[4] == own_vehicle
                         and any(k2[:3] == k[:3] and k2[3] != DEFAULT_PLANT for k2 in by)},
                        key=lambda m: (m not in ("oracle", "nominal"), m != "oracle", m))
        rows = []
        for m in models:
            row = [m]
            for p in plants:
                r = by.get((sc, ctrl, m, p, own_vehicle))
                if r is None and m == "nominal" and p == "sim":
                    r = by.get((sc, ctrl, "oracle", p, own_vehicle))    # on our simulator the two are one model
                row.append(_cell(r))
            rows.append(row)
        parts.append(f"**{sc}, {ctrl.upper()}, {own_vehicle}.** Position RMSE in mm. `oracle` is the plant's own "
                     f"equations where they are known (on RotorPy's ideal set-up the rigid-body equations without "
                     f"drag); `nominal` the rigid-body equations with the vehicle's values (on our simulator the "
                     f"oracle itself).\n\n"
                     + md_table(["model"] + [plant_label(p) for p in plants], rows))
        parts.append(_compare(by, sc, ctrl, own_vehicle, models))
    # 2. Other vehicles: the nominal equations on each plant.
    other_v = [v for v in vehicles if v != own_vehicle]
    if other_v:
        rows = []
        for v in other_v:
            for sc, ctrl in sorted({(k[0], k[1]) for k in by if k[4] == v}):
                for m in sorted({k[2] for k in by if k[4] == v and k[:2] == (sc, ctrl)}):
                    rows.append([v, sc, ctrl.upper(), m] + [_cell(by.get((sc, ctrl, m, p, v))) for p in PLANT_ORDER])
        parts.append("**Other vehicles** (RotorPy's presets). Position RMSE in mm, or the crash.\n\n"
                     + md_table(["vehicle", "scenario", "controller", "model"] + [PLANT_LABELS[p] for p in PLANT_ORDER],
                                rows))
    parts.append(timing_table(ext))
    return "\n\n".join(p for p in [where_sentence(own + others)] + parts if p)


def _compare(by: dict, sc: str, ctrl: str, vehicle: str, models: list[str]) -> str:
    """Sentences: the oracle on both ideal plants; each model's RotorPy-ideal figure against our simulator's."""
    out = []
    o_sim, o_rp = by.get((sc, ctrl, "oracle", "sim", vehicle)), by.get((sc, ctrl, "oracle", "rotorpy-ideal", vehicle))
    if o_sim and o_rp and o_sim.get("rmse_position_m") is not None and o_rp.get("rmse_position_m") is not None:
        out.append(f"The oracle tracks to {1e3 * o_rp['rmse_position_m']:.3f} mm on RotorPy's ideal set-up and "
                   f"{1e3 * o_sim['rmse_position_m']:.3f} mm on our simulator.")
    diffs = []
    for m in models:
        a, b = by.get((sc, ctrl, m, "sim", vehicle)), by.get((sc, ctrl, m, "rotorpy-ideal", vehicle))
        if m in ("oracle", "nominal") or not a or not b:
            continue
        if a.get("rmse_position_m") and b.get("rmse_position_m"):
            diffs.append(abs(b["rmse_position_m"] / a["rmse_position_m"] - 1))
    if diffs:
        out.append(f"Learned models on RotorPy's ideal set-up against our simulator: RMSE within "
                   f"{100 * max(diffs):.1f} % (largest relative difference over {len(diffs)} models).")
    n = by.get((sc, ctrl, "nominal", "rotorpy", vehicle))
    if n and n.get("rmse_position_m") is not None:
        better = [m for m in models if m not in ("oracle", "nominal")
                  and (by.get((sc, ctrl, m, "rotorpy", vehicle)) or {}).get("rmse_position_m") is not None
                  and by[(sc, ctrl, m, "rotorpy", vehicle)]["rmse_position_m"] < n["rmse_position_m"]
                  and not by[(sc, ctrl, m, "rotorpy", vehicle)].get("crashed")]
        out.append(f"With RotorPy's motor lag and aerodynamics the nominal equations track to "
                   f"{1e3 * n['rmse_position_m']:.1f} mm; "
                   + (f"{len(better)} learned model(s) do better: {', '.join(better)}." if better else
                      "no learned model does better."))
    return " ".join(out)
