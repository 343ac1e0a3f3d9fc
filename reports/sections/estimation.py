"""The report's section on the state estimator: the disturbance and noise cases flown with and without it."""

from __future__ import annotations

from ..labels import controller_label
from ..tables import MISSING, crash_text, fmt, md_table

#: Shown when the results folder has no run with the estimator.
NO_ESTIMATOR_RUNS = ("No run of this folder flew with the state estimator (`pinnmpc run` flies the disturbance and "
                     "noise cases both ways by default; `--estimator none` leaves them out).")


def _mm(run: dict | None, key: str) -> str:
    if run is None:
        return MISSING
    if run.get("error") or run.get("crashed"):
        return crash_text(run) if key == "rmse_position_m" else MISSING
    v = run.get(key)
    return fmt(None if v is None else 1e3 * v, ".1f")


def split_by_estimator(runs: list[dict]) -> tuple[list[dict], list[dict]]:
    """``(without, with)``: the runs without a state estimator (every other section's) and those with one."""
    without = [r for r in runs if r.get("estimator", "none") == "none"]
    return without, [r for r in runs if r.get("estimator", "none") != "none"]


def estimation_section(without: list[dict], with_est: list[dict]) -> str:
    """One row per case flown with the estimator: RMSE and settled error with it and, where flown, without it.

    Parameters
    ----------
    without, with_est : list of dict
        Run results (as ``fly --json``) without and with the estimator.
    """
    if not with_est:
        return NO_ESTIMATOR_RUNS
    twin = {(r["scenario"], r["controller"], r["model"], r.get("timing", "ideal")): r for r in without}
    header = ["scenario", "controller", "model", "RMSE without (mm)", "RMSE with (mm)", "settled without (mm)",
              "settled with (mm)", "filter median (ms)", "NEES mean"]
    rows = []
    for r in sorted(with_est, key=lambda r: (r["scenario"], r["controller"], r["model"] != "oracle", r["model"])):
        t = twin.get((r["scenario"], r["controller"], r["model"], r.get("timing", "ideal")))
        est = r.get("estimator_ms") or {}
        rows.append([r["scenario"], controller_label(r["controller"]), r["model"],
                     _mm(t, "rmse_position_m"), _mm(r, "rmse_position_m"),
                     _mm(t, "settled_error_m"), _mm(r, "settled_error_m"),
                     fmt(est.get("median"), ".2f"), fmt(r.get("nees_mean"), ".3g")])
    text = ("The controllers see either the true state plus the scenario's noise (without) or the estimate of an "
            "extended Kalman filter on their own model, fed by motion capture and an IMU, with a disturbance "
            "estimate that enters their prediction and their target (with; `docs/estimation.md`). Settled error: "
            "the largest position error over the last 2 s. The filter's time is charged to the controller. The "
            "NEES is the estimate's normalized error (12 for a consistent filter); a learned model's is large, "
            "because the filter trusts the model's prediction more than it deserves.")
    return text + "\n\n" + md_table(header, rows)
