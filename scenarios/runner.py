"""Closed-loop runs: scenario x controller x prediction model.

One run flies the reference simulator at 1 kHz with control at 100 Hz::

    from scenarios.runner import RunSpec, fly
    result, trace = fly(RunSpec("figure8-slow", "ltv", "models/proposed.onnx"))

``result`` is a JSON-ready dict with the fields of ``pinnmpc fly --json`` and ``trace`` a dict of arrays (saved as ``.npz``). A
crash ends the run and is recorded; a run that cannot start (for example a
model whose hover linearization has no LQR gain) is recorded with its
``error``. :func:`sweep` runs many specs in a process pool.

Per control period ``k`` (``t = k dt``): the controller sees the measured
state (the true state, plus noise in ``+noise`` scenarios) and returns
``u``; with ``delay_steps = d`` the simulator applies the input computed
``d`` periods earlier (hover input before that); the simulator carries
rotor speeds across periods (motor lag of ``+highfi``).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from sim.params import DT, NU, NX, SUBSTEPS, QuadParams

from .errors import ScenarioError
from .library import get_scenario
from .metrics import closed_loop_metrics, crash_reason

CONTROLLERS = ("nmpc", "sqp", "ltv", "lqr")
#: Metrics of a run that never flew (its controller could not be built, or the run raised).
NOT_FLOWN = {"rmse_position_m": None, "max_position_error_m": None, "settled_error_m": None, "rmse_yaw_rad": None,
             "crashed": False, "crash_time_s": None,
             "crash_reason": None, "solve_ms": None, "deadline_misses": 0, "solver_failures": 0, "fallbacks": 0,
             "steps": 0}
#: MPC horizon of every run unless stated, steps of DT.
HORIZON = 30
#: How compute time enters a run: ``ideal`` applies each input at once (deterministic); ``realtime`` applies it
#: after the call's measured wall time, rounded up to the simulator's 1 ms substep (see :func:`fly`).
TIMINGS = ("ideal", "realtime")
#: The control period and the simulator's substep, ms (the substep is the resolution of real-time latencies).
PERIOD_MS = int(round(DT * 1e3))
SUBSTEP_MS = PERIOD_MS // SUBSTEPS


def model_name(model: str) -> str:
    """The name a model has in results: ``oracle``, ``analytic-<factors>``, or a file's stem."""
    if model.startswith("analytic:"):
        from mpc.models import analytic_name, parse_analytic
        return analytic_name(parse_analytic(model))
    return "oracle" if model == "oracle" else Path(model).stem


@dataclass(frozen=True)
class RunSpec:
    """What to fly: a scenario name, a controller, a prediction model (``"oracle"`` or an ONNX path)."""

    scenario: str
    controller: str
    model: str = "oracle"
    seed: int | None = None       # None: the scenario's own seed
    horizon: int = HORIZON        # MPC horizon, steps
    timing: str = "ideal"         # "ideal" (input applied at once) or "realtime" (after the measured compute time)
    member: int | None = None     # ensemble member (Scenario.member: its seed and a perturbed start); None: none

    def __post_init__(self):
        if self.member is not None:
            if isinstance(self.member, bool) or not isinstance(self.member, int) or self.member < 0:
                raise ScenarioError(f"member must be an integer >= 0; found {self.member!r}")
            if self.seed is not None:
                raise ScenarioError("an ensemble member has its own seed; give member or seed, not both")
        if self.controller not in CONTROLLERS:
            raise ScenarioError(f"controller must be one of {', '.join(CONTROLLERS)}; found {self.controller!r}")
        if self.timing not in TIMINGS:
            raise ScenarioError(f"timing must be one of {', '.join(TIMINGS)}; found {self.timing!r}")
        get_scenario(self.scenario)  # raises for an unknown name
        if not isinstance(self.model, str) or not self.model:
            raise ScenarioError(f"model must be 'oracle' or the path of an .onnx file; found {self.model!r}")
        if self.model.startswith("analytic:"):
            from mpc.models import parse_analytic
            parse_analytic(self.model)
        elif self.model != "oracle":
            path = Path(self.model)
            if path.suffix != ".onnx":
                raise ScenarioError(f"model must be 'oracle' or the path of an .onnx file; found {self.model!r}")
            if not path.is_file():
                raise ScenarioError(f"model file {self.model!r} does not exist")

    @property
    def model_name(self) -> str:
        return model_name(self.model)

    @property
    def run_id(self) -> str:
        """File-name-safe identifier ``<scenario>__<controller>__<model>``.

        ``__s<seed>`` is appended for an explicit seed, ``__m<k>`` for ensemble member k, ``__realtime`` for
        that timing.
        """
        base = f"{self.scenario}__{self.controller}__{self.model_name}"
        if self.seed is not None:
            base += f"__s{self.seed}"
        if self.member is not None:
            base += f"__m{self.member}"
        return base if self.timing == "ideal" else f"{base}__{self.timing}"


def _sha256(path: str) -> str | None:
    if path == "oracle" or path.startswith("analytic:"):
        return None
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def make_controller(kind: str, model, reference, horizon: int = HORIZON, timing: str = "ideal"):
    """The controller ``kind`` (``nmpc``, ``sqp``, ``ltv``, ``lqr``) on prediction ``model`` following ``reference``.

    The controller gets the model and the reference only: its vehicle spec
    comes from the model (:meth:`mpc.spec.VehicleSpec.from_model`), never from
    the plant's parameters. With ``ideal`` timing the SQP runs without its
    wall-clock budget (at most its iteration limit), so that the run is
    reproducible bit for bit; with ``realtime`` timing the budget applies.
    """
    from mpc.lqr import LQRController
    from mpc.ltv import LTVMPC, LTVSettings
    from mpc.nmpc import NMPC, NMPCSettings

    if kind == "nmpc":
        return NMPC(model, reference, NMPCSettings(horizon=horizon))
    if kind == "sqp":
        from mpc.sqp import SQPMPC, SQPSettings
        if timing == "ideal":
            return SQPMPC(model, reference, SQPSettings(horizon=horizon, time_budget_s=None, cold_start_budget_s=None))
        return SQPMPC(model, reference, SQPSettings(horizon=horizon))
    if kind == "ltv":
        return LTVMPC(model, reference, LTVSettings(horizon=horizon))
    if kind == "lqr":
        return LQRController(reference, model)
    raise ScenarioError(f"controller must be one of {', '.join(CONTROLLERS)}; found {kind!r}")


class _RealtimeClock:
    """The plant side of real-time timing: when each computed input takes effect.

    The controller is called at a period boundary ``k dt`` only when it is
    idle. A call that took ``L`` seconds of wall time returns ``ceil(L / 1 ms)``
    substeps later; its input takes effect from that substep on (plus the
    scenario's delay periods) and the controller is idle again from then.
    Until then the previous input stays applied (before the first one, the
    vehicle's hover thrust). A period whose input changes mid-way is flown
    in pieces of whole substeps with the same simulator equations.
    """

    def __init__(self, plant, sc, hover):
        from sim import Simulator

        # A piece of ``ms`` milliseconds: the simulator's own substeps, that many of them.
        self._make = lambda ms: Simulator(plant, sc.fidelity, dt=ms * 1e-3, substeps=ms // SUBSTEP_MS,
                                          payload_kg=sc.payload_kg, wind=_wind(sc))
        self._sims: dict[int, object] = {}
        self.delay_ms = PERIOD_MS * sc.delay_steps
        self.u = hover
        self.events: list[tuple[int, np.ndarray]] = []    # (time the input takes effect, ms; input)
        self.busy_until_ms = 0

    def _sim(self, ms: int):
        if ms not in self._sims:
            self._sims[ms] = self._make(ms)
        return self._sims[ms]

    def idle(self, k: int) -> bool:
        return self.busy_until_ms <= PERIOD_MS * k

    def command(self, k: int, u: np.ndarray, latency_s: float) -> None:
        lat_ms = max(SUBSTEP_MS, int(np.ceil(latency_s * 1e3 / SUBSTEP_MS - 1e-9)) * SUBSTEP_MS)
        self.busy_until_ms = PERIOD_MS * k + lat_ms
        self.events.append((self.busy_until_ms + self.delay_ms, np.array(u, dtype=float)))

    def fly_period(self, k: int, x, n, t: float):
        """Advance period ``k``; ``(x, rotor speed, input in effect at its end)``."""
        now, t1 = PERIOD_MS * k, PERIOD_MS * (k + 1)
        while now < t1:
            while self.events and self.events[0][0] <= now:
                self.u = self.events.pop(0)[1]
            nxt = t1 if not self.events else min(t1, self.events[0][0])
            # The wind of a period is evaluated at its start, as in the ideal-timing simulator.
            res = self._sim(nxt - now).step_full(x, self.u, rotor_speed=n, t=t)
            x, n = res.x, res.rotor_speed
            now = nxt
        return x, n, self.u


def _wind(sc):
    """The scenario's wind and gust impulse as one acceleration function (or None)."""
    parts = [w for w in (sc.wind, sc.impulse) if w is not None]
    if not parts:
        return None
    if len(parts) == 1:
        return parts[0]
    return lambda t: parts[0](t) + parts[1](t)


def fly(spec: RunSpec, progress: bool = False, scenario=None, model=None) -> tuple[dict, dict]:
    """Fly one closed-loop run; ``(result, trace)``.

    Raises only for bad input (unknown names, a model that fails the
    contract); everything that happens in flight is recorded.

    ``scenario`` (a :class:`scenarios.library.Scenario`) replaces the named
    scenario's data, for example with a perturbed initial state; ``model`` (a
    loaded :class:`mpc.models.PredictionModel`) saves loading ``spec.model`` again.
    """
    from mpc.controller import collector_paused
    from mpc.models import load_model
    from sim import Simulator

    if scenario is not None:
        sc = scenario
    elif spec.member is not None:
        sc = get_scenario(spec.scenario).member(spec.member)
    else:
        sc = get_scenario(spec.scenario, spec.seed)
    if model is None:
        model = load_model(spec.model)      # contract errors raise here, before anything flies
    ref = sc.reference()
    plant = QuadParams()     # the plant's parameters reach the simulator only
    K = sc.steps
    t_all = DT * np.arange(K + 1)
    X_ref = ref(t_all)
    X = np.full((K + 1, NX), np.nan)
    Xm = np.full((K, NX), np.nan)
    U = np.full((K, NU), np.nan)
    Ucmd = np.full((K, NU), np.nan)
    solve_s = np.zeros(K)
    iters = np.zeros(K, dtype=np.int64)
    status = np.full(K, "", dtype="<U40")
    failed = np.zeros(K, dtype=bool)
    lqr_fb = np.zeros(K, dtype=bool)
    crash_step, why, error = None, None, None
    base = {"run_id": spec.run_id, "scenario": spec.scenario, "controller": spec.controller,
            "model": spec.model_name, "model_file": None if spec.model == "oracle" or spec.model.startswith("analytic:") else str(spec.model),
            "model_sha256": _sha256(spec.model), "seed": sc.seed, "member": spec.member, "horizon": spec.horizon,
            "timing": spec.timing}
    t0 = time.perf_counter()
    k_end = 0
    realtime = spec.timing == "realtime"
    latency = np.full(K, np.nan)
    called = np.zeros(K, dtype=bool)
    try:
        ctrl = make_controller(spec.controller, model, ref, spec.horizon, spec.timing)
        # The reference is known before take-off: its feed-forward is fitted now, and a controller that plans
        # ahead (the SQP) makes its first plan from the state the vehicle stands in.
        ctrl.prepare(K * DT, x0=np.array(sc.x0, dtype=float))
    except ValueError as e:  # e.g. no LQR gain for this model's hover linearization
        error = f"{type(e).__name__}: {e}"
        ctrl = None
    if ctrl is not None:
        sim = Simulator(plant, sc.fidelity, payload_kg=sc.payload_kg, wind=_wind(sc))
        rng = np.random.default_rng([sc.seed, 0x5EED])
        x = np.array(sc.x0, dtype=float)
        X[0] = x
        n = None
        # Before the first (delayed or computed) command arrives, the vehicle's own hover thrust holds it (plant side).
        hover = np.array([plant.m * plant.g, 0.0, 0.0, 0.0])
        pending = [hover] * sc.delay_steps
        clock = _RealtimeClock(plant, sc, hover) if realtime else None
        steps = range(K)
        if progress:
            from tqdm import tqdm
            steps = tqdm(steps, desc=spec.run_id, unit="step", leave=False)
        for k in steps:
            t = k * DT
            if not realtime or clock.idle(k):
                xm = x if sc.noise is None else sim.measure(x, rng, sc.noise)
                Xm[k] = xm
                # In real time the garbage collector waits until the call has returned: a collection triggered
                # by the simulator's allocations is not the controller's time.
                with collector_paused(realtime):
                    c0 = time.perf_counter()
                    u_cmd, info = ctrl(xm, t)
                    latency[k] = time.perf_counter() - c0
                called[k] = True
                Ucmd[k] = u_cmd
                solve_s[k] = info.solve_time_s
                iters[k] = info.iterations
                status[k] = info.status
                failed[k] = info.fallback is not None
                lqr_fb[k] = info.fallback == "lqr"
            if realtime:
                if called[k]:
                    clock.command(k, u_cmd, latency[k])
                with np.errstate(all="ignore"):
                    x, n, u = clock.fly_period(k, x, n, t)
            else:
                if sc.delay_steps:
                    pending.append(u_cmd)
                    u = pending.pop(0)
                else:
                    u = u_cmd
                with np.errstate(all="ignore"):
                    res = sim.step_full(x, u, rotor_speed=n, t=t)
                x, n = res.x, res.rotor_speed
            U[k] = u
            X[k + 1] = x
            k_end = k + 1
            why = crash_reason(x, X_ref[k + 1])
            if why is not None:
                crash_step = k + 1
                break
    wall = time.perf_counter() - t0
    if error is None:
        metrics = closed_loop_metrics(X[:k_end + 1], X_ref[:k_end + 1], solve_s[:k_end], failed[:k_end],
                                      lqr_fb[:k_end], crash_step, why,
                                      impulse_start_s=None if sc.impulse is None else sc.impulse.start_s,
                                      planned_steps=K, called=called[:k_end] if realtime else None)
    else:
        metrics = dict(NOT_FLOWN)
    pre = getattr(ctrl, "preflight", None)    # the SQP's plan made before take-off: what it did, and (timing) how long
    preflight = None if pre is None else {"iterations": int(pre.iterations), "status": pre.status}
    result = {**base, **metrics, "shifted_plan": int(np.sum(failed[:k_end] & ~lqr_fb[:k_end])),
              "preflight": preflight, "preflight_ms": None if pre is None else 1e3 * pre.solve_time_s,
              "error": error, "wall_time_s": wall, "scenario_spec": sc.to_dict()}
    trace = {"t": t_all[:k_end + 1], "x": X[:k_end + 1], "x_ref": X_ref[:k_end + 1], "x_measured": Xm[:k_end],
             "u": U[:k_end], "u_command": Ucmd[:k_end], "solve_s": solve_s[:k_end], "latency_s": latency[:k_end],
             "called": called[:k_end], "iterations": iters[:k_end],
             "status": status[:k_end], "solver_failed": failed[:k_end], "lqr_fallback": lqr_fb[:k_end]}
    return result, trace


def save_run(result: dict, trace: dict, out_dir: Path) -> dict:
    """Write ``runs/<id>.json`` and ``traces/<id>.npz`` under ``out_dir``; the result with its trace path."""
    out_dir = Path(out_dir)
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    (out_dir / "traces").mkdir(parents=True, exist_ok=True)
    rel = None
    if trace:
        rel = f"traces/{result['run_id']}.npz"
        np.savez_compressed(out_dir / rel, **trace)
    result = {**result, "trace": rel}
    # The JSON is written last and atomically: a run interrupted while saving leaves no result, and is flown again.
    path = out_dir / "runs" / f"{result['run_id']}.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)
    return result


_CODE_VERSION: str | None = None


def code_version() -> str:
    """SHA-256 (first 16 hex digits) of the package version and the source of the packages that fly a run.

    Any change to ``sim``, ``mpc`` or ``scenarios`` (or the version) makes a
    new code version, and so invalidates every cached run.
    """
    global _CODE_VERSION
    if _CODE_VERSION is None:
        import sim

        root = Path(__file__).resolve().parents[1]
        h = hashlib.sha256(sim.__version__.encode())
        for pkg in ("sim", "mpc", "scenarios"):
            for f in sorted((root / pkg).rglob("*")):
                if f.suffix in (".py", ".toml") and f.is_file():
                    h.update(str(f.relative_to(root)).encode())
                    h.update(f.read_bytes())
        _CODE_VERSION = h.hexdigest()[:16]
    return _CODE_VERSION


def cache_key(spec: RunSpec) -> str:
    """Identity of a run's result: its spec, its seed, its model file's SHA-256 and the code version."""
    seed = get_scenario(spec.scenario).seed if spec.seed is None else spec.seed
    # The model by name and content, not by path: a results folder stays valid when the models move.
    ident = {"scenario": spec.scenario, "controller": spec.controller, "model": spec.model_name,
             "model_sha256": _sha256(spec.model), "seed": seed, "member": spec.member, "horizon": spec.horizon,
             "timing": spec.timing, "code": code_version()}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


def cached_result(spec: RunSpec, out_dir, key: str | None = None) -> dict | None:
    """The saved result of ``spec`` under ``out_dir`` if it was flown with the same cache key, else None.

    ``key``: the spec's :func:`cache_key`, if already computed. A saved run
    that could not start (its ``error`` is set, for example a model file that
    failed the contract) is not reused.
    """
    path = Path(out_dir) / "runs" / f"{spec.run_id}.json"
    try:
        result = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if result.get("cache_key") != (cache_key(spec) if key is None else key) or result.get("error"):
        return None     # another spec, model or code; or a run that could not start (tried again)
    if result.get("trace") and not (Path(out_dir) / result["trace"]).is_file():
        return None
    return result


def _worker_init() -> None:
    from .engines import WORKER_ENV

    os.environ.update(WORKER_ENV)


def fly_for_sweep(spec: RunSpec) -> tuple[dict, dict]:
    """``fly(spec)`` for a sweep: a run that cannot fly is recorded (its error) and the sweep goes on.

    This is the unit of work of every engine (a process-pool task, a Ray
    task); the sweep stamps the result with its :func:`cache_key`.
    """
    try:
        result, trace = fly(spec)
    except Exception as e:  # noqa: BLE001 - a run that cannot fly is recorded and the sweep goes on
        result = {"run_id": spec.run_id, "scenario": spec.scenario, "controller": spec.controller,
                  "model": spec.model_name, **NOT_FLOWN, "error": f"{type(e).__name__}: {e}"}
        trace = {}
    return result, trace


def sweep(specs: list[RunSpec], out_dir, jobs: int = 1, progress: bool = True, engine: str = "process",
          address: str | None = None, resume: bool = True, on_result=None) -> list[dict]:
    """Fly every spec (independent runs); results in the order of ``specs``.

    Parameters
    ----------
    specs : list of RunSpec
    out_dir : path
        Each result is written to ``out_dir/runs/<id>.json``, its trace to
        ``out_dir/traces/<id>.npz``, as soon as the run returns.
    jobs : int
        Worker processes of the ``process`` engine (1: in this process), and
        the CPUs of a local Ray instance.
    engine : {"process", "ray"}
        ``process``: a pool of worker processes on this machine.
        ``ray``: one Ray task per run (:mod:`scenarios.engines`), on the
        cluster at ``address`` or on a local instance.
    resume : bool
        Reuse every saved result under ``out_dir`` whose cache key (spec,
        seed, model file hash, code version) matches; only the rest is flown.
    on_result : callable, optional
        Called with each new result once it is saved.

    Runs with real-time timing are flown after the others, one at a time, so
    that the compute time they are charged is measured on an otherwise idle
    machine (with two processes on two cores a controller's call takes about
    1.5 times as long).
    """
    from .engines import ENGINES, run_batches

    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ScenarioError(f"jobs must be an integer >= 1; found {jobs!r}")
    if engine not in ENGINES:
        raise ScenarioError(f"engine must be one of {', '.join(ENGINES)}; found {engine!r}")
    if address is not None and engine != "ray":
        raise ScenarioError("address is for the ray engine; found it with engine 'process'")
    ids = [s.run_id for s in specs]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise ScenarioError(f"duplicate runs in the sweep: {sorted(dup)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    keys = {s.run_id: cache_key(s) for s in specs}   # once per run: it hashes the model file and reads the code
    results: dict[str, dict] = {}
    if resume:
        for s in specs:
            r = cached_result(s, out_dir, keys[s.run_id])
            if r is not None:
                results[s.run_id] = r
    todo = [s for s in specs if s.run_id not in results]
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(specs), initial=len(results), desc="closed-loop runs", unit="run")
        if results:
            bar.set_postfix_str(f"{len(results)} from the cache")

    def done(spec, result, trace):
        results[spec.run_id] = save_run({**result, "cache_key": keys[spec.run_id]}, trace, out_dir)
        if bar:
            bar.update()
        if on_result is not None:
            on_result(results[spec.run_id])

    try:
        run_batches(sweep_batches(todo, jobs), done, engine=engine, jobs=jobs, address=address)
    finally:
        if bar:
            bar.close()
    return [results[i] for i in ids]


def sweep_batches(specs: list[RunSpec], jobs: int) -> list[tuple[int, list[RunSpec]]]:
    """``(processes, runs)`` in the order a sweep on ``jobs`` processes flies them.

    Ideal-timing runs first, on ``jobs`` processes, longest first (NMPC, long
    scenarios) so that the pool ends together; then the real-time runs, one
    process, one at a time.
    """
    pooled = [s for s in specs if s.timing != "realtime"]
    alone = [s for s in specs if s.timing == "realtime"]
    order = sorted(pooled, key=lambda s: -(get_scenario(s.scenario).steps * _COST.get((s.controller, s.timing), 1)))
    return [(n, b) for n, b in ((jobs, order), (1, alone)) if b]


#: Rough cost of a period relative to the LTV-MPC's (orders a sweep's runs longest first).
_COST = {("nmpc", "ideal"): 20, ("sqp", "ideal"): 2}


def spec_dict(spec: RunSpec) -> dict:
    """JSON-ready form of a :class:`RunSpec`."""
    return asdict(spec)
