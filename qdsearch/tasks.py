"""The problem: a linear policy flying a Gymnasium task, and what its episode is measured by.

Map:
- what an episode records: `Flight` (a lander's), `Walk` (a walker's);
- the policy and the episodes: `linear_policy`, `burn`, `fly_lander`, `fly_walker` (with
  `renew_world`: a fresh Box2D world per walker episode);
- the tasks: `Environment`, the ENVIRONMENTS table (--env), `DEFAULT_ENV`, `make_env`,
  `check_spaces`;
- the measures: `Measure`, the MEASURES table (--measures), `family_measures`;
- `fly` and `rollout`: one episode of a task, and its objective and measures.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import Box2D
import gymnasium as gym
import numpy as np

from qdsearch.fast_env import FastLunarLander
from qdsearch.flags import UsageError

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


def make_env(fast: bool = True, render_mode: str | None = None, *, env_name: str) -> gym.Env:
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
        on_step: Callable[[Any, np.ndarray], None] | None = None, *, env_name: str) -> Any:
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
            trajectory: list | None = None, *, env_name: str) -> tuple[float, ...]:
    """(objective, *measures) of one episode (default: the task's measures): the objective is the
    episode's total reward."""
    flight = fly(solution, env_seed, env, trajectory, env_name=env_name)
    measures = ENVIRONMENTS[env_name].measures if measures is None else measures
    return (float(flight.reward), *(float(MEASURES[name].of(flight)) for name in measures))
