"""How reproducible is one closed-loop RMSE? Rerun a case from initial states perturbed by nanometres.

``python -m scenarios.studies.sensitivity --model models/fourier.onnx --controller ltv --scenario figure8-fast
[--trials 5] [--step 1e-9] [--jobs 1] [--json FILE]``

Trial ``k`` starts ``k * step`` m north of the scenario's initial state (trial 0 is the scenario
itself). A well-posed case gives the same RMSE to many digits; a case on the edge of what the
model can fly gives a spread, and then a single run's RMSE is one sample of a distribution.
Nothing is asserted; the figures are printed and written as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
from pathlib import Path

from mpc.controllers.factory import CONTROLLERS, HORIZON
from sim.files import write_json

from ..closed_loop.runner import RunSpec, fly


def _trial(spec: RunSpec, offset_m: float, model=None) -> dict:
    from ..closed_loop.library import get_scenario

    base = get_scenario(spec.scenario, spec.seed)
    x0 = list(base.x0)
    x0[0] += offset_m
    res, _ = fly(spec, scenario=dataclasses.replace(base, x0=tuple(x0)), model=model)
    return {"offset_m": offset_m, "rmse_position_m": res["rmse_position_m"], "crashed": res["crashed"],
            "crash_time_s": res["crash_time_s"], "solver_failures": res["solver_failures"]}


def perturbed_rmse(spec: RunSpec, trials: int = 5, step_m: float = 1e-9, jobs: int = 1) -> list[dict]:
    """One result per trial (in order): the start offset (m), RMSE (m), crash flag and time.

    ``jobs`` > 1 flies the trials in that many processes (same results).
    """
    from mpc.prediction.models import load_model

    model = load_model(spec.model)      # a bad model file fails here, once, with the contract's message
    offsets = [k * step_m for k in range(trials)]
    if jobs == 1:
        return [_trial(spec, o, model) for o in offsets]
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from sim.workers import worker_init

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"), initializer=worker_init) as pool:
        return list(pool.map(_trial, [spec] * trials, offsets))


def main(argv=None) -> int:
    """Run the check and print its figures."""
    ap = argparse.ArgumentParser(prog="python -m scenarios.studies.sensitivity", description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--controller", required=True, choices=CONTROLLERS)
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--step", type=float, default=1e-9, help="start offset between trials, m (default 1e-9)")
    ap.add_argument("--horizon", type=int, default=HORIZON)
    ap.add_argument("--jobs", type=int, default=1, help="processes (default 1)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.trials < 2 or not args.step > 0 or args.jobs < 1:
        raise SystemExit("--trials must be >= 2, --step > 0 and --jobs >= 1")
    try:
        spec = RunSpec(args.scenario, args.controller, args.model, None, args.horizon)
        rows = perturbed_rmse(spec, args.trials, args.step, args.jobs)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    for r in rows:
        crash = f"crashed at {r['crash_time_s']} s" if r["crashed"] else "flew"
        print(f"offset {r['offset_m']:.1e} m   RMSE {r['rmse_position_m']:.4f} m   {crash}   "
              f"solver failures {r['solver_failures']}")
    rm = [r["rmse_position_m"] for r in rows if r["rmse_position_m"] is not None]
    if rm:
        med = statistics.median(rm)
        print(f"{spec.run_id}: RMSE {min(rm):.4f}-{max(rm):.4f} m over {len(rows)} starts "
              f"(spread {max(rm) - min(rm):.2g} m, {100 * (max(rm) - min(rm)) / med:.1f} % of the median "
              f"{med:.4f} m), crashes {sum(r['crashed'] for r in rows)}")
    if args.json:
        write_json(args.json, {"spec": dataclasses.asdict(spec), "trials": rows})
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
