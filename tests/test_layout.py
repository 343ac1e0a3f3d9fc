"""The code's layout: no import cycle of any length and no import from a lower layer into a higher one.

Imports are read from the code by ``ast``, at top level and inside functions, package faces (``__init__.py``)
included: a cycle that closes only when a function runs is still a cycle. The layers, lowest first, are
:data:`LAYERS`; a module may import its own layer and those below. Entry points (the command line and the
``bench`` modules) sit above every layer and may import any.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("sim", "mpc", "pinn", "scenarios", "reports")
ENTRY_POINTS = ("cli", "commands", "bench", "__main__")      # a module's last name


def module_name(path: Path, root: Path) -> str:
    """``pkg.sub.mod`` for ``root/pkg/sub/mod.py``, and ``pkg.sub`` for ``root/pkg/sub/__init__.py``."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path, packages=LAYERS) -> dict[str, dict[str, int]]:
    """Every module of ``packages`` under ``root`` -> {project module it imports: line of the first import}.

    ``from a.b import c`` counts ``a.b.c`` when that is a module, else ``a.b``; relative imports are resolved.
    """
    files = {module_name(f, root): f for p in packages for f in sorted((root / p).rglob("*.py"))}
    graph = {}
    for name, path in files.items():
        pkg = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = {}
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    found.setdefault(alias.name, node.lineno)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                for alias in node.names:
                    full = f"{base}.{alias.name}"
                    found.setdefault(full if full in files else base, node.lineno)
        graph[name] = {m: line for m, line in found.items() if m in files and m != name}
    return graph


def cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, without recursion)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(graph[start]))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, edges = work[-1]
            w = next(edges, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(graph[w])))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return sorted(found)


def upward(graph: dict[str, dict[str, int]], layers=LAYERS) -> list[str]:
    """``a -> b (line n)`` for every import of a higher layer's module ``b`` by ``a``, entry points aside."""
    def layer(m):
        return layers.index(m.split(".")[0])

    return [f"{a} -> {b} (line {line})" for a, deps in sorted(graph.items()) for b, line in sorted(deps.items())
            if layer(b) > layer(a) and a.rpartition(".")[2] not in ENTRY_POINTS]


def test_no_import_cycle_of_any_length():
    assert cycles(import_graph(ROOT)) == []


def test_no_module_imports_a_higher_layer():
    assert upward(import_graph(ROOT)) == []


def test_the_checks_see_a_planted_three_module_cycle_and_an_upward_import(tmp_path):
    """A cycle a -> b -> c -> a closed inside a function, through a package face, and an upward import: both
    checks must see them (a check for pairs alone would not see the cycle)."""
    for folder, text in {
        "low/__init__.py": "from .a import A\n",
        "low/a.py": "from low.b import B\nA = 1\n",
        "low/b.py": "import low.c\nB = 2\n",
        "low/c.py": "def f():\n    from low import A\n    return A\n",
        "low/cli.py": "import high.d\n",
        "low/ok.py": "import low.b\n",
        "high/__init__.py": "",
        "high/d.py": "from low.ok import *\n",
        "high/e.py": "from ..low import a\n",
    }.items():
        (tmp_path / folder).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / folder).write_text(text)
    (tmp_path / "low" / "up.py").write_text("def g():\n    from high import d\n")
    graph = import_graph(tmp_path, ("low", "high"))
    assert cycles(graph) == [["low", "low.a", "low.b", "low.c"]]
    assert upward(graph, ("low", "high")) == ["low.up -> high.d (line 2)"]     # low.cli is an entry point


def test_the_graph_sees_imports_inside_functions_and_package_faces():
    """The check reads function-level imports and the imports of ``__init__.py``: mpc.controllers.base imports
    mpc.controllers.lqr at
    top level, mpc.controllers.lqr imports mpc.controllers.controller, and the sim package's face imports
    sim.equations.simulator."""
    graph = import_graph(ROOT)
    assert "mpc.controllers.lqr" in graph["mpc.controllers.base"]
    assert "mpc.controllers.controller" in graph["mpc.controllers.lqr"]
    assert "sim.equations.simulator" in graph["sim"]
