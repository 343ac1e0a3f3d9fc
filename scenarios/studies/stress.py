"""How strong must measurement noise and input delay be before the true model's tracking degrades?

The ``+noise`` and ``+delay`` variants are meant to stress the controller.
This tool sweeps their level with the oracle (the true equations) and prints
the position RMSE and the settled error of each level, so that the levels of
the variants can be chosen where the oracle degrades measurably::

    python -m scenarios.studies.stress [--controller ltv] [--jobs 2] [--json FILE]

Noise levels are multiples of a motion-capture + IMU baseline (1 mm position,
1 mrad attitude, 5 mrad/s body rates, 5 mm/s velocity); delays are whole
control periods. It asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from sim.files import write_json
from sim.params import DT, NoiseModel

BASELINE_NOISE = NoiseModel(position=1e-3, attitude=1e-3, body_rate=5e-3, velocity=5e-3)
NOISE_FACTORS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)
DELAYS = (0, 1, 2, 3, 4, 6)
SCENARIOS = ("hover", "figure8-fast")


def _scaled(f: float) -> NoiseModel | None:
    if f == 0:
        return None
    n = BASELINE_NOISE
    return NoiseModel(n.position * f, n.attitude * f, n.body_rate * f, n.velocity * f, 0.0)


def _one(args):
    from ..closed_loop.library import get_scenario
    from ..closed_loop.runner import RunSpec, fly

    name, controller, kind, level = args
    base = get_scenario(name)
    if kind == "noise":
        sc = dataclasses.replace(base, noise=_scaled(level))
    else:
        sc = dataclasses.replace(base, delay_steps=int(level))
    r, _ = fly(RunSpec(name, controller, "oracle"), scenario=sc)
    return {"scenario": name, "controller": controller, "kind": kind, "level": level,
            "rmse_position_m": r["rmse_position_m"], "settled_error_m": r["settled_error_m"],
            "max_position_error_m": r["max_position_error_m"], "crashed": r["crashed"]}


def sweep_levels(controller: str = "ltv", jobs: int = 2, progress: bool = True) -> list[dict]:
    """One row per (scenario, noise factor or delay) with the oracle's metrics."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from sim.workers import worker_init

    tasks = [(s, controller, "noise", f) for s in SCENARIOS for f in NOISE_FACTORS]
    tasks += [(s, controller, "delay", d) for s in SCENARIOS for d in DELAYS]
    worker_init()
    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"), initializer=worker_init) as pool:
        it = pool.map(_one, tasks)
        if progress:
            from tqdm import tqdm
            it = tqdm(it, total=len(tasks), desc="stress levels", unit="run")
        return list(it)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m scenarios.studies.stress", description=__doc__.split("\n\n")[0])
    ap.add_argument("--controller", default="ltv", choices=("ltv", "lqr", "nmpc"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", default=None, help="write the rows as JSON")
    a = ap.parse_args(argv)
    rows = sweep_levels(a.controller, a.jobs, sys.stderr.isatty())
    n = BASELINE_NOISE
    print(f"noise factor x (position {n.position * 1e3:g} mm, attitude {n.attitude * 1e3:g} mrad, "
          f"rates {n.body_rate * 1e3:g} mrad/s, velocity {n.velocity * 1e3:g} mm/s); delay in periods of {DT * 1e3:g} ms")
    print(f"{'scenario':<14}{'kind':<7}{'level':>6}{'RMSE (mm)':>12}{'settled (mm)':>14}{'max (mm)':>10}  crash")
    for r in rows:
        def mm(k):
            return "-" if r[k] is None else f"{r[k] * 1e3:.3f}"
        print(f"{r['scenario']:<14}{r['kind']:<7}{r['level']:>6g}{mm('rmse_position_m'):>12}"
              f"{mm('settled_error_m'):>14}{mm('max_position_error_m'):>10}  {'yes' if r['crashed'] else 'no'}")
    if a.json:
        write_json(a.json, {"controller": a.controller, "baseline_noise": dataclasses.asdict(BASELINE_NOISE),
                            "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
