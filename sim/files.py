"""Writing the files of every command and benchmark in one way: checked before the work, written whole or not at all."""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

from .errors import SimInputError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _replace_from_temp(path: Path, write) -> Path:
    """Call ``write(file object)`` on a temporary file beside ``path``, then rename it to ``path`` (atomic: a reader
    sees the old file or the whole new one, never a torn one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.chmod(tmp, 0o666 & ~_umask())      # as an ordinary new file (mkstemp makes it private)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_named_toml(spec, folder, kind: str, unknown: str, error=SimInputError) -> tuple[dict, Path]:
    """The table of a TOML file and its path: a shipped one by name (``folder/NAME.toml``) or a ``.toml`` path.

    ``kind`` starts the messages (``"vehicle"``: "vehicle file ... does not exist"), ``unknown`` names what a name
    that is not shipped is (``"unknown vehicle ..."``); every failure raises ``error`` naming the file or the name.
    """
    import tomllib

    folder = Path(folder)
    names = sorted(p.stem for p in folder.glob("*.toml"))
    if not isinstance(spec, (str, Path)) or not str(spec):
        raise error(f"{kind} must be a name ({', '.join(names)}) or a .toml file; found {spec!r}")
    path = Path(spec)
    if path.suffix != ".toml":
        if str(spec) not in names:
            raise error(f"unknown {unknown} {str(spec)!r}; choose from {', '.join(names)}, or give a .toml file")
        path = folder / f"{spec}.toml"
    elif not path.is_file():
        raise error(f"{kind} file {str(path)!r} does not exist")
    try:
        return tomllib.loads(path.read_text()), path
    except (OSError, UnicodeDecodeError) as e:
        raise error(f"{kind} file {str(path)!r} could not be read: {e}") from None
    except tomllib.TOMLDecodeError as e:
        raise error(f"{kind} file {str(path)!r} is not valid TOML: {e}") from None


def json_ready(obj):
    """``obj`` with every float that is not finite (NaN, infinity) replaced by None, in nested dicts, lists and
    tuples: strict JSON, which has no NaN, holds ``null`` for a value that does not exist."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):                # a dict, or a read-only record that reads like one
        return {k: json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    return obj


def write_json(path, obj) -> Path:
    """Write ``obj`` to ``path`` as indented, strict JSON (a value that is not a finite number is ``null``) with a
    final newline, creating the folder; the path."""
    path = Path(path)
    text = (json.dumps(json_ready(obj), indent=2, allow_nan=False) + "\n").encode()
    return _replace_from_temp(path, lambda f: f.write(text))


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` whole or not at all, creating the folder; the path."""
    data = text.encode()
    return _replace_from_temp(Path(path), lambda f: f.write(data))


def write_npz(path, arrays: dict) -> Path:
    """Write ``arrays`` to exactly ``path`` as a compressed ``.npz`` (numpy would add ``.npz`` to a name without
    it), creating the folder; the path."""
    import numpy as np

    return _replace_from_temp(Path(path), lambda f: np.savez_compressed(f, **arrays))


def source_digest(entries, root=None, exclude=()):
    """A ``hashlib.sha256`` over the project's version and the Python source of ``entries`` (folders, searched
    recursively, or single files, under ``root``: the project's root by default), each file's path and bytes in
    sorted order: the identity of code, for a cache key. ``exclude``: folders under ``root`` left out (code the
    keyed computation never imports)."""
    import hashlib

    from ._version import __version__

    root = Path(__file__).resolve().parents[1] if root is None else Path(root)
    skipped = [root / e for e in exclude]
    h = hashlib.sha256(__version__.encode())
    for entry in entries:
        p = root / entry
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            if any(f.is_relative_to(d) for d in skipped):
                continue
            h.update(str(f.relative_to(root)).encode())
            h.update(f.read_bytes())
    return h


def check_writable(path, option: str, folder: bool = False) -> Path:
    """Before any work: that ``path`` (a file, or with ``folder`` a folder) can be written, or a
    :class:`sim.errors.SimInputError` naming ``option`` and why.

    Nothing is created: a probe file is written and removed in the nearest folder that exists (where the
    missing ones would be made).
    """
    path = Path(path)
    if not folder and path.is_dir():
        raise SimInputError(f"{option} {str(path)!r} is a folder; give a file name")
    if folder and path.exists() and not path.is_dir():
        raise SimInputError(f"{option} {str(path)!r} is a file; give a folder")
    where = (path if folder else path.parent).absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        if not where.is_dir():
            raise NotADirectoryError(20, f"{str(where)!r} is a file, so no folder can be made under it")
        fd, probe = tempfile.mkstemp(dir=where, prefix=".write-probe.")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise SimInputError(f"{option} {str(path)!r} cannot be written: {e.strerror or e}") from e
    return path
