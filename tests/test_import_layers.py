"""The product's import graph, read from the source with ``ast`` (every import, module-level or
inside a function): no module outside the command line (``evaluation/cli/``) imports it or
argparse, a lower layer never imports a higher one (factors <- estimation <- ekf_baseline <-
evaluation <- evaluation.cli), and no import cycle."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("factors", "estimation", "ekf_baseline", "evaluation")
CLI = "ddfuse.evaluation.cli"



def product_modules(root: Path = ROOT) -> dict[str, Path]:
    """Module name -> file of every product module (a package by its ``__init__.py``)."""
    mods = {}
    for folder in LAYERS:
        for path in sorted((root / folder).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(["ddfuse", *parts])] = path
    return mods


def imported(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The product modules ``name`` (at ``path``) imports at run time: ``from a.b import c`` is
    the module ``a.b.c`` when there is one, else ``a.b``; relative imports are resolved; imports
    under ``if TYPE_CHECKING:`` are left out."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    tree = ast.parse(path.read_text(), str(path))
    typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                   and ast.unparse(block.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")
                   for stmt in block.body for n in ast.walk(stmt)}
    for node in ast.walk(tree):
        if id(node) in typing_only:  # never executed: not an import at run time
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            out.update(f"{base}.{a.name}" if f"{base}.{a.name}" in known else base
                       for a in node.names)
    return {m for m in out if m in known}


def graph(root: Path = ROOT) -> dict[str, set[str]]:
    """Module -> the product modules it imports; the checkout's read once per process."""
    if root == ROOT and ROOT in _GRAPHS:
        return _GRAPHS[ROOT]
    mods = product_modules(root)
    g = {name: imported(name, path, mods) for name, path in mods.items()}
    if root == ROOT:
        _GRAPHS[ROOT] = g
    return g


_GRAPHS: dict[Path, dict[str, set[str]]] = {}


def cycles(g: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of ``g`` with a cycle (a module importing itself, or
    two or more importing each other)."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    names = sorted(g)
    at = {n: i for i, n in enumerate(names)}
    edges = [(at[a], at[b]) for a in names for b in g[a]]
    rows, cols = zip(*edges, strict=True) if edges else ((), ())
    m = csr_matrix(([1] * len(edges), (rows, cols)), shape=(len(names), len(names)))
    _, label = connected_components(m, directed=True, connection="strong")
    comps: dict[int, set[str]] = {}
    for n, c in zip(names, label, strict=True):
        comps.setdefault(int(c), set()).add(n)
    return [c for c in comps.values() if len(c) > 1 or next(iter(c)) in g[next(iter(c))]]


def layer(module: str) -> int:
    if module == CLI or module.startswith(CLI + "."):
        return len(LAYERS)
    return LAYERS.index(module.split(".")[1])


def test_the_graph_is_read():
    g = graph()
    assert "ddfuse.evaluation.pipeline" in g["ddfuse.evaluation.cli.run"]  # in a function
    assert "ddfuse.estimation.config" in g["ddfuse.evaluation.pipeline"]
    assert "ddfuse.evaluation.cli.dispatch" in g["ddfuse.evaluation.cli"]


def test_no_library_module_imports_the_command_line():
    bad = sorted(f"{a} imports {b}" for a, bs in graph().items() if layer(a) < len(LAYERS)
                 for b in bs if layer(b) == len(LAYERS))
    assert not bad


def test_argument_parsing_is_only_in_the_command_line():
    users = sorted(name for name, path in product_modules().items() if layer(name) < len(LAYERS)
                   and any(isinstance(node, (ast.Import, ast.ImportFrom))
                           and "argparse" in ([a.name for a in node.names]
                                              if isinstance(node, ast.Import) else [node.module])
                           for node in ast.walk(ast.parse(path.read_text()))))
    assert not users


def test_no_module_imports_a_higher_layer():
    bad = sorted(f"{a} imports {b}" for a, bs in graph().items() for b in bs
                 if layer(b) > layer(a))
    assert not bad


def test_no_import_cycle():
    assert not [sorted(c) for c in cycles(graph())]


def test_a_cycle_and_a_wrong_direction_are_found(tmp_path):
    """The checks above can fail: on a made-up tree with a cycle and an upward import."""
    for folder in LAYERS:
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "__init__.py").write_text("")
    (tmp_path / "factors" / "a.py").write_text("from ddfuse.factors import b\n")
    (tmp_path / "factors" / "b.py").write_text(
        "def f():\n    from ddfuse.factors.a import x\n    from ddfuse.evaluation import c\n")
    (tmp_path / "evaluation" / "c.py").write_text("from . import d\n")
    (tmp_path / "evaluation" / "d.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import c\n")
    g = graph(tmp_path)
    assert [sorted(c) for c in cycles(g)] == [["ddfuse.factors.a", "ddfuse.factors.b"]]
    assert g["ddfuse.factors.b"] == {"ddfuse.factors.a", "ddfuse.evaluation.c"}
    assert g["ddfuse.evaluation.c"] == {"ddfuse.evaluation.d"}
    assert g["ddfuse.evaluation.d"] == set()  # for type checkers only: no cycle with c
    assert layer("ddfuse.evaluation.c") > layer("ddfuse.factors.b")
