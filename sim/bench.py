"""Benchmark of the simulator and the data generator.

Run ``python -m sim.bench [--json FILE] [--repeat N]``. Prints simulated
seconds per wall-clock second for a batch of 100 trajectories (nominal and
high fidelity) and the time to build the default dataset (100 trajectories
x 10 s) in each regime, and writes the figures as JSON. It asserts nothing:
the target (default dataset under 10 s on 2 cores) is compared and printed.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from . import HIGH_FIDELITY, NOMINAL, QuadParams, Simulator, __version__
from .identification.excitation import make_dataset
from .files import write_json

DATASET_TARGET_S = 10.0


def _sim_rate(fidelity, batch: int = 100, seconds: float = 2.0, repeat: int = 3) -> float:
    """Best-of-``repeat`` simulated seconds per wall second for ``batch`` vehicles."""
    p = QuadParams()
    rng = np.random.default_rng(0)
    x0 = np.zeros((batch, 12))
    x0[:, 2] = -1.0
    steps = int(round(seconds / 0.01))
    u = np.tile([p.m * p.g, 0.0, 0.0, 0.0], (steps, batch, 1))
    u += rng.normal(0.0, 1.0, u.shape) * [0.02, 1e-5, 1e-5, 1e-5]
    sim = Simulator(p, fidelity)
    best = np.inf
    for _ in range(repeat):
        x = x0
        t0 = time.perf_counter()
        for k in range(steps):
            x = sim.step(x, u[k])
        best = min(best, time.perf_counter() - t0)
    return seconds / best


def main(argv=None) -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(prog="python -m sim.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=Path("bench_sim.json"), help="output file (default bench_sim.json)")
    ap.add_argument("--repeat", type=int, default=3, help="repetitions, best taken (default 3)")
    args = ap.parse_args(argv)

    out = {"code_version": __version__, "python": platform.python_version(), "numpy": np.__version__,
           "machine": platform.machine(), "cpus": os.cpu_count(), "batch": 100}
    for name, fid in (("nominal", NOMINAL), ("high_fidelity", HIGH_FIDELITY)):
        rate = _sim_rate(fid, repeat=args.repeat)
        out[f"sim_seconds_per_wall_second_{name}"] = rate
        print(f"simulator, batch of 100, {name:<13}: {rate:8.1f} simulated s per wall s "
              f"({rate * 100:8.0f} vehicle-s per wall s)")
    for regime in ("small", "aggressive"):
        best = np.inf
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            make_dataset(regime, 100, 10.0, 0)
            best = min(best, time.perf_counter() - t0)
        out[f"default_dataset_seconds_{regime}"] = best
        verdict = "meets" if best < DATASET_TARGET_S else "MISSES"
        print(f"default dataset {regime:<10} (100 x 10 s): {best:6.2f} s  ({verdict} the {DATASET_TARGET_S:g} s target)")
    write_json(args.json, out)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
