#!/usr/bin/env python
"""What Dask's housekeeping costs a cluster that waits: at Dask's own pace, and at the pace of
qdsearch.search.cluster.QUIET_CLUSTER (what a search's local cluster runs at; QUIET_ENVIRONMENT for
processes started by hand).

    python benchmarks/bench_housekeeping.py --seconds 30 --rounds 2

Each round measures, in turn, for each pace: a local cluster of two single-threaded worker
processes, as `--workers 2` starts (the scheduler and the workers' nannies live in this process),
and a `dask scheduler` with one `dask worker` started by hand, as docs/slurm.sbatch starts them.
Each waits `--seconds` once it is up, and the CPU time (user + system) of each of its processes
over that wait is read from the kernel. No task runs: this is the cost that stays when the
rollouts stop, which a busy worker pays on top of them (its profiler's samples hold its GIL).

Prints and writes benchmarks/housekeeping_results.json. Run it on a quiet machine.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import fire
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import qdsearch
from qdsearch.search.cluster import QUIET_CLUSTER, QUIET_ENVIRONMENT  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def cpu_seconds(processes: list[psutil.Process]) -> list[float]:
    return [sum(process.cpu_times()[:2]) for process in processes]


def waiting_cost(processes: list[psutil.Process], seconds: float) -> list[float]:
    """CPU seconds per second of wall time, of each process, over `seconds` of waiting."""
    before = cpu_seconds(processes)
    time.sleep(seconds)
    return [round((after - start) / seconds, 4) for start, after in zip(before, cpu_seconds(processes))]


def local_cluster_cost(quiet: bool, seconds: float) -> dict:
    import dask
    from dask.distributed import Client, LocalCluster

    with dask.config.set(QUIET_CLUSTER if quiet else {}):
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address="127.0.0.1:0", silence_logs=logging.ERROR)
    with cluster, Client(cluster) as client:
        client.wait_for_workers(2)
        time.sleep(2)  # past the start's own work
        this = psutil.Process()
        costs = waiting_cost([this, *this.children(recursive=True)], seconds)
    return {"driver_scheduler_nannies": costs[0], "workers": sum(costs[1:])}


def waited_for(condition, what: str, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"{what} did not come within {timeout:.0f} s")
        time.sleep(0.1)


def by_hand_cost(quiet: bool, seconds: float) -> dict:
    """A `dask scheduler` and a `dask worker` (its nanny and its worker process)."""
    environment = {**os.environ, **(QUIET_ENVIRONMENT if quiet else {})}
    with tempfile.TemporaryDirectory() as folder:
        scheduler_file = Path(folder) / "scheduler.json"
        quietly = dict(cwd=folder, env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        started = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1",
                                     "--port", "0", "--no-dashboard", "--scheduler-file",
                                     str(scheduler_file)], **quietly)]
        try:
            waited_for(scheduler_file.exists, "the scheduler file")
            started.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", "--scheduler-file",
                                             str(scheduler_file), "--nthreads", "1", "--no-dashboard",
                                             "--local-directory", folder], **quietly))
            waited_for(lambda: len(psutil.Process(started[1].pid).children()) >= 2,  # worker, tracker
                       "the worker process")
            time.sleep(8)  # the worker's imports and its registration
            nanny = psutil.Process(started[1].pid)
            worker = max(nanny.children(), key=lambda child: child.memory_info().rss)
            scheduler, nanny_cost, worker_cost = waiting_cost(
                [psutil.Process(started[0].pid), nanny, worker], seconds)
        finally:
            for process in started[::-1]:
                process.terminate()
                process.wait()
    return {"scheduler": scheduler, "nanny": nanny_cost, "worker": worker_cost}


def main(seconds: float = 30.0, rounds: int = 2, out: str = "benchmarks/housekeeping_results.json") -> None:
    rows: dict[str, list[dict]] = {}
    for _ in range(rounds):
        for kind, measure in (("local_cluster", local_cluster_cost), ("by_hand", by_hand_cost)):
            for pace, quiet in (("dask", False), ("quiet", True)):
                rows.setdefault(f"{kind}_{pace}", []).append(measure(quiet, seconds))
                print(kind, pace, rows[f"{kind}_{pace}"][-1], flush=True)
    medians = {name: {key: round(statistics.median(row[key] for row in found), 4) for key in found[0]}
               for name, found in rows.items()}
    result = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
              "unit": "CPU seconds per second of waiting (a share of one core), median over the rounds",
              "quiet": QUIET_CLUSTER, "medians": medians, "rounds": rows}
    print(json.dumps(medians, indent=2))
    Path(out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    fire.Fire(main)
