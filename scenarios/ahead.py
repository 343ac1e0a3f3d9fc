"""Runs flown ahead, on what a long command leaves idle.

A long command (the learning study) knows early some runs its last sweep
will fly, runs that depend on nothing it computes on the way: the nominal
equations on the speed ladder, a shipped model on the evaluation reference.
:class:`FlyAhead` flies them in one extra process at the operating system's
idle priority (Linux ``SCHED_IDLE``; elsewhere the lowest ``nice``), which
gets a core only while nothing else wants it: the single-threaded export of
a trained model, the tail of a pool, the spawning of workers. Each run is
saved where the sweep looks for it, stamped with its cache key exactly as
the sweep stamps its own, so the sweep then finds it flown and does not fly
it again. A run is a function of its spec alone (ideal timing), so the
results are the same either way; only its timing fields (``solve_ms``,
``wall_s``) are measured under whatever ran beside it.

The process dies with its parent, whatever killed the parent (as the pool's
workers do), and :meth:`FlyAhead.stop` ends it at once: a run it was flying
is dropped whole (never a torn file) and flown by the sweep.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

#: How long :meth:`FlyAhead.stop` waits for the process to exit after SIGTERM, seconds (then it is killed).
STOP_WAIT_S = 5.0


def idle_priority() -> str:
    """Lower this process to the idle scheduling class (Linux) or the lowest nice value; which one it got."""
    if hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return "SCHED_IDLE"
        except OSError:
            pass
    try:
        os.nice(19)
        return "nice 19"
    except (OSError, AttributeError):
        return "unchanged"


def _stop_on_sigterm(signum, frame):
    raise SystemExit(0)          # unwinds through the file writers, which remove their temporary files


def fly_ahead(specs, out_dir) -> int:
    """Fly every spec of ``specs`` not yet saved under ``out_dir``, saving each as a sweep would; runs flown.

    A run that could not fly (its ``error`` set) is not saved: the sweep flies it again and reports it.
    """
    from .runner import cache_key, cached_result, fly_for_sweep
    from .sweep import save_swept

    flown = 0
    for spec in specs:
        if cached_result(spec, out_dir) is not None:
            continue
        result, trace = fly_for_sweep(spec)
        if result.get("error"):
            continue
        save_swept(spec, result, trace, Path(out_dir), cache_key(spec))
        flown += 1
    return flown


def _main(specs, out_dir: str, parent_pid: int) -> None:
    from .engines import worker_init
    from .pool import _die_with_parent

    _die_with_parent(parent_pid)
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    worker_init()
    idle_priority()
    fly_ahead(specs, out_dir)


class FlyAhead:
    """One idle-priority process flying ``specs`` into the sweep folder ``out_dir`` (see the module docstring).

    Use as a context manager, or call :meth:`start` and :meth:`stop`; with no specs nothing is started.
    """

    def __init__(self, specs, out_dir):
        self.specs, self.out_dir = list(specs), Path(out_dir)
        self._proc = None

    def start(self) -> "FlyAhead":
        if self.specs and self._proc is None:
            import multiprocessing as mp

            self._proc = mp.get_context("spawn").Process(target=_main, args=(self.specs, str(self.out_dir),
                                                                             os.getpid()), daemon=True)
            self._proc.start()
        return self

    def stop(self) -> None:
        """End the process now (SIGTERM, then SIGKILL after :data:`STOP_WAIT_S`); runs it saved stay saved."""
        p, self._proc = self._proc, None
        if p is None:
            return
        if p.is_alive():
            p.terminate()
            p.join(STOP_WAIT_S)
            if p.is_alive():
                p.kill()
        p.join(STOP_WAIT_S)

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def __enter__(self) -> "FlyAhead":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

