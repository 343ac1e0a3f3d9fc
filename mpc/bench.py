"""Benchmark of the controllers: per-step solve time for each controller x prediction model.

Run ``python -m mpc.bench [--models models] [--controllers nmpc,ltv,lqr] [--json FILE]``.
For the oracle and each shipped ONNX model, each controller flies a 5 s
hover (from a 0.3 m offset) and one slow figure-8 lap (period 6 s, A =
0.75 m) on the nominal simulator; the solve time of every call is recorded
(median / p95 / max, ms) with the deadline misses (> 10 ms), solver failures
and fallbacks, and the position RMSE of the run. It also prints the floor:
one batched model + Jacobian evaluation over the whole horizon (one call).
Nothing is asserted; the figures are written as JSON.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from sim import Simulator
from sim.files import write_json
from sim.params import DT, NX

from .controller import figure8_reference, hover_reference
from .lqr import LQRController
from .ltv import LTVMPC, LTVSettings
from .models import AnalyticModel, OnnxModel
from .nmpc import NMPC, NMPCSettings

HORIZON = 30


def _controller(kind: str, model, reference):
    if kind == "nmpc":
        return NMPC(model, reference, NMPCSettings(horizon=HORIZON))
    if kind == "ltv":
        return LTVMPC(model, reference, LTVSettings(horizon=HORIZON))
    return LQRController(reference)


def run(kind: str, model, reference, x0: np.ndarray, seconds: float) -> dict:
    """Fly one case; solve-time statistics, counts and position RMSE."""
    ctrl = _controller(kind, model, reference)
    sim = Simulator()
    x = x0.copy()
    times, err = [], []
    failures = fallbacks = 0
    for k in range(int(round(seconds / DT))):
        t = k * DT
        u, info = ctrl(x, t)
        times.append(info.solve_time_s)
        failures += info.status not in ("optimal", "lqr")
        fallbacks += info.fallback is not None
        x = sim.step(x, u)
        err.append(np.linalg.norm(x[0:3] - reference(np.array([t + DT]))[0, 0:3]))
        if not np.all(np.isfinite(x)) or err[-1] > 2.0:
            break
    ms = 1e3 * np.array(times)
    return {"solve_ms": {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "max": float(ms.max())},
            "deadline_misses": int(np.sum(ms > 1e3 * DT)), "solver_failures": int(failures),
            "fallbacks": int(fallbacks), "rmse_position_m": float(np.sqrt(np.mean(np.square(err)))),
            "steps": len(times)}


def floor_us(model, repeat: int = 200) -> float:
    """Microseconds of one batched model + Jacobian evaluation over the horizon."""
    x = np.zeros((HORIZON, NX))
    x[:, 2] = -1.0
    u = np.tile([0.667, 0.0, 0.0, 0.0], (HORIZON, 1))
    model.linearize(x, u)
    t0 = time.perf_counter()
    for _ in range(repeat):
        model.linearize(x, u)
    return (time.perf_counter() - t0) / repeat * 1e6


def main(argv=None) -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(prog="python -m mpc.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("models"))
    ap.add_argument("--controllers", default="nmpc,ltv,lqr")
    ap.add_argument("--json", type=Path, default=Path("bench_mpc.json"))
    args = ap.parse_args(argv)
    kinds = [k for k in args.controllers.split(",") if k]
    bad = set(kinds) - {"nmpc", "ltv", "lqr"}
    if bad:
        raise SystemExit(f"--controllers: unknown {sorted(bad)}; choose from nmpc, ltv, lqr")
    files = sorted(p for p in args.models.glob("*.onnx") if not p.name.endswith(".jac.onnx"))
    models = [("oracle", AnalyticModel())] + [(f.stem, OnnxModel(f)) for f in files]
    x_hover = np.zeros(NX)
    x_hover[0:3] = [0.3, 0.0, -1.0]
    fig8 = figure8_reference()
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "horizon": HORIZON, "cases": []}
    print(f"{'controller':<6}{'model':<22}{'case':<10}{'median':>8}{'p95':>8}{'max':>8} ms"
          f"{'misses':>8}{'fail':>6}{'fallb':>6}{'RMSE m':>9}{'floor us':>10}")
    for name, model in models:
        fl = floor_us(model)
        for kind in kinds:
            if kind == "lqr" and name != "oracle":
                continue  # LQR uses the analytic hover linearization whatever the model
            for case, ref, x0, secs in (("hover", hover_reference(), x_hover, 5.0),
                                        ("figure8", fig8, fig8(np.array([0.0]))[0], 6.0)):
                r = run(kind, model, ref, x0, secs)
                out["cases"].append({"controller": kind, "model": name, "case": case, "floor_us": fl, **r})
                s = r["solve_ms"]
                print(f"{kind:<6}{name:<22}{case:<10}{s['median']:>8.2f}{s['p95']:>8.2f}{s['max']:>8.1f}   "
                      f"{r['deadline_misses']:>8}{r['solver_failures']:>6}{r['fallbacks']:>6}"
                      f"{r['rmse_position_m']:>9.4f}{fl:>10.0f}")
    write_json(args.json, out)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
