"""Where a run's folder is written while the loop goes on: a driver's saver threads, and on a
cluster with cores of its own, the saver processes that draw the runs' CSVs and pictures.

Map:
- `SavedConfig`: what a save reads of a run's settings;
- `save_outputs`: a run folder's files besides the checkpoint (metrics, archive.npz for the
  results commands, archive.csv, archive.pkl for pyribs' users if asked, `save_pictures`: heatmaps,
  progress plot): what a save costs, nearly all of it;
- `Savers`: the threads a driver's saves run in, and the processes (`saver_processes`) they
  hand `save_outputs` to (`write_outputs`), started as saves come, with Ctrl-C and SIGTERM
  ignored; if one dies, the threads write the saves themselves.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import multiprocessing.forkserver
import os
import signal
import threading
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any, Callable, Iterator, Protocol

from qdsearch.base import compact_pickle
from qdsearch.base.plots import save_heatmap, save_progress_plot
from qdsearch.base.run_files import atomic_write, write_csv, write_json, write_pickle
from qdsearch.store.archive_data import write_archive_data
from qdsearch.tasks import MEASURES

# At most this many saver processes a driver: two keep up with the saves of the largest
# experiments docs/performance.md#saves predicts (benchmarks/bench_saves.py measures a save).
SAVER_PROCESSES = 2


class SavedConfig(Protocol):
    """What a save reads of a run's settings (the config layer's RunConfig is one)."""

    algorithm: str
    measures: list[str]
    pictures: bool
    archive_pkl: bool

    def to_json(self) -> dict[str, Any]: ...


def save_outputs(run_dir: Path, archive, metrics: list[dict], config: SavedConfig, iteration: int,
                 heat: tuple[float, float]) -> None:
    """The run folder's files besides the checkpoint: metrics, the archive (archive.npz for the
    results commands, which never unpickle, and with --archive_pkl a pickle for pyribs' users),
    its CSV, and unless --pictures is false the heatmaps and the progress plot. At a full Lunar
    Lander archive (300
    iterations) they take ~0.27 s of CPU, the CSV and the pictures nearly all of it
    (benchmarks/bench_saves.py; archive.npz ~5 ms)."""
    write_json(run_dir / "metrics.json", metrics)
    # archive.npz before archive.pkl: a reader that finds the pickle finds the data it reads too.
    write_archive_data(run_dir / "archive.npz", archive, config.to_json())
    if config.archive_pkl:
        write_pickle(run_dir / "archive.pkl", archive)
    write_csv(run_dir / "archive.csv", archive.data(return_type="pandas"))
    if config.pictures:
        save_pictures(run_dir, archive, metrics, config, iteration, heat)


def save_pictures(run_dir: Path, archive, metrics: list[dict], config: SavedConfig, iteration: int,
                  heat: tuple[float, float]) -> None:
    """The heatmap (a snapshot in heatmaps/, and heatmap.png, its colours over the `heat` range of
    objectives: tasks.Returns.heat) and the progress plot."""
    title = f"{config.algorithm} after {iteration} iterations"
    snapshot = run_dir / "heatmaps" / f"heatmap_{iteration:05d}.png"
    save_heatmap(archive, [MEASURES[m] for m in config.measures], snapshot, title, heat)
    atomic_write(run_dir / "heatmap.png", lambda f: f.write(snapshot.read_bytes()))
    save_progress_plot(metrics, run_dir / "progress.png")


class Savers:
    """The threads a driver's saves run in, and with `processes`, the saver processes.

    A driver's own thread holds the GIL its loop needs: on a big cluster a save's ~0.27 s there
    delays every run's tell (a lander run saves every 25 iterations: ~11 ms of the driver per
    run-iteration, against ~4-7 ms for the rest of its work). A saver process takes it to a core
    of its own; each thread hands its save to one (`saver_processes`). Without processes, one
    thread draws (matplotlib is not thread-safe), as the threads do once a process has died.
    """

    def __init__(self, processes: int = 0) -> None:
        self.most = processes
        self.threads = ThreadPoolExecutor(max(1, processes), thread_name_prefix="save")
        self.one_at_a_time = threading.Lock()  # drawing in a thread; the trackers' libraries
        self.processes: ProcessPoolExecutor | None = None  # started with the first save

    def submit(self, write: Callable[..., None], *args: Any) -> Future:
        """`write` a save in a saver thread (called from the main thread, the only one that may
        start the fork server with the stop signals ignored)."""
        if self.most and self.processes is None:
            self.processes = saver_processes(self.most)
        return self.threads.submit(write, *args)

    def write_outputs(self, *outputs: Any) -> None:
        """save_outputs in a saver process, or in this thread if there is none (or one died:
        killed, out of memory). Its faults (a full disk) are raised here."""
        if self.processes is not None:
            with contextlib.suppress(BrokenProcessPool):
                return self.processes.submit(save_outputs, *outputs).result()
        with self.one_at_a_time:
            save_outputs(*outputs)

    def close(self, stopping: bool = False) -> None:
        """Once every save is written; `stopping`, once those under way are (a stop: the saves
        still waiting are dropped, and their runs keep their last checkpoint and files)."""
        self.threads.shutdown(cancel_futures=stopping)
        if self.processes is not None:
            self.processes.shutdown(cancel_futures=stopping)


def saver_processes(most: int) -> ProcessPoolExecutor:
    """Up to `most` processes for save_outputs, each started when a save finds the others busy,
    with Ctrl-C and SIGTERM ignored: a stop never cuts a save in one (nor prints its traceback);
    the driver closes them once its saves are written. They are forked from multiprocessing's
    fork server, started here (in the main thread, those signals ignored, a disposition its
    children keep), which imports once what a save needs (and the script, as a child of it
    would). Starting it does not wait for those imports (3.2-4.0 s of CPU here, 2026-11-28): the
    first saver process, and the saver thread that asks for it, do, while the driver's loop goes
    on. (Waited for here, they held every run of the driver and its workers at its first save.)
    Later saver processes start in ~30 ms."""
    compact_pickle.compact_transfers()  # an archive goes to a saver as its elites, not its cells
    if "forkserver" not in multiprocessing.get_all_start_methods():  # not on Windows
        return ProcessPoolExecutor(most, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=start_saving)
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["__main__", "qdsearch.store.saving", "matplotlib.pyplot",
                                    "ribs.visualize"])
    with stop_signals_ignored():
        multiprocessing.forkserver.ensure_running()
    return ProcessPoolExecutor(most, mp_context=context, initializer=start_saving)


@contextlib.contextmanager
def stop_signals_ignored() -> Iterator[None]:
    """Ctrl-C and SIGTERM ignored in this block, if in the main thread (only it may set them;
    a driver in another thread has no terminal)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handlers = {signum: signal.signal(signum, signal.SIG_IGN) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)


def start_saving() -> None:
    """A saver process's start: it ends itself when its driver is gone (a driver killed with
    SIGKILL leaves no saver behind)."""
    driver = multiprocessing.parent_process()
    if driver is not None:
        threading.Thread(target=end_with, args=(driver.sentinel,), daemon=True).start()


def end_with(sentinel: int) -> None:
    multiprocessing.connection.wait([sentinel])
    os._exit(0)
