"""A researcher's first hour (issue 49): every command's --help whole and quiet, -h and --help help
wherever they are typed, and every refused name named, with the name it likely meant."""

import inspect

import pytest

from qdsearch import algorithms, tasks
from qdsearch.base import flags
from qdsearch.cli import app as ll
from qdsearch.cli import help as cli_help
from qdsearch.cli import signatures
from qdsearch.config import command_settings, settings
from util import assert_one_line_error


def squeezed(text: str) -> str:
    """Text with its line breaks and indents as single spaces: a page wraps what a table declares."""
    return " ".join(text.split())


def help_of(run_cli, name: str, *args: str) -> str:
    """A command's page as --help prints it (exit 0, nothing on stderr)."""
    result = run_cli(*([] if name == "search" else [name]), *args, "--help")
    assert result.returncode == 0 and not result.stderr, (name, result.stderr)
    return result.stdout


def declared(name: str) -> dict[str, str]:
    """Every flag a command takes from the tables, with the help its Flag entry declares: those it
    took (flag_table), and for experiment the search flags it passes on to every run."""
    function = ll.command(name)
    own = inspect.signature(function).parameters
    passed_on = {flag: settings.SEARCH_FLAGS[flag].help for flag in ll.known_flags(function)
                 if flag not in own}
    return {**passed_on, **{flag: entry.help for flag, entry in signatures.flag_table(function).items()}}


def test_the_tables_are_the_flags_commands_take():
    """What the page test below checks is every table: search takes SEARCH_FLAGS whole, and each
    of CLUSTER_FLAGS and SELECTION_FLAGS is taken by some command."""
    assert signatures.flag_table(ll.command("search")) == settings.SEARCH_FLAGS
    taken = {flag for name in ll.COMMANDS for flag in signatures.flag_table(ll.command(name))}
    assert set(settings.CLUSTER_FLAGS) | set(command_settings.SELECTION_FLAGS) <= taken


@pytest.mark.parametrize("name", ll.COMMANDS)
def test_every_flags_help_is_whole_in_its_commands_page(run_cli, name):
    page = help_of(run_cli, name)
    shown = squeezed(page)
    function = ll.command(name)
    parameters = inspect.signature(function).parameters
    for flag in ll.known_flags(function):  # every flag, a positional argument aside (RUN_DIR)
        assert f"--{flag}=" in page or parameters[flag].default is inspect.Parameter.empty, (name, flag)
    for flag, text in declared(name).items():
        assert f"--{flag}=" in page and squeezed(text) in shown, (name, flag)
    for flag, text in cli_help.documented_arguments(function.__doc__).items():  # its own (Args)
        assert squeezed(text) in shown, (name, flag)
    for noise in ("Optional[", "flag_table", "GROUPS", "-h, --"):
        assert noise not in page, (name, noise)


def test_the_pages_the_new_user_found_cut_short_are_whole(run_cli):
    """The help texts Fire's docstring parser cut at a colon, and a hyphen broken by a wrap."""
    search = squeezed(help_of(run_cli, "search"))
    for whole in ("as many as the cores: each is pinned to a core of its own.",
                  "(pyribs' ns_cma: 0.037).", "default: the task's (a grid; Ant-v5's 4 feet: cvt).",
                  "ME-MAP-Elites (bandit)", "Lunar Lander: impact_x, impact_y_velocity"):
        assert whole in search, whole
    part = squeezed(help_of(run_cli, "experiment"))
    assert "(a SLURM job array: docs/clusters.md). Every part is given the same flags" in part
    compare = squeezed(help_of(run_cli, "compare"))
    assert "instead of every pair: with many settings, Holm's adjustment" in compare


def test_the_main_page_lists_every_command(run_cli):
    page = help_of(run_cli, "search")
    commands = page.split("\nCOMMANDS\n")[1].split("\n\n", 2)[1]
    assert [line.split()[0] for line in commands.splitlines() if line.startswith("    ") and
            not line.startswith("     ")] == list(ll.COMMANDS)


@pytest.mark.parametrize("args", [
    ["-h"], ["--help"], ["watch", "-h"], ["watch", "RUN", "-h"], ["video", "RUN", "--best", "--help"],
    ["compare", "A", "B", "-h"], ["--iterations", "3", "-h"], ["experiment", "--seeds", "1", "-h"],
    ["elites", "-h", "RUN"], ["search", "--nope", "-h"],
])
def test_minus_h_and_help_are_help_everywhere(run_cli, tmp_path, args):
    """Help wins wherever it is typed: exit 0, the page, and nothing run (no folder, no search)."""
    result = run_cli(*args)
    assert result.returncode == 0 and result.stdout.startswith("NAME\n") and not result.stderr, result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, message", [
    (["search", "--algoritm", "cma_me"], "unknown flag --algoritm; did you mean --algorithm?"),
    (["--iteratons", "3"], "unknown flag --iteratons; did you mean --iterations?"),
    (["experiment", "--algorithm", "cma_me"], "unknown flag --algorithm; did you mean --algorithms?"),
    (["--algorithm", "sep-cma-mae"], "--algorithm 'sep-cma-mae' is unknown; did you mean sep_cma_mae?"),
    (["wach", "RUN"], "unknown command 'wach'; did you mean watch?"),
    (["--env", "Hoper-v5"], "--env 'Hoper-v5' is unknown; did you mean Hopper-v5?"),
    (["--measures", "x_pos,y_vell"], "--measures 'x_pos' is not one of the measures; choose from impact_x,"),
    (["--measures", "impact_x,y_vell"], "--measures 'y_vell' is not one of the measures; did you mean "
                                        "impact_y_velocity?"),
    (["--track", "tensorbord"], "--track 'tensorbord' is not a tracker; did you mean tensorboard?"),
    (["--policy", "MLP"], "--policy 'MLP' is unknown; did you mean mlp?"),
    (["--archive", "grd"], "--archive 'grd' is unknown; did you mean grid?"),
    (["experiment", "--algorithms", "[cma_me, cma-mae]"], "--algorithms 'cma-mae' is unknown; did you mean "
                                                         "cma_mae?"),
    (["--algorithm", "nope"], "--algorithm 'nope' is unknown; choose from cma_me, cma_mae,"),
    (["serach"], "unknown command 'serach'; did you mean search?"),
])
def test_a_refused_name_is_named_with_the_name_it_likely_meant(run_cli, tmp_path, args, message):
    assert_one_line_error(run_cli(*args), message)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("typed, choices, meant", [
    ("sep-cma-mae", algorithms.ALGORITHMS, "sep_cma_mae"), ("CMA_ME", algorithms.ALGORITHMS, "cma_me"),
    ("y_vel", tasks.MEASURES, "impact_y_velocity"), ("hopper-v5", tasks.ENVIRONMENTS, "Hopper-v5"),
    ("seeds", settings.SEARCH_FLAGS, "seed"), ("zzzz", algorithms.ALGORITHMS, None),
])
def test_nearest_is_the_name_a_typo_meant(typed, choices, meant):
    assert flags.nearest(typed, choices) == meant


def test_a_docstrings_args_are_read_by_indent_not_by_colons():
    def command(run_dir, part=None):
        """Do it.

        Args:
            run_dir: A folder: any.
            part: I/K: part I of K (a SLURM job
                array: docs/clusters.md), run again: it continues.
        """
    assert cli_help.documented_arguments(command.__doc__) == {
        "run_dir": "A folder: any.",
        "part": "I/K: part I of K (a SLURM job array: docs/clusters.md), run again: it continues."}


def test_a_runs_config_is_a_class_in_the_source_every_field_typed_and_on_the_help_page():
    """RunConfig is the settings classes written in config/settings.py (no make_dataclass): a field
    per flag, typed as its check returns (None where it may be unset), then the records; search's
    --help lists every flag field."""
    import dataclasses
    import re

    from conftest import ROOT

    source = (ROOT / "qdsearch" / "config" / "settings.py").read_text()
    fields = dataclasses.fields(settings.RunConfig)
    assert [field.name for field in fields] == [*settings.SEARCH_FLAGS, *settings.RECORDS]
    for field in fields:
        assert re.search(rf"^    {field.name}: {re.escape(field.type)} = ", source, re.M), field.name
    for name, entry in settings.SEARCH_FLAGS.items():
        returned = entry.check.__annotations__["return"] if entry.check else "str"
        typed = f"{returned} | None" if entry.default is None or entry.check is None else returned
        assert fields[list(settings.SEARCH_FLAGS).index(name)].type == typed, name
    package = "".join(path.read_text() for path in (ROOT / "qdsearch").rglob("*.py"))
    assert "make_dataclass" not in package and "def setting(" not in package
    page = ll.help_text("search", ll.command("search"))
    assert all(f"--{name}=" in page for name in settings.SEARCH_FLAGS)


def test_top_is_declared_once_for_every_command_that_picks_the_best_elites():
    """video, trajectories, elites and evaluate take --top from one entry (command_settings.TOP): one
    default, one check; each page says what the K best are for there."""
    tops = {name: signatures.flag_table(ll.command(name))["top"] for name in ("video", "trajectories",
                                                                              "elites",
                                                                         "evaluate")}
    assert all(entry.check is command_settings.TOP.check and entry.default is None for entry in tops.values())
    assert tops["video"] is command_settings.TOP and "Robustness only" in tops["evaluate"].help
