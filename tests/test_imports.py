"""Imports go one way: the script sits on top of the package `qdsearch`, which never imports it, and
no two of the package's modules import each other, directly or through others, at load time or
inside a function."""

import ast
from pathlib import Path

from conftest import ROOT

PACKAGE = ROOT / "qdsearch"


def imported_modules(path: Path) -> set[str]:
    """Every module an `import` or `from ... import` anywhere in the file names (functions too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            if node.module == "qdsearch":  # from qdsearch import tasks
                found |= {f"qdsearch.{alias.name}" for alias in node.names}
    return found


def package_graph() -> dict[str, set[str]]:
    """Each module of the package, and the modules of the package it imports."""
    modules = {f"qdsearch.{path.stem}": path for path in PACKAGE.glob("*.py") if path.stem != "__init__"}
    return {name: {m for m in imported_modules(path) if m in modules and m != name}
            for name, path in modules.items()}


MODULES = {path.stem for path in PACKAGE.glob("*.py")}  # a sibling must be named as qdsearch.NAME


def test_the_package_never_imports_the_script():
    for path in PACKAGE.glob("*.py"):
        assert not imported_modules(path) & MODULES, path  # a sibling by a top-level name
        imported = imported_modules(path)
        assert not any(m == "lunar_lander" or m.startswith("lunar_lander.") for m in imported), path
        assert "import_module(\"lunar_lander" not in path.read_text(), path


def test_no_two_modules_import_each_other_even_through_others():
    graph = package_graph()
    assert len(graph) >= 10 and graph["qdsearch.loop"] >= {"qdsearch.engine", "qdsearch.saving"}

    def reaches(start: str) -> set[str]:
        seen, todo = set(), list(graph[start])
        while todo:
            module = todo.pop()
            if module not in seen:
                seen.add(module)
                todo += graph[module]
        return seen

    cycles = [module for module in graph if module in reaches(module)]
    assert not cycles, {module: sorted(graph[module]) for module in cycles}


def test_the_import_check_sees_a_lazy_import_inside_a_function(tmp_path):
    """The check itself: an import inside a function counts."""
    path = tmp_path / "lazy.py"
    path.write_text("def f():\n    from qdsearch import run\n    import lunar_lander\n")
    assert imported_modules(path) >= {"qdsearch.run", "lunar_lander"}


def map_order() -> dict[str, int]:
    """Each module's place in the package's map (qdsearch/__init__.py: "imports going down the
    list only"); modules named on one line share a place."""
    text = (PACKAGE / "__init__.py").read_text().split("Map,", 1)[1].split('"""', 1)[0]
    lines = [line[2:].split(":", 1)[0] for line in text.splitlines() if line.startswith("- ")]
    return {f"qdsearch.{name}": place for place, line in enumerate(lines) for name in line.split(", ")}


def test_every_module_imports_only_those_above_it_in_the_packages_map():
    order, graph = map_order(), package_graph()
    assert set(order) == set(graph), set(order) ^ set(graph)  # the map names every module once
    upward = {module: sorted(m for m in imported if order[m] >= order[module])
              for module, imported in graph.items()}
    assert not any(upward.values()), {module: up for module, up in upward.items() if up}
