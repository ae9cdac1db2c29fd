"""The arrows between modules point one way.

- simgen never imports clfbev and clfbev never imports simgen, anywhere (a function's own
  imports included): they meet only at the nuScenes format on disk.
- Inside each package no module imports itself back through others: the graph of the imports
  that run as a module loads (module level and class bodies, not under ``if TYPE_CHECKING:``)
  has no cycle, and drawing the imports inside functions as well closes none either. A
  function-level import lets both modules of a circle load, but they still depend on each other.
- The detector's modules never reach clfbev.supervision: the model does not depend on how it is
  trained.

The sources are parsed, not imported: the test needs no optional dependency and runs in a second.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("simgen", "clfbev")


def module_name(path: Path, root: Path) -> str:
    """clfbev/ops/sparse_conv/__init__.py -> clfbev.ops.sparse_conv; clfbev/io.py -> clfbev.io."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules(package: str, root: Path = ROOT) -> dict[str, Path]:
    """{dotted module name: source file} of every module of ``package`` under ``root``."""
    return {module_name(p, root): p for p in sorted((root / package).rglob("*.py"))}


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports(path: Path) -> list[tuple[ast.Import | ast.ImportFrom, bool]]:
    """Every import statement of a source file, with True when it runs as the module is imported
    (at module level or in a class body, outside ``if TYPE_CHECKING:``), False inside a function
    or under ``if TYPE_CHECKING:``."""
    found = []

    def visit(node: ast.AST, at_import: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                found.append((child, at_import))
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, False)
            elif isinstance(child, ast.If) and _is_type_checking(child):
                for stmt in child.body:
                    visit(ast.Module(body=[stmt], type_ignores=[]), False)
                for stmt in child.orelse:
                    visit(ast.Module(body=[stmt], type_ignores=[]), at_import)
            else:
                visit(child, at_import)

    visit(ast.parse(path.read_text(), filename=str(path)), True)
    return found


def imported_base(node: ast.Import | ast.ImportFrom, importer: str, is_package: bool) -> list[str]:
    """The absolute dotted modules an import statement names: ``import a.b, c`` -> [a.b, c];
    ``from .x import y`` in module p.m -> [p.x] (its names may be attributes or submodules)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if not node.level:
        return [node.module or ""]
    package = importer if is_package else importer.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return [f"{package}.{node.module}" if node.module else package]


def import_graph(package: str, at_import_only: bool, root: Path = ROOT) -> dict[str, set[str]]:
    """{module: the modules of the same package it imports}. ``from m import x`` draws an arrow
    to the submodule m.x when there is one, else to m (where x is defined)."""
    mods = modules(package, root)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for name, path in mods.items():
        for node, at_import in imports(path):
            if at_import_only and not at_import:
                continue
            bases = imported_base(node, name, path.name == "__init__.py")
            if isinstance(node, ast.Import):
                targets = {b for b in bases if b in mods}
            else:
                subs = [f"{bases[0]}.{alias.name}" for alias in node.names]
                targets = {s if s in mods else bases[0] for s in subs} & set(mods)
            graph[name] |= targets - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def strongconnect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strongconnect(w)
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
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)
    return found


def function_level_cycles(package: str, root: Path = ROOT) -> list[list[str]]:
    """Cycles that only appear when the imports inside functions are drawn as well."""
    at_import = {tuple(c) for c in cycles(import_graph(package, True, root))}
    return [c for c in cycles(import_graph(package, False, root)) if tuple(c) not in at_import]


@pytest.mark.parametrize("package, other", [("simgen", "clfbev"), ("clfbev", "simgen")])
def test_a_package_never_imports_the_other(package, other):
    offenders = []
    for name, path in modules(package).items():
        for node, _ in imports(path):
            bases = imported_base(node, name, path.name == "__init__.py")
            if any(b == other or b.startswith(other + ".") for b in bases):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not offenders, f"{package} imports {other}: {', '.join(offenders)}"


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycle_at_import_time(package):
    assert cycles(import_graph(package, at_import_only=True)) == []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_circle_hidden_in_a_function_either(package):
    """Moving one import of a circle into a function lets both modules load, but the two still
    depend on each other (the entry point and the training loop did, once)."""
    assert function_level_cycles(package) == []


# The detector's modules: what builds and runs CLFusionBEV. The training supervision builds on
# them, never the reverse (the camera geometry, the depth bins and the direction coding they
# share live in clfbev.geometry).
MODEL_MODULES = ("clfbev.model", "clfbev.camera_encoder", "clfbev.lidar_encoder", "clfbev.fusion", "clfbev.attention",
                 "clfbev.head", "clfbev.camera_aux", "clfbev.bilinear_lift", "clfbev.geometry")


def reachable(graph: dict[str, set[str]], start: str) -> set[str]:
    """The modules ``start`` imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        for w in graph[todo.pop()] - seen:
            seen.add(w)
            todo.append(w)
    return seen


def test_the_model_never_imports_the_training_supervision():
    graph = import_graph("clfbev", at_import_only=False)
    offenders = {m: sorted(w for w in reachable(graph, m) if w.startswith("clfbev.supervision"))
                 for m in MODEL_MODULES}
    assert all(m in graph for m in MODEL_MODULES)
    assert not any(offenders.values()), offenders
    assert "clfbev.geometry" in reachable(graph, "clfbev.supervision.targets")


def test_the_checks_see_a_planted_circle_and_a_crossing(tmp_path):
    """The checks above cannot pass by finding nothing: a circle through a relative import and a
    submodule import is found; an import under TYPE_CHECKING is not drawn; one inside a function
    is drawn only when asked for; a function-level import of the other package is seen."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": "from .sub import b\n",
        "sub/__init__.py": "",
        "sub/b.py": "from ..c import thing\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import d\n",
        "c.py": "import pkg.a\nthing = 1\ndef f():\n    from pkg import d\n    import other.x\n",
        "d.py": "from pkg.c import thing\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    assert import_graph("pkg", True, tmp_path)["pkg.sub.b"] == {"pkg.c"}
    assert cycles(import_graph("pkg", True, tmp_path)) == [["pkg.a", "pkg.c", "pkg.sub.b"]]
    assert function_level_cycles("pkg", tmp_path) == [["pkg.a", "pkg.c", "pkg.d", "pkg.sub.b"]]
    inside_f = [n for n, at_import in imports(pkg / "c.py") if not at_import]
    assert [imported_base(n, "pkg.c", False) for n in inside_f] == [["pkg"], ["other.x"]]
