"""Helpers shared by the tests."""

import json
import pickle
from pathlib import Path

import pandas as pd


def load_pickle(path):
    with open(path, "rb") as file:
        return pickle.load(file)


def archive_table(archive) -> pd.DataFrame:
    """An archive's contents in a fixed row order, for exact comparisons."""
    return archive.data(return_type="pandas").sort_values("index").reset_index(drop=True)


def run_archive(run_dir: Path) -> pd.DataFrame:
    return archive_table(load_pickle(Path(run_dir) / "archive.pkl"))


def run_metrics(run_dir: Path) -> list[dict]:
    """metrics.json without the timings, which differ between any two runs."""
    rows = json.loads((Path(run_dir) / "metrics.json").read_text())
    return [{k: v for k, v in row.items() if k != "elapsed_s"} for row in rows]


def folder_state(path: Path) -> dict:
    """Every file below `path` with its bytes: to check that a failed command touched nothing."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(Path(path).rglob("*")) if p.is_file()}


def launch(*args, **flags):
    """The script as a real process in a session of its own (so a test can kill its whole group)."""
    import subprocess
    import sys

    from conftest import SCRIPT

    return subprocess.Popen([sys.executable, str(SCRIPT), *map(str, args),
                             *[f"--{k}={v}" for k, v in flags.items()]],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def wait_for(condition, process, what, timeout=120):
    """Poll `condition` until it holds; fail with the process's output if it ends first."""
    import time

    deadline = time.time() + timeout
    while time.time() < deadline and process.poll() is None:
        if condition():
            return
        time.sleep(0.01)
    raise AssertionError(f"never saw {what}: {process.communicate()}")


def checkpoint_iteration(run_dir: Path) -> int:
    """The iteration of a run folder's checkpoint, -1 while there is none (or it is being replaced)."""
    try:
        return load_pickle(Path(run_dir) / "checkpoint.pkl")["iteration"]
    except (OSError, EOFError, pickle.UnpicklingError):
        return -1


def assert_one_line_fault(code, stderr, *fragments):
    """Exit code 1 and one line of error, the last one printed (a search's progress bar may
    precede it on stderr)."""
    assert code == 1, stderr
    lines = [line for line in stderr.strip().splitlines() if line.strip()]
    assert lines[-1].startswith("error: ") and "Traceback" not in stderr, stderr
    assert sum(line.startswith("error: ") for line in lines) == 1
    for fragment in fragments:
        assert fragment in lines[-1], lines[-1]
