"""The algorithm: the tutorial's archive, emitters and scheduler, seeded from one run seed."""

import numpy as np
from ribs.archives import GridArchive
from ribs.emitters import EvolutionStrategyEmitter
from ribs.emitters.rankers import TwoStageImprovementRanker
from ribs.schedulers import Scheduler

import lunar_lander as ll

CONFIG = dict(algorithm="cma_me", seed=3, n_emitters=5, sigma0=1.0, batch_size=30)


def test_cma_me_is_the_tutorial_setup():
    scheduler = ll.build_scheduler(CONFIG)
    archive = scheduler.archive

    assert isinstance(scheduler, Scheduler)
    assert isinstance(archive, GridArchive)
    assert tuple(archive.dims) == (50, 50)
    assert np.allclose(archive.lower_bounds, [-1, -3]) and np.allclose(archive.upper_bounds, [1, 0])
    assert archive.qd_score_offset == -600
    assert archive.solution_dim == 32
    assert len(scheduler.emitters) == 5
    for emitter in scheduler.emitters:
        assert isinstance(emitter, EvolutionStrategyEmitter)
        assert isinstance(emitter._ranker, TwoStageImprovementRanker)
        assert emitter.batch_size == 30
        assert emitter.archive is archive
        assert np.array_equal(emitter.x0, np.zeros(32))
        assert emitter._sigma0 == 1.0


def test_seed_fixes_the_proposals_and_emitters_differ():
    first = ll.build_scheduler(CONFIG).ask()
    again = ll.build_scheduler(CONFIG).ask()
    other = ll.build_scheduler({**CONFIG, "seed": 4}).ask()

    assert np.array_equal(first, again)
    assert not np.array_equal(first, other)
    per_emitter = first.reshape(5, 30, 32)
    assert not np.array_equal(per_emitter[0], per_emitter[1])  # each emitter has its own seed
