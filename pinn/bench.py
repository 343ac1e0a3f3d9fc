"""Benchmark of PINN training and of the exported derivative paths.

Run ``python -m pinn.bench [--models models] [--json FILE] [--skip-quick]``.
Prints and writes (no assertions):

* quick-profile training time of each architecture on the default dataset
  (2 threads; the target is under 60 s on 2 cores);
* full-profile training times recorded in ``models/manifest.json`` (target
  under 15 minutes each);
* the two ways to get exact derivatives without torch, for the MPC: the
  derivative graph ``<name>.jac.onnx`` through onnxruntime (one stage, and a
  whole 30-stage horizon in one batched call) against CasADi's own ONNX
  import rebuilt as CasADi expressions (``GraphBuilder.create(name,
  {"symbolic": True})``). CasADi's onnxruntime-backed import gives no
  derivatives for a file without ``jac_*`` outputs, so it is timed for
  evaluation only.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from sim.files import write_json

ARCHS = ("baseline", "modular", "fourier", "proposed")


def _best(fn, repeat: int = 5, number: int = 50) -> float:
    """Best mean time of ``fn()`` in microseconds."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best * 1e6


def quick_training_times() -> dict:
    """Seconds to train each architecture with the quick profile (2 threads)."""
    from sim.identification.excitation import make_dataset

    from .train import make_config, train

    ds = make_dataset("small", 100, 10.0, 0)
    out = {}
    for arch in ARCHS:
        t0 = time.perf_counter()
        train(ds, make_config(arch, "quick", 0, threads=2))
        out[arch] = time.perf_counter() - t0
        print(f"quick profile {arch:<9}: {out[arch]:6.1f} s  ({'meets' if out[arch] < 60 else 'MISSES'} the 60 s target)")
    return out


def derivative_paths(model: Path) -> dict:
    """Microseconds per call of each derivative path for one model."""
    import casadi
    import onnxruntime

    from mpc.prediction.contract import jacobian_path, open_session

    lib = glob.glob(os.path.join(os.path.dirname(onnxruntime.__file__), "capi", "libonnxruntime.so*"))
    if lib:
        os.environ.setdefault("CASADI_ONNXRUNTIME_LIB", lib[0])
    x = np.zeros((1, 12))
    x[0, 2] = -1.0
    u = np.array([[0.667, 0.0, 0.0, 0.0]])
    out = {}
    sess, jac = open_session(model), open_session(jacobian_path(model))
    out["ort_model_eval_batch1_us"] = _best(lambda: sess.run(["x_next"], {"x": x, "u": u}))
    out["ort_jac_graph_batch1_us"] = _best(lambda: jac.run(["A", "B"], {"x": x, "u": u}))
    X, U = np.repeat(x, 30, 0), np.repeat(u, 30, 0)
    out["ort_jac_graph_batch30_us"] = _best(lambda: jac.run(["A", "B"], {"x": X, "u": U}))

    gb = casadi.GraphBuilder(str(model), {})
    gb.bind_dim("batch", 1)
    f_ort = gb.create("f_ort", {})
    out["casadi_ort_import_eval_us"] = _best(lambda: f_ort(x, u))
    f_sym = gb.create("f_sym", {"symbolic": True})
    xs, us = casadi.MX.sym("x", 1, 12), casadi.MX.sym("u", 1, 4)
    J = casadi.Function("J", [xs, us], [casadi.jacobian(f_sym(xs, us), casadi.horzcat(xs, us))])
    out["casadi_symbolic_import_eval_us"] = _best(lambda: f_sym(x, u), number=20)
    out["casadi_symbolic_import_jac_us"] = _best(lambda: J(x, u), number=20)
    # Same Jacobian both ways (a sanity check of the timing comparison).
    A, B = jac.run(["A", "B"], {"x": x, "u": u})
    Jc = np.array(J(x, u))
    out["max_abs_difference_ort_vs_casadi_jacobian"] = float(np.max(np.abs(np.concatenate([A[0], B[0]], 1) - Jc)))
    return out


def main(argv=None) -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(prog="python -m pinn.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("models"))
    ap.add_argument("--json", type=Path, default=Path("bench_pinn.json"))
    ap.add_argument("--skip-quick", action="store_true", help="skip the quick-training timings")
    args = ap.parse_args(argv)
    out = {"python": platform.python_version(), "cpus": os.cpu_count()}
    if not args.skip_quick:
        out["quick_training_seconds"] = quick_training_times()
    manifest = json.loads((args.models / "manifest.json").read_text())
    out["full_training_seconds"] = {k: v["training_seconds"] for k, v in manifest.items()}
    for k, v in out["full_training_seconds"].items():
        print(f"full profile {k:<20}: {v:7.0f} s ({v / 60:.1f} min, recorded in the manifest)")
    paths = derivative_paths(args.models / "baseline.onnx")
    out["derivatives_baseline"] = paths
    for k, v in paths.items():
        print(f"{k:<44}: {v:10.3g}")
    ratio = paths["casadi_symbolic_import_jac_us"] / paths["ort_jac_graph_batch1_us"]
    print(f"derivative graph vs CasADi symbolic import, one stage: {ratio:.1f}x faster; a 30-stage horizon in one "
          f"ORT call costs {paths['ort_jac_graph_batch30_us'] / 30:.0f} us per stage")
    write_json(args.json, out)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
