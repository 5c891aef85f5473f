"""Faults made by hand, as a user meets them: ports where no Dask scheduler answers (a real web
server, a real silent listener), a scheduler without workers, a scheduler killed under a search,
a worker killed while the local cluster starts, absurd sizes, hand-edited config.json files,
huge addresses, over-long and dangling --outdir paths, flags given twice. Each ends in one line,
in bounded time, with nothing written that the user did not ask for; runs stopped by a lost
cluster process resume to the bits of their straight twins."""

import contextlib
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import time

import psutil  # distributed's own dependency
import pytest

from qdsearch.cli import app as ll
from qdsearch.cli import commands
from qdsearch.search import cluster
from util import (
    Result,
    assert_one_line_error,
    assert_same_run,
    checkpoint_iteration,
    folder_state,
    launch,
    small_disk,
    start_scheduler,
    start_worker,
    stop_all,
    tiny_flags,
    wait_for,
)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


SILENT = """
import socket, sys, time
server = socket.create_server(("127.0.0.1", int(sys.argv[1])))
held = []
while True:  # accepts every connection and never says a word
    held.append(server.accept()[0])
"""


@contextlib.contextmanager
def listening(kind: str):
    """A real process on a loopback port that is not a Dask scheduler: `web` (python -m
    http.server) or `silent` (accepts, never answers). Yields its tcp:// address."""
    port = free_port()
    command = ([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1"] if kind == "web"
               else [sys.executable, "-c", SILENT, str(port)])
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)
    try:
        deadline = time.time() + 30
        while time.time() < deadline:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=1):
                break
            time.sleep(0.05)
        yield f"tcp://127.0.0.1:{port}"
    finally:
        stop_all([process])


def timed(run, *args) -> tuple[Result, float]:
    start = time.monotonic()
    result = run(*args)
    return result, time.monotonic() - start


# ---- 1. peers that are not schedulers, and waits that end ------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("kind", ["web", "silent"])
def test_a_port_where_no_scheduler_answers_is_one_line_within_the_timeout(run_cli, tiny_run, tmp_path, kind):
    """By address or by scheduler file, for search, experiment and explore: one line within
    --scheduler_timeout (plus start-up), and no folder made or touched."""
    before = folder_state(tiny_run)
    with listening(kind) as address:
        scheduler_file = tmp_path / "scheduler.json"
        scheduler_file.write_text(json.dumps({"type": "Scheduler", "address": address}))
        for joined in (["--scheduler_address", address], ["--scheduler_file", scheduler_file]):
            for command in (["--iterations", 2, "--outdir", tmp_path / "out"],
                            ["experiment", "--outdir", tmp_path / "out"], ["explore", tiny_run]):
                result, took = timed(run_cli, *command, *joined, "--scheduler_timeout", 0.2)
                assert_one_line_error(result, f"{address} is not a Dask scheduler")
                assert took < 0.2 + 10, took
    assert not (tmp_path / "out").exists()
    assert folder_state(tiny_run) == before


@pytest.mark.slow
def test_the_reported_hang_is_one_line_from_a_real_process(run_process, tmp_path):
    """The report's own command: a scheduler file naming a web server (its --scheduler_timeout 10
    made 3: the wait is the same code whatever its length)."""
    with listening("web") as address:
        scheduler_file = tmp_path / "scheduler.json"
        scheduler_file.write_text(json.dumps({"address": address}))
        result, took = timed(run_process, "--scheduler_file", scheduler_file, "--scheduler_timeout", 3,
                             "--iterations", 2, "--outdir", tmp_path / "X")
    assert_one_line_error(Result(result.returncode, result.stdout, result.stderr), "is not a Dask scheduler",
                          "no answer in 3 s")
    assert took < 3 + 15, took
    assert not (tmp_path / "X").exists()


def catches_sigterm(pid: int) -> bool:
    """Whether the process has its own SIGTERM handler yet (main installs the stop handlers first
    thing; a signal before that would end it as an unprepared process would end)."""
    with open(f"/proc/{pid}/status") as status:
        caught = next(line for line in status if line.startswith("SigCgt:")).split()[1]
    return bool(int(caught, 16) >> (signal.SIGTERM - 1) & 1)


def said_so_far(process, words: str, timeout: float = 60) -> str:
    """The process's stderr up to the first chunk that holds `words` (read from its pipe as it
    comes, so that communicate() later reads the rest)."""
    pipe, read, deadline = process.stderr.fileno(), b"", time.time() + timeout
    while words.encode() not in read:
        if time.time() > deadline or process.poll() is not None:
            raise AssertionError(f"never saw {words!r}: {read.decode()!r}")
        if select.select([pipe], [], [], 0.1)[0]:
            read += os.read(pipe, 4096)
    return read.decode()


@pytest.mark.slow
def test_ctrl_c_and_sigterm_stop_every_wait(tmp_path):
    """Waiting on a silent port's handshake, on workers that never come, or on a scheduler file
    that never appears: SIGTERM or Ctrl-C ends the command at once, with nothing written."""
    scheduler, scheduler_file = start_scheduler(tmp_path / "no-workers")
    processes = [scheduler]
    try:
        with listening("silent") as address:
            waiting = {launch(iterations=2, outdir=tmp_path / "out", **flags): (signum, said)
                       for flags, signum, said in [  # all at once
                           ({"scheduler_address": address, "scheduler_timeout": 60}, signal.SIGTERM, ""),
                           ({"scheduler_file": scheduler_file}, signal.SIGINT, "waiting for workers at"),
                           ({"scheduler_file": tmp_path / "never.json"}, signal.SIGTERM,
                            "waiting for the scheduler file")]}
            processes += waiting
            for process in waiting:
                wait_for(lambda pid=process.pid: catches_sigterm(pid), process, "the stop handlers installed")
            # into the waits: each that says so once it has waited a second, the silent port's at once
            before = {process: said_so_far(process, said) if said else ""
                      for process, (_, said) in waiting.items()}
            time.sleep(1)
            for process, (signum, _) in waiting.items():
                assert process.poll() is None
                process.send_signal(signum)
            for process, (_, said) in waiting.items():
                out, err = process.communicate(timeout=15)
                err = before[process] + err
                assert process.returncode == 130, err
                assert "Traceback" not in err and err.strip().splitlines()[-1] == "stopped", err
                assert said in err
            assert not (tmp_path / "out").exists()
    finally:
        stop_all(processes)


@pytest.mark.slow
def test_a_scheduler_without_workers_says_it_waits_and_ends_or_goes_on_when_one_joins(
        tmp_path, run_cli, dask_cluster):
    scheduler, scheduler_file = start_scheduler(tmp_path / "cluster")  # --no-dashboard
    processes = [scheduler]
    try:
        result, took = timed(run_cli, "--scheduler_file", scheduler_file, "--worker_timeout", 0.5,
                             "--outdir", tmp_path / "out")
        assert result.returncode == 2 and took < 0.5 + 10, (took, result.stderr)
        waiting, error = result.stderr.strip().splitlines()
        assert waiting.startswith("waiting for workers at tcp://127.0.0.1:") and "--worker_timeout" in waiting
        assert error.startswith("error: no worker joined the Dask scheduler") and "Traceback" not in error
        assert not (tmp_path / "out").exists()

        flags = tiny_flags(iterations=2, log_every=2)
        search = launch(**{k: v for k, v in flags.items() if k != "workers"},
                        scheduler_file=scheduler_file, outdir=tmp_path / "run")
        processes.append(search)
        said = search.stderr.readline()  # its first line (the end of its output if it has ended)
        assert said.startswith("waiting for workers at tcp://127.0.0.1:"), said
        assert search.poll() is None and not (tmp_path / "run").exists()  # waiting, nothing written
        processes.append(start_worker(scheduler_file, tmp_path / "worker"))
        out, err = search.communicate(timeout=120)
        assert search.returncode == 0, err
        log = (tmp_path / "run" / "run.log").read_text()
        assert "1 worker(s); no dashboard" in log and ":8787" not in log  # it has none
        commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "twin"))
        assert_same_run(tmp_path / "run", tmp_path / "twin")
    finally:
        stop_all(processes)


def test_scheduler_files_that_are_folders_or_empty_are_refused_at_once(run_cli, tmp_path):
    for named, words in [(tmp_path, "is a folder, not a scheduler file"), ("", "--scheduler_file is empty"),
                         ("  ", "--scheduler_file is empty")]:
        result, took = timed(run_cli, "--scheduler_file", named, "--scheduler_timeout", 60,
                             "--outdir", tmp_path / "out")
        assert_one_line_error(result, words)
        assert took < 10, took
    assert not (tmp_path / "out").exists()


# ---- 2. lost cluster processes ------------------------------------------------------------------

@pytest.mark.slow
def test_a_search_whose_scheduler_dies_says_so_in_one_line_and_resumes_to_its_twin(
        tmp_path, dask_cluster):
    flags = tiny_flags(iterations=20, log_every=2, seed=11)
    scheduler, scheduler_file = start_scheduler(tmp_path / "first")
    processes = [scheduler, start_worker(scheduler_file, tmp_path / "w0")]
    run_dir = tmp_path / "run"
    try:
        search = launch(**{k: v for k, v in flags.items() if k != "workers"},
                        scheduler_file=scheduler_file, outdir=run_dir)
        processes.append(search)
        wait_for(lambda: checkpoint_iteration(run_dir) >= 2, search, "the search past iteration 2")
        os.killpg(scheduler.pid, signal.SIGKILL)  # its job preempted
        (out, err), took = timed(search.communicate, 180)
        assert_one_line_error(Result(search.returncode, out, err), "lost the Dask scheduler",
                              "(its connection closed)", f"resume {run_dir} --scheduler_file", code=1)
        assert took < cluster.HANDSHAKE_TIMEOUT, took  # said at once, not after Dask's reconnection
        held = checkpoint_iteration(run_dir)
        assert 2 <= held < 20 and f"its checkpoint holds iteration {held}" in err
    finally:
        stop_all(processes)
    assert ll.main(["resume", str(run_dir), "--scheduler_address", dask_cluster.scheduler_address]) == 0
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "twin"))
    assert_same_run(run_dir, tmp_path / "twin")


@pytest.mark.slow
def test_a_results_command_whose_scheduler_dies_says_so_in_one_line(tmp_path, tiny_run, monkeypatch):
    """evaluate, flying many terrains on a real cluster when its scheduler is killed: one line,
    exit code 1, and no half-written results."""
    from dask.distributed import Client

    monkeypatch.setenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "5s")
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    scheduler, scheduler_file = start_scheduler(tmp_path / "cluster")
    processes = [scheduler, start_worker(scheduler_file, tmp_path / "w0")]
    try:
        evaluate = launch("evaluate", run_dir, env_seeds="0-1999", scheduler_file=scheduler_file)
        processes.append(evaluate)
        with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
            def flown() -> int:
                return sum(client.run(lambda dask_worker: dask_worker.state.executed_count).values())
            wait_for(lambda: flown() > 0, evaluate, "the first flights done")
        os.killpg(scheduler.pid, signal.SIGKILL)
        out, err = evaluate.communicate(timeout=180)
    finally:
        stop_all(processes)
    assert_one_line_error(Result(evaluate.returncode, out, err), "lost the Dask scheduler", code=1)
    assert not (run_dir / "robustness.csv").exists()


@pytest.mark.slow
def test_a_worker_killed_while_the_local_cluster_starts_is_started_again_and_the_run_ends_exactly(
        tmp_path, dask_cluster):
    """SIGKILL to the first worker process as soon as it is spawned, before its nanny is up."""
    flags = tiny_flags(iterations=4, log_every=2, seed=5)
    run_dir = tmp_path / "run"
    search = launch(**flags, outdir=run_dir)
    killed = None
    try:
        deadline = time.time() + 60
        while killed is None and time.time() < deadline and search.poll() is None:
            for child in psutil.Process(search.pid).children(recursive=True):
                with contextlib.suppress(psutil.Error):
                    if "spawn_main" in " ".join(child.cmdline()) and "resource_tracker" not in " ".join(
                            child.cmdline()):
                        child.kill()
                        killed = child.pid
                        break
            time.sleep(0.005)
        out, err = search.communicate(timeout=180)
    finally:
        stop_all([search])
    assert killed is not None
    assert search.returncode == 0 and "Traceback" not in err, err
    assert "a worker process failed while the local cluster started" in (run_dir / "run.log").read_text()
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "twin"))
    assert_same_run(run_dir, tmp_path / "twin")


# ---- 3. sizes -----------------------------------------------------------------------------------

@pytest.mark.parametrize("args, words", [
    (["--batch_size", 1_000_000_000], "--batch_size must be at most 100,000"),
    (["--n_emitters", 10**12], "--n_emitters must be at most 10,000"),
    (["--iterations", 99999999999999999999999], "--iterations must be at most 1,000,000"),
    (["--n_emitters", 100, "--batch_size", 5000], "asks 500,000 solutions per iteration; at most 100,000"),
    (["--batch_size", 2000, "--env_seed", "0-9999"], "rollouts per iteration; at most 10,000,000"),
    (["--grid", 1000, "--measures", "impact_x,impact_y_velocity,fuel"], "cells; at most 1,000,000"),
    (["--workers", 10**9], "--workers must be at most 1,024"),
    (["experiment", "--batch_size", "[30, 1000000000]"], "--batch_size must be at most 100,000"),
    (["experiment", "--n_emitters", "[5, 100]", "--batch_size", 5000], "solutions per iteration"),
])
def test_every_size_is_bounded_before_anything_is_written(run_cli, tmp_path, args, words):
    assert_one_line_error(run_cli(*args, "--outdir", tmp_path / "out"), words)
    assert not (tmp_path / "out").exists()


def test_the_reported_allocation_is_one_line_from_a_real_process(run_process, tmp_path):
    for args in (["--batch_size", 1_000_000_000], ["experiment", "--batch_size", 1_000_000_000]):
        result = run_process(*args, "--outdir", tmp_path / "out")
        assert_one_line_error(Result(result.returncode, result.stdout, result.stderr),
                              "--batch_size must be at most 100,000")
    assert not (tmp_path / "out").exists()


def test_resume_refuses_a_config_edited_to_an_absurd_size(run_cli, tiny_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, "batch_size": 1_000_000_000}))
    before = folder_state(run_dir)
    assert_one_line_error(run_cli("resume", run_dir), "--batch_size must be at most 100,000")
    assert folder_state(run_dir) == before


# ---- 4. config.json edited by hand -------------------------------------------------------------

COMMANDS = [["resume"], ["elites"], ["video", "--best"], ["trajectories", "--best"], ["explore"],
            ["evaluate", "--env_seeds", "1"], ["compare"]]


@pytest.mark.parametrize("field, value, words", [
    ("env", None, "--env is null"), ("env_seed", None, "--env_seed is null"),
    ("grid", None, "--grid is null"), ("measures", 7, "--measures takes 1 to 10"),
    ("outdir", 3, "--outdir is 3, not a path"), ("resumed", "yes", "resumed is 'yes'"),
])
def test_every_command_refuses_a_config_with_a_wrong_type(run_cli, tiny_run, tmp_path, field, value, words):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, field: value}))
    before = folder_state(run_dir)
    for command in COMMANDS:
        result = run_cli(command[0], run_dir, *command[1:])
        assert_one_line_error(result, words)
    assert folder_state(run_dir) == before


@pytest.fixture(scope="module")
def walker_run(tmp_path_factory, dask_cluster):
    run_dir = tmp_path_factory.mktemp("walker") / "run"
    commands.search(**tiny_flags(dask_cluster, env="BipedalWalker-v3", iterations=1, batch_size=3,
                                 log_every=1),
              outdir=str(run_dir))
    return run_dir


def test_results_commands_refuse_a_config_edited_to_a_task_of_the_same_shape(run_cli, walker_run, tmp_path):
    """Walker to hardcore: the archive fits both; archive.npz's own config (resume: the
    checkpoint's) says which ran."""
    run_dir = tmp_path / "run"
    shutil.copytree(walker_run, run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, "env": "BipedalWalkerHardcore-v3"}))
    before = folder_state(run_dir)
    for command in COMMANDS:
        assert_one_line_error(run_cli(command[0], run_dir, *command[1:]),
                              "says --env 'BipedalWalkerHardcore-v3' but the run's ",
                              "ran with 'BipedalWalker-v3'")  # its archive.npz, or resume's checkpoint
    assert folder_state(run_dir) == before


# ---- 5-8. huge addresses, long and dangling folders, flags given twice, read-only runs -----------

def test_a_huge_address_is_cut_in_its_one_line(run_cli, tmp_path):
    address = "tcp://" + "x" * 10_000_000
    scheduler_file = tmp_path / "scheduler.json"
    scheduler_file.write_text(json.dumps({"address": address}))
    for joined in (["--scheduler_address", address], ["--scheduler_file", scheduler_file]):
        result = run_cli(*joined, "--outdir", tmp_path / "out")
        assert_one_line_error(result, "cannot reach the Dask scheduler at tcp://xxx")
        assert len(result.stderr) < 1000, len(result.stderr)
    assert not (tmp_path / "out").exists()


def test_an_outdir_that_cannot_be_made_leaves_no_parent_behind(run_cli, tmp_path):
    assert_one_line_error(run_cli("--outdir", tmp_path / "a" / "b" / ("x" * 300)), "File name too long")
    assert not (tmp_path / "a").exists()


def test_a_dangling_symlink_outdir_is_refused_by_what_it_is(run_cli, tmp_path):
    (tmp_path / "link").symlink_to(tmp_path / "nowhere")
    assert_one_line_error(run_cli("--outdir", tmp_path / "link"), "is a symbolic link to",
                          "which does not exist")
    assert not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize("args", [["--env", "LunarLander-v3", "--env", "BipedalWalker-v3"],
                                  ["--seed=1", "--seed", "2"], ["experiment", "--seeds", "1", "--seeds=2"]])
def test_a_flag_given_twice_is_refused(run_cli, tmp_path, args):
    assert_one_line_error(run_cli(*args, "--outdir", tmp_path / "out"), "is given twice")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_results_commands_refuse_a_read_only_run_alike_before_flying(tiny_run, tmp_path, run_cli):
    with small_disk(tmp_path, "8m") as disk:
        run_dir = disk / "run"
        shutil.copytree(tiny_run, run_dir)
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        for command in (["video", "--best"], ["trajectories", "--best"], ["explore"],
                        ["evaluate", "--env_seeds", "0-999"]):
            result, took = timed(run_cli, command[0], run_dir, *command[1:])
            assert_one_line_error(result, "cannot write in")
            assert took < 10, (command, took)  # 1,000 terrains per elite were not flown first
