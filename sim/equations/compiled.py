"""Compiled CasADi functions for the analytic model's hot loops.

The analytic model's one-period step and its Jacobian are long expression
graphs (ten RK4 substeps; the Jacobian of one stage is about 44,000
operations), and CasADi's virtual machine evaluates them in about 7 ms for a
30-stage horizon. Compiled to C they take well under a millisecond.

:func:`compiled` generates the C code of a function, compiles it with the
system C compiler into a shared library kept in a cache folder (named by the
SHA-256 of the code, so a changed function is compiled anew and an unchanged
one only once per machine), and loads it with ``casadi.external``. Without a
working compiler it returns the function itself: the results are the same
to rounding, only slower.

Functions are compiled for their use (:data:`OPTIMIZATION`): those of the
control period (the oracles' step and Jacobian) optimized, those evaluated a
few times on whole datasets (the sensitivities of the Fisher information and
of the estimators) unoptimized, which compiles them several times faster.

The cache folder is ``$PINNMPC_CACHE`` or ``~/.cache/pinn-mpc``. The
compiler is ``$CC`` or ``cc``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import casadi as ca

#: Compiler flags of every library.
FLAGS = ("-shared", "-fPIC")
#: Optimization flag by use. ``period``: a function evaluated every control period, where its run time counts; -O1
#: compiles the 44,000-operation Jacobian in about 9 s and runs it about 16x faster than CasADi's virtual machine
#: (-O0: 1.5 s and 5x). ``batch``: a function evaluated a few times on whole datasets, where its compile time counts;
#: -O0 compiled the motor-input sensitivities in 2.7 s against 26 s at -O1 and evaluates 2,000 samples in 0.11 s
#: against 0.06 s (measured on 2 cores). The flags leave the arithmetic alone: both give the same numbers, bit for bit.
OPTIMIZATION = {"period": "-O1", "batch": "-O0"}
_loaded: dict[str, ca.Function] = {}


def cache_dir() -> Path:
    """Folder of the compiled libraries."""
    return Path(os.environ.get("PINNMPC_CACHE") or Path.home() / ".cache" / "pinn-mpc")


def _flags(use: str) -> tuple[str, ...]:
    """The compiler flags of a function of ``use`` (a key of :data:`OPTIMIZATION`)."""
    if use not in OPTIMIZATION:
        raise ValueError(f"use must be one of {', '.join(OPTIMIZATION)}; found {use!r}")
    return (OPTIMIZATION[use], *FLAGS)


def _source(fn: ca.Function, use: str = "period") -> tuple[str, bytes, str, Path]:
    """``(name, C code, cache key, library path)`` of ``fn`` compiled for ``use``."""
    with tempfile.TemporaryDirectory() as tmp:
        name = fn.name()
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        gen.add(fn)
        src_path = Path(tmp) / f"{name}.c"
        gen.generate(str(Path(tmp)) + os.sep)
        code = src_path.read_bytes()
    key = hashlib.sha256(code + " ".join(_flags(use)).encode()).hexdigest()[:20]
    return name, code, key, cache_dir() / f"{name}-{key}.so"


def precompile(fns, jobs: int = 2) -> int:
    """Compile the libraries of ``fns`` that are not in the cache yet, ``jobs`` at a time.

    Each item of ``fns`` is a CasADi function (compiled for the ``period`` use) or a pair ``(function, use)``
    (:data:`OPTIMIZATION`). The later :func:`compiled` calls of the same functions and uses, in this process or in
    workers, then only load them. Returns how many were compiled. Failures are left for :func:`compiled` to report.
    """
    import concurrent.futures as cf

    todo = {}
    for item in fns:
        fn, use = item if isinstance(item, tuple) else (item, "period")
        name, code, _, lib = _source(fn, use)
        if not lib.is_file():
            todo[lib] = (code, name, use)
    if not todo:
        return 0

    def build(item):
        lib, (code, name, use) = item
        try:
            _compile(code, name, lib, use)
        except (OSError, subprocess.SubprocessError):
            pass
    with cf.ThreadPoolExecutor(max(1, int(jobs))) as pool:      # the compiler runs outside Python's lock
        list(pool.map(build, todo.items()))
    return len(todo)


def compiled(fn: ca.Function, use: str = "period") -> ca.Function:
    """``fn`` compiled to C for ``use`` (:data:`OPTIMIZATION`) and loaded (cached by its code and flags), or ``fn``
    itself if that is not possible."""
    name, code, key, lib = _source(fn, use)
    if key in _loaded:
        return _loaded[key]
    try:
        if not lib.is_file():
            _compile(code, name, lib, use)
        out = ca.external(name, str(lib))
    except (OSError, RuntimeError, subprocess.SubprocessError) as e:
        warnings.warn(f"could not compile the CasADi function {name!r} ({e}); using CasADi's virtual machine "
                      "(same results, slower)", RuntimeWarning, stacklevel=2)
        out = fn
    _loaded[key] = out
    return out


def _compile(code: bytes, name: str, lib: Path, use: str = "period") -> None:
    cc = os.environ.get("CC") or "cc"
    if shutil.which(cc) is None:
        raise OSError(f"no C compiler {cc!r} on the PATH")
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        src = Path(tmp) / f"{name}.c"
        src.write_bytes(code)
        out = Path(tmp) / lib.name
        r = subprocess.run([cc, *_flags(use), "-o", str(out), str(src), "-lm"], capture_output=True, text=True,
                           timeout=600)
        if r.returncode != 0:
            raise OSError(f"{cc} failed: {r.stderr.strip()[:500]}")
        os.replace(out, lib)     # atomic: a parallel process sees either no library or a whole one
