#!/usr/bin/env python
"""Search Gymnasium's Lunar Lander for many different good landings with CMA-ME (pyribs), on Dask.

The problem, the algorithm and the results follow the pyribs tutorial "Using CMA-ME to Land a Lunar
Lander Like a Space Shuttle"; this script adds what a research run needs around them: a Dask
evaluation engine, seeded and repeatable runs, checkpoints, metrics, plots and a CLI.

    python lunar_lander.py --iterations 300 --workers 2     # search; writes outputs/<run>/
    python lunar_lander.py --algorithm cma_mae               # or map_elites; default cma_me
    python lunar_lander.py --measures fuel,flight_time --env_seed 0-4   # other axes, 5 terrains
    python lunar_lander.py resume outputs/RUN                # continue a run from its checkpoint
    python lunar_lander.py experiment --algorithms "[cma_me, cma_mae]" --seeds 1-5   # many runs
    python lunar_lander.py video outputs/RUN --cells "[(-0.4, -0.1)]"   # or --best, --top K
    python lunar_lander.py elites outputs/RUN --min_objective 200       # table of elites
    python lunar_lander.py trajectories outputs/RUN --top 10            # flight paths picture
    python lunar_lander.py evaluate outputs/RUN --env_seeds 0-19        # robustness on terrains
    python lunar_lander.py explore outputs/RUN                          # browse, watch landings
    python lunar_lander.py compare outputs/RUN_A outputs/EXPERIMENT     # statistics across seeds
    python lunar_lander.py COMMAND --help                    # every flag of a command

Where to change what (the file reads top to bottom in this order):
- The problem. A measure: add a row to MEASURES (label, range, short name, how a Flight gives
  it); `fly` gathers what measures read from an episode. The objective is `Flight.reward`.
- The algorithms: a row of ALGORITHMS (archive kwargs, emitter class and kwargs).
- The evaluation engine: `submit_flights` chunks (solution, terrain) pairs for Dask; `fly_chunk`
  runs on the workers; `evaluate_batch` averages each solution over the run's terrains.
- The run: `Run` holds one search between iterations and is the one place a checkpoint is built
  and written; `run_loop` is ask -> evaluate -> tell; `save_outputs` writes the run folder's files,
  in a `Saver` thread while the search goes on.
- The commands: `search` and `resume`; `experiment` (`Experiment` drives many `Run`s on one
  cluster with as_completed); then the results commands (video, elites, trajectories, evaluate,
  explore with its page EXPLORER_PAGE near the end, compare with the statistics). A flag is
  declared, documented and defaulted in its command's signature and docstring; FLAG_CHECKS
  says how it is checked; COMMANDS lists the commands.
- The machinery: flag checks, folder locks, atomic file writes, logs, the streamlined env
  (FastLunarLander), and `main`, which turns bad input into one line and exit code 2 (and
  `exit_now`, which skips the interpreter's teardown).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import datetime
import errno
import functools
import importlib
import itertools
import json
import logging
import math
import os
import pickle
import platform
import secrets
import shutil
import signal
import sys
import tempfile
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator

import Box2D
import gymnasium as gym
import numpy as np
from Box2D.b2 import edgeShape, fixtureDef, polygonShape, revoluteJointDef
from gymnasium.envs.box2d import lunar_lander as upstream
from gymnasium.utils import seeding

# Plots are written to files, never shown: no display is needed (set before matplotlib loads).
os.environ.setdefault("MPLBACKEND", "Agg")
# ribs' CMA-ES code is written for numba, which compiles it on the first ask/tell of a process
# (3-8 s). For 32 parameters the uncompiled code is as fast once warm (1.4 vs 1.3 ms per ask+tell,
# measured) and gives bitwise-identical results, so compilation is off unless asked for.
os.environ.setdefault("NUMBA_DISABLE_JIT", "1")

# Dask spawns worker processes that re-import this script, so the heavy libraries that only the
# main process needs (ribs, matplotlib, dask itself) are imported inside the functions using them.
if __name__ == "__mp_main__":
    # A local worker: Ctrl-C in a terminal reaches the whole process group, but stopping is the
    # main process's job (it abandons the iteration and closes the cluster), so workers ignore it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class UsageError(Exception):
    """Bad input from the user: reported as one line on stderr, exit code 2."""


class RunError(Exception):
    """A fault of the machine, not of the input (a full disk, a lost cluster): one line on stderr,
    exit code 1, and nothing already written is lost."""


# ================================================================================================
# The problem: a linear policy flying Lunar Lander, and what its flight is measured by
# ================================================================================================

ENV_ID = "LunarLander-v3"
ACTION_DIM, OBS_DIM = 4, 8  # discrete actions; observation (x, y, vx, vy, angle, spin, leg1, leg2)
SOLUTION_DIM = ACTION_DIM * OBS_DIM
NOOP, LEFT, MAIN, RIGHT = range(ACTION_DIM)  # the discrete actions: engines off, or one fires


def make_env(fast: bool = True, render_mode: str | None = None) -> gym.Env:
    """The environment rollouts fly in: the streamlined copy below, or gym.make's plain one
    (needed to render, and kept as the reference the streamlined one is tested against)."""
    if fast and render_mode is None:
        return FastLunarLander()
    return gym.make(ENV_ID, render_mode=render_mode)


@dataclasses.dataclass
class Flight:
    """One episode summed up: everything a measure may read, gathered in a single pass.

    "Touchdown" is the first step on which either leg touches the ground. A lander that never
    touches it has no touchdown; its impact observation is then its last one.
    """

    reward: float = 0.0  # the episode's total reward: the objective
    steps: int = 0
    touchdown: np.ndarray | None = None  # the observation at touchdown
    touchdown_step: int | None = None
    last: np.ndarray | None = None  # the last observation
    min_y_velocity: float = math.inf  # the fastest descent of the whole episode
    max_tilt: float = 0.0  # the largest |angle| up to touchdown (the whole episode without one)
    firings: list[int] = dataclasses.field(default_factory=lambda: [0] * ACTION_DIM)

    @property
    def impact(self) -> np.ndarray:
        return self.last if self.touchdown is None else self.touchdown


@dataclasses.dataclass(frozen=True)
class Measure:
    """One behaviour a landing is told apart by: its axis label, its range in the archive (values
    outside fall into the edge cells), a short name for file names, and how a flight gives it."""

    label: str
    range: tuple[float, float]
    short: str
    of: Callable[[Flight], float]
    descending: bool = False  # its axis drawn from the lower bound at the top (the tutorial puts the
    # fastest impacts, the most negative y-velocities, on top)


# The measures a search can use (--measures picks 1 to 3, in order). Each is computed per terrain
# and averaged over the run's terrains. The ranges hold what the policies of real runs reach: an
# elite on an edge cell of a 50-cell axis is rare (README, "Measures"). To add one, add a row.
MEASURES: dict[str, Measure] = {
    # The tutorial's two: where and how fast the lander comes down (without a touchdown: its last
    # x-position and its fastest descent).
    "impact_x": Measure("Impact x-position", (-1.0, 1.0), "x", lambda f: f.impact[0]),
    "impact_y_velocity": Measure(
        "Impact y-velocity", (-3.0, 0.0), "v", descending=True,
        of=lambda f: f.min_y_velocity if f.touchdown is None else f.touchdown[3]),
    "impact_x_velocity": Measure("Impact x-velocity", (-3.0, 3.0), "vx", lambda f: f.impact[2]),
    # Angles are not wrapped: a lander that tumbles goes past pi, into the edge cells.
    "impact_angle": Measure("Impact angle (rad)", (-math.pi, math.pi), "angle", lambda f: f.impact[4]),
    # Fuel in main-engine firings: a side firing costs a tenth of one, as in the env's reward.
    "fuel": Measure("Fuel burnt (main-engine firings)", (0.0, 600.0), "fuel",
                    lambda f: f.firings[MAIN] + 0.1 * (f.firings[LEFT] + f.firings[RIGHT])),
    # A lander falling freely touches down after ~51 steps; one that hovers flies all 1000.
    "flight_time": Measure("Steps to touchdown", (50.0, 1000.0), "steps",
                           lambda f: f.steps if f.touchdown_step is None else f.touchdown_step),
    "max_tilt": Measure("Largest tilt before touchdown (rad)", (0.0, math.pi), "tilt",
                        lambda f: f.max_tilt),
}
TUTORIAL_MEASURES = ("impact_x", "impact_y_velocity")  # the default, and what old run folders used


def fly(solution: np.ndarray, env_seed: int, env: gym.Env, trajectory: list | None = None,
        on_step: Callable[[int, np.ndarray], None] | None = None) -> Flight:
    """Fly the policy action = argmax(W @ obs) for one episode on the terrain of `env_seed`.

    With a `trajectory` list, each step's (x, y) position is appended to it; `on_step` is called
    with each step's action and observation (the explorer records poses with it).
    """
    if trajectory is not None:
        def on_step(action: int, obs: np.ndarray) -> None:
            trajectory.append((float(obs[0]), float(obs[1])))
    weights = np.asarray(solution, dtype=np.float64).reshape(ACTION_DIM, OBS_DIM)
    # W.dot(obs) makes the same BLAS call as W @ obs (same bits) for less overhead; a strided W
    # would take matmul's non-BLAS path, so it keeps matmul.
    scores = weights.dot if weights.flags.c_contiguous else weights.__matmul__
    obs, _ = env.reset(seed=env_seed)
    flight, firings, done = Flight(), [0] * ACTION_DIM, False
    total_reward, min_y_velocity, max_tilt, touchdown, steps = 0.0, math.inf, 0.0, None, 0
    while not done:
        action = int(scores(obs).argmax())
        firings[action] += 1
        obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        steps += 1
        total_reward += reward
        if obs[3] < min_y_velocity:
            min_y_velocity = obs[3]
        if touchdown is None:
            max_tilt = max(max_tilt, abs(float(obs[4])))
            if obs[6] or obs[7]:
                touchdown, flight.touchdown_step = obs, steps
        if on_step is not None:
            on_step(action, obs)
    flight.reward, flight.steps, flight.touchdown, flight.last = total_reward, steps, touchdown, obs
    flight.min_y_velocity, flight.max_tilt, flight.firings = float(min_y_velocity), max_tilt, firings
    return flight


def rollout(solution: np.ndarray, env_seed: int, env: gym.Env,
            measures: tuple[str, ...] = TUTORIAL_MEASURES,
            trajectory: list | None = None) -> tuple[float, ...]:
    """(objective, *measures) of one episode: the objective is the episode's total reward."""
    flight = fly(solution, env_seed, env, trajectory)
    return (float(flight.reward), *(float(MEASURES[name].of(flight)) for name in measures))


# ================================================================================================
# The algorithm: an archive of elites, emitters that propose solutions, a scheduler tying them
# ================================================================================================

MAX_CELLS = 1_000_000  # --grid ** len(--measures): each cell keeps a 32-number solution
QD_SCORE_OFFSET = -600.0  # almost every policy scores above -600, so QD score counts every elite

# One row per algorithm, in the spirit of pyribs' examples/sphere.py: the flags only it uses (an
# experiment sweeps them for it alone; labels name them for it alone), the archive's extra kwargs,
# whether a separate result archive keeps the elites, and the emitter class with its kwargs, each
# a small function of the run's config. All rows share the grid, the seeds, x0 and the batch size,
# so every algorithm asks n_emitters * batch_size solutions per iteration.
# - cma_me: the tutorial's CMA-ME (EvolutionStrategyEmitter, two-stage improvement ranker).
# - cma_mae: pyribs' CMA-MAE tutorial and sphere.py's "cma_mae" row: a soft archive with
#   learning_rate (--learning_rate; 0.01 there, 0.5 here: see the README) and threshold_min (0
#   there for objectives in [0, 100]; here the QD offset -600, below almost every episode's
#   reward), a plain result archive of the same grid that keeps the best solutions (metrics,
#   heatmaps and archive.pkl come from it), and emitters with the "imp" ranker, "mu" selection
#   and "basic" restarts.
# - map_elites: sphere.py's "map_elites" row: GaussianEmitters that mutate random elites with a
#   fixed sigma (--sigma0). The policy argmax(W @ obs) ignores W's scale and the search starts
#   from zeros, so only sigma relative to the elites' weights matters, as for CMA-ES's sigma0.
ALGORITHMS: dict[str, dict[str, Any]] = {
    "cma_me": {
        "flags": (),
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config["sigma0"], "ranker": "2imp"},
    },
    "cma_mae": {
        "flags": ("learning_rate",),
        "archive": lambda config: {"learning_rate": config["learning_rate"],
                                   "threshold_min": QD_SCORE_OFFSET},
        "result_archive": True,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config["sigma0"], "ranker": "imp",
                                          "selection_rule": "mu", "restart_rule": "basic"},
    },
    "map_elites": {
        "flags": (),
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "GaussianEmitter",
        "emitter_kwargs": lambda config: {"sigma": config["sigma0"]},
    },
}


ALGORITHM_FLAGS = {flag for spec in ALGORITHMS.values() for flag in spec["flags"]}


def ignores(algorithm: str, flag: str) -> bool:
    """Whether the algorithm ignores the flag (another algorithm's own, like cma_mae's rate)."""
    return flag in ALGORITHM_FLAGS and flag not in ALGORITHMS[algorithm]["flags"]


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent seeds for the archive and each emitter, all fixed by the one run seed."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(count)]


def archive_grid(config: dict[str, Any]) -> dict[str, Any]:
    """The archive's cells: --grid of them along each of the run's --measures, over its range."""
    measures = config["measures"]
    return dict(solution_dim=SOLUTION_DIM, dims=(config["grid"],) * len(measures),
                ranges=[MEASURES[name].range for name in measures], qd_score_offset=QD_SCORE_OFFSET)


def build_scheduler(config: dict[str, Any], x0: np.ndarray | None = None):
    """The archive, emitters and scheduler of `config["algorithm"]`, seeded from `config["seed"]`.

    The emitters start from `x0` (default: zeros, as in the tutorial).
    """
    from ribs import emitters as ribs_emitters
    from ribs.archives import GridArchive
    from ribs.schedulers import Scheduler

    spec = ALGORITHMS[config["algorithm"]]
    # A result archive's seed comes last, so the other seeds are those of a run without one.
    archive_seed, *emitter_seeds, result_seed = derive_seeds(config["seed"], config["n_emitters"] + 2)
    grid = archive_grid(config)
    archive = GridArchive(**grid, seed=archive_seed, **spec["archive"](config))
    result_archive = GridArchive(**grid, seed=result_seed) if spec["result_archive"] else None
    emitter_class = getattr(ribs_emitters, spec["emitter"])
    emitters = [
        emitter_class(
            archive,
            x0=np.zeros(SOLUTION_DIM) if x0 is None else x0,
            batch_size=config["batch_size"],
            seed=emitter_seed,
            **spec["emitter_kwargs"](config),
        )
        for emitter_seed in emitter_seeds
    ]
    return Scheduler(archive, emitters, result_archive=result_archive)


# ================================================================================================
# The evaluation engine: batches of rollouts on a Dask cluster
# ================================================================================================

_WORKER_ENVS: dict[bool, gym.Env] = {}  # one environment per worker process, reused across tasks


def fly_chunk(solutions: np.ndarray, env_seeds: np.ndarray, measures: tuple[str, ...],
              fast_env: bool = True) -> np.ndarray:
    """Runs on a worker: fly solutions[i] on terrain env_seeds[i]; rows of (objective, *measures).

    A chunk of rollouts per task (not one task per rollout) keeps the scheduler's per-task cost
    small next to the rollouts, and the environment is kept between tasks: reset(seed) gives the
    same episode bit for bit as a fresh environment, without paying for gym.make each time.
    """
    env = _WORKER_ENVS.get(fast_env)
    if env is None:
        env = _WORKER_ENVS[fast_env] = make_env(fast_env)
    rows = [rollout(solution, int(seed), env, measures) for solution, seed in zip(solutions, env_seeds)]
    return np.array(rows).reshape(-1, 1 + len(measures))


# Two chunks per worker even out episodes of 60 to 1000 steps across workers as well as more do
# (measured: 1, 2, 3, 4, 8), while each task costs the main process ~0.6 ms of scheduling.
CHUNKS_PER_WORKER = 2
MIN_CHUNK = 4  # rollouts per task at least, on big clusters: a task costs ~0.6 ms to schedule
MAX_CHUNK = 1000  # rollouts per task at most (a few seconds), so big batches report progress


def by_reference(function: Callable) -> Callable:
    """The same function, reached through this script's import name instead of `__main__`.

    Dask pickles functions of `__main__` by value into every task; through the module name they
    travel as a short reference that workers resolve by importing this script.
    """
    if function.__module__ != "__main__":
        return function
    return getattr(importlib.import_module(Path(__file__).stem), function.__name__)


def submit_flights(client, solutions: np.ndarray, env_seeds: list[int], measures: tuple[str, ...],
                   fast_env: bool = True, sharing: int = 1) -> list:
    """Send every solution to be flown on every terrain; the futures of the chunks, in order.

    The work is the (solution, terrain) pairs, split into chunks of about equal count whatever
    the number of terrains, so the workers stay evenly loaded. A batch alone on the cluster is
    split in CHUNKS_PER_WORKER chunks per worker; when `sharing` runs keep the workers busy
    together, each batch needs only its share of that, and fewer tasks cost the scheduler less.
    The chunks go in one message (client.map); tasks of a dead worker are retried.
    """
    workers = max(1, sum(client.nthreads().values()))
    pairs = len(solutions) * len(env_seeds)
    wanted = max(-(-CHUNKS_PER_WORKER * workers // max(1, sharing)), -(-pairs // MAX_CHUNK))
    chunks = np.array_split(np.arange(pairs), min(wanted, max(1, pairs // MIN_CHUNK)))
    seeds = np.tile(np.asarray(env_seeds, dtype=np.int64), len(solutions))
    return client.map(by_reference(fly_chunk), [solutions[chunk // len(env_seeds)] for chunk in chunks],
                      [seeds[chunk] for chunk in chunks], [tuple(measures)] * len(chunks),
                      [fast_env] * len(chunks), pure=False, retries=3)


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


def evaluate_batch(client, solutions: np.ndarray, config: dict) -> tuple[np.ndarray, np.ndarray]:
    """Objectives and measures of `solutions` in the run's setting, flown on the Dask cluster.

    Results come back in the order of the solutions whatever the number of workers, so a fixed
    seed gives the same archive on 1 or 100 workers.
    """
    futures = submit_flights(client, solutions, config["env_seed"], config["measures"],
                             config["fast_env"])
    return averaged(per_terrain(client.gather(futures), config["env_seed"]))


def ship_script(client) -> None:
    """Make this exact script importable by the scheduler and every worker of a cluster.

    Tasks refer to `lunar_lander.fly_chunk` by name, so the scheduler (which unpickles task
    graphs) and the workers must import this script. Machines elsewhere have the libraries but not
    the script, or an older copy: then it is uploaded (to workers that join later too). Where all
    already import this very file (a local cluster), nothing is reloaded.
    """
    import hashlib

    def digest_of_importable_script() -> str | None:  # runs on the scheduler and the workers
        import hashlib
        import importlib.util

        spec = importlib.util.find_spec("lunar_lander")
        if spec is None or not spec.origin:
            return None
        with open(spec.origin, "rb") as file:
            return hashlib.sha256(file.read()).hexdigest()

    path = Path(__file__).resolve()
    ours = hashlib.sha256(path.read_bytes()).hexdigest()
    theirs = [client.run_on_scheduler(digest_of_importable_script),
              *client.run(digest_of_importable_script).values()]
    if any(digest != ours for digest in theirs):
        client.upload_file(str(path))


# What a run imports while its cluster starts (ribs alone brings scikit-learn, scipy, numba and
# pandas: ~2 s of the main process).
RUN_IMPORTS = ("ribs.archives", "ribs.emitters", "ribs.schedulers", "ribs.visualize",
               "matplotlib.pyplot", "matplotlib.backends.backend_agg", "pandas.io.formats.csvs", "tqdm")


@contextlib.contextmanager
def preloading(modules: tuple[str, ...]) -> Iterator[None]:
    """Import `modules` in a thread while the block runs. A local cluster's start is mostly the
    main process waiting for its worker processes to spawn and import: time to import what comes
    next. An import that fails here (even one of Python's rare cross-thread import deadlocks)
    costs nothing: the module is imported again where it is used."""
    import threading

    def load() -> None:
        for module in modules:
            with contextlib.suppress(Exception):
                importlib.import_module(module)

    thread = threading.Thread(target=load, name="preload", daemon=True)
    thread.start()
    try:
        yield
    finally:
        thread.join()


@contextlib.contextmanager
def dask_client(workers: int, scheduler_address: str | None, log: logging.Logger) -> Iterator[Any]:
    """A Dask client: of an existing cluster if `scheduler_address` is given (left running on
    exit), else of a new local cluster of `workers` single-threaded processes (shut down on exit).

    A local cluster listens on localhost only: it runs whatever code it is sent.
    """
    import dask
    from dask.distributed import Client, LocalCluster

    logging.getLogger("asyncio").addFilter(not_dask_stop)  # once: the same filter is kept once
    if scheduler_address:
        try:
            client = Client(scheduler_address, timeout="20s")
        except (OSError, ValueError) as error:
            raise UsageError(f"cannot connect to the Dask scheduler at {scheduler_address}: "
                             f"{str(error).splitlines()[0]}") from None
        with client:
            ship_script(client)
            log.info(f"Dask cluster at {scheduler_address}: {len(client.nthreads())} worker(s); "
                     f"dashboard {client.dashboard_link}")
            yield client
        return
    # A busy port 8787 (another run's dashboard) is fine: Dask picks another and we print it.
    warnings.filterwarnings("ignore", message="Port 8787 is already in use")
    # The imports are over before the search starts: ribs' CMA-ES rebuilds its thread-pool
    # controller whenever the number of imported modules has changed.
    with preloading(RUN_IMPORTS), dask.config.set(QUIET_CLUSTER):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address="127.0.0.1:8787",
                               silence_logs=logging.ERROR)
    with cluster, Client(cluster) as client:
        log.info(f"Dask cluster: {workers} worker process(es); dashboard {client.dashboard_link}")
        yield client


def not_dask_stop(record: logging.LogRecord) -> bool:
    """Ctrl-C during a gather leaves Dask's wait task with its AllExit, which asyncio would print
    with a traceback when it is collected: the stop is ours, and is reported in one line."""
    return not (record.exc_info and type(record.exc_info[1]).__name__ == "AllExit")


# Dask's housekeeping runs in the main process (the scheduler, and the nannies of the local
# workers): at its default pace (memory checks every 100 ms per worker, system monitor every
# 500 ms, event-loop ticks every 20 ms) it took ~6% of a core here, from the workers' 2 cores.
QUIET_CLUSTER = {"distributed.worker.memory.monitor-interval": "1s",
                 "distributed.admin.system-monitor.interval": "2s",
                 "distributed.admin.tick.interval": "200ms"}


# ================================================================================================
# The run: ask -> evaluate -> tell, with metrics, checkpoints and outputs
# ================================================================================================

class StopRequests:
    """Ctrl-C and SIGTERM, acted on only where stopping is safe.

    A signal only records the request, except inside `interruptible()` (waiting for the cluster's
    results), where it stops the wait at once. So a stop never cuts a checkpoint write, an import
    or a tell in half: the iteration in flight is abandoned and the last completed one is kept.
    """

    def __init__(self) -> None:
        self.requested = False
        self._raise_now = False

    def install(self) -> None:
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._on_signal)

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.requested = True
        if self._raise_now:
            self._raise_now = False
            raise KeyboardInterrupt

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        self.check()
        self._raise_now = True
        try:
            yield
        finally:
            self._raise_now = False


STOP = StopRequests()
CHECKPOINT_FORMAT = "lunar_lander.checkpoint/1"


def iteration_metrics(archive, iteration: int, evaluations: int, elapsed: float) -> dict:
    """One row of metrics.json: the archive's state after `iteration` iterations."""
    stats = archive.stats
    return {
        "iteration": iteration,
        "evaluations": evaluations,
        "coverage": float(stats.coverage),
        "num_elites": int(stats.num_elites),
        "qd_score": float(stats.qd_score),
        "best_objective": float(stats.obj_max) if stats.num_elites else None,
        "mean_objective": float(stats.obj_mean) if stats.num_elites else None,
        "elapsed_s": round(elapsed, 3),
    }


class Saver(ThreadPoolExecutor):
    """The thread run folders are written in while the search goes on (one thread: the plots'
    matplotlib is not thread-safe). Leaving it waits for the writes and raises the first fault."""

    def __init__(self) -> None:
        super().__init__(1, thread_name_prefix="save")
        self.writes: list[Future] = []

    def submit(self, function: Callable, /, *args: Any) -> Future:
        self.writes.append(super().submit(function, *args))
        return self.writes[-1]

    def __exit__(self, *exc_info: Any) -> None:
        super().__exit__(*exc_info)
        if exc_info[0] is None:
            for write in self.writes:
                write.result()


class Run:
    """One search between two iterations, and the folder it is saved to.

    The checkpoint is built and written here only. It always holds the last completed iteration:
    ask() moves the emitters on, so the scheduler is snapshotted (pickled, ~1 ms) after every tell,
    and a stop or a fault while the cluster evaluates writes that snapshot. The iteration in flight
    is abandoned, never half-recorded. The scheduler is pickled as one object (its emitters share
    its archive; CMA-ES state and RNGs come along), so a resumed run asks exactly the same.

    The folder's files may be written in a thread while the search goes on (`save(saver)`):
    they are built from that snapshot, so nothing the run does next can change them.
    """

    def __init__(self, run_dir: Path, config: dict, scheduler, metrics: list[dict]) -> None:
        self.dir, self.config, self.scheduler, self.metrics = run_dir, config, scheduler, metrics
        self.snapshot = pickle.dumps(scheduler, protocol=pickle.HIGHEST_PROTOCOL)
        self.saved = self.iteration
        self.pending: Future | None = None  # a save being written by the saver thread
        self._asked_at = 0.0

    @classmethod
    def start(cls, run_dir: Path, config: dict, client, log: logging.Logger,
              seed_archive=None) -> Run:
        """Iteration 0 of a new run, checkpointed at once so the folder always holds one.

        With `seed_archive` (a warm start), its elites are first flown again in this run's setting
        (another terrain, say) and inserted, and the emitters start from the best of them.
        """
        if seed_archive is None:
            run = cls(run_dir, config, build_scheduler(config), [])
        else:
            elites = seed_archive.data(["solution"])["solution"]
            objectives, measures = evaluate_batch(client, elites, config)
            scheduler = build_scheduler(config, x0=elites[int(np.argmax(objectives))])
            for archive in {id(a): a for a in (scheduler.archive, scheduler.result_archive)}.values():
                archive.add(elites, objectives, measures)
            run = cls(run_dir, config, scheduler,
                      [iteration_metrics(scheduler.result_archive, 0, len(elites), 0.0)])
            log.info(f"Warm start: {len(elites)} elites re-evaluated, {len(scheduler.result_archive)} "
                     f"kept; emitters start from the best (objective {objectives.max():.1f})")
        run.save_checkpoint(force=True)
        return run

    @classmethod
    def from_checkpoint(cls, run_dir: Path, checkpoint: dict) -> Run:
        return cls(run_dir, checkpoint["config"], checkpoint["scheduler"], checkpoint["metrics"])

    @property
    def iteration(self) -> int:
        return self.metrics[-1]["iteration"] if self.metrics else 0  # a warm start has iteration 0

    def ask(self) -> np.ndarray:
        self._asked_at = time.perf_counter()
        return self.scheduler.ask()

    def tell(self, objectives: np.ndarray, measures: np.ndarray) -> dict:
        """Record the evaluated batch; returns the new row of metrics."""
        self.scheduler.tell(objectives, measures)
        self.snapshot = pickle.dumps(self.scheduler, protocol=pickle.HIGHEST_PROTOCOL)
        last = self.metrics[-1] if self.metrics else {"evaluations": 0, "elapsed_s": 0.0}
        self.metrics.append(iteration_metrics(
            self.scheduler.result_archive, self.iteration + 1, last["evaluations"] + len(objectives),
            last["elapsed_s"] + time.perf_counter() - self._asked_at))
        return self.metrics[-1]

    def checkpoint(self) -> dict:
        """Everything needed to continue the run, as of the last completed iteration."""
        return {"format": CHECKPOINT_FORMAT, "scheduler": pickle.loads(self.snapshot),
                "metrics": list(self.metrics), "iteration": self.iteration, "config": self.config}

    def save_checkpoint(self, force: bool = False) -> None:
        """Write the checkpoint if iterations were completed since the last save (after the save
        in the saver thread, whose fault, if any, is raised once the checkpoint is written)."""
        try:
            self.settle()
        finally:
            if force or self.iteration > self.saved:
                write_pickle(self.dir / "checkpoint.pkl", self.checkpoint())
                self.saved = self.iteration

    def save(self, saver: Saver | None = None) -> None:
        """Refresh every file of the run folder, the checkpoint first; with a `saver`, in its
        thread, so the workers are fed meanwhile."""
        self.settle()
        checkpoint = self.checkpoint()
        if saver is None:
            self.write(checkpoint)
        else:
            self.pending = saver.submit(self.write, checkpoint)

    def write(self, checkpoint: dict) -> None:
        write_pickle(self.dir / "checkpoint.pkl", checkpoint)
        self.saved = checkpoint["iteration"]
        save_outputs(self.dir, checkpoint)

    def settle(self, wait: bool = True) -> None:
        """Wait for the save in the saver thread (without `wait`: only if it is over); raise its
        fault, so a full disk stops the run at once."""
        if self.pending is not None and (wait or self.pending.done()):
            pending, self.pending = self.pending, None
            pending.result()


def run_loop(run: Run, client, iterations: int, log: logging.Logger, saver: Saver) -> None:
    """Iterate ask -> evaluate -> tell up to `iterations`, refreshing the run folder every
    log_every iterations and at the end, in the saver's thread: the workers fly the next
    iterations meanwhile, and the cluster shuts down during the last write. A stop or a fault
    keeps the last completed iteration."""
    from tqdm import tqdm

    bar = tqdm(range(run.iteration + 1, iterations + 1), initial=run.iteration, total=iterations,
               unit="it", desc="search", dynamic_ncols=True)
    try:
        for iteration in bar:
            STOP.check()
            solutions = run.ask()
            with STOP.interruptible():
                objectives, measures = evaluate_batch(client, solutions, run.config)
            row = run.tell(objectives, measures)
            run.settle(wait=False)  # a fault of the last write (a full disk) stops the run now
            bar.set_postfix(coverage=f"{row['coverage']:.3f}", qd=f"{row['qd_score']:.4g}",
                            best=f"{row['best_objective'] or float('nan'):.1f}", refresh=False)
            if iteration % run.config["log_every"] == 0 and iteration < iterations:
                log.info(describe_progress(row, iterations))
                run.save(saver)
    except BaseException as error:
        bar.close()
        try:
            run.save_checkpoint()
        except RunError:
            if not isinstance(error, RunError):  # a stop, or another fault: report this one
                raise
        raise
    bar.close()
    run.save(saver)
    if run.metrics:
        log.info("Done. " + describe_progress(run.metrics[-1], iterations))


def describe_progress(row: dict, iterations: int) -> str:
    best = row["best_objective"]
    return (f"iteration {row['iteration']}/{iterations}: {row['evaluations']} evaluations, "
            f"coverage {row['coverage']:.3f}, QD score {row['qd_score']:.0f}, "
            f"best {best if best is None else round(best, 1)}, "
            f"{row['elapsed_s'] / max(row['iteration'], 1):.2f} s/iteration")


def load_run_state(run_dir: Path) -> tuple[dict, dict | None]:
    """A run folder's config and checkpoint. A run killed before its first checkpoint (while its
    cluster started) has only config.json: its checkpoint is None, and resume starts it afresh
    from that config, which records the seed, so it ends as the uninterrupted run would."""
    path = run_dir / "checkpoint.pkl"
    if path.is_file() or not (run_dir / "config.json").is_file():
        checkpoint = load_checkpoint(path)
        return checkpoint["config"], checkpoint
    recorded = read_run_json(run_dir, "config.json")
    try:
        return check_run_config(recorded), None
    except UsageError as error:
        raise UsageError(f"{run_dir / 'config.json'}: not a usable run config ({error})") from None


def check_archive(archive: Any, path: Path, config: dict) -> None:
    """The archive must be the grid of the run's config: solution size, cells, measure ranges."""
    from ribs.archives import GridArchive

    if not isinstance(archive, GridArchive):
        raise UsageError(f"{path}: holds a {type(archive).__name__}, not a GridArchive")
    grid = archive_grid(config)
    shape = (archive.solution_dim, tuple(archive.dims), np.round(archive.lower_bounds, 9).tolist(),
             np.round(archive.upper_bounds, 9).tolist())
    lower, upper = zip(*grid["ranges"])
    expected = (grid["solution_dim"], tuple(grid["dims"]), np.round(lower, 9).tolist(),
                np.round(upper, 9).tolist())
    if shape != expected:
        raise UsageError(f"{path}: archive of another shape (solution size, grid, lower and upper "
                         f"bounds {shape}; the run's --measures {','.join(config['measures'])} and "
                         f"--grid {config['grid']} need {expected})")


def check_archive_size(config: dict) -> None:
    if config["grid"] ** len(config["measures"]) > MAX_CELLS:
        raise UsageError(f"--grid {config['grid']} with {len(config['measures'])} measures makes "
                         f"{config['grid'] ** len(config['measures']):,} cells; at most {MAX_CELLS:,}")


def load_archive(path: Path, config: dict):
    """A saved archive, checked against the config of the run that uses it."""
    archive = read_pickle(path, "archive pickle")
    check_archive(archive, path, config)
    if len(archive) == 0:
        raise UsageError(f"{path}: the archive is empty; nothing to start from")
    return archive


def search_defaults() -> dict[str, Any]:
    import inspect

    return {name: parameter.default for name, parameter in inspect.signature(search).parameters.items()}


# What runs recorded before a flag existed ran with, where that is not the flag's default today.
BEFORE_THE_FLAG = {"learning_rate": 0.01}


def check_run_config(config: Any) -> dict:
    """A run's recorded config, every flag valid (a UsageError says which is not); a config from
    before a flag existed ran with what that flag now sets it to (BEFORE_THE_FLAG, or the default)."""
    try:
        config = {**search_defaults(), **BEFORE_THE_FLAG, **config}
        config.update(check_flags({name: config[name] for name in FLAG_CHECKS}))
    except TypeError as error:
        raise UsageError(str(error)) from None
    non_negative_int("seed", config["seed"])
    return config


def load_checkpoint(path: Path) -> dict:
    """A checkpoint written by this script and consistent with this script's problem."""
    if not path.is_file():
        raise UsageError(f"{path}: no checkpoint there (is {path.parent} a run folder of lunar_lander.py?)")
    checkpoint = read_pickle(path, "checkpoint")
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise UsageError(f"{path}: not a lunar_lander checkpoint (holds a {type(checkpoint).__name__})")
    from ribs.schedulers import Scheduler

    try:
        checkpoint["config"] = check_run_config(checkpoint["config"])
        metrics, iteration = checkpoint["metrics"], checkpoint["iteration"]
        if not isinstance(checkpoint["scheduler"], Scheduler):
            raise UsageError(f"holds a {type(checkpoint['scheduler']).__name__}, not a Scheduler")
    except (KeyError, TypeError, UsageError) as error:
        raise UsageError(f"{path}: checkpoint of an incompatible config ({error})") from None
    if [row["iteration"] for row in metrics if row["iteration"] > 0] != list(range(1, iteration + 1)):
        raise UsageError(f"{path}: its metrics do not match its iteration {iteration}")
    check_archive(checkpoint["scheduler"].archive, path, checkpoint["config"])
    return checkpoint



HEATMAP_RANGE = (-300, 300)


def save_heatmap(archive, measures: list[str], path: Path, title: str) -> None:
    """The tutorial's heatmap: objective per cell (the fastest impacts on top). One measure
    gives a strip; with three, each cell of the first two shows the best elite over the third."""
    import matplotlib.pyplot as plt
    from ribs.archives import GridArchive
    from ribs.visualize import grid_archive_heatmap

    if archive.measure_dim == 3:
        data = archive.data(["solution", "objective", "measures"])
        shown = GridArchive(solution_dim=archive.solution_dim, dims=archive.dims[:2],
                            ranges=list(zip(archive.lower_bounds[:2], archive.upper_bounds[:2])))
        shown.add(data["solution"], data["objective"], data["measures"][:, :2])
        title += f" (best over {MEASURES[measures[2]].label.lower()})"
    else:
        shown = archive
    fig, ax = plt.subplots(figsize=(8, 6))
    fig.subplots_adjust(left=0.1, right=0.99, bottom=0.09, top=0.94)  # a fixed layout draws once
    grid_archive_heatmap(shown, ax=ax, vmin=HEATMAP_RANGE[0], vmax=HEATMAP_RANGE[1])
    ax.set_xlabel(MEASURES[measures[0]].label)
    if len(measures) > 1:
        ax.set_ylabel(MEASURES[measures[1]].label)
        if MEASURES[measures[1]].descending:
            ax.invert_yaxis()
    ax.set_title(title)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)


PROGRESS_PANELS = (("qd_score", "QD score"), ("coverage", "Coverage"),
                   ("best_objective", "Best objective"))


def save_progress_plot(metrics: list[dict], path: Path) -> None:
    """QD score, coverage and best objective over iterations, side by side."""
    save_metric_panels({"": [metrics]}, "iteration", "Iteration", path)


def save_metric_panels(groups: dict[str, list[list[dict]]], x_key: str, x_label: str,
                       path: Path) -> None:
    """One panel per metric of PROGRESS_PANELS, one line per group of runs (labelled if it has a
    label): a run's own curve, or for several runs their mean and its 95% confidence band."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PROGRESS_PANELS), figsize=(15, 4))
    # A fixed layout: tight_layout would cost more than the plotting (this runs in the search loop).
    fig.subplots_adjust(left=0.06, right=0.98, bottom=0.14, top=0.9, wspace=0.25)
    for ax, (key, label) in zip(axes, PROGRESS_PANELS):
        for group_label, runs in groups.items():
            length = min(len(metrics) for metrics in runs)
            values = np.array([[np.nan if row[key] is None else row[key] for row in metrics[:length]]
                               for metrics in runs], dtype=float)
            x = [row[x_key] for row in runs[0][:length]]
            line, = ax.plot(x, values.mean(axis=0), label=group_label or None)
            if len(runs) > 1:
                low, high = mean_band(values)
                ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
        ax.set_xlabel(x_label)
        ax.set_title(label)
        ax.grid(alpha=0.3)
    labelled = any(groups)
    if labelled:  # beside the panels, where it hides no curve
        axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1), fontsize="small")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100,
                                             bbox_inches="tight" if labelled else None))
    plt.close(fig)


def mean_band(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 95% bootstrap confidence band of the mean of the rows of `values`, point by point."""
    from scipy.stats import bootstrap

    with warnings.catch_warnings():  # points where every run has the same value: a band of width 0
        warnings.simplefilter("ignore")
        result = bootstrap((values,), np.mean, axis=0, vectorized=True, method="percentile",
                           n_resamples=2000, rng=np.random.default_rng(0))
    return result.confidence_interval.low, result.confidence_interval.high


def save_outputs(run_dir: Path, checkpoint: dict) -> None:
    """The run folder's files besides the checkpoint: metrics, archive, heatmaps, progress."""
    write_json(run_dir / "metrics.json", checkpoint["metrics"])
    archive = checkpoint["scheduler"].result_archive
    iteration = checkpoint["iteration"]
    write_pickle(run_dir / "archive.pkl", archive)
    table = archive.data(return_type="pandas")
    atomic_write(run_dir / "archive.csv", lambda f: table.to_csv(f, index=False), mode="w")
    title = f"{checkpoint['config']['algorithm']} after {iteration} iterations"
    snapshot = run_dir / "heatmaps" / f"heatmap_{iteration:05d}.png"
    save_heatmap(archive, checkpoint["config"]["measures"], snapshot, title)
    atomic_write(run_dir / "heatmap.png", lambda f: f.write(snapshot.read_bytes()))
    save_progress_plot(checkpoint["metrics"], run_dir / "progress.png")


# ================================================================================================
# The commands: search and resume
# ================================================================================================

def search(
    iterations: int = 300,
    workers: int = 2,
    seed: int | None = None,
    env_seed: Any = 52,
    measures: Any = TUTORIAL_MEASURES,
    grid: int = 50,
    algorithm: str = "cma_me",
    n_emitters: int = 5,
    sigma0: float = 1.0,
    batch_size: int = 30,
    learning_rate: float = 0.5,
    log_every: int = 25,
    outdir: str | None = None,
    scheduler_address: str | None = None,
    from_archive: str | None = None,
    fast_env: bool = True,
) -> None:
    """Search Lunar Lander landings with a QD algorithm and write a run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl, archive.pkl, archive.csv, metrics.json, heatmap.png, heatmaps/, progress.png,
    config.json and run.log. Other commands (each with --help): resume, experiment, video, elites,
    trajectories, evaluate, explore, compare.

    Args:
        iterations: Number of ask-evaluate-tell iterations.
        workers: Number of Dask worker processes (one thread each) evaluating rollouts.
        seed: Seed of the archive and emitters; drawn and recorded in config.json if omitted.
            The same seed gives the same archive whatever the number of workers.
        env_seed: The terrain(s) every policy is flown on: one seed (52), a range (0-4), a list
            (3,5,8) or both (0-4,10). With several terrains the objective is the mean return
            over them, and each measure is its per-terrain values averaged.
        measures: 1 to 3 of the MEASURES table's rows, comma-separated, as the archive's axes:
            impact_x, impact_y_velocity (the tutorial's, the default), impact_x_velocity,
            impact_angle, fuel, flight_time, max_tilt.
        grid: Archive cells along each measure.
        algorithm: Which QD algorithm: cma_me (the tutorial's CMA-ME), cma_mae (CMA-MAE) or
            map_elites (MAP-Elites with Gaussian mutation); each asks n_emitters * batch_size
            solutions per iteration.
        n_emitters: Number of emitters.
        sigma0: Initial step size of each emitter (CMA-ES sigma); map_elites: the fixed sigma
            of its Gaussian mutation.
        batch_size: Solutions each emitter proposes per iteration.
        learning_rate: cma_mae only: how fast a cell's threshold follows its improvements, in
            (0, 1]. 0.5 did best of 0.01, 0.1 and 0.5 over 6 seeds of 300 iterations (README,
            Algorithms); pyribs' 0.01 is for far longer runs; 1 makes the archive CMA-ME's.
        log_every: Log a line and refresh the run folder every this many iterations.
        outdir: Run folder; default outputs/<timestamp>_seed<seed>. Must be new or empty.
        scheduler_address: Address of a running Dask scheduler (tcp://HOST:PORT) to evaluate on
            instead of starting a local cluster; --workers is then ignored.
        from_archive: Warm start: an archive.pkl of an earlier run whose elites are re-evaluated
            in this run's setting to fill the archive first; the emitters start from the best.
        fast_env: Fly rollouts in the streamlined LunarLander-v3 (bitwise identical results,
            about a third less time per step); false uses gym.make's plain environment.
    """
    flags = check_flags(dict(locals()))
    check_archive_size(flags)
    seed_archive = load_archive(Path(from_archive), flags) if from_archive else None
    check_scheduler_reachable(scheduler_address)
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    with new_folder(flags["outdir"], f"seed{flags['seed']}") as run_dir:
        config = {**flags, "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
                  "command": sys.argv, "versions": library_versions()}
        if from_archive:
            config["from_archive"] = str(Path(from_archive).resolve())
        write_json(run_dir / "config.json", config)
        with run_session(run_dir, config["workers"], scheduler_address) as (client, log, saver):
            run = Run.start(run_dir, config, client, log, seed_archive)
            run_loop(run, client, config["iterations"], log, saver)


def resume(run_dir: str, iterations: int | None = None, workers: int | None = None,
           scheduler_address: str | None = None) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped; or,
    for an experiment folder, every unfinished run of the experiment.

    Args:
        run_dir: A run folder (or an experiment folder) written by this script.
        iterations: Total iterations to reach; default: those the run was started with. A larger
            number extends a finished run.
        workers: Number of Dask worker processes; default: as the run was started.
        scheduler_address: Address of a running Dask scheduler to evaluate on instead.
    """
    path = Path(run_dir)
    if (path / "experiment.json").is_file():
        return resume_experiment(path, iterations, workers, scheduler_address)
    load_run_state(path)  # refuse a bad folder before anything is written in it
    check_scheduler_reachable(scheduler_address)
    with folder_lock(path):
        config, checkpoint = load_run_state(path)  # as the last writer left it
        iterations = positive_int("iterations", config["iterations"] if iterations is None else iterations)
        workers = positive_int("workers", config["workers"] if workers is None else workers)
        done = checkpoint["iteration"] if checkpoint else 0
        if iterations < done:
            raise UsageError(f"{path} is already at iteration {done}; --iterations must be at least that")
        seed_archive = load_archive(Path(config["from_archive"]), config) if (
            checkpoint is None and config.get("from_archive")) else None
        config = {**config, "iterations": max(iterations, config["iterations"]),
                  "resumed": [*config.get("resumed", []), {
                      "at": datetime.datetime.now().isoformat(), "from_iteration": done,
                      "to_iteration": iterations, "workers": workers}]}
        write_json(path / "config.json", config)
        with run_session(path, workers, scheduler_address) as (client, log, saver):
            if checkpoint is None:
                run = Run.start(path, config, client, log, seed_archive)
            else:
                run = Run.from_checkpoint(path, {**checkpoint, "config": config})
            run_loop(run, client, iterations, log, saver)


@contextlib.contextmanager
def run_session(run_dir: Path, workers: int, scheduler_address: str | None) -> Iterator[tuple]:
    """The Dask client, the log and the saver of a command writing `run_dir`, shut down however
    it ends: the cluster first, while the saver finishes writing the folder.

    A stop or a fault (a full disk, a lost cluster) ends with one line that says which iteration
    the folder's checkpoint holds and the command that continues from it.
    """
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(run_dir / "run.log")
    with logging_redirect_tqdm(loggers=[log]):
        log.info(f"Run folder: {run_dir}")
        try:
            with Saver() as saver, dask_client(workers, scheduler_address, log) as client:
                yield client, log, saver
        except KeyboardInterrupt:
            log.info(f"Stopped; {checkpoint_state(run_dir)}")
            raise
        except (RunError, OSError) as error:
            raise RunError(f"{fault_text(error)}; {checkpoint_state(run_dir)}") from None


def checkpoint_state(run_dir: Path) -> str:
    """What a stopped or failed run folder holds, and the command that continues it."""
    try:
        held = f"its checkpoint holds iteration {read_pickle(run_dir / 'checkpoint.pkl', '')['iteration']}"
    except (UsageError, KeyError, TypeError):
        held = "it holds no checkpoint yet (resume starts the run from its config.json)"
    return f"{held}; continue with: python lunar_lander.py resume {run_dir}"


# ================================================================================================
# Experiments: many runs interleaved on one Dask cluster
# ================================================================================================

EXPERIMENT_FORMAT = "lunar_lander.experiment/1"
# Search flags the experiment sets itself: per run (seed, algorithm, folder) or for the cluster.
EXPERIMENT_OWN = {"seed", "algorithm", "outdir", "workers", "scheduler_address", "from_archive"}
# Search flags whose list of values is one more axis of the grid. (--env_seed and --measures take
# lists of their own: several terrains, several measures of every run.)
SWEEPABLE = ("n_emitters", "sigma0", "batch_size", "learning_rate", "grid")


def experiment(algorithms: Any = ("cma_me",), seeds: Any = "1-5", outdir: str | None = None,
               workers: int = 2, scheduler_address: str | None = None,
               max_in_flight: int | None = None, **search_flags: Any) -> None:
    """Run every combination of the listed settings with every seed, interleaved on one cluster.

    Each run is an ordinary run folder inside the experiment folder (every command works on it),
    bit for bit what `search` writes alone with the same flags. One process drives all runs: when
    a run's batch is back it is told, saved every log_every iterations, and its next batch is
    asked and sent, so the other runs' batches keep the workers busy while one waits for its
    slowest chunk. experiment.json records the grid, the command and each run's state. Ctrl-C,
    SIGTERM or kill -9 lose at most what each run did since its last checkpoint: continue with
    `resume EXPERIMENT_DIR`. A failing run is reported and recorded; the others go on.

    Args:
        algorithms: Rows of the ALGORITHMS table: cma_me, or a list "[cma_me, cma_mae]".
        seeds: The seeds of every setting: a range 1-5, a list 1,2,7 or both.
        outdir: Experiment folder; default outputs/<timestamp>_experiment. Must be new or empty.
        workers: Number of Dask worker processes (one thread each) of the local cluster.
        scheduler_address: Address of a running Dask scheduler to evaluate on instead.
        max_in_flight: Runs evaluated at once (default: all); the others wait their turn. Bounds
            memory with hundreds of runs.
        search_flags: Any flag of search (see: lunar_lander.py --help), for every run:
            --iterations, --env_seed, --measures, --grid, --n_emitters, --sigma0, --batch_size,
            --learning_rate, --log_every, --fast_env. A list of values of --n_emitters,
            --sigma0, --batch_size, --learning_rate or --grid, e.g. --learning_rate "[0.01, 0.1]",
            is one more axis of the grid.
    """
    axes, common, seeds = experiment_grid(algorithms, seeds, search_flags)
    workers = positive_int("workers", workers)
    limit = None if max_in_flight is None else positive_int("max_in_flight", max_in_flight)
    check_scheduler_reachable(scheduler_address)
    with new_folder(outdir, "experiment") as folder:
        plan = {"format": EXPERIMENT_FORMAT, "created": datetime.datetime.now().isoformat(),
                "command": sys.argv, "axes": axes, "seeds": seeds, "common": common,
                "workers": workers, "max_in_flight": limit, "versions": library_versions(),
                "runs": experiment_runs(axes, common, seeds)}
        write_json(folder / "experiment.json", plan)
        run_experiment(folder, plan, workers, scheduler_address)


def experiment_grid(algorithms: Any, seeds: Any, search_flags: dict) -> tuple[dict, dict, list[int]]:
    """The grid's axes (algorithm first, then each swept flag), the flags every run shares and
    the seeds, each value checked as search checks it."""
    if given := sorted(EXPERIMENT_OWN & set(search_flags)):
        raise UsageError(f"--{given[0]} is set by the experiment for each run; use --algorithms, "
                         f"--seeds, --outdir, --workers and --scheduler_address of experiment")
    if unknown := sorted(set(search_flags) - set(search_defaults())):
        raise UsageError(f"unknown flag --{unknown[0]}")
    names = [n.strip() for n in algorithms.split(",")] if isinstance(algorithms, str) else list(algorithms)
    if not names:
        raise UsageError("--algorithms is empty: the grid has no run")
    axes = {"algorithm": [one_of(ALGORITHMS)("algorithms", name) for name in names]}
    common = {name: value for name, value in search_defaults().items() if name not in EXPERIMENT_OWN}
    for name, value in search_flags.items():
        if name in SWEEPABLE and isinstance(value, (list, tuple)):
            if not value:
                raise UsageError(f"--{name} is an empty list: the grid has no run")
            axes[name] = [check_flags({name: v})[name] for v in value]
        else:
            common[name] = value
    common = check_flags(common)
    for setting in itertools.product(*axes.values()):
        check_archive_size({**common, **dict(zip(axes, setting))})
    return axes, common, seed_list("seeds", seeds)


def experiment_runs(axes: dict, common: dict, seeds: list[int]) -> list[dict]:
    """One entry per (setting, seed): its folder name, setting label, config and state."""
    import re

    runs, settings = [], []
    for values in itertools.product(*axes.values()):
        setting = {flag: common.get(flag) if ignores(values[0], flag) else value
                   for flag, value in zip(axes, values)}
        if setting not in settings:  # cma_me at two learning rates is one setting
            settings.append(setting)
    for setting in settings:
        for seed in seeds:
            config = {**common, **setting, "seed": seed}
            label = run_setting(config)
            name = re.sub(r"[^A-Za-z0-9.]+", "_", label) + f"_seed{seed}"
            runs.append({"name": name, "setting": label, "seed": seed, "config": config,
                         "state": "pending"})
    return runs


def run_experiment(folder: Path, plan: dict, workers: int, scheduler_address: str | None) -> None:
    """The cluster and the log of an experiment, shut down however it ends."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(folder / "experiment.log")
    with logging_redirect_tqdm(loggers=[log]):
        log.info(f"Experiment folder: {folder}: {len(plan['runs'])} runs "
                 f"({len(plan['runs']) // len(plan['seeds'])} settings x {len(plan['seeds'])} seeds)")
        try:
            with dask_client(workers, scheduler_address, log) as client:
                Experiment(folder, plan, client, log).drive()
        except KeyboardInterrupt:
            log.info(f"Stopped; every run keeps its last completed iteration; continue with: "
                     f"python lunar_lander.py resume {folder}")
            raise
        except RunsFailed:
            raise
        except (RunError, OSError) as error:  # of the experiment itself (experiment.json, cluster)
            raise RunError(f"{fault_text(error)}; every run keeps its last checkpoint; continue "
                           f"with: python lunar_lander.py resume {folder}") from None


class RunsFailed(RunError):
    """Some runs of an experiment failed (each recorded with its cause); the others finished."""


@dataclasses.dataclass
class LiveRun:
    """A run of the experiment in flight: its state, log, folder lock and batch on the cluster."""

    entry: dict
    run: Run
    log: logging.Logger
    lock: contextlib.ExitStack
    results: list = dataclasses.field(default_factory=list)  # the current batch's chunks, in order
    waiting: int = 0  # chunks of the current batch not back yet

    @property
    def target(self) -> int:
        return self.run.config["iterations"]


def count_as_done_before(bar, iterations: int) -> None:
    """Put a resumed run's earlier iterations on the tqdm bar as its starting point, not as work
    done now, so its rate and time left reflect only this drive."""
    bar.n, bar.last_print_n, bar.initial = (
        count + iterations for count in (bar.n, bar.last_print_n, bar.initial))
    bar.refresh()


class Experiment:
    """Drives many runs on one client: Dask's as_completed hands back chunks in whatever order
    they finish, and each run goes on as soon as its own batch is whole. A run's results depend on
    its own asks and tells only, so it ends as it would alone, whatever the interleaving."""

    def __init__(self, folder: Path, plan: dict, client, log: logging.Logger) -> None:
        from dask.distributed import as_completed

        self.folder, self.plan, self.client, self.log = folder, plan, client, log
        self.todo = collections.deque(e for e in plan["runs"] if e["state"] != "done")
        self.live: dict[str, LiveRun] = {}
        self.owner: dict[str, tuple[str, int]] = {}  # future key -> run name, chunk position
        self.latest: dict[str, dict] = {}  # run name -> its last metrics row
        self.told = 0  # iterations done in this drive
        self.closing: list[LiveRun] = []  # finished runs whose last save is being written
        self.saver = Saver()  # each run's faults are its own: see reap()
        # Results come with their futures (no second round trip to fetch them); a chunk that
        # failed comes as its exception, and fails its run alone.
        self.finished = as_completed(with_results=True, raise_errors=False)
        self.limit = plan.get("max_in_flight") or len(plan["runs"])

    def drive(self) -> None:
        from tqdm import tqdm

        runs = self.plan["runs"]
        total = sum(e["config"]["iterations"] for e in runs)
        done = sum(e["config"]["iterations"] for e in runs if e["state"] == "done")
        self.bar = tqdm(total=total, initial=done, unit="it", desc="experiment", dynamic_ncols=True)
        every, logged = self.plan["common"]["log_every"] * len(runs), done
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            self.start_more()
            while self.live:
                with STOP.interruptible():
                    future, result = next(self.finished)
                name, position = self.owner.pop(future.key, ("", 0))
                live = self.live.get(name)
                if live is not None:  # else a chunk of a run that has failed meanwhile
                    live.results[position] = result
                    live.waiting -= 1
                    if live.waiting == 0:
                        self.advance(live)
                self.reap(wait=False)
                if self.bar.n - logged >= every or not self.live:
                    logged = self.bar.n
                    for line in self.describe_settings():
                        self.log.info(line)
            self.reap(wait=True)
        except BaseException:
            for live in list(self.live.values()):
                with contextlib.suppress(Exception):
                    live.run.save_checkpoint()
                self.close(live, "stopped")
            self.reap(wait=True)
            raise
        finally:
            self.saver.shutdown()
            self.bar.close()
        # The driving loop's own cost: how much of a core the main process took while it ran.
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        self.plan["timing"] = {"drive_s": round(wall, 3), "main_cpu_s": round(cpu, 3),
                               "iterations": self.told}
        write_json(self.folder / "experiment.json", self.plan)
        failed = [e["name"] for e in runs if e["state"] == "failed"]
        self.log.info(f"Done: {len(runs) - len(failed)} of {len(runs)} runs finished in {self.folder} "
                      f"({wall:.1f} s, main process {cpu / max(wall, 1e-9):.0%} of a core)")
        if failed:
            raise RunsFailed(f"{len(failed)} of {len(runs)} runs failed ({', '.join(failed)}): their "
                           f"causes are in {self.folder / 'experiment.json'}; the others finished. "
                           f"Mend the cause and retry them with: python lunar_lander.py resume "
                           f"{self.folder}")

    def start_more(self) -> None:
        """Open waiting runs until `limit` are in flight."""
        while self.todo and len(self.live) < self.limit:
            entry = self.todo.popleft()
            try:
                live = self.open(entry)
            except (UsageError, RunError, OSError) as error:
                self.record(entry, "failed", error)
                continue
            self.live[entry["name"]] = live
            self.latest[entry["name"]] = live.run.metrics[-1] if live.run.metrics else {}
            count_as_done_before(self.bar, live.run.iteration)
            self.record(entry, "running")
            if live.run.iteration >= live.target:
                self.finish(live)
            else:
                self.launch(live)

    def open(self, entry: dict) -> LiveRun:
        """A run's folder (made on first use), locked, and its run from checkpoint or config."""
        run_dir = self.folder / entry["name"]
        run_dir.mkdir(exist_ok=True)
        lock = contextlib.ExitStack()
        lock.enter_context(folder_lock(run_dir))
        try:
            if not (run_dir / "config.json").is_file():
                write_json(run_dir / "config.json", {
                    **entry["config"], "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
                    "command": self.plan["command"], "experiment": str(self.folder),
                    "versions": library_versions()})
            config, checkpoint = load_run_state(run_dir)
            if config["iterations"] < entry["config"]["iterations"]:  # the experiment was extended
                config = {**config, "iterations": entry["config"]["iterations"]}
                write_json(run_dir / "config.json", {**read_run_json(run_dir, "config.json"),
                                                     "iterations": config["iterations"]})
            log = make_logger(run_dir / "run.log", f"lunar_lander.run.{entry['name']}", console=False)
            run = (Run.start(run_dir, config, self.client, log) if checkpoint is None
                   else Run.from_checkpoint(run_dir, {**checkpoint, "config": config}))
        except BaseException:
            lock.close()
            raise
        return LiveRun(entry, run, log, lock)

    def launch(self, live: LiveRun) -> None:
        """Ask the run's next batch and send it to the cluster."""
        config = live.run.config
        futures = submit_flights(self.client, live.run.ask(), config["env_seed"], config["measures"],
                                 config["fast_env"], sharing=len(self.live))
        live.results, live.waiting = [None] * len(futures), len(futures)
        for position, future in enumerate(futures):
            self.owner[future.key] = (live.entry["name"], position)
            self.finished.add(future)

    def advance(self, live: LiveRun) -> None:
        """The run's batch is whole: tell it, save it at its log interval, ask again or finish."""
        try:
            if failed := next((r for r in live.results if isinstance(r, BaseException)), None):
                raise failed
            row = live.run.tell(*averaged(per_terrain(live.results, live.run.config["env_seed"])))
            live.run.settle(wait=False)
            self.latest[live.entry["name"]] = row
            self.told += 1
            self.bar.update(1)
            if row["iteration"] >= live.target:
                self.finish(live)
            else:
                self.launch(live)
                if row["iteration"] % live.run.config["log_every"] == 0:
                    live.log.info(describe_progress(row, live.target))
                    live.run.save(self.saver)
        except Exception as error:  # this run's fault (a task that failed, a write): it alone stops
            self.fail(live, error)
            self.start_more()

    def fail(self, live: LiveRun, error: BaseException) -> None:
        with contextlib.suppress(Exception):
            live.run.save_checkpoint()
        self.close(live, "failed", error)
        self.log.info(f"run {live.entry['name']} failed: {fault_text(error)}")

    def finish(self, live: LiveRun) -> None:
        """The run is complete: its folder is written in the saver thread (reap() closes it)
        while another run takes its place."""
        live.run.save(self.saver)
        self.live.pop(live.entry["name"], None)
        self.closing.append(live)
        self.start_more()

    def reap(self, wait: bool) -> None:
        """Close the finished runs whose last save is written (with `wait`, all of them)."""
        for live in [live for live in self.closing if wait or live.run.pending.done()]:
            self.closing.remove(live)
            try:
                live.run.settle()
            except Exception as error:
                self.fail(live, error)
                continue
            live.log.info("Done. " + describe_progress(live.run.metrics[-1], live.target))
            self.close(live, "done")

    def close(self, live: LiveRun, state: str, error: BaseException | None = None) -> None:
        self.live.pop(live.entry["name"], None)
        close_logger(live.log)
        live.lock.close()
        self.record(live.entry, state, error)

    def record(self, entry: dict, state: str, error: BaseException | None = None) -> None:
        """A run's new state, in experiment.json at once."""
        entry["state"] = state
        if error is not None:
            entry["error"] = fault_text(error) if isinstance(error, (OSError, RunError)) else (
                f"{type(error).__name__}: {fault_text(error)}")
        else:
            entry.pop("error", None)
        write_json(self.folder / "experiment.json", self.plan)

    def describe_settings(self) -> list[str]:
        """A line per setting: its runs' progress, mean QD score and coverage, best objective."""
        lines = []
        for setting in dict.fromkeys(e["setting"] for e in self.plan["runs"]):
            rows = [self.latest[e["name"]] for e in self.plan["runs"]
                    if e["setting"] == setting and self.latest.get(e["name"])]
            if rows:
                best = max((r["best_objective"] for r in rows if r["best_objective"] is not None),
                           default=float("nan"))
                lines.append(f"{setting}: {len(rows)} run(s) at iteration "
                             f"{min(r['iteration'] for r in rows)}-{max(r['iteration'] for r in rows)}, "
                             f"QD score {np.mean([r['qd_score'] for r in rows]):.0f} (mean), coverage "
                             f"{np.mean([r['coverage'] for r in rows]):.3f} (mean), best {best:.1f}")
        return lines


def resume_experiment(folder: Path, iterations: int | None, workers: int | None,
                      scheduler_address: str | None) -> None:
    """Continue every unfinished run of an experiment (failed ones are tried again)."""
    read_experiment(folder)  # refuse a bad folder before anything is written in it
    check_scheduler_reachable(scheduler_address)
    with folder_lock(folder):
        plan = read_experiment(folder)
        workers = positive_int("workers", plan["workers"] if workers is None else workers)
        if iterations is not None:
            iterations = positive_int("iterations", iterations)
            for entry in plan["runs"]:
                if iterations > entry["config"]["iterations"]:
                    entry["config"]["iterations"] = iterations
                    entry["state"] = "pending"
        plan["resumed"] = [*plan.get("resumed", []), {"at": datetime.datetime.now().isoformat(),
                                                      "iterations": iterations, "workers": workers}]
        write_json(folder / "experiment.json", plan)
        run_experiment(folder, plan, workers, scheduler_address)


def read_experiment(folder: Path) -> dict:
    plan = read_run_json(folder, "experiment.json")
    if not (isinstance(plan, dict) and plan.get("format") == EXPERIMENT_FORMAT and plan.get("runs")):
        raise UsageError(f"{folder / 'experiment.json'}: not an experiment of lunar_lander.py")
    return plan


# ================================================================================================
# Looking at the results: videos of chosen cells, elite tables, trajectories, robustness
# ================================================================================================

LANDED = 200.0  # the episode reward Gymnasium calls solved: a good landing


def load_run(run_dir: Any) -> tuple[Any, dict]:
    """A run folder's archive and config (checked against each other). Folders written before
    --measures and --grid existed load with the tutorial's measures on a 50x50 grid."""
    path = Path(str(run_dir))
    if not path.is_dir():
        raise UsageError(f"{path}: no such run folder")
    if not (path / "archive.pkl").is_file():
        raise UsageError(f"{path / 'archive.pkl'}: no such file (is {path} a run folder of lunar_lander.py?)")
    recorded = read_run_json(path, "config.json")
    try:
        config = check_run_config(recorded)
    except UsageError as error:
        raise UsageError(f"{path / 'config.json'}: not a usable run config ({error})") from None
    return load_archive(path / "archive.pkl", config), config


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def parse_cells(cells: Any, measures: list[str]) -> list[tuple[float, ...]]:
    """--cells as points in the run's measures. Fire hands over what it could parse (a list of
    tuples, or one tuple) and the raw text otherwise, so both are accepted."""
    import ast

    points, size = cells, len(measures)
    if isinstance(points, str):
        with contextlib.suppress(ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            points = ast.literal_eval(points)
    if isinstance(points, (int, float)) and size == 1:
        points = [(points,)]
    if isinstance(points, (tuple, list)) and points and all(map(is_number, points)):
        points = [points] if len(points) == size or size > 1 else [(p,) for p in points]
    if not (isinstance(points, (tuple, list)) and points and all(
            isinstance(p, (tuple, list)) and len(p) == size and all(map(is_number, p)) for p in points)):
        example = "(" + ", ".join(f"{sum(MEASURES[m].range) / 2:g}" for m in measures) + ")"
        raise UsageError(f"--cells takes points of ({', '.join(measures)}) such as "
                         f'"[{example}]", got {cells!r}')
    return [tuple(float(v) for v in point) for point in points]


def parse_indices(index: Any, archive) -> list[int]:
    """--index as one archive cell index or several (the cell_index column of `elites`)."""
    values = list(index) if isinstance(index, (tuple, list)) else [index]
    cells = int(np.prod(archive.dims))
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < cells:
            raise UsageError(f"--index takes cell indices from 0 to {cells - 1} (see the elites "
                             f"command's cell_index), got {index!r}")
    return values


def point_text(point) -> str:
    return "(" + ", ".join(f"{value:g}" for value in point) + ")"


def check_in_archive(archive, point: tuple[float, ...], measures: list[str]) -> None:
    ranges = ", ".join(f"{name} in [{lo:g}, {hi:g}]" for name, lo, hi in
                       zip(measures, archive.lower_bounds, archive.upper_bounds))
    if not all(lo <= p <= hi for p, lo, hi in zip(point, archive.lower_bounds, archive.upper_bounds)):
        raise UsageError(f"cell {point_text(point)} is outside the archive: {ranges}")


def elite_rows(archive) -> dict[str, np.ndarray]:
    """Every elite (solution, objective, measures, index), best first; ties by cell index."""
    data = archive.data(["solution", "objective", "measures", "index"])
    order = np.lexsort((data["index"], -data["objective"]))
    return {field: values[order] for field, values in data.items()}


def pick(rows: dict[str, np.ndarray], i: int, name: str) -> dict:
    return {"name": name, **{field: values[i] for field, values in rows.items()}}


def nearest_occupied(archive, point: tuple[float, ...]) -> dict:
    """The elite whose cell is nearest the point's cell, counting in cells (ties: lowest index)."""
    rows = elite_rows(archive)
    target = archive.int_to_grid_index([archive.index_of_single(point)])[0]
    distance = np.linalg.norm(archive.int_to_grid_index(rows["index"]) - target, axis=1)
    return pick(rows, int(np.lexsort((rows["index"], distance))[0]), "")


def describe_elite(elite: dict, measures: list[str]) -> str:
    values = ", ".join(f"{name} {value:.3f}" for name, value in zip(measures, elite["measures"]))
    return f"objective {elite['objective']:.2f}, {values} (cell {elite['index']})"


def file_tag(point, measures: list[str]) -> str:
    """A point in the measures as a file-name part: x-0.40_v-0.10 (the MEASURES short names)."""
    return "_".join(f"{MEASURES[name].short}{value:.2f}" for name, value in zip(measures, point))


def elite_of_cell(archive, point: tuple[float, ...], measures: list[str], nearest: bool) -> dict:
    """The elite of the cell holding `point`, as archive.retrieve_single finds it; for an empty
    cell, the nearest occupied one if asked (else the error names it)."""
    check_in_archive(archive, point, measures)
    name = f"cell_{file_tag(point, measures)}"
    occupied, elite = archive.retrieve_single(point)
    if occupied:
        return {"name": name, **elite}
    near = nearest_occupied(archive, point)
    empty = f"the cell of {point_text(point)} (index {archive.index_of_single(point)}) is empty"
    if not nearest:
        raise UsageError(f"{empty}; the nearest occupied cell holds {describe_elite(near, measures)}; "
                         f"add --nearest to use it")
    print(f"{empty}; using the nearest occupied cell: {describe_elite(near, measures)}")
    return {**near, "name": f"{name}_nearest{near['index']}"}


def select_elites(archive, cells: Any = None, best: Any = False, top: Any = None,
                  index: Any = None, nearest: Any = False,
                  measures: list[str] = TUTORIAL_MEASURES) -> list[dict]:
    """The elites a results command shows, each named for its file: the --cells points' cells,
    the --best, the --top K by objective, the --index cells, in that order."""
    nearest, best, measures = boolean("nearest", nearest), boolean("best", best), list(measures)
    if cells is None and not best and top is None and index is None:
        raise UsageError("choose elites with --cells, --best, --top or --index")
    rows, chosen = elite_rows(archive), []
    if cells is not None:
        chosen += [elite_of_cell(archive, point, measures, nearest)
                   for point in parse_cells(cells, measures)]
    if best:
        chosen.append(pick(rows, 0, "best"))
    if top is not None:
        chosen += [pick(rows, i, f"top{i + 1:02d}")
                   for i in range(min(positive_int("top", top), len(rows["index"])))]
    if index is not None:
        where = {int(cell): i for i, cell in enumerate(rows["index"])}
        for cell in parse_indices(index, archive):
            if cell not in where:
                raise UsageError(f"cell index {cell} is empty (the elites command lists the occupied ones)")
            chosen.append(pick(rows, where[cell], f"index{cell}"))
    for elite in chosen:
        if not elite["name"].startswith("cell_"):
            elite["name"] += f"_{file_tag(elite['measures'], measures)}"
        elite["name"] += f"_obj{elite['objective']:.0f}"
    return chosen


class Mp4Recorder(gym.Wrapper):
    """Streams the frame after reset and after every step into an mp4 at the env's 50 fps, with
    imageio-ffmpeg. Not gymnasium's RecordVideo: it keeps every frame in memory, and its moviepy
    2.2 writer drops the last frame (the landing) whenever 1/fps summed over the frames falls
    short of their count (212 frames -> 4.2399999 s -> 211 written)."""

    def __init__(self, env: gym.Env, path: Path) -> None:
        super().__init__(env)
        self.path, self.frames, self._writer = path, 0, None

    def reset(self, **kwargs):
        result = self.env.reset(**kwargs)
        self._write_frame()
        return result

    def step(self, action):
        result = self.env.step(action)
        self._write_frame()
        return result

    def _write_frame(self) -> None:
        import imageio_ffmpeg

        frame = self.env.render()
        if self._writer is None:  # macro_block_size 8: 600x400 is encoded as is, not rescaled
            self._writer = imageio_ffmpeg.write_frames(
                str(self.path), (frame.shape[1], frame.shape[0]), fps=self.metadata["render_fps"],
                codec="libx264", pix_fmt_out="yuv420p", macro_block_size=8,
                ffmpeg_log_level="quiet")  # a failure is reported once, in one line (record_video)
            self._writer.send(None)
        self._writer.send(np.ascontiguousarray(frame))
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        super().close()


def load_chosen_elites(run_dir: Any, env_seed: Any, *selection: Any) -> tuple[dict, list[dict], int]:
    """The run's config, the elites `selection` (select_elites' flags) picks from its archive, and
    the terrain to show them on: --env_seed, by default the run's first."""
    archive, config = load_run(run_dir)
    shown = shown_terrain(config, env_seed)
    return config, select_elites(archive, *selection, measures=config["measures"]), shown


def shown_terrain(config: dict, env_seed: Any) -> int:
    """The terrain a results command shows a run on: --env_seed, by default the run's first."""
    return config["env_seed"][0] if env_seed is None else non_negative_int("env_seed", env_seed)


def reflown(elite: dict, config: dict) -> tuple[float, list[float]]:
    """The elite flown again in its run's setting (every terrain, averaged as the engine does):
    rollouts are deterministic, so this is exactly its stored objective and measures."""
    env, seeds = make_env(config["fast_env"]), config["env_seed"]
    rows = [np.array([rollout(elite["solution"], seed, env, config["measures"]) for seed in seeds])]
    objectives, measures = averaged(per_terrain(rows, seeds))
    return float(objectives[0]), measures[0].tolist()


def record_video(solution: np.ndarray, env_seed: int, path: Path) -> None:
    """Fly a policy on the plain env, rendered headless (rgb_array) into an mp4 of episode length
    + 1 frames (the reset's frame first); written aside and moved into place whole."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=".recording.") as tmp:
            env = Mp4Recorder(make_env(fast=False, render_mode="rgb_array"), Path(tmp) / "flight.mp4")
            try:
                fly(solution, env_seed, env)
            finally:
                env.close()
            os.replace(env.path, path)
    except OSError as error:
        # When ffmpeg fails, Python sees only a broken pipe: a full disk is the usual cause.
        full = shutil.disk_usage(path.parent).free < 2**20 if path.parent.exists() else False
        cause = os.strerror(errno.ENOSPC) if full else fault_text(error)
        raise RunError(f"cannot write {path}: {cause}") from None


def write_csv(path: Path, table) -> None:
    atomic_write(path, lambda f: table.to_csv(f, index=False), mode="w")


def video(run_dir: str, cells: Any = None, best: bool = False, top: int | None = None,
          index: Any = None, nearest: bool = False, env_seed: int | None = None) -> None:
    """Render an mp4 per chosen elite, flown on one of the run's terrains, into RUN_DIR/videos/.

    Each elite is also flown again in its run's setting and must score exactly its stored
    objective and measures (a warning says if not). videos/index.csv lists the videos with the
    elites' objectives and measures.

    Args:
        run_dir: A run folder written by this script.
        cells: Points in the run's measures "[(m1, m2), ...]": the elite of each point's cell
            (archive.retrieve_single); for the tutorial's impact x and impact y-velocity, e.g.
            "[(-0.4, -0.1), (0.6, -0.1), (0.0, -0.1)]".
        best: The elite with the highest objective.
        top: The K elites with the highest objectives.
        index: Archive cell indices (the cell_index column of the elites command).
        nearest: For an empty cell, use the nearest occupied cell instead of stopping.
        env_seed: The terrain to film on; default: the run's first.
    """
    import pandas as pd

    config, chosen, shown = load_chosen_elites(run_dir, env_seed, cells, best, top, index, nearest)
    folder, rows, measures = Path(str(run_dir)) / "videos", [], config["measures"]
    for elite in chosen:
        STOP.check()  # Ctrl-C is acted on between videos (main defers it, see StopRequests)
        path = folder / f"{elite['name']}.mp4"
        record_video(elite["solution"], shown, path)
        print(f"{path}: {describe_elite(elite, measures)}")
        objective, values = reflown(elite, config)
        reproduced = objective == elite["objective"] and values == list(elite["measures"])
        if not reproduced:
            print(f"warning: flown again, {path.name} scored {objective!r} with measures {values}, "
                  f"not the stored {elite['objective']!r}, {list(elite['measures'])} "
                  f"(other library versions?)", file=sys.stderr)
        rows.append({"video": path.name, "env_seed": shown, "cell_index": int(elite["index"]),
                     "objective": float(elite["objective"]),
                     **{name: float(value) for name, value in zip(measures, elite["measures"])},
                     "reflown_objective": objective, "reproduced": reproduced})
    write_csv(folder / "index.csv", pd.DataFrame(rows))


def elite_table(archive, measures: list[str], min_objective: float | None = None,
                top: int | None = None):
    """The archive's elites as a table (archive.data), best first, filtered and cut; the columns
    are named after the run's measures."""
    table = archive.data(["objective", "measures", "index"], return_type="pandas")
    table = table.sort_values(["objective", "index"], ascending=[False, True], ignore_index=True)
    if min_objective is not None:
        table = table[table["objective"] >= min_objective]
    if top is not None:
        table = table.head(top)
    columns = {"objective": "objective", **{f"measures_{i}": name for i, name in enumerate(measures)},
               "index": "cell_index"}
    return table.rename(columns=columns)[list(columns.values())].reset_index(drop=True)


def elites(run_dir: str, min_objective: float | None = None, top: int | None = None) -> None:
    """Print the run's elites sorted by objective, and write them to RUN_DIR/elites.csv.

    Args:
        run_dir: A run folder written by this script.
        min_objective: Only elites scoring at least this (200: good landings).
        top: Only the K best of those.
    """
    archive, config = load_run(run_dir)
    if min_objective is not None and not is_number(min_objective):
        raise UsageError(f"--min_objective must be a number, got {min_objective!r}")
    table = elite_table(archive, config["measures"], min_objective,
                        None if top is None else positive_int("top", top))
    path = Path(str(run_dir)) / "elites.csv"
    write_csv(path, table)
    print(table.to_string(index=False, float_format=lambda value: f"{value:.3f}")
          if len(table) else "no elites match")
    print(f"{len(table)} of {len(archive)} elites; written to {path}")


def terrain(env_seed: int) -> np.ndarray:
    """The ground line of a terrain, (x, y) in the observation's units (as trajectories)."""
    edges, _, _ = _seeded_randoms(env_seed)
    points = np.array([edges[0][0], *(end for _, end in edges)])
    return np.column_stack([(points[:, 0] - _HALF_W) / _HALF_W, (points[:, 1] - _PAD_Y) / _HALF_H])


def fly_paths(chosen: list[dict], env_seed: int) -> list[tuple[np.ndarray, int]]:
    """Each elite's (x, y) per step, and the index of its touchdown (its last step if none)."""
    env, paths = make_env(), []
    for elite in chosen:
        STOP.check()
        path: list = []
        flight = fly(elite["solution"], env_seed, env, path)
        paths.append((np.array(path), (flight.touchdown_step or flight.steps) - 1))
    return paths


def save_trajectory_plot(chosen: list[dict], paths: list[tuple[np.ndarray, int]], env_seed: int,
                         path: Path) -> None:
    """The tutorial's "many ways to land" on one page: flight paths over the terrain, coloured by
    objective, impacts marked. Equal metres on both axes (x and y are scaled differently)."""
    import matplotlib.pyplot as plt
    from matplotlib import cm, colors

    objectives = [float(elite["objective"]) for elite in chosen]
    norm = colors.Normalize(min(objectives) - 1e-9, max(objectives) + 1e-9)
    cmap = plt.get_cmap("viridis")
    ground = terrain(env_seed)
    fig, ax = plt.subplots(figsize=(11, 7))
    ax.fill_between(ground[:, 0], ground[:, 1], ground[:, 1].min() - 0.2, color="0.75", zorder=0)
    ax.plot([-0.2, 0.2], [ground[5, 1]] * 2, color="gold", lw=4, label="helipad", zorder=1)
    for elite, (flight, step) in zip(chosen, paths):
        colour = cmap(norm(float(elite["objective"])))
        ax.plot(flight[:, 0], flight[:, 1], color=colour, lw=1.2, alpha=0.9,
                label=elite["name"] if len(chosen) <= 12 else None)
        ax.plot(*flight[step], marker="o", ms=7, mec="black", color=colour, zorder=3)
    ax.set_aspect(_HALF_H / _HALF_W)
    ax.set_xlim(-1.05, 1.05)
    ax.set_ylim(ground[:, 1].min() - 0.2, max(1.5, max(float(f[:, 1].max()) for f, _ in paths) + 0.05))
    ax.set_xlabel("x (observation units: -1 and 1 are the screen edges)")
    ax.set_ylabel("y of the lander's centre (0: resting on the helipad)")
    ax.set_title(f"Flight paths of {len(chosen)} elites on terrain {env_seed} (dots: touchdown)")
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="Objective", shrink=0.8)
    ax.legend(fontsize=7, loc="upper left")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100, bbox_inches="tight"))
    plt.close(fig)


def trajectories(run_dir: str, cells: Any = None, best: bool = False, top: int | None = None,
                 index: Any = None, nearest: bool = False, env_seed: int | None = None) -> None:
    """Draw the flight paths of the chosen elites over the run's terrain: RUN_DIR/trajectories.png.

    The elites are chosen as for the video command (see: lunar_lander.py video --help).

    Args:
        run_dir: A run folder written by this script.
        cells: Points in the run's measures "[(m1, m2), ...]", one elite per point's cell.
        best: Add the best elite.
        top: Add the K best elites.
        index: Add these cells' elites.
        nearest: Replace an empty cell by the nearest occupied one.
        env_seed: The terrain to fly on; default: the run's first.
    """
    config, chosen, shown = load_chosen_elites(run_dir, env_seed, cells, best, top, index, nearest)
    path = Path(str(run_dir)) / "trajectories.png"
    save_trajectory_plot(chosen, fly_paths(chosen, shown), shown, path)
    for elite in chosen:
        print(f"{elite['name']}: {describe_elite(elite, config['measures'])}")
    print(f"written to {path}")


def console_log() -> logging.Logger:
    """Messages of commands that only read a run: printed, not appended to its run.log."""
    log = logging.getLogger("lunar_lander.results")
    log.setLevel(logging.INFO)
    log.propagate = False
    log.handlers = [logging.StreamHandler(sys.stdout)]  # today's stdout, not the first call's
    return log


# The explorer page: every elite's flight, recorded as poses and packed into the page.
# Per step, five numbers give the drawing: the lander's x, y and angle and its two legs' angles (a
# leg hangs from the lander's centre by its joint, so its position follows from its angle), plus
# the action (which engine fires). They are quantised to int16, 1 mm and 0.1 mrad (angles wrapped
# to [-pi, pi]), and sent as base64: ~11 bytes a step, ~9 MB for a full 300-iteration archive
# (~615,000 steps). The page decodes them with atob into an Int16Array.
POSE_SCALE = (1000.0, 1000.0, 10000.0, 10000.0, 10000.0)  # int16 units per metre or radian


def record_poses(solutions: np.ndarray, env_seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Runs on a worker: each solution's flight as quantised poses (steps + 1, 5) and actions,
    the reset's pose first (action 0), flown in the streamlined env as `rollout` flies it."""
    env = _WORKER_ENVS.get(True) or _WORKER_ENVS.setdefault(True, make_env(True))
    return [record_flight(solution, env_seed, env) for solution in solutions]


def record_flight(solution: np.ndarray, env_seed: int, env: FastLunarLander) -> tuple[np.ndarray, np.ndarray]:
    def pose() -> list[float]:
        return [env.lander.position.x, env.lander.position.y, env.lander.angle,
                env.legs[0].angle, env.legs[1].angle]

    env.reset(seed=env_seed)
    poses, actions = [pose()], [0]
    fly(solution, env_seed, env, on_step=lambda action, obs: (poses.append(pose()), actions.append(action)))
    values = np.array(poses)  # the first pose is reset's; fly resets again, to the same pose
    values[:, 2:] = (values[:, 2:] + np.pi) % (2 * np.pi) - np.pi
    quantised = np.clip(np.round(values * POSE_SCALE), -32767, 32767).astype("<i2")
    return quantised, np.array(actions, dtype=np.uint8)


def explorer_data(archive, config: dict, rows: dict, flights: list, env_seed: int,
                  run_dir: Path) -> dict:
    """What the page shows, as JSON: cells with their elites, packed flights, terrain, curves."""
    import base64

    import matplotlib

    offsets = np.cumsum([0, *(len(actions) for _, actions in flights)])
    grid = archive.int_to_grid_index(rows["index"])
    robust = {}
    if (run_dir / "robustness.csv").is_file():
        import pandas as pd

        with contextlib.suppress(OSError, ValueError, KeyError):
            table = pd.read_csv(run_dir / "robustness.csv")
            robust = {int(r["cell_index"]): (float(r["mean_objective"]), float(r["landed_share"]))
                      for r in table.to_dict("records")}
    elites = [{"index": int(index), "gx": int(cell[0]), "gy": int(cell[1]) if len(cell) > 1 else 0,
               "objective": float(objective), "measures": [float(m) for m in measures],
               "offset": int(offset), "steps": int(len(actions) - 1),
               **({"robust": robust[int(index)]} if int(index) in robust else {})}
              for index, cell, objective, measures, offset, (_, actions)
              in zip(rows["index"], grid, rows["objective"], rows["measures"], offsets, flights)]
    edges, _, _ = _seeded_randoms(env_seed)
    magma = matplotlib.colormaps["magma"]
    metrics = read_run_json(run_dir, "metrics.json")
    return {
        "run": str(run_dir), "algorithm": config["algorithm"], "env_seed": env_seed,
        "measures": [{"name": name, "label": MEASURES[name].label, "descending": MEASURES[name].descending,
                      "range": [float(lo), float(hi)]}
                     for name, lo, hi in zip(config["measures"], archive.lower_bounds, archive.upper_bounds)],
        "dims": [int(d) for d in archive.dims], "heat_range": list(HEATMAP_RANGE),
        "colormap": [matplotlib.colors.to_hex(magma(i / 255)) for i in range(256)],
        "elites": elites, "pose_scale": list(POSE_SCALE),
        "poses": base64.b64encode(np.concatenate([p for p, _ in flights]).tobytes()).decode(),
        "actions": base64.b64encode(np.concatenate([a for _, a in flights]).tobytes()).decode(),
        "world": {"width": _W, "height": _H, "scale": _S, "helipad_y": _HELIPAD_Y,
                  "helipad_x": [edges[3][1][0], edges[5][1][0]],
                  "ground": [edges[0][0], *(end for _, end in edges)],
                  "lander": [[x / _S, y / _S] for x, y in upstream.LANDER_POLY],
                  "leg": [upstream.LEG_AWAY / _S, upstream.LEG_DOWN / _S, upstream.LEG_W / _S,
                          upstream.LEG_H / _S], "fps": _FPS},
        "metrics": [{k: row.get(k) for k in ("iteration", "evaluations", "qd_score", "coverage",
                                             "best_objective")} for row in metrics],
        "robustness": bool(robust),
    }


def explore(run_dir: str, workers: int = 2, scheduler_address: str | None = None,
            env_seed: int | None = None) -> None:
    """Write RUN_DIR/explorer.html: one self-contained page to browse the archive and watch any
    landing. It opens offline in any current browser (no server, nothing fetched): the heatmap
    (hover a cell for its numbers, click it to watch its elite land), a sortable table of the best
    elites, and the run's progress curves. Every elite is flown again on the cluster to record its
    poses, so the page plays exactly the flight that `video` renders.

    Args:
        run_dir: A run folder written by this script.
        workers: Number of Dask worker processes flying the elites.
        scheduler_address: Address of a running Dask scheduler to evaluate on instead.
        env_seed: The terrain to fly on; default: the run's first.
    """

    archive, config = load_run(run_dir)
    shown = shown_terrain(config, env_seed)
    workers, run = positive_int("workers", workers), Path(str(run_dir))
    check_writable(run)
    rows = elite_rows(archive)
    with dask_client(workers, scheduler_address, console_log()) as client:
        chunks = np.array_split(rows["solution"], max(1, min(len(rows["solution"]) // 25, 64)))
        futures = [client.submit(by_reference(record_poses), chunk, shown, pure=False, retries=3)
                   for chunk in chunks]
        flights = [flight for chunk in gather_with_progress(client, futures) for flight in chunk]
    data = explorer_data(archive, config, rows, flights, shown, run)
    page = EXPLORER_PAGE.replace("/*DATA*/null", json.dumps(data, separators=(",", ":")))
    atomic_write(run / "explorer.html", lambda f: f.write(page), mode="w")
    size = (run / "explorer.html").stat().st_size
    print(f"{len(rows['index'])} elites, {sum(len(a) for _, a in flights):,} poses: wrote "
          f"{run / 'explorer.html'} ({size / 1e6:.1f} MB); open it in a browser")


def robustness_table(rows: dict[str, np.ndarray], measures: list[str], seeds: list[int],
                     objectives: np.ndarray):
    """Per elite (rows), its objectives on each seed (columns of `objectives`) summed up; the
    elites that generalise best first."""
    import pandas as pd

    table = pd.DataFrame({"cell_index": rows["index"], "objective": rows["objective"],
                          **{name: rows["measures"][:, i] for i, name in enumerate(measures)},
                          "mean_objective": objectives.mean(axis=1), "min_objective": objectives.min(axis=1),
                          "std_objective": objectives.std(axis=1),
                          "landed_share": (objectives >= LANDED).mean(axis=1)})
    table = pd.concat([table, pd.DataFrame(objectives, columns=[f"objective_seed{s}" for s in seeds])],
                      axis=1)
    return table.sort_values(["mean_objective", "cell_index"], ascending=[False, True], ignore_index=True)


def evaluate_robustness(run_dir: str, env_seeds: Any = "0-19", top: int | None = None,
                        workers: int = 2, scheduler_address: str | None = None) -> None:
    """Fly the run's elites on other terrains (on Dask) to see which landing styles generalise.

    Writes RUN_DIR/robustness.csv (per elite: its objective in the run, i.e. its mean over the
    run's terrains; mean, min and standard deviation of its objective over the new terrains, share
    of landings >= 200, and each terrain's objective) and RUN_DIR/robustness_heatmap.png (the
    archive coloured by the mean objective on the new terrains).

    Args:
        run_dir: A run folder written by this script.
        env_seeds: Terrains to fly on: a range 0-19, a list 3,5,8, or both 0-4,10.
        top: Only the K elites with the highest objectives (default: all).
        workers: Number of Dask worker processes.
        scheduler_address: Address of a running Dask scheduler to evaluate on instead.
    """
    from ribs.archives import GridArchive

    archive, config = load_run(run_dir)
    seeds, workers = seed_list("env_seeds", env_seeds), positive_int("workers", workers)
    rows = elite_rows(archive)
    if top is not None:
        rows = {field: values[:positive_int("top", top)] for field, values in rows.items()}
    if seen := sorted(set(seeds) & set(config["env_seed"])):
        print(f"note: the run searched on terrain(s) {seen} too; they are not new to its elites")
    with dask_client(workers, scheduler_address, console_log()) as client:
        futures = submit_flights(client, rows["solution"], seeds, (), config["fast_env"])
        objectives = per_terrain(gather_with_progress(client, futures), seeds)[:, :, 0]
    run = Path(str(run_dir))
    table = robustness_table(rows, config["measures"], seeds, objectives)
    write_csv(run / "robustness.csv", table)
    means = GridArchive(solution_dim=archive.solution_dim, dims=archive.dims,
                        ranges=list(zip(archive.lower_bounds, archive.upper_bounds)))
    means.add(rows["solution"], objectives.mean(axis=1), rows["measures"])
    save_heatmap(means, config["measures"], run / "robustness_heatmap.png",
                 f"Mean objective of {len(table)} elites on {len(seeds)} terrain(s) ({env_seeds})")
    landed = table["landed_share"]
    print(f"{len(table)} elites on {len(seeds)} terrains: "
          f"mean objective {table['mean_objective'].mean():.1f}; "
          f"{(landed == 1).sum()} land (>= {LANDED:g}) on every terrain, {(landed >= 0.5).sum()} on at "
          f"least half. Best: {table['mean_objective'][0]:.1f} mean, cell {table['cell_index'][0]}.")
    print(f"written to {run / 'robustness.csv'} and {run / 'robustness_heatmap.png'}")


# ================================================================================================
# Comparing runs: QD score, coverage and best objective against evaluations, and a final table
# ================================================================================================

COMPARED = ("evaluations", "coverage", "num_elites", "qd_score", "best_objective", "mean_objective")
SOLVED_CELLS = f"cells_{LANDED:.0f}+"  # the table's column of cells holding a good landing


def solved_cells(run_dir: Path) -> int | None:
    """Cells of the final archive holding a landing that solves the task (None without archive.csv):
    QD score and coverage count crashes too; this counts only the good landings."""
    import pandas as pd

    try:
        objectives = pd.read_csv(run_dir / "archive.csv", usecols=["objective"])["objective"]
        return int((objectives >= LANDED).sum())
    except (OSError, ValueError):
        return None


def load_run_metrics(run_dir: Path) -> tuple[dict, list[dict]]:
    """A run's config and its metrics rows (at least one, each with every compared field)."""
    config, metrics = read_run_json(run_dir, "config.json"), read_run_json(run_dir, "metrics.json")
    if not isinstance(config, dict):
        raise UsageError(f"{run_dir / 'config.json'}: not a run config")
    if not (isinstance(metrics, list) and metrics
            and all(isinstance(row, dict) and set(COMPARED) <= row.keys() for row in metrics)):
        raise UsageError(f"{run_dir / 'metrics.json'}: no metrics to compare")
    return config, metrics


SETTING_FLAGS = ("env_seed", "measures", "grid", "n_emitters", "batch_size", "sigma0",
                 "learning_rate")


def run_setting(config: dict) -> str:
    """The algorithm with its own flags, and the other flags shaping it that differ from their
    defaults: runs of one setting with different seeds are repeats of one experiment. An
    algorithm's own flags are always named (cma_mae at 0.01 and at 0.5 are different algorithms
    in effect), so a label means the same whatever the defaults become."""
    defaults, changed = check_flags(search_defaults()), []
    config = {**BEFORE_THE_FLAG, **config}  # a config.json from before a flag: what it ran with
    algorithm = config.get("algorithm")
    own = ALGORITHMS[algorithm]["flags"] if algorithm in ALGORITHMS else ()
    for flag in (flag for flag in SETTING_FLAGS if flag in config):
        if algorithm in ALGORITHMS and ignores(algorithm, flag):
            continue
        with contextlib.suppress(UsageError):
            value = check_flags({flag: config[flag]})[flag]  # 52 and [52] are one terrain
            if value != defaults[flag] or flag in own:
                changed.append(f"{flag}={','.join(map(str, value)) if isinstance(value, list) else value}")
    return " ".join([str(config.get("algorithm", "?")), *changed])


def run_labels(run_dirs: list[Path], configs: list[dict]) -> list[str]:
    """'setting seed N' for each run, or the folders as given when that would be ambiguous."""
    labels = [f"{run_setting(config)} seed {config.get('seed', '?')}" for config in configs]
    return labels if len(set(labels)) == len(labels) else [str(run_dir) for run_dir in run_dirs]


def comparison_outputs(out: str | None, overwrite: bool) -> dict[str, Path]:
    """The files of a comparison, all named after the PNG: by default new files under outputs/;
    never an existing file unless --overwrite."""
    def named(png: Path) -> dict[str, Path]:
        return {"png": png, "csv": png.with_suffix(".csv"), "md": png.with_suffix(".md"),
                "settings": png.with_name(f"{png.stem}_settings.csv"),
                "tests": png.with_name(f"{png.stem}_tests.csv")}

    if out is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        candidates = [Path("outputs") / f"compare_{stamp}{suffix}.png" for suffix in
                      ["", *(f"_{i}" for i in range(2, 1000))]]
        files = next(named(p) for p in candidates if not any(f.exists() for f in named(p).values()))
    else:
        files = named(Path(out) if Path(out).suffix.lower() == ".png" else Path(f"{out}.png"))
    existing = [str(p) for p in files.values() if p.exists()]
    if existing and not overwrite:
        raise UsageError(f"{' and '.join(existing)} already exist(s); choose another --out "
                         f"or pass --overwrite")
    return files


QD_AUC, CQD_SCORE = "qd_auc", "cqd_score"
# CQD score (Kent 2022, ribs.archives.cqd_score) with fixed settings, so that a number means the
# same in every table: target points drawn uniformly in the archive's measure box with this seed,
# penalties spread evenly over [0, 1], objectives normalised over [obj_min, obj_max], distances
# over the box's diagonal. Written next to every comparison.
CQD = {"iterations": 1, "targets": 1000, "penalties": 10, "target_seed": 0,
       "obj_min": QD_SCORE_OFFSET, "obj_max": 350.0}
SUMMARISED = ("qd_score", "coverage", "best_objective", SOLVED_CELLS, QD_AUC, CQD_SCORE)
TESTED = ("qd_score", QD_AUC, CQD_SCORE)  # pairwise between settings: final, anytime, spread
FEW_RUNS = 5


def cqd(run_dir: Path) -> float | None:
    """The CQD score of a run's final archive (None without a readable archive.pkl)."""
    from ribs.archives import cqd_score

    try:
        archive = read_pickle(run_dir / "archive.pkl", "archive pickle")
        lower, upper = archive.lower_bounds, archive.upper_bounds
    except (UsageError, AttributeError):
        return None
    targets = np.random.default_rng(CQD["target_seed"]).uniform(
        lower, upper, size=(CQD["iterations"], CQD["targets"], len(lower)))
    return float(cqd_score(archive, iterations=CQD["iterations"], target_points=targets,
                           penalties=CQD["penalties"], obj_min=CQD["obj_min"], obj_max=CQD["obj_max"],
                           dist_max=float(np.linalg.norm(upper - lower))).mean)


def qd_auc(metrics: list[dict]) -> float:
    """Area under QD score against evaluations, from (0, 0), divided by the evaluations: the
    run's QD score averaged over its budget, which rewards reaching a score early."""
    evaluations = [0, *(row["evaluations"] for row in metrics)]
    return float(np.trapezoid([0, *(row["qd_score"] for row in metrics)], evaluations) / evaluations[-1])


def comparison_table(labels: list[str], run_dirs: list[Path], configs: list[dict],
                     runs: list[list[dict]]):
    """One row per run: its final metrics, with the algorithm and seed that produced them."""
    import pandas as pd

    table = pd.DataFrame([
        {"run": label, "folder": str(run_dir), "setting": run_setting(config),
         "seed": config.get("seed"), "iterations": metrics[-1]["iteration"],
         **{key: metrics[-1][key] for key in COMPARED}, SOLVED_CELLS: solved_cells(run_dir),
         QD_AUC: qd_auc(metrics), CQD_SCORE: cqd(run_dir)}
        for label, run_dir, config, metrics in zip(labels, run_dirs, configs, runs)
    ])
    for column in (SOLVED_CELLS, CQD_SCORE):
        table[column] = pd.to_numeric(table[column])  # None (no archive): NaN
    return table


def bootstrap_interval(values: np.ndarray) -> tuple[float, float]:
    """95% BCa bootstrap confidence interval of the mean (seeded, so repeatable)."""
    from scipy.stats import bootstrap

    if len(values) < 2:
        return math.nan, math.nan
    if np.ptp(values) == 0:
        return float(values[0]), float(values[0])
    result = bootstrap((values,), np.mean, confidence_level=0.95, n_resamples=9999, method="BCa",
                       rng=np.random.default_rng(0))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def setting_statistics(table):
    """Per setting and summarised metric: runs, mean, median and the 95% interval of the mean."""
    import pandas as pd

    rows = []
    for setting, group in table.groupby("setting", sort=False):
        for metric in SUMMARISED:
            values = group[metric].dropna().to_numpy(dtype=float)
            low, high = bootstrap_interval(values)
            rows.append({"setting": setting, "metric": metric, "runs": len(values),
                         "mean": values.mean() if len(values) else math.nan,
                         "median": float(np.median(values)) if len(values) else math.nan,
                         "ci95_low": low, "ci95_high": high})
    return pd.DataFrame(rows)


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of p-values for testing them all at once."""
    adjusted, running = [0.0] * len(p_values), 0.0
    for rank, i in enumerate(np.argsort(p_values)):
        running = max(running, min(1.0, (len(p_values) - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def pairwise_tests(table):
    """Every pair of settings, on each TESTED metric: two-sided Mann-Whitney U, Holm-adjusted over
    the pairs, and Vargha-Delaney A12 (the chance that a run of A beats a run of B; 0.5: even)."""
    import pandas as pd
    from scipy.stats import mannwhitneyu

    settings, rows = list(dict.fromkeys(table["setting"])), []
    for metric in TESTED:
        block = []
        for a, b in itertools.combinations(settings, 2):
            x = table.loc[table["setting"] == a, metric].dropna().to_numpy(dtype=float)
            y = table.loc[table["setting"] == b, metric].dropna().to_numpy(dtype=float)
            if len(x) and len(y):
                test = mannwhitneyu(x, y, alternative="two-sided")
                block.append({"metric": metric, "setting_a": a, "setting_b": b, "runs_a": len(x),
                              "runs_b": len(y), "U": float(test.statistic), "p": float(test.pvalue),
                              "A12": float(test.statistic) / (len(x) * len(y))})
        for row, adjusted in zip(block, holm([row["p"] for row in block])):
            row["p_holm"] = adjusted
        rows += block
    return pd.DataFrame(rows, columns=["metric", "setting_a", "setting_b", "runs_a", "runs_b", "U",
                                       "p", "p_holm", "A12"])


METRIC_FORMATS = {"evaluations": "{:.0f}", "num_elites": "{:.0f}", "coverage": "{:.4f}",
                  "qd_score": "{:,.0f}", "best_objective": "{:.1f}", "mean_objective": "{:.1f}",
                  SOLVED_CELLS: "{:.0f}", QD_AUC: "{:,.0f}", CQD_SCORE: "{:.2f}"}


def format_table(table) -> str:
    """The table as aligned text, with as many digits as a reader compares."""
    shown = table.drop(columns=["folder"], errors="ignore")
    return shown.to_string(index=False, formatters={k: v.format for k, v in METRIC_FORMATS.items()
                                                    if k in shown})


def markdown_report(stats, tests) -> str:
    """The statistics as Markdown tables, ready for a README or a paper."""
    def cell(row) -> str:
        number = METRIC_FORMATS[row["metric"]].format
        interval = ("" if math.isnan(row["ci95_low"]) else
                    f" [{number(row['ci95_low'])}, {number(row['ci95_high'])}]")
        return f"{number(row['mean'])}{interval}"

    lines = ["| setting | runs | " + " | ".join(SUMMARISED) + " |",
             "| --- | --- |" + " --- |" * len(SUMMARISED)]
    for setting, group in stats.groupby("setting", sort=False):
        cells = {row["metric"]: cell(row) for row in group.to_dict("records")}
        lines.append(f"| {setting} | {group['runs'].max()} | "
                     + " | ".join(cells[m] for m in SUMMARISED) + " |")
    lines += ["", "Mean [95% bootstrap confidence interval of the mean, BCa] over each setting's runs.",
              f"CQD score: {CQD['targets']:,} target points drawn uniformly in the measure box "
              f"(seed {CQD['target_seed']}), {CQD['penalties']} distance penalties, objectives "
              f"normalised over [{CQD['obj_min']:g}, {CQD['obj_max']:g}].", ""]
    if len(tests):
        lines += ["| metric | A | B | U | p (Holm) | A12 |", "| --- | --- | --- | --- | --- | --- |"]
        lines += [f"| {t['metric']} | {t['setting_a']} | {t['setting_b']} | {t['U']:.1f} | "
                  f"{t['p_holm']:.3g} | {t['A12']:.2f} |" for t in tests.to_dict("records")]
        lines += ["", "Two-sided Mann-Whitney U tests, Holm-adjusted over the pairs of each metric; "
                  "A12: the chance that a run of A beats a run of B (0.5: even; 0.71 or more, or "
                  "0.29 or less: a large effect)."]
        floor = holm_floor(tests)
        if floor > 0.05:
            lines += ["", f"With so few runs per setting, no pair can reach p < 0.05 after Holm's "
                          f"adjustment: the smallest adjusted p possible here is {floor:.3g} (a "
                          f"complete separation, A12 of 0 or 1). Read the effect sizes and the "
                          f"intervals; more seeds give the tests power."]
    return "\n".join(lines) + "\n"


def holm_floor(tests) -> float:
    """The smallest Holm-adjusted p-value any pair of a metric could reach: the exact two-sided
    Mann-Whitney p of a complete separation, 2 / C(n_a + n_b, n_a), times the number of pairs."""
    pairs = tests[tests["metric"] == tests["metric"].iloc[0]]
    return min(1.0, len(pairs) * min(2 / math.comb(int(a + b), int(a))
                                     for a, b in zip(pairs["runs_a"], pairs["runs_b"])))


def expand_folders(paths: list[Path]) -> list[Path]:
    """Run folders, each experiment folder replaced by its runs that have metrics."""
    expanded = []
    for path in paths:
        if (path / "experiment.json").is_file():
            runs = [path / entry["name"] for entry in read_experiment(path)["runs"]]
            expanded += [run for run in runs if (run / "metrics.json").is_file()]
        else:
            expanded.append(path)
    return expanded


def compare(*run_dirs: str, out: str | None = None, overwrite: bool = False) -> None:
    """Compare runs: QD score, coverage and best objective against evaluations on one PNG, and a
    table of their final values (printed, and written as CSV next to the PNG).

    Runs of one setting (the same algorithm and flags, other seeds; an experiment's runs) are
    grouped: the PNG shows their mean with a 95% confidence band, and per setting the number of
    runs, mean, median and 95% bootstrap interval of QD score, coverage, best objective, solved
    cells, QD-score AUC and CQD score are printed and written (OUT_settings.csv); between
    settings, Mann-Whitney U tests on final QD score, QD-score AUC (how soon it got there) and
    CQD score, Holm-adjusted, with Vargha-Delaney A12 (OUT_tests.csv); and both as Markdown
    (OUT.md). Runs of the same batch, iterations and env seed give an equal-budget comparison.

    Args:
        run_dirs: Run folders or experiment folders written by this script.
        out: The PNG to write (the other files get the same name); default: a new
            outputs/compare_<timestamp>.png.
        overwrite: Replace those files if they already exist.
    """
    if not run_dirs:
        raise UsageError("compare needs at least one run folder: "
                         "python lunar_lander.py compare RUN_A RUN_B ...")
    overwrite = boolean("overwrite", overwrite)
    paths = expand_folders([Path(str(run_dir)) for run_dir in run_dirs])
    if not paths:
        raise UsageError(f"no run with metrics in {', '.join(map(str, run_dirs))}")
    configs, runs = zip(*(load_run_metrics(path) for path in paths))
    files = comparison_outputs(None if out is None else str(out), overwrite)
    labels = run_labels(paths, list(configs))
    table = comparison_table(labels, paths, list(configs), list(runs))
    grouped = table["setting"].duplicated().any()
    groups: dict[str, list] = {}
    for label, setting, metrics in zip(labels, table["setting"], runs):
        groups.setdefault(setting if grouped else label, []).append(metrics)
    save_metric_panels(groups, "evaluations", "Evaluations", files["png"])
    write_csv(files["csv"], table)
    print(format_table(table.drop(columns=["setting"])))  # the run's label names its setting
    if table["evaluations"].nunique() > 1:
        print("note: the runs end at different numbers of evaluations; compare at an equal budget")
    written = [files["png"], files["csv"]]
    if grouped:
        stats, tests = setting_statistics(table), pairwise_tests(table)
        write_csv(files["settings"], stats)
        write_csv(files["tests"], tests)
        atomic_write(files["md"], lambda f: f.write(markdown_report(stats, tests)), mode="w")
        print("\nper setting: mean [95% bootstrap interval of the mean] over its runs\n"
              + markdown_report(stats, tests))
        sizes = table["setting"].value_counts()
        if (few := sizes[sizes < FEW_RUNS]).size:
            print(f"note: {', '.join(f'{s} ({n} runs)' for s, n in few.items())}: fewer than "
                  f"{FEW_RUNS} runs; the intervals are wide and the tests can hardly reject anything")
        written += [files["settings"], files["tests"], files["md"]]
    print(f"wrote {', '.join(map(str, written))}")


# ================================================================================================
# Machinery: flag checks, folders and files, logs, the command line
# ================================================================================================

def library_versions() -> dict[str, str]:
    from importlib.metadata import version

    packages = ["ribs", "gymnasium", "box2d", "dask", "distributed", "numpy"]
    return {"python": platform.python_version(), **{name: version(name) for name in packages}}


def positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise UsageError(f"--{name} must be a positive whole number, got {value!r}")
    return value


def non_negative_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise UsageError(f"--{name} must be a whole number >= 0, got {value!r}")
    return value


def positive_float(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise UsageError(f"--{name} must be a positive number, got {value!r}")
    return float(value)


def fraction(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise UsageError(f"--{name} must be a number in (0, 1], got {value!r}")
    return float(value)


def boolean(name: str, value: Any) -> bool:
    """Fire passes --flag=false as the string 'false' (and --flag alone as True)."""
    words = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if str(value).lower() in words:
        return words[str(value).lower()]
    raise UsageError(f"--{name} must be true or false, got {value!r}")


def one_of(choices: dict) -> Callable[[str, Any], str]:
    def check(name: str, value: Any) -> str:
        if value not in choices:
            raise UsageError(f"--{name} must be one of {', '.join(choices)}, got {value!r}")
        return value
    return check


def seed_list(name: str, value: Any) -> list[int]:
    """Seeds as a range 0-19, a list 3,5,8 or both (0-4,10); Fire may have made a number or a
    tuple of it already."""
    import re

    parts = [str(part) for part in value] if isinstance(value, (tuple, list)) else str(value).split(",")
    seeds: list[int] = []
    for part in parts:
        match = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if isinstance(value, bool) or not match or (match[2] and int(match[2]) < int(match[1])):
            raise UsageError(f"--{name} takes seeds >= 0 such as 52, 0-19, 3,5,8 or 0-4,10; got {value!r}")
        seeds += range(int(match[1]), int(match[2] or match[1]) + 1)
    return list(dict.fromkeys(seeds))


def measure_names(name: str, value: Any) -> list[str]:
    """1 to 3 distinct rows of MEASURES, as "a,b" or a list."""
    names = [str(v).strip() for v in value] if isinstance(value, (tuple, list)) else str(value).split(",")
    names = [n.strip() for n in names]
    unknown = [n for n in names if n not in MEASURES]
    if unknown or not 1 <= len(names) <= 3 or len(set(names)) != len(names):
        raise UsageError(f"--{name} takes 1 to 3 different measures of {', '.join(MEASURES)}; "
                         f"got {value!r}")
    return names


# How each search flag is checked; None (a drawn seed, a default folder) passes unchecked.
FLAG_CHECKS: dict[str, Callable[[str, Any], Any]] = {
    "iterations": positive_int,
    "workers": positive_int,
    "seed": non_negative_int,
    "env_seed": seed_list,
    "measures": measure_names,
    "grid": positive_int,
    "algorithm": one_of(ALGORITHMS),
    "n_emitters": positive_int,
    "sigma0": positive_float,
    "batch_size": positive_int,
    "learning_rate": fraction,
    "log_every": positive_int,
    "fast_env": boolean,
}


def check_flags(flags: dict[str, Any]) -> dict[str, Any]:
    return {name: value if value is None or name not in FLAG_CHECKS
            else FLAG_CHECKS[name](name, value) for name, value in flags.items()}


def check_scheduler_reachable(address: str | None) -> None:
    """Fail before anything is written if the scheduler's address is malformed or nobody listens."""
    import socket

    if address is None:
        return
    from distributed.comm import get_address_host_port

    try:
        host, port = get_address_host_port(address)
        socket.create_connection((host, port), timeout=10).close()
    except (OSError, ValueError) as error:
        raise UsageError(f"cannot reach the Dask scheduler at {address}: {error}") from None


LOCK_FILE = ".lock"  # in every folder being written; holds the writer's pid


@contextlib.contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Be the only writer of `folder` while the block runs, or refuse with the holder's pid.

    An OS lock (flock) on folder/.lock: the kernel drops it when its process ends, however it ends,
    so a kill -9 never leaves a stale lock. Readers (elites, compare) take no lock.
    """
    import fcntl

    try:
        fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as error:
        raise UsageError(f"cannot write the folder {folder}: {error.strerror or error}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise UsageError(f"{folder} is being written by another lunar_lander.py process "
                             f"(pid {holder}); wait for it to end, or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def holds_files(folder: Path) -> bool:
    """Whether `folder` exists with anything in it but a lock file (or is not a folder)."""
    return folder.exists() and (not folder.is_dir() or any(
        path.name != LOCK_FILE for path in folder.iterdir()))


@contextlib.contextmanager
def new_folder(outdir: str | None, name: str) -> Iterator[Path]:
    """A new, empty run (or experiment) folder, locked for this process: an existing one is never
    written over, not even by a second command started into the same --outdir at the same moment.
    By default outputs/<timestamp>_<name>."""
    if outdir is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        run_dir = Path("outputs") / f"{stamp}_{name}"
        run_dir = next(p for p in [run_dir, *(Path(f"{run_dir}_{i}") for i in range(2, 1000))]
                       if not p.exists())
    else:
        run_dir = Path(outdir)
    taken = UsageError(f"{run_dir} already exists and is not empty; choose another --outdir "
                       f"(to continue a run there: python lunar_lander.py resume {run_dir})")
    if holds_files(run_dir):
        raise taken
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UsageError(f"cannot write the run folder {run_dir}: {error.strerror or error}") from None
    with folder_lock(run_dir):
        if holds_files(run_dir):  # another process filled it between the check and the lock
            raise taken
        yield run_dir


UMASK = os.umask(0o022)
os.umask(UMASK)


def check_writable(folder: Path) -> None:
    """Refuse, before any work, a folder where nothing can be written (a read-only disk)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".write-test.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as error:
        raise UsageError(f"cannot write in {folder}: {error.strerror or error}") from None


def atomic_write(path: Path, write: Callable[[Any], None], mode: str = "wb") -> None:
    """Write `path` via a temporary file and os.replace, so a crash never leaves half a file.

    A failed write (a full disk, say) leaves the previous file whole and raises a RunError that
    names `path`, not the temporary file the error happened in.
    """
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.chmod(tmp, 0o666 & ~UMASK)  # mkstemp makes files private; outputs are ordinary files
        with os.fdopen(fd, mode) as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(error, OSError):
            raise RunError(f"cannot write {path}: {error.strerror or error}") from None
        raise


def write_json(path: Path, data: Any) -> None:
    atomic_write(path, lambda f: json.dump(data, f, indent=2), mode="w")


def write_pickle(path: Path, obj: Any) -> None:
    atomic_write(path, lambda f: pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL))


def read_run_json(run_dir: Path, name: str) -> Any:
    """A JSON file of a run folder, or a UsageError naming what is missing or wrong."""
    path = run_dir / name
    if not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such run folder")
    if not path.is_file():
        raise UsageError(f"{path}: no such file (is {run_dir} a run folder of lunar_lander.py?)")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise UsageError(f"{path}: not readable JSON ({error})") from None


def read_pickle(path: Path, what: str) -> Any:
    """Unpickle a file of ours, or raise a UsageError that names the file and what is wrong.

    Pickles can run code when loaded: only load files you trust (archive.csv is for sharing).
    """
    if not path.is_file():
        raise UsageError(f"{path}: no such file (expected {what})")
    try:
        with open(path, "rb") as file:
            return pickle.load(file)
    except Exception as error:  # truncated, corrupt, or not a pickle at all
        raise UsageError(f"{path}: not a readable {what} ({type(error).__name__}: {error})") from None


def fault_text(error: BaseException) -> str:
    """An OSError (or our RunError) as one line: the file and the cause, without a traceback."""
    if isinstance(error, OSError) and error.filename:
        return f"{error.filename}: {error.strerror or error}"
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


class QuietFileHandler(logging.FileHandler):
    """run.log is a copy of the console: a failed write (a full disk) must not print a traceback;
    the fault is reported once, by the write that matters."""

    def handleError(self, record: logging.LogRecord) -> None:
        pass


def make_logger(path: Path, name: str = "lunar_lander", console: bool = True) -> logging.Logger:
    """Messages go to the console (if asked) and, appended, to the file `path`."""
    log = logging.getLogger(name)
    log.setLevel(logging.INFO)
    log.propagate = False
    close_logger(log)
    logfile = QuietFileHandler(path, encoding="utf-8", delay=True)
    logfile.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%Y-%m-%d %H:%M:%S"))
    log.addHandler(logfile)
    if console:
        log.addHandler(logging.StreamHandler(sys.stdout))
    return log


def close_logger(log: logging.Logger) -> None:
    for handler in list(log.handlers):
        log.removeHandler(handler)
        handler.close()


# ------------------------------------------------------------------------------------------------
# A streamlined LunarLander-v3: the same episode, bit for bit, for about two thirds of the cost.
# gym.make's env spends much of each step outside Box2D: wrappers, an action-space check, numpy
# calls on 8 floats, two RNG draws, rebuilding body definitions on reset. This copy mirrors
# gymnasium 1.4.0's lunar_lander.py operation for operation without those costs; the tests
# compare it with gym.make over many policies on every run (re-run them after upgrading).
# ------------------------------------------------------------------------------------------------

MAX_STEPS = 1000  # the TimeLimit gym.make("LunarLander-v3") adds
_S, _FPS = upstream.SCALE, upstream.FPS
_W, _H = upstream.VIEWPORT_W / _S, upstream.VIEWPORT_H / _S
# Same expressions as upstream, hence the same bits.
_HALF_W, _HALF_H = upstream.VIEWPORT_W / _S / 2, upstream.VIEWPORT_H / _S / 2
_HELIPAD_Y = _H / 4
_PAD_Y = _HELIPAD_Y + upstream.LEG_DOWN / _S
_MAIN_Y, _SIDE_Y = upstream.MAIN_ENGINE_Y_LOCATION / _S, upstream.SIDE_ENGINE_HEIGHT / _S


@functools.lru_cache(maxsize=64)
def _seeded_randoms(seed: int) -> tuple[list, tuple, list[float]]:
    """Terrain edges, initial force and engine dispersions: upstream's np_random calls.

    Upstream draws two dispersions on *every* step (firing or not, also in reset's own
    step), so all draws depend on the seed alone; one vectorised draw yields the same
    PCG64 stream, and the same bits, as upstream's scalar draws.
    """
    rng, _ = seeding.np_random(seed)
    chunks = 11
    height = rng.uniform(0, _H / 2, size=(chunks + 1,))
    chunk_x = [_W / (chunks - 1) * i for i in range(chunks)]
    height[chunks // 2 - 2 : chunks // 2 + 3] = _HELIPAD_Y
    smooth_y = [0.33 * (height[i - 1] + height[i + 0] + height[i + 1]) for i in range(chunks)]
    edges = [((chunk_x[i], smooth_y[i]), (chunk_x[i + 1], smooth_y[i + 1]))
             for i in range(chunks - 1)]
    force = tuple(rng.uniform(-upstream.INITIAL_RANDOM, upstream.INITIAL_RANDOM) for _ in range(2))
    dispersions = (rng.uniform(-1.0, +1.0, size=2 * (MAX_STEPS + 1)) / _S).tolist()
    return edges, force, dispersions


def _body_def(body_type: int, **kwargs) -> Box2D.b2BodyDef:
    """A reusable body definition (upstream passes the same kwargs on every reset)."""
    return Box2D.b2BodyDef(type=body_type, **kwargs)


class FastLunarLander(upstream.LunarLander):
    """Discrete LunarLander-v3 (default kwargs, no rendering) with a lean `advance`.

    Reuse one instance for many rollouts; every `reset` needs a seed. Engine particles
    are never created (upstream creates them only when rendering); np_random is unused.
    """

    def __init__(self) -> None:
        super().__init__()
        x0, y0, dyn = _W / 2, _H, Box2D.b2_dynamicBody  # upstream's initial_x, initial_y
        self._moon_def = _body_def(Box2D.b2_staticBody,
                                   shapes=edgeShape(vertices=[(0, 0), (_W, 0)]))
        self._edge = edgeShape()
        self._edge_fixture = fixtureDef(shape=self._edge, density=0, friction=0.1)
        self._lander_def = _body_def(dyn, position=(x0, y0), angle=0.0, fixtures=fixtureDef(
            shape=polygonShape(vertices=[(x / _S, y / _S) for x, y in upstream.LANDER_POLY]),
            density=5.0, friction=0.1, categoryBits=0x0010, maskBits=0x001, restitution=0.0))
        self._leg_defs = [_body_def(
            dyn, position=(x0 - i * upstream.LEG_AWAY / _S, y0), angle=(i * 0.05), fixtures=fixtureDef(
                shape=polygonShape(box=(upstream.LEG_W / _S, upstream.LEG_H / _S)), density=1.0,
                restitution=0.0, categoryBits=0x0020, maskBits=0x001)) for i in [-1, +1]]
        self._joint_defs = [revoluteJointDef(
            localAnchorA=(0, 0), localAnchorB=(i * upstream.LEG_AWAY / _S, upstream.LEG_DOWN / _S),
            enableMotor=True, enableLimit=True, maxMotorTorque=upstream.LEG_SPRING_TORQUE,
            motorSpeed=+0.3 * i, lowerAngle=+0.9 - 0.5 if i == -1 else -0.9,
            upperAngle=+0.9 if i == -1 else -0.9 + 0.5) for i in [-1, +1]]
        self._listener = upstream.ContactDetector(self)
        self._disp: list[float] = []
        self._t = 0  # steps taken in this world, reset's own step included

    def reset(self, *, seed: int, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Build a new world as upstream does (same calls, same order), then its no-op step."""
        if seed is None:
            raise ValueError("FastLunarLander.reset needs an explicit seed")
        edges, force, self._disp = _seeded_randoms(seed)
        self.world = world = Box2D.b2World(gravity=(0, self.gravity))
        world.contactListener = self._listener
        self.game_over, self.prev_shaping, self._t, self.helipad_y = False, None, 0, _HELIPAD_Y
        self.moon = world.CreateBody(self._moon_def)
        for p1, p2 in edges:  # CreateFixture copies the shape, so one edgeShape serves all
            self._edge.vertex1, self._edge.vertex2 = p1, p2
            self.moon.CreateFixture(self._edge_fixture)
        self.lander = world.CreateBody(self._lander_def)
        self.lander.ApplyForceToCenter(force, True)
        self.legs = []
        for leg_def, joint_def in zip(self._leg_defs, self._joint_defs):
            leg = world.CreateBody(leg_def)
            leg.ground_contact = False
            joint_def.bodyA, joint_def.bodyB = self.lander, leg
            joint_def.referenceAngle = leg.angle - self.lander.angle  # as pybox2d's kwargs init
            leg.joint = world.CreateJoint(joint_def)
            self.legs.append(leg)
        return np.array(self.advance(0)[0], dtype=np.float32), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Gym-style step, with the 1000-step time limit (fast_rollout uses `advance`)."""
        state, reward, terminated = self.advance(action)
        return np.array(state, dtype=np.float32), reward, terminated, self._t > MAX_STEPS, {}

    def advance(self, action: int) -> tuple[list[float], float, bool]:
        """One step with upstream's arithmetic in plain floats; the state is not yet float32.

        The engines use the lander pose read after the previous world.Step (nothing moves
        the lander in between), which saves four Box2D property reads per firing step.
        """
        lander, t = self.lander, self._t
        self._t = t + 1
        m_power = s_power = 0.0
        if action:
            px, py, angle = self._pose
            tip0, tip1 = math.sin(angle), math.cos(angle)
            side0, side1 = -tip1, tip0
            d0, d1 = self._disp[2 * t], self._disp[2 * t + 1]
            if action == 2:
                m_power = 1.0
                ox = tip0 * (_MAIN_Y + 2 * d0) + side0 * d1
                oy = -tip1 * (_MAIN_Y + 2 * d0) - side1 * d1
                power, at = upstream.MAIN_ENGINE_POWER, (px + ox, py + oy)
                lander.ApplyLinearImpulse((-ox * power * m_power, -oy * power * m_power), at, True)
            else:
                s_power = 1.0
                direction = action - 2
                ox = tip0 * d0 + side0 * (3 * d1 + direction * upstream.SIDE_ENGINE_AWAY / _S)
                oy = -tip1 * d0 - side1 * (3 * d1 + direction * upstream.SIDE_ENGINE_AWAY / _S)
                power = upstream.SIDE_ENGINE_POWER
                at = (px + ox - tip0 * 17 / _S, py + oy + tip1 * _SIDE_Y)
                lander.ApplyLinearImpulse((-ox * power * s_power, -oy * power * s_power), at, True)
        self.world.Step(1.0 / _FPS, 6 * 30, 2 * 30)

        pos, vel, legs = lander.position, lander.linearVelocity, self.legs
        px, py, angle = pos.x, pos.y, lander.angle
        self._pose = px, py, angle
        x, y = (px - _HALF_W) / _HALF_W, (py - _PAD_Y) / _HALF_H
        vx, vy = vel.x * _HALF_W / _FPS, vel.y * _HALF_H / _FPS
        leg0 = 1.0 if legs[0].ground_contact else 0.0
        leg1 = 1.0 if legs[1].ground_contact else 0.0
        state = [x, y, vx, vy, angle, 20.0 * lander.angularVelocity / _FPS, leg0, leg1]
        shaping = (-100 * math.sqrt(x * x + y * y) - 100 * math.sqrt(vx * vx + vy * vy)
                   - 100 * abs(angle) + 10 * leg0 + 10 * leg1)  # math.sqrt == np.sqrt, bitwise
        reward = 0.0 if self.prev_shaping is None else shaping - self.prev_shaping
        self.prev_shaping = shaping
        reward = reward - m_power * 0.30 - s_power * 0.03
        if not lander.awake:  # checked last upstream, so it wins
            return state, 100.0, True
        if self.game_over or abs(x) >= 1.0:
            return state, -100.0, True
        return state, reward, False



# The explorer's page (see `explore`): plain HTML, CSS and JavaScript, no library, nothing fetched.
# The Python side replaces /*DATA*/null with the run's data (explorer_data).
EXPLORER_PAGE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<title>Lunar Lander archive explorer</title>
<style>
  body { font: 14px system-ui, sans-serif; margin: 16px; background: #f6f6f8; color: #222; }
  h1 { font-size: 20px; margin: 0 0 4px; } h2 { font-size: 15px; margin: 0 0 8px; }
  .row { display: flex; gap: 16px; flex-wrap: wrap; align-items: flex-start; margin-bottom: 16px; }
  .panel { background: #fff; border: 1px solid #ddd; border-radius: 6px; padding: 12px; }
  #tip { position: fixed; pointer-events: none; background: #222; color: #fff; padding: 6px 8px;
         border-radius: 4px; font-size: 12px; white-space: pre; display: none; z-index: 2; }
  #info { font-size: 13px; margin-top: 8px; min-height: 3em; white-space: pre-line; }
  table { border-collapse: collapse; font-size: 13px; }
  th, td { padding: 3px 10px; text-align: right; border-bottom: 1px solid #eee; }
  th { cursor: pointer; background: #f0f0f4; user-select: none; } tbody tr { cursor: pointer; }
  tbody tr:hover td, tr.playing td { background: #e8e8ff; }
  .axis { font-size: 12px; color: #555; }
</style></head>
<body>
<h1>Lunar Lander archive explorer</h1>
<div class="axis" id="subtitle"></div>
<div class="row">
  <div class="panel"><h2>Archive: objective per cell (hover for numbers, click to watch)</h2>
    <canvas id="heatmap"></canvas>
    <div id="switch" style="display:none">Colour by:
      <label><input type="radio" name="colour" value="objective" checked> objective</label>
      <label><input type="radio" name="colour" value="robust"> mean objective on other terrains</label>
    </div></div>
  <div class="panel"><h2>Landing</h2>
    <canvas id="flight" width="600" height="400"></canvas>
    <div><button id="play">Play</button> <button id="restart">Restart</button>
      <input type="range" id="slider" min="0" max="0" value="0" style="width:330px">
      <span id="step" class="axis"></span></div>
    <div id="info">Click a cell of the archive or a row of the table to watch its elite land.</div>
  </div>
</div>
<div class="row"><div class="panel"><h2>Progress</h2>
  <canvas id="curves" width="960" height="220"></canvas></div></div>
<div class="row"><div class="panel"><h2>Best elites (click a header to sort, a row to watch)</h2>
  <table id="elites"><thead></thead><tbody></tbody></table></div></div>
<div id="tip"></div>
<script>
"use strict";
const DATA = /*DATA*/null;

// ---- data: the packed flights (see POSE_SCALE in lunar_lander.py) ----
function bytes(base64) {
  const text = atob(base64), out = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) out[i] = text.charCodeAt(i);
  return out;
}
const POSES = new Int16Array(bytes(DATA.poses).buffer), ACTIONS = bytes(DATA.actions);
const SCALE = DATA.pose_scale, W = DATA.world;
function pose(elite, step) {  // [x, y, angle, left leg angle, right leg angle], metres and radians
  const at = (elite.offset + step) * 5;
  return [0, 1, 2, 3, 4].map(k => POSES[at + k] / SCALE[k]);
}
const fmt = (v, d = 2) => (v === null || v === undefined) ? "-" : Number(v).toFixed(d);

// ---- the heatmap: cells of the first two measures (the best elite over a third) ----
const [NX, NY] = [DATA.dims[0], DATA.dims[1] || 1];
const CELL = Math.max(4, Math.floor(400 / Math.max(NX, NY)));
const PAD = 50, heat = document.getElementById("heatmap");
heat.width = NX * CELL + PAD + 70; heat.height = NY * CELL + PAD;
const cells = new Map();  // "gx,gy" -> the elite drawn there
for (const e of DATA.elites) {
  const key = e.gx + "," + e.gy, there = cells.get(key);
  if (!there || e.objective > there.objective) cells.set(key, e);
}
const yDown = DATA.measures.length > 1 && DATA.measures[1].descending;
const cellRow = gy => yDown ? gy : NY - 1 - gy;
let colourBy = "objective";
function colour(value) {
  const [lo, hi] = DATA.heat_range;
  const i = Math.round(255 * Math.min(1, Math.max(0, (value - lo) / (hi - lo))));
  return DATA.colormap[i];
}
function drawHeatmap() {
  const g = heat.getContext("2d");
  g.fillStyle = "#fff"; g.fillRect(0, 0, heat.width, heat.height);
  g.fillStyle = "#eee"; g.fillRect(PAD, 0, NX * CELL, NY * CELL);
  for (const e of cells.values()) {
    const value = colourBy === "robust" ? (e.robust ? e.robust[0] : null) : e.objective;
    g.fillStyle = value === null ? "#ccc" : colour(value);
    g.fillRect(PAD + e.gx * CELL, cellRow(e.gy) * CELL, CELL, CELL);
  }
  g.fillStyle = "#333"; g.font = "12px sans-serif"; g.textAlign = "center";
  const [mx, my] = DATA.measures;
  g.fillText(mx.label + "  [" + mx.range.join(", ") + "]", PAD + NX * CELL / 2, NY * CELL + 30);
  if (my) {
    g.save(); g.translate(14, NY * CELL / 2); g.rotate(-Math.PI / 2);
    const span = yDown ? "  (" + my.range[0] + " on top)" : "  [" + my.range.join(", ") + "]";
    g.fillText(my.label + span, 0, 0);
    g.restore();
  }
  for (let i = 0; i < 100; i++) {  // the colour bar
    g.fillStyle = colour(DATA.heat_range[0] + (i / 99) * (DATA.heat_range[1] - DATA.heat_range[0]));
    g.fillRect(PAD + NX * CELL + 16, NY * CELL * (1 - (i + 1) / 100), 14, NY * CELL / 100 + 1);
  }
  g.textAlign = "left"; g.fillStyle = "#333";
  g.fillText(DATA.heat_range[1], PAD + NX * CELL + 34, 10);
  g.fillText(DATA.heat_range[0], PAD + NX * CELL + 34, NY * CELL);
}
function cellAt(event) {
  const box = heat.getBoundingClientRect();
  const gx = Math.floor((event.clientX - box.left - PAD) / CELL);
  const row = Math.floor((event.clientY - box.top) / CELL);
  if (gx < 0 || gx >= NX || row < 0 || row >= NY) return null;
  return cells.get(gx + "," + (yDown ? row : NY - 1 - row)) || null;
}
function describe(e) {
  const lines = ["cell " + e.index, "objective " + fmt(e.objective)];
  DATA.measures.forEach((m, i) => lines.push(m.name + " " + fmt(e.measures[i], 3)));
  if (e.robust) {
    lines.push("other terrains: mean " + fmt(e.robust[0]) + ", landed " + fmt(100 * e.robust[1], 0) + "%");
  }
  return lines.join("\n");
}
const tip = document.getElementById("tip");
heat.addEventListener("mousemove", event => {
  const e = cellAt(event);
  if (!e) { tip.style.display = "none"; return; }
  tip.textContent = describe(e); tip.style.display = "block";
  tip.style.left = (event.clientX + 14) + "px"; tip.style.top = (event.clientY + 14) + "px";
});
heat.addEventListener("mouseleave", () => { tip.style.display = "none"; });
heat.addEventListener("click", event => { const e = cellAt(event); if (e) watch(e); });
if (DATA.robustness) {
  document.getElementById("switch").style.display = "block";
  for (const radio of document.getElementsByName("colour"))
    radio.addEventListener("change", () => { colourBy = radio.value; drawHeatmap(); });
}

// ---- the landing: terrain, flight path, lander and legs at their recorded poses ----
const flight = document.getElementById("flight"), fg = flight.getContext("2d");
const PX = flight.width / W.width;  // pixels per metre: the env's own view, 600 x 400
const toX = x => x * PX, toY = y => flight.height - y * PX;
let current = null, step = 0, playing = false, last = 0;
const slider = document.getElementById("slider");
function drawFlight() {
  fg.fillStyle = "#000"; fg.fillRect(0, 0, flight.width, flight.height);
  fg.fillStyle = "#fff"; fg.beginPath(); fg.moveTo(0, flight.height);  // the ground
  for (const [x, y] of W.ground) fg.lineTo(toX(x), toY(y));
  fg.lineTo(flight.width, flight.height); fg.closePath(); fg.fill();
  for (const x of W.helipad_x) {  // the helipad's flags
    fg.strokeStyle = "#fff"; fg.beginPath(); fg.moveTo(toX(x), toY(W.helipad_y));
    fg.lineTo(toX(x), toY(W.helipad_y) - 50); fg.stroke();
    fg.fillStyle = "#cccc00"; fg.beginPath(); fg.moveTo(toX(x), toY(W.helipad_y) - 50);
    fg.lineTo(toX(x), toY(W.helipad_y) - 40); fg.lineTo(toX(x) + 25, toY(W.helipad_y) - 45); fg.fill();
  }
  if (!current) return;
  fg.strokeStyle = "#6cf"; fg.lineWidth = 1.5; fg.beginPath();  // the flight path so far
  for (let i = 0; i <= step; i++) {
    const [x, y] = pose(current, i);
    i ? fg.lineTo(toX(x), toY(y)) : fg.moveTo(toX(x), toY(y));
  }
  fg.stroke(); fg.lineWidth = 1;
  const [x, y, angle, ...legs] = pose(current, step);
  const action = ACTIONS[current.offset + step];
  [-1, 1].forEach((side, i) => drawLeg(x, y, legs[i], side));
  drawBody(x, y, angle, action);
}
function rotate(px, py, angle) {
  return [px * Math.cos(angle) - py * Math.sin(angle), px * Math.sin(angle) + py * Math.cos(angle)];
}
function polygon(points, fill, stroke) {
  fg.beginPath();
  points.forEach(([px, py], i) => i ? fg.lineTo(toX(px), toY(py)) : fg.moveTo(toX(px), toY(py)));
  fg.closePath(); fg.fillStyle = fill; fg.fill(); fg.strokeStyle = stroke; fg.stroke();
}
function drawLeg(x, y, angle, side) {  // the joint holds the leg's anchor at the lander's centre
  const [away, down, w, h] = W.leg, [ax, ay] = rotate(side * away, down, angle);
  const cx = x - ax, cy = y - ay;
  polygon([[-w, -h], [w, -h], [w, h], [-w, h]].map(([px, py]) => {
    const [rx, ry] = rotate(px, py, angle); return [cx + rx, cy + ry]; }), "#8066e6", "#4d4d80");
}
function drawBody(x, y, angle, action) {
  if (action) {  // the firing engine's flame: main below, sides (1: left engine, 3: right)
    const flame = action === 2 ? [[-0.15, -0.25], [0.15, -0.25], [0, -0.9]]
      : action === 1 ? [[0.45, 0.05], [0.45, 0.25], [0.95, 0.15]]
      : [[-0.45, 0.05], [-0.45, 0.25], [-0.95, 0.15]];
    polygon(flame.map(([px, py]) => { const [rx, ry] = rotate(px, py, angle); return [x + rx, y + ry]; }),
            "#ff9a1f", "#ff5a00");
  }
  polygon(W.lander.map(([px, py]) => { const [rx, ry] = rotate(px, py, angle); return [x + rx, y + ry]; }),
          "#8066e6", "#4d4d80");
}
function show(newStep) {
  step = Math.max(0, Math.min(newStep, current ? current.steps : 0));
  slider.value = step;
  document.getElementById("step").textContent = current ? "step " + step + " / " + current.steps : "";
  drawFlight();
}
function watch(e) {
  current = e; slider.max = e.steps;
  document.getElementById("info").textContent = describe(e).replace(/\n/g, ", ")
    + "\nepisode: " + e.steps + " steps on terrain " + DATA.env_seed;
  for (const tr of document.querySelectorAll("tbody tr")) tr.classList.toggle("playing", tr.elite === e);
  show(0); play(true);
}
function play(on) {
  playing = on && current !== null && step < current.steps;
  document.getElementById("play").textContent = playing ? "Pause" : "Play";
  if (playing) { last = performance.now(); requestAnimationFrame(tick); }
}
function tick(now) {  // the env's 50 steps a second
  if (!playing) return;
  const steps = Math.floor((now - last) * W.fps / 1000);
  if (steps > 0) { last += steps * 1000 / W.fps; show(step + steps); }
  if (step >= current.steps) { play(false); return; }
  requestAnimationFrame(tick);
}
document.getElementById("play").addEventListener("click", () => {
  if (current && step >= current.steps) show(0);
  play(!playing);
});
document.getElementById("restart").addEventListener("click", () => { show(0); play(true); });
slider.addEventListener("input", () => { play(false); show(Number(slider.value)); });

// ---- the table of the best elites ----
const columns = [["cell", e => e.index], ["objective", e => e.objective],
  ...DATA.measures.map((m, i) => [m.name, e => e.measures[i]]), ["steps", e => e.steps]];
if (DATA.robustness) columns.push(["mean other terrains", e => e.robust ? e.robust[0] : null]);
const best = [...DATA.elites].sort((a, b) => b.objective - a.objective).slice(0, 200);
let sortBy = 1, ascending = false;
function drawTable() {
  const head = document.querySelector("#elites thead"), body = document.querySelector("#elites tbody");
  head.innerHTML = ""; body.innerHTML = "";
  const tr = head.insertRow();
  columns.forEach(([name], i) => {
    const th = document.createElement("th");
    th.textContent = name + (i === sortBy ? (ascending ? " \u25b2" : " \u25bc") : "");
    th.addEventListener("click", () => {
      ascending = i === sortBy ? !ascending : false; sortBy = i; drawTable();
    });
    tr.appendChild(th);
  });
  const key = columns[sortBy][1];
  const rows = [...best].sort(
    (a, b) => (ascending ? 1 : -1) * ((key(a) ?? -Infinity) - (key(b) ?? -Infinity)));
  for (const e of rows) {
    const row = body.insertRow(); row.elite = e; row.classList.toggle("playing", e === current);
    columns.forEach(([name, value], i) => {
      row.insertCell().textContent = i === 0 ? value(e) : fmt(value(e), name === "steps" ? 0 : 2);
    });
    row.addEventListener("click", () => watch(e));
  }
}

// ---- the run's progress: QD score, coverage and best objective against iterations ----
function drawCurves() {
  const canvas = document.getElementById("curves"), g = canvas.getContext("2d");
  const panels = [["qd_score", "QD score"], ["coverage", "Coverage"], ["best_objective", "Best objective"]];
  const w = canvas.width / 3, M = DATA.metrics;
  g.fillStyle = "#fff"; g.fillRect(0, 0, canvas.width, canvas.height); g.font = "12px sans-serif";
  panels.forEach(([key, title], p) => {
    const points = M.filter(r => r[key] !== null).map(r => [r.iteration, r[key]]);
    if (!points.length) return;
    const xs = points.map(q => q[0]), ys = points.map(q => q[1]);
    const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    const left = p * w + 50, right = (p + 1) * w - 14, top = 24, bottom = canvas.height - 30;
    const sx = x => left + (right - left) * (x1 > x0 ? (x - x0) / (x1 - x0) : 0.5);
    const sy = y => bottom - (bottom - top) * (y1 > y0 ? (y - y0) / (y1 - y0) : 0.5);
    g.strokeStyle = "#999"; g.strokeRect(left, top, right - left, bottom - top);
    g.fillStyle = "#333"; g.textAlign = "center"; g.fillText(title, (left + right) / 2, 16);
    g.fillText("iteration", (left + right) / 2, canvas.height - 8);
    g.textAlign = "right"; g.fillText(fmt(y1, key === "coverage" ? 3 : 0), left - 4, top + 8);
    g.fillText(fmt(y0, key === "coverage" ? 3 : 0), left - 4, bottom);
    g.strokeStyle = "#1f77b4"; g.lineWidth = 2; g.beginPath();
    points.forEach(([x, y], i) => i ? g.lineTo(sx(x), sy(y)) : g.moveTo(sx(x), sy(y)));
    g.stroke(); g.lineWidth = 1;
  });
}

document.getElementById("subtitle").textContent = DATA.run + ": " + DATA.algorithm + ", "
  + DATA.elites.length + " elites, flown on terrain " + DATA.env_seed;
drawHeatmap(); drawTable(); drawCurves(); drawFlight();
window.explorerReady = performance.now();  // ms since the page was opened: interactive from here
</script>
</body></html>
"""


COMMANDS: dict[str, Callable] = {
    "search": search, "resume": resume, "experiment": experiment, "video": video, "elites": elites,
    "trajectories": trajectories, "evaluate": evaluate_robustness, "explore": explore,
    "compare": compare,
}


def reject_unknown_flags(command: Callable, args: list[str]) -> None:
    """Fire would print a page of usage for a mistyped flag; one line naming it is clearer."""
    import inspect

    known = set(inspect.signature(command).parameters) - {"search_flags"}
    if command is experiment:
        known |= set(inspect.signature(search).parameters) - EXPERIMENT_OWN
    for arg in args:
        if arg.startswith("--") and arg not in ("--help", "--"):
            name = arg[2:].split("=", 1)[0].replace("-", "_")
            if name not in known:
                raise UsageError(f"unknown flag --{name}; valid flags: "
                                 + ", ".join(f"--{flag}" for flag in known))


def main(argv: list[str]) -> int:
    import fire

    name = argv[0] if argv and not argv[0].startswith("-") else "search"
    args = argv[1:] if argv and not argv[0].startswith("-") else argv
    STOP.install()
    try:
        if name not in COMMANDS:
            raise UsageError(f"unknown command {name!r}; commands: {', '.join(COMMANDS)}")
        reject_unknown_flags(COMMANDS[name], args)
        fire.Fire(COMMANDS[name], command=args, name="lunar_lander.py" if name == "search" else name)
    except UsageError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except (RunError, OSError) as error:  # OSError: any fault not already described better
        print(f"error: {fault_text(error)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
        return 130
    return 0


def exit_now(code: Any) -> None:
    """Leave as sys.exit would, without the interpreter's teardown of ribs, dask, matplotlib and
    the rest (most of a second here): every file is written and closed, the cluster is down."""
    if not isinstance(code, int):
        if code is not None:
            print(code, file=sys.stderr)
        code = 0 if code is None else 1
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    try:
        exit_now(main(sys.argv[1:]))
    except SystemExit as done:  # fire's --help and its own usage messages
        exit_now(done.code)
