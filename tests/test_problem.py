"""The problem: rollouts and their measures, checked against a manual step-by-step trace."""

import gymnasium as gym
import numpy as np

import lunar_lander as ll


def step_trace(weights: np.ndarray, env_seed: int) -> list[tuple[np.ndarray, float]]:
    """(observation, reward) after every step of one episode, stepped by hand."""
    env = gym.make("LunarLander-v3")
    obs, _ = env.reset(seed=env_seed)
    trace, done = [], False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(int(np.argmax(weights @ obs)))
        trace.append((obs.copy(), reward))
        done = terminated or truncated
    env.close()
    return trace


DO_NOTHING = np.zeros((4, 8))  # argmax of zeros is action 0: the lander falls onto the ground
THRUST_UP = np.zeros((4, 8))
THRUST_UP[2, 1] = 1.0  # main engine while above the ground: flies off the screen, never touches


def test_measures_at_first_leg_contact():
    trace = step_trace(DO_NOTHING, 52)
    first_contact = next(i for i, (obs, _) in enumerate(trace) if obs[6] or obs[7])
    assert 0 < first_contact < len(trace) - 1  # the contact is not simply the last step
    obs = trace[first_contact][0]
    expected = (sum(reward for _, reward in trace), float(obs[0]), float(obs[3]))

    result = ll.rollout(DO_NOTHING.ravel(), 52, gym.make("LunarLander-v3"))

    assert result == expected
    assert result[2] != float(trace[-1][0][3])  # measured at contact, not at the end


def test_measures_without_contact_are_last_x_and_fastest_descent():
    trace = step_trace(THRUST_UP, 52)
    assert not any(obs[6] or obs[7] for obs, _ in trace)
    expected = (sum(reward for _, reward in trace), float(trace[-1][0][0]),
                min(float(obs[3]) for obs, _ in trace))

    result = ll.rollout(THRUST_UP.ravel(), 52, gym.make("LunarLander-v3"))

    assert result == expected
    assert result[1] < -1.0  # flew off the left edge: the last x is outside the archive's range


def test_terrain_seed_changes_the_episode():
    env = gym.make("LunarLander-v3")
    assert ll.rollout(DO_NOTHING.ravel(), 52, env) != ll.rollout(DO_NOTHING.ravel(), 7, env)


def test_worker_chunk_matches_single_rollouts():
    rng = np.random.default_rng(0)
    solutions = rng.normal(size=(5, ll.SOLUTION_DIM))
    env = gym.make("LunarLander-v3")
    expected = [ll.rollout(s, 52, env) for s in solutions]
    assert ll.evaluate_chunk(solutions, 52).tolist() == [list(row) for row in expected]


def test_dask_evaluation_keeps_solution_order(dask_client):
    rng = np.random.default_rng(1)
    solutions = rng.normal(size=(11, ll.SOLUTION_DIM))
    env = gym.make("LunarLander-v3")
    expected = np.array([ll.rollout(s, 52, env) for s in solutions])

    objectives, measures = ll.evaluate(dask_client, solutions, 52)

    assert objectives.tolist() == expected[:, 0].tolist()
    assert measures.tolist() == expected[:, 1:].tolist()
