"""The one run loop: runs ask, have their batches flown on the cluster, and tell, any number of
them at once on one Dask client. `search` and `resume` drive one run through it (run.py),
`experiment` many (experiments.py). A run itself, what it asks and tells, is run.py's `Run`.

A run's results depend on its own asks and tells only, so a run ends bit for bit the same
whether it is driven alone or among others, whatever the order its chunks come back in.
The driver runs in a process's main thread: its saves start saver processes with the stop
signals ignored (saving.py's `Savers`), which only the main thread may set.

Map:
- `DrivenRun`: what the loop asks of a run (run.py's `Run` is one): `send` its batch to the
  cluster, `take` a chunk back, `tell_batch`, `save` its folder, and where it stands;
- `Driver`: the loop. Chunks come back in whatever order they finish (Dask's as_completed); a run
  goes on as soon as its own batch is whole: it tells, saves at its log interval, and sends its
  next batch or finishes. Its subclasses say how runs are opened and recorded (experiments.py's
  `Experiment`; `OneRun` for search and resume), and whether a run's fault stops it alone. Its
  saves are written by saving.py's `Savers`;
- `count_as_done_before`: a resumed run's earlier iterations on the progress bar.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Callable, Protocol

from qdsearch.base.flags import UsageError, clipped
from qdsearch.base.run_files import RunError, fault_text
from qdsearch.base.signing import user_key
from qdsearch.base.stopping import STOP
from qdsearch.search.cluster import SchedulerLost, shares_this_machine
from qdsearch.search.engine import ClusterShare
from qdsearch.store.metrics import describe_progress
from qdsearch.store.saving import SAVER_PROCESSES, Savers
from qdsearch.store.trackers import Tracking, wait_for_trackers


class DrivenRun(Protocol):
    """What the loop reads and calls of a run between two iterations (run.py's `Run`): its batch
    sent, taken back chunk by chunk and told, its folder saved, and where it stands."""

    name: str
    here: bool  # scored in this process (a benchmark function): no batch on the cluster
    metrics: list[dict]
    target: int  # where this drive stops
    saved: int  # the iteration of its last checkpoint
    log: logging.Logger
    tracking: Tracking
    leaving: contextlib.ExitStack
    pending: Future | None  # a save being written

    @property
    def iteration(self) -> int: ...
    def send(self, client, sharing: int = 1, threads: int | None = None) -> list: ...
    def take(self, position: int, result: Any) -> bool: ...
    def tell_batch(self) -> dict | None: ...
    def due(self, row: dict) -> bool: ...
    def save_checkpoint(self, force: bool = False) -> None: ...
    def save(self, savers: Savers) -> None: ...
    def settle(self, wait: bool = True) -> None: ...


def count_as_done_before(bar, iterations: int) -> None:
    """Put a resumed run's earlier iterations on the tqdm bar as its starting point, not as work
    done now, so its rate and time left reflect only this drive (a bar not drawn: nothing)."""
    if bar.disable:
        return
    bar.n, bar.last_print_n, bar.initial = (
        count + iterations for count in (bar.n, bar.last_print_n, bar.initial))
    bar.refresh()


STOP_CHECKPOINTS_S = 2.0  # how long a stop writes the live runs' checkpoints (Driver.checkpoint_on_stop)


class Driver:
    """Drives runs on one client until each reaches its target: the one loop of search, resume
    and experiment.

    `entries` are the runs to drive, each a dict with at least its "name"; `open` (a subclass's)
    makes an entry's run, `record` notes each change of its state ("running", "done", "stopped",
    "failed"). With `isolated` runs a run's fault stops it alone; otherwise it ends the drive.
    Every `every` iterations told, `lines()` are logged. The runs' states noted by `record` are
    kept by `flush`: once the runs of a batch are opened, at most every so often while they go
    on, and at the drive's end, however many runs change at once.
    """

    desc = "runs"  # the progress bar's label
    isolated = False

    def __init__(self, client, log: logging.Logger, entries: list[dict], total: int, done: int = 0,
                 limit: int | None = None, every: int | None = None) -> None:
        from dask.distributed import as_completed

        user_key()  # the key checkpoints are signed with, made (or refused) before any run opens
        self.client, self.log, self.total, self.done, self.every = client, log, total, done, every
        self.todo = collections.deque(entries)
        self.entries = {entry["name"]: entry for entry in entries}
        self.limit = limit or len(entries)
        self.live: dict[str, DrivenRun] = {}
        self.owner: dict[str, tuple[DrivenRun, int]] = {}  # future key -> its run, chunk position
        self.latest: dict[str, dict] = {}  # run name -> its last metrics row
        self.told = 0  # iterations told in this drive
        self.closing: list[DrivenRun] = []  # finished runs whose last save is being written
        # Run folders are written while the runs go on. A cluster whose workers are elsewhere
        # runs on cores of its own, and so may saver processes. On a cluster it starts itself
        # (--workers), or one joined whose workers all listen on loopback, the driver shares the
        # machine's cores with the workers: a saver process would gain nothing (measured on 2
        # cores: docs/performance.md) and cost its fork server's start (its imports: 3.2-4.0 s of
        # CPU here, 2026-11-28): one thread draws.
        self.savers = Savers(0 if client is None or shares_this_machine(client)
                             else min(SAVER_PROCESSES, self.limit))
        self.ready: collections.deque[DrivenRun] = collections.deque()  # runs whose batch was scored here
        # Results come with their futures (no second round trip to fetch them); a chunk that
        # failed comes as its exception, and is its run's fault alone.
        self.finished = None if client is None else as_completed(with_results=True, raise_errors=False)
        self.share = ClusterShare(client)  # the worker threads and the runs sharing them

    # ---- what subclasses say ----
    def open(self, entry: dict) -> DrivenRun:
        raise NotImplementedError

    def record(self, entry: dict, state: str, error: BaseException | None = None) -> None:
        """A run's new state (an experiment writes it to experiment.json)."""

    def flush(self, due_only: bool = False) -> None:
        """Keep the states `record` noted (with `due_only`, only if they are due)."""

    def lines(self) -> list[str]:
        """Lines logged every `every` iterations told."""
        return []

    def log_lines(self) -> None:
        for line in self.lines():
            self.log.info(line)

    # ---- the loop ----
    def drive(self) -> None:
        """Drive every entry's run to its target; a stop or a fault keeps each run's last
        completed iteration in its checkpoint."""
        from tqdm import tqdm

        # disable=None: no bar where stderr is not a terminal (a pipe, a batch job's log), whose
        # frames would be written there one after another; the log's lines say the progress.
        self.bar = tqdm(total=self.total, initial=self.done, unit="it", desc=self.desc,
                        dynamic_ncols=True, disable=None)
        logged, stopping = 0, False
        try:
            self.start_more()
            self.flush()  # the states of the runs just opened, written once
            self.bar.unpause()  # its rate counts from here: opening runs (a CVT's k-means) is no iteration's
            while self.live:
                if self.ready:  # a run scored in this process: its next iteration, a stop acted on first
                    STOP.check()
                    if (run := self.ready.popleft()).name in self.live:
                        self.step_here(run)
                else:
                    with STOP.interruptible():
                        future, result = self.next_chunk()
                    run, position = self.owner.pop(future.key, (None, 0))
                    if run is not None and run.name in self.live and run.take(position, result):
                        self.advance(run)  # else a chunk of a run that has failed meanwhile
                if not self.live:  # the closing lines go under the finished bar, not redrawn after them
                    self.bar.close()
                self.reap(wait=False)
                self.flush(due_only=True)
                if self.every and self.live and self.told - logged >= self.every:
                    logged = self.told
                    self.log_lines()
            self.reap(wait=True)
            self.flush()
            if self.every:
                self.log_lines()
        except BaseException:
            self.todo.clear()  # nothing more is opened
            stopping = True
            self.checkpoint_on_stop()
            for run in list(self.live.values()):
                self.close(run, "stopped")
            with contextlib.suppress(Exception):
                self.reap(wait=True)
            with contextlib.suppress(Exception):  # the fault or the stop under way is the one said
                self.flush()
            raise
        finally:
            self.savers.close(stopping)
            self.bar.close()
            wait_for_trackers(self.log)

    def checkpoint_on_stop(self) -> None:
        """At a stop or a fault, the live runs' checkpoints, those with the most iterations since
        their last one first, for STOP_CHECKPOINTS_S at most once the first is written: a stop
        comes within seconds however many runs are live (each checkpoint takes milliseconds), and
        a run not reached keeps its last checkpoint, which resume goes on from as exactly."""
        deadline = None
        for run in sorted(self.live.values(), key=lambda run: run.saved - run.iteration):
            if deadline is not None and time.monotonic() > deadline:
                return
            with contextlib.suppress(Exception):
                run.save_checkpoint()
            deadline = deadline or time.monotonic() + STOP_CHECKPOINTS_S

    def next_chunk(self) -> tuple[Any, Any]:
        """The next chunk back, as as_completed hands it. A client that has lost its scheduler
        leaves the futures sent since pending, and as_completed would wait on them for ever: the
        wait looks at the client as it goes (check_connected), as as_completed's own wait does (a
        condition woken by each result, or every 0.1 s)."""
        while not self.finished.has_ready():
            self.check_connected()
            with self.finished.thread_condition:
                self.finished.thread_condition.wait(timeout=0.1)
        return next(self.finished)

    def start_more(self) -> None:
        """Open waiting runs until `limit` are in flight. A stop is acted on between two runs:
        opening thousands takes minutes."""
        while self.todo and len(self.live) < self.limit:
            STOP.check()
            entry = self.todo.popleft()
            try:
                run = self.open(entry)
            except (UsageError, RunError, OSError) as error:  # a bad folder, a full disk
                self.fail(entry, None, error)
                continue
            self.live[run.name] = run
            self.latest[run.name] = run.metrics[-1] if run.metrics else {}
            count_as_done_before(self.bar, run.iteration)
            self.record(entry, "running")
            if run.iteration >= run.target:
                self.finish(run)
            else:
                self.send(run)

    def send(self, run: DrivenRun) -> None:
        """The run's next batch, to the cluster (a run scored here waits its turn: `ready`)."""
        if run.here:
            self.ready.append(run)
            return
        self.check_connected()
        threads, sharing = self.share(len(self.live))
        for position, future in enumerate(run.send(self.client, sharing, threads)):
            self.owner[future.key] = (run, position)
            self.finished.add(future)

    def step_here(self, run: DrivenRun) -> None:
        """A run scored in this process: its next iteration (a DQD row's two batches) asked,
        scored and told in one step. A fault on the way is its own (`fail`): its checkpoint keeps
        the last iteration saved."""
        try:
            run.send(self.client)
            while (row := run.tell_batch()) is None:
                run.send(self.client)
            self.after_tell(run, row)
        except Exception as error:
            self.fail(self.entries[run.name], run, error)

    def figures(self, row: dict) -> dict[str, str]:
        """What the progress bar shows beside its count, after a run told `row`: that run's
        coverage, QD score and best objective (a driver of many runs shows its own figures)."""
        best = float("nan") if row["best_objective"] is None else row["best_objective"]
        return {"coverage": f"{row['coverage']:.3f}", "qd": f"{row['qd_score']:.4g}", "best": f"{best:.1f}"}

    def advance(self, run: DrivenRun) -> None:
        """The run's batch is whole: tell it, save it at its log interval, send again or finish."""
        try:
            row = run.tell_batch()
            if row is None:  # the iteration's next batch (a DQD row's branched solutions)
                self.send(run)
                return
            self.after_tell(run, row)
        except Exception as error:  # a task that failed, a write
            self.check_scheduler(error)
            self.fail(self.entries[run.name], run, error)

    def after_tell(self, run: DrivenRun, row: dict) -> None:
        """The run has told an iteration (`row`, its metrics): save it at its log interval, send
        again or finish."""
        run.settle(wait=False)  # a fault of the last save (a full disk) stops the run now
        self.latest[run.name] = row
        self.told += 1
        self.bar.update(1)
        self.bar.set_postfix(self.figures(row), refresh=False)
        if row["iteration"] >= run.target:
            self.finish(run)
        else:
            self.send(run)
            if run.due(row):
                run.log.info(describe_progress(row, run.target))
                run.save(self.savers)

    def check_connected(self) -> None:
        """Stop at once when the client has lost its scheduler. While it tries to reconnect
        ("connecting", for up to HANDSHAKE_TIMEOUT) it has already cancelled every future in
        flight, so no run can go on; a batch sent or a question asked then (the chunks' worker
        count) would wait out the whole reconnection, or the closed client's futures for ever."""
        if self.client is not None and self.client.status != "running":
            self.check_scheduler(RunError(f"the Dask client is {self.client.status}"))

    def check_scheduler(self, error: BaseException) -> None:
        """A task lost with the scheduler is no run's fault: the whole drive stops (every run
        keeps its checkpoint) rather than failing its runs one by one."""
        if isinstance(error, SchedulerLost):
            raise error
        if self.client is None:  # a run scored here has no scheduler to lose
            return
        status = self.client.status
        if status != "running":  # while it reconnects, every fault is the loss's: one cause said
            why = "its connection closed" if status == "connecting" else clipped(fault_text(error))
            raise SchedulerLost(f"lost the Dask scheduler at {self.client.scheduler.address} "
                                f"({why})") from None

    def fail(self, entry: dict, run: DrivenRun | None, error: BaseException) -> None:
        """A run's fault: with `isolated` runs, it stops that run alone (its checkpoint kept, its
        state and cause recorded) and another takes its place; otherwise it ends the drive, as a
        fault of the machine (a RunError) unless it is one already."""
        if not self.isolated:
            if isinstance(error, (UsageError, RunError, OSError)):
                raise error
            raise RunError(f"{type(error).__name__}: {fault_text(error)}") from error
        if run is not None:
            with contextlib.suppress(Exception):
                run.save_checkpoint()
            self.close(run, "failed", error)
        else:
            self.record(entry, "failed", error)
        self.log.info(f"run {entry['name']} failed: {fault_text(error)}")
        self.start_more()

    def finish(self, run: DrivenRun) -> None:
        """The run is complete: its folder is written in the saver thread (reap() closes it)
        while another run takes its place."""
        run.save(self.savers)
        self.live.pop(run.name, None)
        self.closing.append(run)
        self.start_more()

    def reap(self, wait: bool) -> None:
        """Close the finished runs whose last save is written (with `wait`, all of them)."""
        for run in [run for run in self.closing if wait or run.pending.done()]:
            self.closing.remove(run)
            try:
                run.settle()
            except Exception as error:
                self.fail(self.entries[run.name], run, error)
                continue
            if run.metrics:
                run.log.info("Done. " + describe_progress(run.metrics[-1], run.target))
            self.close(run, "done")

    def close(self, run: DrivenRun, state: str, error: BaseException | None = None) -> None:
        self.live.pop(run.name, None)
        run.tracking.close()
        run.leaving.close()
        self.record(self.entries[run.name], state, error)


class OneRun(Driver):
    """search and resume: one run, made by `make` once the drive begins; its fault ends the drive."""

    desc = "search"

    def __init__(self, client, log: logging.Logger, run_dir: Path, iterations: int,
                 make: Callable[[], DrivenRun]) -> None:
        super().__init__(client, log, [{"name": run_dir.name}], total=iterations)
        self.make = make

    def open(self, entry: dict) -> DrivenRun:
        return self.make()
