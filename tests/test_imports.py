"""Imports go one way. The package `qdsearch` is in layers, each a subpackage, named from the bottom
up in qdsearch/__init__.py's map: a module imports only the layers below its own and, in its own
layer, the modules its layer's map names before it (qdsearch/LAYER/__init__.py). So no two modules
import each other, directly or through others, at load time or inside a function. The command
line (qdsearch.cli) is the top layer: no other imports it or Fire, and the package never imports
the script."""

import ast
import inspect
import re
from pathlib import Path

from conftest import ROOT

PACKAGE = ROOT / "qdsearch"


def imported_modules(path: Path) -> set[str]:
    """Every module an `import` or `from ... import` anywhere in the file names (functions too);
    `from qdsearch.base import flags` names qdsearch.base.flags."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            if node.module.split(".")[0] == "qdsearch":
                found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return found


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def map_lines(path: Path, marker: str) -> list[list[str]]:
    """The names of a map's entries ("- name, name: what they are") after `marker` in a module's
    docstring, in order, up to the paragraph's end; names on one line share a place."""
    text = path.read_text().split(marker, 1)[1].split('"""', 1)[0].split("\n\n", 1)[0]
    return [line[2:].split(":", 1)[0].split(", ") for line in text.splitlines() if line.startswith("- ")]


LAYERS = [names[0] for names in map_lines(PACKAGE / "__init__.py", "Map,")]


def module_places() -> dict[str, tuple[int, int]]:
    """Each module's place: its layer's, then its place in its layer's map; a layer whose
    __init__ holds code (the tasks' registry, the algorithms' table) has it where its map
    names `__init__`, or last."""
    places = {}
    for layer_place, layer in enumerate(LAYERS):
        lines = map_lines(PACKAGE / layer / "__init__.py", "imports going down the list only")
        places[f"qdsearch.{layer}"] = (layer_place, len(lines))
        for place, names in enumerate(lines):
            places |= {f"qdsearch.{layer}" + ("" if name == "__init__" else f".{name}"): (layer_place, place)
                       for name in names}
    return places


def package_graph() -> dict[str, set[str]]:
    """Each module of the package's layers, and the modules of the package it imports."""
    paths = {module_name(path): path for path in PACKAGE.glob("*/*.py")}
    return {name: {m for m in imported_modules(path) if m in paths and m != name}
            for name, path in paths.items()}


def test_every_module_imports_only_layers_below_and_modules_above_it_in_its_layer():
    places, graph = module_places(), package_graph()
    assert LAYERS == ["base", "tasks", "algorithms", "store", "config", "search", "analysis", "cli"]
    assert set(places) == set(graph), set(places) ^ set(graph)  # every map names every module once
    assert graph["qdsearch.search.loop"] >= {"qdsearch.search.engine", "qdsearch.store.saving"}
    upward = {module: sorted(m for m in imported if places[m] >= places[module])
              for module, imported in graph.items()}
    assert not any(upward.values()), {module: up for module, up in upward.items() if up}


def test_no_two_modules_import_each_other_even_through_others():
    graph = package_graph()

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


def test_only_the_command_line_layer_imports_fire_or_itself_and_none_imports_the_script():
    for path in PACKAGE.rglob("*.py"):
        imported, text = imported_modules(path), path.read_text()
        assert not any(m == "lunar_lander" or m.startswith("lunar_lander.") for m in imported), path
        assert "import_module(\"lunar_lander" not in text, path
        if path.parent.name != "cli":
            assert not {m for m in imported if m == "fire" or m.startswith("qdsearch.cli")}, path
            assert '"qdsearch.cli' not in text and "'qdsearch.cli" not in text, path  # by name neither


def test_a_module_names_its_siblings_by_their_full_names():
    """`from qdsearch.base import flags`, never `import flags` or a relative import."""
    stems = {path.stem for path in PACKAGE.rglob("*.py")}
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text())
        relative = [node for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.level]
        assert not relative, path
        assert not imported_modules(path) & stems, path


def test_the_import_check_sees_a_lazy_import_inside_a_function(tmp_path):
    """The check itself: an import inside a function counts, by its module's full name."""
    path = tmp_path / "lazy.py"
    path.write_text("def f():\n    from qdsearch.search import run\n    import lunar_lander\n")
    assert imported_modules(path) >= {"qdsearch.search.run", "lunar_lander"}


# Every layer but the command line names a setting only through base.flags.named (the command
# line words it as --name, a Python caller reads the keyword). A command a message tells the user
# to type (ours, `python lunar_lander.py resume RUN --part 1/2`, or Dask's) is written as typed.
NAMING_LAYERS = [layer for layer in LAYERS if layer != "cli"]
COMMANDS_TO_TYPE = ("lunar_lander.py", "dask worker")


def message_texts(path: Path) -> list[tuple[int, str]]:
    """Each string a module may show (line, text): every literal but docstrings, the help a table
    declares (a `help=`/`summary=` keyword, a Flag entry) and the statements that write a command
    to type (COMMANDS_TO_TYPE)."""
    source = path.read_text()
    tree = ast.parse(source)
    skipped = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Return, ast.Assign, ast.Raise, ast.Expr)) and any(
                command in ast.get_source_segment(source, node) for command in COMMANDS_TO_TYPE):
            skipped |= {id(inner) for inner in ast.walk(node)}
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef)) and ast.get_docstring(node):
            skipped.add(id(node.body[0].value))
        if isinstance(node, ast.keyword) and node.arg in ("help", "summary"):
            skipped |= {id(inner) for inner in ast.walk(node.value)}
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("Flag", "flag", "retold"):
            skipped |= {id(inner) for inner in ast.walk(node)}
    texts = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr) and id(node) not in skipped:  # an f-string: {} for each value
            skipped |= {id(part) for part in node.values}
            texts.append((node.lineno, "".join(part.value if isinstance(part, ast.Constant) else "{}"
                                               for part in node.values)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skipped:
            texts.append((node.lineno, node.value))
    return texts


# Texts with a "--" that are no message: a library's own option, set in the environment.
NOT_MESSAGES = {"--xla_cpu_max_isa=AVX2"}  # base/kernels.py: JAX's kernels held to AVX2


def test_no_layer_but_the_command_line_names_a_flag_in_its_messages():
    for layer in NAMING_LAYERS:
        for path in (PACKAGE / layer).glob("*.py"):
            flagged = [(line, text) for line, text in message_texts(path)
                       if re.search(r"--[a-z{]", text) and text not in NOT_MESSAGES]
            assert not flagged, (path, flagged)


def test_the_check_sees_a_flag_in_a_message(tmp_path):
    """The check itself: a flag written into a message is found, a docstring's and a help's not."""
    path = tmp_path / "m.py"
    path.write_text('"""Uses --env."""\nx = Flag(1, "--grid cells")\ndef f(name):\n'
                    '    raise UsageError(f"--{name} is bad; see --env")\n'
                    'y = f"python lunar_lander.py resume X --part 1/2"\n')
    assert [text for _, text in message_texts(path)] == ["--{} is bad; see --env"]


def test_the_installed_command_runs_what_the_script_runs():
    """pyproject.toml's entry point `lunar-lander` is the function lunar_lander.py calls."""
    import importlib
    import tomllib

    target = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]["lunar-lander"]
    module, _, function = target.partition(":")
    script = (ROOT / "lunar_lander.py").read_text()
    assert f"from {module} import {function}" in script and f"    {function}()" in script
    assert callable(getattr(importlib.import_module(module), function))


def test_the_installed_command_titles_its_pages_by_its_own_name(tmp_path):
    """Run as the installed `lunar-lander` (the entry point's own file name), --help names that
    command, not the script; run as the script, the script."""
    import subprocess
    import sys

    def page(program: str, *args: str) -> str:
        code = (f"import sys; sys.argv = [{program!r}, *{list(args)!r}]; "
                "from qdsearch.cli.app import run_as_script; run_as_script()")
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stderr
        return done.stdout

    installed = page(str(tmp_path / "bin" / "lunar-lander"), "video", "--help")
    assert "    lunar-lander video - Render an mp4" in installed
    assert "    lunar-lander video RUN_DIR [--FLAG=VALUE ...]" in installed
    assert "lunar_lander.py" not in installed
    main = page(str(tmp_path / "bin" / "lunar-lander"), "--help")
    assert "    lunar-lander COMMAND --help: a command's own page." in main
    script = page(str(ROOT / "lunar_lander.py"), "video", "--help")
    assert "    python lunar_lander.py video RUN_DIR [--FLAG=VALUE ...]" in script


def test_the_core_commands_take_typed_settings_never_flags():
    """Each command's core function takes typed settings (a settings class, a RunConfig, a path),
    never `**flags`: only the command line makes a signature of flags (cli/signatures.py)."""
    import dataclasses
    import typing

    from qdsearch.analysis import comparison, evaluation, explorer, live, results
    from qdsearch.search import experiments, run

    cores = (run.search, run.resume_run, experiments.resume, experiments.experiment, results.video,
             results.elites, results.trajectories, evaluation.evaluate, explorer.explore,
             comparison.compare, live.watch)
    for function in cores:
        parameters = inspect.signature(function).parameters.values()
        assert not any(p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL) for p in parameters), function
        hints = typing.get_type_hints(function)
        assert any(dataclasses.is_dataclass(hint) for hint in hints.values()), function


def test_no_layer_but_the_command_line_and_the_config_reads_a_flag_table():
    """The flag tables (a name ending in _FLAGS: the entries a command's signature and --help are
    made from) are the config layer's and the command line's; the others read typed settings and
    what settings.py says of them (SETTINGS, PASSED_ON, SWEEPS, LABELLED, checked_settings; the
    names of the flags some rows alone use, ROW_FLAGS and POLICY_FLAGS, are sets, not tables)."""
    import importlib

    for layer in LAYERS:
        if layer in ("config", "cli"):
            continue
        for path in (PACKAGE / layer).glob("*.py"):
            tables = sorted({alias.name for node in ast.walk(ast.parse(path.read_text()))
                             if isinstance(node, ast.ImportFrom) and node.module.startswith("qdsearch")
                             for alias in node.names if isinstance(
                                 getattr(importlib.import_module(node.module), alias.name, None), dict)
                             and alias.name.endswith("_FLAGS")})
            assert not tables, (path, tables)


def config_parameters(path: Path) -> list[tuple[str, str]]:
    """Each (function, annotation) of the file's functions' parameters named `config`."""
    return [(node.name, ast.unparse(arg.annotation) if arg.annotation else "")
            for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            for arg in node.args.args + node.args.kwonlyargs if arg.arg == "config"]


def test_below_the_config_layer_a_run_s_settings_are_typed_never_a_dict():
    """Outside the config layer (whose constructors check raw values) and the command line, a
    function takes a run's settings as a type that says what it reads (a RunConfig, or the
    Protocol of its layer: tasks.TaskConfig, algorithms.RowConfig, ...), never `Any` or a dict;
    a record as read or written (config.json's JSON) is named `recorded`."""
    untyped = [(path.relative_to(PACKAGE).as_posix(), function, annotation)
               for layer in LAYERS if layer not in ("config", "cli")
               for path in sorted((PACKAGE / layer).glob("*.py"))
               for function, annotation in config_parameters(path)
               if annotation in ("", "Any", "dict") or annotation.startswith(("dict[", "Any |"))]
    assert not untyped, untyped
    assert ("episode_of", "TaskConfig") in config_parameters(PACKAGE / "tasks" / "__init__.py")


def test_the_check_sees_a_run_s_settings_taken_as_a_dict(tmp_path):
    path = tmp_path / "module.py"
    path.write_text("def f(x, config: dict[str, int]):\n    pass\n\ndef g(*, config):\n    pass\n")
    assert config_parameters(path) == [("f", "dict[str, int]"), ("g", "")]


def protocol_members(protocol: type) -> set[str]:
    """The attributes and methods a Protocol (and the Protocols it extends) declares."""
    declared = [cls for cls in protocol.__mro__ if cls is not object and getattr(cls, "_is_protocol", False)]
    methods = {key for cls in declared for key, value in vars(cls).items()
               if callable(value) and not key.startswith("_")}
    return methods | {name for cls in declared for name in vars(cls).get("__annotations__", {})}


def test_a_run_config_is_what_every_layer_reads_of_a_run():
    """RunConfig has every attribute and method each layer's Protocol reads: the layers below the
    config layer name what they read, and the config gives it."""
    from qdsearch.algorithms import RowConfig
    from qdsearch.config.options import search_defaults, with_task
    from qdsearch.config.run_config import check_run_config
    from qdsearch.search.engine import FlownConfig
    from qdsearch.store.saving import SavedConfig
    from qdsearch.store.trackers import TrackedConfig
    from qdsearch.tasks import TaskConfig

    config = check_run_config(with_task({**search_defaults(), "seed": 1}))
    for protocol in (TaskConfig, RowConfig, FlownConfig, SavedConfig, TrackedConfig):
        members = protocol_members(protocol)
        assert len(members) >= 5, (protocol, members)
        assert not [name for name in members if not hasattr(config, name)], protocol
    assert {"fast_env", "network", "env", "reset"} <= protocol_members(FlownConfig)  # its own and
    assert {"algorithm", "network", "env"} <= protocol_members(RowConfig)  # those it extends
    assert "to_json" in protocol_members(SavedConfig)
