"""CasADi functions compiled to C (sim.equations.compiled): the same numbers as CasADi's virtual machine, a cache per
machine, compilation ahead of time, and a fallback without a compiler."""

import casadi as ca
import numpy as np
import pytest

import sim.equations.compiled as sc

TOL = {
    "compiled_vs_vm": 1e-13,   # the same operations in C; only the compiler's reassociation may differ
}


def _function(name="t_fn"):
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    y = ca.vertcat(ca.sin(x[0]) * u[0], x[1] * x[2] + u[1] ** 2, ca.exp(-x[2]) * u[0] * u[1])
    return ca.Function(name, [x, u], [y, ca.densify(ca.jacobian(y, x))])


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("PINNMPC_CACHE", str(tmp_path))
    monkeypatch.setattr(sc, "_loaded", {})
    return tmp_path


def test_compiled_function_gives_the_virtual_machines_numbers(cache):
    f = _function()
    g = sc.compiled(f)
    assert g is not f and len(list(cache.glob("t_fn-*.so"))) == 1
    rng = np.random.default_rng(3)
    for _ in range(20):
        x, u = rng.normal(size=3), rng.normal(size=2)
        for a, b in zip(f(x, u), g(x, u)):
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=TOL["compiled_vs_vm"],
                                       atol=TOL["compiled_vs_vm"])


def test_precompile_builds_each_library_once_and_compiled_only_loads_it(cache, monkeypatch):
    fns = [_function("t_a"), _function("t_b")]
    assert sc.precompile(fns, jobs=2) == 2
    assert sc.precompile(fns, jobs=2) == 0         # in the cache now

    def no_compiler(*args):
        raise AssertionError("compiled() compiled a library that precompile() had built")
    monkeypatch.setattr(sc, "_compile", no_compiler)
    g = sc.compiled(fns[0])
    assert g is not fns[0]
    np.testing.assert_allclose(np.asarray(g([0.1, 0.2, 0.3], [1.0, 2.0])[0]),
                               np.asarray(fns[0]([0.1, 0.2, 0.3], [1.0, 2.0])[0]), rtol=TOL["compiled_vs_vm"])


def test_without_a_compiler_the_function_itself_is_used_with_a_warning(cache, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-pinnmpc")
    f = _function("t_nocc")
    with pytest.warns(RuntimeWarning, match="virtual machine"):
        g = sc.compiled(f)
    assert g is f
    assert sc.precompile([_function("t_nocc2")]) == 1     # tried, failed quietly: compiled() reports it
    assert not list(cache.glob("t_nocc*.so"))


def test_sensitivities_refuse_a_sparse_output():
    from sim.identification.fisher import _map_eval

    x = ca.SX.sym("x", 12)
    u, th = ca.SX.sym("u", 4), ca.SX.sym("theta", 6)
    f = ca.Function("sparse", [x, u, th], [ca.jacobian(x[0] * th[0], th)])    # one nonzero in six
    with pytest.raises(ValueError, match="densify"):
        _map_eval(f, np.zeros((3, 12)), np.zeros((3, 4)), np.ones(6))


def test_a_batch_function_compiles_unoptimized_to_the_same_numbers_bit_for_bit(cache, monkeypatch):
    """The ``batch`` use compiles at -O0 and the ``period`` use at -O1, into two libraries of one function; both give
    the same numbers to the last bit on the analytic model's step (ten RK4 substeps)."""
    from sim.equations.dynamics_casadi import step_function
    from sim.params import QuadParams

    calls = []
    real = sc._compile
    monkeypatch.setattr(sc, "_compile", lambda code, name, lib, use="period": calls.append(use) or real(code, name,
                                                                                                        lib, use))
    f = step_function(QuadParams())
    fast_run, fast_build = sc.compiled(f, "period"), sc.compiled(f, "batch")
    assert calls == ["period", "batch"] and len(list(cache.glob("*.so"))) == 2
    rng = np.random.default_rng(7)
    x = rng.normal(size=(12, 200)) * np.r_[1, 1, 1, 0.5, 0.5, 3, 2, 2, 2, 2, 2, 2][:, None]
    u = np.abs(rng.normal(size=(4, 200))) * 0.1
    a = np.asarray(fast_run.map(200)(x, u))
    b = np.asarray(fast_build.map(200)(x, u))
    assert np.array_equal(a, b) and np.all(np.isfinite(a))


def test_an_unknown_use_is_refused_by_name(cache):
    with pytest.raises(ValueError, match="use must be one of period, batch, kernel; found 'fast'"):
        sc.compiled(_function("t_use"), "fast")


def _sparse_function(name):
    """A function with a sparse output (the Jacobian of a map whose first entry ignores x[1]) and a shared
    parameter input."""
    x, u, p = ca.SX.sym("x", 3), ca.SX.sym("u", 2), ca.SX.sym("p", 2)
    y = ca.vertcat(p[0] * ca.sin(x[0]) * u[0], x[1] * x[2] + u[1] ** 2 * p[1], ca.exp(-x[2]) * u[0])
    return ca.Function(name, [x, u, p], [y, ca.jacobian(y, x)])


def test_the_point_loop_gives_casadis_numbers_bit_for_bit_dense_and_sparse(cache):
    """Many points in one C call (Pointwise) against CasADi's own call of the same compiled library, point by point:
    equal to the last bit (the same compiled function), structural zeros written as zeros, a shared input broadcast,
    and one point as a batch of one."""
    rng = np.random.default_rng(0)
    x, u, p = rng.standard_normal((7, 3)), rng.standard_normal((7, 2)), np.array([0.7, -1.3])
    for f in (_sparse_function("t_points"), _function("t_points_dense")):
        g, lib = sc.compiled_library(f)
        assert lib is not None and lib.is_file()
        pw = sc.Pointwise(g, lib)
        args = (x, u, p)[:f.n_in()]
        outs = pw(*args)
        for i in range(len(x)):
            ref = g(*[a[i] if a.ndim == 2 else a for a in args])
            ref = ref if isinstance(ref, (list, tuple)) else [ref]
            for j, r in enumerate(ref):
                r = np.asarray(ca.DM(r).full())
                assert np.array_equal(outs[j][i], r.ravel(order="F")), (f.name(), i, j)
        one = pw(*[a[:1] if a.ndim == 2 else a for a in args])
        assert all(np.array_equal(o1[0], o[0]) for o1, o in zip(one, outs))


def test_the_point_loop_names_a_wrong_input():
    f = _sparse_function("t_points_bad")
    g, lib = sc.compiled_library(f)
    pw = sc.Pointwise(g, lib)
    x = np.zeros((4, 3))
    with pytest.raises(ValueError, match=r"input 1 must be \(2,\) or \(n, 2\); found \(4, 3\)"):
        pw(x, np.zeros((4, 3)), np.zeros(2))
    with pytest.raises(ValueError, match="input 1 has 5 points, an earlier one 4"):
        pw(x, np.zeros((5, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="takes 3 inputs; found 2"):
        pw(x, np.zeros((4, 2)))


def test_a_c_source_is_compiled_once_per_processor_and_refused_with_a_warning_without_a_compiler(cache, monkeypatch):
    code = "double t_twice(double x) { return 2.0 * x; }\n"
    lib = sc.c_library("t_twice", code)
    assert lib is not None and lib.parent == cache
    import ctypes
    fn = ctypes.CDLL(str(lib)).t_twice
    fn.restype, fn.argtypes = ctypes.c_double, [ctypes.c_double]
    assert fn(1.25) == 2.5
    monkeypatch.setattr(sc, "_loaded", {})
    monkeypatch.setattr(sc, "_cpu_signature", lambda: "another processor")
    other = sc.c_library("t_twice", code)
    assert other != lib and len(list(cache.glob("t_twice-*.so"))) == 2    # never another machine's instructions
    monkeypatch.setattr(sc, "_loaded", {})
    monkeypatch.setenv("CC", "no-such-compiler-pinnmpc")
    with pytest.warns(RuntimeWarning, match="numpy path"):
        assert sc.c_library("t_thrice", code.replace("2.0", "3.0")) is None
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")                   # once per process: not tried, nor said, again
        assert sc.c_library("t_thrice", code.replace("2.0", "3.0")) is None
