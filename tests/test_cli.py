"""The command line: help, and bad input answered with one line, an exit code and no damage."""

import inspect

import pytest

import lunar_lander as ll
from util import assert_one_line_error


def test_help_documents_every_flag(run_cli):
    result = run_cli("--help")
    assert result.returncode == 0
    for flag in inspect.signature(ll.search).parameters:
        assert f"--{flag}" in result.stdout + result.stderr, flag


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
