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
