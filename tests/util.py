"""Helpers shared by the tests: the tiny run's flags, reading run folders, comparing runs, real
processes, Dask clusters started as a search and an HPC job start them (local_cluster, by_hand),
the one-line error check, policies that land and hover, a small real disk, and the explorer
page's data."""

import contextlib
import dataclasses
import json
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

LANDER = "LunarLander-v3"  # the tutorial's task: what the lander-only tests fly

# A seconds-long search: 3 iterations of 2 emitters x 6 policies, saved at its end, its data alone
# (a save's two pictures cost ~0.2 s of CPU each: a test that looks at them asks for them).
TINY = dict(iterations=3, workers=2, seed=7, env_seed=52, algorithm="cma_me", n_emitters=2,
            sigma0=1.0, batch_size=6, log_every=3, pictures=False)
REFERENCE_ITERATIONS = 12  # the uninterrupted run that stopped-and-resumed runs must equal
# Tiny runs of the walkers and robots fly episodes of this many steps (--episode_length), not their
# tasks' 1,000-2,000: a fortieth of the time or less, and nothing a test checks needs a long walk (the tasks'
# own episodes are checked by the hand-made traces). A test that flies a tiny run's elite by hand
# makes its env with `tiny_env`. The landers keep their own episodes (most end in a crash or a
# landing well before their limit).
TINY_EPISODE = 25


def tiny_episode(env_name: str):
    """The episode rules of a tiny run of `env_name`."""
    from qdsearch import tasks
    from qdsearch.tasks import lander

    task = tasks.ENVIRONMENTS[env_name]
    own = task.family is lander.LANDER or task.function is not None  # a function has no episode
    return tasks.Episode(None if own else TINY_EPISODE)


def tiny_env(env_name: str):
    """The env a tiny run of `env_name` flies in."""
    from qdsearch import tasks

    return tasks.make_env(env_name=env_name, episode=tiny_episode(env_name))


def tiny_flags(cluster=None, **overrides) -> dict:
    """Keyword arguments of `search` for a tiny run, on `cluster` (a LocalCluster) if given; a
    task whose archive is a CVT gets 32 cells (k-means makes 1,024 in seconds); a walker's or a
    robot's episodes last TINY_EPISODE steps."""
    from qdsearch import tasks

    address = {} if cluster is None else {"scheduler_address": cluster.scheduler_address}
    flags = {**TINY, **address, **overrides}
    env_name = flags.get("env", tasks.DEFAULT_ENV)
    length = tiny_episode(env_name).length if env_name in tasks.ENVIRONMENTS else None
    flags = {"episode_length": length, **flags} if length else flags
    cvt = (flags.get("archive") or tasks.ENVIRONMENTS[env_name].archive) == "cvt"
    return {"cells": 32, **flags} if cvt else flags


def load_pickle(path):
    with open(path, "rb") as file:
        return pickle.load(file)


def checkpoint_payload(path) -> bytes:
    """A checkpoint's pickle: its bytes after the signature's header (qdsearch/base/signing.py), if it
    has one."""
    from qdsearch.base import signing

    data = Path(path).read_bytes()
    return data[len(signing.MAGIC) + signing.DIGITS + 1:] if data.startswith(signing.MAGIC) else data


def read_checkpoint(path):
    """A checkpoint.pkl unpickled, its signature stripped unchecked (the tests read their own)."""
    return pickle.loads(checkpoint_payload(path))


def write_checkpoint(path, checkpoint) -> None:
    """A checkpoint (any object) pickled and signed with the tests' key, as a run writes one."""
    from qdsearch.base import signing

    signing.write_signed_pickle(Path(path), checkpoint)


def archive_table(archive) -> pd.DataFrame:
    """An archive's contents in a fixed row order, for exact comparisons. (DDS's density archive
    keeps no elites: its contents are the reservoir of measures its KDE is built on.)"""
    if hasattr(archive, "buffer"):
        return pd.DataFrame(archive.buffer)
    return archive.data(return_type="pandas").sort_values("index").reset_index(drop=True)


def saved_archive(run_dir: Path, name: str = "archive"):
    """A run folder's archive as the commands read it: its archive.npz (or corrected_archive.npz),
    made back into the pyribs archive (a run writes archive.pkl only with --archive_pkl)."""
    from qdsearch.store.archive_data import read_archive_data

    return read_archive_data(Path(run_dir) / f"{name}.npz")[0]


def run_archive(run_dir: Path) -> pd.DataFrame:
    return archive_table(saved_archive(Path(run_dir)))


def run_metrics(run_dir: Path) -> list[dict]:
    """metrics.json without the timings, which differ between any two runs."""
    rows = json.loads((Path(run_dir) / "metrics.json").read_text())
    return [{k: v for k, v in row.items() if k != "elapsed_s"} for row in rows]


def assert_same_run(run_dir: Path, reference: Path) -> None:
    """Same archive, same metrics row by row, and the emitters' next proposals are the same too."""
    assert run_archive(run_dir).equals(run_archive(reference))
    assert run_metrics(run_dir) == run_metrics(reference)
    iterations = [row["iteration"] for row in run_metrics(reference)]
    assert [row["iteration"] for row in run_metrics(run_dir)] == iterations
    schedulers = [read_checkpoint(Path(d) / "checkpoint.pkl")["scheduler"] for d in (run_dir, reference)]
    assert np.array_equal(schedulers[0].ask(), schedulers[1].ask())


def folder_state(path: Path) -> dict:
    """Every file below `path` with its bytes: to check that a failed command touched nothing."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(Path(path).rglob("*")) if p.is_file()}


@dataclasses.dataclass
class Result:
    """What a command left: its exit code, stdout and stderr."""

    returncode: int
    stdout: str
    stderr: str


def assert_one_line_error(result: Result, *fragments: str, code: int = 2) -> None:
    """Exit code `code` (2: bad input, 1: a fault) and one line of error, holding every fragment,
    with no traceback. It is the last line printed: a search's progress bar may precede it."""
    assert result.returncode == code, result.stderr
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error: ") and "Traceback" not in result.stderr, result.stderr
    assert sum(line.startswith("error: ") for line in lines) == 1, result.stderr
    if code == 2:  # refused before any work: nothing else was printed
        assert len(lines) == 1, result.stderr
    for fragment in fragments:
        assert fragment in lines[-1], lines[-1]


def launch(*args, **flags):
    """The script as a real process in a session of its own (so a test can kill its whole group)."""
    from conftest import SCRIPT

    return subprocess.Popen([sys.executable, str(SCRIPT), *map(str, args),
                             *[f"--{k}={v}" for k, v in flags.items()]],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def wait_for(condition, process, what, timeout=120):
    """Poll `condition` until it holds; fail with the process's output if it ends first."""
    deadline = time.time() + timeout
    while time.time() < deadline and process.poll() is None:
        if condition():
            return
        time.sleep(0.01)
    raise AssertionError(f"never saw {what}: {process.communicate()}")


@contextlib.contextmanager
def slowed(*processes: subprocess.Popen, share: float = 0.1, period: float = 0.25):
    """While the block runs, `processes` run a `share` of each `period` and are stopped the rest
    (SIGSTOP and SIGCONT, as cpulimit holds a process down): runs that must outlast what a test
    waits for (workers joining, retiring, dying) need not be long, nor burn CPU to pass the time."""
    done = threading.Event()

    def signal_each(sent: signal.Signals) -> None:
        for process in processes:
            process.send_signal(sent)  # nothing once the process has ended

    def hold() -> None:
        while not done.is_set():
            signal_each(signal.SIGSTOP)
            done.wait(period * (1 - share))
            signal_each(signal.SIGCONT)
            done.wait(period * share)

    holder = threading.Thread(target=hold, daemon=True)
    holder.start()
    try:
        yield
    finally:
        done.set()
        holder.join()
        signal_each(signal.SIGCONT)


@contextlib.contextmanager
def slowed_once(under_way: dict, what: str, share: float = 0.1, timeout: float = 120):
    """Waits until each process's condition in `under_way` holds, and slows each (`slowed`) from the
    moment its own holds until the block ends: processes that must all be under way at once, one
    of which alone would be done before another has started."""
    with contextlib.ExitStack() as held:
        waiting, deadline = dict(under_way), time.time() + timeout
        while waiting:
            for process, condition in list(waiting.items()):
                if condition():
                    held.enter_context(slowed(process, share=share))
                    del waiting[process]
                elif process.poll() is not None or time.time() > deadline:
                    raise AssertionError(f"never saw {what}: {process.communicate(timeout=60)}")
            time.sleep(0.01)
        yield


def checkpoint_iteration(run_dir: Path) -> int:
    """The iteration of a run folder's checkpoint, -1 while there is none (or it is being replaced)."""
    try:
        return read_checkpoint(Path(run_dir) / "checkpoint.pkl")["iteration"]
    except (OSError, EOFError, pickle.UnpicklingError):
        return -1


def assert_killed_then_resumed_as_its_twin(tmp_path: Path, cluster, one_worker, flags: dict) -> None:
    """A search of `flags` (a tiny run's) killed with kill -9 past its checkpoint of iteration 3,
    then resumed on `one_worker`'s single worker, ends bit for bit as its twin that never stopped
    on `cluster`."""
    import signal

    from qdsearch.cli import commands

    commands.search(**tiny_flags(cluster, **flags), outdir=str(tmp_path / "twin"))
    run_dir = tmp_path / "killed"
    process = launch(**{**tiny_flags(cluster, **flags), "outdir": run_dir})
    wait_for(lambda: checkpoint_iteration(run_dir) >= 3, process, "a checkpoint past iteration 3")
    os.killpg(process.pid, signal.SIGKILL)
    process.communicate(timeout=60)
    assert 3 <= checkpoint_iteration(run_dir) < flags["iterations"]
    commands.resume(str(run_dir), scheduler_address=one_worker.scheduler_address)
    assert run_archive(run_dir).equals(run_archive(tmp_path / "twin"))
    assert run_metrics(run_dir) == run_metrics(tmp_path / "twin")


def local_cluster(workers: int, host: str = "127.0.0.1", threads: int = 1):
    """A real local cluster of `workers` worker processes of `threads` threads on `host`, with the
    housekeeping a search's own local cluster has (cluster.QUIET_CLUSTER)."""
    import logging

    import dask
    from dask.distributed import LocalCluster

    from qdsearch.search.cluster import QUIET_CLUSTER

    with dask.config.set(QUIET_CLUSTER):
        return LocalCluster(n_workers=workers, threads_per_worker=threads, processes=True, host=host,
                            dashboard_address=f"{host}:0", silence_logs=logging.ERROR)


def by_hand(command: list[str], folder: Path, **environment: str) -> subprocess.Popen:
    """A `dask` command started in `folder` (where no code of ours is) in a session of its own, as
    docs/slurm.sbatch starts it: with cluster.QUIET_ENVIRONMENT, and `environment`."""
    from qdsearch.search.cluster import QUIET_ENVIRONMENT

    folder.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([sys.executable, "-m", "dask", *command], cwd=folder,
                            env={**os.environ, **QUIET_ENVIRONMENT, **environment},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def start_scheduler(folder: Path) -> tuple[subprocess.Popen, Path]:
    """`dask scheduler --scheduler-file` on loopback, started in `folder`: the process and its
    scheduler file, once written."""
    scheduler_file = folder / "scheduler.json"
    process = by_hand(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                       "--scheduler-file", str(scheduler_file)], folder)
    deadline = time.time() + 60
    while not scheduler_file.exists() and time.time() < deadline:
        time.sleep(0.05)
    return process, scheduler_file


def start_worker(scheduler_file: Path, folder: Path, *options: str, **environment: str) -> subprocess.Popen:
    """`dask worker --scheduler-file F --nthreads 1` (a nanny and its worker) in a folder of its
    own, as an HPC job starts one; `options` such as --lifetime."""
    return by_hand(["worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1",
                    "--nworkers", "1", "--no-dashboard", "--local-directory", str(folder), *options],
                   folder, **environment)


def stop_all(processes: list[subprocess.Popen]) -> None:
    """End the processes a test started, each with its process group (a nanny and its worker)."""
    for process in processes:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
    for process in processes:
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()


# Policies (4x8 weights) found by searches, and the terrains the fast-env tests fly them on.
LANDER_W = [-0.3024, 0.7899, 0.1059, 1.7391, -0.215, 0.0505, -0.2158, -1.7166,
            0.2988, -0.67, -0.657, 1.8182, -0.8447, 0.5054, 0.1409, -1.0683,
            -0.2659, -1.2483, 0.0842, -0.3101, 0.4834, -1.1872, -1.7291, -1.3206,
            0.2836, -1.3753, -1.1726, 0.1392, 0.4555, 1.2182, -0.7852, -1.0979]  # 225.6, 775 steps
HOVER_W = [0.2009, -0.5722, 1.6418, 1.0927, 0.3113, 0.3791, -0.1347, -1.1235,
           -0.0686, 0.1895, 0.3739, 1.6421, 0.3101, -0.2985, -0.6611, -0.4438,
           -0.1713, 0.0616, -0.701, -0.9206, 0.0249, -1.4127, 0.8403, -1.5734,
           0.4111, 0.3603, -1.6134, 1.0472, 0.7142, 1.2502, -0.6327, 0.2311]  # hovers 1000 steps
SEEDS = [52, 0, 1, 7, 2024]


@contextlib.contextmanager
def small_disk(tmp_path, size):
    """A real tmpfs of `size` mounted at tmp_path/disk, for as long as the block runs."""
    mount_point = tmp_path / f"disk-{uuid.uuid4().hex[:6]}"
    mount_point.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount_point)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {mounted.stderr.strip()}")
    try:
        yield mount_point
    finally:
        subprocess.run(["umount", "-l", str(mount_point)], check=False)


DATA_BLOCK = '<script id="data" type="application/json">'


def page_data(run_dir) -> dict:
    html = (run_dir / "explorer.html").read_text()
    start = html.index(DATA_BLOCK) + len(DATA_BLOCK)
    return json.loads(html[start:html.index("</script>", start)])


def wandb_records(run_dir: Path, kind: str = "history") -> list:
    """The records of one kind ("history", "run", ...) in a run folder's W&B offline run files
    (run-ID.wandb, in W&B's LevelDB-style log: 32 KiB blocks of checksummed pieces, each record a
    protobuf Record), read in the order they were written, file after file."""
    import struct

    from wandb.proto import wandb_internal_pb2

    found = []
    for path in sorted(Path(run_dir).glob("wandb/offline-run-*/run-*.wandb")):
        data, pending = path.read_bytes(), b""
        assert data[:4] == b":W&B", path
        position = 7  # the file's header: ":W&B", a magic number and a version
        while position + 7 <= len(data):
            if 32768 - position % 32768 < 7:  # a block's tail too short for a piece's header
                position += 32768 - position % 32768
                continue
            _, length, piece = struct.unpack("<IHB", data[position:position + 7])
            if piece == 0 and length == 0:
                break
            chunk = data[position + 7:position + 7 + length]
            position += 7 + length
            pending = chunk if piece in (1, 2) else pending + chunk  # full, first; middle, last
            if piece in (1, 4):
                record = wandb_internal_pb2.Record()
                record.ParseFromString(pending)
                if record.WhichOneof("record_type") == kind:
                    found.append(getattr(record, kind))
    return found


def wandb_history(run_dir: Path) -> list[dict]:
    """Each logged step of a run folder's W&B runs: its items by key (nested keys joined by /)."""
    import json as json_module

    return [{(item.key or "/".join(item.nested_key)): json_module.loads(item.value_json)
             for item in history.item} for history in wandb_records(run_dir)]


class Replacements:
    """How many times a file of `folder` named `name` was replaced (an atomic write's rename onto
    it), counted by Linux's inotify: the kernel queues every rename, so none is missed however
    fast they come (polling the file's inode would miss some). The renames from its temporary
    files are watched too: inotify merges an event with the one queued before it if they are the
    same, as two renames onto the file in a row are."""

    MOVED, MOVED_TO, OVERFLOW = 0xC0, 0x80, 0x4000  # <sys/inotify.h>: IN_MOVE, IN_MOVED_TO, IN_Q_OVERFLOW

    def __init__(self, folder: Path, name: str) -> None:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        self.fd = libc.inotify_init1(os.O_NONBLOCK) if hasattr(libc, "inotify_init1") else -1
        if self.fd < 0 or libc.inotify_add_watch(self.fd, str(folder).encode(), self.MOVED) < 0:
            pytest.skip("no inotify here")
        self.name, self.seen = name.encode(), 0

    def count(self) -> int:
        import struct

        while True:
            try:
                data = os.read(self.fd, 1 << 16)
            except BlockingIOError:
                return self.seen
            position = 0
            while position < len(data):  # struct inotify_event: wd, mask, cookie, len, name
                _, mask, _, length = struct.unpack_from("iIII", data, position)
                assert not mask & self.OVERFLOW, "inotify's queue overflowed"
                name = data[position + 16:position + 16 + length].rstrip(b"\0")
                self.seen += bool(mask & self.MOVED_TO) and name == self.name
                position += 16 + length

    def close(self) -> None:
        os.close(self.fd)
