"""QD-RL as papers run it: the MLP policy against a network computed by hand, the ES gradients
against dqd-rl's formula, the DQD rows on real MuJoCo rollouts (the same archive on 1 and 2
workers and after a resume), budgets in evaluations, the episode rules against gym.make's own
env, a row that can't hold a network refused, and every results command flying an MLP run."""

import math

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
from scipy import stats

from qdsearch import tasks
from qdsearch.algorithms import ALGORITHMS, evaluations_per_iteration, gradients
from qdsearch.cli import commands
from qdsearch.config import run_config, settings
from qdsearch.config.run_config import load_run_config
from qdsearch.tasks import policies
from qdsearch.tasks.policies import LINEAR, POLICIES, Policy
from util import assert_one_line_error, run_archive, run_metrics, saved_archive, tiny_flags

HOPPER = "Hopper-v5"
# A tiny DQD run: 2 emitters, each flying its point, 10 gradient samples and 6 branches: 34 an iteration.
# Episodes of 12 steps: the best's video renders 13 frames (MuJoCo draws in software here: the
# suite's costliest frames).
DQD = dict(env=HOPPER, policy="mlp", hidden=[8, 8], algorithm="cma_mega_es", n_emitters=2,
           batch_size=6, es_samples=10, es_sigma=0.02, episode_length=12)


def hand_network(solution, shape, hidden, obs):
    """The network's output by hand: layers cut from the solution in order, each W (outputs x
    inputs, row-major) then b; tanh between layers, none after the last."""
    widths, at, h = [shape[1], *hidden, shape[0]], 0, np.asarray(obs, dtype=np.float64)
    for layer, (inputs, outputs) in enumerate(zip(widths, widths[1:])):
        weights = solution[at:at + inputs * outputs].reshape(outputs, inputs)
        bias = solution[at + inputs * outputs:at + inputs * outputs + outputs]
        at += inputs * outputs + outputs
        h = weights @ h + bias
        if layer < len(hidden):
            h = np.tanh(h)
    assert at == len(solution)
    return h


@pytest.mark.parametrize("env_name", ["LunarLander-v3", "Walker2d-v5"])
def test_the_mlp_acts_as_the_network_computed_by_hand(env_name):
    task, hidden = tasks.ENVIRONMENTS[env_name], (5, 3)
    policy = Policy("mlp", hidden)
    obs_dim, act_dim = task.shape[1], task.shape[0]
    assert policy.size(task.shape) == (obs_dim * 5 + 5) + (5 * 3 + 3) + (3 * act_dim + act_dim)
    rng = np.random.default_rng(3)
    for _ in range(20):
        solution, obs = rng.normal(size=policy.size(task.shape)), rng.normal(size=obs_dim)
        act = policy.act(solution, task.shape, task.continuous)
        action, out = act(obs), hand_network(solution, task.shape, hidden, obs)
        if task.continuous:
            np.testing.assert_allclose(action, np.tanh(out), rtol=1e-12, atol=1e-15)
        else:
            assert action == int(np.argmax(out))


def test_the_linear_policy_is_the_tutorials():
    task = tasks.ENVIRONMENTS["LunarLander-v3"]
    solution, obs = np.arange(32.0) - 16, np.linspace(-1, 1, 8)
    assert LINEAR.size(task.shape) == 32 and not LINEAR.start(task.shape, 42).any()
    act = LINEAR.act(solution, task.shape, task.continuous)
    assert act(obs) == int(np.argmax(solution.reshape(4, 8) @ obs))


def test_the_network_starts_from_a_seeded_glorot_draw():
    shape, hidden = (6, 17), (64, 32)
    policy = Policy("mlp", hidden)
    start = policy.start(shape, 7)
    assert np.array_equal(start, policy.start(shape, 7)) and not np.array_equal(start, policy.start(shape, 8))
    at = 0
    for inputs, outputs in zip([17, 64, 32], [64, 32, 6]):
        weights = start[at:at + inputs * outputs]
        bias = start[at + inputs * outputs:at + (inputs + 1) * outputs]
        at += (inputs + 1) * outputs
        limit = math.sqrt(6 / (inputs + outputs))
        assert not bias.any() and np.abs(weights).max() <= limit
        assert abs(weights.std() - limit / math.sqrt(3)) < 0.15 * limit  # a uniform's spread
    assert at == len(start) == policy.size(shape)


def test_the_start_is_one_stream_of_draws_from_the_runs_seed():
    """Every layer's weights drawn in turn from one generator of (seed, 0x6107), as a run of an
    earlier version drew them: a fixed --seed keeps its start."""
    shape, hidden, seed = (3, 5), (4,), 12
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6107]))
    expected = np.concatenate([rng.uniform(-math.sqrt(6 / 9), math.sqrt(6 / 9), 20), np.zeros(4),
                               rng.uniform(-math.sqrt(6 / 7), math.sqrt(6 / 7), 12), np.zeros(3)])
    assert np.array_equal(Policy("mlp", hidden).start(shape, seed), expected)


def test_a_policy_is_read_from_its_runs_config():
    """Runs from before --policy are linear; --hidden belongs to a network only; --start is any
    policy's (runs from before it start as their row does)."""
    from qdsearch.base.flags import UsageError
    from qdsearch.config.options import search_defaults
    from qdsearch.config.run_config import check_run_config

    recorded = {**search_defaults(), "seed": 1, "archive": "grid", "grid": 50}
    before = {name: value for name, value in recorded.items() if name not in ("policy", "hidden", "start")}
    assert check_run_config(before).network == LINEAR
    mlp = check_run_config({**recorded, "policy": "mlp", "hidden": [8, 4]})
    assert mlp.network == Policy("mlp", (8, 4))
    assert check_run_config({**recorded, "start": "glorot"}).network == Policy("linear", (), "glorot")
    with pytest.raises(UsageError, match="--hidden is a flag of --policy mlp"):
        check_run_config({**recorded, "hidden": [8]})


def test_start_gives_either_form_either_start():
    """--start glorot draws the linear policy's W as the network's layers are drawn (no bias);
    --start zeros starts a network at zeros; a row's own start is unchanged by the flag's
    existence (the linear at zeros, the network's draw)."""
    shape, seed = (6, 17), 9
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x6107]))
    limit = math.sqrt(6 / (17 + 6))
    assert np.array_equal(Policy("linear", (), "glorot").start(shape, seed), rng.uniform(-limit, limit, 102))
    network = Policy("mlp", (8,), "zeros")
    assert network.start(shape, seed).shape == (network.size(shape),) and not network.start(shape, seed).any()
    drawn = Policy("mlp", (8,), "glorot").start(shape, seed)
    assert np.array_equal(drawn, Policy("mlp", (8,)).start(shape, seed))
    assert not Policy("linear", (), "zeros").start(shape, seed).any() and not LINEAR.start(shape, seed).any()


def test_a_runs_emitters_start_where_start_says():
    from qdsearch.algorithms import build_scheduler
    from qdsearch.config.options import search_defaults

    config = run_config.search_config({**search_defaults(), "seed": 4, "env": HOPPER, "start": "glorot",
                                "algorithm": "sep_cma_mae", "n_emitters": 2})
    scheduler = build_scheduler(config)
    expected = Policy("linear", (), "glorot").start(tasks.ENVIRONMENTS[HOPPER].shape, 4)
    assert expected.any() and all(np.array_equal(emitter.x0, expected) for emitter in scheduler.emitters)


def test_a_strided_solution_acts_as_w_at_obs():
    """A solution that is a strided view (a column of a bigger array) acts with W @ obs's bits,
    as the contiguous one does."""
    rng = np.random.default_rng(0)
    solution, obs = rng.normal(size=64)[::2], rng.normal(size=8)
    weights = solution.reshape(4, 8)
    assert np.array_equal(LINEAR.act(solution, (4, 8), True)(obs), np.tanh(weights @ obs))
    assert np.array_equal(LINEAR.act(solution.copy(), (4, 8), True)(obs), np.tanh(weights.copy() @ obs))


def test_each_layers_start_is_its_own_draw():
    """One generator draws the layers in turn: a generator made anew per layer would start every
    layer with a rescaled copy of the first layer's weights."""
    shape, hidden = (4, 8), (8, 8)
    start, at, scaled = Policy("mlp", hidden).start(shape, 5), 0, []
    for inputs, outputs in zip([8, 8, 8], [8, 8, 4]):
        scaled.append(start[at:at + 24] / math.sqrt(6 / (inputs + outputs)))  # uniform(-1, 1) draws
        at += (inputs + 1) * outputs
    assert not np.allclose(scaled[0], scaled[1]) and not np.allclose(scaled[0], scaled[2])


def test_the_gradient_batch_is_each_point_then_its_mirrored_samples():
    points, eps = np.array([[0.0, 0.0], [10.0, 20.0]]), np.arange(8.0).reshape(2, 2, 2)
    batch = gradients.sample_points(points, eps, 0.5)
    assert np.array_equal(batch[:2], points)
    assert np.array_equal(batch[2:6], [[0, 0.5], [1, 1.5], [0, -0.5], [-1, -1.5]])
    assert np.array_equal(batch[6:], [[12, 22.5], [13, 23.5], [8, 17.5], [7, 16.5]])
    again = gradients.noise(seed=4, iteration=9, points=2, samples=10, dim=3)
    assert again.shape == (2, 5, 3) and np.array_equal(again, gradients.noise(4, 9, 2, 10, 3))
    assert not np.array_equal(again, gradients.noise(4, 10, 2, 10, 3))  # each iteration its own draws
    assert not np.array_equal(again, gradients.noise(5, 9, 2, 10, 3))  # each seed: a repeat of its own


def test_centred_ranks_share_ties():
    """Ranks over n - 1 less one half; equal values (a measure that many samples share) each take
    their mean rank."""
    assert np.array_equal(gradients.centred_ranks(np.array([3.0, 1.0, 2.0])), [0.5, -0.5, 0.0])
    tied = gradients.centred_ranks(np.tile([1.0, 0.0], 50))  # ranks 74.5 and 24.5 of 0-99
    assert np.array_equal(tied, np.tile([74.5 / 99 - 0.5, 24.5 / 99 - 0.5], 50))
    shared = 1 / 3 - 0.5  # three 2.0s: ranks 0, 1, 2, each 1 of 0-3
    assert np.array_equal(gradients.centred_ranks(np.array([[2.0, 2.0, 5.0, 2.0], [7.0] * 4])),
                          [[shared, shared, 0.5, shared], [0.0] * 4])


def test_a_flat_measure_has_no_gradient_and_one_differing_sample_gives_one():
    """A measure every sample shares (a foot on the ground all along, or never) is estimated flat:
    a zero gradient, not -sum(eps). One sample apart is a direction: its own eps, signed."""
    point, sigma = np.zeros((1, 6)), 0.02
    eps = gradients.noise(seed=3, iteration=0, points=1, samples=100, dim=6)
    batch = gradients.sample_points(point, eps, sigma)
    flat = np.column_stack([batch[:, 0], np.full(len(batch), 0.25)])  # an objective, a flat measure
    _, _, jacobian = gradients.estimate(flat, eps, sigma)
    assert np.array_equal(jacobian[0, 1], np.zeros(6)) and np.abs(jacobian[0, 0]).sum() > 0
    flat[1 + 7, 1] = 0.5  # the sample +eps_7 alone is apart, above the rest
    _, _, jacobian = gradients.estimate(flat, eps, sigma)
    # its rank 99 against the others' mean rank 49 (of 0-98): every other pair's ranks cancel
    np.testing.assert_allclose(jacobian[0, 1], eps[0, 7] * (0.5 - (49 / 99 - 0.5)) / (50 * sigma), rtol=1e-12)


def test_a_dqd_run_flies_its_samples_at_es_sigma(tmp_path):
    """The first batch of a DQD run's iteration: its emitters' points, then each point's mirrored
    samples at --es_sigma (not the emitters' --sigma0), drawn from the run's seed."""
    import logging

    from qdsearch import algorithms
    from qdsearch.config import options, run_config
    from qdsearch.search import run

    config = run_config.check_run_config(options.with_task(
        {**options.search_defaults(), "algorithm": "cma_mega_es", "n_emitters": 2, "batch_size": 2,
         "es_samples": 6, "es_sigma": 0.03, "sigma0": 0.5, "seed": 9}))
    one = run.Run(tmp_path, config, algorithms.build_scheduler(config), [], logging.getLogger("dqd"))
    batch = one.ask()
    points, eps = batch[:2], gradients.noise(9, 0, 2, 6, batch.shape[1])
    offsets = (batch[2:].reshape(2, 6, -1) - points[:, None, :]) / 0.03
    np.testing.assert_allclose(offsets, np.concatenate([eps, -eps], axis=1), rtol=1e-9, atol=1e-9)


def test_the_gradient_estimate_is_dqd_rls_formula():
    """dqd-rl: grad = sum_i eps_i (r_i - r_{i+n/2}) / (n/2 sigma), r the centred ranks of the n
    samples' values (scipy's ranks, ties sharing their mean), the objective first, then each
    measure."""
    rng = np.random.default_rng(0)
    points, half, dim, sigma, measures = 3, 6, 4, 0.05, 2
    eps = rng.normal(size=(points, half, dim))
    flown = rng.normal(size=(points * (1 + 2 * half), 1 + measures))
    objective, values, jacobian = gradients.estimate(flown, eps, sigma)
    assert np.array_equal(objective, flown[:points, 0]) and np.array_equal(values, flown[:points, 1:])
    for p in range(points):
        samples = flown[points + p * 2 * half:points + (p + 1) * 2 * half]
        for k in range(1 + measures):
            ranks = (stats.rankdata(samples[:, k], method="average") - 1) / (2 * half - 1) - 0.5
            expected = sum(eps[p, i] * (ranks[i] - ranks[i + half]) for i in range(half)) / (half * sigma)
            np.testing.assert_allclose(jacobian[p, k], expected, rtol=1e-12)


def test_the_gradient_estimate_points_uphill():
    rng = np.random.default_rng(1)
    slope, dim, sigma = rng.normal(size=10), 10, 0.02
    point = rng.normal(size=(1, dim))
    eps = gradients.noise(seed=1, iteration=0, points=1, samples=100, dim=dim)
    batch = gradients.sample_points(point, eps, sigma)
    flown = np.column_stack([batch @ slope, -batch[:, 0]])  # an objective, and a measure: -x0
    _, _, jacobian = gradients.estimate(flown, eps, sigma)
    cosine = jacobian[0, 0] @ slope / np.linalg.norm(jacobian[0, 0]) / np.linalg.norm(slope)
    assert cosine > 0.8, cosine
    assert jacobian[0, 1, 0] / np.linalg.norm(jacobian[0, 1]) < -0.8  # the measure's: down along x0


def test_an_iteration_costs_its_rows_evaluations():
    config = type("Config", (), dict(n_emitters=3, batch_size=7, es_samples=20))
    for name, row in ALGORITHMS.items():
        config.algorithm = name
        expected = 3 * 21 if row.es_steps else 21 + (3 * 21 if row.dqd else 0)  # ME-ES: samples, offspring
        expected -= 3 * 20 if row.exact else 0  # exact gradients: each point alone, no samples
        expected += row.learns is not None  # a learning row's greedy actor
        assert evaluations_per_iteration(config) == expected, name


def test_a_budget_in_evaluations_sets_the_most_iterations_within_it():
    """cma_mega_es, 2 emitters of 6 and 10 samples: 34 evaluations an iteration; a budget of
    exactly one iteration is one; one short of it is refused; a huge one stops at MAX_ITERATIONS."""
    from qdsearch.base.flags import UsageError
    from qdsearch.config import options

    config = {**options.search_defaults(), **DQD, "iterations": 7}
    for budget, iterations in [(34, 1), (135, 3), (136, 4), (10**12, settings.MAX_ITERATIONS)]:
        made = options.with_budget({**config, "evaluations": budget})
        assert made == {**config, "evaluations": budget, "iterations": iterations}
        assert type(made["iterations"]) is int
    with pytest.raises(UsageError, match="--evaluations 33 is less than one iteration of --algorithm "
                                         "cma_mega_es, which flies 34"):
        options.with_budget({**config, "evaluations": 33})


def rules_env(env_name, length, unhealthy):
    kwargs = {"max_episode_steps": length, "terminate_when_unhealthy": unhealthy}
    return gym.make(tasks.ENVIRONMENTS[env_name].gym_id, **{k: v for k, v in kwargs.items() if v is not None})


@pytest.mark.parametrize("length, unhealthy", [(40, None), (300, False)])
def test_episodes_follow_the_rules_gym_makes_them_with(length, unhealthy):
    """The episode's length and return as gym.make's env gives them for a hand-flown network."""
    task, policy = tasks.ENVIRONMENTS[HOPPER], Policy("mlp", (8, 8))
    solution = policy.start(task.shape, 3)
    rules = tasks.Episode(length, unhealthy)
    env = tasks.make_env(env_name=HOPPER, episode=rules)
    flight = policies.fly(solution, 5, env, env_name=HOPPER, policy=policy)
    env = rules_env(HOPPER, length, unhealthy)
    obs, _ = env.reset(seed=5)
    total, steps, done = 0.0, 0, False
    while not done:
        action = np.tanh(hand_network(solution, task.shape, (8, 8), obs))
        obs, reward, terminated, truncated, _ = env.step(action)
        total, steps, done = total + reward, steps + 1, terminated or truncated
    assert (flight.steps, flight.reward) == (steps, pytest.approx(total, rel=1e-12))
    if unhealthy is False:
        assert steps == length  # a fallen hopper goes on to the end
    else:
        assert steps <= length


def test_flags_a_policy_or_a_task_cannot_use_are_refused(run_cli, tmp_path):
    out = str(tmp_path / "run")
    for flags, words in [
        (["--hidden", "16,16"], ["--hidden", "--policy linear"]),
        (["--terminate_when_unhealthy", "false"], ["LunarLander-v3", "Hopper-v5, Walker2d-v5, Ant-v5"]),
        (["--policy", "mlp", "--hidden", "16,0"], ["--hidden", "128,128"]),
        (["--algorithm", "cma_mega_es", "--es_samples", "7"], ["--es_samples", "even"]),
        (["--es_samples", "10"], ["--es_samples", "cma_mega_es", "cma_me does not"]),
        (["--iterations", "3", "--evaluations", "90"], ["--iterations and --evaluations"]),
        (["--evaluations", "100"], ["less than one iteration", "150"]),
    ]:
        assert_one_line_error(run_cli(*flags, "--outdir", out), *words)
        assert not (tmp_path / "run").exists()


def test_a_row_whose_emitters_cannot_hold_the_network_is_refused_at_once(run_cli, tmp_path):
    """Ant-v5's 128x128 network has 21,128 weights: CMA-ME's five full covariances don't fit."""
    for command in ([], ["experiment", "--seeds", "1", "--algorithms", "cma_me"]):
        result = run_cli(*command, "--env", "Ant-v5", "--policy", "mlp", "--hidden", "128,128",
                         *([] if command else ["--algorithm", "cma_me"]), "--outdir", str(tmp_path / "run"))
        assert_one_line_error(result, "cma_me", "21,128 weights", "sep_cma_mae", "lm_ma_mae",
                              "line_map_elites", "cma_mega_es")
        fits = result.stderr.split("rows that fit: ")[1].split(" (or")[0].split(", ")
        assert "cma_mae" not in fits and "cma_me" not in fits and "line_map_elites" in fits
        assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def dqd_runs(tmp_path_factory, dask_cluster, one_worker_cluster):
    """The tiny DQD run on the shared 2-worker cluster, on the 1-worker one, and stopped after 2
    iterations then resumed to 4; their data alone (what they are compared by, what the results
    commands read)."""
    root, flags = tmp_path_factory.mktemp("dqd"), dict(DQD, seed=11)
    commands.search(**tiny_flags(dask_cluster, **flags, iterations=4), outdir=str(root / "two"))
    commands.search(**tiny_flags(one_worker_cluster, **flags, iterations=4), outdir=str(root / "one"))
    commands.search(**tiny_flags(dask_cluster, **flags, iterations=2), outdir=str(root / "resumed"))
    commands.resume(str(root / "resumed"), iterations=4, scheduler_address=dask_cluster.scheduler_address)
    return root


@pytest.mark.slow  # real MuJoCo searches
def test_a_dqd_run_is_the_same_on_one_and_two_workers_and_resumed(dqd_runs):
    two = run_archive(dqd_runs / "two")
    assert len(two) > 5
    for other in ("one", "resumed"):
        assert two.equals(run_archive(dqd_runs / other)), other
        assert run_metrics(dqd_runs / "two") == run_metrics(dqd_runs / other), other
    rows = run_metrics(dqd_runs / "two")
    assert [row["evaluations"] for row in rows] == [34, 68, 102, 136]  # 2 x (1 + 10) + 2 x 6 each
    assert sum(column.startswith("solution_") for column in two) == 11 * 8 + 8 + 8 * 8 + 8 + 8 * 3 + 3


@pytest.mark.slow  # real MuJoCo searches
def test_a_dqd_run_of_an_experiment_is_its_lone_twin(dqd_runs, tmp_path, dask_cluster):
    flags = {key: value for key, value in DQD.items() if key != "algorithm"}
    commands.experiment(algorithms="cma_mega_es", seeds="11", iterations=4, outdir=str(tmp_path / "exp"),
                           scheduler_address=dask_cluster.scheduler_address, **flags)
    [run_dir] = [path for path in (tmp_path / "exp").iterdir() if (path / "archive.npz").is_file()]
    assert run_archive(run_dir).equals(run_archive(dqd_runs / "two"))
    assert run_metrics(run_dir) == run_metrics(dqd_runs / "two")


@pytest.mark.slow  # real MuJoCo searches
def test_elites_of_a_dqd_run_are_their_networks_flown_by_hand(dqd_runs):
    """Every elite's stored objective and foot contact is its network flown in gym.make's env
    (the run's 12-step episodes), computed here without the tool's policy or family code."""
    import mujoco

    elites = saved_archive(dqd_runs / "two").data()
    env = rules_env(HOPPER, DQD["episode_length"], None)
    model = env.unwrapped.model
    foot = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "foot_geom")
    for solution, objective, measures in zip(elites["solution"], elites["objective"], elites["measures"]):
        obs, _ = env.reset(seed=52)
        total, steps, touching, done = 0.0, 0, 0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(
                np.tanh(hand_network(solution, (3, 11), (8, 8), obs)))
            data = env.unwrapped.data
            touching += any(foot in pair and 0 in pair for pair in data.contact.geom[:data.ncon].tolist())
            total, steps, done = total + reward, steps + 1, terminated or truncated
        assert objective == pytest.approx(total, rel=1e-9)
        assert measures[0] == pytest.approx(touching / steps, abs=1e-12)


@pytest.mark.slow  # real MuJoCo searches
def test_a_budget_in_evaluations_stops_at_the_last_iteration_within_it(tmp_path, dask_cluster):
    commands.search(**tiny_flags(dask_cluster, **DQD, evaluations=120, seed=2), outdir=str(tmp_path / "run"))
    rows, config = run_metrics(tmp_path / "run"), load_run_config(tmp_path / "run")
    assert [row["evaluations"] for row in rows] == [34, 68, 102]  # a fourth would fly 136 > 120
    assert (config.evaluations, config.iterations) == (120, 3)


@pytest.mark.slow  # real MuJoCo searches
def test_resume_to_a_budget_in_evaluations_equals_a_run_started_with_it(tmp_path, dask_cluster):
    """resume --evaluations 240 of a run of 120: 3 -> 7 iterations of 34, bit for bit a run of 240."""
    short, whole = tmp_path / "short", tmp_path / "whole"
    commands.search(**tiny_flags(dask_cluster, **DQD, evaluations=120, seed=2), outdir=str(short))
    commands.search(**tiny_flags(dask_cluster, **DQD, evaluations=240, seed=2), outdir=str(whole))
    commands.resume(str(short), evaluations=240, scheduler_address=dask_cluster.scheduler_address)
    assert run_archive(short).equals(run_archive(whole)) and run_metrics(short) == run_metrics(whole)
    config = load_run_config(short)
    assert (config.evaluations, config.iterations) == (240, 7)
    assert run_metrics(short)[-1]["evaluations"] == 7 * 34


@pytest.mark.slow  # real MuJoCo searches
def test_the_results_commands_fly_a_runs_network(run_cli, dqd_runs, tmp_path, dask_cluster):
    """video, elites, trajectories, evaluate, explore and compare on an MLP DQD run: each flies the
    elites as the run's policy (video reflies the best to its stored objective)."""
    folder = str(dqd_runs / "two")
    best = run_archive(folder)["objective"].max()
    result = run_cli("video", folder, "--best")
    assert result.returncode == 0, result.stderr
    assert f"objective {best:.2f}" in result.stdout
    elites, on_cluster = len(run_archive(folder)), ["--scheduler_address", dask_cluster.scheduler_address]
    for command, said in ((["elites", folder], f"{elites} of {elites} elites"),
                          (["trajectories", folder, "--top", "2"], "trajectories.png"),
                          (["explore", folder, *on_cluster], f"{elites} elites"),
                          (["evaluate", folder, "--env_seeds", "0-1", *on_cluster], "")):
        result = run_cli(*command)
        assert result.returncode == 0 and said in result.stdout, (command, result.stderr)
    result = run_cli("compare", folder, str(dqd_runs / "one"), "--at_evaluations", "100",
                     "--out", str(tmp_path / "cmp.png"))
    assert result.returncode == 0, result.stderr
    expected = next(row for row in run_metrics(folder)[::-1] if row["evaluations"] <= 100)
    for row in pd.read_csv(tmp_path / "cmp.csv").to_dict("records"):
        assert row["evaluations"] == 68 and row["iterations"] == 2
        assert row["qd_score"] == pytest.approx(expected["qd_score"], rel=1e-12)
        assert math.isnan(row["cqd_score"])  # the archive is of iteration 4, not 2


def test_every_policy_row_says_its_own_flags():
    assert POLICIES["linear"].flags == () and POLICIES["mlp"].flags == ("hidden",)


def test_curves_over_evaluations_keep_their_tick_labels_apart(tmp_path, monkeypatch):
    """Budgets of 100,000s of evaluations: at most 6 labels on a panel's x axis, none overlapping."""
    from qdsearch.base import plots

    drawn, panel_figure = [], plots.panel_figure

    def kept(*args):  # the figure, to read its axes
        figure, axes = panel_figure(*args)
        drawn.append(figure)
        return figure, axes

    monkeypatch.setattr(plots, "panel_figure", kept)
    rows = [{"evaluations": 200 * i, "qd_score": i * 1e4, "coverage": i / 100, "best_objective": float(i)}
            for i in range(1, 81)]
    plots.save_metric_panels({"run": [rows]}, "evaluations", "Evaluations", tmp_path / "curves.png")
    [figure] = drawn
    figure.canvas.draw()
    for ax in figure.axes:
        low, high = ax.get_xlim()
        labels = [label for label in ax.get_xticklabels() if low <= label.get_position()[0] <= high]
        boxes = [label.get_window_extent() for label in labels]
        assert len(labels) <= 6
        assert all(a.x1 < b.x0 for a, b in zip(boxes, boxes[1:])), [label.get_text() for label in labels]
