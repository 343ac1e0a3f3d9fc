"""The LTV-MPC's QP condensed onto its inputs and solved by a dense active-set solver (DAQP).

The QP the LTV-MPC and the SQP solve each period is, over states ``x_0..x_N``
and inputs ``u_0..u_{N-1}``::

    min  1/2 sum_{k<N} |x_k - r_k|_Q^2 + 1/2 |x_N - r_N|_P^2 + 1/2 sum_k |u_k - v_k|_R^2
    s.t. x_0 = x,   x_{k+1} = A_k x_k + B_k u_k + c_k,
         lo_u <= L u_k <= hi_u   (k < N),   lo_s <= S x_k <= hi_s   (1 <= k <= N)

OSQP solves it as it stands (sparse, states and inputs). Here the states are
eliminated (``x = G u + w``, a forward recursion through the dynamics), which
leaves a dense QP in the ``N * nu`` inputs alone, small enough for a dense
active-set solver: on the SQP's own QPs of ``figure8-fast`` (120 inputs, 180
constraint rows) DAQP takes about 0.15 ms where OSQP took about 1.2 ms, and
the two agree to 1e-7 in the inputs.

:func:`solve_ltv_qp` gives the solution of the original QP: states, inputs and
the multipliers of every constraint in OSQP's convention (``H z + q + A' y =
0``), the dynamics' ones recovered by a backward recursion, so that a caller
that reads OSQP's duals reads the same thing. DAQP is an optional dependency
(``python -m pip install -e ".[dense]"``).

The condensing has two backends with the same recursions: numpy, and the C of
``condense.c`` beside this file, compiled into the cache of
:mod:`sim.equations.compiled` on first use. Each numpy call on these small
blocks costs a microsecond or two whatever its size, and the recursions make
about 150 of them per QP (0.3 ms for the SQP's 30 stages); the C loop does the
same arithmetic in about a third of that. Where no C compiler works, numpy.
They agree to rounding (``tests/test_dense_qp.py``).
"""

from __future__ import annotations

import ctypes
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigurationError, SolverError

#: QP solvers of the LTV-MPC and the SQP (:attr:`mpc.controllers.ltv.LTVSettings.qp`): OSQP on the sparse QP, or DAQP
#: on this
#: module's condensed one. Kept here, in a module that imports only numpy, so that the command line can offer them
#: without loading a solver.
QP_SOLVERS = ("osqp", "daqp")
#: DAQP's exit flags that mean a solution: optimal, and optimal with soft constraints relaxed.
SOLVED_FLAGS = (1, 2)
#: The condensing's backends (:func:`condense_matrices`, :func:`prepare_ltv_qp`): the compiled C loop, or numpy.
CONDENSE_BACKENDS = ("c", "numpy")
_KERNEL: list = []      # the compiled condensing (a ctypes function), or None where it could not be compiled


@dataclass(frozen=True)
class LTVQP:
    """One QP of the form in the module docstring.

    Attributes
    ----------
    A : ndarray, shape (N, nx, nx)
    B : ndarray, shape (N, nx, nu)
    c : ndarray, shape (N, nx)
        Dynamics ``x_{k+1} = A_k x_k + B_k u_k + c_k``.
    x0 : ndarray, shape (nx,)
    Q, P : ndarray, shape (nx, nx)
        Stage and terminal state weights (symmetric, positive semidefinite).
    R : ndarray, shape (nu, nu)
        Input weight (symmetric, positive definite).
    ref : ndarray, shape (N + 1, nx)
    u_ref : ndarray, shape (N, nu)
    L : ndarray, shape (m, nu)
    lo_u, hi_u : ndarray, shape (m,)
        Input constraints, every stage.
    S : ndarray, shape (p, nx)
    lo_s, hi_s : ndarray, shape (p,)
        State constraints, stages 1..N (``p = 0``: none).
    """

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray
    x0: np.ndarray
    Q: np.ndarray
    P: np.ndarray
    R: np.ndarray
    ref: np.ndarray
    u_ref: np.ndarray
    L: np.ndarray
    lo_u: np.ndarray
    hi_u: np.ndarray
    S: np.ndarray
    lo_s: np.ndarray
    hi_s: np.ndarray

    def __post_init__(self):
        N, nx, nu = self.B.shape
        shapes = {"A": (N, nx, nx), "c": (N, nx), "x0": (nx,), "Q": (nx, nx), "P": (nx, nx), "R": (nu, nu),
                  "ref": (N + 1, nx), "u_ref": (N, nu), "L": (self.L.shape[0], nu),
                  "lo_u": (self.L.shape[0],), "hi_u": (self.L.shape[0],), "S": (self.S.shape[0], nx),
                  "lo_s": (self.S.shape[0],), "hi_s": (self.S.shape[0],)}
        for name, shape in shapes.items():
            found = np.shape(getattr(self, name))
            if found != shape:
                raise ConfigurationError(f"{name} must have shape {shape} (B is {self.B.shape}); found {found}")


@dataclass(frozen=True)
class Condensed:
    """The part of a condensed QP that depends only on its matrices (``A``, ``B``, the weights and the constraint
    rows), not on ``c``, ``x0``, the references or the bounds: what QPs with the same matrices share (a
    second-order correction's QP, an SQP iteration that keeps its Jacobians).

    ``G`` (N + 1, nx, n): ``x_k = G_k u + w_k``; ``WG`` (N + 1, nx, n): ``W_k G_k`` with ``W_k`` the stage
    weight (``P`` at ``k = N``); ``H`` (n, n), the dense Hessian; ``C`` (r, n), the constraint rows.
    """

    G: np.ndarray
    WG: np.ndarray
    H: np.ndarray
    C: np.ndarray


@dataclass(frozen=True)
class DenseSolution:
    """The solution of an :class:`LTVQP` by :func:`solve_ltv_qp`.

    ``x`` (N + 1, nx) and ``u`` (N, nu); the multipliers ``y_init`` (nx,) of ``x_0 = x``, ``y_dyn`` (N, nx) of
    the dynamics rows written ``-x_{k+1} + A_k x_k + B_k u_k = -c_k``, ``y_u`` (N, m) and ``y_s`` (N, p) of the
    constraints (positive where an upper bound holds, negative at a lower one); ``flag``, DAQP's exit flag;
    ``iterations``; ``solve_s`` (condensing included) and ``condense_s``; ``matrices``, the :class:`Condensed`
    part, for a next QP with the same matrices.
    """

    x: np.ndarray
    u: np.ndarray
    y_init: np.ndarray
    y_dyn: np.ndarray
    y_u: np.ndarray
    y_s: np.ndarray
    flag: int
    iterations: int
    solve_s: float
    condense_s: float
    matrices: Condensed = field(repr=False, default=None)

    @property
    def solved(self) -> bool:
        """DAQP found a solution and it is finite."""
        return self.flag in SOLVED_FLAGS and bool(np.all(np.isfinite(self.u)))

    def is_optimal(self, qp: LTVQP, eps: float = 1e-6) -> bool:
        """Every KKT condition of the original (sparse) QP holds within ``eps`` (absolute, unscaled)."""
        return self.solved and max(kkt_residuals(qp, self).values()) <= eps


def condense_matrices(qp: LTVQP, backend: str | None = None) -> Condensed:
    """The matrix part of :func:`condense`.

    ``G`` by a forward recursion through the dynamics; ``H = G' W G + R`` by a
    backward one, which never multiplies the zero blocks of ``G`` (``x_k``
    depends only on the inputs before stage ``k``): with ``Z_N = W_N G_N`` and
    ``Z_k = W_k G_k + A_k' Z_{k+1}``, the rows of input ``j`` are
    ``B_j' Z_{j+1}``. ``backend``: one of :data:`CONDENSE_BACKENDS`, or None for
    the C loop where it compiles and numpy elsewhere.
    """
    kernel = _kernel(backend)
    if kernel is not None:
        return _condense_c(kernel, qp, 0)[0]
    return _condensed(qp, _forward(qp, free=False))


def _kernel(backend: str | None):
    """The compiled condensing for ``backend`` (None: where it compiles), or None for numpy."""
    if backend not in (None, *CONDENSE_BACKENDS):
        raise ConfigurationError(f"backend must be one of {', '.join(CONDENSE_BACKENDS)} or None; found {backend!r}")
    if backend == "numpy":
        return None
    if not _KERNEL:
        from sim.equations.compiled import c_library

        lib = c_library("pinnmpc_condense", Path(__file__).with_name("condense.c").read_text())
        fn = None
        if lib is not None:
            fn = ctypes.CDLL(str(lib)).pinnmpc_condense
            fn.restype = ctypes.c_int
            fn.argtypes = [ctypes.c_int] * 3 + [ctypes.c_void_p] * 6 + [ctypes.c_int] * 2 + [ctypes.c_void_p] * 5
        _KERNEL.append(fn)
    if _KERNEL[0] is None and backend == "c":
        raise ConfigurationError("backend 'c' asked for, but the condensing could not be compiled (no working C "
                                 "compiler; see the warning); use backend='numpy' or None")
    return _KERNEL[0]


def _condense_c(kernel, qp: LTVQP, f: int):
    """``(Condensed, M)`` by the compiled loop: ``M`` (N + 1, nx, f), the free response ``[Phi | v | Psi]`` of
    :func:`_forward` (``f`` = 0: none, None; nx + 1: without ``Psi``; 2 nx + 1: with it)."""
    N, nx, nu = qp.B.shape
    n = N * nu
    a = [np.ascontiguousarray(v, dtype=np.float64) for v in (qp.A, qp.B, qp.c, qp.Q, qp.P, qp.R)]
    diagonal = _diagonal_weights(qp)
    G, WG = np.empty((N + 1, nx, n)), np.empty((N + 1, nx, n))
    H, Z = np.empty((n, n)), np.empty((2, nx, n))
    M = np.empty((N + 1, nx, max(f, 1)))
    ptr = [v.ctypes.data for v in (*a, G, WG, H, M, Z)]
    if kernel(N, nx, nu, *ptr[:6], int(diagonal), f, *ptr[6:]):
        raise SolverError(f"the compiled condensing refused N={N}, nx={nx}, nu={nu}, f={f}")
    return Condensed(G=G, WG=WG, H=H, C=_constraint_rows(qp, G)), (M if f else None)


def _forward(qp: LTVQP, free: bool, offsets: bool = True, inputs: bool = True) -> np.ndarray:
    """The forward recursion through the dynamics: ``T`` (N + 1, r, g + f) whose first nx rows hold ``G`` of
    :class:`Condensed` in their first ``g = N nu`` columns (``g = 0`` without ``inputs``) and, with ``free``, the
    free response ``[Phi | v | Psi]`` of :class:`PreparedQP` in the other ``f`` (``Psi`` only with ``offsets``;
    ``f = 0`` without ``free``).

    Per stage: ``A_k`` times the columns of the inputs before stage ``k`` (the others are zero), ``B_k`` into
    input ``k``'s; and with ``free`` one more product, in which the constant terms ride along as rows: the free
    columns hold ``[Phi_k | v_k | Psi_k]`` over the constant rows ``[0 | 1 | 0]`` and ``[0 | 0 | I]`` (``r = 2 nx
    + 1``; ``nx + 1`` without ``Psi``; ``nx`` without ``free``), so that ``[A_k | c_k | I]`` times them is the
    next stage's."""
    N, nx, nu = qp.B.shape
    n = N * nu
    e = nx if offsets else 0
    g = n if inputs else 0
    rows = nx + 1 + e if free else nx
    T = np.zeros((N + 1, rows, g + (rows if free else 0)))
    if free:
        T[0, :nx, g:g + nx] = np.eye(nx)                    # Phi_0 = I, v_0 = 0, Psi_0 = 0
        T[:, nx, g + nx] = 1.0                              # the constant rows
        T[:, nx + 1:, g + nx + 1:] = np.eye(e)
        step = np.zeros((N, nx, rows))                      # [A_k | c_k | I]
        step[:, :, :nx] = qp.A
        step[:, :, nx] = qp.c
        step[:, :, nx + 1:] = np.eye(nx)[:, :e]
    for k in range(N):
        m = k * nu
        if inputs:
            np.matmul(qp.A[k], T[k, :nx, :m], out=T[k + 1, :nx, :m])    # only the inputs before stage k move x_k
            T[k + 1, :nx, m:m + nu] = qp.B[k]
        if free:
            np.matmul(step[k], T[k, :, g:], out=T[k + 1, :nx, g:])
    return T


def _diagonal_weights(qp: LTVQP) -> bool:
    """The state weights ``Q`` and ``P`` are diagonal (both backends then scale rows instead of multiplying)."""
    return all(np.array_equal(w, np.diag(np.diag(w))) for w in (qp.Q, qp.P))


def _condensed(qp: LTVQP, T: np.ndarray) -> Condensed:
    """:class:`Condensed` of ``qp`` from its forward recursion ``T`` (:func:`_forward`)."""
    N, nx, nu = qp.B.shape
    n = N * nu
    G = T[:, :nx, :n]
    WG = np.empty((N + 1, nx, n))
    if _diagonal_weights(qp):
        np.multiply(G[:N], np.diag(qp.Q)[:, None], out=WG[:N])    # the usual case: each row scaled
        np.multiply(G[N], np.diag(qp.P)[:, None], out=WG[N])
    else:
        np.matmul(qp.Q, G[:N], out=WG[:N])
        np.matmul(qp.P, G[N], out=WG[N])
    Z = np.empty((N + 1, nx, n))
    Z[N] = WG[N]
    At = qp.A.transpose(0, 2, 1)
    for k in range(N - 1, 0, -1):
        np.matmul(At[k], Z[k + 1], out=Z[k])
        Z[k] += WG[k]
    H = np.matmul(qp.B.transpose(0, 2, 1), Z[1:]).reshape(n, n)
    d = np.arange(N)
    H.reshape(N, nu, N, nu)[d, :, d, :] += qp.R          # the input weight on the diagonal blocks
    H += H.T
    H *= 0.5
    return Condensed(G=G, WG=WG, H=H, C=_constraint_rows(qp, G))


def _constraint_rows(qp: LTVQP, G: np.ndarray) -> np.ndarray:
    """The dense QP's constraint rows ``C`` (r, n): the input constraints of every stage, then the state
    constraints of stages 1..N through the state maps ``G`` (N + 1, nx, n)."""
    N, nx, nu = qp.B.shape
    n = N * nu
    d = np.arange(N)
    m, ps = qp.L.shape[0], qp.S.shape[0]
    C = np.zeros((N * (m + ps), n))
    C[:N * m].reshape(N, m, N, nu)[d, :, d, :] = qp.L   # the input constraints, stage by stage
    if ps:
        C[N * m:] = np.matmul(qp.S, G[1:]).reshape(N * ps, n)
    return C


def condense(qp: LTVQP, matrices: Condensed | None = None):
    """The dense QP in the inputs: ``(H (n, n), f (n,), C (r, n), lo (r,), hi (r,), G, w)`` with ``n = N nu``.

    ``G`` (N + 1, nx, n) and ``w`` (N + 1, nx) give the states ``x_k = G_k u + w_k``; the rows of ``C`` are the
    input constraints of every stage, then the state constraints of stages 1..N. ``matrices``: the
    :class:`Condensed` part of a QP with the same matrices (:func:`condense_matrices` of it), reused as it is.
    """
    if matrices is None:
        matrices = condense_matrices(qp)
    N, nx, nu = qp.B.shape
    w = np.empty((N + 1, nx))
    w[0] = qp.x0
    for k in range(N):
        w[k + 1] = qp.A[k] @ w[k] + qp.c[k]
    f, lo, hi = _cost_and_bounds(qp, matrices.WG, w, qp.ref, qp.u_ref)
    return matrices.H, f, matrices.C, lo, hi, matrices.G, w


def _cost_and_bounds(qp: LTVQP, WG: np.ndarray, w: np.ndarray, ref: np.ndarray, u_ref: np.ndarray):
    """The dense QP's linear cost ``f`` (n,) and its rows' bounds ``lo``, ``hi`` (r,), for the states with no input
    ``w`` (N + 1, nx), the weighted state maps ``WG`` (N + 1, nx, n) (:class:`Condensed`), the reference ``ref`` and
    the feed-forward ``u_ref``: ``f = sum_k (W_k G_k)' (w_k - ref_k) - R u_ref``; the input bounds at every stage,
    then the state bounds less ``S w_k`` at stages 1..N."""
    N = len(qp.c)
    f = (w - ref).ravel() @ WG.reshape(-1, WG.shape[2]) - (u_ref @ qp.R).ravel()
    Sw = (w[1:] @ qp.S.T).ravel()
    lo = np.concatenate([np.tile(qp.lo_u, N), np.tile(qp.lo_s, N) - Sw])
    hi = np.concatenate([np.tile(qp.hi_u, N), np.tile(qp.hi_s, N) - Sw])
    return f, lo, hi


def _daqp(H, f, C, lo, hi, time_limit_s: float | None):
    """DAQP on the dense QP ``min u' H u / 2 + f' u, lo <= C u <= hi``: ``(u, flag, iterations, lam)``, its own
    errors wrapped in a :class:`SolverError` that says what was asked of it."""
    from ctypes import c_int

    import daqp

    opts = {} if time_limit_s is None else {"time_limit": float(time_limit_s)}
    try:
        u, _, flag, info = daqp.solve(H, f, C, hi, lo, np.zeros(len(lo), dtype=c_int), **opts)
    except Exception as e:  # noqa: BLE001 - DAQP's own errors, wrapped with what was asked of it
        raise SolverError(f"DAQP failed on a QP of {H.shape[0]} inputs and {C.shape[0]} rows: {e}") from e
    lam = np.asarray(info.get("lam", np.full(len(lo), np.nan)), dtype=float)
    return np.asarray(u, dtype=float), int(flag), int(info.get("iterations", 0)), lam


@dataclass(frozen=True)
class PreparedQP:
    """An :class:`LTVQP` condensed for every initial state at once: what the real-time iteration's preparation
    builds before the state is measured, so that its feedback only embeds the state and solves.

    The states are ``x_k = G_k u + Phi_k x_0 + v_k + Psi_k delta``, where ``delta`` (nx,) is added to every
    ``c_k`` (a disturbance offset that changed since the preparation); the dense QP's linear cost and its bounds
    follow from them and from the reference (:func:`solve_prepared`). ``qp`` is the QP it was made from (its ``x0``
    unused).

    Attributes
    ----------
    H : ndarray, shape (n, n)
    C : ndarray, shape (r, n)
    G : ndarray, shape (N + 1, nx, n)
    WG : ndarray, shape (N + 1, nx, n)
        ``W_k G_k``: the linear cost is ``sum_k (W_k G_k)' (x_free_k - ref_k) - R u_ref``.
    Phi, Psi : ndarray, shape (N + 1, nx, nx)
        ``Psi`` None until a feedback first needs it (:func:`prepare_ltv_qp`'s ``offsets``).
    v : ndarray, shape (N + 1, nx)
    """

    qp: LTVQP
    H: np.ndarray
    C: np.ndarray
    G: np.ndarray
    WG: np.ndarray
    Phi: np.ndarray
    Psi: np.ndarray | None
    v: np.ndarray

    def free(self, x0: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
        """The states (N + 1, nx) with no input: from ``x0`` (nx,), with every ``c_k`` moved by ``delta``."""
        w = self.Phi @ x0 + self.v
        if delta is None:
            return w
        if self.Psi is None:            # made once, on the first feedback that needs it
            T = _forward(self.qp, free=True, offsets=True, inputs=False)
            object.__setattr__(self, "Psi", T[:, :self.qp.A.shape[1], -self.qp.A.shape[1]:])
        return w + self.Psi @ delta

    def states(self, x0: np.ndarray, u: np.ndarray, delta: np.ndarray | None = None) -> np.ndarray:
        """The states (N + 1, nx) of the inputs ``u`` (N nu,) from ``x0`` (nx,) (and ``delta``, as :meth:`free`)."""
        return np.matmul(self.G, u) + self.free(x0, delta)


def prepare_ltv_qp(qp: LTVQP, matrices: Condensed | None = None, offsets: bool = True,
                   backend: str | None = None) -> PreparedQP:
    """Condense ``qp`` for any initial state (its ``x0`` is not used): a :class:`PreparedQP`.

    ``matrices``: the :class:`Condensed` part of a QP with the same matrices, reused as it is. ``offsets``: also
    make the response to a change of the constant terms (``Psi``) now; without, it is made when a feedback first
    asks for it (a model with no disturbance offset never does). ``backend``: as :func:`condense_matrices`.
    """
    N, nx, nu = qp.B.shape
    kernel = _kernel(backend)
    if matrices is None and kernel is not None:
        matrices, M = _condense_c(kernel, qp, 2 * nx + 1 if offsets else nx + 1)
        return PreparedQP(qp=qp, H=matrices.H, C=matrices.C, G=matrices.G, WG=matrices.WG, Phi=M[:, :, :nx],
                          Psi=M[:, :, nx + 1:] if offsets else None, v=M[:, :, nx])
    g = N * nu if matrices is None else 0
    T = _forward(qp, free=True, offsets=offsets, inputs=matrices is None)   # G and the free response at once
    if matrices is None:
        matrices = _condensed(qp, T)
    M = T[:, :nx, g:]
    return PreparedQP(qp=qp, H=matrices.H, C=matrices.C, G=matrices.G, WG=matrices.WG, Phi=M[:, :, :nx],
                      Psi=M[:, :, nx + 1:] if offsets else None, v=M[:, :, nx])


@dataclass(frozen=True)
class Feedback:
    """What :func:`solve_prepared` found: the inputs ``u`` (N, nu), DAQP's ``flag`` and ``iterations``, the constraint
    multipliers ``lam`` (r,) and ``solve_s``, s."""

    u: np.ndarray
    flag: int
    iterations: int
    lam: np.ndarray
    solve_s: float

    @property
    def solved(self) -> bool:
        """DAQP found a solution and it is finite."""
        return self.flag in SOLVED_FLAGS and bool(np.all(np.isfinite(self.u)))


def solve_prepared(prep: PreparedQP, x0: np.ndarray, time_limit_s: float | None = None,
                   delta: np.ndarray | None = None, ref: np.ndarray | None = None,
                   u_ref: np.ndarray | None = None) -> Feedback:
    """The real-time iteration's feedback: the prepared QP with the initial state ``x0`` (nx,), solved by DAQP.

    ``delta`` (nx,): added to every ``c_k`` (an offset that changed since the preparation; None: none); ``ref``
    (N + 1, nx) and ``u_ref`` (N, nu): the reference and feed-forward now (None: the prepared QP's). Its inputs
    equal :func:`solve_ltv_qp`'s for the QP with these. A failure of DAQP is data (``flag``, ``solved``).
    """
    t0 = time.perf_counter()
    qp = prep.qp
    w = prep.free(np.asarray(x0, dtype=float), delta)
    f, lo, hi = _cost_and_bounds(qp, prep.WG, w, qp.ref if ref is None else ref, qp.u_ref if u_ref is None else u_ref)
    u, flag, iterations, lam = _daqp(prep.H, f, prep.C, lo, hi, time_limit_s)
    return Feedback(u=u.reshape(-1, qp.B.shape[2]), flag=flag, iterations=iterations, lam=lam,
                    solve_s=time.perf_counter() - t0)


def daqp_installed() -> bool:
    """DAQP (the optional extra ``dense``) can be imported."""
    import importlib.util

    return importlib.util.find_spec("daqp") is not None


def require_daqp() -> None:
    """Raise a :class:`ConfigurationError` that says how to install DAQP if it is missing."""
    if not daqp_installed():
        raise ConfigurationError('the dense QP path needs DAQP, an optional extra: python -m pip install -e ".[dense]"')


def solve_ltv_qp(qp: LTVQP, time_limit_s: float | None = None, matrices: Condensed | None = None) -> DenseSolution:
    """Solve ``qp`` condensed, by DAQP; states, inputs and every multiplier (:class:`DenseSolution`).

    A failure of DAQP (infeasible, iteration or time limit) is data: the solution says so in ``flag`` and
    ``solved``. ``time_limit_s``: DAQP's time limit (None: none). ``matrices``: the condensed matrices of a QP
    with the same matrices as ``qp`` (the solution's ``matrices`` of it), reused instead of condensed again.
    """
    require_daqp()
    t0 = time.perf_counter()
    if matrices is None:
        matrices = condense_matrices(qp)
    H, f, C, lo, hi, G, w = condense(qp, matrices)
    t1 = time.perf_counter()
    u, flag, iterations, lam = _daqp(H, f, C, lo, hi, time_limit_s)
    N, nx, nu = qp.B.shape
    x = (G.reshape(-1, N * nu) @ u).reshape(N + 1, nx) + w
    U = u.reshape(N, nu)
    m, p = qp.L.shape[0], qp.S.shape[0]
    y_u, y_s = lam[:N * m].reshape(N, m), lam[N * m:].reshape(N, p)
    y_init, y_dyn = _dynamics_multipliers(qp, x, y_s)
    return DenseSolution(x=x, u=U, y_init=y_init, y_dyn=y_dyn, y_u=y_u, y_s=y_s, flag=flag,
                         iterations=iterations, solve_s=time.perf_counter() - t0,
                         condense_s=t1 - t0, matrices=matrices)


def _dynamics_multipliers(qp: LTVQP, x: np.ndarray, y_s: np.ndarray):
    """Multipliers of ``x_0 = x`` (nx,) and of the dynamics rows (N, nx), from stationarity in the states:
    ``y_{k-1} = W_k (x_k - r_k) + A_k' y_k + S' y_s,k`` backwards from ``y_{N-1} = P (x_N - r_N) + S' y_s,N``."""
    N, nx, _ = qp.B.shape
    g = (x - qp.ref) @ qp.Q            # g_k = W_k (x_k - r_k) + S' y_s,k, every stage at once (W, Q symmetric)
    g[N] = qp.P @ (x[N] - qp.ref[N])
    g[1:] += y_s @ qp.S
    y = np.empty((N, nx))
    y[N - 1] = g[N]
    for k in range(N - 1, 0, -1):
        y[k - 1] = g[k] + y[k] @ qp.A[k]
    y_init = -(g[0] + y[0] @ qp.A[0])
    return y_init, y


def kkt_residuals(qp: LTVQP, sol: DenseSolution) -> dict:
    """Largest violation of each KKT condition of the original QP at ``sol``: ``dynamics``, ``initial``,
    ``inputs`` (stationarity in u), ``bounds`` (constraints), ``signs`` (a multiplier of the wrong sign for the
    bound it is at, or nonzero off its bounds: complementarity)."""
    x, u = sol.x, sol.u
    dyn = x[1:] - (np.einsum("kij,kj->ki", qp.A, x[:-1]) + np.einsum("kij,kj->ki", qp.B, u) + qp.c)
    stat_u = (u - qp.u_ref) @ qp.R + np.einsum("kij,ki->kj", qp.B, sol.y_dyn) + sol.y_u @ qp.L
    Lu, Sx = u @ qp.L.T, x[1:] @ qp.S.T
    bounds = max(np.max(np.maximum(qp.lo_u - Lu, Lu - qp.hi_u), initial=0.0),
                 np.max(np.maximum(qp.lo_s - Sx, Sx - qp.hi_s), initial=0.0))

    def complementarity(y, v, lo, hi):
        return np.max(np.abs(np.minimum(np.maximum(y, 0.0), np.abs(hi - v))
                             + np.minimum(np.maximum(-y, 0.0), np.abs(v - lo))), initial=0.0)

    return {"dynamics": float(np.max(np.abs(dyn))), "initial": float(np.max(np.abs(x[0] - qp.x0))),
            "inputs": float(np.max(np.abs(stat_u))), "bounds": float(bounds),
            "signs": float(max(complementarity(sol.y_u, Lu, qp.lo_u, qp.hi_u),
                               complementarity(sol.y_s, Sx, qp.lo_s, qp.hi_s)))}
