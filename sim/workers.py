"""The environment of a pool worker: one BLAS thread (the workers already fill the cores) and, on x86-64, the
BLAS kernel the project pins (see :mod:`sim`), set before the worker loads numpy. Every process pool of the
project (the closed-loop sweep, the open-loop evaluation, the studies) starts its workers with :func:`worker_init`.
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
