"""Clusters as HPC jobs start them: `dask scheduler --scheduler-file` and `dask worker
--scheduler-file` processes started from the command line, in folders without our code; workers
that join late, retire (SIGTERM, --lifetime) or are killed while an experiment runs; a scheduler
that dies; and a scheduler file that appears late, never, stale or garbled."""

import json
import os
import signal
import time

import pytest
from dask.distributed import Client

from qdsearch import run
from util import (
    Result,
    assert_one_line_error,
    checkpoint_iteration,
    launch,
    run_archive,
    run_metrics,
    start_scheduler,
    start_worker,
    stop_all,
    tiny_flags,
    wait_for,
)

pytestmark = pytest.mark.slow  # real scheduler and worker processes

# Two runs long enough for workers to come and go while they fly.
RUNS = dict(algorithms="cma_me", seeds="1-2", iterations=60, n_emitters=2, batch_size=6, log_every=2)


@pytest.fixture(scope="module")
def twins(tmp_path_factory, dask_cluster):
    """Each run of RUNS flown alone by `search` on the session's cluster, by seed."""
    root = tmp_path_factory.mktemp("twins")
    flags = {k: v for k, v in RUNS.items() if k not in ("algorithms", "seeds")}
    for seed in (1, 2):
        run.search(**tiny_flags(dask_cluster, **flags, seed=seed), outdir=str(root / str(seed)))
    return {seed: root / str(seed) for seed in (1, 2)}


def plan_of(folder):
    return json.loads((folder / "experiment.json").read_text())


def assert_runs_equal_their_twins(folder, twins):
    for entry in plan_of(folder)["runs"]:
        assert entry["state"] == "done"
        assert run_archive(folder / entry["name"]).equals(run_archive(twins[entry["seed"]]))
        assert run_metrics(folder / entry["name"]) == run_metrics(twins[entry["seed"]])


def executed(client, worker: str) -> int:
    """Tasks the worker has run."""
    return client.run(lambda dask_worker: dask_worker.state.executed_count, workers=[worker])[worker]


def experiment_under_way(folder, scheduler_file, processes):
    """The experiment of RUNS as a process joining the scheduler file's cluster, once both runs
    are past iteration 2 (it is added to `processes`)."""
    experiment = launch("experiment", **RUNS, outdir=folder, scheduler_file=scheduler_file)
    processes.append(experiment)
    wait_for(lambda: (folder / "experiment.json").exists() and all(
        checkpoint_iteration(folder / entry["name"]) >= 2 for entry in plan_of(folder)["runs"]),
        experiment, "both runs past iteration 2")
    return experiment


def test_workers_that_join_retire_and_die_change_nothing(tmp_path, twins):
    scheduler, scheduler_file = start_scheduler(tmp_path / "elsewhere")
    processes = [scheduler, start_worker(scheduler_file, tmp_path / "w0")]
    folder = tmp_path / "exp"
    try:
        experiment = experiment_under_way(folder, scheduler_file, processes)
        with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
            processes.append(start_worker(scheduler_file, tmp_path / "w1"))  # joins late
            short_lived = start_worker(scheduler_file, tmp_path / "w2", "--lifetime", "4s",
                                       "--lifetime-stagger", "0s")  # joins, then retires on its own
            processes.append(short_lived)
            processes.append(start_worker(scheduler_file, tmp_path / "w3", "--lifetime", "2s",
                                          "--lifetime-stagger", "1s", "--lifetime-restart"))  # comes back
            def late_worker():
                return next((address for address, info in client.scheduler_info()["workers"].items()
                             if str(tmp_path / "w1") in info["local_directory"]), None)
            wait_for(lambda: late_worker() is not None, experiment, "the late worker joined")
            late = late_worker()
            wait_for(lambda: executed(client, late) > 0, experiment, "the late worker at work")
            late_pid = client.run(os.getpid, workers=[late])[late]
            os.killpg(processes[1].pid, signal.SIGTERM)  # the first worker retires
            os.kill(late_pid, signal.SIGKILL)  # the late one dies mid-task; its nanny restarts it
            wait_for(lambda: short_lived.poll() is not None, experiment, "the short-lived worker gone")
            assert experiment.poll() is None  # all of it happened while the runs flew
        out, err = experiment.communicate(timeout=300)
        assert experiment.returncode == 0, err
        assert_runs_equal_their_twins(folder, twins)
    finally:
        stop_all(processes)


def test_a_lost_scheduler_stops_the_experiment_and_resume_on_a_new_one_finishes_it(
        tmp_path, twins, monkeypatch):
    monkeypatch.setenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "5s")  # notice the loss sooner
    scheduler, scheduler_file = start_scheduler(tmp_path / "first")
    processes = [scheduler, start_worker(scheduler_file, tmp_path / "w0")]
    folder = tmp_path / "exp"
    try:
        experiment = experiment_under_way(folder, scheduler_file, processes)
        os.killpg(scheduler.pid, signal.SIGKILL)  # its job preempted
        out, err = experiment.communicate(timeout=180)
        assert_one_line_error(Result(experiment.returncode, out, err), "lost the Dask scheduler",
                              f"resume {folder} --scheduler_file", code=1)
        held = {entry["name"]: checkpoint_iteration(folder / entry["name"])
                for entry in plan_of(folder)["runs"]}
        assert {entry["state"] for entry in plan_of(folder)["runs"]} == {"stopped"}
        assert all(iteration >= 2 for iteration in held.values())

        # resume is started before the new scheduler exists: it waits for the file
        second = tmp_path / "second" / "scheduler.json"
        resumed = launch("resume", folder, scheduler_file=second)
        processes.append(resumed)
        time.sleep(2)
        new_scheduler, _ = start_scheduler(second.parent)
        processes += [new_scheduler, start_worker(second, tmp_path / "w1")]
        out, err = resumed.communicate(timeout=300)
        assert resumed.returncode == 0, err
        assert_runs_equal_their_twins(folder, twins)
        assert plan_of(folder)["timing"]["iterations"] == sum(RUNS["iterations"] - i for i in held.values())
    finally:
        stop_all(processes)


def test_scheduler_files_that_never_appear_are_stale_or_garbled(run_cli, tmp_path):
    garbled = tmp_path / "garbled.json"
    garbled.write_text("{not json")
    stale = tmp_path / "stale.json"
    stale.write_text(json.dumps({"type": "Scheduler", "address": "tcp://127.0.0.1:9"}))
    for args, words in [
        (["--scheduler_file", tmp_path / "never.json", "--scheduler_timeout", "0.5"],
         ["never.json: no scheduler file appeared in 0.5 s"]),
        (["--scheduler_file", garbled], ["garbled.json: not a Dask scheduler file"]),
        (["--scheduler_file", stale], ["cannot reach the Dask scheduler at tcp://127.0.0.1:9",
                                       "named by", "stale.json"]),
        (["--scheduler_file", stale, "--scheduler_address", "tcp://127.0.0.1:9"], ["not both"]),
    ]:
        for command in ([], ["experiment"]):
            assert_one_line_error(run_cli(*command, *args, "--outdir", tmp_path / "out"), *words)
    assert not (tmp_path / "out").exists()
