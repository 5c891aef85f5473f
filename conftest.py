"""Shared fixtures: one real Dask LocalCluster for the session, and tiny search configurations.

numba would compile ribs' CMA-ES code in every process that runs a search (5-8 s each);
NUMBA_DISABLE_JIT gives bitwise-identical results, so the tests (and the processes they start)
run with it.
"""

import contextlib
import dataclasses
import io
import logging
import os
import signal
import sys
from pathlib import Path

os.environ.setdefault("NUMBA_DISABLE_JIT", "1")

import pytest

ROOT = Path(__file__).resolve().parent
SCRIPT = ROOT / "lunar_lander.py"

# The files whose tests take longest (real processes, signals, full experiments), longest first.
# pytest-xdist hands whole files to its workers in collection order (see pyproject.toml): the long
# ones first keeps the two workers' loads even, as the short files fill in at the end.
LONGEST_FIRST = ["test_resume.py", "test_experiment.py", "test_run_folder.py", "test_fast_env.py",
                 "test_scale_out.py", "test_algorithms.py"]


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)
    items.sort(key=rank)  # stable: each file's tests keep their order


@pytest.fixture(scope="session")
def dask_cluster():
    """A real local cluster of two single-threaded worker processes, as `--workers 2` starts."""
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR) as cluster:
        yield cluster


@pytest.fixture(scope="session")
def dask_client(dask_cluster):
    from dask.distributed import Client

    with Client(dask_cluster) as client:
        yield client


@pytest.fixture
def tiny_config(dask_cluster):
    """Keyword arguments of `search` for a seconds-long run on the session cluster."""
    return dict(iterations=3, workers=2, seed=7, env_seed=52, algorithm="cma_me", n_emitters=2,
                sigma0=1.0, batch_size=6, log_every=2,
                scheduler_address=dask_cluster.scheduler_address)


@dataclasses.dataclass
class Result:
    returncode: int
    stdout: str
    stderr: str


@pytest.fixture
def run_cli(tmp_path, monkeypatch):
    """The command line as a user types it, run in-process through main() (no interpreter start,
    no re-import): the exit code, stdout and stderr, from tmp_path as the working folder."""
    import lunar_lander as ll

    monkeypatch.chdir(tmp_path)

    def run(*args):
        out, err = io.StringIO(), io.StringIO()
        handlers = {signum: signal.getsignal(signum) for signum in (signal.SIGINT, signal.SIGTERM)}
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    code = ll.main([str(arg) for arg in args])
                except SystemExit as exit:  # Fire's --help
                    code = exit.code or 0
        finally:
            for signum, handler in handlers.items():  # main() installs its stop handlers
                signal.signal(signum, handler)
        return Result(code, out.getvalue(), err.getvalue())
    return run


@pytest.fixture
def run_process(tmp_path):
    """The script as a real process (for what needs one: a fresh interpreter, signals, shipping
    the script to a cluster); returns the CompletedProcess."""
    import subprocess

    def run(*args, timeout=300):
        return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=tmp_path,
                              capture_output=True, text=True, timeout=timeout)
    return run


CHROMIUM = "/usr/bin/chromium"  # Debian's package; .ci/run installs it when it is missing
CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-quic",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="session")
def browser():
    """A real headless Chromium driven by Playwright, or a skip that says what is missing."""
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install chromium); browser tests skipped")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("Playwright is not installed (pip install playwright); browser tests skipped")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS)
        yield browser
        browser.close()
