"""qdsearch.tasks: the tasks a search can fly. This module is the layer's registry: every family
module's rows gathered into the tables --env and --measures pick from.

The layer's modules, imports going down the list only:
- family: what a task family declares (`Family`, `Environment` with its env's spaces, `Measure`),
  `require_drawing`;
- fast_lander: the streamlined Lunar Lander (bitwise gym.make's);
- lander, walker, locomotion: a module per task family (locomotion: MuJoCo's robots, a family
  each): its rows, its episode, how it is drawn;
- functions: the benchmark functions (sphere, Rastrigin, the planar arm): points, not episodes;
- transitions: an episode's steps kept as rows, for the learning rows' replay buffer;
- __init__: this registry;
- policies: the policies a solution makes (POLICIES: linear, mlp; `Policy`), and one episode of
  a solution flown as one, on any task of the registry (`fly`, `rollout`).

A family lives in a module of its own (lander.py, walker.py, locomotion.py, functions.py; family.py says what
one declares). To add one, write its module and name it in FAMILY_MODULES: its families, tasks
and measures are gathered from it (docs/extending.md lists every step).

Map:
- the registration: FAMILY_MODULES, `register_family` (a module's rows into the tables, checked);
- the tables: FAMILIES, ENVIRONMENTS (--env), MEASURES (--measures), DEFAULT_ENV,
  TUTORIAL_MEASURES; `family_measures`;
- `TaskConfig`: what the layer reads of a run's settings;
- the episode's rules: `Episode` (--episode_length, --terminate_when_unhealthy; `episode_of` a
  config's), `check_episode`; `returns_of` (a run's range of objectives: family.Returns);
- the resets: RESETS (--reset), `reset_seeds` (each solution's episodes' reset seeds);
- the environment: `make_env` (`plain_env`: gym.make's), `check_spaces` (a policy can serve the
  env's spaces); `renderer_missing` (family.py's, for the video command);
- a benchmark function's points (functions.py): `dim_of` (a run's --dim), `shape_of` (a run's
  policy shape, any task), `measure_bounds` (a run's measures' ranges, any task),
  `scored_here` (a function's run needs no cluster), `evaluate_points` (a batch scored at
  once, in the caller's process), `has_gradients` and `point_gradients` (their exact Jacobians).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib
import inspect
import struct
import warnings
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

from qdsearch.base.flags import UsageError, named
from qdsearch.tasks.family import Environment, Family, Measure, Returns
from qdsearch.tasks.family import renderer_missing as renderer_missing  # results.py's video imports it here

# The family modules, by import name: the one place a family is registered. Each declares its
# ENVIRONMENTS and MEASURES rows (family.py); a module outside the package must be importable
# wherever the search runs (its driver, its Dask workers and saver processes).
FAMILY_MODULES = ("qdsearch.tasks.lander", "qdsearch.tasks.walker", "qdsearch.tasks.locomotion",
                  "qdsearch.tasks.functions")

# The tables, gathered from FAMILY_MODULES in their order (and each module's rows in theirs).
FAMILIES: list[Family] = []  # each in the order its module's rows first name it
ENVIRONMENTS: dict[str, Environment] = {}  # the tasks (--env)
MEASURES: dict[str, Measure] = {}  # the measures (--measures picks 1 to 3 of its task's family)


def register_family(module_name: str) -> None:
    """Gather a family module's ENVIRONMENTS and MEASURES rows, and the families they name, into
    the tables. By name, so that a process can be told to (Dask's client.run on the workers).
    A module whose rows are all there already changes nothing; a row named as another module's,
    or a task whose default measures are not its family's, is refused at once."""
    module = importlib.import_module(module_name)
    tasks, measures = module.ENVIRONMENTS, module.MEASURES
    if all(ENVIRONMENTS.get(name) is row for name, row in tasks.items()) and all(
            MEASURES.get(name) is row for name, row in measures.items()):
        return
    if taken := sorted((tasks.keys() & ENVIRONMENTS.keys()) | (measures.keys() & MEASURES.keys())):
        raise ValueError(f"{module_name}: {', '.join(taken)} already named by another family module")
    known = {**MEASURES, **measures}
    for name, task in tasks.items():
        if wrong := [m for m in task.measures if m not in known or task.family not in known[m].families]:
            raise ValueError(f"{module_name}: {named('env')} {name}'s default measures {', '.join(wrong)} "
                             f"are not measures of its family {task.family.name}")
    ENVIRONMENTS.update(tasks)
    MEASURES.update(measures)
    declared = [task.family for task in tasks.values()] + [f for m in measures.values() for f in m.families]
    FAMILIES.extend(dict.fromkeys(family for family in declared if family not in FAMILIES))


for _module in FAMILY_MODULES:
    register_family(_module)

DEFAULT_ENV = "LunarLander-v3"  # the tutorial's, and what run folders from before --env flew
TUTORIAL_MEASURES = ENVIRONMENTS[DEFAULT_ENV].measures  # what old run folders used


def family_measures(family: Family) -> list[str]:
    return [name for name, measure in MEASURES.items() if family in measure.families]


class TaskConfig(Protocol):
    """What this layer reads of a run's settings (the config layer's RunConfig is one): its task,
    measures and size, its env seeds and resets, and its episodes' rules and offset."""

    env: str
    dim: int | None
    measures: list[str]
    env_seed: list[int]
    seed: int
    reset: str
    episode_length: int | None
    terminate_when_unhealthy: bool | None
    qd_offset: float | None


@dataclasses.dataclass(frozen=True)
class Episode:
    """The rules of a run's episodes where they are not the task's own (None: the task's): how many
    steps at most (gym.make's max_episode_steps), and whether a robot that falls (MuJoCo's
    "unhealthy" state) ends its episode."""

    length: int | None = None
    terminate_when_unhealthy: bool | None = None

    def kwargs(self) -> dict[str, Any]:
        """gym.make's keyword arguments for these rules."""
        return {**({} if self.length is None else {"max_episode_steps": self.length}),
                **({} if self.terminate_when_unhealthy is None
                   else {"terminate_when_unhealthy": self.terminate_when_unhealthy})}


TASKS_OWN = Episode()


def episode_of(config: TaskConfig) -> Episode:
    """A run's episode rules, from its config (a RunConfig); runs from before the flags flew the
    task's own (None: the task's)."""
    return Episode(config.episode_length, config.terminate_when_unhealthy)


def returns_of(config: TaskConfig) -> Returns:
    """A run's range of objectives (its QD offset as recorded, the rest for its episode's length)."""
    return ENVIRONMENTS[config.env].returns(episode_of(config).length, config.qd_offset)


def fixed_resets(solutions: np.ndarray, env_seeds: list[int], run_seed: int) -> np.ndarray:
    """--reset fixed: every solution flies from the same resets, its --env_seed ones."""
    return np.tile(np.asarray(env_seeds, dtype=np.int64), (len(solutions), 1))


def own_resets(solutions: np.ndarray, env_seeds: list[int], run_seed: int) -> np.ndarray:
    """--reset each: every evaluation its own reset seed per env seed, a hash of the run's seed,
    the env seed and the solution's weights. A fresh reset for each solution flown (an ES
    sample, a mutant), yet the same on any worker, after a resume, and when an elite is flown
    again by the results commands: its reset is known from the elite alone."""
    rows = np.ascontiguousarray(solutions, dtype=np.float64).reshape(len(solutions), -1)
    return np.array([[int.from_bytes(hashlib.blake2b(
        row.tobytes(), digest_size=4, key=struct.pack("<QQ", run_seed, seed)).digest(), "little")
        for seed in env_seeds] for row in rows], dtype=np.int64).reshape(len(rows), len(env_seeds))


# --reset: how each solution's episodes are reset, as (solutions, env seeds, run seed) -> the
# reset seeds, a row per solution and a column per env seed.
RESETS = {"fixed": fixed_resets, "each": own_resets}


def reset_seeds(solutions: np.ndarray, config: TaskConfig, env_seeds: list[int] | None = None) -> np.ndarray:
    """The reset seeds of each solution's episodes in a run: a row per solution, a column per env
    seed (its --env_seed, or `env_seeds`; runs from before --reset flew fixed ones)."""
    seeds = list(config.env_seed) if env_seeds is None else env_seeds
    return RESETS[config.reset](solutions, seeds, config.seed)


def flown_seeds(solutions: np.ndarray, env_seed: int, config: TaskConfig) -> list[int]:
    """The reset each solution of a run flies from for its env seed `env_seed` (the results
    commands' one shown seed): the seed itself, or under --reset each each solution's own."""
    return [int(seed) for seed in reset_seeds(solutions, config, [env_seed])[:, 0]]


@functools.cache
def has_unhealthy_state(env_name: str) -> bool:
    """Whether the task's env takes terminate_when_unhealthy (MuJoCo's Hopper, Walker2d, Ant)."""
    if ENVIRONMENTS[env_name].function:
        return False
    entry = gym.spec(ENVIRONMENTS[env_name].gym_id).entry_point
    if isinstance(entry, str):
        module, _, name = entry.partition(":")
        entry = getattr(importlib.import_module(module), name)
    return "terminate_when_unhealthy" in inspect.signature(entry).parameters


def check_episode(env_name: str, episode: Episode) -> None:
    """Refuse rules the task can't follow: a fall that ends an episode needs a task that falls."""
    if episode.terminate_when_unhealthy is not None and not has_unhealthy_state(env_name):
        able = [name for name in ENVIRONMENTS if has_unhealthy_state(name)]
        raise UsageError(f"{named('terminate_when_unhealthy')}: {named('env')} {env_name} has no unhealthy "
                         f"state; the tasks that do: {', '.join(able)}")


def make_env(fast: bool = True, render_mode: str | None = None, *, env_name: str,
             episode: Episode = TASKS_OWN) -> gym.Env:
    """The environment rollouts fly in: the task's streamlined copy if it has one (fast_lander.py)
    and the episodes follow the task's own rules, or gym.make's plain one (needed to render, to
    change the rules, and the reference the copy is tested against)."""
    task = ENVIRONMENTS[env_name]
    if fast and render_mode is None and task.fast is not None and episode == TASKS_OWN:
        return task.fast()
    return plain_env(env_name, render_mode, episode)


def plain_env(env_name: str, render_mode: str | None = None, episode: Episode = TASKS_OWN) -> gym.Env:
    """gym.make's env of the task; a simulator that is not installed (MuJoCo), or frames its env
    can't render (a family's own env may draw nothing: the video command), is one line."""
    task = ENVIRONMENTS[env_name]
    with warnings.catch_warnings():  # Gymnasium's warning of frames the env can't render: refused below
        warnings.filterwarnings("ignore", ".*not in the possible render_modes")
        env = task.make(render_mode, env_name, **episode.kwargs())
    if render_mode is not None and render_mode not in env.metadata.get("render_modes", ()):
        env.close()
        raise UsageError(f"{named('env')} {env_name} cannot be drawn: {task.gym_id} renders no "
                         f"{render_mode} frames")
    return env


def check_spaces(env_name: str) -> None:
    """Refuse a row whose task the policies can't serve. Its shape is read from the env's
    spaces, so only their kinds can be wrong: the observation must be a vector (a 1-D box), the
    actions a choice among n (Discrete from 0: argmax) or a vector in [-1, 1] (a 1-D box: tanh).
    The env is made through `plain_env` first: a missing simulator is one line naming --env."""
    task = ENVIRONMENTS[env_name]
    if task.function:  # a point: no spaces
        return
    plain_env(env_name).close()
    obs, act = task.spaces

    def vector(space: gym.Space) -> bool:
        return isinstance(space, gym.spaces.Box) and len(space.shape) == 1

    choice = isinstance(act, gym.spaces.Discrete) and int(act.start) == 0
    box = vector(act) and bool(np.all(act.low >= -1.0)) and bool(np.all(act.high <= 1.0))
    if not (vector(obs) and (choice or box)):
        raise UsageError(f"{named('env')} {env_name}: the policies (an argmax or a tanh of their outputs) "
                         f"can't serve {task.gym_id}'s observations {obs} and actions {act}")


def dim_of(config: TaskConfig) -> int | None:
    """A benchmark function's dimension in a run (its --dim, the task's own in a run that recorded
    none); None for a Gymnasium task."""
    task = ENVIRONMENTS[config.env]
    return (config.dim or task.dim) if task.function else None


def shape_of(config: TaskConfig) -> tuple[int, int]:
    """The policy's shape in a run, (actions, observations): the env's, or a function's (dim, 1)."""
    return ENVIRONMENTS[config.env].shape_for(dim_of(config))


def measure_bounds(config: TaskConfig) -> list[tuple[float, float]]:
    """The ranges of a run's measures (a benchmark function's grow with its dimension)."""
    return [MEASURES[name].bounds(dim_of(config)) for name in config.measures]


def scored_here(env_name: str) -> bool:
    """Whether a run of the task's solutions are scored in its driver's process, with no cluster:
    a benchmark function's batch costs less than a round trip to a worker."""
    return ENVIRONMENTS[env_name].function is not None


def evaluate_points(solutions: np.ndarray, measures: tuple[str, ...], *, env_name: str) -> np.ndarray:
    """Rows of (objective, *measures) of a benchmark function's points, the batch scored at once."""
    task = ENVIRONMENTS[env_name]
    points = np.asarray(solutions, dtype=np.float64).reshape(len(solutions), -1)
    summary = task.function(points)
    columns = [task.objective(summary), *(MEASURES[name].of(summary) for name in measures)]
    return np.column_stack([np.asarray(column, dtype=np.float64) for column in columns]).reshape(
        len(points), 1 + len(measures))


def has_gradients(env_name: str) -> bool:
    """Whether the task gives its values' exact gradients (a benchmark function's)."""
    return ENVIRONMENTS[env_name].gradients is not None


def point_gradients(solutions: np.ndarray, measures: tuple[str, ...], *, env_name: str) -> np.ndarray:
    """The Jacobians of a benchmark function's (objective, *measures) at each point: (points, 1 +
    measures, dim), the objective's gradient first (pyribs' tell_dqd's order)."""
    task = ENVIRONMENTS[env_name]
    points = np.asarray(solutions, dtype=np.float64).reshape(len(solutions), -1)
    summary = task.gradients(points)
    rows = [task.objective(summary), *(MEASURES[name].of(summary) for name in measures)]
    return np.stack([np.asarray(row, dtype=np.float64) for row in rows], axis=1)

