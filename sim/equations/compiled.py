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

Each library also holds a small loop, ``<name>_points``, that evaluates the
function at many points in one C call. :class:`Pointwise` calls it through
``ctypes`` on numpy arrays: CasADi's own call converts its arguments and
results to and from its matrices, which cost about 20 µs per call and, for a
30-stage Jacobian (a 12 x 360 result), more than the compiled arithmetic of a
one-step integrator. Both run the same compiled function, so their numbers are
the same bit for bit.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import casadi as ca
import numpy as np

#: Compiler flags of every library.
FLAGS = ("-shared", "-fPIC")
#: Optimization flag by use. ``period``: a function evaluated every control period, where its run time counts; -O1
#: compiles the 44,000-operation Jacobian in about 9 s and runs it about 16x faster than CasADi's virtual machine
#: (-O0: 1.5 s and 5x). ``batch``: a function evaluated a few times on whole datasets, where its compile time counts;
#: -O0 compiled the motor-input sensitivities in 2.7 s against 26 s at -O1 and evaluates 2,000 samples in 0.11 s
#: against 0.06 s (measured on 2 cores). The flags leave the arithmetic alone: both give the same numbers, bit for bit.
#: ``kernel``: a small hand-written C loop (:func:`c_library`), compiled in well under a second, where every
#: microsecond of its run counts.
OPTIMIZATION = {"period": "-O1", "batch": "-O0", "kernel": "-O3"}
_loaded: dict[str, tuple] = {}

#: The loop appended to every library: the function ``NAME`` at ``n`` points, input ``j`` of point ``i`` at
#: ``in[j] + i * in_step[j]`` (step 0: one value for every point) and output ``j`` (its nonzeros) at
#: ``out[j] + i * out_step[j]``; the work arrays are the caller's (sized by ``NAME_work``). Returns the first
#: failing point's status, 0 when every point is evaluated.
_POINTS = """
/* pinn-mpc: NAME at n points in one call */
CASADI_SYMBOL_EXPORT int NAME_points(casadi_int n, const casadi_real** in, const casadi_int* in_step,
                                     casadi_real** out, const casadi_int* out_step, const casadi_real** arg,
                                     casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {
  casadi_int i, j, n_in = NAME_n_in(), n_out = NAME_n_out();
  int flag;
  for (i = 0; i < n; ++i) {
    for (j = 0; j < n_in; ++j) arg[j] = in[j] + i * in_step[j];
    for (j = 0; j < n_out; ++j) res[j] = out[j] + i * out_step[j];
    flag = NAME(arg, res, iw, w, mem);
    if (flag) return flag;
  }
  return 0;
}
"""


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
        code = src_path.read_bytes() + _POINTS.replace("NAME", name).encode()
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
    return _load(fn, use)[0]


def compiled_library(fn: ca.Function, use: str = "period") -> tuple[ca.Function, Path | None]:
    """``(function, library)``: :func:`compiled`'s function and the library it was loaded from, for a
    :class:`Pointwise` call of it; ``(fn, None)`` when it could not be compiled."""
    return _load(fn, use)


def c_library(name: str, code: str, use: str = "kernel") -> Path | None:
    """The library of the C source ``code`` (a file of this project, not CasADi's), compiled for ``use`` into the
    cache, or None, with a warning once per process, when it cannot be compiled (the caller then has its numpy
    path).

    It is compiled for this machine's processor first (``-march=native``; the library's name then holds a digest
    of the processor's description as well as of the code and flags, so that a cache folder shared by different
    machines never hands one of them another's instructions), and for any processor of its kind when the compiler
    does not take that flag.
    """
    keys = []
    for flags in [(*_flags(use), "-march=native"), _flags(use)]:
        extra = _cpu_signature() if "-march=native" in flags else ""
        key = hashlib.sha256(code.encode() + " ".join(flags).encode() + extra.encode()).hexdigest()[:20]
        if key in _loaded:
            return _loaded[key]
        keys.append(key)
        lib = cache_dir() / f"{name}-{key}.so"
        try:
            if not lib.is_file():
                _compile(code.encode(), name, lib, use, flags=flags)
            _loaded[key] = lib
            return lib
        except (OSError, subprocess.SubprocessError) as e:
            error = e
    warnings.warn(f"could not compile {name} ({error}); using its numpy path (same results to rounding, slower)",
                  RuntimeWarning, stacklevel=2)
    _loaded.update(dict.fromkeys(keys))          # not tried again in this process
    return None


def _cpu_signature() -> str:
    """What tells this machine's processor from another's: its architecture and, on Linux, the first processor's
    model and feature flags."""
    import platform

    out = [platform.machine(), platform.processor()]
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.split(":")[0].strip() in ("model name", "flags", "Features", "CPU part") and line not in out:
                out.append(line)
            if line.strip() == "":
                break             # the first processor's block
    except OSError:
        pass
    return "\n".join(out)


def _load(fn: ca.Function, use: str) -> tuple[ca.Function, Path | None]:
    """``(function, library)``: ``fn`` compiled and loaded, or ``(fn, None)`` with a warning when that fails."""
    name, code, key, lib = _source(fn, use)
    if key in _loaded:
        return _loaded[key]
    try:
        if not lib.is_file():
            _compile(code, name, lib, use)
        out = (ca.external(name, str(lib)), lib)
    except (OSError, RuntimeError, subprocess.SubprocessError) as e:
        warnings.warn(f"could not compile the CasADi function {name!r} ({e}); using CasADi's virtual machine "
                      "(same results, slower)", RuntimeWarning, stacklevel=3)
        out = (fn, None)
    _loaded[key] = out
    return out


class Pointwise:
    """A compiled CasADi function evaluated at many points in one C call (its library's ``<name>_points``).

    Parameters
    ----------
    fn : casadi.Function
        The function (its sparsity patterns; every input dense).
    lib : path
        Its compiled library (:func:`compiled_library`).

    Calling it with one array per input gives one array per output: an input of shape ``(n, numel)`` has a value
    per point, one of shape ``(numel,)`` the same value at every point; each output is
    ``(n, rows * cols)``, its matrix flattened column by column (CasADi's order), structural zeros included. One
    instance serves one thread at a time (its work arrays are its own).
    """

    def __init__(self, fn: ca.Function, lib: Path):
        self._made_of = (fn, Path(lib))
        self.name = fn.name()
        dll = ctypes.CDLL(str(lib))
        self._call = getattr(dll, f"{self.name}_points")
        self._call.restype = ctypes.c_int
        self._call.argtypes = [ctypes.c_longlong, *[ctypes.c_void_p] * 8, ctypes.c_int]
        self.n_in, self.n_out = fn.n_in(), fn.n_out()
        self.in_sizes = [fn.sparsity_in(j).numel() for j in range(self.n_in)]
        for j in range(self.n_in):
            if not fn.sparsity_in(j).is_dense():
                raise ValueError(f"{self.name}: input {j} is sparse; the point loop takes dense inputs")
        sp = [fn.sparsity_out(j) for j in range(self.n_out)]
        self.out_sizes = [s.numel() for s in sp]
        self._nnz = [s.nnz() for s in sp]
        #: Where each output's nonzeros go in its dense column-major flattening (None: dense already).
        self._where = [None if s.is_dense() else np.array(s.find(), dtype=np.intp) for s in sp]
        work = getattr(dll, f"{self.name}_work")
        sizes = [ctypes.c_longlong() for _ in range(4)]
        if work(*[ctypes.byref(v) for v in sizes]):
            raise OSError(f"{self.name}_work failed")
        sz_arg, sz_res, sz_iw, sz_w = (max(int(v.value), 1) for v in sizes)
        self._arg = (ctypes.c_void_p * sz_arg)()
        self._res = (ctypes.c_void_p * sz_res)()
        self._iw = np.zeros(sz_iw, dtype=np.int64)
        self._w = np.zeros(sz_w, dtype=np.float64)
        self._in = (ctypes.c_void_p * self.n_in)()
        self._out = (ctypes.c_void_p * self.n_out)()
        self._in_step = np.zeros(self.n_in, dtype=np.int64)
        self._out_step = np.array(self._nnz, dtype=np.int64)
        # the addresses that do not change from call to call, read once
        self._fixed = (self._in_step.ctypes.data, self._out_step.ctypes.data, self._iw.ctypes.data,
                       self._w.ctypes.data)

    def __reduce__(self):
        # made again from its function and library (a copy, or in another process): its ctypes pointers cannot travel
        return Pointwise, self._made_of

    def __call__(self, *args) -> list[np.ndarray]:
        if len(args) != self.n_in:
            raise ValueError(f"{self.name} takes {self.n_in} inputs; found {len(args)}")
        n, held = None, []
        for j, (a, size) in enumerate(zip(args, self.in_sizes)):
            a = np.ascontiguousarray(a, dtype=np.float64)
            if a.ndim == 1 and a.size == size:
                step = 0
            elif a.ndim == 2 and a.shape[1] == size:
                if n is not None and a.shape[0] != n:
                    raise ValueError(f"{self.name}: input {j} has {a.shape[0]} points, an earlier one {n}")
                n, step = a.shape[0], size
            else:
                raise ValueError(f"{self.name}: input {j} must be ({size},) or (n, {size}); found {a.shape}")
            held.append(a)
            self._in[j] = a.__array_interface__["data"][0]
            self._in_step[j] = step
        n = 1 if n is None else n
        outs = [np.empty((n, nnz)) for nnz in self._nnz]
        for j, o in enumerate(outs):
            self._out[j] = o.__array_interface__["data"][0]
        in_step, out_step, iw, w = self._fixed
        flag = self._call(n, self._in, in_step, self._out, out_step, self._arg, self._res, iw, w, 0)
        if flag:
            raise RuntimeError(f"{self.name} failed at a point (status {flag})")
        for j, where in enumerate(self._where):
            if where is not None:
                dense = np.zeros((n, self.out_sizes[j]))
                dense[:, where] = outs[j]
                outs[j] = dense
        return outs


def _compile(code: bytes, name: str, lib: Path, use: str = "period", flags: tuple[str, ...] | None = None) -> None:
    flags = _flags(use) if flags is None else flags
    cc = os.environ.get("CC") or "cc"
    if shutil.which(cc) is None:
        raise OSError(f"no C compiler {cc!r} on the PATH")
    lib.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        src = Path(tmp) / f"{name}.c"
        src.write_bytes(code)
        out = Path(tmp) / lib.name
        r = subprocess.run([cc, *flags, "-o", str(out), str(src), "-lm"], capture_output=True, text=True,
                           timeout=600)
        if r.returncode != 0:
            raise OSError(f"{cc} failed: {r.stderr.strip()[:500]}")
        os.replace(out, lib)     # atomic: a parallel process sees either no library or a whole one
