"""A case as a distribution: fly it from M ensemble members and give intervals.

``python -m scenarios.studies.ensemble --model models/proposed.onnx --controller ltv --scenario figure8-fast
[--members 10] [--jobs 2] [--engine {process,ray}] [--address ADDR] [--out DIR] [--json FILE]``

Member ``k`` flies the scenario with seed ``k`` (noise and gusts redrawn) from
an initial state moved by a seeded draw
(:data:`scenarios.closed_loop.library.ENSEMBLE_X0_SIGMA`; :meth:`Scenario.member`). It
prints the crash probability with its Wilson 95 % interval and the median
RMSE of the runs that did not crash with a bootstrap 95 % interval. The runs
are a sweep: saved under ``--out`` (default ``results/ensembles``) and reused
when the same command is run again.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mpc.controllers.factory import CONTROLLERS, HORIZON
from sim.files import write_json

from ..sweeps.engines import ENGINES
from ..closed_loop.runner import RunSpec
from ..sweeps.sweep import sweep
from .stats import summarize


def ensemble_specs(scenario: str, controller: str, model: str, members: int, horizon: int = HORIZON,
                   timing: str = "ideal") -> list[RunSpec]:
    """The runs of one case's ensemble: members 0 .. ``members`` - 1."""
    return [RunSpec(scenario, controller, model, None, horizon, timing, member=k) for k in range(members)]


def fly_ensemble(scenario: str, controller: str, model: str, members: int = 10, out_dir="results/ensembles",
                 jobs: int = 1, progress: bool = True, metric: str = "rmse_position_m", **sweep_kwargs) -> dict:
    """Fly one case's ensemble (a :func:`scenarios.sweeps.sweep.sweep`) and summarize it
    (:func:`scenarios.studies.stats.summarize`)."""
    specs = ensemble_specs(scenario, controller, model, members)
    results = sweep(specs, out_dir, jobs=jobs, progress=progress, **sweep_kwargs)
    return {"case": {"scenario": scenario, "controller": controller, "model": specs[0].model_name,
                     "members": members}, "summary": summarize(results, metric),
            "runs": [{"member": s.member, "run_id": r["run_id"], "crashed": r["crashed"],
                      "crash_time_s": r.get("crash_time_s"), metric: r.get(metric)} for s, r in zip(specs, results)]}


def format_summary(out: dict) -> str:
    c, s = out["case"], out["summary"]
    lines = [f"{c['scenario']} / {c['controller']} / {c['model']}: {s['runs']} members"]
    lo, hi = s["crash_probability_ci95"]
    lines.append(f"  crashes {s['crashes']} of {s['runs']}: probability {s['crash_probability']:.2f} "
                 f"(Wilson 95 % {lo:.2f}-{hi:.2f})")
    if s["median"] is None:
        lines.append(f"  {s['metric']}: no run flew to the end")
    else:
        ci = "" if s["median_ci95"] is None else f" (bootstrap 95 % {s['median_ci95'][0]:.4f}-{s['median_ci95'][1]:.4f})"
        lines.append(f"  {s['metric']} over the {s['flown']} runs that flew: median {s['median']:.4f}{ci}, "
                     f"range {s['min']:.4f}-{s['max']:.4f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    """Fly the ensemble and print its summary."""
    ap = argparse.ArgumentParser(prog="python -m scenarios.studies.ensemble", description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="{oracle,FILE.onnx}")
    ap.add_argument("--controller", required=True, choices=CONTROLLERS)
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--members", type=int, default=10, help="ensemble members (default 10)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes, or local Ray CPUs (default 1)")
    ap.add_argument("--engine", choices=ENGINES, default="process")
    ap.add_argument("--address", default=None, metavar="ADDR", help="Ray cluster (with --engine ray)")
    ap.add_argument("--out", type=Path, default=Path("results/ensembles"), help="results folder (runs are reused)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.members < 1 or args.jobs < 1:
        raise SystemExit("error: --members and --jobs must be >= 1")
    try:
        out = fly_ensemble(args.scenario, args.controller, args.model, args.members, args.out, args.jobs,
                           engine=args.engine, address=args.address)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    print(format_summary(out))
    if args.json:
        write_json(args.json, out)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
