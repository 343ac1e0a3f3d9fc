"""Sweeps: many independent runs, resumable, on a process pool or on Ray.

``sweep(specs, out_dir)`` flies every :class:`scenarios.closed_loop.runner.RunSpec` not
already saved in ``out_dir`` with the same cache key, on the engine asked
for (:mod:`scenarios.sweeps.engines`), and saves each result and trace as it
returns.
"""

from __future__ import annotations

from pathlib import Path

from .engines import ENGINES, run_batches
from ..errors import ScenarioError
from ..closed_loop.library import get_scenario
from .lock import folder_lock
from ..closed_loop.runner import RunSpec
from ..closed_loop.record import RunRecord, cache_key, cached_result, not_flown, save_run


def sweep(specs: list[RunSpec], out_dir, jobs: int = 1, progress: bool = True, engine: str = "process",
          address: str | None = None, resume: bool = True, on_result=None) -> list[RunRecord]:
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
        ``ray``: one Ray task per run (:mod:`scenarios.sweeps.engines`), on the
        cluster at ``address`` or on a local instance.
    resume : bool
        Reuse every saved result under ``out_dir`` whose cache key (spec,
        seed, the hashes of the files it read, code version) matches the
        files as they are now, and whose trace reads back whole; only the
        rest is flown (a damaged file is said so on stderr).
    on_result : callable, optional
        Called with each new result once it is saved.

    Runs with real-time timing are flown after the others, one at a time, so
    that the compute time they are charged is measured on an otherwise idle
    machine (with two processes on two cores a controller's call takes about
    1.5 times as long).
    """
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
    with folder_lock(out_dir):          # one sweep per folder (re-entrant for the command that called this one)
        return _sweep(specs, out_dir, jobs, progress, engine, address, resume, on_result)


def _sweep(specs, out_dir: Path, jobs, progress, engine, address, resume, on_result) -> list[RunRecord]:
    ids = [s.run_id for s in specs]
    keys = {s.run_id: cache_key(s) for s in specs}   # once per run: it hashes the model file and reads the code
    results: dict[str, RunRecord] = {}
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
        # Keyed by the files the run read when it started flying (a file replaced during the sweep shows there).
        key = cache_key(spec, result["inputs_sha256"]) if "inputs_sha256" in result else keys[spec.run_id]
        results[spec.run_id] = save_run(RunRecord.from_dict(result).replace(cache_key=key), trace, out_dir)
        if bar:
            bar.update()
        if on_result is not None:
            on_result(results[spec.run_id])

    def failed(spec, reason):      # its worker died on every try: recorded as a run that did not fly
        done(spec, not_flown(spec, f"not flown: {reason}"), {})

    try:
        run_batches(sweep_batches(todo, jobs), done, engine=engine, jobs=jobs, address=address, failed=failed)
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
    order = sorted(pooled, key=lambda s: -(get_scenario(s.scenario).steps * _COST.get((s.controller, s.timing), 1)
                                           * _PLANT_COST.get(s.plant, 1)))
    return [(n, b) for n, b in ((jobs, order), (1, alone)) if b]


#: Rough cost of a period relative to the LTV-MPC's (orders a sweep's runs longest first).
_COST = {("nmpc", "ideal"): 20, ("sqp", "ideal"): 2}
#: Rough cost of a plant's period relative to the reference simulator's, with the controller's included.
_PLANT_COST = {"rotorpy": 2, "rotorpy-ideal": 2}
