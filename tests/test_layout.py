"""The package's layout, read from its source: no import cycle, no private name used across modules, no module
over 600 lines, choices typed rather than passed as strings, and no alias module left from earlier layouts.

No paper section: these are the house rules of ``docs/architecture.md``. Every check parses the source with
:mod:`ast`, so it holds for imports inside functions too (``if TYPE_CHECKING:`` blocks are left out: they never
run).
"""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pushtorch"

#: Module paths of earlier layouts, gone now (CHANGELOG.md names where each went).
GONE = ["pushtorch.shapes", "pushtorch.metrics", "pushtorch.likelihood", "pushtorch.baselines", "pushtorch.cli",
        "pushtorch.config_check", "pushtorch.simulate", "pushtorch.train", "pushtorch.predict_cli",
        "pushtorch.collect", "pushtorch.predict", "pushtorch.deprecation", "pushtorch.prediction.conditions",
        "pushtorch.prediction.evidence", "pushtorch.prediction.clearance", "pushtorch.prediction.predict"]


def _module_name(path: Path) -> str:
    return ".".join(("pushtorch", *path.relative_to(PACKAGE).with_suffix("").parts)).removesuffix(".__init__")


MODULES = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` outside ``if TYPE_CHECKING:`` blocks."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        stack.extend(child for child in ast.iter_child_nodes(node) if not _type_checking(child))


def _absolute(module: str, node: ast.ImportFrom) -> str | None:
    if not node.level:
        return node.module
    base = module.split(".") if MODULES[module].name == "__init__.py" else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str) -> list[tuple[str, str | None]]:
    """``(imported module, imported name or None)`` of every runtime import in ``module``."""
    found = []
    for node in _runtime_nodes(ast.parse(MODULES[module].read_text())):
        if isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(module, node)
            found += [(source, alias.name) for alias in node.names]
    return found


def _edges(module: str) -> set[str]:
    """The project's modules ``module`` imports: ``from a import b`` imports the module ``a.b`` if there is one,
    else ``a`` (the parent packages a dotted import runs are not counted: every package would cycle with its
    own modules)."""
    out = set()
    for source, name in _imports(module):
        if source is None or not source.startswith("pushtorch"):
            continue
        target = f"{source}.{name}" if name and f"{source}.{name}" in MODULES else source
        if target in MODULES and target != module:
            out.add(target)
    return out


def _cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    graph = {m: _edges(m) for m in MODULES}
    index, low, on_stack, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle_inside_or_across_packages():
    assert _cycles() == []


def test_the_cycle_finder_finds_a_cycle(tmp_path, monkeypatch):
    """The check can fail: two modules importing each other (one inside a function) form a cycle."""
    (tmp_path / "pushtorch").mkdir()
    (tmp_path / "pushtorch" / "a.py").write_text("from pushtorch.b import x\n")
    (tmp_path / "pushtorch" / "b.py").write_text("def f():\n    from pushtorch import a\n")
    (tmp_path / "pushtorch" / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                                 "    from pushtorch.a import y\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", tmp_path / "pushtorch")
    monkeypatch.setattr(sys.modules[__name__], "MODULES", {_module_name(p): p for p in
                                                           (tmp_path / "pushtorch").glob("*.py")})
    assert _cycles() == [["pushtorch.a", "pushtorch.b"]]


def test_no_module_imports_another_modules_private_names():
    found = [f"{module}: from {source} import {name}" for module in MODULES for source, name in _imports(module)
             if name and name.startswith("_") and not name.startswith("__") and source != module
             and source and source.startswith("pushtorch")]
    assert found == []


def test_no_module_is_over_600_lines():
    long = {module: n for module, path in MODULES.items() if (n := len(path.read_text().splitlines())) > 600}
    assert long == {}


def test_every_module_says_what_it_is_for():
    assert [m for m, path in MODULES.items() if not ast.get_docstring(ast.parse(path.read_text()))] == []


def test_the_evaluation_path_is_a_type_below_the_api():
    """No parameter is typed ``method: str``: the density's evaluation path is a :class:`pushtorch.kde.Evaluation`
    (parsed once, by ``Evaluation.of``, where a user passes a string), and experiments name predictors otherwise."""
    typed_str, checks = [], []
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.arg) and node.arg == "method" and node.annotation is not None \
                    and ast.unparse(node.annotation) == "str":
                typed_str.append(f"{module}:{node.lineno}")
            if isinstance(node, ast.FunctionDef) and node.name == "_check_method":
                checks.append(module)
    assert typed_str == [] and checks == []


def test_experiments_are_imported_by_name_in_one_registry_only():
    """``import_module(f"...")`` (a module found from a name) appears in the registry alone."""
    found = [module for module, path in MODULES.items()
             for node in ast.walk(ast.parse(path.read_text()))
             if isinstance(node, ast.Call) and ast.unparse(node.func).endswith("import_module")
             and node.args and isinstance(node.args[0], ast.JoinedStr)]
    assert len(set(found)) <= 1, found


@pytest.mark.parametrize("old", GONE)
def test_no_alias_module_is_left(old):
    assert importlib.util.find_spec(old) is None, f"{old} still exists"


@pytest.mark.parametrize("script", ["pushtorch", "pushtorch-simulate", "pushtorch-train", "pushtorch-predict"])
def test_the_console_scripts_run_the_apps(script):
    executable = Path(sys.executable).parent / script
    result = subprocess.run([str(executable), "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and "Configuration groups" in result.stdout, result.stderr[-2000:]


def test_predict_is_a_function_of_the_package():
    probe = ("import pushtorch, pushtorch.prediction, inspect; "
             "assert inspect.isfunction(pushtorch.predict) and pushtorch.predict is pushtorch.prediction.predict")
    subprocess.run([sys.executable, "-c", probe], check=True)
