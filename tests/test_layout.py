"""The code's layout: no two modules of the project import each other (at top level or inside a function)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sim", "pinn", "mpc", "scenarios", "reports")


def _module(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Project modules ``path`` imports anywhere in its body (``from .x import y`` counts ``pkg.x``, or ``pkg.x.y``)."""
    pkg = _module(path).rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return {m for m in out if m in modules}


def test_no_two_modules_import_each_other():
    files = [f for p in PACKAGES for f in (ROOT / p).glob("*.py") if f.name != "__init__.py"]
    modules = {_module(f) for f in files}
    graph = {_module(f): _imports(f, modules) - {_module(f)} for f in files}
    pairs = sorted({tuple(sorted((a, b))) for a, deps in graph.items() for b in deps if a in graph.get(b, ())})
    assert pairs == []
    # The check sees function-level imports: mpc.base imports mpc.lqr at top level, and mpc.lqr imports
    # mpc.controller, which must not import either back.
    assert "mpc.lqr" in graph["mpc.base"] and "mpc.controller" in graph["mpc.lqr"]
