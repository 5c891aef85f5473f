"""The command line: help, and bad input answered with one line, an exit code and no damage."""

import inspect

import pytest

import lunar_lander as ll
from qdsearch import options, run
from util import assert_one_line_error


def test_help_documents_every_flag(run_cli):
    result = run_cli("--help")
    assert result.returncode == 0
    for flag in inspect.signature(run.search).parameters:
        assert f"--{flag}" in result.stdout + result.stderr, flag


def test_minus_h_is_help_not_a_flags_short_name(run_cli):
    """Fire names --hidden -h; -h stays help, as everywhere."""
    for command in ([], ["compare"]):
        result = run_cli(*command, "-h")
        assert result.returncode == 0 and "NAME" in result.stdout + result.stderr, result.stderr


@pytest.mark.parametrize("flag, value", [
    ("iterations", 0), ("iterations", -3), ("iterations", "ten"), ("workers", 0),
    ("batch_size", 0), ("n_emitters", 0), ("log_every", 0), ("sigma0", 0), ("seed", -1),
    ("algorithm", "nope"),
])
def test_bad_flag_values(run_cli, tmp_path, flag, value):
    result = run_cli(f"--{flag}={value}", "--outdir", tmp_path / "run")
    assert_one_line_error(result, f"--{flag}")
    assert not (tmp_path / "run").exists()


def test_unknown_flag_and_command(run_cli):
    assert_one_line_error(run_cli("--iteratons", "3"), "--iteratons")
    assert_one_line_error(run_cli("serach"), "serach")


def test_existing_run_folder_is_not_touched(run_cli, tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text("precious")
    assert_one_line_error(run_cli("--iterations", 1, "--outdir", run_dir), str(run_dir))
    assert [p.name for p in run_dir.iterdir()] == ["metrics.json"]
    assert (run_dir / "metrics.json").read_text() == "precious"


def test_unwritable_run_folder(run_cli, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert_one_line_error(run_cli("--iterations", 1, "--outdir", blocker / "run"), "cannot write")
    assert blocker.read_text() == "not a folder"


def test_the_readmes_flag_table_says_what_the_flag_table_declares():
    """The README's main flags come from SEARCH_FLAGS: the same defaults, and only real flags."""
    import re

    from conftest import ROOT

    rows = re.findall(r"^\| `--(\w+)` \| ([^|]+) \|", (ROOT / "README.md").read_text(), re.MULTILINE)
    assert len(rows) >= 10
    shown = {None: ["none", "drawn", "the task's"], "cma_me": ["`cma_me`"],
             "LunarLander-v3": ["`LunarLander-v3`"]}
    for name, default in rows:
        assert name in options.SEARCH_FLAGS, name
        flag = options.SEARCH_FLAGS[name]
        expected = {"outdir": ["`outputs/<timestamp>_seed<seed>`"],  # the default says where
                    "grid": [f"{options.DEFAULT_GRID} on a grid"],  # or of what archive
                    "cells": [f"{options.DEFAULT_CVT_CELLS} in a CVT"]}.get(
            name, shown.get(flag.default, [str(flag.default)]))
        assert default.strip() in expected, (name, default)


def test_every_command_documents_its_flags_from_the_tables(run_cli):
    for name in ll.COMMANDS:
        function = ll.command(name)
        result = run_cli(*([] if name == "search" else [name]), "--help")
        assert result.returncode == 0, name
        parameters = inspect.signature(function).parameters
        for flag in ll.known_flags(function):
            if flag in parameters and parameters[flag].default is inspect.Parameter.empty:
                continue  # a positional argument (RUN_DIR)
            if flag not in parameters:
                continue  # experiment passes search's flags on: its help lists them in one line
            assert f"--{flag}" in result.stdout + result.stderr, (name, flag)
        shown = " ".join((result.stdout + result.stderr).split())
        own = inspect.signature(getattr(function, "__wrapped__", function)).parameters
        tables = (options.SEARCH_FLAGS, options.CLUSTER_FLAGS, options.RESUME_FLAGS, options.SELECTION_FLAGS,
                  options.TERRAIN_FLAGS)
        for flag in (flag for flag in parameters if flag not in own):  # taken from a table
            helps = [" ".join(table[flag].help.split()[:6]) for table in tables if flag in table]
            assert any(help in shown for help in helps), (name, flag)
