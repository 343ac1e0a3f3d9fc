"""The benchmark's command line refuses what it cannot fly, by name (no timing is asserted anywhere)."""

import pytest

from mpc import bench


def refused(argv, capsys) -> str:
    """The one line on stderr with which the benchmark refuses ``argv`` (exit status 2)."""
    with pytest.raises(SystemExit) as stop:
        bench.main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and len(err.strip().splitlines()) == 1, (stop.value.code, err)
    return err


@pytest.mark.parametrize("compare", ["full", "full,full", "full,bad", "full,partial,dense", ""])
def test_a_bad_pair_of_paths_is_refused_by_name(compare, capsys):
    assert "--compare: two different paths of full, partial, dense, rti, rti1, rti_full expected" in \
        refused(["--answers", "--compare", compare], capsys)


def test_the_speed_benchmark_flies_the_dense_path_only_with_daqp(monkeypatch, capsys):
    import importlib.util

    have = importlib.util.find_spec("daqp") is not None
    assert ("dense" in bench.speed_paths()) == have
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "daqp" else real(name, *a))
    assert list(bench.speed_paths()) == ["full", "partial"]
    assert "the dense path needs DAQP" in refused(["--answers", "--compare", "full,dense"], capsys)
    assert "the dense and rti paths need DAQP" in refused(["--answers", "--compare", "dense,rti"], capsys)


@pytest.mark.parametrize("argv,match", [(["--paths", "full,nope"], "--paths: different paths of full, partial"),
                                        (["--paths", ","], "--paths: different paths of"),
                                        (["--paths", "full,full"], "--paths: different paths of"),
                                        (["--load", "0"], "--load: an integer >= 1 expected; found 0"),
                                        (["--load", "-3"], "--load: an integer >= 1 expected; found -3")])
def test_bad_speed_options_are_refused_by_name(argv, match, monkeypatch, capsys):
    monkeypatch.setattr(bench, "daqp_installed", lambda: False)
    assert match in refused(["--controllers", "sqp", "--cases", "hover", *argv], capsys)


@pytest.mark.parametrize("argv,match", [(["--cases", "nope"], "--cases: unknown ['nope']"),
                                        (["--controllers", "pid"], "--controllers: unknown ['pid']"),
                                        (["--models", "no-such-folder"], "--models: 'no-such-folder' is not a folder"),
                                        (["--derivatives", "--models", "no-such-folder"], "is not a folder"),
                                        (["--slowdown", "0.5"], "--slowdown: a factor >= 1 expected; found 0.5"),
                                        (["--answers", "--members", "0"], "--members and --jobs: integers >= 1")])
def test_every_bad_option_is_one_line_and_exit_status_2(argv, match, capsys):
    assert match in refused(argv, capsys)


def test_copies_of_a_flight_pool_their_periods():
    """Two copies flown at once count as one flight of twice the periods: the pooled median, p99 and max are those
    of all periods, the counts summed, the RMSE their mean."""
    import numpy as np

    def copy(load, lat, rmse, misses):      # per-period times in ms, handed over in s as run() records them
        return {"_load_s": 1e-3 * np.asarray(load, float), "_latency_s": 1e-3 * np.asarray(lat, float),
                "_cold": np.zeros(len(load), bool), "deadline_misses": misses, "solver_failures": 0, "fallbacks": 0,
                "steps": len(load), "rmse_position_m": rmse, "iterations": {"mean": 1.0}}

    r = bench._pooled([copy([1, 2, 3], [0.1, 0.2, 0.3], 0.01, 0), copy([4, 5, 11], [0.4, 0.5, 0.6], 0.03, 1)])
    exact = dict(rel=1e-12)     # ms back from s: rounding only
    assert r["solve_ms"]["median"] == pytest.approx(3.5, **exact)
    assert r["solve_ms"]["max"] == pytest.approx(11.0, **exact)
    assert r["solve_ms"]["max_without_cold_starts"] == pytest.approx(11.0, **exact)
    assert r["latency_ms"]["median"] == pytest.approx(0.35) and r["latency_ms"]["max"] == pytest.approx(0.6, **exact)
    assert r["latency_ms"]["p99"] == pytest.approx(float(np.percentile([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], 99)))
    assert r["deadline_misses"] == 1 and r["steps"] == 6 and r["rmse_position_m"] == pytest.approx(0.02)
    assert r["copies"] == 2 and not any(k.startswith("_") for k in r)


def test_an_unwritable_output_is_refused_before_any_flight(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as stop:
        bench.main(["--controllers", "sqp", "--cases", "hover", "--json", str(tmp_path / "file" / "out.json")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--json" in err and len(err.strip().splitlines()) == 1


def test_the_real_time_iterations_step_is_set_against_acados_as_a_ratio_of_its_medians(capsys):
    """Each oracle's RTI period on figure8-fast over acados' highest and lowest median (0.46 and 0.35 ms); the
    other rows and models are not compared; oracle_rk1, acados' own problem, first."""
    by = {("oracle", "figure8-fast", "rti"): {"solve_ms": {"median": 0.70}},
          ("oracle_rk1", "figure8-fast", "rti"): {"solve_ms": {"median": 0.46}},
          ("oracle", "figure8-fast", "dense"): {"solve_ms": {"median": 9.0}},
          ("baseline", "figure8-fast", "rti"): {"solve_ms": {"median": 9.0}},
          ("oracle", "hover", "rti"): {"solve_ms": {"median": 9.0}}}
    rows = bench._against_acados(by)
    assert [r["model"] for r in rows] == ["oracle_rk1", "oracle"]
    assert rows[0]["ratio"] == pytest.approx([1.0, 0.46 / 0.35])
    assert rows[1]["ratio"] == pytest.approx([0.7 / 0.46, 2.0])
    out = capsys.readouterr().out.split()
    assert out[out.index("oracle_rk1") + 1:out.index("oracle_rk1") + 6] == ["0.460", "ms", "=", "1.00-1.31", "x"]
    assert bench._against_acados({}) == []
