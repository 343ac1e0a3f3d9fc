"""Where a sweep's runs are flown: a process pool on this machine, or Ray tasks on a cluster.

Every run is independent: the unit of work is
:func:`scenarios.closed_loop.runner.fly_for_sweep`, which returns the run's result and
trace; the driver (the process that called :func:`scenarios.sweeps.sweep.sweep`)
saves them as they arrive, so the results folder only needs to exist where the
driver runs.

* ``process`` (the default; no extra dependency): ``jobs`` worker processes
  (spawned, one BLAS thread each); ``jobs = 1`` flies in the calling process.
* ``ray``: one Ray task per run (one CPU each). With ``address`` the tasks go
  to that cluster (``ray start --head`` on one node, ``ray start
  --address=HEAD:6379`` on the others, then ``--address HEAD:6379``); without
  it a local Ray instance with ``jobs`` CPUs is started for the sweep and shut
  down after it. Each node needs this project installed in the same Python
  environment and the model files at the same paths as the driver (a shared
  file system, or the same checkout in the same place). Ray is an optional
  extra: ``python -m pip install -e ".[ray]"``.

Both engines fly the ideal-timing runs first, as many at a time as they have
workers, and the real-time runs after them, one at a time (their compute time
is what they measure). Both fix the worker's BLAS kernel and thread count, so
that an ideal-timing run gives the same numbers on either engine.
"""

from __future__ import annotations

import logging
import os
import sys

from sim.workers import worker_env

from ..errors import ScenarioError
from .pool import RETRIES, run_pool

ENGINES = ("process", "ray")



def run_batches(batches, done, engine: str = "process", jobs: int = 1, address: str | None = None,
                failed=None) -> None:
    """Fly ``batches`` (``[(workers, [RunSpec, ...]), ...]`` from :func:`scenarios.sweeps.sweep.sweep_batches`).

    ``done(spec, result, trace)`` is called in this process as each run returns.
    ``failed(spec, reason)`` is called for a run whose worker died twice while
    flying it (it was tried on a fresh worker after the first death; a line on
    stderr says so each time); the sweep goes on with the others.
    An exception raised by ``done`` (or a KeyboardInterrupt) stops the sweep:
    runs not yet returned are cancelled, and whatever was saved stays saved.
    """
    if failed is None:
        def failed(spec, reason):
            raise ScenarioError(f"run {spec.run_id}: {reason}")
    if engine == "ray":
        _ray(batches, done, jobs, address, failed)
    else:
        _process(batches, done, jobs, failed)


def _said_death(spec, reason: str, retried: bool) -> None:
    again = "flying it again on a fresh worker" if retried else "recorded as not flown"
    print(f"run {spec.run_id}: its worker process died ({reason}); {again}", file=sys.stderr, flush=True)


def _process(batches, done, jobs: int, failed) -> None:
    from ..closed_loop.runner import fly_for_sweep

    if jobs == 1:
        for _, batch in batches:
            for spec in batch:
                done(spec, *fly_for_sweep(spec))
        return
    for workers, batch in batches:
        run_pool(fly_for_sweep, batch, workers, lambda spec, value: done(spec, *value), failed,
                 on_death=_said_death)


def _fly_in(spec, cwd: str):
    """A Ray task: fly ``spec`` with the driver's working directory (relative model paths resolve as there)."""
    from ..closed_loop.runner import fly_for_sweep

    if os.path.isdir(cwd) and os.getcwd() != cwd:
        os.chdir(cwd)
    return fly_for_sweep(spec)


def _ray(batches, done, jobs: int, address: str | None, failed) -> None:
    try:
        import ray
    except ImportError as e:
        raise ScenarioError("engine 'ray' needs Ray, an optional extra: python -m pip install -e \".[ray]\"") from e
    started = False
    if not ray.is_initialized():
        try:
            ray.init(address=address, num_cpus=None if address else jobs, include_dashboard=False,
                     log_to_driver=False, logging_level=logging.ERROR, runtime_env={"env_vars": worker_env()})
        except Exception as e:  # noqa: BLE001 - Ray's connection errors come in several types
            where = f"the Ray cluster at {address!r}" if address else "a local Ray instance"
            raise ScenarioError(f"could not start or reach {where}: {type(e).__name__}: {e}") from e
        started = True
    task = ray.remote(num_cpus=1, max_retries=RETRIES)(_fly_in)   # retried on a fresh worker if its worker dies
    died = tuple(getattr(ray.exceptions, n) for n in ("WorkerCrashedError", "OutOfMemoryError", "NodeDiedError")
                 if hasattr(ray.exceptions, n))

    def get(spec, ref):
        try:
            result, trace = ray.get(ref)
        except died as e:
            failed(spec, f"its Ray worker died {RETRIES + 1} times on it (last: {type(e).__name__})")
            return
        done(spec, result, trace)

    cwd = os.getcwd()
    pending: dict = {}
    try:
        for workers, batch in batches:
            if workers == 1:
                for spec in batch:      # one at a time: a real-time run is charged for its compute
                    ref = task.remote(spec, cwd)
                    pending[ref] = spec
                    get(spec, ref)
                    del pending[ref]
                continue
            pending.update({task.remote(s, cwd): s for s in batch})
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    get(pending.pop(ref), ref)
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()
