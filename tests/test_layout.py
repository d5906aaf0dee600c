"""The layout's promises (README, "Architecture"), read from the source with ``ast``:
imports run one way between the wings, no folder imports one that imports it back, and no
module imports one that imports it back (an import inside a function counts; one under
``if TYPE_CHECKING:`` does not, since it never runs)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
MODULE_ROOTS = ("service", "training", "evaluation", "benchmarks", "scripts")
WINGS = (  # the folders whose imports are checked, most specific first
    "service/__main__",  # the entry point: it wires the wings together
    "service/engine",
    "service/api",
    "service/gallery",
    "service/client",
    "service",
    "training",
    "evaluation",
    "benchmarks",
    "scripts",
)


def wing_of(module: str) -> str | None:
    """The wing a dotted module name lives in (``service.engine.grid`` -> ``service/engine``)."""
    path = module.replace(".", "/")
    return next((w for w in WINGS if path == w or path.startswith(w + "/")), None)


def imports(path: Path) -> set[str]:
    """Every module a file imports, absolute, wherever the import statement stands."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def sources(wing: str) -> list[Path]:
    if (REPO / f"{wing}.py").is_file():
        return [REPO / f"{wing}.py"]
    files = sorted((REPO / wing).rglob("*.py"))
    deeper = [REPO / w for w in WINGS if w.startswith(wing + "/")]
    return [
        f for f in files if not any(f.with_suffix("") == d or f.is_relative_to(d) for d in deeper)
    ]


def wing_graph() -> dict[str, set[str]]:
    """Which wings each wing imports (itself left out)."""
    graph: dict[str, set[str]] = {}
    for wing in WINGS:
        targets = {wing_of(name) for f in sources(wing) for name in imports(f)}
        graph[wing] = {t for t in targets if t and t != wing}
    return graph


def test_the_engine_imports_neither_the_api_nor_the_store_nor_a_web_framework():
    for file in sources("service/engine"):
        for name in imports(file):
            top = name.split(".")[0]
            assert top not in ("fastapi", "starlette", "uvicorn", "torch"), (file, name)
            assert wing_of(name) in (None, "service/engine", "service"), (file, name)


def test_the_store_does_not_import_the_api():
    for file in sources("service/gallery"):
        assert not any(wing_of(name) == "service/api" for name in imports(file)), file


def test_the_client_needs_only_numpy_and_httpx():
    """``service.client`` runs on a cell controller: none of the service's own wings, no server."""
    for file in sources("service/client"):
        for name in imports(file):
            assert wing_of(name) in (None, "service/client"), (file, name)
            top = name.split(".")[0]
            assert top not in ("fastapi", "starlette", "uvicorn", "onnxruntime", "torch"), name


def test_the_service_never_imports_torch():
    for file in (REPO / "service").rglob("*.py"):
        assert not any(name.split(".")[0] == "torch" for name in imports(file)), file


def test_no_folder_imports_one_that_imports_it_back():
    graph = wing_graph()

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for nxt in graph.get(start, ()):
            if nxt == goal or (nxt not in seen and reaches(nxt, goal, seen | {nxt})):
                return True
        return False

    cycles = [wing for wing in WINGS if reaches(wing, wing, {wing})]
    assert not cycles, {wing: sorted(graph[wing]) for wing in cycles}


@pytest.mark.parametrize(
    "wing, allowed",
    [
        ("service/engine", {"service"}),
        ("service/gallery", {"service", "service/engine"}),
        ("training", {"service", "service/engine", "service/gallery"}),
        ("evaluation", {"service", "service/engine", "service/gallery", "service/api", "training"}),
    ],
)
def test_imports_run_one_way(wing, allowed):
    assert wing_graph()[wing] <= allowed


# --- modules ---------------------------------------------------------------------------------


def module_name(path: Path, repo: Path) -> str:
    """``service/gallery/store.py`` -> ``service.gallery.store``; a package is its folder."""
    parts = list(path.relative_to(repo).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def runtime_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement, wherever it stands, but those under ``if TYPE_CHECKING:``."""

    def checking(test: ast.expr) -> bool:
        name = test.id if isinstance(test, ast.Name) else getattr(test, "attr", None)
        return name == "TYPE_CHECKING"

    found, stack = [], [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and checking(node.test):
            stack.extend(node.orelse)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        else:
            stack.extend(ast.iter_child_nodes(node))
    return found


def module_graph(repo: Path = REPO, roots: tuple[str, ...] = MODULE_ROOTS) -> dict[str, set]:
    """Which of the modules under ``roots`` each one imports: the most specific module an import
    names (``from a import b`` is module ``a.b`` where there is one, else ``a``)."""
    files = {module_name(p, repo): p for root in roots for p in sorted((repo / root).rglob("*.py"))}

    def known(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set] = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in runtime_imports(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {known(alias.name) for alias in node.names}
                continue
            base = node.module or ""
            if node.level:  # relative: from the module's package, one folder up per extra dot
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*parent, *filter(None, [node.module])])
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                targets.add(submodule if submodule in files else known(base))
        graph[name] = {t for t in targets if t and t != name}
    return graph


def cycles(graph: dict[str, set]) -> list[list[str]]:
    """The groups of modules that import each other, round a cycle (Tarjan's strongly connected
    components of more than one module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in graph.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while not group or group[-1] != node:
                group.append(stack.pop())
            if len(group) > 1:
                found.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_module_imports_one_that_imports_it_back():
    graph = module_graph()
    assert "service.gallery.store" in graph["service.gallery.sqlite_store"]  # the graph sees
    assert cycles(graph) == []


def test_the_module_check_finds_a_cycle_a_lazy_import_makes(tmp_path):
    """A function's import makes a cycle; an import for type checkers alone does not."""
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def later():\n    from pkg import b\n")
    (package / "b.py").write_text("from . import a\n")
    (package / "c.py").write_text("from typing import TYPE_CHECKING\nfrom pkg.a import later\n")
    (package / "d.py").write_text(
        "from typing import TYPE_CHECKING\nimport pkg.c\nif TYPE_CHECKING:\n    import pkg.e\n"
    )
    (package / "e.py").write_text("import pkg.d\n")
    graph = module_graph(tmp_path, ("pkg",))
    assert graph["pkg.d"] == {"pkg.c"} and graph["pkg.b"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.b"]]
