"""An episode's transitions, for the learning rows' replay buffer (algorithms/td3.py): the
environment of a rollout wrapped so that each step is kept as one float32 row, as dqd-rl's gym
loop keeps its Experience: the observation, the action, the reward, the next observation, and
whether the episode ended there (at a time limit too, as dqd-rl's old gym API said done).

Wrapping changes no result: every call goes through to the env unchanged (tests hold a recorded
rollout equal to a plain one).

Map: `Recorder` (`take`: the episode's rows), `transition_width`.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def transition_width(obs_dim: int, act_dim: int) -> int:
    """The float32 columns of a transition row: obs, action, reward, next obs, done."""
    return 2 * obs_dim + act_dim + 2


class Recorder:
    """An environment that keeps a row per step since the last `take`; anything else is the
    wrapped env's (a family's episode reads its model, its hull, its lander)."""

    def __init__(self, env: Any) -> None:
        self.env, self.rows, self.obs = env, [], None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.env, name)

    def reset(self, **kwargs: Any) -> tuple[Any, dict]:
        self.obs, info = self.env.reset(**kwargs)
        return self.obs, info

    def step(self, action: Any) -> tuple:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.rows.append(np.concatenate([self.obs, np.ravel(action), (reward,), obs,
                                         (float(terminated or truncated),)]))
        self.obs = obs
        return obs, reward, terminated, truncated, info

    def take(self) -> np.ndarray:
        """The rows kept since the last take, as float32, and forget them."""
        rows, self.rows = np.asarray(self.rows, dtype=np.float32), []
        return rows
