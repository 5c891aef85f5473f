#!/usr/bin/env python
"""How many chunks per worker a batch is split into (chunks_per_worker in qdsearch/search/engine.py), for a
task's episodes: the seconds of one batch of the default search (5 emitters x 30 policies) on a
local cluster of --workers processes, for each chunk count, in interleaved rounds (the same
batches for every count), with the median and its ratio to today's count.

Policies are N(0, sigma^2) weights: for the walker they mix episodes that fall within ~60 steps
with ones that stand or shuffle to the 1,600-step limit, the unevenness chunking must absorb.

    python benchmarks/bench_chunking.py --env BipedalWalker-v3 --counts "[1, 2, 3, 4, 8]" --rounds 3
"""

from __future__ import annotations

import logging
import statistics
import sys
import time
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import qdsearch
from qdsearch import tasks  # noqa: E402
from qdsearch.config import options, run_config  # noqa: E402
from qdsearch.search import engine  # noqa: E402
from qdsearch.search.cluster import dask_client  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def main(env: str = "BipedalWalker-v3", counts: tuple[int, ...] = (1, 2, 3, 4, 8), rounds: int = 3,
         workers: int = 2, batch: int = 150, sigma: float = 0.5) -> None:
    task = tasks.ENVIRONMENTS[env]
    flags = {**options.search_defaults(), "env": env, "seed": 1}
    config = run_config.check_run_config(options.with_task(flags))
    today = engine.chunks_per_worker(workers, 1)  # a lone batch's
    rule = engine.CHUNKS_PER_WORKER, engine.CHUNKS_PER_WORKER_FEW_RUNS
    times: dict[int, list[float]] = {count: [] for count in counts}
    with dask_client(workers, None, logging.getLogger("bench")) as client:
        engine.evaluate_batch(client, np.zeros((workers * 4, task.solution_dim)), config)  # warm the workers
        for round_ in range(rounds):
            solutions = np.random.default_rng(round_).normal(0, sigma, (batch, task.solution_dim))
            for count in counts:
                engine.CHUNKS_PER_WORKER = engine.CHUNKS_PER_WORKER_FEW_RUNS = count
                start = time.perf_counter()
                engine.evaluate_batch(client, solutions, config)
                times[count].append(time.perf_counter() - start)
    engine.CHUNKS_PER_WORKER, engine.CHUNKS_PER_WORKER_FEW_RUNS = rule
    base = statistics.median(times[today]) if today in times else None
    print(f"{env}, {batch} policies per batch, {workers} workers, {rounds} rounds")
    print(f"{'chunks/worker':>13} {'median s':>9} {'vs ' + str(today):>7}")
    for count in counts:
        median = statistics.median(times[count])
        print(f"{count:>13} {median:>9.2f} {median / base if base else float('nan'):>7.3f}")


if __name__ == "__main__":
    fire.Fire(main)
