"""The benchmark's command line refuses what it cannot fly, by name (no timing is asserted anywhere)."""

import pytest

from mpc import bench


@pytest.mark.parametrize("compare", ["full", "full,full", "full,bad", "full,partial,dense", ""])
def test_a_bad_pair_of_paths_is_refused_by_name(compare, capsys):
    with pytest.raises(SystemExit, match="--compare: two different paths of full, partial, dense expected"):
        bench.main(["--answers", "--compare", compare])


def test_the_speed_benchmark_flies_the_dense_path_only_with_daqp(monkeypatch):
    import importlib.util

    have = importlib.util.find_spec("daqp") is not None
    assert ("dense" in bench.speed_paths()) == have
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "daqp" else real(name, *a))
    assert list(bench.speed_paths()) == ["full", "partial"]
    with pytest.raises(SystemExit, match="the dense path needs DAQP"):
        bench.main(["--answers", "--compare", "full,dense"])
