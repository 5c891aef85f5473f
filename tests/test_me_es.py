"""ME-ES (qdsearch/algorithms/me_es.py) held against dqd-rl's rules computed here by hand: the
novelty, the ES gradient and Adam step, the draws of a parent, the schedule of phases; and a
Hopper MLP run that is the same on 1 and 2 workers."""

import numpy as np
import pytest
from ribs.archives import GridArchive
from ribs.schedulers import Scheduler

from qdsearch.algorithms import me_es
from qdsearch.cli import commands
from util import run_archive, run_metrics, tiny_flags


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
    emitter = me_es.MEESEmitter(archive, x0=np.ones(dim), batch_size=1, seed=seed, sigma=0.02)
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


@pytest.mark.slow  # two small Hopper searches
def test_me_es_on_hopper_with_an_mlp_is_the_same_on_one_and_two_workers(tmp_path, dask_cluster,
                                                                        one_worker_cluster):
    flags = dict(algorithm="me_es", env="Hopper-v5", policy="mlp", hidden="4", episode_length=20,
                 es_samples=6, n_emitters=2, iterations=3)
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(tmp_path / "two"))
    commands.search(**tiny_flags(one_worker_cluster, **flags), outdir=str(tmp_path / "one"))
    assert run_archive(tmp_path / "two").equals(run_archive(tmp_path / "one"))
    metrics = run_metrics(tmp_path / "one")
    assert [row["evaluations"] for row in metrics] == [2, 2 + 14, 2 + 28]  # x0s, then 6 samples + 1
    assert metrics == run_metrics(tmp_path / "two") and metrics[-1]["num_elites"] > 0
