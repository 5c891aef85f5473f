"""The tasks a search can fly: every family's rows gathered into the tables --env and --measures
pick from, and one episode of any of them.

A family lives in a module of its own (lander.py, walker.py; family.py says what one declares).
To add one, write its module and add it to FAMILIES.

Map:
- the tables: FAMILIES, ENVIRONMENTS (--env), MEASURES (--measures), DEFAULT_ENV,
  TUTORIAL_MEASURES; `family_measures`;
- the environment: `make_env` (`plain_env`: gym.make's), `check_spaces`; `renderer_missing`
  (GL_PACKAGES: what MuJoCo's headless renderers need);
- an episode: `fly` (its summary, and its path if asked) and `rollout` (its objective and
  measures).
"""

from __future__ import annotations

import os
import sys
from typing import Any

import gymnasium as gym
import numpy as np

from qdsearch import lander, locomotion, walker
from qdsearch.family import Environment, Family, Measure, OnStep
from qdsearch.flags import UsageError, one_line
from qdsearch.run_files import RunError

FAMILIES: tuple[Family, ...] = (lander.LANDER, walker.WALKER, *locomotion.PLANAR, locomotion.ANT)
FAMILY_MODULES = (lander, walker, locomotion)  # each declares ENVIRONMENTS and MEASURES rows

# The tasks (--env) and the measures (--measures picks 1 to 3 of its task's family, in order).
ENVIRONMENTS: dict[str, Environment] = {
    name: row for module in FAMILY_MODULES for name, row in module.ENVIRONMENTS.items()}
MEASURES: dict[str, Measure] = {
    name: row for module in FAMILY_MODULES for name, row in module.MEASURES.items()}
DEFAULT_ENV = "LunarLander-v3"  # the tutorial's, and what run folders from before --env flew
TUTORIAL_MEASURES = ENVIRONMENTS[DEFAULT_ENV].measures  # what old run folders used


def family_measures(family: Family) -> list[str]:
    return [name for name, measure in MEASURES.items() if family in measure.families]


def make_env(fast: bool = True, render_mode: str | None = None, *, env_name: str) -> gym.Env:
    """The environment rollouts fly in: the task's streamlined copy if it has one (fast_lander.py),
    or gym.make's plain one (needed to render, and the reference the copy is tested against)."""
    task = ENVIRONMENTS[env_name]
    if fast and render_mode is None and task.fast is not None:
        return task.fast()
    return plain_env(env_name, render_mode)


def plain_env(env_name: str, render_mode: str | None = None) -> gym.Env:
    """gym.make's env of the task; a simulator that is not installed (MuJoCo) is one line."""
    task = ENVIRONMENTS[env_name]
    try:
        task.family.prepare()
        return gym.make(task.gym_id, render_mode=render_mode, **task.kwargs)
    except gym.error.DependencyNotInstalled as error:
        raise UsageError(f"--env {env_name} needs a package that is not installed "
                         f"({one_line(str(error))[:200]}): pip install -r requirements.txt") from None
    except (ImportError, AttributeError, RuntimeError) as error:
        if not os.environ.get("MUJOCO_GL") or "mujoco" in sys.modules:  # not MuJoCo's import failing
            raise
        raise renderer_missing(error) from None


# The Debian packages each of MuJoCo's headless renderers (MUJOCO_GL) needs.
GL_PACKAGES = {"egl": "libegl1 libegl-mesa0", "osmesa": "libosmesa6"}


def renderer_missing(error: BaseException) -> RunError:
    """One line for a MuJoCo renderer whose library the machine lacks, naming what to install."""
    gl = os.environ.get("MUJOCO_GL", "")
    needs = GL_PACKAGES.get(gl, " or ".join(GL_PACKAGES.values()))
    return RunError(f"MuJoCo cannot render headless here through MUJOCO_GL={gl} "
                    f"({one_line(str(error))[:200]}): apt-get install -y {needs}")


def check_spaces(env_name: str) -> None:
    """Refuse a row whose task the linear policy can't serve: its observation must be a vector of
    obs_dim numbers, its actions action_dim choices, or a box of action_dim numbers in [-1, 1]."""
    task = ENVIRONMENTS[env_name]
    env = plain_env(env_name)
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


def fly(solution: np.ndarray, env_seed: int, env: gym.Env, trajectory: list | None = None,
        on_step: OnStep | None = None, *, env_name: str) -> Any:
    """Fly the task's linear policy for one episode on the terrain of `env_seed`; its summary.

    With a `trajectory` list, each step's point of the family's path is appended to it (the
    lander's normalised (x, y), the walker's hull in metres); `on_step` is called with each
    step's action and observation (the explorer records poses with it).
    """
    task = ENVIRONMENTS[env_name]
    if trajectory is not None:
        def on_step(action: Any, obs: np.ndarray) -> None:
            trajectory.append(task.family.position(env, obs))
    return task.family.fly(solution, env_seed, env, task, on_step)


def rollout(solution: np.ndarray, env_seed: int, env: gym.Env, measures: tuple[str, ...] | None = None,
            trajectory: list | None = None, *, env_name: str) -> tuple[float, ...]:
    """(objective, *measures) of one episode (default: the task's measures): the objective is the
    task's (its total reward, for every task but ant_omni)."""
    flight, task = fly(solution, env_seed, env, trajectory, env_name=env_name), ENVIRONMENTS[env_name]
    measures = task.measures if measures is None else measures
    return (float(task.objective(flight)), *(float(MEASURES[name].of(flight)) for name in measures))
