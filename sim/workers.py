"""The environment of a pool worker: one BLAS thread (the workers already fill the cores) and, on x86-64, the
BLAS kernel the project pins (see :mod:`sim`), set before the worker loads numpy. The project's own pool
(:func:`scenarios.sweeps.pool.run_pool`: the sweeps, the studies, the benchmark) starts its workers in
:func:`worker_env`; a :class:`concurrent.futures.ProcessPoolExecutor` gets it by :func:`worker_init` in the
parent before its workers are spawned (they inherit it), and again as their initializer.
"""

from __future__ import annotations

import os

#: Environment of every worker.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def worker_env() -> dict[str, str]:
    """:data:`WORKER_ENV` plus this process's pinned BLAS kernel, if any (for workers on other machines)."""
    env = dict(WORKER_ENV)
    if "OPENBLAS_CORETYPE" in os.environ:
        env["OPENBLAS_CORETYPE"] = os.environ["OPENBLAS_CORETYPE"]
    return env


def worker_init() -> None:
    """Set :data:`WORKER_ENV` in this process (the initializer of every pool worker)."""
    os.environ.update(WORKER_ENV)
