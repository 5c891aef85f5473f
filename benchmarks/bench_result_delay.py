#!/usr/bin/env python
"""How late a one-thread Dask worker hands over a finished chunk of real rollouts: the time from
the chunk's end (on the worker) to its result's arrival in the client, with the worker's switch
interval (sys.setswitchinterval, set by each chunk before it flies) at each of --intervals, in
alternating rounds on the same local cluster.

Each round keeps --in_flight chunks queued on one worker, so the next chunk starts (and holds the
GIL) as soon as one ends: the case of a search whose runs keep every worker busy. A chunk is
--rollouts Lunar Lander episodes of N(0, 1) policies, flown by the engine's own fly_chunk.

    python benchmarks/bench_result_delay.py --rounds 3 --chunks 30 --rollouts 30
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import qdsearch
from qdsearch import tasks  # noqa: E402
from qdsearch.search import engine  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def timed_chunk(solutions: np.ndarray, seeds: np.ndarray, env_name: str, interval: float) -> float:
    """Runs on the worker: with this switch interval, fly the chunk as the engine does; the wall
    time it ended."""
    sys.setswitchinterval(interval)
    engine.fly_chunk(engine.Chunk(solutions, seeds, (), env_name))
    return time.time()


def one_round(client, env_name: str, chunks: int, rollouts: int, in_flight: int, interval: float,
              rng: np.random.Generator) -> list[float]:
    """Delays (s) of `chunks` chunks, `in_flight` kept queued on the worker."""
    from dask.distributed import as_completed

    dim = tasks.ENVIRONMENTS[env_name].solution_dim
    make = lambda: client.submit(timed_chunk, rng.normal(0, 1, (rollouts, dim)),  # noqa: E731
                                 np.full(rollouts, 52), env_name, interval, pure=False)
    delays, queue = [], as_completed([make() for _ in range(in_flight)])
    sent = in_flight
    for future in queue:
        delays.append(time.time() - future.result())
        if sent < chunks:
            queue.add(make())
            sent += 1
    return delays


def main(rounds: int = 6, chunks: int = 40, rollouts: int = 30, in_flight: int = 3,
         env: str = "LunarLander-v3", intervals: tuple = (0.005, 0.0005)) -> None:
    from dask.distributed import Client, LocalCluster

    delays: dict[float, list[float]] = {float(i): [] for i in intervals}
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        rng = np.random.default_rng(0)
        one_round(client, env, 4, rollouts, in_flight, float(intervals[0]), rng)  # warm the worker
        for _ in range(rounds):
            for interval in delays:
                delays[interval] += one_round(client, env, chunks, rollouts, in_flight, interval, rng)
    print(f"{env}: {rounds} rounds x {chunks} chunks of {rollouts} rollouts, {in_flight} queued on 1 worker")
    print(f"{'switch interval ms':>18} {'median ms':>10} {'p90 ms':>8}")
    for interval, values in delays.items():
        values = sorted(values)
        print(f"{interval * 1e3:>18g} {statistics.median(values) * 1e3:>10.1f} "
              f"{values[int(0.9 * len(values))] * 1e3:>8.1f}")


if __name__ == "__main__":
    fire.Fire(main)
