"""The digest of a results folder's answers (tests/answers.py): blind to timing and provenance, and to nothing else."""

import json
import shutil

import numpy as np
import pytest

from answers import compare, digests, main


def _folder(root, rmse=0.1, solve_ms=3.0, key="abc", x0=0.0, solve_s=0.002, realtime_x=0.0):
    root.mkdir(parents=True, exist_ok=True)
    (root / "runs").mkdir(exist_ok=True)
    (root / "traces").mkdir(exist_ok=True)
    runs = []
    for rid, timing, x in (("a", "ideal", x0), ("b__realtime", "realtime", realtime_x)):
        rec = {"run_id": rid, "timing": timing, "rmse_position_m": rmse, "cache_key": key,
               "inputs_sha256": {"model": "m1"}, "solve_ms": {"median": solve_ms}, "trace": f"traces/{rid}.npz",
               "wall_time_s": 10 * solve_ms, "estimator_ms": {"median": solve_ms}}
        (root / "runs" / f"{rid}.json").write_text(json.dumps(rec))
        np.savez(root / "traces" / f"{rid}.npz", x=np.full((3, 12), x), solve_s=np.full(3, solve_s),
                 estimator_s=np.full(3, 2 * solve_s))
        runs.append(rec)
    (root / "results.json").write_text(json.dumps({"plan": {"full": False}, "runs": runs}))
    (root / "fisher.json").write_text(json.dumps({"cases": [1.0], "inputs_sha256": key, "seconds": solve_ms}))
    return root


def test_timing_provenance_and_realtime_runs_leave_the_digests_equal(tmp_path):
    ref = digests(_folder(tmp_path / "ref"))
    assert sorted(ref) == ["fisher.json", "results.json", "runs/a.json", "traces/a.npz"]
    other = digests(_folder(tmp_path / "other", solve_ms=9.0, key="def", solve_s=0.2, realtime_x=5.0))
    assert compare(other, ref) == []


@pytest.mark.parametrize("change,files", [
    ({"rmse": 0.1 + 1e-16}, ["results.json", "runs/a.json"]),      # the last bit of an answer
    ({"x0": 1e-300}, ["traces/a.npz"]),
])
def test_a_changed_answer_changes_its_files_digest(tmp_path, change, files):
    ref = digests(_folder(tmp_path / "ref"))
    found = digests(_folder(tmp_path / "other", **change))
    assert compare(found, ref) == [f"differs: {f}" for f in files]


def test_the_command_says_which_files_differ_and_exits_1(tmp_path, capsys):
    stored = tmp_path / "stored.json"
    ref = _folder(tmp_path / "ref")
    assert main([str(ref), "--write", "--stored", str(stored)]) == 0
    assert main([str(ref), "--stored", str(stored)]) == 0
    assert "same answers: 4 files" in capsys.readouterr().out
    (ref / "runs" / "a.json").unlink()
    shutil.copy(ref / "traces" / "a.npz", ref / "traces" / "c.npz")
    assert main([str(ref), "--stored", str(stored)]) == 1
    assert capsys.readouterr().out.splitlines() == ["missing: runs/a.json", "missing: traces/a.npz"]
    assert main([str(tmp_path / "none")]) == 2
    assert main([str(ref), "--stored", str(tmp_path / "missing.json")]) == 2
    (tmp_path / "bad.json").write_text("{not json")
    assert main([str(ref), "--stored", str(tmp_path / "bad.json")]) == 2
    assert main([str(ref), "--write", "--stored", str(tmp_path / "no" / "such" / "dir" / "x.json")]) == 0
    assert main([str(ref), "--write", "--stored", "/proc/answers.json"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 4 and all(line.startswith("answers: ") for line in err.splitlines())   # with "none"
