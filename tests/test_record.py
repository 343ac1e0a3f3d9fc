"""The run record: one type written in one place, the JSON keys results folders have always had, read back whole."""

import json
import pickle

import pytest

from scenarios.closed_loop.record import ABSENT, KEYS, RunRecord, not_flown, save_run
from scenarios.closed_loop.runner import RunSpec, fly
from scenarios.errors import ScenarioError

#: The keys of a saved run as the runner wrote them before the record type existed (hover with the LQR, the
#: ideal timing, no estimator), in the order it wrote them, with the command level after the QP solver and the
#: input latency after the solve time; and of a run that never flew.
FLOWN_KEYS = ("run_id", "scenario", "controller", "model", "model_file", "model_sha256", "seed", "member",
              "horizon", "timing", "plant", "vehicle", "estimator", "qp", "level", "inputs_sha256",
              "gust_peak_error_m", "recovery_time_s",
              "settled_error_m", "rmse_yaw_rad", "rmse_position_m", "max_position_error_m", "crashed",
              "crash_time_s", "crash_reason", "solve_ms", "latency_ms", "deadline_misses", "own_work_misses",
              "solver_failures",
              "fallbacks", "steps", "shifted_plan", "deadline_fallbacks", "failure_causes", "preflight", "preflight_ms",
              "error", "wall_time_s", "scenario_spec", "plant_spec", "vehicle_spec")
NOT_FLOWN_KEYS = ("run_id", "scenario", "controller", "model", "plant", "vehicle", "qp", "level", "rmse_position_m",
                  "max_position_error_m", "settled_error_m", "rmse_yaw_rad", "crashed", "crash_time_s",
                  "crash_reason", "solve_ms", "deadline_misses", "solver_failures", "fallbacks", "steps", "error",
                  "inputs_sha256")

@pytest.fixture(scope="module")
def hover():
    return fly(RunSpec("hover", "lqr", "oracle"))


def test_a_flown_run_has_the_keys_results_folders_have(hover):
    record, _ = hover
    assert isinstance(record, RunRecord)
    assert list(record) == list(FLOWN_KEYS)           # the hover scenario's gust impulse adds its two metrics
    assert list(record.to_dict()) == list(FLOWN_KEYS)
    assert record.estimator_ms is ABSENT and "estimator_ms" not in record and "nees_mean" not in record
    with pytest.raises(KeyError):
        record["nees_mean"]


def test_a_run_that_never_flew_has_its_old_keys():
    r = not_flown(RunSpec("hover", "lqr", "oracle"), "not flown: worker died")
    assert set(r) == set(NOT_FLOWN_KEYS) and len(r) == len(NOT_FLOWN_KEYS)
    assert r["error"] == "not flown: worker died" and r["rmse_position_m"] is None and r["steps"] == 0


def test_a_saved_record_reads_back_equal_and_writes_back_the_same_text(hover, tmp_path):
    record, trace = hover
    saved = save_run(record.replace(cache_key="k" * 64), trace, tmp_path)
    text = (tmp_path / "runs" / f"{record.run_id}.json").read_text()
    back = RunRecord.from_dict(json.loads(text))
    assert back == saved and back.trace == f"traces/{record.run_id}.npz" and back.cache_key == "k" * 64
    assert json.dumps(back.to_dict(), indent=2, sort_keys=True) + "\n" == text
    assert back.rmse_position_m == record.rmse_position_m      # the float itself, not a rounded copy


def test_keys_this_version_does_not_know_are_kept_and_missing_ones_stay_missing():
    old = {"run_id": "a", "scenario": "hover", "controller": "lqr", "model": "oracle", "crashed": False,
           "a_key_from_elsewhere": [1, 2]}
    r = RunRecord.from_dict(old)
    assert r.to_dict() == old and list(r) == list(old)
    assert r.extra == {"a_key_from_elsewhere": [1, 2]} and r.horizon is ABSENT and r.get("horizon", 30) == 30


def test_a_record_is_read_only_and_survives_pickling(hover):
    record, _ = hover
    with pytest.raises(AttributeError):
        record.error = "changed"                              # frozen
    with pytest.raises(TypeError):
        record["error"] = "changed"                           # no item assignment
    back = pickle.loads(pickle.dumps(record))                 # the worker's result crosses a process boundary
    assert back == record and back.estimator_ms is ABSENT and list(back) == list(record)


def test_only_json_objects_are_records():
    with pytest.raises(ScenarioError, match="run 3: expected a JSON object; found list"):
        RunRecord.from_dict([1, 2], "run 3")
    with pytest.raises(TypeError):
        RunRecord(rmse_m=1.0)                                 # a key the record does not have is refused
    assert KEYS[0] == "run_id" and "extra" not in KEYS
