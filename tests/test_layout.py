"""The layout's promises (README, "Architecture"), read from the source with ``ast``:
imports run one way between the wings, and no folder imports one that imports it back."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
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
