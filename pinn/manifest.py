"""The manifest of a models folder: one JSON entry per trained file (command, seed, data, metrics)."""

from __future__ import annotations

import json
from pathlib import Path


def update_manifest(folder: Path, name: str, entry: dict, file: str = "manifest.json") -> Path:
    """Set ``entry`` under ``name`` in ``folder/file`` (locked: trainings may run in parallel)."""
    import fcntl

    path = folder / file
    with open(folder / ".manifest.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        data = json.loads(path.read_text()) if path.exists() else {}
        data[name] = entry
        path.write_text(json.dumps(dict(sorted(data.items())), indent=2) + "\n")
    return path
