"""What a task family is: the types every family module fills in, and the linear policy they share.

A family (lander.py, walker.py) is a group of Gymnasium tasks flown by one episode function and
told apart by one set of measures. It declares itself once, as a `Family` value, and its tasks and
measures as rows that point to it; tasks.py gathers the families' rows into the tables --env and
--measures pick from.

Map:
- `Family`: a family's episode function and how the results commands draw it (path points, the
  step a path marks, poses for the explorer page, the page's scene, the trajectories picture);
- `Environment`: a task a search can fly (a row of ENVIRONMENTS);
- `Measure`: a behaviour solutions are told apart by (a row of MEASURES);
- `linear_policy`: the policy W @ obs every task flies.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import gymnasium as gym
import numpy as np

OnStep = Callable[[Any, np.ndarray], None]  # called with each step's action and observation


@dataclasses.dataclass(frozen=True, eq=False)
class Family:
    """A family of tasks: one episode function, one set of measures, one way to be drawn.

    Families are compared by identity: a task's measures are the rows whose `family` is its own.
    """

    name: str  # in --help and in messages
    title: str  # how --help introduces its measures
    fly: Callable[..., Any]  # (solution, env_seed, env, task, on_step) -> the episode's summary
    position: Callable[[gym.Env, np.ndarray], tuple[float, float]]  # a path's point after a step
    marked_step: Callable[[Any], int]  # the step (1-based) a path marks, from the episode's summary
    pose: Callable[[gym.Env, Any], list[float]]  # what the explorer page draws a step from
    pose_scale: tuple[float, ...]  # the pose's units per int16 step (metres or radians)
    pose_angles: tuple[int, ...]  # the pose's columns that are angles (wrapped to [-pi, pi])
    scene: Callable[[int, Environment], dict]  # the page's world and bodies (explorer_page.html)
    draw_paths: Callable[[Any, list, int, Environment], str]  # the trajectories picture's
    # ground and axes on a matplotlib Axes; returns its title with {} for the count and terrain
    prepare: Callable[[], None] = lambda: None  # called before one of its envs is made


@dataclasses.dataclass(frozen=True)
class Environment:
    """A Gymnasium task a search can fly (a row of ENVIRONMENTS, picked by --env).

    The policy is W @ obs with no bias: `action_dim` rows of `obs_dim` weights, the solution the
    QD algorithm searches. Its family flies the episode and gives its measures; `objective` says
    what of the episode is maximised.
    """

    gym_id: str
    kwargs: dict[str, Any]
    obs_dim: int
    action_dim: int
    continuous: bool  # action = tanh(W @ obs) (a Box of [-1, 1]); else argmax(W @ obs) (Discrete)
    family: Family
    measures: tuple[str, ...]  # the default --measures
    qd_offset: float  # below (almost) every return: QD score counts every elite
    env_seed: str  # what --env_seed picks in this task
    solved: float  # the return its env calls solved
    fast: Callable[[], gym.Env] | None = None  # a streamlined copy, bitwise the same
    heat: tuple[float, float] = (-300.0, 300.0)  # the heatmaps' colour range of objectives
    objective_max: float = 350.0  # a return above (almost) every policy's: CQD's normalisation
    archive: str = "grid"  # the default --archive (a CVT for measures too many for a grid)
    objective: Callable[[Any], float] = lambda summary: summary.reward  # of an episode's summary:
    # its total reward, unless the task says otherwise (ant_omni leaves the forward reward out)

    @property
    def solution_dim(self) -> int:
        return self.action_dim * self.obs_dim


@dataclasses.dataclass(frozen=True)
class Measure:
    """One behaviour solutions are told apart by: its axis label, its range in the archive (values
    outside fall into the edge cells), a short name for file names, how an episode's summary gives
    it, and the families whose summary that is (several robots may share a measure)."""

    label: str
    range: tuple[float, float]
    short: str
    of: Callable[[Any], float]
    families: tuple[Family, ...]
    descending: bool = False  # its axis drawn from the lower bound at the top (the tutorial puts the
    # fastest impacts, the most negative y-velocities, on top)


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
