"""Writing the JSON files of every command and benchmark in one way."""

from __future__ import annotations

import json
from pathlib import Path


def write_json(path, obj) -> Path:
    """Write ``obj`` to ``path`` as indented JSON with a final newline, creating the folder; the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2) + "\n")
    return path
