"""The policies a search can fly (--policy), declared once as rows of POLICIES, and one episode
of a solution flown as one: the worker's rollout, from a run's policy to the task's episode.

A task gives a policy its shape, (actions, observations), from the env's spaces (family.py's
`Environment.shape`); the policy says how many weights it has, how it acts, and where the
emitters start. Every family flies any policy: its episode function calls the `act` it is given.

Map:
- `PolicyKind`: a row of POLICIES (its weights' count, its act, its start, its own flags);
- POLICIES: `linear` (W @ obs, no bias: the tutorial's, zeros at the start) and `mlp` (tanh
  hidden layers with biases, a Glorot draw at the start, as dqd-rl and QDax start theirs);
- STARTS (--start): where the emitters start, zeros or a Glorot draw, for any row;
- `Policy`: what a run flies (a row, its hidden sizes, its start), small and hashable: it travels
  with every chunk of rollouts (a run's config makes it once: `PolicySettings.network`); LINEAR;
- `layer_sizes`, `mlp_act`, `glorot`: the network, its forward pass and its initial draw;
- an episode, on any task of the registry (the package's __init__): `fly` (its summary, and its
  path if asked: the family's episode function flies the policy's act) and `rollout` (its
  objective and measures).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from qdsearch.tasks import ENVIRONMENTS, MEASURES
from qdsearch.tasks.family import OnStep, require_drawing

Shape = tuple[int, int]  # (actions, observations), from the task's spaces


def linear_size(shape: Shape, hidden: tuple[int, ...]) -> int:
    return shape[0] * shape[1]


def linear_act(solution: np.ndarray, shape: Shape, hidden: tuple[int, ...], continuous: bool) -> Callable:
    """obs -> action of W @ obs (no bias): argmax for a choice, tanh of each component for a box
    (tasks.check_spaces holds every action box to [-1, 1])."""
    weights = np.asarray(solution, dtype=np.float64).reshape(shape)
    # W.dot(obs) makes the same BLAS call as W @ obs (same bits) for less overhead; a strided W
    # would take matmul's non-BLAS path, so it keeps matmul.
    scores = weights.dot if weights.flags.c_contiguous else weights.__matmul__
    return output(scores, continuous)


def output(scores: Callable[[np.ndarray], np.ndarray], continuous: bool) -> Callable:
    """The action of a network's last layer: tanh of each component for a box, argmax for a choice."""
    if continuous:
        return lambda obs: np.tanh(scores(obs))
    return lambda obs: int(scores(obs).argmax())


def zeros(shape: Shape, hidden: tuple[int, ...], seed: int, biases: bool) -> np.ndarray:
    """Every weight zero (the tutorial's linear start)."""
    return np.zeros(sum(out * (inputs + biases) for out, inputs in layer_sizes(shape, hidden)))


def layer_sizes(shape: Shape, hidden: tuple[int, ...]) -> list[tuple[int, int]]:
    """Each layer's (outputs, inputs), from the observations through `hidden` to the actions."""
    widths = [shape[1], *hidden, shape[0]]
    return list(zip(widths[1:], widths[:-1]))


def mlp_size(shape: Shape, hidden: tuple[int, ...]) -> int:
    return sum(out * (inputs + 1) for out, inputs in layer_sizes(shape, hidden))


def mlp_layers(solution: np.ndarray, shape: Shape, hidden: tuple[int, ...]) -> list[tuple[np.ndarray, ...]]:
    """The solution cut into each layer's (W, b), in order: W row-major (outputs x inputs), then b."""
    flat, layers, at = np.ascontiguousarray(solution, dtype=np.float64), [], 0
    for out, inputs in layer_sizes(shape, hidden):
        weights, at = flat[at:at + out * inputs].reshape(out, inputs), at + out * inputs
        layers.append((weights, flat[at:at + out]))
        at += out
    return layers


def mlp_act(solution: np.ndarray, shape: Shape, hidden: tuple[int, ...], continuous: bool) -> Callable:
    """obs -> action of the network: tanh(W h + b) through the hidden layers, then the last layer's
    W h + b, as `output` makes it an action. The layers are views of the solution, cut once."""
    *inner, (last_w, last_b) = mlp_layers(solution, shape, hidden)

    def scores(obs: np.ndarray) -> np.ndarray:
        h = obs
        for weights, bias in inner:
            h = np.tanh(weights.dot(h) + bias)
        return last_w.dot(h) + last_b
    return output(scores, continuous)


def glorot(shape: Shape, hidden: tuple[int, ...], seed: int, biases: bool) -> np.ndarray:
    """A Glorot (Xavier) uniform draw of every layer's weights, biases (if the row has them) zero:
    dqd-rl's and QDax's start; seeded from the run's seed apart from the archive's and emitters'
    seeds."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6107]))
    parts = []
    for out, inputs in layer_sizes(shape, hidden):
        limit = np.sqrt(6.0 / (inputs + out))
        parts += [rng.uniform(-limit, limit, out * inputs), np.zeros(out if biases else 0)]
    return np.concatenate(parts)


# --start: where a run's emitters start, as (shape, hidden, seed, biases) -> the weights.
STARTS: dict[str, Callable[[Shape, tuple[int, ...], int, bool], np.ndarray]] = {
    "zeros": zeros, "glorot": glorot}


@dataclasses.dataclass(frozen=True, kw_only=True)
class PolicyKind:
    """A row of POLICIES: its weights' count, its act and its start, each a function of the task's
    shape and the hidden sizes; `flags`, the search flags only this row uses."""

    summary: str  # what --help calls it
    size: Callable[[Shape, tuple[int, ...]], int]
    act: Callable[[np.ndarray, Shape, tuple[int, ...], bool], Callable]
    start: str  # its STARTS row unless --start names another: the emitters' x0, from the run's seed
    biases: bool  # whether each layer has a bias after its weights
    flags: tuple[str, ...] = ()


POLICIES: dict[str, PolicyKind] = {
    "linear": PolicyKind(summary="W @ obs, no bias, starting at zeros (the tutorial's)",
                         size=linear_size, act=linear_act, start="zeros", biases=False),
    "mlp": PolicyKind(summary="tanh hidden layers of --hidden units with biases, starting from a "
                              "Glorot draw (dqd-rl's 128,128; QDax's 64,64)",
                      size=mlp_size, act=mlp_act, start="glorot", biases=True, flags=("hidden",)),
}


@dataclasses.dataclass(frozen=True)
class Policy:
    """What a run flies: a row of POLICIES and, for a network, its hidden layers' sizes; and where
    its emitters start (a row of STARTS; "": the row's own)."""

    kind: str = "linear"
    hidden: tuple[int, ...] = ()
    start_rule: str = ""

    @property
    def row(self) -> PolicyKind:
        return POLICIES[self.kind]

    def size(self, shape: Shape) -> int:
        """The number of weights: the solution's size."""
        return self.row.size(shape, self.hidden)

    def act(self, solution: np.ndarray, shape: Shape, continuous: bool) -> Callable:
        """obs -> action of `solution` in a task of this shape."""
        return self.row.act(solution, shape, self.hidden, continuous)

    def start(self, shape: Shape, seed: int) -> np.ndarray:
        return STARTS[self.start_rule or self.row.start](shape, self.hidden, seed, self.row.biases)


LINEAR = Policy()


# One episode of a solution flown as a policy, on any task of the registry.
def fly(solution: np.ndarray, env_seed: int, env: gym.Env, trajectory: list | None = None,
        on_step: OnStep | None = None, *, env_name: str, policy: Policy = LINEAR) -> Any:
    """Fly `solution` as `policy` (default: linear) for one episode on the terrain of `env_seed`;
    its summary.

    With a `trajectory` list, each step's point of the family's path is appended to it (the
    lander's normalised (x, y), the walker's hull in metres; a family that declares no path is
    refused in one line); `on_step` is called with each step's action and observation (the
    explorer records poses with it).
    """
    task = ENVIRONMENTS[env_name]
    if trajectory is not None:
        require_drawing(task.family, "trajectories")

        def on_step(action: Any, obs: np.ndarray) -> None:
            trajectory.append(task.family.position(env, obs))
    return task.family.fly(policy.act(solution, task.shape, task.continuous), env_seed, env, task, on_step)


def rollout(solution: np.ndarray, env_seed: int, env: gym.Env, measures: tuple[str, ...] | None = None,
            trajectory: list | None = None, *, env_name: str, policy: Policy = LINEAR) -> tuple[float, ...]:
    """(objective, *measures) of one episode (default: the task's measures): the objective is the
    task's (its total reward, for every task but ant_omni)."""
    task = ENVIRONMENTS[env_name]
    flight = fly(solution, env_seed, env, trajectory, env_name=env_name, policy=policy)
    measures = task.measures if measures is None else measures
    return (float(task.objective(flight)), *(float(MEASURES[name].of(flight)) for name in measures))
