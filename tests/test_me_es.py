"""ME-ES (qdsearch/algorithms/me_es.py) held against dqd-rl's rules computed here by hand: the
novelty, the ES gradient and Adam step, the draws of a parent, the schedule of phases; and a
Hopper MLP run that is the same on 1 and 2 workers."""


import numpy as np
import pytest
from ribs.archives import GridArchive
from ribs.schedulers import Scheduler

from qdsearch.algorithms import me_es
from qdsearch.cli import commands
from util import assert_killed_then_resumed_as_its_twin, run_archive, run_metrics, tiny_flags


def hand_novelty(point, against, skip_self=False):
    """Mean squared distance to the 10 nearest, one exact copy of the point left out."""
    squared = sorted(float(np.sum((point - other) ** 2)) for other in against)
    if skip_self and squared and squared[0] == 0.0:
        squared = squared[1:]
    elif skip_self:
        squared = squared[:-1]
    return float(np.mean(squared[:10]))


def test_novelty_is_the_mean_squared_distance_to_the_ten_nearest():
    rng = np.random.default_rng(0)
    against = rng.uniform(size=(40, 3))
    points = np.vstack([rng.uniform(size=(5, 3)), against[:4]])
    for skip in (False, True):
        expected = [hand_novelty(p, against, skip) for p in points]
        assert np.allclose(me_es.novelty(points, against, skip_self=skip), expected, rtol=1e-12)
    few = against[:4]  # fewer than 10: all of them
    assert np.allclose(me_es.novelty(points[:2], few), [hand_novelty(p, few) for p in points[:2]])


def test_the_es_gradient_is_dqd_rls_over_centred_ranks_not_divided_by_sigma():
    rng = np.random.default_rng(1)
    eps = rng.standard_normal((6, 4))
    scores = rng.normal(size=12)  # +eps samples, then -eps
    order = np.argsort(np.argsort(scores))  # each score's rank, 0 to 11 (no ties)
    ranks = order / 11 - 0.5
    expected = sum(eps[j] * (ranks[j] - ranks[6 + j]) for j in range(6)) / 6
    assert np.allclose(me_es.es_gradient(scores, eps), expected, rtol=1e-12)


def hand_adam(theta, gradients, lr=0.01, l2=0.005):
    """Uber's Adam (dqd-rl's optimizers.py) on the ascent direction, with L2 on theta."""
    m, v = np.zeros_like(theta), np.zeros_like(theta)
    for t, g in enumerate(gradients, 1):
        g = -g + l2 * theta
        a = lr * np.sqrt(1 - 0.999 ** t) / (1 - 0.9 ** t)
        m, v = 0.9 * m + 0.1 * g, 0.999 * v + 0.001 * g * g
        theta = theta - a * m / (np.sqrt(v) + 1e-8)
    return theta


def lone_chain(seed=0, dim=3):
    """A GridArchive of 2 measures in [0, 1] and one ME-ES emitter on it, x0 = ones."""
    archive = GridArchive(solution_dim=dim, dims=[10, 10], ranges=[(0, 1), (0, 1)])
    emitter = me_es.MEESEmitter(archive, x0=np.ones(dim), batch_size=1, seed=seed)
    return archive, emitter, Scheduler(archive, [emitter])


def tell(scheduler, objective, measures):
    solutions = scheduler.ask()
    scheduler.tell(np.array([objective]), np.array([measures]))
    return solutions[0]


def test_a_chain_steps_by_adam_from_its_parent_and_exploits_first():
    archive, emitter, scheduler = lone_chain()
    assert emitter.es_point() is None  # the first iteration flies x0 alone
    assert np.array_equal(tell(scheduler, 5.0, [0.5, 0.5]), np.ones(3))
    rng = np.random.default_rng(2)
    theta = emitter.es_point()
    assert not emitter.explore and np.array_equal(theta, np.ones(3))  # exploit: the one elite
    gradients = []
    for step in range(3):
        eps, objectives = rng.standard_normal((4, 3)), rng.normal(size=8)
        emitter.es_step(objectives, rng.uniform(size=(8, 2)), eps)
        gradients.append(me_es.es_gradient(objectives, eps))
        assert np.allclose(tell(scheduler, 1.0, [0.1 * step, 0.9]), hand_adam(np.ones(3), gradients))
        emitter.es_point()
    assert emitter.steps == 3 and len(emitter.offspring) == 4


def test_every_ten_steps_a_new_parent_from_the_other_phase_with_adam_reset():
    archive, emitter, scheduler = lone_chain(dim=2)
    emitter.es_point()
    tell(scheduler, 0.0, [0.05, 0.05])
    rng = np.random.default_rng(3)
    phases = []
    for step in range(25):
        theta = emitter.es_point()
        phases.append(emitter.explore)
        if step % 10 == 0:  # a new parent: an elite, Adam's moments at zero
            assert emitter.opt._t == 0 and not emitter.opt._m.any()
            assert any(np.array_equal(theta, s) for s in archive.data("solution"))
        emitter.es_step(rng.normal(size=4), rng.uniform(size=(4, 2)), rng.standard_normal((2, 2)))
        tell(scheduler, float(step), rng.uniform(size=2))
    assert phases == [False] * 10 + [True] * 10 + [False] * 5


def test_explore_draws_the_five_most_novel_by_novelty_and_every_elite_a_little():
    novelties = np.array([0.0, 5.0, 1.0, 4.0, 3.0, 2.0, 6.0, 0.5])
    top = {6: 6.0, 1: 5.0, 3: 4.0, 4: 3.0, 5: 2.0}
    expected = [0.1 / 8 + (0.9 * top[i] / 20 if i in top else 0.0) for i in range(8)]
    assert np.allclose(me_es.novelty_bias(novelties), expected, rtol=1e-12)
    assert np.allclose(me_es.novelty_bias(np.zeros(3)), [1 / 3] * 3)  # no novelty yet: even


def test_exploit_takes_the_best_or_one_of_the_two_best_recent_cells():
    cells, scores = np.array([10, 11, 12, 13, 14, 15]), np.array([9.0, 1.0, 3.0, 2.0, 7.0, 0.0])
    discovered = [10, 11, 12, 13, 14, 15, 11, 12, 13, 15]  # the last 5: 12, 13, 15 and 11
    picks = [me_es.best_recent_or_best(cells, scores, discovered, np.random.default_rng(seed))
             for seed in range(400)]
    counts = np.bincount(picks, minlength=6) / len(picks)
    # Half the best (cell 10); half the 2 best of the recent (12: 3.0, 13: 2.0) at 2 : 1.
    assert np.allclose(counts, [0.5, 0, 0.5 * 2 / 3, 0.5 / 3, 0, 0], atol=0.06)
    assert me_es.best_recent_or_best(cells[:4], scores[:4], discovered, np.random.default_rng(0)) == 0


@pytest.mark.slow  # two small searches
@pytest.mark.parametrize("env", ["Hopper-v5", "HalfCheetah-v5"])
def test_me_es_with_an_mlp_is_the_same_on_one_and_two_workers(tmp_path, dask_cluster, one_worker_cluster,
                                                              env):
    flags = dict(algorithm="me_es", env=env, policy="mlp", hidden="4", episode_length=20,
                 es_samples=6, n_emitters=2, iterations=3)
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "two"))
    commands.search(**tiny_flags(one_worker_cluster, **flags), outdir=str(tmp_path / "one"))
    assert run_archive(tmp_path / "two").equals(run_archive(tmp_path / "one"))
    metrics = run_metrics(tmp_path / "one")
    assert [row["evaluations"] for row in metrics] == [2, 2 + 14, 2 + 28]  # x0s, then 6 samples + 1
    assert metrics == run_metrics(tmp_path / "two") and metrics[-1]["num_elites"] > 0


def hand_weights(novelties):
    """dqd-rl's novelty_bias by hand: 0.1 / n each, and 0.9 shared by the 5 most novel (the
    first of equals first) in proportion to their novelty."""
    n = len(novelties)
    order = sorted(range(n), key=lambda i: (-novelties[i], i))[:5]
    total = sum(novelties[i] for i in order)
    return [0.1 / n + (0.9 * novelties[i] / total if i in order else 0.0) for i in range(n)]


def test_explore_ties_go_to_the_first_cell_and_a_lone_point_has_no_novelty():
    novelties = np.array([1.0, 2.0, 2.0, 2.0, 2.0, 2.0, 2.0])  # six of 2.0 for five places
    assert np.allclose(me_es.novelty_bias(novelties), hand_weights(list(novelties)), rtol=1e-12)
    small = np.array([0.01, 0.05, 0.02, 0.04, 0.03, 0.06, 0.001])  # scaled measures': sums below 1
    assert np.allclose(me_es.novelty_bias(small), hand_weights(list(small)), rtol=1e-12)
    none = me_es.novelty_bias(np.zeros(7))  # no novelty yet: the first five share 0.9 evenly
    assert np.allclose(none, [0.1 / 7 + 0.9 / 5] * 5 + [0.1 / 7] * 2, rtol=1e-12)
    point, other = np.array([[0.3, 0.3]]), np.array([[0.3, 0.3], [0.6, 0.7]])
    assert me_es.novelty(point, point, skip_self=True).tolist() == [0.0]
    assert np.allclose(me_es.novelty(point, other, skip_self=True), [0.3 ** 2 + 0.4 ** 2])


@pytest.mark.parametrize("found, recent", [(12, [7, 8, 9, 10, 11]), (10, [5, 6, 7, 8, 9]),
                                           (6, [3, 4, 5]), (3, [2]), (1, [0])])
def test_exploit_draws_from_the_last_five_discovered_or_the_last_half_under_ten(found, recent):
    cells = np.arange(12)
    scores = np.array([10.0, 1.0, 0.0, 6.0, 0.5, 2.0, 7.0, 3.0, 0.0, 1.0, 2.0, 2.5])
    # cell 0 the best of all; the cells just before each recent run score high, to be left out
    picks = {me_es.best_recent_or_best(cells, scores, list(range(found)), np.random.default_rng(seed))
             for seed in range(300)}
    best_two = sorted(recent, key=lambda cell: (-scores[cell], cell))[:2]
    assert picks == {0, *best_two}


def test_exploit_takes_the_best_under_five_cells_and_when_no_recent_cell_is_held():
    scores = np.array([1.0, 4.0, 2.0, 3.0, 0.0])
    picks = {me_es.best_recent_or_best(np.arange(5), scores, [4, 4, 4, 4, 4, 4], np.random.default_rng(s))
             for s in range(100)}
    assert picks == {1, 4}  # five cells: the best, or the recent 4
    assert {me_es.best_recent_or_best(np.arange(4), scores[:4], [3], np.random.default_rng(s))
            for s in range(50)} == {1}  # four cells: always the best
    assert {me_es.best_recent_or_best(np.arange(5), scores, [9, 8], np.random.default_rng(s))
            for s in range(50)} == {1}  # the recent cells were emptied: the best


def test_exploit_never_draws_an_elite_no_step_of_the_chain_made():
    """A warm start's elites are in the archive before the chain: they have no score."""
    archive, emitter, scheduler = lone_chain(dim=2)
    archive.add(np.array([[5.0, 5.0], [6.0, 6.0], [7.0, 7.0]]), np.array([50.0, 60.0, 70.0]),
                np.array([[0.9, 0.9], [0.8, 0.8], [0.7, 0.7]]))
    emitter.es_point()
    tell(scheduler, 1.0, [0.1, 0.1])  # x0, the chain's one cell (4 cells: the best is drawn)
    assert np.array_equal(emitter.es_point(), np.ones(2)) and not emitter.explore


def ranged_chain(seed=4):
    """An ME-ES chain on an archive whose measures span [-1, 1] and [0, 10]."""
    archive = GridArchive(solution_dim=2, dims=[4, 5], ranges=[(-1, 1), (0, 10)])
    emitter = me_es.MEESEmitter(archive, x0=np.zeros(2), batch_size=1, seed=seed)
    return archive, emitter, Scheduler(archive, [emitter])


def test_exploring_steps_on_the_samples_novelty_among_the_offspring_in_scaled_measures():
    archive, emitter, scheduler = ranged_chain()
    emitter.es_point()
    for objective, measures in ((1.0, [-0.5, 2.0]), (2.0, [0.5, 8.0])):
        tell(scheduler, objective, measures)
    scaled = np.array([[0.25, 0.2], [0.75, 0.8]])  # (m - low) / (high - low), by hand
    assert np.allclose(emitter.offspring, scaled)
    emitter.explore, emitter.steps = True, 1  # in an explore phase, between parents
    theta = emitter.opt.theta.copy()
    eps = np.array([[1.0, 0.0], [0.0, 1.0]])
    measures = np.array([[-1.0, 0.0], [0.9, 9.0], [0.0, 5.0], [1.0, 10.0]])
    emitter.es_step(np.array([1.0, 9.0, 5.0, 3.0]), measures, eps)  # ranked apart from novelty
    against = emitter.offspring
    novelties = [hand_novelty((m - [-1, 0]) / [2, 10], against) for m in measures]
    assert np.allclose(emitter.opt.theta, hand_adam(theta, [me_es.es_gradient(np.array(novelties), eps)]))
    assert emitter.step_best == 9.0


def test_a_cell_takes_the_best_sample_return_of_the_step_that_made_or_improved_it():
    archive, emitter, scheduler = ranged_chain()
    emitter.es_point()
    tell(scheduler, 1.0, [-0.9, 1.0])  # x0: its own return, a new cell
    first = int(archive.index_of(np.array([[-0.9, 1.0]]))[0])
    assert emitter.best_train == {first: 1.0} and emitter.discovered == [first]
    for step_best, objective, measures, status in ((7.0, 0.5, [-0.9, 1.0], 0), (8.0, 3.0, [-0.9, 1.0], 1),
                                                   (6.0, 2.0, [0.9, 9.0], 2)):
        emitter.step_best = step_best
        tell(scheduler, objective, measures)
        cell = int(archive.index_of(np.array([measures]))[0])
        assert emitter.best_train.get(cell) == ({0: 1.0, 1: 8.0, 2: 6.0}[status])
        assert emitter.discovered[-1] == cell and len(emitter.discovered) == (1 if status < 2 else 2)


@pytest.mark.parametrize("seed", range(12))
def test_a_new_parent_is_drawn_as_dqd_rl_draws_it_with_the_chains_own_generator(seed):
    archive, emitter, scheduler = ranged_chain(seed=seed)
    emitter.es_point()
    rng = np.random.default_rng(100 + seed)
    for _ in range(16):
        emitter.opt.reset(rng.normal(size=2))  # each offspring a solution of its own
        tell(scheduler, float(rng.normal()), [rng.uniform(-1, 1), rng.uniform(0, 10)])
        emitter.step_best = float(rng.normal())
    assert len({tuple(solution) for solution in archive.data("solution")}) == len(archive) > 5
    elites = archive.data(["index", "measures", "solution"])
    twin = np.random.default_rng(seed)  # the emitter's generator, drawn from here as it will be
    emitter.explore = False  # so that the draw below explores
    emitter.steps = 0
    drawn = emitter.es_point()
    scaled = (elites["measures"] - [-1, 0]) / [2, 10]
    novelties = [hand_novelty(m, emitter.offspring, skip_self=True) for m in scaled]
    expected = elites["solution"][twin.choice(len(novelties), p=hand_weights(novelties))]
    assert emitter.explore and np.array_equal(drawn, expected)
    scores = np.array([emitter.best_train[int(cell)] for cell in elites["index"]])
    emitter.steps, emitter.explore = 0, True  # so that the next draw exploits
    chosen = me_es.best_recent_or_best(elites["index"], scores, emitter.discovered, twin)
    expected = elites["solution"][chosen]
    assert np.array_equal(emitter.es_point(), expected) and not emitter.explore


@pytest.mark.slow  # a Hopper search killed and resumed, and its uninterrupted twin
def test_me_es_killed_mid_chain_then_resumed_ends_as_its_uninterrupted_twin(tmp_path, dask_cluster,
                                                                            one_worker_cluster):
    """kill -9 past a checkpoint, in a chain's first phase; resumed on one worker, through the
    change of parent and phase (Adam's moments, the draws, the novelty set: all in the checkpoint),
    it ends bit for bit as the run that never stopped on two."""
    flags = dict(algorithm="me_es", env="Hopper-v5", policy="mlp", hidden="4", episode_length=20,
                 es_samples=6, n_emitters=2, iterations=14, log_every=1, pictures="false")
    assert_killed_then_resumed_as_its_twin(tmp_path, dask_cluster, one_worker_cluster, flags)


def test_a_folded_network_acts_on_raw_observations_as_its_theta_on_normalised_ones():
    from qdsearch.tasks.policies import Policy

    policy, shape = Policy("mlp", (5, 4)), (3, 7)  # 3 actions, 7 observations
    rng = np.random.default_rng(6)
    theta = rng.normal(size=policy.size(shape))
    mean, std = rng.normal(size=7), rng.uniform(0.1, 3.0, size=7)
    folded = me_es.fold(theta[None], (5, 7), mean, std)[0]
    raw = rng.normal(size=(20, 7)) * 4
    on_raw = policy.act(folded, shape, True)
    on_normalised = policy.act(theta, shape, True)
    assert np.allclose([on_raw(obs) for obs in raw], [on_normalised((obs - mean) / std) for obs in raw])
    assert np.allclose(me_es.unfold(folded, (5, 7), mean, std), theta)
    assert np.array_equal(me_es.fold(theta[None], (5, 7), np.zeros(7), np.ones(7))[0], theta)  # at first
    thetas = rng.normal(size=(3, policy.size(shape)))  # a chain's samples: row by row
    assert np.array_equal(me_es.fold(thetas, (5, 7), mean, std),
                          np.concatenate([me_es.fold(row[None], (5, 7), mean, std) for row in thetas]))


def test_a_networks_chain_counts_the_observations_of_its_collected_negative_samples(monkeypatch):
    archive = GridArchive(solution_dim=5 * (2 + 1) + 1 * (5 + 1), dims=[4, 4], ranges=[(0, 1), (0, 1)])
    x0 = np.random.default_rng(4).normal(size=archive.solution_dim)
    chain = me_es.MEESEmitter(archive, x0=x0, batch_size=1, seed=2, first_layer=(5, 2))
    linear = me_es.MEESEmitter(archive, x0=np.zeros(4), batch_size=1, seed=2)
    assert len(linear.collecting(10)) == 0 and len(chain.collecting(1000)) < 10  # 0.1% of 500
    monkeypatch.setattr(me_es, "OBS_COLLECT_PROB", 0.5)  # which ones: the chain's seed says
    twins = [me_es.MEESEmitter(archive, x0=np.zeros(archive.solution_dim), batch_size=1, seed=seed,
                               first_layer=(5, 2)).collecting(200).tolist() for seed in (2, 2, 3)]
    assert twins[0] == twins[1] != twins[2] and all(100 <= i < 200 for i in twins[0])
    monkeypatch.setattr(me_es, "OBS_COLLECT_PROB", 1.0)
    assert chain.collecting(10).tolist() == [5, 6, 7, 8, 9]  # every negative sample
    observations = np.random.default_rng(3).normal(size=(50, 2)) * [1.0, 0.01] + [3.0, -1.0]
    scheduler = Scheduler(archive, [chain])
    chain.observe(observations)
    assert np.array_equal(chain.normaliser()[0], [0, 0])  # counted only once the offspring is told
    tell(scheduler, 1.0, [0.5, 0.5])
    count = len(observations) + 1e-2  # dqd-rl's RunningStat: its sums start at 0, 0.01, 0.01
    mean = observations.sum(axis=0) / count
    variance = (np.sum(observations ** 2, axis=0) + 1e-2) / count - mean ** 2
    assert np.allclose(chain.normaliser()[0], mean)
    assert np.allclose(chain.normaliser()[1], np.sqrt(np.maximum(variance, 1e-2)))  # the floor: the 2nd
    assert chain.normaliser()[1][1] == 0.1 and chain.observed is None
    stored = archive.data("solution")[0]  # the offspring as flown: theta folded (at the first
    assert np.array_equal(stored, x0)  # statistics, theta itself)
    chain.steps, chain.explore = 0, True  # a new parent: the theta that folds back to the stored
    theta = chain.es_point()
    assert np.array_equal(theta, me_es.unfold(stored, (5, 2), *chain.normaliser()))
    assert not np.allclose(theta, stored)
    assert np.allclose(chain.ask()[0], stored) and not np.allclose(chain.normaliser()[1], 1.0)


@pytest.mark.slow  # small Hopper searches whose every negative sample is observed
def test_a_normalising_me_es_run_is_exact_on_one_and_two_workers_and_flies_what_it_stored(
        tmp_path, dask_cluster, one_worker_cluster, monkeypatch):
    import qdsearch

    monkeypatch.setattr(me_es, "OBS_COLLECT_PROB", 1.0)  # the driver flies the search's own
    flags = dict(algorithm="me_es", env="Hopper-v5", policy="mlp", hidden="4", episode_length=20,
                 es_samples=4, n_emitters=1, iterations=4)
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "two"))
    one = tmp_path / "one"
    commands.search(**tiny_flags(one_worker_cluster, **{**flags, "iterations": 2}), outdir=str(one))
    commands.resume(str(one), iterations=4, scheduler_address=one_worker_cluster.scheduler_address)
    assert run_archive(tmp_path / "one").equals(run_archive(tmp_path / "two"))
    assert run_metrics(tmp_path / "one") == run_metrics(tmp_path / "two")
    from util import read_checkpoint

    [chain] = read_checkpoint(tmp_path / "two" / "checkpoint.pkl")["scheduler"].emitters
    # 3 steps x 2 negative samples, each episode up to 20 steps (a Hopper may fall sooner)
    assert 1e-2 + 3 * 2 * 5 <= chain.obs_count <= 1e-2 + 3 * 2 * 20
    assert not np.allclose(chain.normaliser()[1], 1.0)
    run = qdsearch.read_run(tmp_path / "two")
    for row in range(len(run.archive)):  # each stored network flies to its stored numbers
        flight = qdsearch.fly_elite(run, row)
        assert flight.objective == run.archive["objective"].iloc[row]
