"""The code runs on the Python that pyproject.toml promises (requires-python >= 3.10): no
standard-library name that only Python 3.11+ has. (report.py used ``datetime.UTC``: every
``run`` and ``report`` ended in an AttributeError on 3.10.)"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ddfuse", "estimation", "factors", "ekf_baseline", "evaluation", "data")

# module -> names it has only from Python 3.11
NEW_IN_311 = {
    "datetime": {"UTC"},
    "typing": {"Self", "LiteralString", "Never", "assert_never", "reveal_type", "Required",
               "NotRequired", "dataclass_transform", "assert_type", "TypeVarTuple", "Unpack"},
    "enum": {"StrEnum", "ReprEnum", "verify", "EnumCheck", "FlagBoundary", "member",
             "nonmember", "global_enum"},
    "asyncio": {"TaskGroup", "timeout", "Runner"},
    "contextlib": {"chdir"},
    "hashlib": {"file_digest"},
    "logging": {"getLevelNamesMapping"},
    "operator": {"call"},
}
NEW_MODULES = {"tomllib", "wsgiref.types"}
NEW_BUILTINS = {"ExceptionGroup", "BaseExceptionGroup"}


def _sources():
    for pkg in PACKAGES:
        if (ROOT / pkg).is_dir():
            yield from sorted((ROOT / pkg).rglob("*.py"))


def _uses_of_311(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if node.attr in NEW_IN_311.get(node.value.id, ()):
                found.append(f"{where} {node.value.id}.{node.attr}")
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.module in NEW_MODULES:
                found.append(f"{where} from {node.module}")
            for a in node.names:
                if a.name in NEW_IN_311.get(node.module, ()):
                    found.append(f"{where} from {node.module} import {a.name}")
        elif isinstance(node, ast.Import):
            found += [f"{where} import {a.name}" for a in node.names if a.name in NEW_MODULES]
        elif isinstance(node, ast.Name) and node.id in NEW_BUILTINS:
            found.append(f"{where} {node.id}")
        elif type(node).__name__ == "TryStar":
            found.append(f"{where} except*")
        elif (isinstance(node, ast.Attribute) and node.attr == "add_note"
              and isinstance(node.ctx, ast.Load)):
            found.append(f"{where} .add_note")
    return found


@pytest.mark.slow
def test_no_python_311_only_names_while_310_is_promised():
    text = (ROOT / "pyproject.toml").read_text()
    assert re.search(r'^requires-python = ">=3\.10"$', text, re.M)
    assert re.search(r'^target-version = "py310"$', text, re.M)  # ruff judges for the same
    found = [u for p in _sources() for u in _uses_of_311(p)]
    assert found == []

