"""The evaluation engine: batches of rollouts on a Dask cluster.

Map:
- on the workers: `worker_env` (one env per task kind, reused), `fly_chunk` (a `Chunk`: one
  task's (solution, reset seed) rollouts, and what they fly as; a learning row's transitions);
- in the driver: `submit_flights` (the chunks, as many as `chunk_count` says from
  `chunks_per_worker`, MIN_CHUNK and MAX_CHUNK, the rollouts dealt out to them by
  `chunk_pairs`; batches flown first come, first served: FIFO_TIMEOUT), `per_terrain` and
  `averaged` (results back in solution order, averaged over terrains; `in_pair_order`, a
  learning row's transitions so), `gather_with_progress`,
  and `evaluate_batch` (a run's batch, end to end; `FlownConfig`, what it reads of the run's
  settings);
- `ClusterShare`: the cluster's worker threads (asked every few seconds), which with the
  driver's runs in flight size a batch's chunks.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from typing import Protocol

import gymnasium as gym
import numpy as np

from qdsearch.base.stopping import STOP
from qdsearch.tasks import (
    TASKS_OWN,
    Episode,
    TaskConfig,
    episode_of,
    evaluate_points,
    make_env,
    reset_seeds,
    scored_here,
)
from qdsearch.tasks.policies import LINEAR, Policy, rollout
from qdsearch.tasks.transitions import Recorder

_WORKER_ENVS: dict[tuple[str, bool, Episode, int], gym.Env] = {}  # per worker thread, reused across tasks


def worker_env(env_name: str, fast: bool = True, episode: Episode = TASKS_OWN) -> gym.Env:
    """This thread's environment of the task: reset(seed) gives the same episode bit for bit as
    a fresh environment, without paying for gym.make each time. One per thread: the threads of a
    worker started with --nthreads above 1 fly at once, and an environment shared between two
    would mix their episodes."""
    key = (env_name, fast, episode, threading.get_ident())
    if key not in _WORKER_ENVS:
        _WORKER_ENVS[key] = make_env(fast, env_name=env_name, episode=episode)
    return _WORKER_ENVS[key]


@dataclasses.dataclass(frozen=True)
class Chunk:
    """One task's work on a worker: rollout i flies solutions[i] as `policy` from reset seed
    env_seeds[i], by the `episode` rules, in the task `env_name` (its streamlined copy where it
    has one and `fast_env`), and is scored by its objective and `measures`."""

    solutions: np.ndarray  # a row per rollout
    env_seeds: np.ndarray  # a reset seed per rollout
    measures: tuple[str, ...]
    env_name: str
    policy: Policy = LINEAR
    episode: Episode = TASKS_OWN
    fast_env: bool = True
    transitions: bool = False  # a learning row's: each rollout's transitions come back too


def fly_chunk(chunk: Chunk) -> np.ndarray | tuple[np.ndarray, list[np.ndarray]]:
    """Runs on a worker: the chunk's rollouts, rows of (objective, *measures); with
    `chunk.transitions`, also each rollout's transitions (tasks/transitions.py), in order.

    A chunk of rollouts per task (not one task per rollout) keeps the scheduler's per-task cost
    small next to the rollouts, and the environment is kept between tasks (worker_env).
    """
    env = worker_env(chunk.env_name, chunk.fast_env, chunk.episode)
    recorder = Recorder(env) if chunk.transitions else None
    rows, transitions = [], []
    for solution, seed in zip(chunk.solutions, chunk.env_seeds):
        rows.append(rollout(solution, int(seed), recorder or env, chunk.measures, env_name=chunk.env_name,
                            policy=chunk.policy))
        if recorder is not None:
            transitions.append(recorder.take())
    rows = np.array(rows).reshape(-1, 1 + len(chunk.measures))
    return (rows, transitions) if chunk.transitions else rows


# Two chunks per worker; three where several runs in flight each have two workers or more: it paid
# 0.87 against 0.83 of an ideal cluster for 4 runs on 17 real worker processes
# (docs/performance.md#chunks-and-the-workers-result-delay, benchmarks/scale/bench_scale.py).
CHUNKS_PER_WORKER = 2
CHUNKS_PER_WORKER_FEW_RUNS = 3
MIN_CHUNK = 4  # rollouts per task at least: a task costs the scheduler about a millisecond
# Rollouts per task at most, so that big batches (evaluate's, say) report progress as they go: a
# few seconds of lander episodes, up to minutes of walker ones.
MAX_CHUNK = 1000
# Batches are flown first come, first served: each batch its own generation of Dask's ranking, so
# that a batch's last chunk never waits behind other batches' first ones (its run would tell
# late; docs/performance.md#chunks-and-the-workers-result-delay).
FIFO_TIMEOUT = "0ms"


def chunks_per_worker(workers: int, sharing: int) -> int:
    """CHUNKS_PER_WORKER, or CHUNKS_PER_WORKER_FEW_RUNS where each of the `sharing` runs in
    flight (two or more: a lone run has no other run's chunks to wait for its workers) has two
    of the `workers` or more."""
    return CHUNKS_PER_WORKER_FEW_RUNS if 2 <= sharing <= workers / 2 else CHUNKS_PER_WORKER


def chunk_count(pairs: int, workers: int, sharing: int = 1, per_worker: int | None = None) -> int:
    """How many chunks a batch of `pairs` rollouts is split into: `per_worker` chunks for each
    worker (by default `chunks_per_worker`'s), shared among the `sharing` runs in flight (fewer,
    larger tasks when runs outnumber workers); never under MIN_CHUNK rollouts nor over
    MAX_CHUNK."""
    per_worker = chunks_per_worker(workers, sharing) if per_worker is None else per_worker
    fewest = -(-pairs // MAX_CHUNK)
    wanted = -(-per_worker * workers // max(1, sharing))
    return max(1, min(max(wanted, fewest), pairs // MIN_CHUNK))


def submit_flights(client, solutions: np.ndarray, env_seeds: list[int] | np.ndarray,
                   measures: tuple[str, ...], fast_env: bool, sharing: int = 1, threads: int | None = None, *,
                   env_name: str, policy: Policy = LINEAR, episode: Episode = TASKS_OWN,
                   transitions: bool = False) -> list:
    """Send every solution to be flown on every terrain; the futures of the chunks, in order.
    `env_seeds`: the terrains every solution flies on, or a row of its own per solution (the
    reset seeds of a --reset each run: tasks.reset_seeds).

    The work is the (solution, terrain) pairs, dealt out into chunks of about equal count
    whatever the number of terrains (chunk_pairs), so the workers stay evenly loaded. A batch
    alone on the cluster is split in `chunks_per_worker` chunks per worker; when `sharing` runs
    keep the workers busy together, each batch needs only its share of that, and fewer tasks
    cost the scheduler less (`chunk_count`). The chunks go in one message (client.map), ranked after every
    batch sent before them (FIFO_TIMEOUT); tasks of a dead worker are retried. `threads`, the
    cluster's worker threads if the caller knows them, saves asking the scheduler (a round trip).
    With `transitions`, each chunk's result also holds its rollouts' transitions (fly_chunk).
    """
    workers = max(1, threads if threads is not None else sum(client.nthreads().values()))
    terrains = np.asarray(env_seeds, dtype=np.int64)
    seeds = np.broadcast_to(terrains, (len(solutions), terrains.shape[-1])).reshape(-1)
    pairs, per_solution = len(seeds), terrains.shape[-1]
    chunks = chunk_pairs(pairs, chunk_count(pairs, workers, sharing))
    work = [Chunk(solutions[dealt // per_solution], seeds[dealt], tuple(measures), env_name, policy, episode,
                  fast_env, transitions) for dealt in chunks]
    return client.map(fly_chunk, work, pure=False, retries=3, fifo_timeout=FIFO_TIMEOUT)


def chunk_pairs(pairs: int, count: int) -> list[np.ndarray]:
    """Which of a batch's `pairs` (solution, terrain) rollouts each of `count` chunks flies: pair
    i in chunk i mod count. Dealt out so, every chunk holds some of each emitter's solutions:
    neighbours in a batch come from one emitter and often fly alike (a region of hovering
    landers, of quick crashes), so runs of neighbours make chunks of unequal length. Over the
    300 iterations of a real search (benchmarks/scale/episode_lengths_lander.npz), 4 chunks on 2
    workers, each taking the next chunk when free, end 1.084x as late as perfectly shared work
    when cut into runs, 1.037x when dealt out (2 chunks: 1.157x and 1.038x)."""
    return [np.arange(first, pairs, count) for first in range(count)]


def per_terrain(chunk_results: list[np.ndarray], env_seeds: list[int] | np.ndarray) -> np.ndarray:
    """The chunks' rows back in pair order (chunk_pairs dealt them out): (solutions, terrains,
    1 + measures); `env_seeds` as submit_flights took them."""
    pairs = sum(len(rows) for rows in chunk_results)
    rows = np.empty((pairs, chunk_results[0].shape[1]), dtype=np.result_type(*chunk_results))
    for chunk, chunk_rows in zip(chunk_pairs(pairs, len(chunk_results)), chunk_results):
        rows[chunk] = chunk_rows
    return rows.reshape(-1, np.shape(env_seeds)[-1], rows.shape[1])


def in_pair_order(per_chunk: list[list[np.ndarray]]) -> list[np.ndarray]:
    """The chunks' per-rollout items (a learning row's transitions) back in pair order, as
    per_terrain puts their rows: the same whatever the number of chunks, so of workers."""
    pairs = sum(len(items) for items in per_chunk)
    ordered: list = [None] * pairs
    for chunk, items in zip(chunk_pairs(pairs, len(per_chunk)), per_chunk):
        for pair, item in zip(chunk, items):
            ordered[pair] = item
    return ordered


def averaged(flights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Objectives and measures: each solution's mean over its terrains (one terrain: itself)."""
    means = flights.mean(axis=1)
    return means[:, 0], means[:, 1:]


def gather_with_progress(client, futures: list) -> list:
    """The futures' results in their order, with a progress bar while they come back (for the
    long batches of the results commands); Ctrl-C stops the wait."""
    from dask.distributed import as_completed
    from tqdm import tqdm

    with STOP.interruptible():  # (disable=None: no bar where stderr is no terminal, a pipe or a log)
        for _ in tqdm(as_completed(futures), total=len(futures), desc="flights", unit="task",
                      dynamic_ncols=True, disable=None):
            pass
        return client.gather(futures)


class FlownConfig(TaskConfig, Protocol):
    """What a batch's flights read of a run's settings (the config layer's RunConfig is one): the
    task's (tasks.TaskConfig), which copy of the env, and the policy. Not the config layer itself,
    which a worker that imports this module has no need to load."""

    fast_env: bool
    network: Policy


def evaluate_batch(client, solutions: np.ndarray, config: FlownConfig) -> tuple[np.ndarray, np.ndarray]:
    """Objectives and measures of `solutions` in the run's setting, flown on the Dask cluster.

    Results come back in the order of the solutions whatever the number of workers, so a fixed
    seed gives the same archive on 1 or 100 workers. A benchmark function's points are scored
    here (the client unused: None).
    """
    if scored_here(config.env):
        rows = evaluate_points(solutions, config.measures, env_name=config.env)
        return rows[:, 0], rows[:, 1:]
    seeds = reset_seeds(solutions, config)
    futures = submit_flights(client, solutions, seeds, config.measures, config.fast_env,
                             env_name=config.env, policy=config.network, episode=episode_of(config))
    return averaged(per_terrain(client.gather(futures), seeds))


class ClusterShare:
    """The cluster's worker threads, which size a driver's chunks: asked of the scheduler at most
    every `every` seconds rather than for every batch (a round trip), since workers come and go
    and a stale count only sizes the chunks, never changes a result. Runs of other drivers on
    the same scheduler are not counted: no measurement showed that counting them pays (the
    recipes give each part its own scheduler). A scheduler that cannot answer keeps the last
    count: if it is lost, the driver says so (Driver.check_connected), rather than the run whose
    batch was being sized failing with the question's broken connection."""

    def __init__(self, client, every: float = 2.0) -> None:
        self.client, self.every = client, every
        self.asked_at, self.worker_threads = -float("inf"), 1

    def __call__(self, own_runs: int) -> tuple[int, int]:
        """(worker threads, runs sharing them): the driver's own runs, as they are now."""
        if time.monotonic() - self.asked_at > self.every:
            self.asked_at = time.monotonic()
            try:
                self.worker_threads = sum(self.client.nthreads().values())
            except OSError:  # the comm's faults (CommClosedError, a reset, a refused connection)
                pass
        return self.worker_threads, own_runs
