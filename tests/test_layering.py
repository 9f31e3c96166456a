"""Layering of the code base (docs/architecture.md): parsed with ``ast``, imports inside
functions included.

* :mod:`seqat` imports nothing from :mod:`pipeline`;
* no import cycles in :mod:`pipeline`, neither between modules nor between its subpackages;
* no ``from X import _private`` across modules of :mod:`pipeline` and :mod:`seqat`;
* no module of :mod:`pipeline` or :mod:`seqat` over :data:`MAX_MODULE_LINES` lines.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 800


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO_ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(package: str) -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((REPO_ROOT / package).rglob("*.py"))}


PIPELINE = _modules("pipeline")

#: What each subpackage of pipeline may import (docs/architecture.md, *Packages*).
ALLOWED: dict[str, set[str]] = {
    "common": set(),
    "tracking": {"common"},
    "flight": {"common", "tracking"},
    "run": {"common", "tracking", "flight"},
    "reference": {"common", "flight", "run"},
    "ortho": {"common", "flight", "run"},
    "simulate": {"common", "flight", "run", "ortho"},
    "report": {"common", "flight", "run", "reference"},
    "campaign": {"common", "flight", "run", "reference", "ortho", "report"},
    "bench": {"common", "flight", "run", "reference", "ortho", "simulate", "report",
              "campaign"},
    "serve": {"common", "run"},
    "cli": {"common", "tracking", "flight", "run", "reference", "ortho", "simulate", "report",
            "campaign", "bench", "serve"},
}
SEQAT = _modules("seqat")


def _imports(name: str, path: Path) -> Iterator[tuple[str, tuple[str, ...], int]]:
    """``(module, imported names, line)`` of every import statement, at any depth."""
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, (), node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[:len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            yield module, tuple(a.name for a in node.names), node.lineno


def _targets(module: str, names: tuple[str, ...], known: dict[str, Path]) -> set[str]:
    """Modules of ``known`` an import reaches (``from pkg import mod`` reaches ``pkg.mod``)."""
    found = {f"{module}.{n}" for n in names if f"{module}.{n}" in known}
    if module in known and (not names or len(found) < len(names)):
        found.add(module)
    return found


def _graph(collapse: bool) -> dict[str, set[str]]:
    """Import graph of pipeline's modules, or (``collapse``) of its top-level units: each
    subpackage ``pipeline.X`` counts as one node."""
    def unit(module: str) -> str:
        return ".".join(module.split(".")[:2]) if collapse else module

    graph: dict[str, set[str]] = {}
    for name, path in PIPELINE.items():
        edges = graph.setdefault(unit(name), set())
        for module, names, _ in _imports(name, path):
            for target in _targets(module, names, PIPELINE):
                if unit(target) != unit(name) and unit(target) != "pipeline":
                    edges.add(unit(target))
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_modules_are_found() -> None:
    assert "pipeline.cli" in PIPELINE and "seqat" in SEQAT
    assert len(PIPELINE) > 40


def test_seqat_imports_nothing_from_pipeline() -> None:
    bad = [f"{name}:{line}: {module}" for name, path in SEQAT.items()
           for module, _, line in _imports(name, path)
           if module == "pipeline" or module.startswith("pipeline.")]
    assert bad == []


def test_every_pipeline_import_resolves_in_this_tree() -> None:
    bad = [f"{name}:{line}: {module}" for name, path in PIPELINE.items()
           for module, names, line in _imports(name, path)
           if (module == "pipeline" or module.startswith("pipeline."))
           and not _targets(module, names, PIPELINE)]
    assert bad == []


@pytest.mark.parametrize("collapse", [False, True], ids=["modules", "subpackages"])
def test_no_import_cycles_in_pipeline(collapse: bool) -> None:
    assert _cycles(_graph(collapse)) == []


def test_subpackages_import_only_what_the_architecture_allows() -> None:
    def short(unit: str) -> str:
        return unit.removeprefix("pipeline.")

    graph = {short(k): {short(t) for t in v} for k, v in _graph(True).items()}
    units = {u for u in graph if u != "pipeline"}
    assert units == set(ALLOWED)  # every module lives in one of the subpackages
    bad = {u: sorted(graph[u] - ALLOWED[u]) for u in units if graph[u] - ALLOWED[u]}
    assert bad == {}


def test_no_private_names_imported_across_modules() -> None:
    bad = [f"{name}:{line}: from {module} import {n}"
           for name, path in {**PIPELINE, **_modules("seqat")}.items()
           for module, names, line in _imports(name, path)
           if module.split(".")[0] in ("pipeline", "seqat") and module != name
           for n in names if n.startswith("_") and not n.startswith("__")]
    assert bad == []


def test_no_module_over_the_line_limit() -> None:
    long = {name: n for name, path in {**PIPELINE, **_modules("seqat")}.items()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert long == {}
