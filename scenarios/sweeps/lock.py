"""One sweep per results folder: a lock file that names its holder.

A sweep (and the commands built on one: ``run``, ``study``, ``versus``) holds
``<folder>/.lock`` while it works. A second one started on the same folder
stops at once with a line naming the holder (process, host, command, start
time), instead of flying everything again beside the first and timing its
real-time runs under the other's load.

The lock is an advisory ``flock`` on that file, which the operating system
releases when the holder exits, however it ends (SIGKILL included): a stale
file never keeps a folder locked. Within one process the lock is re-entrant
(a command that locks its folder can call a sweep that locks it again). On a
system without ``fcntl`` (Windows) folders are not locked.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from ..errors import ScenarioError

LOCK_NAME = ".lock"

_HELD: dict[str, list] = {}      # folder -> [open file, depth]


class FolderInUseError(ScenarioError):
    """Another process holds the lock of a results folder."""


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text())
        return (f"process {info['pid']} on {info['host']} (`{info['command']}`, since {info['since']})")
    except (OSError, ValueError, KeyError, TypeError):
        return "another process"


@contextmanager
def folder_lock(folder):
    """Hold ``folder``'s lock (the folder is created) for the ``with`` block; :class:`FolderInUseError` if taken."""
    try:
        import fcntl
    except ImportError:          # no advisory locks here: nothing to hold
        yield
        return
    folder = Path(folder)
    made = [p for p in (folder, *folder.parents) if not p.exists()]     # removed again if left empty
    folder.mkdir(parents=True, exist_ok=True)
    key = str(folder.resolve())
    if key in _HELD:
        _HELD[key][1] += 1
        try:
            yield
        finally:
            _HELD[key][1] -= 1
        return
    path = folder / LOCK_NAME
    while True:
        f = open(path, "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            raise FolderInUseError(f"{folder} is in use by {_holder(path)}; wait for it to end or stop it "
                                   f"(or give another --out)") from None
        try:
            same = os.path.samestat(os.fstat(f.fileno()), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        f.close()                # the holder removed the file as we opened it: take the new one
    f.seek(0)
    f.truncate()
    f.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
                        "since": time.strftime("%Y-%m-%d %H:%M:%S %Z")}) + "\n")
    f.flush()
    _HELD[key] = [f, 1]
    try:
        yield
    finally:
        del _HELD[key]
        try:
            path.unlink()
        except OSError:
            pass
        f.close()
        for p in made:           # a command that stopped before writing anything leaves no folder behind
            try:
                p.rmdir()
            except OSError:
                break


def locks_out_dir(fn):
    """Decorate a command function whose ``out_dir`` argument is a results folder: it runs holding that folder's
    lock (:func:`folder_lock`)."""
    import functools
    import inspect

    sig = inspect.signature(fn)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        bound = sig.bind(*args, **kwargs)
        bound.apply_defaults()
        with folder_lock(bound.arguments["out_dir"]):
            return fn(*args, **kwargs)

    return wrapper
