"""The record of one closed-loop run: what was flown, how it went, where its trace is; written and read here.

A :class:`RunRecord` is made in two places only, both in this package: :func:`scenarios.closed_loop.runner.fly`
for a run that flew (or could not start) and :func:`not_flown` for a run that never reached the loop. The sweep
stamps it with its :func:`cache_key` and :func:`save_run` writes it as ``runs/<id>.json`` beside its trace
``traces/<id>.npz``; :func:`cached_result`, the reports and ``pinnmpc bounds`` read it back with
:meth:`RunRecord.from_dict`. Its JSON keys are its field names: a field a run does not have (the estimator's
figures of a run without one, everything but the identity of a run that never flew) is :data:`ABSENT` and
written as no key at all, so records read from older results folders keep the keys they had, and a key this
version does not know is kept in :attr:`RunRecord.extra` and written back.

A record is read-only and reads like the JSON object it is written as (``record["rmse_position_m"]``,
``record.get("error")``, ``{**record}``), so code written for the JSON reads a record unchanged.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mpc.prediction.models import is_equation_model

from ..errors import ScenarioError


class _Absent:
    """The value of a field a run does not have (no JSON key); one object, kept one by pickling by name."""

    def __repr__(self) -> str:
        return "ABSENT"

    def __reduce__(self):
        return "ABSENT"


#: A field the run has no value for: not written, not a key of the record.
ABSENT: Any = _Absent()


def _absent():
    return field(default=ABSENT)


@dataclass(frozen=True, eq=False)
class RunRecord(Mapping):
    """One run's result, in the order its JSON object lists it.

    Identity (what was flown): ``run_id``, ``scenario``, ``controller``, ``model`` (its name), ``model_file`` and
    ``model_sha256`` (an ONNX model's path and SHA-256; None for an equation model), ``seed``, ``member``,
    ``horizon`` (steps of 10 ms), ``timing``, ``plant``, ``vehicle``, ``estimator``, ``qp`` (the QP solver flown;
    None for a controller without one), ``scheme`` (``"rti"`` for the SQP's real-time iteration; absent for the
    iterating SQP and the other controllers) and ``inputs_sha256`` (SHA-256 of each file read, by role).

    Metrics (:func:`scenarios.closed_loop.metrics.closed_loop_metrics`): ``gust_peak_error_m`` and
    ``recovery_time_s`` (a gust impulse's scenario only), ``skipped_periods`` (real-time timing only),
    ``settled_error_m``, ``rmse_yaw_rad``, ``rmse_position_m``, ``max_position_error_m`` (m, rad), ``crashed``,
    ``crash_time_s``, ``crash_reason``, ``solve_ms`` (median, p95, max: each period's load, the controller's
    preparation of the next period included), ``deadline_misses``, ``own_work_misses`` (periods whose controller
    thread's CPU time alone passed the period: the misses it caused itself), ``solver_failures``, ``fallbacks``
    (LQR fallbacks flown) and ``steps`` (control periods flown); ``latency_ms`` (median, p95, p99, max: from the
    measurement to the input out, a state estimator's time included).

    The flight: ``shifted_plan`` (failed solves that flew the shifted plan), ``deadline_fallbacks`` (real time:
    periods whose plan missed its deadline), ``failure_causes`` (solver status: count), ``preflight`` and
    ``preflight_ms`` (the SQP's plan before take-off), ``error`` (why a run could not start or fly; None when it
    flew), ``wall_time_s``, ``scenario_spec``, ``plant_spec`` and ``vehicle_spec`` (what was flown, in full),
    and with the state estimator ``estimator_ms`` (median, max) and ``nees_mean``.

    Saved: ``cache_key`` (:func:`cache_key`, stamped by the sweep) and ``trace`` (the trace file relative to the
    results folder, None without one). ``extra``: keys of a record read from a file that this version does not
    know, kept as they were.
    """

    run_id: Any = _absent()
    scenario: Any = _absent()
    controller: Any = _absent()
    model: Any = _absent()
    model_file: Any = _absent()
    model_sha256: Any = _absent()
    seed: Any = _absent()
    member: Any = _absent()
    horizon: Any = _absent()
    timing: Any = _absent()
    plant: Any = _absent()
    vehicle: Any = _absent()
    estimator: Any = _absent()
    qp: Any = _absent()
    scheme: Any = _absent()
    level: Any = _absent()
    inputs_sha256: Any = _absent()
    gust_peak_error_m: Any = _absent()
    recovery_time_s: Any = _absent()
    skipped_periods: Any = _absent()
    settled_error_m: Any = _absent()
    rmse_yaw_rad: Any = _absent()
    rmse_position_m: Any = _absent()
    max_position_error_m: Any = _absent()
    crashed: Any = _absent()
    crash_time_s: Any = _absent()
    crash_reason: Any = _absent()
    solve_ms: Any = _absent()
    latency_ms: Any = _absent()
    deadline_misses: Any = _absent()
    own_work_misses: Any = _absent()
    solver_failures: Any = _absent()
    fallbacks: Any = _absent()
    steps: Any = _absent()
    shifted_plan: Any = _absent()
    deadline_fallbacks: Any = _absent()
    failure_causes: Any = _absent()
    preflight: Any = _absent()
    preflight_ms: Any = _absent()
    error: Any = _absent()
    wall_time_s: Any = _absent()
    scenario_spec: Any = _absent()
    plant_spec: Any = _absent()
    vehicle_spec: Any = _absent()
    estimator_ms: Any = _absent()
    nees_mean: Any = _absent()
    cache_key: Any = _absent()
    trace: Any = _absent()
    extra: dict = field(default_factory=dict)

    # -- the JSON object it is written as

    def _items(self) -> Iterator[tuple[str, Any]]:
        for name in KEYS:
            value = getattr(self, name)
            if value is not ABSENT:
                yield name, value
        yield from self.extra.items()

    def __getitem__(self, key: str):
        if key in _KEY_SET:
            value = getattr(self, key)
            if value is ABSENT:
                raise KeyError(key)
            return value
        return self.extra[key]

    def __iter__(self) -> Iterator[str]:
        return (k for k, _ in self._items())

    def __len__(self) -> int:
        return sum(1 for _ in self._items())

    def __repr__(self) -> str:
        return f"RunRecord({dict(self._items())!r})"

    def to_dict(self) -> dict:
        """The JSON object of the record: its keys in field order, then :attr:`extra`'s."""
        return dict(self._items())

    @classmethod
    def from_dict(cls, data, source: str = "run record") -> "RunRecord":
        """The record written as the JSON object ``data`` (its keys as they are: a reader checks the ones it needs);
        a :class:`ScenarioError` naming ``source`` when it is not an object."""
        if not isinstance(data, Mapping):
            raise ScenarioError(f"{source}: expected a JSON object; found {type(data).__name__}")
        if isinstance(data, RunRecord):
            return data
        known = {k: v for k, v in data.items() if k in _KEY_SET}
        return cls(**known, extra={k: v for k, v in data.items() if k not in _KEY_SET})

    def replace(self, **changes) -> "RunRecord":
        """A copy with the fields ``changes`` set (records are read-only)."""
        return dataclasses.replace(self, **changes)


#: The JSON keys of a record, in the order it writes them.
KEYS = tuple(f.name for f in dataclasses.fields(RunRecord) if f.name != "extra")
_KEY_SET = frozenset(KEYS)

#: Metrics of a run that never flew (its controller could not be built, or the run raised).
NOT_FLOWN = {"rmse_position_m": None, "max_position_error_m": None, "settled_error_m": None, "rmse_yaw_rad": None,
             "crashed": False, "crash_time_s": None,
             "crash_reason": None, "solve_ms": None, "deadline_misses": 0, "solver_failures": 0, "fallbacks": 0,
             "steps": 0}


def not_flown(spec, error: str) -> RunRecord:
    """The record of a run of ``spec`` (:class:`scenarios.closed_loop.runner.RunSpec`) that did not fly: its
    metrics null, ``error`` the reason (one line)."""
    return RunRecord(run_id=spec.run_id, scenario=spec.scenario_name, controller=spec.controller,
                     model=spec.model_name, plant=spec.plant, vehicle=spec.vehicle_data.name, qp=spec.qp_solver,
                     level=spec.level,
                     **NOT_FLOWN, error=error, inputs_sha256=input_hashes(spec))


# -- what a run reads, and the identity of its result

def input_files(spec) -> dict[str, Path]:
    """The files a run reads, by role: ``model`` (an ONNX file) and ``jacobian`` (its derivative graph, read when it
    exists: without it the controllers take central differences), ``vehicle`` and ``scenario`` (when given as
    files). Equation models and shipped names read no file of their own."""
    from mpc.prediction.contract import jacobian_path

    files = {}
    if not is_equation_model(spec.model):
        files["model"] = Path(spec.model)
        files["jacobian"] = jacobian_path(spec.model)
    for role, name in (("vehicle", spec.vehicle), ("scenario", spec.scenario)):
        if isinstance(name, str) and name.endswith(".toml"):
            files[role] = Path(name)
    return files


def input_hashes(spec) -> dict[str, str | None]:
    """SHA-256 of each of :func:`input_files` now, by role (None: the file is absent, as a model without a
    derivative graph is)."""
    out = {}
    for role, path in input_files(spec).items():
        try:
            out[role] = _digest(path)
        except FileNotFoundError:
            out[role] = None
    return out


def _digest(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def file_sha256(path: str) -> str | None:
    """SHA-256 of the model file ``path``; None for an equation model (no file)."""
    return None if is_equation_model(path) else _digest(path)


_CODE_VERSION: str | None = None


def code_version() -> str:
    """SHA-256 (first 16 hex digits) of the package version and the source of the packages that fly a run.

    Any change to the Python source of ``sim``, ``mpc`` or ``scenarios`` (or
    the version) makes a new code version, and so invalidates every cached
    run. Data files are not code: the CI bounds (``scenarios/studies/bounds.toml``)
    do not change a flight, and a run's vehicle and scenario enter its
    :func:`cache_key` by their content.
    """
    global _CODE_VERSION
    if _CODE_VERSION is None:
        from sim.files import source_digest

        root = Path(__file__).resolve().parents[2]
        _CODE_VERSION = source_digest(("sim", "mpc", "scenarios"), root).hexdigest()[:16]
    return _CODE_VERSION


def cache_key(spec, inputs: dict | None = None) -> str:
    """Identity of a run's result: its spec, its seed, the SHA-256 of every file it reads and the code version.

    The QP solver (``spec.qp_solver``) is part of it: a run flown with one solver is never reused for
    the other. It enters only where it is not OSQP, so an OSQP run's key is made as before the choice existed.

    ``inputs``: those hashes (:func:`input_hashes`) as a run recorded them when it started flying; None: the
    files as they are now. A saved result is reused only when the two agree, so a run flown with a file that was
    replaced since (or replaced during the sweep) is flown again.
    """
    from mpc.controllers.factory import DEFAULT_QP

    from .library import get_scenario

    sc = get_scenario(spec.scenario)
    seed = sc.seed if spec.seed is None else spec.seed
    inputs = input_hashes(spec) if inputs is None else inputs
    # The model by name and content, not by path: a results folder stays valid when the models move. The vehicle
    # and a scenario file by content too.
    ident = {"scenario": sc.to_dict(), "controller": spec.controller, "model": spec.model_name,
             "model_sha256": inputs.get("model"), "inputs": inputs, "seed": seed, "member": spec.member,
             "horizon": spec.horizon,
             "timing": spec.timing, "plant": spec.plant, "vehicle": spec.vehicle_data.to_dict(),
             "estimator": spec.estimator, "code": code_version()}
    if spec.qp_solver not in (None, DEFAULT_QP):
        # Only where it is not OSQP, the solver of every run before the choice: an OSQP run keeps its identity.
        ident["qp"] = spec.qp_solver
    if spec.level != "wrench":
        ident["level"] = spec.level       # likewise: a wrench run keeps its identity
    if spec.own_scheme is not None:
        ident["scheme"] = spec.own_scheme   # likewise: a run in its timing's own scheme keeps its identity
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


# -- the results folder

def save_run(record: RunRecord, trace: dict, out_dir: Path) -> RunRecord:
    """Write ``runs/<id>.json`` and ``traces/<id>.npz`` under ``out_dir``; the record with its trace path."""
    from sim.files import write_npz, write_text

    out_dir = Path(out_dir)
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    (out_dir / "traces").mkdir(parents=True, exist_ok=True)
    rel = None
    if trace:
        rel = f"traces/{record.run_id}.npz"
        write_npz(out_dir / rel, trace)
    record = RunRecord.from_dict(record).replace(trace=rel)
    # Both files are written whole (a temporary file renamed), the JSON last: a run interrupted while saving leaves
    # no result, and is flown again.
    write_text(out_dir / "runs" / f"{record.run_id}.json",
               json.dumps(record.to_dict(), indent=2, sort_keys=True) + "\n")
    return record


def cached_result(spec, out_dir, key: str | None = None) -> RunRecord | None:
    """The saved record of ``spec`` under ``out_dir`` if it was flown with the same cache key, else None.

    ``key``: the spec's :func:`cache_key`, if already computed. A saved run
    that could not start (its ``error`` is set, for example a model file that
    failed the contract) is not reused.
    """
    path = Path(out_dir) / "runs" / f"{spec.run_id}.json"
    if not path.is_file():
        return None
    try:
        record = RunRecord.from_dict(json.loads(path.read_text()), str(path))
    except (OSError, ValueError) as e:
        _say(f"{path}: damaged ({e}); flying {spec.run_id} again")
        return None
    if record.get("cache_key") != (cache_key(spec) if key is None else key) or record.get("error"):
        return None     # another spec, file or code; or a run that could not start (tried again)
    if record.get("trace"):
        why = trace_damage(Path(out_dir) / record.trace)
        if why is not None:
            _say(f"{Path(out_dir) / record.trace}: {why}; flying {spec.run_id} again")
            return None
    return record


def _say(line: str) -> None:
    import sys

    print(line, file=sys.stderr, flush=True)


def trace_damage(path: Path) -> str | None:
    """Why the trace file ``path`` cannot be trusted (missing, not a readable ``.npz``, an array that fails its
    checksum, no ``t`` and ``x``), or None when it reads back whole."""
    import zipfile

    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}     # reading every array checks its CRC
    except FileNotFoundError:
        return "missing"
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        return f"damaged ({type(e).__name__}: {e})"
    if "t" not in arrays or "x" not in arrays or len(arrays["t"]) != len(arrays["x"]):
        return "damaged (no time and state arrays of one length)"
    return None
