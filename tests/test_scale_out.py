"""Joining an existing Dask cluster: `dask scheduler` and two `dask worker` processes on loopback,
started where the script is not, as on other machines that have the packages but not the script."""

import contextlib
import os
import subprocess
import sys
import time

import pytest

from util import run_archive, run_metrics, start_scheduler, start_worker, stop_all, tiny_flags

pytestmark = pytest.mark.slow  # real processes, signals, clusters: not in the quick subset


@pytest.fixture
def external_cluster(tmp_path):
    """A scheduler and two single-threaded workers, each in a folder without lunar_lander.py."""
    from dask.distributed import Client

    elsewhere = tmp_path / "elsewhere"
    scheduler, scheduler_file = start_scheduler(elsewhere)
    processes = [scheduler]
    try:
        processes += [start_worker(scheduler_file, elsewhere / f"w{i}") for i in range(2)]
        with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
            yield client
    finally:
        stop_all(processes)


def can_import_the_code(client) -> list[bool]:
    """Whether each worker can import the package whose functions tasks name."""
    def finds_it() -> bool:
        import importlib.util

        return importlib.util.find_spec("qdsearch") is not None and (
            importlib.util.find_spec("qdsearch.search.engine") is not None)
    return list(client.run(finds_it).values())


def test_search_on_an_existing_cluster_equals_a_local_run(tmp_path, tiny_run, run_process,
                                                           external_cluster):
    assert can_import_the_code(external_cluster) == [False, False]
    address = external_cluster.scheduler.address

    result = run_process(*[f"--{k}={v}" for k, v in tiny_flags().items()], f"--scheduler_address={address}",
                         f"--outdir={tmp_path / 'remote'}")
    assert result.returncode == 0, result.stderr
    assert f"Dask cluster at {address}: 2 worker(s)" in result.stdout

    remote = run_archive(tmp_path / "remote")  # tiny_run flew on the session's local cluster
    assert len(remote) > 0 and remote.equals(run_archive(tiny_run))
    assert run_metrics(tmp_path / "remote") == run_metrics(tiny_run)

    # The cluster is not ours to shut down: still there, and the code was shipped to it.
    assert len(external_cluster.nthreads()) == 2
    assert can_import_the_code(external_cluster) == [True, True]


@pytest.mark.parametrize("workers", ["elsewhere", "on loopback"])
def test_a_search_on_a_joined_cluster_draws_in_a_saver_process_what_it_would_draw_itself(
        tmp_path, request, workers):
    """With workers elsewhere (any address but loopback), the driver's process never draws (every
    run's tell needs its GIL): its saver process writes the CSV and the pictures, the very bytes
    the driver would have written. With workers on loopback (this machine's cores), its thread
    draws them, as with a cluster of its own (no fork server's imports)."""
    import json

    from conftest import ROOT
    from qdsearch import tasks
    from qdsearch.config.run_config import check_run_config
    from qdsearch.store import saving
    from util import read_checkpoint

    cluster = request.getfixturevalue("off_loopback_cluster" if workers == "elsewhere" else "dask_cluster")
    flags = {**tiny_flags(cluster, pictures=True), "outdir": str(tmp_path / "run")}
    code = ("import json, sys; from qdsearch.cli import commands; "
            "commands.search(**json.loads(sys.argv[1])); "
            "print('driver imported matplotlib:', 'matplotlib' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code, json.dumps(flags)], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert f"driver imported matplotlib: {workers == 'on loopback'}" in result.stdout

    checkpoint = read_checkpoint(tmp_path / "run" / "checkpoint.pkl")
    (tmp_path / "here").mkdir()
    heat = tasks.returns_of(check_run_config(checkpoint["config"])).heat
    saving.save_outputs(tmp_path / "here", checkpoint["scheduler"].result_archive, checkpoint["metrics"],
                        check_run_config(checkpoint["config"]), checkpoint["iteration"], heat)
    names = ["archive.csv", "heatmap.png", "progress.png",
             f"heatmaps/heatmap_{checkpoint['iteration']:05d}.png"]
    assert all((tmp_path / "run" / name).read_bytes() == (tmp_path / "here" / name).read_bytes()
               for name in names)


def test_explore_on_an_existing_cluster_ships_the_package(tmp_path, tiny_run, run_process,
                                                          external_cluster):
    """The explorer's poses are recorded by explorer.record_poses, on workers that have never seen
    the package."""
    import shutil

    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    result = run_process("explore", run_dir, f"--scheduler_address={external_cluster.scheduler.address}")
    assert result.returncode == 0, result.stderr
    assert (run_dir / "explorer.html").stat().st_size > 10_000


def test_unreachable_scheduler_is_a_one_line_error(run_cli, tmp_path):
    result = run_cli("--iterations", 1, "--scheduler_address", "tcp://127.0.0.1:9",
                     "--outdir", tmp_path / "run")
    assert result.returncode != 0 and "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and "127.0.0.1:9" in result.stderr


def test_local_workers_fly_without_dasks_profiler():
    """The local cluster a search starts switches off each worker's statistical profiler, which
    would take the GIL from the rollouts every 10 ms (cluster.QUIET_CLUSTER)."""
    import logging

    from qdsearch.search import cluster

    with cluster.dask_client(2, None, logging.getLogger("test")) as client:
        callbacks = client.run(lambda dask_worker: sorted(dask_worker.periodic_callbacks))
    assert len(callbacks) == 2
    assert all("heartbeat" in names and "profile" not in names for names in callbacks.values())


def threads_cores(dask_worker) -> tuple:
    """Run on a worker: its name, its process and the cores of each of its threads."""
    return (dask_worker.name, os.getpid(),
            {frozenset(os.sched_getaffinity(int(thread))) for thread in os.listdir("/proc/self/task")})


def pinned_workers(client) -> dict:
    """Worker name: (process, the cores its threads may run on), once each has run a task (its
    task thread is started then)."""
    for address in client.scheduler_info()["workers"]:
        client.submit(os.getpid, workers=[address], pure=False).result(timeout=60)
    return {name: (pid, cores) for name, pid, cores in client.run(threads_cores).values()}


def restarted(client, name: int, old_address: str, count: int) -> bool:
    """Whether the scheduler knows `count` workers again, worker `name` at a new address."""
    workers = client.scheduler_info()["workers"]
    return len(workers) == count and any(worker["name"] == name and address != old_address
                                         for address, worker in workers.items())


@contextlib.contextmanager
def on_cores(cores: set[int]):
    """This process, every thread of it, on `cores` (a big machine's test starts two workers, not
    one per core), and back as it was."""
    threads = {}
    for thread in map(int, os.listdir("/proc/self/task")):
        with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile (CI saw one)
            threads[thread] = os.sched_getaffinity(thread)
    for thread in threads:
        with contextlib.suppress(OSError):
            os.sched_setaffinity(thread, cores)
    try:
        yield
    finally:  # threads started meanwhile (Dask's) as the process was
        for thread in map(int, os.listdir("/proc/self/task")):
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(thread, threads.get(thread, threads[os.getpid()]))


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="Linux's affinity")
def test_a_local_worker_per_core_is_pinned_to_its_core_and_so_is_its_restart():
    """A worker per core: worker i on core i, every thread of it, and again once its nanny has
    started it anew after a SIGKILL. Fewer workers than cores are left free."""
    import logging
    import signal

    from qdsearch.search import cluster
    from qdsearch.search.pinning import PinToCore

    cores = sorted(os.sched_getaffinity(0))[:2]
    with on_cores(set(cores)), cluster.dask_client(len(cores), None, logging.getLogger("test")) as client:
        before = pinned_workers(client)
        assert {name: cores_of for name, (_, cores_of) in before.items()} == {
            i: {frozenset([core])} for i, core in enumerate(cores)}
        victim, (pid, _) = max(before.items())
        address = next(address for address, worker in client.scheduler_info()["workers"].items()
                       if worker["name"] == victim)
        os.kill(pid, signal.SIGKILL)
        deadline = time.time() + 90
        while time.time() < deadline and not restarted(client, victim, address, len(cores)):
            time.sleep(0.2)
        after = pinned_workers(client)
        assert after[victim][0] != pid and after[victim][1] == {frozenset([cores[victim]])}
    if len(cores) > 1:
        with on_cores(set(cores)), cluster.dask_client(1, None, logging.getLogger("test")) as client:
            assert all(cores_of == {frozenset(cores)} for _, cores_of in pinned_workers(client).values())
            # a core that can't be had is no fault: the worker stays where it was
            client.register_plugin(PinToCore([os.cpu_count() + 1000]), name="unreachable core")
            assert all(cores_of == {frozenset(cores)} for _, cores_of in pinned_workers(client).values())


def test_a_cluster_where_some_workers_have_the_code_and_some_do_not_gets_it_everywhere(tmp_path, monkeypatch):
    """A mixed cluster: the scheduler and one worker elsewhere, one worker with the package on its
    path (PYTHONPATH). ship_code sends the package when any of them lacks it, so that every
    worker can run a task, and a worker that joins later gets it too; the zip it sent is not left
    behind in the temporary folder."""
    import tempfile

    from dask.distributed import Client

    from conftest import ROOT
    from qdsearch.search.cluster import ship_code

    (tmp_path / "temp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "temp"))
    scheduler, scheduler_file = start_scheduler(tmp_path / "scheduler")
    processes = [scheduler]
    try:
        for i, path in enumerate(("", str(ROOT))):
            processes.append(start_worker(scheduler_file, tmp_path / f"w{i}", PYTHONPATH=path))
        with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=60)
            assert sorted(can_import_the_code(client)) == [False, True]
            ship_code(client)
            assert can_import_the_code(client) == [True, True]
            assert list((tmp_path / "temp").iterdir()) == []
            processes.append(start_worker(scheduler_file, tmp_path / "w2", PYTHONPATH=""))
            client.wait_for_workers(3, timeout=60)
            assert can_import_the_code(client) == [True, True, True]
    finally:
        stop_all(processes)
