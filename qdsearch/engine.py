"""The evaluation engine: batches of rollouts on a Dask cluster.

Map:
- on the workers: `worker_env` (one env per task kind, reused), `fly_chunk` (a chunk of
  (solution, terrain) rollouts);
- in the driver: `submit_flights` (the chunks, as many as `chunk_count` says from
  CHUNKS_PER_WORKER, TASK_RATE, MIN_CHUNK and MAX_CHUNK; batches flown first come, first served:
  FIFO_TIMEOUT), `per_terrain` and `averaged`
  (results back in solution order, averaged over terrains), `gather_with_progress`, and
  `evaluate_batch` (a run's batch, end to end).
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


# Two chunks per worker. On 2 workers any count evens out lander episodes (60 to 1,000 steps) as
# well as another (measured: 1, 2, 3, 4, 8), and walker ones (60 to 1,600 steps: 1, 4 and 8 took
# 0.96, 0.95 and 1.01 of the time of 2; benchmarks/bench_chunking.py, 6 rounds of 150 policies,
# 2026-11-24). Three pay in the scale model at 256 workers (60 runs in 15 parts: 0.98 against
# 0.86), but on the real benchmark at 64 simulated workers, paired, they cost, even with batches
# flown first come first served (FIFO_TIMEOUT): 0.814/0.857 with 2 against 0.834/0.840 with 3
# (one part: a draw), 0.891/0.902 against 0.865/0.855 (two), 0.872/0.854 against 0.788/0.808
# (four), 2026-11-25: more tasks for a scheduler and workers that share the driver's cores. Each
# task costs the scheduler ~0.5-0.9 ms: TASK_RATE bounds them.
CHUNKS_PER_WORKER = 2
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


def chunk_count(pairs: int, workers: int, sharing: int = 1, cycle_s: float | None = None,
                per_worker: int | None = None, rate: float | None = None) -> int:
    """How many chunks a batch of `pairs` rollouts is split into: `per_worker` chunks for each
    worker, shared among the `sharing` runs in flight on the scheduler (fewer, larger tasks when
    runs outnumber workers); at most the run's share of `rate` over its last cycle
    (`cycle_s`, from one batch to the next); never under MIN_CHUNK rollouts nor over MAX_CHUNK."""
    per_worker = CHUNKS_PER_WORKER if per_worker is None else per_worker
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

    The work is the (solution, terrain) pairs, split into chunks of about equal count whatever
    the number of terrains, so the workers stay evenly loaded. A batch alone on the cluster is
    split in CHUNKS_PER_WORKER chunks per worker; when `sharing` runs keep the workers busy
    together, each batch needs only its share of that, and fewer tasks cost the scheduler less
    (`chunk_count`; `cycle_s`, the run's last cycle, keeps the scheduler's load in bounds).
    The chunks go in one message (client.map), ranked after every batch sent before them
    (FIFO_TIMEOUT); tasks of a dead worker are retried. `threads`, the cluster's worker threads
    if the caller knows them, saves asking the scheduler (a round trip).
    """
    workers = max(1, threads if threads is not None else sum(client.nthreads().values()))
    pairs = len(solutions) * len(env_seeds)
    chunks = np.array_split(np.arange(pairs), chunk_count(pairs, workers, sharing, cycle_s))
    seeds = np.tile(np.asarray(env_seeds, dtype=np.int64), len(solutions))
    return client.map(fly_chunk, [solutions[chunk // len(env_seeds)] for chunk in chunks],
                      [seeds[chunk] for chunk in chunks], [tuple(measures)] * len(chunks),
                      [fast_env] * len(chunks), [env_name] * len(chunks), pure=False, retries=3,
                      fifo_timeout=FIFO_TIMEOUT)


def per_terrain(chunk_results: list[np.ndarray], env_seeds: list[int]) -> np.ndarray:
    """The chunks' rows, put together: (solutions, terrains, 1 + measures)."""
    rows = np.concatenate(chunk_results)
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
