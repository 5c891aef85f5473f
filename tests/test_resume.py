"""Reruns: exact resume, crash safety (Ctrl-C, SIGTERM, kill -9, lost workers) and warm starts."""

import json
import os
import pickletools
import signal
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
from ribs.archives import GridArchive

from qdsearch import algorithms, tasks
from qdsearch.base import signing
from qdsearch.cli import commands
from qdsearch.config import run_config
from qdsearch.store import archive_data
from qdsearch.tasks import policies
from util import (
    LANDER,
    REFERENCE_ITERATIONS,
    assert_same_run,
    checkpoint_iteration,
    checkpoint_payload,
    folder_state,
    launch,
    read_checkpoint,
    saved_archive,
    tiny_flags,
    wait_for,
    write_checkpoint,
)

pytestmark = pytest.mark.slow  # real processes, signals, clusters: not in the quick subset

TUTORIAL_RANGES = [tasks.MEASURES[name].range for name in tasks.TUTORIAL_MEASURES]
ITERATIONS = REFERENCE_ITERATIONS  # long enough for a process to be stopped part-way


def run_flags(dask_cluster, **overrides):
    """The reference run's flags, saved every 3 iterations."""
    return tiny_flags(dask_cluster, **{"iterations": ITERATIONS, "log_every": 3, **overrides})


@pytest.mark.parametrize("stop_at", [1, 4])
def test_stopped_then_resumed_equals_uninterrupted(tmp_path, dask_cluster, reference, stop_at):
    run_dir = tmp_path / "run"
    commands.search(**run_flags(dask_cluster, iterations=stop_at), outdir=str(run_dir))
    commands.resume(str(run_dir), iterations=ITERATIONS, scheduler_address=dask_cluster.scheduler_address)

    assert_same_run(run_dir, reference)
    config = json.loads((run_dir / "config.json").read_text())
    assert config["iterations"] == ITERATIONS
    assert config["resumed"][0]["from_iteration"] == stop_at
    # the run's clock goes on from where the checkpoint left it (its rows before the stop kept)
    rows = json.loads((run_dir / "metrics.json").read_text())
    elapsed = [row["elapsed_s"] for row in rows]
    assert all(later > earlier for earlier, later in zip(elapsed, elapsed[1:])), elapsed


def launch_run(run_dir, dask_cluster):
    """The search as a real process, on the session's cluster (a signal or kill -9 is the main
    process's to survive; its own cluster would only add seconds of start-up)."""
    return launch(**run_flags(dask_cluster), outdir=run_dir)


def wait_for_checkpoint(run_dir, process, at_least):
    wait_for(lambda: checkpoint_iteration(run_dir) >= at_least, process,
             f"a checkpoint past iteration {at_least}")


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM])
def test_interrupt_keeps_a_checkpoint_and_resume_completes(tmp_path, dask_cluster, reference,
                                                            stop_signal):
    run_dir = tmp_path / "run"
    process = launch_run(run_dir, dask_cluster)
    wait_for_checkpoint(run_dir, process, at_least=3)
    process.send_signal(stop_signal)
    out, err = process.communicate(timeout=60)

    assert process.returncode == 130, err
    assert "Traceback" not in err and f"resume {run_dir}" in out
    checkpoint = read_checkpoint(run_dir / "checkpoint.pkl")
    assert 3 <= checkpoint["iteration"] < ITERATIONS
    assert [r["iteration"] for r in checkpoint["metrics"]] == list(range(1, checkpoint["iteration"] + 1))

    commands.resume(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    assert_same_run(run_dir, reference)


def test_kill_9_leaves_a_loadable_checkpoint(tmp_path, dask_cluster, reference):
    run_dir = tmp_path / "run"
    process = launch_run(run_dir, dask_cluster)
    wait_for_checkpoint(run_dir, process, at_least=6)
    os.killpg(process.pid, signal.SIGKILL)  # the search and its Dask workers, at once
    process.communicate(timeout=60)

    assert read_checkpoint(run_dir / "checkpoint.pkl")["iteration"] >= 6
    commands.resume(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    assert_same_run(run_dir, reference)


def test_a_worker_killed_mid_iteration_changes_nothing(tmp_path, dask_cluster, reference):
    from dask.distributed import Client

    killed = []

    def kill_a_busy_worker(client, stop):
        pids = client.run(os.getpid)
        while not stop.is_set():
            busy = [address for address, tasks in client.processing().items() if tasks]
            if busy:
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed.append(pids[busy[0]])
                return
            time.sleep(0.001)

    with Client(dask_cluster) as client:  # the session's cluster: its nanny restarts the worker
        stop = threading.Event()
        killer = threading.Thread(target=kill_a_busy_worker, args=(client, stop))
        killer.start()
        try:
            commands.search(**run_flags(dask_cluster), outdir=str(tmp_path / "run"))
        finally:
            stop.set()
            killer.join()
        client.wait_for_workers(2, timeout=60)  # the nanny brought the worker back
        assert killed and killed[0] not in client.run(os.getpid).values()
    assert_same_run(tmp_path / "run", reference)


def test_warm_start_from_an_archive_on_another_terrain(tmp_path, dask_cluster, reference):
    source = saved_archive(reference)
    run_dir = tmp_path / "warm"
    commands.search(**run_flags(dask_cluster, iterations=2, env_seed=7, seed=11),
              outdir=str(run_dir), from_archive=str(reference / "archive.pkl"))

    elites = source.data(["solution"])["solution"]
    env = gym.make("LunarLander-v3")
    flown = np.array([policies.rollout(solution, 7, env, env_name=LANDER) for solution in elites])
    expected = GridArchive(solution_dim=32, dims=(50, 50), ranges=TUTORIAL_RANGES)
    expected.add(elites, flown[:, 0], flown[:, 1:])

    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert [row["iteration"] for row in metrics] == [0, 1, 2]
    assert metrics[0]["evaluations"] == len(elites)
    assert metrics[0]["num_elites"] == len(expected)
    assert metrics[0]["best_objective"] == flown[:, 0].max()
    assert metrics[2]["evaluations"] == len(elites) + 2 * 12
    config = json.loads((run_dir / "config.json").read_text())
    assert config["from_archive"] == str((reference / "archive.pkl").resolve())
    for emitter in read_checkpoint(run_dir / "checkpoint.pkl")["scheduler"].emitters:
        assert np.array_equal(emitter.x0, elites[np.argmax(flown[:, 0])])


def bad_checkpoints(reference):
    """(name, writer of a checkpoint.pkl that must be refused, words the error must contain)."""
    good = read_checkpoint(reference / "checkpoint.pkl")
    small = GridArchive(solution_dim=32, dims=(10, 10), ranges=TUTORIAL_RANGES)
    other_scheduler = algorithms.build_scheduler(run_config.check_run_config(good["config"]))
    other_scheduler._archive = small
    return [
        ("truncated", lambda p: signing.write_signed(
            p, checkpoint_payload(reference / "checkpoint.pkl")[:5000]), "not a readable checkpoint"),
        ("garbage", lambda p: signing.write_signed(p, b"this is not a pickle"), "not a readable checkpoint"),
        ("plain dict", lambda p: write_checkpoint(p, {"iteration": 3}), "not a lunar_lander checkpoint"),
        ("incompatible config", lambda p: write_checkpoint(p, {**good, "config": {**good["config"],
                                                            "batch_size": 0}}), "incompatible config"),
        ("other archive shape", lambda p: write_checkpoint(p, {**good, "scheduler": other_scheduler}),
         "another shape"),
        ("unsigned", lambda p: p.write_bytes(checkpoint_payload(reference / "checkpoint.pkl")), "--trust"),
    ]


@pytest.mark.parametrize("case", range(6))
def test_bad_checkpoint_is_refused_and_the_folder_untouched(tmp_path, reference, run_cli, case):
    name, write, words = bad_checkpoints(reference)[case]
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text("[]")
    write(run_dir / "checkpoint.pkl")
    before = folder_state(run_dir)

    result = run_cli("resume", run_dir)

    assert result.returncode == 2, name
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert words in result.stderr and "checkpoint.pkl" in result.stderr, result.stderr
    assert folder_state(run_dir) == before


def test_resume_of_a_folder_without_checkpoint(tmp_path, run_cli):
    result = run_cli("resume", tmp_path)
    assert result.returncode == 2 and "no checkpoint there" in result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("content, words", [
    (None, "no such file"),
    (b"\x80\x05garbage", "not a readable"),
    ({"a": 1}, "archive data of format None"),
    (GridArchive(solution_dim=32, dims=(10, 10), ranges=TUTORIAL_RANGES), "another shape"),
    (GridArchive(solution_dim=32, dims=(50, 50), ranges=TUTORIAL_RANGES), "empty"),
])
def test_bad_warm_start_archive(tmp_path, run_cli, content, words):
    """--from_archive reads the archive.npz beside a named archive.pkl, never the pickle."""
    path, data = tmp_path / "archive.pkl", tmp_path / "archive.npz"
    if isinstance(content, bytes):
        data.write_bytes(content)
    elif isinstance(content, dict):
        np.savez(data, **content)
    elif content is not None:
        archive_data.write_archive_data(data, content, {})
    result = run_cli("--iterations", 1, "--from_archive", path, "--outdir", tmp_path / "run")
    assert result.returncode == 2 and words in result.stderr and result.stderr.count("\n") == 1
    assert not (tmp_path / "run").exists()


def as_before_the_layers(payload: bytes) -> bytes:
    """A checkpoint's pickle as the package wrote it before it had layers: the module of the
    function that rebuilds an archive's rows named qdsearch.compact_pickle, not
    qdsearch.base.compact_pickle (the stream unframed: frames only hint at sizes)."""
    out, start, renamed = [], 0, 0
    for op, arg, at in pickletools.genops(payload):
        end = at + 1 + (8 if op.name == "FRAME" else 0)
        if op.name == "FRAME":
            out.append(payload[start:at])
            start = end
        elif op.name == "SHORT_BINUNICODE" and arg == "qdsearch.base.compact_pickle":
            out.append(payload[start:at])
            old = b"qdsearch.compact_pickle"
            out.append(b"\x8c" + bytes([len(old)]) + old)
            start, renamed = at + 2 + len(arg), renamed + 1
    assert renamed == 1, renamed  # the checkpoint names the module once (memoised after)
    return b"".join(out) + payload[start:]


def test_a_checkpoint_from_before_the_package_had_layers_resumes(tmp_path, dask_cluster, reference):
    """A checkpoint names the function that rebuilds its archive's rows by its module; before the
    package had layers that module was qdsearch.compact_pickle. Such a checkpoint resumes, and the
    run ends as the uninterrupted one."""
    run_dir = tmp_path / "run"
    commands.search(**run_flags(dask_cluster, iterations=2), outdir=str(run_dir))
    payload = as_before_the_layers(checkpoint_payload(run_dir / "checkpoint.pkl"))
    assert b"qdsearch.compact_pickle" in payload and b"qdsearch.base.compact_pickle" not in payload
    signing.write_signed(run_dir / "checkpoint.pkl", payload)

    commands.resume(str(run_dir), iterations=ITERATIONS, scheduler_address=dask_cluster.scheduler_address)
    assert_same_run(run_dir, reference)
