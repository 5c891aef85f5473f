"""Shared fixtures: one real Dask LocalCluster for the session, the tiny run and the reference run
(util.py has their flags), the command line in-process or as a process, and a headless browser.

The tests' searches compute the command line's bits: conftest.py sets what it sets
(`qdsearch.hold_kernels`: numba off, x86-64 CPUs held to AVX2's kernels; docs/performance.md)
before anything loads numpy, and the processes the tests start inherit it.
"""

import atexit
import contextlib
import io
import os
import shutil
import signal
import sys
import tempfile
from pathlib import Path

import pytest

import qdsearch

qdsearch.hold_kernels()  # before numpy loads (the import below loads it)

# The tests read the messages as the command line words them: loading qdsearch.cli sets NAMING's
# style to --{} (as data, not by a call, which mutmut's forced-fail run would make fail).
from qdsearch.cli import commands  # noqa: E402

ROOT = Path(__file__).resolve().parent
SCRIPT = ROOT / "lunar_lander.py"

# Checkpoints are signed with a key (qdsearch/base/signing.py): the tests', never the user's. Made once
# for the session (its pytest-xdist workers, and every process a test starts, inherit it), in a
# folder that goes with the process that made it.
if not os.environ.get("QDSEARCH_TESTS_KEY"):
    _KEY_FOLDER = tempfile.mkdtemp(prefix="qdsearch-tests-key-")
    atexit.register(shutil.rmtree, _KEY_FOLDER, ignore_errors=True)
    os.environ["QDSEARCH_TESTS_KEY"] = str(Path(_KEY_FOLDER) / "key")
os.environ["QDSEARCH_KEY"] = os.environ["QDSEARCH_TESTS_KEY"]

# The files whose tests take longest (real processes, signals, full experiments), longest first.
# pytest-xdist hands whole files to its workers in collection order (see pyproject.toml): the long
# ones first keeps the workers' loads even, as the short files fill in at the end.
# (Their order as `--durations=0` summed them per file on 2026-11-29.)
LONGEST_FIRST = ["test_environments.py", "test_clusters.py", "test_faults.py", "test_experiment.py",
                 "test_scale_out.py", "test_trackers.py", "test_run_folder.py", "test_first_hour.py",
                 "test_terminal.py", "test_algorithms.py", "test_qdrl.py", "test_search.py", "test_resume.py",
                 "test_guards.py", "test_safe_folders.py", "test_parsers.py", "test_locomotion.py"]


# The quick subset (-m "not slow") is what runs in this process alone: a test that needs a Dask
# cluster, a run folder searched on one, a browser or a process of its own is slow, as is one
# marked so by hand (signals, experiments, clusters of its own).
HEAVY_FIXTURES = {"dask_cluster", "dask_client", "one_worker_cluster", "off_loopback_cluster", "tiny_run",
                  "reference", "browser", "run_process"}


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)
    items.sort(key=rank)  # stable: each file's tests keep their order
    for item in items:
        if HEAVY_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def dask_cluster():
    """A real local cluster of two single-threaded worker processes, as `--workers 2` starts."""
    from util import local_cluster

    with local_cluster(2) as cluster:
        yield cluster


@pytest.fixture(scope="session")
def one_worker_cluster():
    """A real local cluster of one single-threaded worker process, as `--workers 1` starts: what
    the runs that must equal their two-worker twins fly on (one cluster for all of them, not one
    each)."""
    from util import local_cluster

    with local_cluster(1) as cluster:
        yield cluster


@pytest.fixture
def off_loopback_cluster():
    """A real local cluster of one worker process on this machine's outward address, not
    loopback: what a driver takes for workers with cores of their own (cluster.shares_this_machine),
    so it draws in saver processes."""
    from distributed.utils import get_ip

    from qdsearch.search.cluster import is_loopback
    from util import local_cluster

    host = get_ip()
    if is_loopback(host):
        pytest.skip("this machine has no address but loopback")
    with local_cluster(1, host) as cluster:
        yield cluster


@pytest.fixture(scope="session")
def dask_client(dask_cluster):
    from dask.distributed import Client

    with Client(dask_cluster) as client:
        yield client


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory, dask_cluster):
    """A tiny finished run folder (3 iterations, a few dozen elites), with its pictures, as a user's
    run has them; shared: only read it; a test that writes in a run folder copies it first."""
    from util import tiny_flags

    run_dir = tmp_path_factory.mktemp("tiny") / "run"
    commands.search(**tiny_flags(dask_cluster, pictures=True), outdir=str(run_dir))
    return run_dir


@pytest.fixture(scope="session")
def reference(tmp_path_factory, dask_cluster):
    """The uninterrupted run every stopped-and-resumed (or faulted) run must end equal to: the tiny
    run carried on to REFERENCE_ITERATIONS, saved once at its end (only the end is compared)."""
    from util import REFERENCE_ITERATIONS, tiny_flags

    run_dir = tmp_path_factory.mktemp("reference") / "run"
    commands.search(**tiny_flags(dask_cluster, iterations=REFERENCE_ITERATIONS,
                           log_every=REFERENCE_ITERATIONS), outdir=str(run_dir))
    return run_dir


@pytest.fixture
def run_cli(tmp_path, monkeypatch):
    """The command line as a user types it, run in-process through main() (no interpreter start,
    no re-import): the exit code, stdout and stderr, from tmp_path as the working folder."""
    from qdsearch.cli import app as ll
    from util import Result

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
