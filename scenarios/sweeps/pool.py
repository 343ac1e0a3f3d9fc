"""A pool of worker processes that outlives its workers and never outlives its parent.

:func:`run_pool` calls ``fn(item)`` for every item in spawned worker
processes and hands each value back to the calling process as it returns.

* A worker that dies while it holds an item (killed, out of memory, a crash in
  native code) is replaced by a fresh one and the item is tried again there;
  an item whose worker died ``retries + 1`` times is given up with the reason
  (``failed(item, reason)``) and the pool goes on with the others.
* Workers die with their parent, whatever killed it (SIGKILL included): on
  Linux the kernel sends them SIGKILL when the parent goes
  (``PR_SET_PDEATHSIG``), and on every system each worker watches its parent
  and exits within :data:`WATCH_PERIOD_S` once it is gone.
* An exception raised by ``fn`` is raised again in the caller (the pool is
  stopped first: workers are killed, nothing more is handed back).
* Workers start with :data:`sim.workers.WORKER_ENV` (one BLAS thread each: the
  workers fill the cores) in their environment from their first instruction.
  An ``initializer`` is too late for that: a spawned worker unpickles ``fn``
  first, and its module loads numpy, which starts its BLAS threads then (two
  workers on two cores ran four threads, and the bench's periods under
  ``--load 2`` lost whole scheduler slices, 5 to 11 ms).

:class:`concurrent.futures.ProcessPoolExecutor`, which the sweeps used
before, does none of the first two: one dead worker breaks the whole pool
(``BrokenProcessPool``, the other runs in flight lost), and after a SIGKILL of
its parent its workers wait for work forever.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections import deque
from contextlib import contextmanager

#: How often a worker checks that its parent is still alive, seconds.
WATCH_PERIOD_S = 0.5
#: Times an item is tried again on a fresh worker after its worker died.
RETRIES = 1
#: How long a worker is given to exit once told to, seconds (then it is killed).
STOP_WAIT_S = 5.0


def _die_with_parent(parent_pid: int) -> None:
    """Make this process end when ``parent_pid`` does (kernel signal on Linux, a watching thread everywhere)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)          # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass

    def watch():
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            threading.Event().wait(WATCH_PERIOD_S)

    if os.getppid() != parent_pid:          # the parent went before the signal was armed
        os._exit(1)
    threading.Thread(target=watch, name="watch-parent", daemon=True).start()


def _worker(conn, parent_pid: int, fn, initializer) -> None:
    _die_with_parent(parent_pid)
    if initializer is not None:
        initializer()
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        index, item = msg
        try:
            reply = (index, True, fn(item))
        except BaseException as e:  # noqa: BLE001 - handed to the parent, which raises it
            reply = (index, False, e)
        try:
            conn.send(reply)
        except Exception as e:  # noqa: BLE001 - a value or an exception that does not pickle
            conn.send((index, False, RuntimeError(f"{type(reply[2]).__name__} could not be sent back: {e}")))


def _death(exitcode) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


@contextmanager
def _environment(env: dict):
    """This process's environment with ``env`` set (a process started inside inherits it), as it was after."""
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _Worker:
    def __init__(self, ctx, fn, initializer):
        from sim.workers import worker_env

        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker, args=(child, os.getpid(), fn, initializer), daemon=True)
        with _environment(worker_env()):
            self.proc.start()
        child.close()
        self.index = None           # the item it holds

    def kill(self):
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(STOP_WAIT_S)
        self.conn.close()


def run_pool(fn, items, workers: int, done, failed, retries: int | None = None, initializer=None,
             on_death=None) -> None:
    """Call ``fn(item)`` for every item on ``workers`` spawned processes.

    Parameters
    ----------
    fn : callable
        A module-level function (it is pickled by name into the workers).
    items : sequence
        Handed out in order, one per idle worker.
    workers : int
        Processes at most (never more than there are items).
    done : callable
        ``done(item, value)``, in this process, as each item returns.
    failed : callable
        ``failed(item, reason)`` for an item whose worker died ``retries + 1``
        times while holding it; ``reason`` is one line.
    retries : int, optional
        Fresh workers an item is tried on after the first died
        (:data:`RETRIES` by default).
    initializer : callable, optional
        Called once in every worker before its first item.
    on_death : callable, optional
        ``on_death(item, reason, retried)`` each time a worker dies holding
        ``item`` (for a line on stderr); ``retried`` says whether it will be
        tried again.

    An exception raised by ``fn``, ``done`` or ``failed`` (or a
    KeyboardInterrupt) kills the workers and propagates.
    """
    import multiprocessing as mp
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    retries = RETRIES if retries is None else retries
    items = list(items)
    queue = deque(range(len(items)))
    deaths = [0] * len(items)
    pool: list[_Worker] = []
    try:
        while queue or any(w.index is not None for w in pool):
            while queue and len(pool) < workers:
                pool.append(_Worker(ctx, fn, initializer))
            for w in list(pool):
                if w.index is None and queue:
                    try:
                        w.conn.send((queue[0], items[queue[0]]))
                    except OSError:             # it died idle (before its first item or between two): replaced
                        w.kill()
                        pool.remove(w)
                        continue
                    w.index = queue.popleft()
            busy = [w for w in pool if w.index is not None]
            if not busy:
                continue
            ready = set(wait([w.conn for w in busy] + [w.proc.sentinel for w in busy]))
            for w in busy:
                reply = None
                if w.conn in ready:
                    try:
                        reply = w.conn.recv()
                    except (EOFError, OSError):
                        reply = None
                elif w.proc.sentinel not in ready:
                    continue
                if reply is not None:
                    index, ok, value = reply
                    w.index = None
                    if not ok:
                        raise value
                    done(items[index], value)
                    continue
                # the worker died holding its item
                w.proc.join(STOP_WAIT_S)
                reason = _death(w.proc.exitcode)
                index, w.index = w.index, None
                w.kill()
                pool.remove(w)
                deaths[index] += 1
                if on_death is not None:
                    on_death(items[index], reason, deaths[index] <= retries)
                if deaths[index] > retries:
                    failed(items[index], f"its worker process died {deaths[index]} times on it (last: {reason})")
                else:
                    queue.appendleft(index)
    except BaseException:
        for w in pool:
            w.kill()
        raise
    for w in pool:
        try:
            w.conn.send(None)
        except OSError:
            pass
    for w in pool:
        w.proc.join(STOP_WAIT_S)
        w.kill()
