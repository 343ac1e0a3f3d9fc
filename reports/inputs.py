"""Reading a saved results folder: the JSON files and the run traces.

Required: ``results.json``, ``evaluation.json``, ``fisher.json`` (a missing or
malformed one raises :class:`~reports.errors.ReportError` naming the file).
Optional: ``ablation.json``, ``provenance.json``, ``study.json`` (the zoo
study, copied by ``pinnmpc run``), ``versus.json`` (learned against nominal,
copied likewise), ``levels.json`` (the three command levels, copied likewise), ``learn_<plant>.json``
(learning from flown flights, copied likewise), ``realdata.json`` (``pinnmpc realdata --out`` this folder) and
``traces/<run_id>.npz`` (missing ones are reported in the text instead; a malformed ``study.json``,
``versus.json`` or ``levels.json`` raises).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenarios.closed_loop.record import RunRecord
from scenarios.studies.learn import study_tag

from .errors import ReportError
from .labels import run_key

#: Keys every closed-loop result must have.
RUN_KEYS = ("scenario", "controller", "model")
#: Keys a study.json must have.
STUDY_KEYS = ("scenario", "members", "controllers", "ladder", "models", "scores", "oracle_rmse_m")
#: Keys a versus.json must have.
VERSUS_KEYS = ("scenario", "controller", "members", "ladder_members", "ladder", "goal", "plants")
#: Keys a levels.json must have.
LEVELS_KEYS = ("scenario", "controller", "members", "levels", "plants")
#: Keys a realdata.json must have.
REALDATA_KEYS = ("source", "horizons", "splits", "models", "published_h50", "goal_h50", "identification")
#: Keys a learn_<plant>.json must have.
LEARN_KEYS = ("plant", "settings", "curve", "evaluation", "wall_time_s")
#: Trace arrays the figures use: t (K+1,) s, x and x_ref (K+1, 12), solve_s (K,) s.
TRACE_KEYS = ("t", "x", "x_ref")


def _read_json(path: Path, required: bool):
    """The parsed JSON at ``path``; None when absent and not ``required``."""
    if not path.is_file():
        if required:
            raise ReportError(f"required file {path.name!r} not found in {str(path.parent)!r}")
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ReportError(f"cannot read {path.name!r} in {str(path.parent)!r}: {e}") from e


def _runs(results, path: Path) -> list[RunRecord]:
    """The run records of ``results`` (the object of ``results.json``), sorted by :func:`run_key`."""
    runs = results.get("runs") if isinstance(results, dict) else None
    if not isinstance(runs, list):
        raise ReportError(f"{path.name!r}: expected an object with a list 'runs'")
    for i, r in enumerate(runs):
        if not isinstance(r, dict) or any(k not in r for k in RUN_KEYS):
            raise ReportError(f"{path.name!r}: run {i} lacks one of the keys {', '.join(RUN_KEYS)}")
    return sorted((RunRecord.from_dict(r) for r in runs), key=run_key)


def _read_trace(path: Path, rel: str) -> tuple[dict | None, str | None]:
    """The arrays of the trace file ``path`` and None, or None and why it is unusable."""
    if not path.is_file():
        return None, f"trace file {rel!r} not found"
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        return None, f"trace file {rel!r} unreadable: {e}"
    bad = [k for k in TRACE_KEYS if k not in arrays]
    if bad:
        return None, f"trace file {rel!r} lacks {', '.join(bad)}"
    t, x, x_ref = arrays["t"], arrays["x"], arrays["x_ref"]
    if x.ndim != 2 or x_ref.ndim != 2 or x.shape[1] < 3 or x_ref.shape[1] < 3:
        return None, f"trace file {rel!r}: x and x_ref are not (K+1, 12) arrays"
    if not (t.ndim == 1 and len(t) == len(x) == len(x_ref)):
        return None, f"trace file {rel!r}: t, x and x_ref differ in length"
    if len(t) < 2:
        return None, f"trace file {rel!r} holds no flight"
    return arrays, None


@dataclass
class Inputs:
    """Everything the report shows, as read from ``run_dir``.

    Attributes
    ----------
    run_dir : Path
        The results folder.
    runs : list of dict
        Closed-loop results (``results.json`` ``runs``), sorted by scenario,
        controller, model (:func:`reports.labels.run_key`).
    plan : dict
        ``results.json`` ``plan`` (empty when absent).
    evaluation : dict
        ``evaluation.json``: ``models`` (open-loop accuracy, identified
        parameters) and ``paper`` (the paper's claims).
    fisher : dict
        ``fisher.json``: ``cases`` and ``settings``.
    ablation : dict or None
        ``ablation.json`` (Table III), None when absent.
    provenance : dict or None
        ``provenance.json``, None when absent.
    study : dict or None
        ``study.json`` (the zoo's dose-response study), None when absent.
    versus : dict or None
        ``versus.json`` (learned models against the nominal equations), None when absent.
    study_ekf : dict or None
        ``study_ekf.json`` (the study's ensembles flown with the state estimator), None when absent.
    realdata : dict or None
        ``realdata.json`` (``pinnmpc realdata``: real flight logs under the benchmark's protocol), None when absent.
    learn : dict or None
        ``learn_<plant>.json`` by plant (``pinnmpc learn``: learning from flown flights), None when there is none.
    levels : dict or None
        ``levels.json`` (``pinnmpc levels``: the three command levels side by side), None when absent.
    versus_levels : dict
        ``versus_<level>.json`` by level (``pinnmpc versus --level``), empty when there is none.
    """

    run_dir: Path
    runs: list
    plan: dict
    evaluation: dict
    fisher: dict
    ablation: dict | None
    provenance: dict | None
    study: dict | None = None
    versus: dict | None = None
    study_ekf: dict | None = None
    realdata: dict | None = None
    learn: dict | None = None
    levels: dict | None = None
    versus_levels: dict = field(default_factory=dict)
    _traces: dict = field(default_factory=dict, repr=False)

    def models_by_name(self) -> dict:
        """Open-loop evaluation entries of ``evaluation.json`` by model name."""
        return {str(m.get("name")): m for m in self.evaluation.get("models", []) if isinstance(m, dict)}

    def trace(self, run: dict) -> tuple[dict | None, str | None]:
        """The trace arrays of ``run`` and None, or None and why there is none.

        Returns
        -------
        trace : dict of ndarray or None
            ``t`` (K+1,) s, ``x`` and ``x_ref`` (K+1, 12) (NED, m, rad, m/s),
            and whatever else the file holds (``solve_s`` (K,) s, ...).
        reason : str or None
            Why the trace is unusable (no file, unreadable, empty), else None.
        """
        rel = run.get("trace")
        if not rel:
            return None, "no trace recorded"
        if rel in self._traces:
            return self._traces[rel]
        out = _read_trace(self.run_dir / rel, rel)
        self._traces[rel] = out
        return out


def load_inputs(run_dir) -> Inputs:
    """Read the results folder ``run_dir`` (see the module docstring).

    Raises
    ------
    ReportError
        ``run_dir`` is not a folder, or a required file is missing or malformed
        (the message names the file).
    """
    d = Path(run_dir)
    if not d.is_dir():
        raise ReportError(f"results folder {str(d)!r} does not exist")
    results = _read_json(d / "results.json", True)
    runs = _runs(results, d / "results.json")
    evaluation = _read_json(d / "evaluation.json", True)
    if not isinstance(evaluation, dict) or not isinstance(evaluation.get("models"), list):
        raise ReportError("'evaluation.json': expected an object with a list 'models'")
    fisher = _read_json(d / "fisher.json", True)
    if not isinstance(fisher, dict) or not isinstance(fisher.get("cases"), list):
        raise ReportError("'fisher.json': expected an object with a list 'cases'")
    ablation = _read_json(d / "ablation.json", False)
    if ablation is not None and not isinstance(ablation, dict):
        ablation = None
    provenance = _read_json(d / "provenance.json", False)
    if provenance is not None and not isinstance(provenance, dict):
        provenance = None
    study, study_ekf = (_read_study(d, name) for name in ("study.json", "study_ekf.json"))
    versus, versus_levels = None, {}
    for name in ("versus.json", "versus_ctbr.json", "versus_ctatt.json"):
        v = _read_json(d / name, False)
        if v is None:
            continue
        missing = [k for k in VERSUS_KEYS if not isinstance(v, dict) or k not in v]
        if missing:
            raise ReportError(f"{name!r}: not the output of pinnmpc versus (lacks {', '.join(missing)})")
        if name == "versus.json":
            versus = v
        else:
            versus_levels[name[len("versus_"):-len(".json")]] = v
    levels = _read_json(d / "levels.json", False)
    if levels is not None:
        missing = [k for k in LEVELS_KEYS if not isinstance(levels, dict) or k not in levels]
        if missing:
            raise ReportError(f"'levels.json': not the output of pinnmpc levels (lacks {', '.join(missing)})")
    realdata = _read_json(d / "realdata.json", False)
    if realdata is not None:
        missing = [k for k in REALDATA_KEYS if not isinstance(realdata, dict) or k not in realdata]
        if missing:
            raise ReportError(f"'realdata.json': not the output of pinnmpc realdata (lacks {', '.join(missing)})")
    learn = {}
    for path in sorted(d.glob("learn_*.json")):
        st = _read_json(path, False)
        missing = [k for k in LEARN_KEYS if not isinstance(st, dict) or k not in st]
        if missing:
            raise ReportError(f"{path.name!r}: not the output of pinnmpc learn (lacks {', '.join(missing)})")
        learn[study_tag(st)] = st  # the plant, with _<level> beside the wrench level
    plan = results.get("plan") if isinstance(results.get("plan"), dict) else {}
    return Inputs(d, runs, plan, evaluation, fisher, ablation, provenance, study, versus, study_ekf, realdata,
                  learn or None, levels, versus_levels)


def _read_study(d: Path, name: str) -> dict | None:
    study = _read_json(d / name, False)
    if study is not None:
        missing = [k for k in STUDY_KEYS if not isinstance(study, dict) or k not in study]
        if missing:
            raise ReportError(f"'{name}': not the output of pinnmpc study (lacks {', '.join(missing)})")
    return study
