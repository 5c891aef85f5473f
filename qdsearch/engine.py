"""The evaluation engine: batches of rollouts on a Dask cluster.

Map:
- on the workers: `worker_env` (one env per task kind, reused), `fly_chunk` (a chunk of
  (solution, terrain) rollouts);
- in the driver: `submit_flights` (the chunks, as many as `chunk_count` says from
  `chunks_per_worker`, TASK_RATE, MIN_CHUNK and MAX_CHUNK, the rollouts dealt out to them by
  `chunk_pairs`; batches flown first come, first served: FIFO_TIMEOUT), `per_terrain` and
  `averaged` (results back in solution order, averaged over terrains), `gather_with_progress`,
  and `evaluate_batch` (a run's batch, end to end).
"""

from __future__ import annotations

import threading
from typing import Any

import gymnasium as gym
import numpy as np

from qdsearch.cluster import STOP
from qdsearch.tasks import make_env, rollout

_WORKER_ENVS: dict[tuple[str, bool, int], gym.Env] = {}  # per worker thread, reused across tasks


def worker_env(env_name: str, fast: bool = True) -> gym.Env:
    """This thread's environment of the task: reset(seed) gives the same episode bit for bit as
    a fresh environment, without paying for gym.make each time. One per thread: the threads of a
    worker started with --nthreads above 1 fly at once, and an environment shared between two
    would mix their episodes."""
    key = (env_name, fast, threading.get_ident())
    if key not in _WORKER_ENVS:
        _WORKER_ENVS[key] = make_env(fast, env_name=env_name)
    return _WORKER_ENVS[key]


def fly_chunk(solutions: np.ndarray, env_seeds: np.ndarray, measures: tuple[str, ...],
              fast_env: bool, env_name: str) -> np.ndarray:
    """Runs on a worker: fly solutions[i] on terrain env_seeds[i]; rows of (objective, *measures).

    A chunk of rollouts per task (not one task per rollout) keeps the scheduler's per-task cost
    small next to the rollouts, and the environment is kept between tasks (worker_env).
    """
    env = worker_env(env_name, fast_env)
    rows = [rollout(solution, int(seed), env, measures, env_name=env_name)
            for solution, seed in zip(solutions, env_seeds)]
    return np.array(rows).reshape(-1, 1 + len(measures))


# Two chunks per worker, three where several runs in flight each have two workers or more. A
# run's turn between two batches (the driver's tell and ask, the batch's way to the workers, its
# results' way back: ~25 ms) idles the workers its chunks would fill unless other runs' chunks
# wait for them; with few runs on many workers, two a worker leave too few waiting. On real
# schedulers, one-thread worker processes as on a cluster and tasks that sleep as long as real
# chunks (bench_scale.py, 2026-11-25, 3 pairs, benchmarks/scale_chunks_*_runs.json): 4 runs on
# 17 workers (one of 15 parts of 256 workers) 0.827-0.833 with 2 against 0.869-0.878 with 3 (4 a
# worker: 0.80, 6: 0.61, one run each); 8 runs on 16 workers 0.923-0.932 against 0.961; 15 runs
# on 16 workers 0.971-0.974 against 0.970-0.971. A lone run has no other run's chunks to fill its
# turn: on 2 workers its lander batches took 0.96 and 0.99 of the time with 2 chunks a worker
# that they took with 3 (benchmarks/bench_chunking.py, 30 rounds, 2026-11-25), and its walker
# ones (60 to 1,600 steps) 0.96, 0.95 and 1.01 of the time of 2 with 1, 4 and 8 (6 rounds,
# 2026-11-24).
# Each task costs the scheduler ~0.5-0.9 ms: TASK_RATE bounds them.
CHUNKS_PER_WORKER = 2
CHUNKS_PER_WORKER_FEW_RUNS = 3
MIN_CHUNK = 4  # rollouts per task at least, on big clusters: a task costs ~0.6 ms to schedule
# Rollouts per task at most, so that big batches (evaluate's, say) report progress as they go: a
# few seconds of lander episodes (<= 1,000 steps of ~18-27 us), up to minutes of walker ones.
MAX_CHUNK = 1000
# What one scheduler is asked to sustain, all its runs' batches together, in tasks a second:
# about half of what it can (~0.5 ms of its CPU a task, docs/performance.md), so that on a big
# cluster it never becomes what the workers wait for.
TASK_RATE = 1000
# Batches are flown first come, first served. Dask ranks the tasks of graphs sent within its
# fifo_timeout (100 ms by default) as one generation, by their index in their own graph: every
# batch's first chunk before any batch's second, so a batch's last chunk waits behind the other
# batches' first ones and its run tells late. Each batch its own generation took 60 runs on 64
# simulated workers from 0.794/0.817 to 0.883/0.887 with one part, paired (bench_scale.py,
# 2026-11-25).
FIFO_TIMEOUT = "0ms"


def chunks_per_worker(workers: int, sharing: int) -> int:
    """CHUNKS_PER_WORKER, or CHUNKS_PER_WORKER_FEW_RUNS where each of the `sharing` runs in
    flight (two or more: a lone run has no other run's chunks to wait for its workers) has two
    of the `workers` or more."""
    return CHUNKS_PER_WORKER_FEW_RUNS if 2 <= sharing <= workers / 2 else CHUNKS_PER_WORKER


def chunk_count(pairs: int, workers: int, sharing: int = 1, cycle_s: float | None = None,
                per_worker: int | None = None, rate: float | None = None) -> int:
    """How many chunks a batch of `pairs` rollouts is split into: `per_worker` chunks for each
    worker (by default `chunks_per_worker`'s), shared among the `sharing` runs in flight on the
    scheduler (fewer, larger tasks when runs outnumber workers); at most the run's share of
    `rate` over its last cycle (`cycle_s`, from one batch to the next); never under MIN_CHUNK
    rollouts nor over MAX_CHUNK."""
    per_worker = chunks_per_worker(workers, sharing) if per_worker is None else per_worker
    rate = TASK_RATE if rate is None else rate
    fewest = -(-pairs // MAX_CHUNK)
    wanted = -(-per_worker * workers // max(1, sharing))
    if cycle_s is not None:
        wanted = min(wanted, int(rate * cycle_s / max(1, sharing)))
    return max(1, min(max(wanted, fewest), pairs // MIN_CHUNK))


def submit_flights(client, solutions: np.ndarray, env_seeds: list[int], measures: tuple[str, ...],
                   fast_env: bool, sharing: int = 1, threads: int | None = None, *,
                   env_name: str, cycle_s: float | None = None) -> list:
    """Send every solution to be flown on every terrain; the futures of the chunks, in order.

    The work is the (solution, terrain) pairs, dealt out into chunks of about equal count
    whatever the number of terrains (chunk_pairs), so the workers stay evenly loaded. A batch
    alone on the cluster is split in `chunks_per_worker` chunks per worker; when `sharing` runs
    keep the workers busy together, each batch needs only its share of that, and fewer tasks
    cost the scheduler less (`chunk_count`; `cycle_s`, the run's last cycle, keeps the
    scheduler's load in bounds). The chunks go in one message (client.map), ranked after every
    batch sent before them (FIFO_TIMEOUT); tasks of a dead worker are retried. `threads`, the
    cluster's worker threads if the caller knows them, saves asking the scheduler (a round trip).
    """
    workers = max(1, threads if threads is not None else sum(client.nthreads().values()))
    pairs = len(solutions) * len(env_seeds)
    chunks = chunk_pairs(pairs, chunk_count(pairs, workers, sharing, cycle_s))
    seeds = np.tile(np.asarray(env_seeds, dtype=np.int64), len(solutions))
    return client.map(fly_chunk, [solutions[chunk // len(env_seeds)] for chunk in chunks],
                      [seeds[chunk] for chunk in chunks], [tuple(measures)] * len(chunks),
                      [fast_env] * len(chunks), [env_name] * len(chunks), pure=False, retries=3,
                      fifo_timeout=FIFO_TIMEOUT)


def chunk_pairs(pairs: int, count: int) -> list[np.ndarray]:
    """Which of a batch's `pairs` (solution, terrain) rollouts each of `count` chunks flies: pair
    i in chunk i mod count. Dealt out so, every chunk holds some of each emitter's solutions:
    neighbours in a batch come from one emitter and often fly alike (a region of hovering
    landers, of quick crashes), so runs of neighbours make chunks of unequal length. Over the
    300 iterations of a real search (benchmarks/episode_lengths_lander.npz), 4 chunks on 2
    workers, each taking the next chunk when free, end 1.084x as late as perfectly shared work
    when cut into runs, 1.037x when dealt out (2 chunks: 1.157x and 1.038x)."""
    return [np.arange(first, pairs, count) for first in range(count)]


def per_terrain(chunk_results: list[np.ndarray], env_seeds: list[int]) -> np.ndarray:
    """The chunks' rows back in pair order (chunk_pairs dealt them out): (solutions, terrains,
    1 + measures)."""
    pairs = sum(len(rows) for rows in chunk_results)
    rows = np.empty((pairs, chunk_results[0].shape[1]), dtype=np.result_type(*chunk_results))
    for chunk, chunk_rows in zip(chunk_pairs(pairs, len(chunk_results)), chunk_results):
        rows[chunk] = chunk_rows
    return rows.reshape(-1, len(env_seeds), rows.shape[1])


def averaged(flights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Objectives and measures: each solution's mean over its terrains (one terrain: itself)."""
    means = flights.mean(axis=1)
    return means[:, 0], means[:, 1:]


def gather_with_progress(client, futures: list) -> list:
    """The futures' results in their order, with a progress bar while they come back (for the
    long batches of the results commands); Ctrl-C stops the wait."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    with STOP.interruptible():
        for _ in tqdm(as_completed(futures), total=len(futures), desc="flights", unit="task",
                      dynamic_ncols=True):
            pass
        return client.gather(futures)


def evaluate_batch(client, solutions: np.ndarray, config: Any) -> tuple[np.ndarray, np.ndarray]:
    """Objectives and measures of `solutions` in the run's setting, flown on the Dask cluster.

    Results come back in the order of the solutions whatever the number of workers, so a fixed
    seed gives the same archive on 1 or 100 workers.
    """
    futures = submit_flights(client, solutions, config.env_seed, config.measures,
                             config.fast_env, env_name=config.env)
    return averaged(per_terrain(client.gather(futures), config.env_seed))
