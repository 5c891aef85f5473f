"""The command line: bad input answered with one line, an exit code and no damage (its help, and
the names it refuses: test_help.py)."""

import pytest

from qdsearch.config import settings
from util import assert_one_line_error


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
        assert name in settings.SEARCH_FLAGS, name
        flag = settings.SEARCH_FLAGS[name]
        expected = {"outdir": ["`outputs/<timestamp>_seed<seed>`"],  # the default says where
                    "grid": [f"{settings.DEFAULT_GRID} on a grid"],  # or of what archive
                    "cells": [f"{settings.DEFAULT_CVT_CELLS} in a CVT"]}.get(
            name, shown.get(flag.default, [str(flag.default)]))
        assert default.strip() in expected, (name, default)
