"""The problem: rollouts and every measure of the MEASURES table, checked against a step-by-step
trace of gym.make's env made by hand; several terrains averaged by the engine."""

import math

import gymnasium as gym
import numpy as np
import pytest

from qdsearch import tasks
from qdsearch.config import options, run_config
from qdsearch.search import engine
from qdsearch.tasks import lander, policies
from qdsearch.tasks.policies import Policy
from util import LANDER, LANDER_W, local_cluster


def step_trace(weights: np.ndarray, env_seed: int) -> list[tuple[int, np.ndarray, float]]:
    """(action, observation after it, reward) for every step of one episode, stepped by hand."""
    env = gym.make("LunarLander-v3")
    obs, _ = env.reset(seed=env_seed)
    trace, done = [], False
    while not done:
        action = int(np.argmax(weights @ obs))
        obs, reward, terminated, truncated, _ = env.step(action)
        trace.append((action, obs.copy(), reward))
        done = terminated or truncated
    env.close()
    return trace


DO_NOTHING = np.zeros((4, 8))  # argmax of zeros is action 0: the lander falls onto the ground
THRUST_UP = np.zeros((4, 8))
THRUST_UP[2, 1] = 1.0  # main engine while above the ground: flies off the screen, never touches
RNG = np.random.default_rng(11)
MIXED = np.reshape(LANDER_W, (4, 8))  # a found lander: fires every engine, tilts, lands


def expected_measures(trace) -> dict[str, float]:
    """Every measure, computed from the trace as its MEASURES row describes it."""
    touch = next((i for i, (_, obs, _) in enumerate(trace) if obs[6] or obs[7]), None)
    impact = trace[-1 if touch is None else touch][1]
    flight = trace if touch is None else trace[:touch + 1]
    actions = [action for action, _, _ in trace]
    return {
        "impact_x": float(impact[0]),
        "impact_y_velocity": float(min(obs[3] for _, obs, _ in trace) if touch is None else impact[3]),
        "impact_x_velocity": float(impact[2]),
        "impact_angle": float(impact[4]),
        "fuel": actions.count(2) + 0.1 * (actions.count(1) + actions.count(3)),
        "flight_time": float(len(trace) if touch is None else touch + 1),
        "max_tilt": max(abs(float(obs[4])) for _, obs, _ in flight),
    }


@pytest.mark.parametrize("weights", [DO_NOTHING, THRUST_UP, MIXED], ids=["falls", "flies off", "mixed"])
def test_every_measure_matches_a_hand_made_trace(weights):
    trace = step_trace(weights, 52)
    expected = expected_measures(trace)
    names = tuple(tasks.family_measures(lander.LANDER))

    result = policies.rollout(weights.ravel(), 52, gym.make("LunarLander-v3"), names, env_name=LANDER)

    assert result[0] == sum(reward for _, _, reward in trace)
    assert dict(zip(names, result[1:])) == pytest.approx(expected, rel=1e-12, abs=0)
    streamlined = tasks.make_env(env_name=LANDER)
    assert policies.rollout(weights.ravel(), 52, streamlined, names, env_name=LANDER) == result


def test_the_traces_cover_what_the_measures_tell_apart():
    falls, flies = expected_measures(step_trace(DO_NOTHING, 52)), expected_measures(step_trace(THRUST_UP, 52))
    mixed_actions = {action for action, _, _ in step_trace(MIXED, 52)}
    assert falls["fuel"] == 0 and flies["fuel"] > 0 and mixed_actions == {0, 1, 2, 3}
    assert 50 < falls["flight_time"] < 100  # free fall touches down after ~60 steps
    assert flies["impact_x"] < -1.0  # flew off the left edge: the last x is outside the range
    for row in tasks.MEASURES.values():
        assert row.range[0] < row.range[1] and row.label and row.short


def test_measures_at_first_leg_contact():
    trace = step_trace(DO_NOTHING, 52)
    first_contact = next(i for i, (_, obs, _) in enumerate(trace) if obs[6] or obs[7])
    assert 0 < first_contact < len(trace) - 1  # the contact is not simply the last step
    result = policies.rollout(DO_NOTHING.ravel(), 52, gym.make("LunarLander-v3"), env_name=LANDER)
    assert result[1:] == (float(trace[first_contact][1][0]), float(trace[first_contact][1][3]))
    assert result[2] != float(trace[-1][1][3])  # measured at contact, not at the end


def test_terrain_seed_changes_the_episode():
    env = gym.make("LunarLander-v3")
    assert policies.rollout(DO_NOTHING.ravel(), 52, env, env_name=LANDER) != (
        policies.rollout(DO_NOTHING.ravel(), 7, env, env_name=LANDER))


def test_worker_chunk_matches_single_rollouts():
    solutions = RNG.normal(size=(5, tasks.ENVIRONMENTS[tasks.DEFAULT_ENV].solution_dim))
    seeds = np.array([52, 52, 7, 7, 3])
    env = gym.make("LunarLander-v3")
    expected = [policies.rollout(s, int(seed), env, ("fuel",), env_name=LANDER)
                for s, seed in zip(solutions, seeds)]
    flown = engine.fly_chunk(engine.Chunk(solutions, seeds, ("fuel",), LANDER))
    assert flown.tolist() == [list(row) for row in expected]


def test_a_chunk_flies_its_policy_by_its_episodes_rules():
    """A chunk's policy (a network) and episode (30 steps) are the ones its rollouts fly."""
    network, short = Policy("mlp", (4,)), tasks.Episode(30)
    solutions = RNG.normal(size=(3, network.size(tasks.ENVIRONMENTS[LANDER].shape)))
    env = tasks.plain_env(LANDER, episode=short)
    expected = [policies.rollout(s, 52, env, ("flight_time",), env_name=LANDER, policy=network)
                for s in solutions]
    chunk = engine.Chunk(solutions, np.full(3, 52), ("flight_time",), LANDER, network, short)
    assert engine.fly_chunk(chunk).tolist() == [list(row) for row in expected]
    assert all(row[1] <= 30 for row in expected)  # none flew past its 30 steps


@pytest.mark.parametrize("terrains", [[52], [52, 7, 3]])
def test_dask_evaluation_keeps_order_and_averages_terrains(dask_client, terrains):
    solutions = np.random.default_rng(1).normal(size=(11, tasks.ENVIRONMENTS[tasks.DEFAULT_ENV].solution_dim))
    measures = ["impact_x", "flight_time", "max_tilt"]
    env = gym.make("LunarLander-v3")
    direct = np.array([[policies.rollout(s, seed, env, measures, env_name=LANDER) for seed in terrains]
                       for s in solutions])
    config = run_config.check_run_config(options.with_task(
        {**options.search_defaults(), "seed": 1, "env_seed": terrains, "measures": measures}))

    objectives, values = engine.evaluate_batch(dask_client, solutions, config)

    assert objectives.shape == (11,) and values.shape == (11, 3)
    assert np.allclose(objectives, direct[:, :, 0].mean(axis=1), rtol=1e-12, atol=0)
    assert np.allclose(values, direct[:, :, 1:].mean(axis=1), rtol=1e-12, atol=0)
    if len(terrains) == 1:  # one terrain: exactly the rollouts, bit for bit
        assert objectives.tolist() == direct[:, 0, 0].tolist()


def test_chunks_are_sized_by_rollouts_not_policies(dask_client):
    solutions = np.zeros((6, tasks.ENVIRONMENTS[tasks.DEFAULT_ENV].solution_dim))
    futures = engine.submit_flights(dask_client, solutions, list(range(40)), (), True, env_name=LANDER)
    sizes = [len(chunk) for chunk in dask_client.gather(futures)]
    assert sum(sizes) == 240 and max(sizes) - min(sizes) <= 1 and len(sizes) == 4  # 2 per worker
    assert math.isclose(sum(sizes) / len(sizes), 60)


def test_a_batchs_rollouts_are_dealt_out_to_its_chunks_and_come_back_in_order():
    """Pair i goes to chunk i mod count, so each chunk holds some of every emitter's solutions
    (neighbours fly alike: runs of them would make chunks of unequal length); per_terrain puts
    the chunks' rows back in pair order."""
    assert [chunk.tolist() for chunk in engine.chunk_pairs(10, 3)] == [[0, 3, 6, 9], [1, 4, 7], [2, 5, 8]]
    rows = np.arange(24, dtype=float).reshape(12, 2)  # 6 solutions x 2 terrains, 2 columns
    chunks = [rows[chunk] for chunk in engine.chunk_pairs(12, 5)]
    assert np.array_equal(engine.per_terrain(chunks, [52, 7]), rows.reshape(6, 2, 2))


@pytest.mark.slow  # a cluster of its own
def test_a_drivers_runs_in_flight_share_the_chunks_and_never_change_the_results():
    """ClusterShare counts the cluster's worker threads (a worker that joins is counted at the next
    refresh) and the driver's own runs; more runs in flight split each batch into fewer chunks, and
    the rows come back the same."""
    from dask.distributed import Client

    from qdsearch.search.engine import ClusterShare

    with local_cluster(2) as cluster, Client(cluster) as client:
        share = ClusterShare(client, every=0.0)
        assert share(3) == (2, 3)
        cluster.scale(3)
        client.wait_for_workers(3)
        assert share(1) == (3, 1)
        solutions = np.zeros((150, tasks.ENVIRONMENTS[LANDER].solution_dim))
        alone = engine.submit_flights(client, solutions, [52], (), True, sharing=1, threads=2,
                                      env_name=LANDER)
        shared = engine.submit_flights(client, solutions, [52], (), True, sharing=4, threads=2,
                                       env_name=LANDER)
        assert len(alone) == 4 and len(shared) == 1  # ceil(2 chunks x 2 workers / runs)
        assert np.array_equal(engine.per_terrain(client.gather(alone), [52]),
                              engine.per_terrain(client.gather(shared), [52]))


@pytest.mark.slow  # a cluster of its own
def test_a_worker_of_several_threads_flies_as_a_worker_of_one():
    """Each thread keeps its own environment: threads that shared one would mix their episodes."""
    from dask.distributed import Client

    solutions = np.random.default_rng(0).normal(0, 1, (150, tasks.ENVIRONMENTS[LANDER].solution_dim))
    serial = engine.fly_chunk(engine.Chunk(solutions, np.full(150, 52), (), LANDER))
    with local_cluster(1, threads=4) as cluster, Client(cluster) as client:
        futures = engine.submit_flights(client, solutions, [52], (), True, env_name=LANDER)
        assert len(futures) == 8  # 2 chunks for each of the 4 threads, flown at once
        assert np.array_equal(engine.per_terrain(client.gather(futures), [52])[:, 0], serial)


def test_batches_are_flown_first_come_first_served(dask_client):
    """Each batch is its own generation on the scheduler, so every chunk of an earlier batch ranks
    before any of a later one. With Dask's default fifo_timeout (100 ms), batches sent together
    rank chunk by chunk across batches: a run's last chunk waits behind the others' first."""
    solutions = np.random.default_rng(0).normal(0, 1, (16, tasks.ENVIRONMENTS[LANDER].solution_dim))
    first, second = (engine.submit_flights(dask_client, solutions, [52], (), True, threads=2,
                                           env_name=LANDER) for _ in range(2))
    assert len(first) == len(second) == 4
    dask_client.gather(first + second)  # the scheduler keeps the tasks while their futures live

    def priorities(keys, dask_scheduler=None):
        return [dask_scheduler.tasks[key].priority for key in keys]
    earlier, later = (dask_client.run_on_scheduler(priorities, [f.key for f in batch])
                      for batch in (first, second))
    assert max(earlier) < min(later)
