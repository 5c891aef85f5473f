"""Clusters as HPC jobs start them: `dask scheduler --scheduler-file` and `dask worker
--scheduler-file` processes started from the command line, in folders without our code; workers
that join late, retire (SIGTERM, --lifetime) or are killed while an experiment runs; a scheduler
that dies; and a scheduler file that appears late, never, stale or garbled."""

import json
import os
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from dask.distributed import Client

from qdsearch.cli import commands
from qdsearch.search import experiments
from qdsearch.search.engine import ClusterShare
from util import (
    Result,
    assert_one_line_error,
    checkpoint_iteration,
    launch,
    run_archive,
    run_metrics,
    slowed,
    slowed_once,
    start_scheduler,
    start_worker,
    stop_all,
    tiny_flags,
    wait_for,
)

pytestmark = pytest.mark.slow  # real scheduler and worker processes

# Runs that must still fly while workers come and go, or when their cluster fails, are held to a
# twentieth of their time (util.slowed, HELD) while they wait for it: short runs that write their
# data alone (what they are compared by) outlast it without pictures drawn to pass the time (the
# workers' comings and goings ended by iteration 12 of 24 with the other core busy, 2026-11-29).
# Their first checkpoint is at iteration 2.
HELD = 0.05
LONG_RUNS = dict(algorithms="cma_me", seeds="1-2", iterations=24, n_emitters=2, batch_size=6, log_every=2,
                 pictures=False)
SHORT_RUNS = dict(LONG_RUNS, iterations=12)


def fly_twins(root, cluster, runs: dict) -> dict:
    """Each run of `runs` flown alone by `search` on the session's cluster, by seed (saved once,
    at its end: only the end is compared)."""
    flags = {k: v for k, v in runs.items() if k not in ("algorithms", "seeds")}
    for seed in (1, 2):
        commands.search(**tiny_flags(cluster, **flags, seed=seed) | {"log_every": runs["iterations"]},
                   outdir=str(root / str(seed)))
    return {seed: root / str(seed) for seed in (1, 2)}


@pytest.fixture(scope="module")
def long_twins(tmp_path_factory, dask_cluster):
    return fly_twins(tmp_path_factory.mktemp("long_twins"), dask_cluster, LONG_RUNS)


@pytest.fixture(scope="module")
def short_twins(tmp_path_factory, dask_cluster):
    return fly_twins(tmp_path_factory.mktemp("short_twins"), dask_cluster, SHORT_RUNS)


def plan_of(folder):
    """The experiment's plan with its runs' states, as every command reads it."""
    return experiments.read_experiment(folder)


def assert_runs_equal_their_twins(folder, twins):
    for entry in plan_of(folder)["runs"]:
        assert entry["state"] == "done"
        assert run_archive(folder / entry["name"]).equals(run_archive(twins[entry["seed"]]))
        assert run_metrics(folder / entry["name"]) == run_metrics(twins[entry["seed"]])


def executed(client, worker: str) -> int:
    """Tasks the worker has run."""
    return client.run(lambda dask_worker: dask_worker.state.executed_count, workers=[worker])[worker]


def experiment_under_way(folder, scheduler_file, processes, runs):
    """The experiment of `runs` as a process joining the scheduler file's cluster, once both runs
    are past iteration 2 (it is added to `processes`)."""
    experiment = launch("experiment", **runs, outdir=folder, scheduler_file=scheduler_file)
    processes.append(experiment)
    wait_for(lambda: (folder / "experiment.json").exists() and all(
        checkpoint_iteration(folder / entry["name"]) >= 2 for entry in plan_of(folder)["runs"]),
        experiment, "both runs past iteration 2")
    return experiment


def test_workers_that_join_retire_and_die_then_a_lost_scheduler_change_nothing(tmp_path, long_twins):
    """An experiment on a cluster started by hand: workers join late, retire and die while it
    flies; then its scheduler dies (its job preempted), and resume, started before the new
    scheduler is, waits for its file and finishes the runs as their lone twins."""
    scheduler, scheduler_file = start_scheduler(tmp_path / "elsewhere")
    processes = [scheduler, start_worker(scheduler_file, tmp_path / "w0")]
    folder = tmp_path / "exp"
    try:
        experiment = experiment_under_way(folder, scheduler_file, processes, LONG_RUNS)
        with slowed(experiment, share=HELD):
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
            os.killpg(scheduler.pid, signal.SIGKILL)  # then its job is preempted
        out, err = experiment.communicate(timeout=180)
        assert_one_line_error(Result(experiment.returncode, out, err), "lost the Dask scheduler",
                              f"resume {folder} --scheduler_file", code=1)
        held = {entry["name"]: checkpoint_iteration(folder / entry["name"])
                for entry in plan_of(folder)["runs"]}
        assert {entry["state"] for entry in plan_of(folder)["runs"]} == {"stopped"}, plan_of(folder)["runs"]
        assert all(iteration >= 2 for iteration in held.values())

        # resume is started before the new scheduler exists: it waits for the file, and says so
        second = tmp_path / "second" / "scheduler.json"
        resumed = launch("resume", folder, scheduler_file=second)
        processes.append(resumed)
        said = resumed.stderr.readline()  # its first line (the end of its output if it has ended)
        assert said.startswith(f"waiting for the scheduler file {second} to appear"), said
        new_scheduler, _ = start_scheduler(second.parent)
        processes += [new_scheduler, start_worker(second, tmp_path / "w4")]
        out, err = resumed.communicate(timeout=300)
        assert resumed.returncode == 0, err
        assert_runs_equal_their_twins(folder, long_twins)
        told = sum(LONG_RUNS["iterations"] - iteration for iteration in held.values())
        assert plan_of(folder)["timing"]["iterations"] == told
    finally:
        stop_all(processes)


def test_a_scheduler_lost_while_asked_its_workers_leaves_the_chunks_their_last_count(tmp_path):
    """The driver asks the scheduler its worker threads every few seconds (ClusterShare) to size a
    batch's chunks. A scheduler that dies while that question is in flight must not fail the run
    whose batch was being sized: the driver reports the loss as a whole (the test above). With a
    question at every batch, that race failed a run in 3 of 12 losses."""
    scheduler, scheduler_file = start_scheduler(tmp_path)
    processes = [scheduler, start_worker(scheduler_file, tmp_path / "w0")]
    try:
        with Client(scheduler_file=str(scheduler_file), timeout="5s") as client, \
                ThreadPoolExecutor(1) as pool:
            client.wait_for_workers(1)
            share = ClusterShare(client, every=0.0)
            assert share(2) == (1, 2)
            os.kill(scheduler.pid, signal.SIGSTOP)  # the next question waits for its answer
            asking = pool.submit(share, 2)
            time.sleep(0.5)
            assert not asking.done()
            os.kill(scheduler.pid, signal.SIGKILL)  # its connection breaks under the question
            assert asking.result(timeout=60) == (1, 2)
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
        (["--scheduler_file", garbled, "--scheduler_timeout", "0.2"],
         ["garbled.json: not a Dask scheduler file"]),
        (["--scheduler_file", stale], ["cannot reach the Dask scheduler at tcp://127.0.0.1:9",
                                       "named by", "stale.json"]),
        (["--scheduler_file", stale, "--scheduler_address", "tcp://127.0.0.1:9"], ["not both"]),
    ]:
        for command in ([], ["experiment"]):
            assert_one_line_error(run_cli(*command, *args, "--outdir", tmp_path / "out"), *words)
    assert not (tmp_path / "out").exists()


def part_state(folder, part, parts=2):
    return json.loads((folder / "parts" / f"{part}_of_{parts}" / "state.json").read_text())


def test_a_split_experiment_on_two_schedulers_ends_as_its_lone_twins_after_a_worker_and_a_scheduler_die(
        tmp_path, short_twins):
    """Two parts, each its own process and `dask scheduler`, as two elements of a SLURM array:
    part 1 loses its worker (a new one joins), part 2 its scheduler (resumed on a new one)."""
    folder, processes = tmp_path / "exp", []
    try:
        files = {}
        for part in (1, 2):
            scheduler, files[part] = start_scheduler(tmp_path / f"scheduler{part}")
            processes += [scheduler, start_worker(files[part], tmp_path / f"w{part}")]
        schedulers, first_worker = {1: processes[0], 2: processes[2]}, processes[1]
        parts = {part: launch("experiment", **SHORT_RUNS, outdir=folder, part=f"{part}/2",
                              scheduler_file=files[part]) for part in (1, 2)}
        processes += parts.values()
        wait_for(lambda: (folder / "experiment.json").exists(), parts[1], "the plan")
        names = {part: plan_of(folder)["runs"][part - 1]["name"] for part in (1, 2)}
        under_way = {parts[part]: lambda name=names[part]: checkpoint_iteration(folder / name) >= 2
                     for part in (1, 2)}  # run i belongs to part i mod 2 + 1: one run each
        with slowed_once(under_way, "both parts past iteration 2"):
            os.killpg(first_worker.pid, signal.SIGKILL)  # part 1's worker dies; another joins
            os.killpg(schedulers[2].pid, signal.SIGKILL)  # part 2's scheduler dies
        processes.append(start_worker(files[1], tmp_path / "w1b"))
        out, err = parts[2].communicate(timeout=180)
        assert_one_line_error(Result(parts[2].returncode, out, err), "lost the Dask scheduler",
                              f"resume {folder} --part 2/2 --scheduler_file", code=1)
        assert part_state(folder, 2)["runs"] == {names[2]: {"state": "stopped"}}
        new_scheduler, new_file = start_scheduler(tmp_path / "scheduler2b")
        processes += [new_scheduler, start_worker(new_file, tmp_path / "w2b")]
        resumed = launch("resume", folder, part="2/2", scheduler_file=new_file)
        processes.append(resumed)
        for process in (parts[1], resumed):
            out, err = process.communicate(timeout=300)
            assert process.returncode == 0, err
        assert_runs_equal_their_twins(folder, short_twins)  # experiment.json's plan with the parts' states
        assert [part_state(folder, part)["runs"] for part in (1, 2)] == [
            {names[1]: {"state": "done"}}, {names[2]: {"state": "done"}}]
        assert len(part_state(folder, 2)["drives"]) == 2
        assert {entry["state"] for entry in json.loads((folder / "experiment.json").read_text())["runs"]} == {
            "pending"}  # the plan, written once, by one part
    finally:
        stop_all(processes)


@pytest.mark.parametrize("script", ["slurm.sbatch", "slurm_parts.sbatch"])
def test_the_slurm_scripts_start_dask_at_the_local_clusters_pace(script):
    """The batch scripts export, for the scheduler and workers they start, the settings a search's
    own local cluster runs with (cluster.QUIET_ENVIRONMENT), and no other Dask setting."""
    from conftest import ROOT
    from qdsearch.search.cluster import QUIET_ENVIRONMENT

    lines = (ROOT / "docs" / script).read_text().splitlines()
    exported = dict(line.removeprefix("export ").split("=", 1) for line in lines
                    if line.startswith("export DASK_"))
    assert exported == QUIET_ENVIRONMENT
    assert not any("DASK_" in line for line in lines if not line.startswith(("export DASK_", "#")))
    first_dask = next(i for i, line in enumerate(lines) if "dask scheduler" in line)
    assert max(i for i, line in enumerate(lines) if line.startswith("export DASK_")) < first_dask


def test_a_future_that_fails_to_release_itself_after_its_client_closed_prints_nothing(capsys):
    """A Dask future collected after its client has closed whose release fails printed "Exception
    ignored in: Future.__del__" and a traceback after an experiment's SIGTERM (once in the suite;
    such faults are reported without a reproducer: dask/distributed#4305, #8500). Here the future
    lacks what its release reads, as one whose construction was cut short would. The commands'
    quiet (cluster.quiet_dask_logs) keeps it off the terminal, and only it: another object's fault
    in `__del__` still prints."""
    import gc
    import logging

    from dask.distributed import LocalCluster

    from qdsearch.search.cluster import quiet_dask_logs

    class Faulty:
        def __del__(self):
            raise ValueError("a fault of our own")

    def collected_after_close(client) -> str:
        futures = [client.submit(sum, [1, i]) for i in range(2)]
        client.gather(futures)
        client.close()
        for future in futures:
            del future._cleared  # its release raises AttributeError
        del future, futures
        gc.collect()
        return capsys.readouterr().err

    hook = sys.unraisablehook
    try:
        with LocalCluster(n_workers=1, processes=False, dashboard_address=None,
                          silence_logs=logging.ERROR) as cluster:
            sys.unraisablehook = sys.__unraisablehook__
            assert "Future.__del__" in collected_after_close(Client(cluster))  # the fault is real
            quiet_dask_logs()
            assert collected_after_close(Client(cluster)) == ""
            Faulty()
            assert "a fault of our own" in capsys.readouterr().err
    finally:
        sys.unraisablehook = hook
