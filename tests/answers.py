"""The answers of a main-job results folder, without its timing and provenance, as one digest per file.

Code that computes the same answers gives the same digests: a change that only moves code (a refactor) must leave
them equal to the last bit. Compare a folder written by ``pinnmpc run`` with the stored digests, or store them::

    python tests/answers.py results/main            # exit 0 when every file matches tests/answers.json
    python tests/answers.py results/main --write    # store this folder's digests as the reference

What is left out, because it is not an answer:

* the measured compute time of every run (:data:`TIMING_KEYS`, :data:`TIMING_ARRAYS`), and the whole of a run
  whose timing is ``realtime`` (its inputs apply after the measured compute time, so its path is timing too);
* provenance: the code's digest in a cache key (:data:`PROVENANCE_KEYS`), and ``provenance.json``;
* the copies of shipped studies and the report, which the job copies or draws from these.

The digests are those of one machine kind: another CPU may round the last bits differently (see ``sim``'s note on
the BLAS kernel).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from sim.files import write_text

STORED = Path(__file__).with_name("answers.json")
TIMING_KEYS = frozenset({"solve_ms", "latency_ms", "preflight_ms", "deadline_misses", "own_work_misses", "seconds",
                         "wall_time_s", "estimator_ms"})
TIMING_ARRAYS = frozenset({"solve_s", "latency_s", "load_s", "load_cpu_s", "estimator_s"})
PROVENANCE_KEYS = frozenset({"cache_key", "inputs_sha256"})
#: Tables the job computes (or reuses when their key matches); the runs are found under runs/ and traces/.
TABLES = ("results.json", "evaluation.json", "fisher.json")


def _strip(obj):
    """``obj`` without its timing and provenance keys, at any depth. A provenance key is dropped when it holds
    the code's digest (a string); a run's ``inputs_sha256`` that names its model files' bytes (a dict) stays."""
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items()
                if k not in TIMING_KEYS and not (k in PROVENANCE_KEYS and isinstance(v, str))}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _realtime(record: dict) -> bool:
    return record.get("timing") == "realtime"


def _json_digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, allow_nan=True).encode()).hexdigest()


def digests(folder) -> dict[str, str]:
    """``{relative path: sha256}`` of the answers in a results folder (see the module's note)."""
    folder = Path(folder)
    out = {}
    for name in TABLES:
        path = folder / name
        if not path.is_file():
            continue
        data = json.loads(path.read_text())
        if name == "results.json":
            data = {**data, "runs": [r for r in data["runs"] if not _realtime(r)]}
        out[name] = _json_digest(_strip(data))
    for path in sorted((folder / "runs").glob("*.json")):
        record = json.loads(path.read_text())
        if _realtime(record):
            continue
        out[f"runs/{path.name}"] = _json_digest(_strip(record))
        trace = folder / (record.get("trace") or "")
        if record.get("trace") and trace.is_file():
            h = hashlib.sha256()
            with np.load(trace) as npz:
                for key in sorted(set(npz.files) - TIMING_ARRAYS):
                    a = npz[key]
                    h.update(key.encode() + str(a.dtype).encode() + str(a.shape).encode())
                    h.update(np.ascontiguousarray(a).tobytes())
            out[record["trace"]] = h.hexdigest()
    return out


def compare(found: dict[str, str], stored: dict[str, str]) -> list[str]:
    """One line per file that differs, is missing or is new; empty when the answers are the same."""
    lines = [f"differs: {k}" for k in sorted(found.keys() & stored.keys()) if found[k] != stored[k]]
    lines += [f"missing: {k}" for k in sorted(stored.keys() - found.keys())]
    lines += [f"new:     {k}" for k in sorted(found.keys() - stored.keys())]
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path, help="a results folder written by pinnmpc run")
    ap.add_argument("--write", action="store_true", help=f"store its digests in {STORED.name}")
    ap.add_argument("--stored", type=Path, default=STORED, help="the stored digests (default: %(default)s)")
    args = ap.parse_args(argv)
    if not (args.folder / "results.json").is_file():
        print(f"answers: {args.folder} holds no results.json (run pinnmpc run first)", file=sys.stderr)
        return 2
    found = digests(args.folder)
    try:
        if args.write:
            write_text(args.stored, json.dumps(found, indent=1, sort_keys=True) + "\n")
            print(f"stored {len(found)} digests in {args.stored}")
            return 0
        stored = json.loads(args.stored.read_text())
    except (OSError, ValueError) as e:
        print(f"answers: {args.stored}: {e}", file=sys.stderr)
        return 2
    lines = compare(found, stored)
    print("\n".join(lines) if lines else f"same answers: {len(found)} files")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())
