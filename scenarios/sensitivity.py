"""How reproducible is one closed-loop RMSE? Rerun a case from initial states perturbed by nanometres.

``python -m scenarios.sensitivity --model models/fourier.onnx --controller ltv --scenario figure8-fast
[--trials 5] [--step 1e-9] [--json FILE]``

Trial ``k`` starts ``k * step`` m north of the scenario's initial state (trial 0 is the scenario
itself). A well-posed case gives the same RMSE to many digits; a case on the edge of what the
model can fly gives a spread, and then a single run's RMSE is one sample of a distribution.
Nothing is asserted; the figures are printed and written as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from sim.files import write_json

from .runner import CONTROLLERS, HORIZON, RunSpec, fly


def perturbed_rmse(spec: RunSpec, trials: int = 5, step_m: float = 1e-9) -> list[dict]:
    """One result per trial: the start offset (m), RMSE (m), crash flag and time."""
    from mpc.models import load_model

    from .library import get_scenario

    base = get_scenario(spec.scenario, spec.seed)
    model = load_model(spec.model)
    out = []
    for k in range(trials):
        x0 = list(base.x0)
        x0[0] += k * step_m
        res, _ = fly(spec, scenario=dataclasses.replace(base, x0=tuple(x0)), model=model)
        out.append({"offset_m": k * step_m, "rmse_position_m": res["rmse_position_m"], "crashed": res["crashed"],
                    "crash_time_s": res["crash_time_s"], "solver_failures": res["solver_failures"]})
    return out


def main(argv=None) -> int:
    """Run the check and print its figures."""
    ap = argparse.ArgumentParser(prog="python -m scenarios.sensitivity", description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--controller", required=True, choices=CONTROLLERS)
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--trials", type=int, default=5)
    ap.add_argument("--step", type=float, default=1e-9, help="start offset between trials, m (default 1e-9)")
    ap.add_argument("--horizon", type=int, default=HORIZON)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.trials < 2 or not args.step > 0:
        raise SystemExit("--trials must be >= 2 and --step > 0")
    try:
        spec = RunSpec(args.scenario, args.controller, args.model, None, args.horizon)
        rows = perturbed_rmse(spec, args.trials, args.step)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    for r in rows:
        crash = f"crashed at {r['crash_time_s']} s" if r["crashed"] else "flew"
        print(f"offset {r['offset_m']:.1e} m   RMSE {r['rmse_position_m']:.4f} m   {crash}   "
              f"solver failures {r['solver_failures']}")
    rm = [r["rmse_position_m"] for r in rows]
    print(f"{spec.run_id}: RMSE {min(rm):.4f}-{max(rm):.4f} m over {len(rows)} starts "
          f"(spread {max(rm) - min(rm):.2g} m), crashes {sum(r['crashed'] for r in rows)}")
    if args.json:
        write_json(args.json, {"spec": dataclasses.asdict(spec), "trials": rows})
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
