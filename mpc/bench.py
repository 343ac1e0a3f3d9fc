"""Benchmark of the controllers: per-period solve time for each controller x prediction model.

Run ``python -m mpc.bench [--models models] [--controllers nmpc,sqp,ltv,lqr] [--cases hover,figure8-fast]
[--json FILE]``, or ``python -m mpc.bench --derivatives [--models models] [--json FILE]`` for the cost and
accuracy of the three ways to get a model's A and B over a 30-stage horizon (:func:`derivative_paths`), or
``python -m mpc.bench --estimator [--models models] [--json FILE]`` for the state estimator's cost per period:
the SQP with the estimator flies ``figure8-fast`` in real-time timing with the oracle and every shipped model
(:func:`estimator_cost`), or ``python -m mpc.bench --slowdown 2 [--estimator]`` for the same flights on a machine
twice as slow for the models (:func:`slow_machine`: every model call takes twice as long), or
``python -m mpc.bench --units [--vehicles crazyflie,hummingbird,FILE.toml] [--plant rotorpy] [--estimator]`` for
each vehicle flown in its own rotor unit and in normalized units (``n_max`` = 1): the same QP, so the same time
(:func:`unit_cost`).

The speed benchmark times each period's **input latency** (from the state handed over to the input returned)
and its **load** (that and the real-time iteration's preparation of the next period, which runs after the input
is out): ``latency_ms`` and ``solve_ms`` (median, p95, p99, max) per model and path. ``--paths P,Q`` picks the
SQP's paths (default every one it can fly: :func:`speed_paths`). ``--load N`` flies every case N times at once,
each in a process, and pools their periods: what contention does (the main job flies two runs at once). Beside
the shipped models it flies the learning studies' final models (16 states) on their own plants: our
high-fidelity simulator, and RotorPy when it is installed.

``python -m mpc.bench --answers [--members 5] [--jobs 2] [--compare BASE,NEW]`` compares the answers of two of
the SQP's paths (:data:`ALL_PATHS`; by default the full and the partial derivative path) in ideal timing: median RMSE over ensemble members on figure8-fast, figure8-slow and hover with the
oracle and every shipped model, and the crashes of every zoo model on figure8-fast (:func:`same_answers`,
:func:`zoo_crashes`).

For the oracle and each shipped ONNX model, each controller flies a 5 s
hover (from a 0.3 m offset) and two laps of ``figure8-fast`` (period 3 s,
A = 0.75 m) on the nominal simulator, with the input applied at once. The
model ``oracle_highfi`` (the high-fidelity equations, with the rotor speeds
as four extra states that the controller carries) flies the same cases on
the high-fidelity simulator (not with the NMPC: about 0.4 s per solve). The
SQP runs with its default 8 ms budget. The solve time of every call is
recorded (median / p95 / max, ms; the max also without the SQP's counted
cold-start periods) with the deadline misses (> 10 ms), solver failures and
fallbacks and the position RMSE of the run; for the SQP also the SQP
iterations per period and the split of its time: derivative graph, QP
assembly (including OSQP's matrix update), OSQP's solve, line search, and
the rest (Python). The SQP flies each case by each of its paths
(:func:`speed_paths`: today's full refresh, the partial one and, with DAQP,
the partial one on the dense QP), with the share of periods that refreshed
every stage's Jacobians, and each path's median and p95 over the full one's
are printed per model. It also prints the floor: one batched model + Jacobian
evaluation over the whole horizon, with float64 Jacobians (as IPOPT uses
them) and with float32 ones (as the QP controllers do). Nothing is asserted; the
figures are written as JSON.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections import deque
from pathlib import Path

import numpy as np

from sim import Simulator
from sim.files import write_json
from sim.params import DT, NX

from .prediction.contract import model_files
from .controllers.controller import collector_paused, hover_reference
from .controllers.dense_qp import daqp_installed
from .controllers.lqr import LQRController
from .controllers.ltv import LTVMPC, LTVSettings
from .prediction.models import AnalyticModel, OnnxModel, PredictionModel
from .controllers.nmpc import NMPC, NMPCSettings
from .controllers.sqp import SQPMPC, SQPSettings
from .controllers.timing import period_stats
from .references.trajectory import Figure8

HORIZON = 30
#: The real-time iteration's preparation must end this long before the next period's measurement, s (the closed
#: loop's margin: :data:`scenarios.closed_loop.loop.DEADLINE_MARGIN_S`).
PREPARATION_MARGIN_S = 0.001
CONTROLLERS = ("nmpc", "sqp", "ltv", "lqr")
SPLIT = ("derivatives", "assembly", "osqp", "line_search")
#: The SQP's two ways to its derivatives, flown side by side: today's (every Jacobian in every iteration that
#: evaluates them) and the partial refresh (:class:`mpc.controllers.sqp.SQPSettings`).
PATHS = {"full": {"jacobian_refresh": "full", "scheme": "sqp"},
         "partial": {"jacobian_refresh": "partial", "scheme": "sqp"}}
#: The speed benchmark also flies the partial path with the condensed QP solved by DAQP
#: (:mod:`mpc.controllers.dense_qp`), when
#: DAQP is installed.
DENSE_PATH = {"dense": {"jacobian_refresh": "partial", "qp": "daqp", "scheme": "sqp"}}
#: And the real-time iteration (:attr:`mpc.controllers.sqp.SQPSettings.scheme`) on the dense QP, when DAQP is
#: installed: the input waits for the feedback's QP; the derivatives follow it (their partial refresh).
RTI_PATH = {"rti": {"jacobian_refresh": "partial", "qp": "daqp", "scheme": "rti"},
            # and with one correction iteration in each preparation, when the next measurement leaves it time
            "rti1": {"jacobian_refresh": "partial", "qp": "daqp", "scheme": "rti", "rti_corrections": 1},
            # and with every stage's derivatives made again in each preparation
            "rti_full": {"jacobian_refresh": "full", "qp": "daqp", "scheme": "rti"}}
#: Every path a benchmark can fly by name.
ALL_PATHS = {**PATHS, **DENSE_PATH, **RTI_PATH}
#: The paths that need DAQP.
DAQP_PATHS = (*DENSE_PATH, *RTI_PATH)
#: The cases of the same-answers comparison.
ANSWER_CASES = ("figure8-fast", "figure8-slow", "hover")
#: acados' real-time iteration on the problem of ``oracle_rk1`` (the nominal equations, 12 states, 4 inputs, N = 30,
#: dt = 0.01 s, one RK4 step per interval, least-squares tracking of the 1.5 m/s figure-8, HPIPM), whole step
#: (preparation and feedback), median per period over runs on a 2-core machine of this project's kind, ms; measured
#: outside this project (acados is not one of its dependencies). The speed benchmark prints the oracles' RTI step
#: against it.
ACADOS_RTI_MS = (0.35, 0.46)


def speed_paths() -> dict:
    """The SQP's paths the speed benchmark flies: :data:`PATHS`, and :data:`DENSE_PATH` and :data:`RTI_PATH` when
    DAQP is installed."""
    return {**PATHS, **({**DENSE_PATH, **RTI_PATH} if daqp_installed() else {})}


def _controller(kind: str, model, reference, path: str = "full"):
    if kind == "nmpc":
        return NMPC(model, reference, NMPCSettings(horizon=HORIZON))
    if kind == "sqp":
        return SQPMPC(model, reference, SQPSettings(horizon=HORIZON, **ALL_PATHS[path]))
    if kind == "ltv":
        return LTVMPC(model, reference, LTVSettings(horizon=HORIZON))
    return LQRController(reference, model)


def run(kind: str, model, reference, x0: np.ndarray, seconds: float, fidelity=None, path: str = "full",
        plant=None, raw: bool = False) -> dict:
    """Fly one case; solve-time statistics, counts, position RMSE and (SQP) iterations and time split.

    ``fidelity``: the simulator's (nominal when None); with a motor lag its rotor speeds carry over. ``path``: the
    SQP's way to its derivatives (:data:`ALL_PATHS`). ``plant``: a :class:`sim.plants.plant.Plant` flown instead
    of the simulator.

    Each period's input latency (the call: from the state handed over to the input returned) and its load (the
    call and the preparation of the next period after it, the real-time iteration's) are timed: ``latency_ms``
    and ``solve_ms`` (the load, as the other paths' solve time) with median, p95, p99 and max. ``raw``: also the
    per-period times (``_load_s``, ``_latency_s``, s) and cold starts (``_cold``), for pooling.
    """
    from sim.params import NOMINAL

    ctrl = _controller(kind, model, reference, path)
    steps = int(round(seconds / DT))
    ctrl.prepare(steps * DT, x0=x0)   # the SQP plans its first period before take-off
    sim = None
    if plant is None:
        sim = Simulator(fidelity=NOMINAL if fidelity is None else fidelity)
    else:
        plant.reset(x0)
    n = None
    x = x0.copy()
    times, latency, err, iters, cold, full = [], [], [], [], [], []
    split = dict.fromkeys(SPLIT, 0.0)
    failures = fallbacks = 0
    for k in range(steps):
        t = k * DT
        with collector_paused():   # the garbage collector runs between periods, as in real-time runs
            c0 = time.perf_counter()
            u, info = ctrl(x, t)
            c1 = time.perf_counter()
            ctrl.prepare_next(c0 + DT - PREPARATION_MARGIN_S)    # by the next measurement
            c2 = time.perf_counter()
        times.append(info.solve_time_s + (c2 - c1))
        latency.append(c1 - c0)
        failures += info.status not in ("optimal", "lqr")
        fallbacks += info.fallback is not None
        if kind == "sqp":
            iters.append(info.iterations)
            cold.append(info.extra["cold_start"])
            full.append(info.extra["full_refreshes"] > 0)
            for key in SPLIT:
                split[key] += info.extra["time_split_s"][key]
            rti = info.extra.get("rti")
            if rti is not None and not rti["reused"]:       # the preparation it solved, made after the last input
                for key, v in rti["preparation_split_s"].items():
                    split[key] += v
        if plant is None:
            out = sim.step_full(x, u, rotor_speed=n)
            x, n = out.x, out.rotor_speed
        else:
            x = plant.advance(u, DT).x
        ctrl.applied(u)       # the command just flown (the controller carries its model's extra states)
        err.append(np.linalg.norm(x[0:3] - reference(np.array([t + DT]))[0, 0:3]))
        if not np.all(np.isfinite(x)) or err[-1] > 2.0:
            break
    ms = 1e3 * np.array(times)
    warm = ms[~np.array(cold, dtype=bool)] if cold else ms
    out = {"solve_ms": {**period_stats(times), "max_without_cold_starts": float(warm.max()) if warm.size else None},
           "latency_ms": period_stats(latency),
           "deadline_misses": int(np.sum(ms > 1e3 * DT)), "solver_failures": int(failures),
           "fallbacks": int(fallbacks), "rmse_position_m": float(np.sqrt(np.mean(np.square(err)))),
           "steps": len(times)}
    if kind == "sqp":
        n = len(times)
        it = np.array(iters)
        parts = {key: 1e3 * v / n for key, v in split.items()}
        parts["python"] = float(np.mean(ms)) - sum(parts.values())
        out.update(iterations={"mean": float(it.mean()), "counts": np.bincount(it).tolist()},
                   cold_starts=int(np.sum(cold)), time_split_ms=parts, full_refresh_share=float(np.mean(full)))
    if raw:
        out.update(_load_s=np.array(times), _latency_s=np.array(latency),
                   _cold=np.array(cold, dtype=bool) if cold else np.zeros(len(ms), dtype=bool))
    return out


def floor_us(model, repeat: int = 200, single: bool = False) -> float:
    """Microseconds of one batched model + Jacobian evaluation over the horizon.

    ``single``: with the Jacobians in single precision, as the QP controllers
    evaluate them (:meth:`mpc.prediction.models.PredictionModel.linearize_single`).
    """
    x = np.zeros((HORIZON, NX))
    x[:, 2] = -1.0
    u = np.tile([0.667, 0.0, 0.0, 0.0], (HORIZON, 1))
    if model.n_extra:
        from .prediction.extended import extra_equilibrium

        x = np.hstack([x, extra_equilibrium(model, x, u)])
    lin = model.linearize_single if single else model.linearize
    lin(x, u)
    t0 = time.perf_counter()
    for _ in range(repeat):
        lin(x, u)
    return (time.perf_counter() - t0) / repeat * 1e6


def _median_us(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(times))


def derivative_paths(path, stages: int = HORIZON, repeats: int = 200) -> dict:
    """Median time (us) of A and B over ``stages`` states across the flight envelope, by each path, and the error
    of the central differences against the derivative graph (relative Frobenius norm of ``[A B]``, max over stages).

    Paths: the derivative graph in float64 and its float32 copy (onnxruntime; the float32 one also stage by stage,
    one call each, and batched on two intra-op threads instead of one), central differences of the model
    (one onnxruntime call, 33 evaluations per stage), the derivative in numpy from the exported weights
    (:class:`mpc.prediction.weights.WeightDerivative`, with its largest difference from the float64 graph relative to
    the largest entry; None with the reason where the graph has an operation it does not differentiate), and
    CasADi's import of the model with its AD Jacobian (mapped over the stages; None when CasADi cannot import the
    graph).
    """
    import shutil
    import tempfile

    import casadi as ca

    from .prediction.contract import _envelope_batch
    from .errors import ModelContractError
    from .prediction.symbolic import casadi_step

    x, u = _envelope_batch(stages, np.float64, seed=3)
    graph = OnnxModel(path)
    with tempfile.TemporaryDirectory() as d:
        bare_path = Path(d) / Path(path).name
        shutil.copy(path, bare_path)
        bare = OnnxModel(bare_path)
    two = OnnxModel(path, threads=2)
    out = {"graph_float64_us": _median_us(lambda: graph.linearize(x, u), repeats),
           "graph_float32_us": _median_us(lambda: graph.linearize_single(x, u), repeats),
           # the same float32 graph stage by stage (one call per stage), and batched on two intra-op threads
           "graph_float32_per_stage_us": _median_us(
               lambda: [graph.linearize_single(x[i:i + 1], u[i:i + 1]) for i in range(stages)], max(10, repeats // 10)),
           "graph_float32_two_threads_us": _median_us(lambda: two.linearize_single(x, u), repeats),
           "differences_us": _median_us(lambda: bare.linearize(x, u), repeats)}
    _, A0, B0 = graph.linearize(x, u)
    _, A, B = bare.linearize(x, u)
    J0, J = np.concatenate([A0, B0], axis=2), np.concatenate([A, B], axis=2)
    out["differences_rel_error"] = float(np.max(np.linalg.norm(J - J0, axis=(1, 2)) / np.linalg.norm(J0, axis=(1, 2))))
    from .prediction.weights import UnsupportedGraph, WeightDerivative

    try:         # the derivative in numpy from the exported weights, against the float64 derivative graph
        weights = WeightDerivative(path)
        out["numpy_weights_us"] = _median_us(lambda: weights.linearize(x, u), max(10, repeats // 4))
        _, Aw, Bw = weights.linearize(x, u)
        Jw = np.concatenate([Aw, Bw], axis=2)
        out["numpy_weights_rel_error"] = float(np.max(np.abs(Jw - J0)) / np.max(np.abs(J0)))
        out["numpy_weights_refused"] = None
    except UnsupportedGraph as e:
        out["numpy_weights_us"] = out["numpy_weights_rel_error"] = None
        out["numpy_weights_refused"] = str(e)
    try:
        F = casadi_step(path)
        xs, us = ca.MX.sym("x", NX), ca.MX.sym("u", 4)
        jac = ca.Function("ab_of_model", [xs, us], [ca.jacobian(F(xs, us), ca.vertcat(xs, us))]).map(stages, "serial")
        X, U = ca.DM(x.T), ca.DM(u.T)
        out["casadi_import_us"] = _median_us(lambda: jac(X, U), max(10, repeats // 10))
    except ModelContractError as e:
        out["casadi_import_us"] = None
        out["casadi_import_refused"] = str(e)[:200]
    return out


def main(argv=None) -> int:
    """Run the benchmark and print its figures."""
    ap = argparse.ArgumentParser(prog="python -m mpc.bench", description=__doc__.splitlines()[0])
    ap.add_argument("--models", type=Path, default=Path("models"))
    ap.add_argument("--controllers", default=",".join(CONTROLLERS))
    ap.add_argument("--cases", default="hover,figure8-fast")
    ap.add_argument("--paths", default=None, metavar="P,Q",
                    help="the SQP's paths the speed benchmark flies (default: all it can, full, partial and with DAQP "
                         "dense and rti)")
    ap.add_argument("--load", type=int, default=1, metavar="N",
                    help="fly every case N times at once, each in a process, and pool their periods: what contention "
                         "does to the times (the main job flies two runs at once; default 1)")
    ap.add_argument("--json", type=Path, default=None, help="output (default bench_mpc.json, or "
                    "bench_derivatives.json with --derivatives)")
    ap.add_argument("--derivatives", action="store_true",
                    help="only compare the derivative paths (graph, float32 graph, central differences, CasADi import)")
    ap.add_argument("--estimator", action="store_true",
                    help="only the state estimator's cost per period: the SQP with it on figure8-fast in real time")
    ap.add_argument("--units", action="store_true",
                    help="only the SQP and the LTV-MPC on figure8-fast with each of --vehicles in its own rotor unit "
                         "and in normalized units (n_max = 1)")
    ap.add_argument("--vehicles", default="crazyflie,hummingbird",
                    help="with --units: vehicle names or files (default crazyflie,hummingbird)")
    ap.add_argument("--plant", default="rotorpy", help="with --units: the plant flown (default rotorpy)")
    ap.add_argument("--repeats", type=int, default=3, help="with --units: flights per vehicle and unit (default 3)")
    ap.add_argument("--answers", action="store_true",
                    help="only the same-answers comparison: the SQP by both derivative paths in ideal timing on "
                         "figure8-fast, figure8-slow and hover, --members ensemble members, and the zoo's crashes")
    ap.add_argument("--members", type=int, default=5, help="with --answers: ensemble members per case (default 5)")
    ap.add_argument("--jobs", type=int, default=2, help="with --answers: processes (default 2)")
    ap.add_argument("--compare", default="full,partial", metavar="BASE,NEW",
                    help=f"with --answers and --slowdown: the two SQP paths flown, of {', '.join(ALL_PATHS)} "
                         "(default full,partial; dense needs DAQP)")
    ap.add_argument("--slowdown", type=float, default=None, metavar="FACTOR",
                    help="only the SQP on figure8-fast in real time with every model call FACTOR times as long (a "
                         "machine that much slower); with --estimator, the state estimator flies too")
    args = ap.parse_args(argv)
    if args.json is not None:       # before any flight: a run's figures are not lost to an unwritable output
        from sim.errors import SimInputError
        from sim.files import check_writable

        try:
            check_writable(args.json, "--json")
        except SimInputError as e:
            _refuse(str(e))
    args.compare = tuple(p for p in args.compare.split(",") if p)
    if len(args.compare) != 2 or len(set(args.compare)) != 2 or not set(args.compare) <= set(ALL_PATHS):
        _refuse(f"--compare: two different paths of {', '.join(ALL_PATHS)} expected; found "
                         f"{','.join(args.compare) or 'none'}")
    needs = [p for p in args.compare if p in DAQP_PATHS]
    if needs and (args.answers or args.slowdown is not None) and not daqp_installed():
        what = " and ".join(needs) + (" paths need" if len(needs) > 1 else " path needs")
        _refuse(f'--compare: the {what} DAQP: python -m pip install -e ".[dense]"')
    if args.slowdown is not None:
        if not args.slowdown >= 1.0:
            _refuse(f"--slowdown: a factor >= 1 expected; found {args.slowdown:g}")
        return _main_slowdown(args)
    if args.units:
        return _main_units(args)
    if args.answers:
        if args.members < 1 or args.jobs < 1:
            _refuse(f"--members and --jobs: integers >= 1 expected; found {args.members}, {args.jobs}")
        return _main_answers(args)
    if args.derivatives:
        return _main_derivatives(args)
    if args.estimator:
        return _main_estimator(args)
    args.json = args.json or Path("bench_mpc.json")
    kinds = [k for k in args.controllers.split(",") if k]
    bad = set(kinds) - set(CONTROLLERS)
    if bad:
        _refuse(f"--controllers: unknown {sorted(bad)}; choose from {', '.join(CONTROLLERS)}")
    cases = [c for c in args.cases.split(",") if c]
    bad = set(cases) - set(SPEED_CASES)
    if bad:
        _refuse(f"--cases: unknown {sorted(bad)}; choose from {', '.join(SPEED_CASES)}")
    if not args.models.is_dir():
        _refuse(f"--models: {str(args.models)!r} is not a folder")
    paths = speed_paths() if args.paths is None else [p for p in args.paths.split(",") if p]
    if set(paths) - set(speed_paths()) or not paths or len(set(paths)) != len(paths):
        _refuse(f"--paths: different paths of {', '.join(speed_paths())} expected; found {args.paths!r}")
    if args.load < 1:
        _refuse(f"--load: an integer >= 1 expected; found {args.load}")
    sources = speed_models(args.models)
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "horizon": HORIZON, "load": args.load,
           "cases": []}
    tasks, floors = [], {}
    for name, (source, plant) in sources.items():
        model = _bench_model(source)
        floors[name] = (floor_us(model), floor_us(model, single=True))
        for kind in kinds:
            if kind == "lqr" and name not in ("oracle", "oracle_rk1", "oracle_highfi"):
                continue  # LQR uses the analytic hover linearization whatever the model
            if kind == "nmpc" and model.n_extra:
                continue  # about 0.4 s per IPOPT solve with the 16-state high-fidelity equations
            tasks += [(kind, name, case, path) for case in cases for path in (paths if kind == "sqp" else ("full",))]
    results = _fly_speed(tasks, sources, args.load)
    print(f"{'ctrl':<12}{'model':<22}{'case':<14}{'median':>8}{'p95':>8}{'max':>8}{'max*':>8} ms"
          f"{'lat med':>8}{'lat p99':>8}{'misses':>8}{'fail':>6}{'fallb':>6}{'RMSE m':>9}{'floor us':>10}"
          f"{'f32 us':>8}")
    sqp_rows = []
    for (kind, name, case, path), r in results.items():
        fl, fl32 = floors[name]
        label = f"sqp/{path}" if kind == "sqp" else kind
        out["cases"].append({"controller": kind, "path": path if kind == "sqp" else None, "model": name,
                             "plant": sources[name][1], "case": case, "floor_us": fl, "floor_single_us": fl32, **r})
        s, lat = r["solve_ms"], r["latency_ms"]
        print(f"{label:<12}{name:<22}{case:<14}{s['median']:>8.2f}{s['p95']:>8.2f}{s['max']:>8.1f}"
              f"{s['max_without_cold_starts']:>8.1f}   {lat['median']:>8.2f}{lat['p99']:>8.2f}{r['deadline_misses']:>8}"
              f"{r['solver_failures']:>6}{r['fallbacks']:>6}{r['rmse_position_m']:>9.4f}{fl:>10.0f}{fl32:>8.0f}",
              flush=True)
        if kind == "sqp":
            sqp_rows.append((name, case, path, r))
    if sqp_rows:
        print("\nmax*: without the SQP's counted cold-start periods. SQP iterations, time split per period (ms) and "
              "the share of periods with a full Jacobian refresh:")
        print(f"{'model':<22}{'case':<14}{'path':<9}{'iter mean':>10}  {'counts 0,1,2..':<18}"
              + "".join(f"{k:>12}" for k in (*SPLIT, "python")) + f"{'full refr.':>11}")
        for name, case, path, r in sqp_rows:
            sp = r["time_split_ms"]
            print(f"{name:<22}{case:<14}{path:<9}{r['iterations']['mean']:>10.2f}  {str(r['iterations']['counts']):<18}"
                  + "".join(f"{sp[k]:>12.2f}" for k in (*SPLIT, "python")) + f"{r['full_refresh_share']:>11.2f}")
        by = {(n, c, p): r for n, c, p, r in sqp_rows}
        print("\nThe other paths against today's (full), same run: median and p95 ratios (path / full)")
        out["ratios"] = []
        for (n, c, p), r in by.items():
            if p == "full" or (n, c, "full") not in by:
                continue
            f = by[(n, c, "full")]["solve_ms"]
            ratio = {"model": n, "case": c, "path": p, "median": r["solve_ms"]["median"] / f["median"],
                     "p95": r["solve_ms"]["p95"] / f["p95"]}
            out["ratios"].append(ratio)
            print(f"{n:<22}{c:<14}{p:<9}{ratio['median']:>8.2f}{ratio['p95']:>8.2f}")
        if args.load == 1:      # acados' figure is one flight at a time
            out["acados"] = _against_acados(by)
    write_json(args.json, out)
    print(f"wrote {args.json}")
    return 0


def _against_acados(by: dict) -> list:
    """The nominal equations' real-time iteration against acados' (:data:`ACADOS_RTI_MS`): for each oracle flown on
    ``figure8-fast`` by the ``rti`` path, its whole step's median (the period load, ms) and that over acados'
    lowest and highest median; printed, and returned for the JSON."""
    rows = []
    for name in ("oracle_rk1", "oracle"):
        r = by.get((name, "figure8-fast", "rti"))
        if r is None:
            continue
        ms = r["solve_ms"]["median"]
        rows.append({"model": name, "rti_step_median_ms": ms, "acados_ms": list(ACADOS_RTI_MS),
                     "ratio": [ms / ACADOS_RTI_MS[1], ms / ACADOS_RTI_MS[0]]})
    if rows:
        print(f"\nThe real-time iteration's whole step (preparation and feedback, median) against acados' "
              f"{ACADOS_RTI_MS[0]:.2f}-{ACADOS_RTI_MS[1]:.2f} ms on figure8-fast (oracle_rk1 is acados' problem; "
              f"oracle integrates 1 ms RK4 steps, as the plant):")
        for row in rows:
            lo, hi = row["ratio"]
            print(f"{row['model']:<22}{row['rti_step_median_ms']:>8.3f} ms = {lo:.2f}-{hi:.2f} x acados'")
    return rows


def _refuse(message: str):
    """Stop on bad input: one line on stderr, exit status 2."""
    print(f"python -m mpc.bench: {message}", file=sys.stderr)
    raise SystemExit(2)


def _speed_cases() -> dict:
    """The speed benchmark's cases: ``{name: (reference, start state (12,), seconds)}``."""
    fig8 = Figure8(0.75, 3.0, 1.0)
    x_hover = np.zeros(NX)
    x_hover[0:3] = [0.3, 0.0, -1.0]
    return {"hover": (hover_reference(), x_hover, 5.0), "figure8-fast": (fig8, fig8(np.array([0.0]))[0], 6.0)}


#: The names of the speed benchmark's cases (:func:`_speed_cases`).
SPEED_CASES = tuple(_speed_cases())


def speed_models(models_dir) -> dict:
    """The models the speed benchmark flies: ``{name: (source, plant)}``. ``source`` is ``"oracle"``,
    ``"oracle_rk1"`` (the nominal equations with one RK4 step per period, acados' default discretization: the
    problem of :data:`ACADOS_RTI_MS`), ``"oracle_highfi"`` or an ONNX file; ``plant`` is None (the simulator, at
    the model's own fidelity) or the learning study's plant the model was learned on (its key of
    :data:`scenarios.studies.learn.LEARN_PLANTS`): the oracles, the high-fidelity equations, every shipped model,
    and the final models of the learning studies on our
    high-fidelity plant and on RotorPy (16 states: the rotor speeds carried), each on its own plant (RotorPy's only
    when RotorPy is installed)."""
    from scenarios.studies.campaign import learned_models
    from sim.plants.named import rotorpy_available

    out = {"oracle": ("oracle", None), "oracle_rk1": ("oracle_rk1", None), "oracle_highfi": ("oracle_highfi", None)}
    out.update({f.stem: (str(f), None) for f in model_files(models_dir)})
    for key in ("highfi", "rotorpy"):
        if key == "rotorpy" and not rotorpy_available():
            continue
        out.update({Path(m).stem: (m, key) for m in learned_models(models_dir, key)})
    return out


_MODELS: dict = {}


def _bench_model(source: str):
    """The prediction model of ``source`` (:func:`speed_models`), loaded once per process."""
    from sim.params import HIGH_FIDELITY

    if source not in _MODELS:
        _MODELS[source] = (AnalyticModel() if source == "oracle" else
                           AnalyticModel(name="oracle_rk1", substeps=1) if source == "oracle_rk1" else
                           AnalyticModel(fidelity=HIGH_FIDELITY) if source == "oracle_highfi" else OnnxModel(source))
    return _MODELS[source]


def _speed_plant(key):
    """The plant of a learning study (its key of :data:`scenarios.studies.learn.LEARN_PLANTS`), or None."""
    if key is None:
        return None
    from scenarios.studies.learn import LEARN_PLANTS
    from sim.plants.named import make_plant

    lp = LEARN_PLANTS[key]
    return make_plant(lp.plant, lp.vehicle, high_fidelity=lp.high_fidelity)


def _speed_task(task) -> dict:
    """One flight of the speed benchmark: ``(kind, name, case, path, source, plant)`` (and a copy number, unused);
    :func:`run`'s result with its per-period times (``_load_s``, ``_latency_s``) for pooling."""
    kind, name, case, path, source, plant = task[:6]
    model = _bench_model(source)
    ref, x0, secs = _speed_cases()[case]
    return run(kind, model, ref, x0, secs, fidelity=getattr(model, "fidelity", None), path=path,
               plant=_speed_plant(plant), raw=True)


def _pooled(copies: list) -> dict:
    """The results of copies of one flight flown at once, as one: every period's times pooled (the statistics of
    all of them), the counts summed, the RMSE the copies' mean; iterations and time split the first copy's."""
    first = dict(copies[0])
    load = np.concatenate([c["_load_s"] for c in copies])
    cold = np.concatenate([c["_cold"] for c in copies])
    warm = load[~cold] if cold.any() else load
    first["solve_ms"] = {**period_stats(load),
                         "max_without_cold_starts": 1e3 * float(warm.max()) if warm.size else None}
    first["latency_ms"] = period_stats(np.concatenate([c["_latency_s"] for c in copies]))
    for key in ("deadline_misses", "solver_failures", "fallbacks", "steps"):
        first[key] = int(sum(c[key] for c in copies))
    first["rmse_position_m"] = float(np.mean([c["rmse_position_m"] for c in copies]))
    first["copies"] = len(copies)
    return {k: v for k, v in first.items() if not k.startswith("_")}


def _fly_speed(tasks, sources: dict, load: int) -> dict:
    """``{task: result}`` of the speed benchmark's flights (``(kind, name, case, path)``): in this process one after
    the other, or with ``load`` > 1 each flown ``load`` times at once on as many worker processes (the sweeps'
    pool, with their worker environment), its copies pooled (:func:`_pooled`)."""
    full = [t + sources[t[1]] for t in tasks]
    if load == 1:
        return {t[:4]: _pooled([_speed_task(t)]) for t in full}
    from tqdm import tqdm

    from scenarios.sweeps.pool import run_pool

    copies: dict = {t[:4]: [] for t in full}
    with tqdm(total=len(full) * load, desc=f"{load} flights at once", unit="flight") as bar:
        def done(item, value):
            copies[item[:4]].append(value)
            bar.update()

        def failed(item, reason):
            raise SystemExit(f"--load: a flight's worker died: {item[:4]}: {reason}")

        run_pool(_speed_task, [t + (i,) for t in full for i in range(load)], load, done, failed)
    return {t: _pooled(c) for t, c in copies.items()}


def _ms(v) -> dict:
    v = 1e3 * np.asarray(v, dtype=float)
    v = v[np.isfinite(v)]
    return {"median": float(np.median(v)), "p95": float(np.percentile(v, 95)), "max": float(np.max(v))} \
        if v.size else {"median": None, "p95": None, "max": None}


def estimator_cost(model: str, scenario: str = "figure8-fast") -> dict:
    """The SQP with the state estimator on ``scenario`` in real-time timing with ``model`` ('oracle' or a file).

    Returns the filter's time per period, the controller's and what the clock charged (their sum), ms
    (median / p95 / max), the deadline misses of the charged time, the periods that sent the shifted plan because
    no plan could be made before the deadline, and the position RMSE, m.
    """
    from scenarios.closed_loop.runner import RunSpec, fly     # the closed loop with sensors lives with the scenarios

    r, tr = fly(RunSpec(scenario, "sqp", model, timing="realtime", estimator="ekf"))
    called = np.asarray(tr.get("called", np.ones(len(tr["solve_s"]), dtype=bool)), dtype=bool)
    est = np.asarray(tr["estimator_s"], dtype=float)[called]
    ctrl = np.asarray(tr["solve_s"], dtype=float)[called]
    return {"estimator_ms": _ms(est), "controller_ms": _ms(ctrl), "charged_ms": _ms(est + ctrl),
            "deadline_misses": r.get("deadline_misses"), "deadline_fallbacks": r.get("deadline_fallbacks"),
            "rmse_position_m": r.get("rmse_position_m"), "crashed": r.get("crashed"), "periods": int(called.sum())}


def clock_stalls(seconds: float = 10.0) -> dict:
    """How long this process is held up with nothing else to do: a loop that only reads the clock for ``seconds``.

    Returns the number of gaps between two reads over 1, 2 and 4 ms and the longest gap, ms. A gap is time in
    which no code of this process ran (another process, the kernel or the hypervisor had the core); in a control
    period such a gap counts against the deadline whatever the controller does.
    """
    gaps = []
    t0 = last = time.perf_counter()
    while last - t0 < seconds:
        now = time.perf_counter()
        if now - last > 1e-3:
            gaps.append(now - last)
        last = now
    g = 1e3 * np.asarray(gaps)
    return {"seconds": seconds, "over_1ms": int(np.sum(g > 1)), "over_2ms": int(np.sum(g > 2)),
            "over_4ms": int(np.sum(g > 4)), "longest_ms": float(g.max()) if g.size else 0.0}


#: How many recent calls of a method at a batch size give a slowed model call its typical duration.
SLOWED_RECENT = 25


class SlowedModel(PredictionModel):
    """A prediction model whose every call takes ``factor`` times as long: a machine that slow, for the model.

    Each call of ``step``, ``linearize``, ``linearize_single`` and ``jacobians`` is timed and followed by a busy
    wait of ``factor - 1`` times its typical duration (a sleep would hand the core away and come back late). The
    typical duration is the median of the process's CPU time over the last :data:`SLOWED_RECENT` calls of that
    method at that batch size, this one included: a moment the host took the core away, or a call the host made
    slower than usual, passes through once, as it would on the slow machine, instead of ``factor`` times.
    Everything else is the wrapped model's. The controllers' own Python, the QP solver and the simulator keep this
    machine's speed: the model and its derivative graph are most of a period's time (:func:`run`'s time split).
    """

    def __init__(self, base, factor: float = 2.0):
        if not (isinstance(factor, (int, float)) and factor >= 1.0):
            raise ValueError(f"factor must be a number >= 1; found {factor!r}")
        self.base, self.factor = base, float(factor)
        self.name, self.theta, self.extra_names, self.extra_scale = (base.name, base.theta, base.extra_names,
                                                                     base.extra_scale)
        self.wall, self.cpu = time.perf_counter, time.process_time     # the clocks (a test gives fake ones)
        self._recent: dict = {}          # (method, batch size) -> recent CPU times of its calls, s

    def __getattr__(self, name):      # what the wrapped model has beyond the interface (its file, its dtype)
        return getattr(self.base, name)

    def reference_states(self, trajectory, times):
        return self.base.reference_states(trajectory, times)

    def _slowed(self, fn, *args):
        c0 = self.cpu()
        out = fn(*args)
        recent = self._recent.setdefault((fn.__name__, len(np.atleast_2d(args[0]))), deque(maxlen=SLOWED_RECENT))
        recent.append(self.cpu() - c0)
        end = self.wall() + (self.factor - 1.0) * statistics.median(recent)
        while self.wall() < end:
            pass
        return out

    def step(self, x, u):
        return self._slowed(self.base.step, x, u)

    def linearize(self, x, u):
        return self._slowed(self.base.linearize, x, u)

    def linearize_single(self, x, u):
        return self._slowed(self.base.linearize_single, x, u)

    def jacobians(self, x, u):
        return self._slowed(self.base.jacobians, x, u)


def slow_machine(model: str, factor: float = 2.0, scenario: str = "figure8-fast", estimator: str = "none",
                 path: str = "full") -> dict:
    """The SQP on ``scenario`` in real-time timing with ``model`` ('oracle' or a file) made ``factor`` times slower
    (:class:`SlowedModel`; the state estimator's model calls too, with ``estimator="ekf"``), the SQP by its
    derivative ``path`` (:data:`ALL_PATHS`).

    Returns the time charged per period, ms (median / p95 / max), the periods charged more than the 10 ms period
    (the deadline misses), the periods that sent the shifted plan because no plan could be made in time, and the
    position RMSE, m.
    """
    from scenarios.closed_loop.runner import RunSpec, fly, load_run_model

    spec = RunSpec(scenario, "sqp", model, timing="realtime", estimator=estimator)
    r, tr = fly(spec, model=SlowedModel(load_run_model(spec), factor), sqp=ALL_PATHS[path])
    called = np.asarray(tr["called"], dtype=bool)
    charged = np.asarray(tr["solve_s"], dtype=float)[called]
    if tr.get("estimator_s") is not None and len(tr["estimator_s"]):
        charged = charged + np.nan_to_num(np.asarray(tr["estimator_s"], dtype=float)[called])
    return {"charged_ms": _ms(charged), "over_10ms": int(np.sum(charged > DT)),
            "deadline_misses": r.get("deadline_misses"), "deadline_fallbacks": r.get("deadline_fallbacks"),
            "rmse_position_m": r.get("rmse_position_m"), "crashed": r.get("crashed"), "periods": int(called.sum()),
            "error": r.get("error")}


def _main_slowdown(args) -> int:
    if not args.models.is_dir():
        _refuse(f"--models: {str(args.models)!r} is not a folder")
    models = ["oracle"] + [str(f) for f in model_files(args.models)]
    est = "ekf" if args.estimator else "none"
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "scenario": "figure8-fast",
           "controller": "sqp", "timing": "realtime", "estimator": est, "factor": args.slowdown, "models": {}}
    stalls = out["idle_clock_loop"] = clock_stalls()
    print(f"This process doing nothing but read the clock for {stalls['seconds']:.0f} s: gaps over 1 / 2 / 4 ms "
          f"{stalls['over_1ms']} / {stalls['over_2ms']} / {stalls['over_4ms']}, longest {stalls['longest_ms']:.1f} ms")
    print(f"The SQP{' with the state estimator' if args.estimator else ''}, figure8-fast, real-time timing, every "
          f"model call {args.slowdown:g} times as long; ms charged per period")
    print(f"{'model':<22}{'path':<9}{'median':>8}{'p95':>8}{'max':>8}{'>10 ms':>8}{'late':>6}{'RMSE m':>9}")
    for m in models:
        name = Path(m).stem if m != "oracle" else m
        for path in args.compare:
            r = slow_machine(m, args.slowdown, estimator=est, path=path)
            out["models"][f"{name}/{path}"] = r
            c = r["charged_ms"]
            if r["error"]:
                print(f"{name:<22}{path:<9}could not fly: {r['error']}", flush=True)
                continue
            rmse = "crashed" if r["crashed"] else format(r["rmse_position_m"], ".4f")
            print(f"{name:<22}{path:<9}{c['median']:>8.2f}{c['p95']:>8.2f}{c['max']:>8.1f}{r['over_10ms']:>8}"
                  f"{r['deadline_fallbacks']:>6}{rmse:>9}", flush=True)
    out["idle_clock_loop_after"] = after = clock_stalls()
    print(f"The same clock loop after: gaps over 1 / 2 / 4 ms {after['over_1ms']} / {after['over_2ms']} / "
          f"{after['over_4ms']}, longest {after['longest_ms']:.1f} ms")
    return _write(args.json or Path("bench_slowdown.json"), out)


def _main_estimator(args) -> int:
    if not args.models.is_dir():
        _refuse(f"--models: {str(args.models)!r} is not a folder")
    models = ["oracle"] + [str(f) for f in model_files(args.models)]
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "scenario": "figure8-fast",
           "controller": "sqp", "timing": "realtime", "models": {}}
    stalls = out["idle_clock_loop"] = clock_stalls()
    print(f"This process doing nothing but read the clock for {stalls['seconds']:.0f} s: gaps over 1 / 2 / 4 ms "
          f"{stalls['over_1ms']} / {stalls['over_2ms']} / {stalls['over_4ms']}, longest {stalls['longest_ms']:.1f} ms")
    print("The SQP with the state estimator, figure8-fast, real-time timing; ms per period (median / p95 / max)")
    print(f"{'model':<22}{'filter':>22}{'controller':>22}{'charged':>22}{'misses':>8}{'late':>6}{'RMSE m':>9}")
    for m in models:
        name = Path(m).stem if m != "oracle" else m
        r = estimator_cost(m)
        out["models"][name] = r

        def f(d):
            return "–" if d["median"] is None else f"{d['median']:.2f} / {d['p95']:.2f} / {d['max']:.1f}"
        rmse = "crashed" if r["crashed"] else format(r["rmse_position_m"], ".4f")
        print(f"{name:<22}{f(r['estimator_ms']):>22}{f(r['controller_ms']):>22}{f(r['charged_ms']):>22}"
              f"{r['deadline_misses']:>8}{r['deadline_fallbacks']:>6}{rmse:>9}", flush=True)
    return _write(args.json or Path("bench_estimator.json"), out)


def unit_cost(vehicle: str, controller: str, plant: str = "rotorpy", estimator: str = "none",
              scenario: str = "figure8-fast", repeats: int = 3) -> dict:
    """The nominal equations with ``controller`` on ``scenario`` (ideal timing), ``vehicle`` (a name or file) flown
    in its own rotor unit and in normalized units (:meth:`sim.vehicles.vehicle.Vehicle.normalized`), alternately
    ``repeats`` times (this machine's speed drifts between flights).

    Returns, for ``"own"`` and ``"normalized"``: the per-period time (ms: median of the flights' medians, largest
    p95 and max), deadline misses (calls over 10 ms, summed), solver failures, RMSE (m, the last flight's), the
    periods' summed iterations (the last flight's), and ``ratio``: the own unit's median over the normalized one's.
    """
    import tempfile

    from scenarios.closed_loop.runner import RunSpec, fly
    from sim.vehicles.vehicle import load_vehicle

    v = load_vehicle(vehicle)
    out = {"vehicle": v.name, "n_max": v.n_max_value, "controller": controller, "plant": plant,
           "estimator": estimator}
    with tempfile.TemporaryDirectory() as tmp:
        norm = Path(tmp) / f"{v.name}-normalized.toml"
        norm.write_text(v.normalized().to_toml())
        flights = {"own": [], "normalized": []}
        for _ in range(repeats):
            for label, file in (("own", vehicle), ("normalized", str(norm))):
                flights[label].append(fly(RunSpec(scenario, controller, "nominal", plant=plant, vehicle=file,
                                                  estimator=estimator)))
        for label, runs in flights.items():
            r, tr = runs[-1]
            solve = [x["solve_ms"] for x, _ in runs if x["solve_ms"]]
            out[label] = {"solve_ms": None if not solve else
                          {"median": float(np.median([s["median"] for s in solve])),
                           "p95": max(s["p95"] for s in solve), "max": max(s["max"] for s in solve),
                           "flight_medians": [s["median"] for s in solve]},
                          "deadline_misses": sum(x["deadline_misses"] or 0 for x, _ in runs),
                          "solver_failures": sum(x["solver_failures"] or 0 for x, _ in runs),
                          "rmse_position_m": r["rmse_position_m"], "crashed": any(x["crashed"] for x, _ in runs),
                          "iterations": int(np.sum(tr["iterations"])), "flights": len(runs)}
    own, nrm = out["own"]["solve_ms"], out["normalized"]["solve_ms"]
    out["ratio"] = None if not (own and nrm) else own["median"] / nrm["median"]
    return out


def _main_units(args) -> int:
    vehicles = [v for v in args.vehicles.split(",") if v]
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "scenario": "figure8-fast",
           "plant": args.plant, "estimator": "ekf" if args.estimator else "none", "runs": []}
    print(f"The nominal equations on figure8-fast, plant {args.plant}, ideal timing"
          + (", with the state estimator" if args.estimator else "")
          + f"; ms per period (median of {args.repeats} flights' medians / largest), deadline misses over the "
          f"flights, iterations of one flight")
    print(f"{'vehicle':<26}{'ctrl':<6}{'own unit':>22}{'normalized':>22}{'ratio':>7}{'misses':>9}{'iterations':>16}")
    for v in vehicles:
        for c in ("sqp", "ltv"):
            r = unit_cost(v, c, args.plant, out["estimator"], repeats=args.repeats)
            out["runs"].append(r)

            def f(d):
                s = d["solve_ms"]
                return "–" if not s else f"{s['median']:.2f} / {s['max']:.1f}"
            print(f"{r['vehicle']:<26}{c:<6}{f(r['own']):>22}{f(r['normalized']):>22}"
                  f"{'–' if r['ratio'] is None else format(r['ratio'], '.2f'):>7}"
                  f"{r['own']['deadline_misses']:>4} /{r['normalized']['deadline_misses']:>3}"
                  f"{r['own']['iterations']:>8} /{r['normalized']['iterations']:>7}", flush=True)
    return _write(args.json or Path("bench_units.json"), out)


def _fly_path(task):
    """One ideal-timing SQP run of ``(model, scenario, member, path)``: ``(RMSE m, crashed)``."""
    from scenarios.closed_loop.runner import RunSpec, fly

    model, scenario, member, path = task
    r, _ = fly(RunSpec(scenario, "sqp", model, member=member), sqp=ALL_PATHS[path])
    return r["rmse_position_m"], bool(r["crashed"])


def _fly_all(tasks, jobs: int, what: str) -> dict:
    """``{task: (RMSE m, crashed)}`` for :func:`_fly_path` tasks on ``jobs`` workers of the sweeps' pool
    (:func:`scenarios.sweeps.pool.run_pool`, with their worker environment), with a progress bar. A task whose worker
    died twice is ``(None, None)``: not flown."""
    from tqdm import tqdm

    from scenarios.sweeps.pool import run_pool

    flown = {}
    with tqdm(total=len(tasks), desc=what, unit="run") as bar:
        def done(task, value):
            flown[task] = value
            bar.update()

        def failed(task, reason):
            print(f"not flown: {task}: {reason}", flush=True)
            done(task, (None, None))

        run_pool(_fly_path, tasks, jobs, done, failed)
    return flown


def same_answers(models: dict, cases=ANSWER_CASES, members: int = 5, jobs: int = 2,
                 paths=("full", "partial")) -> dict:
    """Each model (``{name: "oracle" or file}``) on each case, ``members`` ensemble members, by two ``paths``
    (:data:`ALL_PATHS`: the base, then the new one) in ideal timing (the runs are reproducible, so the paths'
    differences are theirs): per path the median RMSE (m) and the crashes, and the new path's median over the
    base's (``ratio``) and their difference (m)."""
    base, new = paths
    tasks = [(m, c, i, p) for m in models.values() for c in cases for i in range(members) for p in paths]
    flown = _fly_all(tasks, jobs, "same answers")
    out = {}
    for name, m in models.items():
        for c in cases:
            row = {}
            for p in paths:
                runs = [flown[(m, c, i, p)] for i in range(members)]
                rmse = [r for r, crashed in runs if crashed is False and r is not None]
                row[p] = {"median_rmse_m": float(np.median(rmse)) if rmse else None,
                          "rmse_m": [r for r, _ in runs], "crashes": sum(crashed is True for _, crashed in runs)}
            f, q = row[base]["median_rmse_m"], row[new]["median_rmse_m"]
            row["ratio"] = None if not (f and q) else q / f
            row["difference_m"] = None if f is None or q is None else q - f
            out[f"{name}/{c}"] = row
    return out


def zoo_crashes(models_dir, jobs: int = 2, paths=("full", "partial")) -> dict:
    """Every zoo model on ``figure8-fast`` (ensemble member 0) by both ``paths``: ``{model: {path: crashed}}``
    (None: not flown)."""
    files = model_files(models_dir)
    tasks = [(str(f), "figure8-fast", 0, p) for f in files for p in paths]
    flown = _fly_all(tasks, jobs, "zoo")
    return {f.stem: {p: flown[(str(f), "figure8-fast", 0, p)][1] for p in paths} for f in files}


def _main_answers(args) -> int:
    if not args.models.is_dir():
        _refuse(f"--models: {str(args.models)!r} is not a folder")
    models = {"oracle": "oracle", **{f.stem: str(f) for f in model_files(args.models)}}
    base, new = args.compare
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "members": args.members,
           "timing": "ideal", "controller": "sqp", "paths": {p: ALL_PATHS[p] for p in args.compare}}
    print(f"The SQP by two paths, ideal timing, {args.members} ensemble members: median position RMSE (mm), "
          f"crashes, {new} / {base}")
    out["cases"] = rows = same_answers(models, members=args.members, jobs=args.jobs, paths=args.compare)
    print(f"{'model / case':<40}{base:>10}{new:>10}{'crashes':>9}{'ratio':>8}{'diff mm':>9}")
    for key, r in rows.items():
        def mm(v):
            return "–" if v is None else f"{1e3 * v:.2f}"
        ratio = "–" if r["ratio"] is None else f"{r['ratio']:.3f}"
        print(f"{key:<40}{mm(r[base]['median_rmse_m']):>10}{mm(r[new]['median_rmse_m']):>10}"
              f"{r[base]['crashes']:>4} /{r[new]['crashes']:>2}{ratio:>8}{mm(r['difference_m']):>9}")
    zoo = args.models / "zoo"
    if zoo.is_dir():
        out["zoo"] = crashes = zoo_crashes(zoo, jobs=args.jobs, paths=args.compare)
        changed = {k: v for k, v in crashes.items() if v[base] != v[new]}
        print(f"Zoo on figure8-fast (member 0): {sum(v[base] is True for v in crashes.values())} crashes by the "
              f"{base} path, {sum(v[new] is True for v in crashes.values())} by the {new} one, of "
              f"{len(crashes)} models; changed: "
              + (", ".join(f"{k} ({'crashes' if v[new] else 'flies'} now)" for k, v in changed.items())
                 or "none"))
    return _write(args.json or Path("bench_answers.json"), out)


def _main_derivatives(args) -> int:
    if not args.models.is_dir():
        _refuse(f"--models: {str(args.models)!r} is not a folder")
    files = model_files(args.models)
    out = {"python": platform.python_version(), "cpus": os.cpu_count(), "stages": HORIZON, "models": {}}
    print(f"A and B at {HORIZON} states across the flight envelope, median us per call "
          f"(one call = one period's linearization of the LTV-MPC, or one SQP iteration's)")
    print(f"{'model':<22}{'graph f64':>10}{'graph f32':>10}{'f32 /stage':>11}{'f32 2 thr':>10}{'differences':>12}"
          f"{'CasADi AD':>11}{'diff. error':>13}{'numpy':>9}{'numpy error':>13}")
    for f in files:
        r = derivative_paths(f)
        out["models"][f.stem] = r
        cas = "refused" if r["casadi_import_us"] is None else f"{r['casadi_import_us']:.0f}"
        print(f"{f.stem:<22}{r['graph_float64_us']:>10.0f}{r['graph_float32_us']:>10.0f}"
              f"{r['graph_float32_per_stage_us']:>11.0f}{r['graph_float32_two_threads_us']:>10.0f}"
              f"{r['differences_us']:>12.0f}{cas:>11}{r['differences_rel_error']:>13.1e}"
              + (f"{'refused':>9}{'':>13}" if r["numpy_weights_us"] is None else
                 f"{r['numpy_weights_us']:>9.0f}{r['numpy_weights_rel_error']:>13.1e}"), flush=True)
    return _write(args.json or Path("bench_derivatives.json"), out)


def _write(path: Path, out: dict) -> int:
    """Write a benchmark's figures as JSON and say where (the exit status of the command)."""
    write_json(path, out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
