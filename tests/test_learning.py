"""The learning rows (pga_me, cma_mega_td3_es): the TD3 learner (qdsearch/algorithms/td3.py) held
against computations made here in numpy (the actor's forward pass, Adam, the critic's targets, the
soft updates, the objective gradient by finite differences), the transitions a real episode
records, and real runs: the same on 1 and 2 workers, after kill -9 and resume, with the buffer
holding exactly the episodes flown; without JAX, one line."""

import pickle
import subprocess
import sys

import numpy as np
import pytest

from qdsearch.algorithms import td3
from qdsearch.algorithms.pga_me import PG_SIGMA0, PGAMEEmitter
from qdsearch.cli import commands
from qdsearch.search.engine import in_pair_order, per_terrain, submit_flights
from qdsearch.tasks import ENVIRONMENTS, Episode, make_env
from qdsearch.tasks.policies import Policy, rollout
from qdsearch.tasks.transitions import Recorder
from util import (
    assert_killed_then_resumed_as_its_twin,
    assert_one_line_error,
    read_checkpoint,
    run_archive,
    run_metrics,
    tiny_flags,
)

SHAPE = (2, 3)  # (actions, observations) of the hand-made cases
NET = Policy("mlp", (4,))


def hand_actor(flat, obs, shape=SHAPE, hidden=(4,)):
    """policies.py's layout by hand: each layer's W (outputs x inputs, row-major), then b; tanh."""
    widths, at, h = [shape[1], *hidden, shape[0]], 0, np.asarray(obs, dtype=np.float64)
    for inputs, out in zip(widths[:-1], widths[1:]):
        weights = flat[at:at + out * inputs].reshape(out, inputs)
        at += out * inputs
        h, at = np.tanh(h @ weights.T + flat[at:at + out]), at + out
    return h


def hand_q(layers, obs, actions):
    h = np.concatenate([obs, actions], axis=-1).astype(np.float64)
    for weights, bias in layers[:-1]:
        h = np.maximum(h @ np.asarray(weights, np.float64) + np.asarray(bias, np.float64), 0.0)
    weights, bias = layers[-1]
    return (h @ np.asarray(weights, np.float64) + np.asarray(bias, np.float64))[:, 0]


def learner(capacity=1_000, seed=0, shape=SHAPE, policy=NET):
    x0 = policy.start(shape, seed)
    return td3.Learner(policy, shape, x0, capacity, seed)


def test_the_actor_acts_as_the_flown_policy():
    """The critic's gradients go through the policy the episodes fly: the same actions."""
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(5, 3))
    for policy in (NET, Policy("linear")):
        flat = rng.normal(size=policy.size(SHAPE))
        acts = td3.compiled(SHAPE, policy.hidden, policy.row.biases).actor_forward(flat.astype(np.float32),
                                                                                   obs.astype(np.float32))
        flown = np.array([policy.act(flat, SHAPE, True)(o) for o in obs])
        assert np.allclose(np.asarray(acts), flown, atol=1e-5)
    assert np.allclose(hand_actor(flat := rng.normal(size=NET.size(SHAPE)), obs),
                       [NET.act(flat, SHAPE, True)(o) for o in obs])


def test_adam_is_pytorchs():
    rng = np.random.default_rng(1)
    params, grads = rng.normal(size=4).astype(np.float32), rng.normal(size=(3, 4)).astype(np.float32)
    state, got = td3.adam_state(params), params
    m, v, theta = np.zeros(4), np.zeros(4), params.astype(np.float64)
    for t, g in enumerate(grads, 1):
        got, state = td3.adam(got, g, state, 0.1)
        m, v = 0.9 * m + 0.1 * g, 0.999 * v + 0.001 * g * g
        theta = theta - 0.1 * (m / (1 - 0.9 ** t)) / (np.sqrt(v / (1 - 0.999 ** t)) + 1e-8)
    assert np.allclose(np.asarray(got), theta, atol=1e-6) and int(state[2]) == 3


def test_the_buffer_keeps_the_last_rows_in_order_and_its_state():
    buffer = td3.ReplayBuffer(5, 1, 1)  # rows of 2 * 1 + 1 + 2 = 5 columns
    rows = np.arange(7 * 5, dtype=np.float32).reshape(7, 5)
    buffer.add(rows[:3])
    buffer.add(rows[3:])
    assert buffer.size == 5 and buffer.next == 2 and buffer.rows.dtype == np.float32  # half a float64's bytes
    assert np.array_equal(buffer.rows[[2, 3, 4, 0, 1]], rows[2:])  # oldest overwritten first
    again = td3.ReplayBuffer.restore(pickle.loads(pickle.dumps(buffer.state())))
    assert np.array_equal(again.rows, buffer.rows) and (again.next, again.size) == (2, 5)
    drawn = buffer.sample(np.random.default_rng(0), (40,))
    assert np.array_equal(drawn, buffer.rows[np.random.default_rng(0).integers(0, 5, 40)])  # uniformly
    assert {tuple(row) for row in drawn} <= {tuple(row) for row in rows[2:]}
    big = td3.ReplayBuffer(3, 1, 1)
    big.add(rows)  # more rows than it holds at once: the last three
    assert np.array_equal(big.rows[[1, 2, 0]], rows[4:]) and big.next == 1


def fill(learner, count=600, seed=3, done=0.0):
    """Transitions with random observations and actions, reward obs[0] + action[0]."""
    rng = np.random.default_rng(seed)
    obs, actions = rng.normal(size=(count, 3)), rng.uniform(-1, 1, size=(count, 2))
    rewards = obs[:, 0] + actions[:, 0]
    learner.buffer.add(np.column_stack([obs, actions, rewards, rng.normal(size=(count, 3)),
                                        np.full(count, done)]))
    return obs, actions, rewards


def test_a_critic_step_follows_the_td3_target_and_the_actor_and_targets_wait_a_step():
    """One step: Adam on the twin critic's MSE to r + 0.99 (1 - d) min(Q'(s', clip(pi'(s') +
    clipped noise))), checked by finite differences of that loss computed here; the actor and
    targets move on the second step only, the targets by tau."""
    one = learner(seed=5)
    fill(one)
    critic0, actor0, target0 = one.critic, np.asarray(one.actor), one.critic_target
    draws = np.random.default_rng()
    draws.bit_generator.state = one.rng.bit_generator.state
    batch = one.buffer.sample(draws, (1, td3.BATCH))[0].astype(np.float64)
    noise = draws.standard_normal((1, td3.BATCH, 2), dtype=np.float32)[0].astype(np.float64)
    obs, actions, reward = batch[:, :3], batch[:, 3:5], batch[:, 5]
    next_obs, done = batch[:, 6:9], batch[:, 9]
    next_actions = np.clip(hand_actor(actor0, next_obs) + np.clip(0.2 * noise, -0.5, 0.5), -1, 1)
    target = reward + 0.99 * (1 - done) * np.minimum(hand_q(target0[0], next_obs, next_actions),
                                                     hand_q(target0[1], next_obs, next_actions))

    def loss(twin):
        return sum(np.mean((hand_q(q, obs, actions) - target) ** 2) for q in twin)

    one.train(1)
    assert np.array_equal(np.asarray(one.actor), actor0)  # the actor waits for the 2nd step
    assert all(np.array_equal(a, b) for a, b in zip(jax_leaves(one.critic_target), jax_leaves(target0)))
    # Adam's first step moves each weight by lr against the sign of its gradient
    moved = np.asarray(one.critic[0][2][1]) - np.asarray(critic0[0][2][1])  # q1's output bias
    h = 1e-3
    twin = [[(np.asarray(w, np.float64), np.asarray(b, np.float64)) for w, b in q] for q in critic0]
    up = [[*q] for q in twin]
    up[0][2] = (twin[0][2][0], twin[0][2][1] + h)
    down = [[*q] for q in twin]
    down[0][2] = (twin[0][2][0], twin[0][2][1] - h)
    slope = (loss(up) - loss(down)) / (2 * h)
    assert np.allclose(moved, -td3.ADAM_LR * np.sign(slope), rtol=1e-3)
    one.train(1)
    assert not np.array_equal(np.asarray(one.actor), actor0) and one.steps == 2
    leaves = zip(jax_leaves(one.critic_target), jax_leaves(target0), jax_leaves(one.critic))
    for target, before, now in leaves:
        assert np.allclose(target, td3.TAU * now + (1 - td3.TAU) * before, atol=1e-7)


def jax_leaves(tree):
    import jax

    return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(tree)]


def test_with_every_episode_ended_the_critic_learns_the_reward():
    """d = 1 everywhere: the target is the reward alone, which the twin critic comes to predict."""
    one = learner(seed=6)
    obs, actions, rewards = fill(one, done=1.0)
    before = np.mean(np.abs(hand_q(one.critic[0], obs, actions) - rewards))
    one.train(1_500)
    after = np.mean(np.abs(hand_q(one.critic[0], obs, actions) - rewards))
    assert after < 0.15 * before and after < 0.2


def test_the_objective_gradient_is_the_critics_value_by_finite_differences():
    one = learner(seed=7)
    fill(one)
    obs = np.random.default_rng(8).normal(size=(64, 3))
    point = NET.start(SHAPE, 9) + 0.3
    functions = td3.compiled(SHAPE, NET.hidden, True)
    got = np.asarray(functions.objective_gradients(point[None].astype(np.float32), one.critic[0],
                                                   obs.astype(np.float32)))[0]

    def value(flat):
        return hand_q(one.critic[0], obs, hand_actor(flat, obs)).mean()

    h, picked = 1e-4, [0, 5, 13, len(point) - 1]
    numeric = [(value(point + h * np.eye(len(point))[i]) - value(point - h * np.eye(len(point))[i])) / (2 * h)
               for i in picked]
    assert np.allclose(got[picked], numeric, rtol=2e-2, atol=1e-5)
    empty = learner(seed=7)  # dqd-rl: random directions while nothing is known
    assert empty.objective_gradients(point[None]).shape == (1, len(point))


# Adam's steps are about its learning rate each (a little more where a gradient grows): 10 of them.
PG_REACH = 1.1 * td3.PG_STEPS * td3.PG_LR


def test_pg_variation_climbs_the_critic_by_adam_steps_of_a_thousandth():
    one = learner(seed=10)
    fill(one)
    one.train(200)
    parents = NET.start(SHAPE, 11) + np.random.default_rng(12).normal(scale=0.2, size=(6, NET.size(SHAPE)))
    improved = one.improve(parents)
    assert improved.shape == parents.shape and np.all(np.abs(improved - parents) <= PG_REACH)
    obs = one.buffer.rows[:600, :3].astype(np.float64)
    gains = [hand_q(one.critic[0], obs, hand_actor(new, obs)).mean() - hand_q(one.critic[0], obs,
                                                                              hand_actor(old, obs)).mean()
             for new, old in zip(improved, parents)]
    assert all(gain > 0 for gain in gains)


def test_the_learners_state_restores_to_the_same_next_steps():
    one = learner(seed=13)
    fill(one)
    one.train(10)
    saved = pickle.dumps((one.state(), one.buffer.state()))
    again = td3.Learner.restore(*pickle.loads(saved))
    for each in (one, again):
        each.train(6)
    assert np.array_equal(one.greedy(), again.greedy())
    parents = np.tile(one.greedy(), (2, 1))
    assert np.array_equal(one.improve(parents), again.improve(parents))


def test_pga_me_asks_iso_line_then_pg_children_and_noise_around_x0_at_first():
    from ribs.archives import GridArchive

    archive = GridArchive(solution_dim=NET.size(SHAPE), dims=[4], ranges=[(0, 1)], seed=1)
    x0 = NET.start(SHAPE, 1)
    emitter = PGAMEEmitter(archive, x0=x0, batch_size=5, seed=2, iso_sigma=0.005, line_sigma=0.05)
    twin, other = (PGAMEEmitter(archive, x0=x0, batch_size=5, seed=seed, iso_sigma=0.005, line_sigma=0.05)
                   for seed in (2, 3))
    first = emitter.ask()
    assert np.array_equal(twin.ask(), first) and not np.array_equal(other.ask(), first)  # its seed's
    assert first.shape == (5, len(x0))
    assert np.all(emitter.genetic.iso_sigma == 0.005) and np.all(emitter.genetic.line_sigma == 0.05)
    assert 0.8 < np.std(first[:3] - x0) / 0.005 < 1.2  # iso+line of x0 alone: x0 plus noise of 0.005
    assert 0.8 < np.std(first[3:] - x0) / PG_SIGMA0 < 1.2  # x0 plus noise of 0.02
    one = learner(seed=3)
    fill(one)
    emitter.learner = one
    archive.add(first, np.arange(5.0), np.linspace(0.05, 0.95, 5)[:, None])
    asked = emitter.ask()
    elites = archive.data("solution")
    nearest = [np.abs(elites - row).max(axis=1).min() for row in asked[3:]]
    assert all(gap <= PG_REACH for gap in nearest)  # an elite after 10 small steps
    assert pickle.loads(pickle.dumps(emitter)).learner is None  # the checkpoint keeps it apart


def test_a_recorded_episode_is_the_plain_one_and_its_transitions_add_up():
    """Hopper, 40 steps: the same objective and measures; each row's action is the policy's of
    its observation, the next observation is the next row's, the rewards sum to the return."""
    policy, name = Policy("mlp", (4,)), "Hopper-v5"
    shape = ENVIRONMENTS[name].shape
    solution = policy.start(shape, 1) * 3
    episode = Episode(40)
    plain = rollout(solution, 5, make_env(env_name=name, episode=episode), env_name=name, policy=policy)
    recorder = Recorder(make_env(env_name=name, episode=episode))
    recorded = rollout(solution, 5, recorder, env_name=name, policy=policy)
    rows = recorder.take()
    assert recorded == plain and rows.dtype == np.float32 and recorder.take().shape[0] == 0
    o, a = shape[1], shape[0]
    assert rows.shape[1] == 2 * o + a + 2 and 1 <= len(rows) <= 40
    act = policy.act(solution, shape, True)
    assert np.allclose(rows[:, o:o + a], [act(obs) for obs in rows[:, :o].astype(np.float64)], atol=1e-5)
    assert np.array_equal(rows[1:, :o], rows[:-1, o + a + 1:2 * o + a + 1])
    assert np.isclose(rows[:, o + a].astype(np.float64).sum(), plain[0], rtol=1e-5)
    assert rows[-1, -1] == 1.0 and not rows[:-1, -1].any()


def test_transitions_come_back_in_solution_order_whatever_the_chunks(dask_cluster):
    name, policy = "HalfCheetah-v5", Policy("mlp", (4,))
    shape, episode = ENVIRONMENTS[name].shape, Episode(12)
    solutions = policy.start(shape, 2) + np.random.default_rng(0).normal(size=(9, policy.size(shape)))
    seeds = np.arange(9)[:, None]
    from dask.distributed import Client

    client, ordered = Client(dask_cluster), []
    for threads in (1, 3):  # 1 chunk of 9, then 6 chunks
        futures = submit_flights(client, solutions, seeds, ENVIRONMENTS[name].measures, True, threads=threads,
                                 env_name=name, policy=policy, episode=episode, transitions=True)
        chunks = client.gather(futures)
        ordered.append(in_pair_order([t for _, t in chunks]))
        assert per_terrain([r for r, _ in chunks], seeds).shape == (9, 1, 3)  # objective, 2 feet
    assert len(ordered[0]) == 9 and all(np.array_equal(a, b) for a, b in zip(*ordered))
    for solution, seed, rows in zip(solutions, seeds[:, 0], ordered[0]):
        recorder = Recorder(make_env(env_name=name, episode=episode))
        rollout(solution, int(seed), recorder, env_name=name, policy=policy)
        assert np.array_equal(recorder.take(), rows)
    client.close()


LEARNING = dict(env="Hopper-v5", policy="mlp", hidden="4", n_emitters=1, batch_size=5, grid=8,
                iterations=3, episode_length=20)


@pytest.mark.parametrize("algorithm, per_iteration", [("pga_me", 6), ("cma_mega_td3_es", 6 + 1 + 6)])
@pytest.mark.parametrize("env", ["Hopper-v5", "HalfCheetah-v5"])
def test_a_learning_row_is_the_same_on_one_and_two_workers(
        tmp_path, dask_cluster, one_worker_cluster, algorithm, per_iteration, env):
    """pga_me: a batch of 5 and the greedy actor; cma_mega_td3_es: its point and 6 samples too."""
    samples = {"es_samples": 6} if "cma" in algorithm else {}
    flags = {**LEARNING, "env": env, "algorithm": algorithm, **samples}
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "two"))
    commands.search(**tiny_flags(one_worker_cluster, **flags), outdir=str(tmp_path / "one"))
    assert run_archive(tmp_path / "two").equals(run_archive(tmp_path / "one"))
    metrics = run_metrics(tmp_path / "one")
    assert [row["evaluations"] for row in metrics] == [per_iteration * i for i in (1, 2, 3)]
    assert metrics == run_metrics(tmp_path / "two") and metrics[-1]["num_elites"] > 0
    learned = read_checkpoint(tmp_path / "one" / "checkpoint.pkl")["learning"]
    steps = {"pga_me": 300, "cma_mega_td3_es": 600}[algorithm]
    assert learned["learner"]["steps"] == steps * 2  # none while the first batch flies: no data yet
    transitions = len(learned["buffer"]["rows"])
    assert per_iteration * 3 <= transitions <= per_iteration * 3 * 20  # Hopper may fall early
    assert env == "Hopper-v5" or transitions == per_iteration * 3 * 20  # HalfCheetah never does


def whole_episodes(rows, length, obs):
    """Rows that are whole episodes of `length` steps one after another: each ends (and only its
    last step), and each step's next observation is its successor's observation."""
    ends = np.flatnonzero(rows[:, -1])
    assert np.array_equal(ends, np.arange(length - 1, len(rows), length))
    chained = np.ones(len(rows) - 1, dtype=bool)
    chained[ends[:-1]] = False  # a new episode starts from its own reset
    assert np.array_equal(rows[1:, :obs][chained], rows[:-1, -1 - obs:-1][chained])


def test_the_buffer_holds_every_step_flown_up_to_its_bound(tmp_path, dask_cluster):
    """HalfCheetah never ends early: 3 iterations of 6 episodes of 20 steps are 360 transitions;
    --buffer_size 100 keeps the last 100: the last five episodes, oldest first."""
    flags = {**LEARNING, "env": "HalfCheetah-v5", "algorithm": "pga_me"}
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "all"))
    commands.search(**tiny_flags(dask_cluster, **flags, buffer_size=100), outdir=str(tmp_path / "bound"))
    full = read_checkpoint(tmp_path / "all" / "checkpoint.pkl")["learning"]["buffer"]
    bound = read_checkpoint(tmp_path / "bound" / "checkpoint.pkl")["learning"]["buffer"]
    assert len(full["rows"]) == 360 and full["next"] == 360 and len(bound["rows"]) == 100
    obs = ENVIRONMENTS["HalfCheetah-v5"].shape[1]
    whole_episodes(full["rows"], 20, obs)
    whole_episodes(np.roll(bound["rows"], -bound["next"], axis=0), 20, obs)


@pytest.mark.slow  # a search killed and resumed, and its uninterrupted twin
@pytest.mark.parametrize("algorithm, env", [("pga_me", "Hopper-v5"), ("cma_mega_td3_es", "HalfCheetah-v5")])
def test_a_learning_run_killed_then_resumed_ends_as_its_uninterrupted_twin(tmp_path, dask_cluster,
                                                                          one_worker_cluster, algorithm, env):
    """kill -9 past a checkpoint: the buffer, the networks, their Adam moments and the draws come
    back from it, the emitters are handed the learner again, and the run ends bit for bit as the
    one that never stopped."""
    samples = {"es_samples": 4} if "cma" in algorithm else {}
    flags = {**LEARNING, "env": env, "algorithm": algorithm, **samples, "iterations": 7, "log_every": 1}
    assert_killed_then_resumed_as_its_twin(tmp_path, dask_cluster, one_worker_cluster, flags)


def test_a_learning_row_needs_continuous_actions(run_cli, tmp_path):
    result = run_cli("--algorithm", "pga_me", "--outdir", tmp_path / "out")
    assert_one_line_error(result, "--algorithm pga_me learns a critic of continuous actions",
                          "--env LunarLander-v3 has a choice of actions", "Hopper-v5")
    assert not (tmp_path / "out").exists()


def without_jax(*args, cwd):
    """The script in a process where JAX cannot be imported, as where it is not installed."""
    from conftest import SCRIPT

    code = ("import os, runpy, sys; sys.modules['jax'] = None; sys.argv = sys.argv[1:]; "
            "sys.path.insert(0, os.path.dirname(sys.argv[0])); "
            "runpy.run_path(sys.argv[0], run_name='__main__')")
    return subprocess.run([sys.executable, "-c", code, str(SCRIPT), *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.slow  # processes of their own
def test_without_jax_a_learning_row_is_one_line_and_its_runs_still_read(tmp_path, dask_cluster):
    refused = without_jax("--algorithm", "cma_mega_td3_es", "--env", "Hopper-v5", "--outdir", tmp_path / "x",
                          cwd=tmp_path)
    assert_one_line_error(refused, "--algorithm cma_mega_td3_es learns with JAX, which is not installed",
                          "pip install -r requirements-learning.txt")
    assert not (tmp_path / "x").exists()
    run_dir = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, **{**LEARNING, "iterations": 2}, algorithm="pga_me"),
                    outdir=str(run_dir))
    listed = without_jax("elites", run_dir, "--top", 2, cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert (run_dir / "elites.csv").exists()
    resumed = without_jax("resume", run_dir, "--iterations", 3, cwd=tmp_path)
    assert_one_line_error(resumed, "learns with JAX, which is not installed")


@pytest.mark.slow  # a tracked search, its video, its elites flown again and its explorer page
def test_every_results_command_reads_a_learning_run(tmp_path, dask_cluster):
    """A PGA-ME Hopper run tracked in TensorBoard (read back by its own reader); video, elites,
    evaluate and explore on it: each elite flown again scores what the archive holds."""
    import csv

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from qdsearch.analysis import results
    from util import page_data, saved_archive

    run_dir = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, **LEARNING, algorithm="pga_me", track="tensorboard"),
                    outdir=str(run_dir))
    events = EventAccumulator(str(run_dir / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    assert [event.value for event in events.Scalars("qd/qd_score")] == pytest.approx(
        [row["qd_score"] for row in run_metrics(run_dir)], rel=1e-6)
    best = saved_archive(run_dir).best_elite
    commands.video(str(run_dir), best=True)
    with open(run_dir / "videos" / "index.csv") as file:
        [row] = list(csv.DictReader(file))
    assert float(row["objective"]) == best["objective"] and row["reproduced"] == "True"
    commands.elites(str(run_dir), top=3)
    with open(run_dir / "elites.csv") as file:
        assert float(next(csv.DictReader(file))["objective"]) == best["objective"]
    address = dask_cluster.scheduler_address
    commands.evaluate(str(run_dir), env_seeds="3", top=2, scheduler_address=address)
    table = __import__("pandas").read_csv(run_dir / "robustness.csv")
    elites = results.elite_rows(results.load_run(run_dir)[0])
    solutions = dict(zip(elites["index"], elites["solution"]))
    policy, name = Policy("mlp", (4,)), "Hopper-v5"
    for entry in table.to_dict("records"):
        flown = rollout(solutions[entry["cell_index"]], 3, make_env(env_name=name, episode=Episode(20)),
                        env_name=name, policy=policy)
        assert entry["objective_seed3"] == flown[0]
    commands.explore(str(run_dir), scheduler_address=address)
    assert len(page_data(run_dir)["elites"]) == len(saved_archive(run_dir))


def test_chunks_items_come_back_in_pair_order_however_dealt():
    from qdsearch.search.engine import chunk_pairs

    for pairs in (1, 7, 12):
        for count in range(1, min(pairs, 5) + 1):
            dealt = [[f"pair {i}" for i in chunk] for chunk in chunk_pairs(pairs, count)]
            assert in_pair_order(dealt) == [f"pair {i}" for i in range(pairs)]


def hopper_learning_run(algorithm="pga_me"):
    """A learning row's config and scheduler on Hopper (nothing flown), and its Learning."""
    from qdsearch.algorithms import build_scheduler
    from qdsearch.config import options, run_config
    from qdsearch.search.learning import Learning

    config = run_config.check_run_config(options.with_task(dict(
        options.search_defaults(), algorithm=algorithm, env="Hopper-v5", policy="mlp", hidden=[4], seed=3,
        n_emitters=1, batch_size=4, grid=5, buffer_size=50)))
    scheduler = build_scheduler(config)
    return config, scheduler, Learning.of(config, scheduler)


def test_a_runs_learning_holds_an_iterations_transitions_until_it_is_told():
    from qdsearch.search.learning import Learning

    """The greedy actor after the batch; the chunks' transitions kept in pair order and added at
    the commit; the checkpoint is the learner as of the last commit, whatever it learns after."""
    config, scheduler, learning = hopper_learning_run()
    assert scheduler.emitters[0].learner is learning.learner  # handed over
    start = learning.checkpoint()  # iteration 0's: the learner as made, the buffer empty
    assert start["learner"]["steps"] == 0 and len(start["buffer"]["rows"]) == 0
    assert np.allclose(start["learner"]["actor"], scheduler.emitters[0].x0, atol=1e-6)
    assert learning.learns.critic_steps == 300 and not learning.learns.objective_gradient
    batch = scheduler.ask()
    flown = learning.with_greedy(batch)
    assert np.array_equal(flown[:-1], batch) and np.array_equal(flown[-1], learning.learner.greedy())
    width = learning.learner.buffer.rows.shape[1]
    episodes = [np.full((3, width), float(i), dtype=np.float32) for i in range(5)]  # 5 rollouts' rows
    chunks = [(np.array([[float(i)]]), [episodes[i] for i in dealt]) for i, dealt in
              enumerate([[0, 2, 4], [1, 3]])]
    rows = learning.collect(chunks)
    assert [r[0, 0] for r in rows] == [0.0, 1.0] and learning.learner.buffer.size == 0
    learning.commit()
    assert np.array_equal(learning.learner.buffer.rows[:15, 0], np.repeat(np.arange(5.0), 3))
    frozen = learning.checkpoint()
    learning.train()  # the next iteration's steps, while its batch flies
    assert learning.learner.steps == 300
    later = learning.checkpoint()
    assert later["learner"]["steps"] == frozen["learner"]["steps"] == 0
    assert np.array_equal(later["learner"]["actor"], frozen["learner"]["actor"])
    assert len(later["buffer"]["rows"]) == 15
    learning.collect(chunks)  # the next iteration's, after the first
    learning.commit()
    assert learning.learner.buffer.size == 30 and learning.checkpoint()["learner"]["steps"] == 300
    saved = learning.checkpoint()  # a resume: the learner back from the checkpoint, handed over
    resumed = Learning.of(config, scheduler, pickle.loads(pickle.dumps(saved)))
    assert scheduler.emitters[0].learner is resumed.learner is not learning.learner
    assert np.array_equal(resumed.learner.buffer.rows[:30], learning.learner.buffer.rows[:30])
    assert resumed.learner.steps == 300
    assert np.array_equal(resumed.learner.greedy(), learning.learner.greedy())
    measures = np.array([0.5])
    learning.insert_greedy(scheduler, 12.5, measures)
    inserted = scheduler.archive.data()
    assert np.array_equal(inserted["solution"][0], flown[-1]) and inserted["objective"][0] == 12.5


def test_cma_mega_td3_es_takes_the_critics_objective_gradients_and_other_rows_learn_nothing():
    from qdsearch.search.learning import Learning

    config, scheduler, learning = hopper_learning_run("cma_mega_td3_es")
    assert learning.learns.objective_gradient and learning.learns.critic_steps == 600
    fill_hopper = np.random.default_rng(0).normal(size=(64, learning.learner.buffer.rows.shape[1]))
    learning.learner.buffer.add(fill_hopper)
    points = scheduler.ask_dqd()
    assert learning.objective_gradients(points).shape == points.shape
    plain = config.replace(algorithm="cma_mega_es")
    from qdsearch.algorithms import build_scheduler

    assert Learning.of(plain, build_scheduler(plain)) is None
