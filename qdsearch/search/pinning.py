"""A local cluster's worker processes pinned to cores, one each, when there is a worker per core.

Map:
- `cores_to_pin`: the cores, or none (fewer or more workers than cores; not on macOS or Windows);
- `PinToCore`: the Dask worker plugin that pins each worker process, and each restarted one;
  `pin_workers` sends it to a new local cluster.

Why (docs/performance.md, "Each worker on a core of its own"): a worker per core leaves no core
to the main process (the scheduler, the client, tell and ask, the saves: ~7% of the two cores
here). Wherever the main process ran, the operating system moved a worker away from its core;
kept each on a core of its own, the 2-worker, 4-run experiment drove its runs faster in 8 of 8
pairs (median 13.20 s against 13.94 s) and a lone 40-iteration search in 5 of 5 (10.32 s against
11.42 s), on 2 cores, 2026-11-25. Two processes alone ran as fast pinned as not: the gain is in
sharing the cores with the main process.
"""

from __future__ import annotations

import contextlib
import os

from distributed.diagnostics.plugin import WorkerPlugin


def cores_to_pin(workers: int) -> list[int]:
    """The cores a local cluster's `workers` are pinned to, one each: every core this process may
    use, when there are as many as workers; else none. With fewer workers, two experiments at
    once would pin theirs to the same cores; with more, a pinned worker could not move to a core
    another left idle."""
    if not hasattr(os, "sched_getaffinity"):
        return []
    cores = sorted(os.sched_getaffinity(0))
    return cores if len(cores) == workers else []


class PinToCore(WorkerPlugin):
    """Worker i (a local cluster names its workers 0, 1, ...) on cores[i], its nanny's restarts
    included (Dask sets a plugin up on every worker that joins). Pinning is never worth a fault:
    a core that can't be had (a cgroup changed meanwhile) leaves the worker where it was."""

    name = "qdsearch-pin-to-core"

    def __init__(self, cores: list[int]) -> None:
        self.cores = cores

    def setup(self, worker) -> None:
        """Every thread of the worker's process on its core (the threads it starts later, such
        as its task threads, inherit it)."""
        if not isinstance(worker.name, int):
            return
        core = {self.cores[worker.name % len(self.cores)]}
        with contextlib.suppress(OSError):  # no /proc/self/task (a sandbox): left where it is
            for thread in os.listdir("/proc/self/task"):
                with contextlib.suppress(OSError):  # a thread that ended meanwhile; a core not ours
                    os.sched_setaffinity(int(thread), core)


def pin_workers(client, workers: int) -> None:
    """Pin a new local cluster's `workers` (PinToCore) if there is one per core. A worker lost
    while the plugin is sent (the scheduler's broadcast raises its fault) leaves the run as it
    is: the scheduler keeps the plugin for every worker that joins later, and a lost scheduler is
    reported where the run next uses it."""
    if cores := cores_to_pin(workers):
        with contextlib.suppress(Exception):
            client.register_plugin(PinToCore(cores), name=PinToCore.name)
