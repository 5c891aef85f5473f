#!/usr/bin/env python
"""Search Gymnasium's Lunar Lander for many different good landings with CMA-ME (pyribs), on Dask;
and other Gymnasium tasks (BipedalWalker, the continuous lander) through the same tables.

The problem, the algorithm and the results follow the pyribs tutorial "Using CMA-ME to Land a Lunar
Lander Like a Space Shuttle"; this script adds what a research run needs around them: a Dask
evaluation engine, seeded and repeatable runs, checkpoints, metrics, plots and a CLI.

    python lunar_lander.py --iterations 300 --workers 2     # search; writes outputs/<run>/
    python lunar_lander.py --algorithm cma_mae               # or map_elites; default cma_me
    python lunar_lander.py --measures fuel,flight_time --env_seed 0-4   # other axes, 5 terrains
    python lunar_lander.py --env BipedalWalker-v3            # another task: a row of ENVIRONMENTS
    python lunar_lander.py resume outputs/RUN                # continue a run from its checkpoint
    python lunar_lander.py experiment --algorithms "[cma_me, cma_mae]" --seeds 1-5   # many runs
    python lunar_lander.py video outputs/RUN --cells "[(-0.4, -0.1)]"   # or --best, --top K
    python lunar_lander.py elites outputs/RUN --min_objective 200       # table of elites
    python lunar_lander.py trajectories outputs/RUN --top 10            # flight paths picture
    python lunar_lander.py evaluate outputs/RUN --env_seeds 0-19        # robustness on terrains
    python lunar_lander.py explore outputs/RUN                          # browse, watch landings
    python lunar_lander.py compare outputs/RUN_A outputs/EXPERIMENT     # statistics across seeds
    python lunar_lander.py COMMAND --help                    # every flag of a command

This file tells the tutorial's story, top to bottom:
- The problem. A task: a row of ENVIRONMENTS (Gymnasium id, the linear policy's shape, its
  family's episode function, default measures, QD offset). A measure: a row of MEASURES (label,
  range, short name, how an episode's summary gives it, its family). `fly_lander` and
  `fly_walker` gather what measures read from an episode; the objective is its total reward.
- The algorithms: a row of ALGORITHMS (archive kwargs, emitter class and kwargs).
- The evaluation engine: `submit_flights` chunks (solution, terrain) pairs for Dask; `fly_chunk`
  runs on the workers; `evaluate_batch` averages each solution over the run's terrains.
- The run: `Run` holds one search between iterations and is the one place a checkpoint is built
  and written; `run_loop` is ask -> evaluate -> tell; `save_outputs` writes the run folder's files,
  in a `Saver` thread while the search goes on.
- The commands: the flag tables (SEARCH_FLAGS, CLUSTER_FLAGS, SELECTION_FLAGS: each flag's
  default, help, check and part in experiments, declared once), `search` and `resume`, and the
  command line (COMMANDS, `main`: bad input is one line and exit code 2).

The supporting work lives in sibling modules, each opening with a map of itself:
- experiments.py: `experiment`, many runs interleaved on one cluster, and their resume;
- results.py: the commands that look at a run (video, elites, trajectories, evaluate, explore),
  with the explorer's page in explorer_page.html;
- comparison.py: `compare` and its statistics across seeds;
- cluster.py: the Dask cluster: found, checked and joined with bounded waits, or started locally;
  STOP (Ctrl-C and SIGTERM);
- fast_env.py: the streamlined Lunar Lander the rollouts fly in (bitwise gym.make's);
- plots.py: the heatmaps and progress curves;
- run_files.py: locks, atomic writes, JSON and pickles, logs;
- flags.py: the `Flag` entry, the checkers and UsageError.
They import this module; this module imports only cluster, fast_env, plots, run_files and flags
at load time.
"""

from __future__ import annotations

import sys

if __name__ == "__main__":
    # Run as a script: the work is done by the module imported by its name, the one module that
    # Dask's workers and the sibling modules import too (one STOP, one set of tables).
    import lunar_lander

    lunar_lander.run_as_script()

import contextlib
import dataclasses
import datetime
import importlib
import logging
import math
import os
import pickle
import secrets
import shlex
import signal
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator

import Box2D
import gymnasium as gym
import numpy as np

from cluster import STOP, SchedulerLost, dask_client, scheduler_of
from fast_env import FastLunarLander
from flags import (
    Flag,
    UsageError,
    as_typed,
    boolean,
    check_flags,
    distinct_names,
    fraction,
    one_line,
    one_of,
    positive_float,
    positive_int,
    seed_list,
    seed_number,
    shown,
    takes,
    whole_number_up_to,
)
from plots import save_heatmap, save_progress_plot
from run_files import (
    RunError,
    atomic_write,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
    read_pickle,
    read_run_json,
    write_csv,
    write_json,
    write_pickle,
)

# Plots are written to files, never shown: no display is needed (set before matplotlib loads).
os.environ.setdefault("MPLBACKEND", "Agg")
# ribs' CMA-ES code is written for numba, which compiles it on the first ask/tell of a process
# (2.6-4.5 s). The compiled code's last bits differ (from the 26th iteration on, for 32 weights),
# and it is not much faster: 1.31 vs 1.39 ms per ask+tell for 32 weights (the lander), 1.79 vs
# 2.01 for 96 (the walker), 3.39 vs 4.02 for 216 (benchmarks/bench_ask_tell.py, 2026-11-24). So
# compilation is off unless asked for, and every search computes the same bits.
os.environ.setdefault("NUMBA_DISABLE_JIT", "1")

# Dask spawns worker processes that re-import this script, so the heavy libraries that only the
# main process needs (ribs, matplotlib, dask itself) are imported inside the functions using them.
if __name__ == "__mp_main__":
    # A local worker: Ctrl-C in a terminal reaches the whole process group, but stopping is the
    # main process's job (it abandons the iteration and closes the cluster), so workers ignore it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# ================================================================================================
# The problem: a linear policy flying a Gymnasium task, and what its episode is measured by
# ================================================================================================

NOOP, LEFT, MAIN, RIGHT = range(4)  # Lunar Lander's discrete actions: engines off, or one fires


@dataclasses.dataclass
class Flight:
    """A Lunar Lander episode summed up: everything a lander measure may read, in a single pass.

    "Touchdown" is the first step on which either leg touches the ground. A lander that never
    touches it has no touchdown; its impact observation is then its last one. `firings` counts
    each engine's firings; with throttles (the continuous lander) it sums their power, as the
    env's fuel cost does.
    """

    reward: float = 0.0  # the episode's total reward: the objective
    steps: int = 0
    touchdown: np.ndarray | None = None  # the observation at touchdown
    touchdown_step: int | None = None
    last: np.ndarray | None = None  # the last observation
    min_y_velocity: float = math.inf  # the fastest descent of the whole episode
    max_tilt: float = 0.0  # the largest |angle| up to touchdown (the whole episode without one)
    firings: list[float] = dataclasses.field(default_factory=lambda: [0] * 4)

    @property
    def impact(self) -> np.ndarray:
        return self.last if self.touchdown is None else self.touchdown


@dataclasses.dataclass
class Walk:
    """A BipedalWalker episode summed up, for the walker measures."""

    reward: float = 0.0  # the episode's total reward: the objective
    steps: int = 0
    contacts: list[int] = dataclasses.field(default_factory=lambda: [0, 0])  # steps on which each
    # lower leg touches the ground (observations 8 and 13)
    distance: float = 0.0  # the hull's x at the end less its x at the start, in metres
    hull_angles: float = 0.0  # the hull's angle (observation 0), summed over the steps

    def share(self, leg: int) -> float:
        return self.contacts[leg] / max(self.steps, 1)


def linear_policy(solution: np.ndarray, continuous: bool, shape: tuple[int, int]) -> Callable:
    """obs -> action of the policy W @ obs (no bias): argmax for discrete actions, tanh of each
    component for continuous ones (the action box is [-1, 1] in every task here)."""
    weights = np.asarray(solution, dtype=np.float64).reshape(shape)
    # W.dot(obs) makes the same BLAS call as W @ obs (same bits) for less overhead; a strided W
    # would take matmul's non-BLAS path, so it keeps matmul.
    scores = weights.dot if weights.flags.c_contiguous else weights.__matmul__
    if continuous:
        return lambda obs: np.tanh(scores(obs))
    return lambda obs: int(scores(obs).argmax())


def burn(firings: list[float], action: np.ndarray) -> None:
    """The continuous lander's engine powers of one step, as its env computes them: the main
    engine fires at half to full power when action[0] > 0, a side engine when |action[1]| > 0.5."""
    if action[0] > 0.0:
        firings[MAIN] += (min(float(action[0]), 1.0) + 1.0) * 0.5
    if abs(action[1]) > 0.5:
        firings[RIGHT if action[1] > 0 else LEFT] += min(abs(float(action[1])), 1.0)


def fly_lander(solution: np.ndarray, env_seed: int, env: gym.Env, task: Environment,
               on_step: Callable[[Any, np.ndarray], None] | None = None) -> Flight:
    """One Lunar Lander episode of the linear policy on the terrain of `env_seed`; `on_step` is
    called with each step's action and observation."""
    policy = linear_policy(solution, task.continuous, (task.action_dim, task.obs_dim))
    obs, _ = env.reset(seed=env_seed)
    flight, firings, done, continuous = Flight(), [0] * 4, False, task.continuous
    total_reward, min_y_velocity, max_tilt, touchdown, steps = 0.0, math.inf, 0.0, None, 0
    while not done:
        action = policy(obs)
        if continuous:
            burn(firings, action)
        else:
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


def fly_walker(solution: np.ndarray, env_seed: int, env: gym.Env, task: Environment,
               on_step: Callable[[Any, np.ndarray], None] | None = None) -> Walk:
    """One BipedalWalker episode of the linear policy on the terrain of `env_seed`."""
    policy = linear_policy(solution, task.continuous, (task.action_dim, task.obs_dim))
    renew_world(env.unwrapped)
    obs, _ = env.reset(seed=env_seed)
    hull, walk, done = env.unwrapped.hull, Walk(), False
    start_x, contacts, total_reward, angles, steps = hull.position.x, [0, 0], 0.0, 0.0, 0
    while not done:
        action = policy(obs)
        obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        steps += 1
        total_reward += reward
        angles += float(obs[0])  # in float64: a float32 sum drifts over 1,600 steps
        contacts[0] += obs[8] > 0.5
        contacts[1] += obs[13] > 0.5
        if on_step is not None:
            on_step(action, obs)
    walk.reward, walk.steps, walk.contacts = total_reward, steps, contacts
    walk.distance, walk.hull_angles = float(hull.position.x - start_x), float(angles)
    return walk


def renew_world(walker: Any) -> None:
    """Give a BipedalWalker a new Box2D world before its reset. Its reset only destroys the last
    episode's bodies, and a world that has held them solves contacts in another order: episodes
    in a reused env differed from a fresh env's (measured). With a new world they are the same,
    bit for bit."""
    walker._destroy()
    walker.world = Box2D.b2World()


@dataclasses.dataclass(frozen=True)
class Environment:
    """A Gymnasium task a search can fly (a row of ENVIRONMENTS, picked by --env).

    The policy is W @ obs with no bias: `action_dim` rows of `obs_dim` weights, the solution the
    QD algorithm searches. Tasks of one `family` share an episode function and its measures.
    """

    gym_id: str
    kwargs: dict[str, Any]
    obs_dim: int
    action_dim: int
    continuous: bool  # action = tanh(W @ obs) (a Box of [-1, 1]); else argmax(W @ obs) (Discrete)
    family: str  # "lander" or "walker": the MEASURES rows it may use, and the picture it makes
    fly: Callable  # the episode function: (solution, env_seed, env, task, on_step) -> its summary
    measures: tuple[str, ...]  # the default --measures
    qd_offset: float  # below (almost) every return: QD score counts every elite
    env_seed: str  # what --env_seed picks in this task
    solved: float  # the return its env calls solved
    fast: Callable[[], gym.Env] | None = None  # a streamlined copy, bitwise the same (fast_env.py)

    @property
    def solution_dim(self) -> int:
        return self.action_dim * self.obs_dim


# The tasks a search can fly (--env). To add a Gymnasium task with a Box observation, add a row
# (and, for a new family, an episode function and its MEASURES rows). The QD offsets are below
# the lowest returns of real runs (docs/environments.md).
ENVIRONMENTS: dict[str, Environment] = {
    # The tutorial's: observation (x, y, vx, vy, angle, spin, leg1, leg2); 4 actions.
    "LunarLander-v3": Environment(
        "LunarLander-v3", {}, 8, 4, False, "lander", fly_lander, ("impact_x", "impact_y_velocity"),
        -600.0, "the terrain and the initial push", 200.0, fast=FastLunarLander),
    # Throttles instead of switches: main engine and lateral engine, each in [-1, 1].
    "LunarLanderContinuous-v3": Environment(
        "LunarLander-v3", {"continuous": True}, 8, 2, True, "lander", fly_lander,
        ("impact_x", "impact_y_velocity"), -1200.0, "the terrain and the initial push", 200.0),
    # Hull angle, speeds, 4 joints' angles and speeds, 2 foot contacts, 10 lidar readings; 4
    # torques. An episode ends when the hull touches the ground, or after 1,600 steps.
    "BipedalWalker-v3": Environment(
        "BipedalWalker-v3", {}, 24, 4, True, "walker", fly_walker, ("foot1_contact", "foot2_contact"),
        -300.0, "the grassland's heights", 300.0),
    # The same walker among stumps, pits and stairs, for up to 2,000 steps.
    "BipedalWalkerHardcore-v3": Environment(
        "BipedalWalkerHardcore-v3", {}, 24, 4, True, "walker", fly_walker,
        ("foot1_contact", "foot2_contact"), -350.0, "the obstacles and the grassland", 300.0),
}
DEFAULT_ENV = "LunarLander-v3"  # the tutorial's, and what run folders from before --env flew


def make_env(fast: bool = True, render_mode: str | None = None, env_name: str = DEFAULT_ENV) -> gym.Env:
    """The environment rollouts fly in: the task's streamlined copy if it has one (fast_env.py),
    or gym.make's plain one (needed to render, and the reference the copy is tested against)."""
    task = ENVIRONMENTS[env_name]
    if fast and render_mode is None and task.fast is not None:
        return task.fast()
    return gym.make(task.gym_id, render_mode=render_mode, **task.kwargs)


def check_spaces(env_name: str) -> None:
    """Refuse a row whose task the linear policy can't serve: its observation must be a vector of
    obs_dim numbers, its actions action_dim choices, or a box of action_dim numbers in [-1, 1]."""
    task = ENVIRONMENTS[env_name]
    env = gym.make(task.gym_id, **task.kwargs)
    obs, act = env.observation_space, env.action_space
    env.close()
    fits = isinstance(obs, gym.spaces.Box) and obs.shape == (task.obs_dim,) and (
        isinstance(act, gym.spaces.Box) and act.shape == (task.action_dim,)
        and bool(np.all(act.low >= -1.0)) and bool(np.all(act.high <= 1.0))
        if task.continuous else isinstance(act, gym.spaces.Discrete) and act.n == task.action_dim)
    if not fits:
        policy = "tanh(W @ obs)" if task.continuous else "argmax(W @ obs)"
        raise UsageError(f"--env {env_name}: the linear policy {policy} of {task.action_dim} x "
                         f"{task.obs_dim} weights can't serve {task.gym_id}'s observations {obs} "
                         f"and actions {act}")


@dataclasses.dataclass(frozen=True)
class Measure:
    """One behaviour solutions are told apart by: its axis label, its range in the archive (values
    outside fall into the edge cells), a short name for file names, how an episode's summary gives
    it, and the family of tasks whose summary that is."""

    label: str
    range: tuple[float, float]
    short: str
    of: Callable[[Any], float]
    family: str
    descending: bool = False  # its axis drawn from the lower bound at the top (the tutorial puts the
    # fastest impacts, the most negative y-velocities, on top)


# The measures a search can use (--measures picks 1 to 3, in order, of its task's family). Each
# is computed per terrain and averaged over the run's terrains. The ranges hold what the policies
# of real runs reach: an elite on an edge cell of a 50-cell axis is rare (docs/terrains.md,
# docs/environments.md). To add one, add a row.
MEASURES: dict[str, Measure] = {
    # The tutorial's two: where and how fast the lander comes down (without a touchdown: its last
    # x-position and its fastest descent).
    "impact_x": Measure("Impact x-position", (-1.0, 1.0), "x", lambda f: f.impact[0], "lander"),
    "impact_y_velocity": Measure(
        "Impact y-velocity", (-3.0, 0.0), "v", descending=True, family="lander",
        of=lambda f: f.min_y_velocity if f.touchdown is None else f.touchdown[3]),
    "impact_x_velocity": Measure("Impact x-velocity", (-3.0, 3.0), "vx", lambda f: f.impact[2], "lander"),
    # Angles are not wrapped: a lander that tumbles goes past pi, into the edge cells.
    "impact_angle": Measure("Impact angle (rad)", (-math.pi, math.pi), "angle", lambda f: f.impact[4],
                            "lander"),
    # Fuel in main-engine firings at full power: a side firing costs a tenth of one, as in the
    # env's reward (with throttles: each firing weighed by its power).
    "fuel": Measure("Fuel burnt (main-engine firings)", (0.0, 600.0), "fuel",
                    lambda f: f.firings[MAIN] + 0.1 * (f.firings[LEFT] + f.firings[RIGHT]), "lander"),
    # A lander falling freely touches down after ~51 steps; one that hovers flies all 1000.
    "flight_time": Measure("Steps to touchdown", (50.0, 1000.0), "steps",
                           lambda f: f.steps if f.touchdown_step is None else f.touchdown_step, "lander"),
    "max_tilt": Measure("Largest tilt before touchdown (rad)", (0.0, math.pi), "tilt",
                        lambda f: f.max_tilt, "lander"),
    # The QD literature's walker measures (Cully et al. 2015's duty factor): the share of steps
    # each foot touches the ground.
    "foot1_contact": Measure("Share of steps foot 1 touches the ground", (0.0, 1.0), "foot1",
                             lambda w: w.share(0), "walker"),
    "foot2_contact": Measure("Share of steps foot 2 touches the ground", (0.0, 1.0), "foot2",
                             lambda w: w.share(1), "walker"),
    # How far, and how fast: the course is ~88 m from the start to its end.
    "distance": Measure("Distance walked (m)", (-10.0, 90.0), "dist", lambda w: w.distance, "walker"),
    "speed": Measure("Mean speed (m/s)", (-1.0, 3.0), "speed",
                     lambda w: w.distance * 50 / max(w.steps, 1), "walker"),  # 50 steps a second
    "hull_angle": Measure("Mean hull angle (rad)", (-1.0, 1.0), "hull",
                          lambda w: w.hull_angles / max(w.steps, 1), "walker"),
}
TUTORIAL_MEASURES = ENVIRONMENTS[DEFAULT_ENV].measures  # what old run folders used


def family_measures(family: str) -> list[str]:
    return [name for name, measure in MEASURES.items() if measure.family == family]


def fly(solution: np.ndarray, env_seed: int, env: gym.Env, trajectory: list | None = None,
        on_step: Callable[[Any, np.ndarray], None] | None = None, env_name: str = DEFAULT_ENV) -> Any:
    """Fly the task's linear policy for one episode on the terrain of `env_seed`; its summary.

    With a `trajectory` list, each step's position is appended to it (the lander's normalised
    (x, y), the walker's hull in metres); `on_step` is called with each step's action and
    observation (the explorer records poses with it).
    """
    task = ENVIRONMENTS[env_name]
    if trajectory is not None:
        if task.family == "walker":
            def on_step(action: Any, obs: np.ndarray) -> None:
                position = env.unwrapped.hull.position  # the hull of this episode (reset makes one)
                trajectory.append((float(position.x), float(position.y)))
        else:
            def on_step(action: Any, obs: np.ndarray) -> None:
                trajectory.append((float(obs[0]), float(obs[1])))
    return task.fly(solution, env_seed, env, task, on_step)


def rollout(solution: np.ndarray, env_seed: int, env: gym.Env, measures: tuple[str, ...] | None = None,
            trajectory: list | None = None, env_name: str = DEFAULT_ENV) -> tuple[float, ...]:
    """(objective, *measures) of one episode (default: the task's measures): the objective is the
    episode's total reward."""
    flight = fly(solution, env_seed, env, trajectory, env_name=env_name)
    measures = ENVIRONMENTS[env_name].measures if measures is None else measures
    return (float(flight.reward), *(float(MEASURES[name].of(flight)) for name in measures))

# ================================================================================================
# The algorithm: an archive of elites, emitters that propose solutions, a scheduler tying them
# ================================================================================================

# Every size a user gives is bounded before anything is allocated or written (check_sizes and the
# flags' checks): each bound is far past what QD papers run (1,000s of solutions per iteration,
# 10,000s of iterations), and what it lets a run hold at once stays within a laptop's memory.
MAX_CELLS = 1_000_000  # --grid ** len(--measures): each cell keeps one solution
MAX_ITERATIONS = 1_000_000  # the checkpoint keeps a row of metrics (~1 KB in memory) per iteration
MAX_EMITTERS = 10_000  # each keeps its own CMA-ES state (a weights x weights covariance)
MAX_SOLUTIONS = 100_000  # asked per iteration (n_emitters * batch_size): 173 MB of 216 weights
MAX_ROLLOUTS = 10_000_000  # solutions x terrains flown in one batch: ~32 bytes of results each
MAX_WORKERS = 1_024  # worker processes of a local cluster (and what memory holds: check_local_memory)

# One row per algorithm, in the spirit of pyribs' examples/sphere.py: the archive's extra kwargs,
# whether a separate result archive keeps the elites, and the emitter class with its kwargs, each
# a small function of the run's config. All rows share the grid, the seeds, x0 and the batch
# size, so every algorithm asks n_emitters * batch_size solutions per iteration. (A flag only some
# algorithms use says so in its entry of SEARCH_FLAGS: an experiment sweeps it for them alone, and
# labels name it for them alone.)
# - cma_me: the tutorial's CMA-ME (EvolutionStrategyEmitter, two-stage improvement ranker).
# - cma_mae: pyribs' CMA-MAE tutorial and sphere.py's "cma_mae" row: a soft archive with
#   learning_rate (--learning_rate; 0.01 there, 0.5 here: docs/algorithms.md) and threshold_min (0
#   there for objectives in [0, 100]; here the task's QD offset, below almost every episode's
#   return), a plain result archive of the same grid that keeps the best solutions (metrics,
#   heatmaps and archive.pkl come from it), and emitters with the "imp" ranker, "mu" selection
#   and "basic" restarts.
# - map_elites: sphere.py's "map_elites" row: GaussianEmitters that mutate random elites with a
#   fixed sigma (--sigma0). (Lunar Lander's policy argmax(W @ obs) ignores W's scale, so there
#   only sigma relative to the elites' weights matters; tanh(W @ obs) does not ignore it.)
ALGORITHMS: dict[str, dict[str, Any]] = {
    "cma_me": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config["sigma0"], "ranker": "2imp"},
    },
    "cma_mae": {
        "archive": lambda config: {"learning_rate": config["learning_rate"],
                                   "threshold_min": task_of(config).qd_offset},
        "result_archive": True,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config["sigma0"], "ranker": "imp",
                                          "selection_rule": "mu", "restart_rule": "basic"},
    },
    "map_elites": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "GaussianEmitter",
        "emitter_kwargs": lambda config: {"sigma": config["sigma0"]},
    },
}


def own_flags(algorithm: str) -> tuple[str, ...]:
    """The flags only some algorithms use that this one does (cma_mae: learning_rate)."""
    return tuple(name for name, flag in SEARCH_FLAGS.items() if algorithm in flag.only_for)


def ignores(algorithm: str, flag: str) -> bool:
    """Whether the algorithm ignores the flag (another algorithm's own, like cma_mae's rate)."""
    only_for = SEARCH_FLAGS[flag].only_for if flag in SEARCH_FLAGS else ()
    return bool(only_for) and algorithm not in only_for


def task_of(config: dict[str, Any]) -> Environment:
    """The run's row of ENVIRONMENTS (run folders from before --env flew Lunar Lander)."""
    return ENVIRONMENTS[config.get("env", DEFAULT_ENV)]


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent seeds for the archive and each emitter, all fixed by the one run seed."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(count)]


def archive_grid(config: dict[str, Any]) -> dict[str, Any]:
    """The archive's cells: --grid of them along each of the run's --measures, over its range."""
    measures = config["measures"]
    task = task_of(config)
    return dict(solution_dim=task.solution_dim, dims=(config["grid"],) * len(measures),
                ranges=[MEASURES[name].range for name in measures], qd_score_offset=task.qd_offset)


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
            x0=np.zeros(task_of(config).solution_dim) if x0 is None else x0,
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

_WORKER_ENVS: dict[tuple[str, bool], gym.Env] = {}  # per worker process, reused across tasks


def worker_env(env_name: str, fast: bool = True) -> gym.Env:
    """This process's environment of the task: reset(seed) gives the same episode bit for bit as
    a fresh environment, without paying for gym.make each time."""
    key = (env_name, fast)
    if key not in _WORKER_ENVS:
        _WORKER_ENVS[key] = make_env(fast, env_name=env_name)
    return _WORKER_ENVS[key]


def fly_chunk(solutions: np.ndarray, env_seeds: np.ndarray, measures: tuple[str, ...],
              fast_env: bool = True, env_name: str = DEFAULT_ENV) -> np.ndarray:
    """Runs on a worker: fly solutions[i] on terrain env_seeds[i]; rows of (objective, *measures).

    A chunk of rollouts per task (not one task per rollout) keeps the scheduler's per-task cost
    small next to the rollouts, and the environment is kept between tasks (worker_env).
    """
    env = worker_env(env_name, fast_env)
    rows = [rollout(solution, int(seed), env, measures, env_name=env_name)
            for solution, seed in zip(solutions, env_seeds)]
    return np.array(rows).reshape(-1, 1 + len(measures))


# Two chunks per worker even out lander episodes (60 to 1,000 steps) across workers as well as
# more do (measured: 1, 2, 3, 4, 8), while each task costs the main process ~0.6 ms of
# scheduling. Walker episodes (60 to 1,600 steps) too: 1, 4 and 8 chunks per worker took 0.96,
# 0.95 and 1.01 of the time of 2, within this machine's noise (benchmarks/bench_chunking.py,
# 6 rounds of 150 policies on 2 workers, 2026-11-24).
CHUNKS_PER_WORKER = 2
MIN_CHUNK = 4  # rollouts per task at least, on big clusters: a task costs ~0.6 ms to schedule
# Rollouts per task at most, so that big batches (evaluate's, say) report progress as they go: a
# few seconds of lander episodes (<= 1,000 steps of ~27 us), up to minutes of walker ones.
MAX_CHUNK = 1000


def submit_flights(client, solutions: np.ndarray, env_seeds: list[int], measures: tuple[str, ...],
                   fast_env: bool = True, sharing: int = 1, threads: int | None = None,
                   env_name: str = DEFAULT_ENV) -> list:
    """Send every solution to be flown on every terrain; the futures of the chunks, in order.

    The work is the (solution, terrain) pairs, split into chunks of about equal count whatever
    the number of terrains, so the workers stay evenly loaded. A batch alone on the cluster is
    split in CHUNKS_PER_WORKER chunks per worker; when `sharing` runs keep the workers busy
    together, each batch needs only its share of that, and fewer tasks cost the scheduler less.
    The chunks go in one message (client.map); tasks of a dead worker are retried. `threads`, the
    cluster's worker threads if the caller knows them, saves asking the scheduler (a round trip).
    """
    workers = max(1, threads if threads is not None else sum(client.nthreads().values()))
    pairs = len(solutions) * len(env_seeds)
    wanted = max(-(-CHUNKS_PER_WORKER * workers // max(1, sharing)), -(-pairs // MAX_CHUNK))
    chunks = np.array_split(np.arange(pairs), min(wanted, max(1, pairs // MIN_CHUNK)))
    seeds = np.tile(np.asarray(env_seeds, dtype=np.int64), len(solutions))
    return client.map(fly_chunk, [solutions[chunk // len(env_seeds)] for chunk in chunks],
                      [seeds[chunk] for chunk in chunks], [tuple(measures)] * len(chunks),
                      [fast_env] * len(chunks), [env_name] * len(chunks), pure=False, retries=3)


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
                             config["fast_env"], env_name=config["env"])
    return averaged(per_terrain(client.gather(futures), config["env_seed"]))


# ================================================================================================
# The run: ask -> evaluate -> tell, with metrics, checkpoints and outputs
# ================================================================================================

CHECKPOINT_FORMAT = "lunar_lander.checkpoint/1"


# A row of metrics.json: each field and what it holds (None: no elite yet).
METRIC_FIELDS: dict[str, tuple[type, ...]] = {
    "iteration": (int,), "evaluations": (int,), "coverage": (float,), "num_elites": (int,),
    "qd_score": (float,), "best_objective": (float, type(None)),
    "mean_objective": (float, type(None)), "elapsed_s": (float,),
}


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


def check_metrics(rows: Any, path: Path) -> list[dict]:
    """metrics.json's rows (at least one), each with every field of METRIC_FIELDS holding a value
    of its type (an int counts as a float; NaN and infinities do not), or a UsageError that names
    the first that does not."""
    if not isinstance(rows, list) or not rows:
        raise UsageError(f"{path}: no metrics (a list of one row per iteration)")
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise UsageError(f"{path}: row {i} is a {type(row).__name__}, not a row of metrics")
        for field, kinds in METRIC_FIELDS.items():
            if field not in row and field != "elapsed_s":  # older runs recorded no timings
                raise UsageError(f"{path}: row {i} has no {field}")
            if field in row and not holds(row[field], kinds):
                raise UsageError(f"{path}: row {i} has {field} = {shown(row[field])}, not "
                                 f"{' or '.join(kind.__name__ for kind in kinds)}")
    return rows


def holds(value: Any, kinds: tuple[type, ...]) -> bool:
    """Whether a JSON value is one of `kinds`: a whole number counts as a float; NaN, infinities
    and booleans count as nothing."""
    if value is None or isinstance(value, bool):
        return value is None and type(None) in kinds
    if float in kinds:
        return isinstance(value, (int, float)) and math.isfinite(value)
    return isinstance(value, int)


def load_metrics(run_dir: Path) -> list[dict]:
    """A run folder's metrics.json, checked (check_metrics)."""
    return check_metrics(read_run_json(run_dir, "metrics.json"), run_dir / "metrics.json")


def load_run_config(run_dir: Path) -> dict:
    """A run folder's config.json, every flag valid (check_run_config)."""
    recorded = read_run_json(run_dir, "config.json")  # its own error for a missing or bad file
    try:
        return check_run_config(recorded)
    except UsageError as error:
        raise UsageError(f"{run_dir / 'config.json'}: not a usable run config ({error})") from None


def load_checked_config(run_dir: Path) -> dict:
    """What the results commands read of a run: its config.json, checked, and checked against its
    checkpoint where it has one (an edit to another task of the same shape would go unseen by
    the archive's own checks)."""
    config = load_run_config(run_dir)
    if (run_dir / "checkpoint.pkl").is_file():
        check_same_config(config, load_checkpoint(run_dir / "checkpoint.pkl")["config"], run_dir)
    return config


# Flags that config.json may hold apart from its checkpoint: resume writes a larger --iterations
# into config.json before the run's next checkpoint records it.
MAY_DIFFER = ("iterations",)


def load_run_state(run_dir: Path) -> tuple[dict, dict | None]:
    """A run folder's config and checkpoint, which must agree (a hand edit of config.json is
    refused, not silently ignored). A run killed before its first checkpoint (while its cluster
    started) has only config.json: its checkpoint is None, and resume starts it afresh from that
    config, which records the seed, so it ends as the uninterrupted run would."""
    path = run_dir / "checkpoint.pkl"
    if path.is_file() or not (run_dir / "config.json").is_file():
        checkpoint = load_checkpoint(path)
        if (run_dir / "config.json").is_file():
            check_same_config(load_run_config(run_dir), checkpoint["config"], run_dir)
        return checkpoint["config"], checkpoint
    return load_run_config(run_dir), None


def check_same_config(recorded: dict, checkpointed: dict, run_dir: Path) -> None:
    """config.json must say what the checkpoint ran with: a run goes on as it started."""
    for name in SEARCH_FLAGS:
        if name not in MAY_DIFFER and name not in CLUSTER_FLAGS and recorded[name] != checkpointed[name]:
            raise UsageError(
                f"{run_dir / 'config.json'} says --{name} {shown(recorded[name])} but the run's "
                f"checkpoint ran with {shown(checkpointed[name])}: a run goes on with the settings "
                f"it started with; undo the edit, or start a new run with the flags you want")


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
    if shape[0] != expected[0]:
        raise UsageError(f"{path}: its solutions have {shape[0]} weights, but --env "
                         f"{config['env']}'s policy has {expected[0]}: an archive of another task's run")
    if shape != expected:
        raise UsageError(f"{path}: archive of another shape (solution size, grid, lower and upper "
                         f"bounds {shape}; the run's --measures {','.join(config['measures'])} and "
                         f"--grid {config['grid']} need {expected})")


def check_sizes(config: dict) -> None:
    """The sizes that flags make together are bounded too: the archive's cells, the solutions
    asked per iteration and the rollouts they are flown in."""
    cells, solutions = config["grid"] ** len(config["measures"]), config["n_emitters"] * config["batch_size"]
    if cells > MAX_CELLS:
        raise UsageError(f"--grid {config['grid']} with {len(config['measures'])} measures makes "
                         f"{cells:,} cells; at most {MAX_CELLS:,}")
    if solutions > MAX_SOLUTIONS:
        raise UsageError(f"--n_emitters {config['n_emitters']} x --batch_size {config['batch_size']} "
                         f"asks {solutions:,} solutions per iteration; at most {MAX_SOLUTIONS:,}")
    check_rollouts(solutions, len(config["env_seed"]), "per iteration")


def check_rollouts(solutions: int, terrains: int, when: str) -> None:
    """At most MAX_ROLLOUTS rollouts in one batch: their results are held at once."""
    if solutions * terrains > MAX_ROLLOUTS:
        raise UsageError(f"{solutions:,} solutions on {terrains:,} terrain(s) make "
                         f"{solutions * terrains:,} rollouts {when}; at most {MAX_ROLLOUTS:,}")


def load_archive(path: Path, config: dict):
    """A saved archive, checked against the config of the run that uses it."""
    archive = read_pickle(path, "archive pickle")
    check_archive(archive, path, config)
    if len(archive) == 0:
        raise UsageError(f"{path}: the archive is empty; nothing to start from")
    return archive


def check_run_config(config: Any) -> dict:
    """A run's recorded config, every flag valid (a UsageError says which is not); a config from
    before a flag existed ran with what that flag now sets it to (its entry's `before`, or its
    default)."""
    if not isinstance(config, dict):
        raise UsageError(f"holds a {type(config).__name__}, not the flags of a run")
    config = {**search_defaults(), **before_the_flags(), **config}
    for name, flag in SEARCH_FLAGS.items():
        if config[name] is None and flag.default is not None:  # a check passes None: refuse it here
            raise UsageError(f"--{name} is null")
        if flag.check is None and not isinstance(config[name], (str, type(None))):
            raise UsageError(f"--{name} is {shown(config[name])}, not a path or an address")
    config.update(check_flags(SEARCH_FLAGS, {name: config[name] for name in SEARCH_FLAGS}))
    if not isinstance(config.get("resumed", []), list):
        raise UsageError(f"resumed is {shown(config['resumed'])}, not a list of resumptions")
    config = with_task(config)
    seed_number("seed", config["seed"])
    check_sizes(config)
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
    if metrics:
        check_metrics(metrics, path)
    if [row["iteration"] for row in metrics if row["iteration"] > 0] != list(range(1, iteration + 1)):
        raise UsageError(f"{path}: its metrics do not match its iteration {iteration}")
    check_archive(checkpoint["scheduler"].archive, path, checkpoint["config"])
    return checkpoint



def save_outputs(run_dir: Path, checkpoint: dict) -> None:
    """The run folder's files besides the checkpoint: metrics, archive, heatmaps, progress."""
    write_json(run_dir / "metrics.json", checkpoint["metrics"])
    archive = checkpoint["scheduler"].result_archive
    iteration = checkpoint["iteration"]
    write_pickle(run_dir / "archive.pkl", archive)
    table = archive.data(return_type="pandas")
    write_csv(run_dir / "archive.csv", table)
    title = f"{checkpoint['config']['algorithm']} after {iteration} iterations"
    snapshot = run_dir / "heatmaps" / f"heatmap_{iteration:05d}.png"
    save_heatmap(archive, [MEASURES[m] for m in checkpoint["config"]["measures"]], snapshot, title)
    atomic_write(run_dir / "heatmap.png", lambda f: f.write(snapshot.read_bytes()))
    save_progress_plot(checkpoint["metrics"], run_dir / "progress.png")


# ================================================================================================
# The commands: their flags, search and resume, and the command line
# ================================================================================================

# Each flag is declared once, here: its default, its --help line, its check, and its part in
# experiments (see flags.Flag). `takes` turns a table into a command's keyword arguments, so the
# signature, the docstring's Args and --help come from these entries.

CLUSTER_FLAGS: dict[str, Flag] = {  # every command that flies policies on a cluster
    "workers": Flag(2, "Number of Dask worker processes (one thread each) of the local cluster "
                       f"flying the rollouts (at most {MAX_WORKERS:,}, and what memory holds).",
                    whole_number_up_to(MAX_WORKERS), per_run=True),
    "scheduler_address": Flag(None, "Address of a running Dask scheduler (tcp://HOST:PORT) to "
                                    "evaluate on instead of starting a local cluster; --workers "
                                    "is then ignored.", per_run=True),
    "scheduler_file": Flag(None, "A Dask scheduler file (written by dask scheduler "
                                 "--scheduler-file, dask-mpi or dask-jobqueue's SLURMRunner): "
                                 "wait for it to appear, then join the scheduler it names; "
                                 "instead of --scheduler_address.", per_run=True),
    "scheduler_timeout": Flag(120, "Seconds to wait for --scheduler_file to appear; the "
                                   "scheduler must answer within this too (at most 20 s).",
                              positive_float, per_run=True),
    "worker_timeout": Flag(600, "Seconds to wait for the first worker of the cluster named by "
                                "--scheduler_address or --scheduler_file to join (it says it waits).",
                           positive_float, per_run=True),
}

SEARCH_FLAGS: dict[str, Flag] = {
    "iterations": Flag(300, f"Number of ask-evaluate-tell iterations (at most {MAX_ITERATIONS:,}).",
                       whole_number_up_to(MAX_ITERATIONS)),
    "workers": CLUSTER_FLAGS["workers"],
    "seed": Flag(None, "Seed of the archive and emitters; drawn and recorded in config.json if "
                       "omitted. The same seed gives the same archive whatever the number of "
                       "workers.", seed_number, per_run=True),
    "env": Flag(DEFAULT_ENV, "The Gymnasium task, a row of ENVIRONMENTS: " + ", ".join(ENVIRONMENTS)
                + " (docs/environments.md).", one_of(ENVIRONMENTS)),
    "env_seed": Flag(52, "The terrain(s) every policy is flown on: one seed (52), a range (0-4), a "
                         "list (3,5,8) or both (0-4,10). With several terrains the objective is "
                         "the mean return over them, and each measure is its per-terrain values "
                         "averaged.", seed_list, label=1, text=True),
    "measures": Flag(None, "1 to 3 rows of the MEASURES table of the task's family, "
                           "comma-separated, as the archive's axes; default: the task's own. Lunar "
                           "Lander: " + ", ".join(family_measures("lander")) + " (the tutorial's "
                           "impact_x,impact_y_velocity by default); BipedalWalker: "
                           + ", ".join(family_measures("walker")) + " (foot1_contact,"
                           "foot2_contact by default).",
                     distinct_names(MEASURES, "measures", 3), label=2, text=True),
    "grid": Flag(50, "Archive cells along each measure.", positive_int, sweep=True, label=3),
    "algorithm": Flag("cma_me", "Which QD algorithm: cma_me (the tutorial's CMA-ME), cma_mae "
                                "(CMA-MAE) or map_elites (MAP-Elites with Gaussian mutation); "
                                "each asks n_emitters * batch_size solutions per iteration.",
                      one_of(ALGORITHMS), per_run=True),
    "n_emitters": Flag(5, f"Number of emitters (at most {MAX_EMITTERS:,}).",
                       whole_number_up_to(MAX_EMITTERS), sweep=True, label=4),
    "sigma0": Flag(1.0, "Initial step size of each emitter (CMA-ES sigma); map_elites: the fixed "
                        "sigma of its Gaussian mutation.", positive_float, sweep=True, label=6),
    "batch_size": Flag(30, f"Solutions each emitter proposes per iteration (n_emitters * "
                           f"batch_size: at most {MAX_SOLUTIONS:,}).", whole_number_up_to(MAX_SOLUTIONS),
                       sweep=True, label=5),
    "learning_rate": Flag(0.5, "cma_mae only: how fast a cell's threshold follows its "
                               "improvements, in (0, 1]. 0.5 did best of 0.01, 0.1 and 0.5 over "
                               "6 seeds of 300 iterations (docs/algorithms.md); pyribs' 0.01 is "
                               "for far longer runs; 1 makes the archive CMA-ME's.", fraction,
                          sweep=True, label=7, only_for=("cma_mae",), before=0.01),
    "log_every": Flag(25, "Log a line and refresh the run folder every this many iterations.",
                      positive_int),
    "outdir": Flag(None, "Run folder; default outputs/<timestamp>_seed<seed>. Must be new or "
                         "empty.", per_run=True),
    "scheduler_address": CLUSTER_FLAGS["scheduler_address"],
    "scheduler_file": CLUSTER_FLAGS["scheduler_file"],
    "scheduler_timeout": CLUSTER_FLAGS["scheduler_timeout"],
    "worker_timeout": CLUSTER_FLAGS["worker_timeout"],
    "from_archive": Flag(None, "Warm start: an archive.pkl of an earlier run whose elites are "
                               "re-evaluated in this run's setting to fill the archive first; the "
                               "emitters start from the best.", per_run=True),
    "fast_env": Flag(True, "Fly rollouts in the task's streamlined copy where it has one "
                           "(LunarLander-v3: bitwise identical results, about a third less time "
                           "per step); false uses gym.make's plain environment.", boolean),
}

# resume: a run goes on as it was started unless told otherwise.
RESUME_FLAGS: dict[str, Flag] = {
    "iterations": dataclasses.replace(
        SEARCH_FLAGS["iterations"], default=None, help="Total iterations to reach; default: those "
        "the run was started with. A larger number extends a finished run."),
    "workers": dataclasses.replace(CLUSTER_FLAGS["workers"], default=None, help=(
        CLUSTER_FLAGS["workers"].help + " Default: as the run was started.")),
    **{name: flag for name, flag in CLUSTER_FLAGS.items() if name != "workers"},
}

# Which elites a results command shows (video, trajectories), and on which terrain (explore too).
SELECTION_FLAGS: dict[str, Flag] = {
    "cells": Flag(None, 'Points in the run\'s measures "[(m1, m2), ...]": the elite of each '
                        "point's cell (archive.retrieve_single); for the tutorial's impact x and "
                        'impact y-velocity, e.g. "[(-0.4, -0.1), (0.6, -0.1), (0.0, -0.1)]".'),
    "best": Flag(False, "The elite with the highest objective.", boolean),
    "top": Flag(None, "The K elites with the highest objectives.", positive_int),
    "index": Flag(None, "Archive cell indices (the cell_index column of the elites command)."),
    "nearest": Flag(False, "For an empty cell, use the nearest occupied cell instead of "
                           "stopping.", boolean),
}
TERRAIN_FLAGS: dict[str, Flag] = {
    "env_seed": Flag(None, "The terrain to fly on, one of the run's; default: the run's first.",
                     seed_number),
}


def checked(name: str, value: Any) -> Any:
    """A value checked as the flag `name` of SEARCH_FLAGS checks it (None included: refused)."""
    return SEARCH_FLAGS[name].check(name, value)


def with_task(config: dict[str, Any]) -> dict[str, Any]:
    """The config with its task's default measures if it names none, and its measures checked
    against its task (a walker has no impact x)."""
    env = config.get("env", DEFAULT_ENV)
    task = ENVIRONMENTS[env]
    measures = list(task.measures if config.get("measures") is None else config["measures"])
    if wrong := [name for name in measures if MEASURES[name].family != task.family]:
        raise UsageError(f"--measures {wrong[0]} is not a measure of --env {env}; its measures: "
                         + ", ".join(family_measures(task.family)))
    return {**config, "env": env, "measures": measures}


def search_defaults() -> dict[str, Any]:
    return {name: flag.default for name, flag in SEARCH_FLAGS.items()}


def before_the_flags() -> dict[str, Any]:
    """What runs recorded before a flag existed ran with, where that is not today's default."""
    return {name: flag.before for name, flag in SEARCH_FLAGS.items() if flag.before is not None}


@takes(SEARCH_FLAGS)
def search(**flags: Any) -> None:
    """Search a task (--env; Lunar Lander's landings by default) with a QD algorithm and write a
    run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl, archive.pkl, archive.csv, metrics.json, heatmap.png, heatmaps/, progress.png,
    config.json and run.log. Other commands (each with --help): resume, experiment, video, elites,
    trajectories, evaluate, explore, compare.
    """
    flags = with_task(check_flags(SEARCH_FLAGS, flags))
    check_spaces(flags["env"])
    check_sizes(flags)
    from_archive = flags["from_archive"]
    seed_archive = load_archive(Path(from_archive), flags) if from_archive else None
    address = scheduler_of(flags)
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    with new_folder(flags["outdir"], f"seed{flags['seed']}") as run_dir:
        config = {**flags, "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
                  "command": sys.argv, "versions": library_versions()}
        if from_archive:
            config["from_archive"] = str(Path(from_archive).resolve())
        write_json(run_dir / "config.json", config)
        with run_session(run_dir, config["workers"], address) as (client, log, saver):
            run = Run.start(run_dir, config, client, log, seed_archive)
            run_loop(run, client, config["iterations"], log, saver)
    print(where_to_look(run_dir))


@takes(RESUME_FLAGS)
def resume(run_dir: str, **flags: Any) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped; or,
    for an experiment folder, every unfinished run of the experiment.

    Args:
        run_dir: A run folder (or an experiment folder) written by this script.
    """
    path, iterations, workers = Path(run_dir), flags["iterations"], flags["workers"]
    if (path / "experiment.json").is_file():
        from experiments import resume_experiment

        return resume_experiment(path, iterations, workers, flags)
    load_run_state(path)  # refuse a bad folder before anything is written in it
    scheduler_address = scheduler_of(flags)
    with folder_lock(path):
        config, checkpoint = load_run_state(path)  # as the last writer left it
        iterations = checked("iterations", config["iterations"] if iterations is None else iterations)
        workers = checked("workers", config["workers"] if workers is None else workers)
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
    print(where_to_look(path))


def where_to_look(run_dir: Path) -> str:
    """The end of a finished search: where its results are, and the commands that show them."""
    folder = shlex.quote(str(run_dir))
    return (f"Results in {run_dir}: heatmap.png, progress.png, metrics.json, archive.csv. Look at "
            f"them with:\n  python lunar_lander.py explore {folder}      # a page to browse the "
            f"archive and watch any elite\n  python lunar_lander.py video {folder} --best   # an "
            f"mp4 of the best elite")


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
            elsewhere = " --scheduler_file NEW_FILE" if isinstance(error, SchedulerLost) else ""
            raise RunError(f"{fault_text(error)}; {checkpoint_state(run_dir, elsewhere)}") from None


def checkpoint_state(run_dir: Path, flags: str = "") -> str:
    """What a stopped or failed run folder holds, and the command that continues it (with
    `flags`, such as a new cluster's)."""
    try:
        held = f"its checkpoint holds iteration {read_pickle(run_dir / 'checkpoint.pkl', '')['iteration']}"
    except (UsageError, KeyError, TypeError):
        held = "it holds no checkpoint yet (resume starts the run from its config.json)"
    return f"{held}; continue with: python lunar_lander.py resume {shlex.quote(str(run_dir))}{flags}"


# The commands, each the module and function that implement it: a command's module is imported
# only when it is run (the siblings import this module, never the other way at load time).
COMMANDS: dict[str, tuple[str, str]] = {
    "search": ("lunar_lander", "search"), "resume": ("lunar_lander", "resume"),
    "experiment": ("experiments", "experiment"), "video": ("results", "video"),
    "elites": ("results", "elites"), "trajectories": ("results", "trajectories"),
    "evaluate": ("results", "evaluate_robustness"), "explore": ("results", "explore"),
    "compare": ("comparison", "compare"),
}


def command(name: str) -> Callable:
    """The function of a command of COMMANDS."""
    module, function = COMMANDS[name]
    return getattr(importlib.import_module(module), function)


def known_flags(function: Callable) -> list[str]:
    """The flags a command takes: its signature's, and for experiment those of search it passes
    on to every run."""
    import inspect

    parameters = inspect.signature(function).parameters
    known = [name for name, p in parameters.items() if p.kind is not p.VAR_KEYWORD]
    if any(p.kind is p.VAR_KEYWORD for p in parameters.values()):  # experiment's **search_flags
        known += [name for name, flag in SEARCH_FLAGS.items() if not flag.per_run and name not in known]
    return known


def text_flags(function: Callable) -> set[str]:
    """The flags of a command whose checks read the text as typed (Flag.text)."""
    entries = {**{name: SEARCH_FLAGS[name] for name in known_flags(function) if name in SEARCH_FLAGS},
               **getattr(function, "flag_table", {})}
    return {name for name, flag in entries.items() if flag.text}


def reject_unknown_flags(function: Callable, args: list[str]) -> None:
    """Fire would print a page of usage for a mistyped flag; one line naming it is clearer. A
    flag given twice is refused too."""
    known, given = known_flags(function), set()
    for arg in args:
        if arg == "--":
            return
        if arg.startswith("--") and arg != "--help":
            name = arg[2:].split("=", 1)[0].replace("-", "_")
            if name not in known:
                raise UsageError(f"unknown flag --{name}; valid flags: "
                                 + ", ".join(f"--{flag}" for flag in known))
            if name in given:  # Fire would silently keep the last
                raise UsageError(f"--{name} is given twice; give each flag once")
            given.add(name)


def main(argv: list[str]) -> int:
    import fire

    name = argv[0] if argv and not argv[0].startswith("-") else "search"
    args = argv[1:] if argv and not argv[0].startswith("-") else argv
    STOP.install()
    try:
        if name not in COMMANDS:
            raise UsageError(f"unknown command {shown(name)}; commands: {', '.join(COMMANDS)}")
        function = command(name)
        reject_unknown_flags(function, args)
        if "--help" in args and "--" not in args:  # else a command taking **flags reads it as one
            args = [arg for arg in args if arg != "--help"] + ["--", "--help"]
        args = as_typed(args, text_flags(function))
        fire.Fire(function, command=args, name="lunar_lander.py" if name == "search" else name)
    except UsageError as error:
        print(f"error: {one_line(str(error))}", file=sys.stderr)
        return 2
    except (RunError, OSError) as error:  # OSError: any fault not already described better
        print(f"error: {one_line(fault_text(error))}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
        return 130
    return 0


def run_as_script() -> None:
    """`python lunar_lander.py ...`: main, then a quick exit (see exit_now)."""
    try:
        exit_now(main(sys.argv[1:]))
    except SystemExit as done:  # fire's --help and its own usage messages
        exit_now(done.code)


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
