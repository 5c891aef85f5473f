"""A run's episode rules (--episode_length) are what its workers fly, whatever flew before.

Each episode is checked against gym.make's env with the same max_episode_steps, flown by hand:
the streamlined lander must not be used where the rules are not the task's own, and a worker's
reused env must be the one made for these rules, not one a chunk of another run left behind.
"""

import gymnasium as gym
import numpy as np
import pytest

from qdsearch import tasks
from qdsearch.search import engine
from qdsearch.tasks import policies
from util import HOVER_W, LANDER

TERRAIN = 52  # HOVER_W hovers the whole 1,000 steps here: any shorter limit cuts its episode


def hand_flown(solution, length: int | None) -> tuple[float, int]:
    """(total reward, steps) of the linear policy on gym.make's lander, at most `length` steps."""
    env = gym.make("LunarLander-v3", **({} if length is None else {"max_episode_steps": length}))
    weights = np.asarray(solution, dtype=np.float64).reshape(4, 8)
    obs, _ = env.reset(seed=TERRAIN)
    total, steps, done = 0.0, 0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(int(np.argmax(weights @ obs)))
        total, steps, done = total + reward, steps + 1, terminated or truncated
    env.close()
    return total, steps


def chunk_objective(length: int | None, fast: bool = True) -> float:
    """The objective a worker's chunk gives HOVER_W under these rules (the chunk's env reused)."""
    rows = engine.fly_chunk(engine.Chunk(np.array([HOVER_W]), np.array([TERRAIN]), (), LANDER,
                                         episode=tasks.Episode(length), fast_env=fast))
    return float(rows[0, 0])


def test_the_hover_runs_its_whole_episode():
    assert hand_flown(HOVER_W, None)[1] == 1000


@pytest.mark.parametrize("fast", [True, False])
def test_an_episode_length_cuts_the_lander_with_or_without_the_streamlined_env(fast):
    """--episode_length on LunarLander: the streamlined env flies only the task's own rules."""
    env = tasks.make_env(fast, env_name=LANDER, episode=tasks.Episode(60))
    flight = policies.fly(np.array(HOVER_W), TERRAIN, env, env_name=LANDER)
    total, steps = hand_flown(HOVER_W, 60)
    assert (flight.steps, flight.reward) == (steps, total) == (60, total)


def test_a_worker_flies_each_chunk_by_its_own_rules_in_any_order():
    """The env kept between chunks is keyed by the rules too: chunks of runs with other episode
    lengths, flown by one worker thread in turn, each end where their own rules say."""
    for length in (40, 90, None, 40, 250, None):
        assert chunk_objective(length) == hand_flown(HOVER_W, length)[0], length
    assert chunk_objective(90, fast=False) == hand_flown(HOVER_W, 90)[0]
