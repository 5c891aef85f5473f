"""The algorithm table: the tutorial's CMA-ME, CMA-MAE and MAP-Elites, their setups, complete run
folders, resume and warm starts for each, and the `compare` command."""

import csv
import json
import pickle

import numpy as np
import pytest
from ribs.archives import DensityArchive, DNSArchive, GridArchive, ProximityArchive
from ribs.emitters import (
    EvolutionStrategyEmitter,
    GaussianEmitter,
    GradientArborescenceEmitter,
    IsoLineEmitter,
)
from ribs.emitters.opt import LMMAEvolutionStrategy, SeparableCMAEvolutionStrategy
from ribs.emitters.rankers import (
    DensityRanker,
    ImprovementRanker,
    NoveltyRanker,
    NSLCRanker,
    ObjectiveRanker,
    TwoStageImprovementRanker,
    TwoStageRandomDirectionRanker,
)
from ribs.schedulers import BanditScheduler, Scheduler

from qdsearch import algorithms, tasks
from qdsearch.algorithms.pga_me import PGAMEEmitter
from qdsearch.cli import commands
from qdsearch.config import options, run_config
from qdsearch.search.learning import Learning
from util import (
    archive_table,
    assert_one_line_error,
    read_checkpoint,
    run_archive,
    run_metrics,
    saved_archive,
    tiny_flags,
    write_checkpoint,
)

# Every row that flies episodes: a run folder each, and their resumes (the rows of exact gradients
# run on the benchmark functions alone: tests/test_functions.py)
ALGORITHMS = [name for name, row in algorithms.ALGORITHMS.items() if not row.exact]
RUN_FILES = {"config.json", "checkpoint.pkl", "archive.csv", "metrics.json",
             "heatmap.png", "progress.png", "run.log"}


CONFIG = run_config.check_run_config(options.with_task(dict(
    options.search_defaults(), algorithm="cma_me", seed=3, n_emitters=5, sigma0=1.0, batch_size=30,
    measures=list(tasks.TUTORIAL_MEASURES), grid=50)))


def test_cma_me_is_the_tutorial_setup():
    scheduler = algorithms.build_scheduler(CONFIG)
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
    first = algorithms.build_scheduler(CONFIG).ask()
    again = algorithms.build_scheduler(CONFIG).ask()
    other = algorithms.build_scheduler(CONFIG.replace(seed=4)).ask()

    assert np.array_equal(first, again)
    assert not np.array_equal(first, other)
    per_emitter = first.reshape(5, 30, 32)
    assert not np.array_equal(per_emitter[0], per_emitter[1])  # each emitter has its own seed


def algorithm_flags(dask_cluster, algorithm, **overrides):
    """The tiny run's flags for 2 iterations of `algorithm` (a DQD row: 4 gradient samples; a
    learning row: the lander of continuous actions)."""
    row = algorithms.ALGORITHMS[algorithm]
    dqd = {"es_samples": 4} if row.samples else {}
    box = {"env": CONTINUOUS} if row.learns else {}
    return tiny_flags(dask_cluster, **{"algorithm": algorithm, "iterations": 2, **dqd, **box, **overrides})


CONTINUOUS = "LunarLanderContinuous-v3"


def told_gradients(scheduler, rng, lower, upper):
    """A DQD scheduler's points told made-up values and gradients (ask_dqd, tell_dqd), so that its
    ask branches; the points' shape."""
    points = scheduler.ask_dqd()
    count = len(points)
    scheduler.tell_dqd(rng.uniform(-100, 100, count), rng.uniform(lower, upper, (count, len(lower))),
                       rng.normal(size=(count, 1 + len(lower), points.shape[1])))
    return points.shape


def next_asks(scheduler, dqd: bool) -> np.ndarray:
    """What a scheduler asks first in its next iteration."""
    return scheduler.ask_dqd() if dqd else scheduler.ask()


class TinyRuns(dict):
    """A 2-iteration run folder of each algorithm, with its pictures, made when a test first asks
    for it."""

    def __init__(self, root, cluster) -> None:
        super().__init__()
        self.root, self.cluster = root, cluster

    def __missing__(self, algorithm: str):
        commands.search(**algorithm_flags(self.cluster, algorithm, pictures=True),
                   outdir=str(self.root / algorithm))
        self[algorithm] = self.root / algorithm
        return self[algorithm]


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory, dask_cluster):
    return TinyRuns(tmp_path_factory.mktemp("algorithms"), dask_cluster)


# The tutorial's three in the quick subset; pyribs' other rows in the whole suite.
QUICK = ("cma_me", "cma_mae", "map_elites")
EVERY_ROW = [name if name in QUICK else pytest.param(name, marks=pytest.mark.slow) for name in ALGORITHMS]


def test_each_algorithm_is_its_pyribs_setup_with_the_same_batch():
    config = CONFIG.replace(learning_rate=0.01)
    schedulers = {name: algorithms.build_scheduler(config.replace(algorithm=name)) for name in ALGORITHMS}

    mae = schedulers["cma_mae"]
    assert mae.archive.learning_rate == 0.01 and mae.archive.threshold_min == -600
    assert isinstance(mae.result_archive, GridArchive) and mae.result_archive is not mae.archive
    assert mae.result_archive.learning_rate == 1.0
    assert tuple(mae.result_archive.dims) == (50, 50) and mae.result_archive.qd_score_offset == -600
    for emitter in mae.emitters:
        assert isinstance(emitter, EvolutionStrategyEmitter) and emitter.archive is mae.archive
        assert type(emitter._ranker) is ImprovementRanker
        assert emitter._restart_rule == "basic" and emitter._selection_rule == "mu"
    me = schedulers["cma_me"]
    assert me.result_archive is me.archive
    assert all(type(e._ranker) is TwoStageImprovementRanker for e in me.emitters)
    elites = schedulers["map_elites"]
    assert elites.result_archive is elites.archive
    assert all(isinstance(e, GaussianEmitter) and np.all(e.sigma == 1.0) for e in elites.emitters)
    line = schedulers["line_map_elites"]  # pyribs' sphere.py rows, with our step sizes
    assert all(isinstance(e, IsoLineEmitter) and np.all(e.iso_sigma == 1.0)
               and np.all(e.line_sigma == 0.2) for e in line.emitters)
    assert all(e._selection_rule == "mu" and type(e._ranker) is TwoStageImprovementRanker
               for e in schedulers["cma_me_mu"].emitters)
    assert all(type(e._ranker) is TwoStageRandomDirectionRanker for e in schedulers["cma_me_rd"].emitters)
    scalable_rows = (("sep_cma_mae", SeparableCMAEvolutionStrategy), ("lm_ma_mae", LMMAEvolutionStrategy))
    for name, es in scalable_rows:
        scalable = schedulers[name]
        assert scalable.archive.learning_rate == 0.01 and scalable.result_archive is not scalable.archive
        assert all(type(e._opt) is es and type(e._ranker) is ImprovementRanker for e in scalable.emitters)
        # CMA-MAE's own selection and restart, with only the ES changed (Tjanaka et al. 2023)
        assert all(e._selection_rule == "mu" and e._restart_rule == "basic" for e in scalable.emitters)
    bandit = schedulers["me_map_elites"]  # a pool of 4 kinds x 5, 5 of them active
    assert isinstance(bandit, BanditScheduler) and len(bandit.emitter_pool) == 20
    assert [type(e._ranker) for e in bandit.emitter_pool[:15:5]] == [
        ObjectiveRanker, TwoStageRandomDirectionRanker, TwoStageImprovementRanker]
    assert all(isinstance(e, IsoLineEmitter) and np.all(e.iso_sigma == 0.02) and np.all(e.line_sigma == 0.1)
               for e in bandit.emitter_pool[15:])
    span = 2.5  # the mean width of x in [-1, 1] and y-velocity in [-3, 0]
    for name, ranker, competes in (("ns_cma", NoveltyRanker, False), ("nslc", NSLCRanker, True)):
        novelty = schedulers[name]
        assert isinstance(novelty.archive, ProximityArchive) and novelty.archive.k_neighbors == 15
        assert novelty.archive.novelty_threshold == pytest.approx(0.037 * span)
        assert novelty.archive.local_competition is competes
        assert isinstance(novelty.result_archive, GridArchive)
        assert all(type(e._ranker) is ranker and e.archive is novelty.archive for e in novelty.emitters)
    dns = schedulers["dns"]
    assert isinstance(dns.archive, DNSArchive) and dns.archive.capacity == 2500
    assert all(isinstance(e, IsoLineEmitter) and e.archive is dns.archive for e in dns.emitters)
    dds = schedulers["dds"]
    assert isinstance(dds.archive, DensityArchive) and dds.archive._bandwidth == pytest.approx(0.05 * span)
    assert all(type(e._ranker) is DensityRanker and e.archive is dds.result_archive and e._sigma0 == 3.0
               for e in dds.emitters)
    for name in ("cma_mega_es", "cma_maega_es"):  # dqd-rl's CMA-MEGA (ES); sphere.py's cma_maega
        dqd = schedulers[name]
        assert all(isinstance(e, GradientArborescenceEmitter)
                   and type(e._grad_opt).__name__ == "GradientAscentOpt" for e in dqd.emitters)
    assert all(e._selection_rule == "mu" for e in schedulers["cma_mega_es"].emitters)
    assert schedulers["cma_maega_es"].archive.learning_rate == 0.01
    assert all(type(e._ranker) is ImprovementRanker for e in schedulers["cma_maega_es"].emitters)
    pga = schedulers["pga_me"]  # dqd-rl's PGA-ME: iso+line (--sigma0, --line_sigma) for the larger half
    assert all(isinstance(e, PGAMEEmitter) and e.batch_size == 30 and e.genetic.batch_size == 15
               and np.all(e.genetic.iso_sigma == 1.0) and np.all(e.genetic.line_sigma == 0.2)
               and e.genetic.archive is pga.archive for e in pga.emitters)
    td3_es = schedulers["cma_mega_td3_es"]  # CMA-MEGA (ES)'s emitters, the critic's objective gradient
    assert all(isinstance(e, GradientArborescenceEmitter) and e._selection_rule == "mu"
               for e in td3_es.emitters)
    assert algorithms.ALGORITHMS["cma_mega_td3_es"].learns.objective_gradient
    rng = np.random.default_rng(0)
    for name, scheduler in schedulers.items():
        if algorithms.ALGORITHMS[name].dqd:
            assert told_gradients(scheduler, rng, [-1, -3], [1, 0]) == (5, 32)
        batch = 1 if algorithms.ALGORITHMS[name].es_steps else 30  # ME-ES: one offspring a chain
        assert scheduler.ask().shape == (5 * batch, 32)
    assert sum(bandit.active) == 5


@pytest.mark.parametrize("env", list(tasks.ENVIRONMENTS))
def test_every_row_asks_and_tells_on_every_task(env):
    """Each row's objects fit each task: its solution size, measures and archive kind (a learning
    row's, each task of continuous actions, with its learner)."""
    for name, row in algorithms.ALGORITHMS.items():
        if row.learns and not tasks.ENVIRONMENTS[env].continuous:
            continue  # refused (tests/test_learning.py)
        if row.es_steps and tasks.ENVIRONMENTS[env].function:
            continue  # ME-ES on a benchmark function: refused (tests/test_functions.py)
        if row.exact and not tasks.ENVIRONMENTS[env].function:
            continue  # exact gradients on an episode: refused (tests/test_functions.py)
        cells = {"cells": 64} if tasks.ENVIRONMENTS[env].archive == "cvt" else {}  # k-means: quick
        config = run_config.check_run_config(options.with_task(dict(
            options.search_defaults(), algorithm=name, env=env, seed=3, n_emitters=2, batch_size=3, **cells)))
        scheduler = algorithms.build_scheduler(config)
        Learning.of(config, scheduler)  # hands a learning row's emitters their learner
        rng = np.random.default_rng(0)
        for _ in range(2):
            lower, upper = np.array(algorithms.archive_shape(config)["ranges"]).T
            if algorithms.ALGORITHMS[name].dqd:
                shape = told_gradients(scheduler, rng, lower, upper)
                assert shape == (2, tasks.ENVIRONMENTS[env].solution_dim)
            solutions = scheduler.ask()
            count = 2 if algorithms.ALGORITHMS[name].es_steps else 6  # ME-ES: one offspring a chain
            assert solutions.shape == (count, tasks.ENVIRONMENTS[env].solution_dim)
            scheduler.tell(rng.uniform(-100, 100, count), rng.uniform(lower, upper, (count, len(lower))))
        assert len(scheduler.result_archive) > 0


@pytest.mark.parametrize("algorithm", EVERY_ROW)
def test_each_algorithm_writes_a_complete_run_folder(tiny_runs, algorithm):
    run_dir = tiny_runs[algorithm]
    assert RUN_FILES <= {p.name for p in run_dir.iterdir()}
    assert [p.name for p in (run_dir / "heatmaps").iterdir()] == ["heatmap_00002.png"]
    metrics = run_metrics(run_dir)
    assert [row["iteration"] for row in metrics] == [1, 2]
    row = algorithms.ALGORITHMS[algorithm]
    spent = 12 + (2 * (1 + 4) if row.dqd else 0) + bool(row.learns)  # a DQD row's points, samples; an actor
    # ME-ES: x0 alone on each of its 2 chains, then each chain's 4 samples and offspring
    assert [row["evaluations"] for row in metrics] == ([2, 2 + 2 * (1 + 4)] if algorithms.ALGORITHMS[
        algorithm].es_steps else [spent, 2 * spent])
    assert json.loads((run_dir / "config.json").read_text())["algorithm"] == algorithm
    checkpoint = read_checkpoint(run_dir / "checkpoint.pkl")
    assert checkpoint["config"]["algorithm"] == algorithm
    assert 0 < metrics[-1]["num_elites"] == len(saved_archive(run_dir))


def test_cma_mae_saves_and_measures_its_result_archive(tiny_runs):
    run_dir = tiny_runs["cma_mae"]
    scheduler = read_checkpoint(run_dir / "checkpoint.pkl")["scheduler"]
    saved = saved_archive(run_dir)

    assert saved.learning_rate == 1.0  # the result archive, not the soft archive
    assert archive_table(saved).equals(archive_table(scheduler.result_archive))
    result_qd_score = float(scheduler.result_archive.stats.qd_score)
    assert run_metrics(run_dir)[-1]["qd_score"] == pytest.approx(result_qd_score)
    # The soft archive keeps later, worse solutions that passed a threshold: the best are elsewhere.
    assert scheduler.archive.learning_rate == options.search_defaults()["learning_rate"]
    assert saved.stats.obj_max >= scheduler.archive.stats.obj_max


@pytest.mark.slow  # a resume or warm start per algorithm: the whole suite has them
@pytest.mark.parametrize("algorithm", [name for name in ALGORITHMS if name != "cma_me"])
def test_stopped_then_resumed_on_one_worker_equals_uninterrupted_on_two(tmp_path, dask_cluster, tiny_runs,
                                                                       algorithm, one_worker_cluster):
    run_dir = tmp_path / "run"
    commands.search(**algorithm_flags(dask_cluster, algorithm, iterations=1), outdir=str(run_dir))
    commands.resume(str(run_dir), iterations=2, scheduler_address=one_worker_cluster.scheduler_address)

    reference = tiny_runs[algorithm]
    assert run_archive(run_dir).equals(run_archive(reference))
    assert run_metrics(run_dir) == run_metrics(reference)
    checkpoints = [read_checkpoint(d / "checkpoint.pkl") for d in (run_dir, reference)]
    schedulers = [checkpoint["scheduler"] for checkpoint in checkpoints]
    if algorithms.ALGORITHMS[algorithm].learns:  # the learner, its buffer: the same; handed to the emitters
        saved = [checkpoint["learning"] for checkpoint in checkpoints]
        assert np.array_equal(saved[0]["buffer"]["rows"], saved[1]["buffer"]["rows"])
        assert pickle.dumps(saved[0]["learner"]) == pickle.dumps(saved[1]["learner"])
        for checkpoint in checkpoints:
            Learning.of(run_config.check_run_config(checkpoint["config"]), checkpoint["scheduler"],
                        checkpoint["learning"])
    dqd = algorithms.ALGORITHMS[algorithm].dqd
    assert np.array_equal(next_asks(schedulers[0], dqd), next_asks(schedulers[1], dqd))
    assert archive_table(schedulers[0].archive).equals(archive_table(schedulers[1].archive))


@pytest.mark.slow  # a resume or warm start per algorithm: the whole suite has them
@pytest.mark.parametrize("algorithm", ["cma_mae", "map_elites"])
def test_warm_start_fills_every_archive(tmp_path, dask_cluster, tiny_runs, algorithm):
    source = tiny_runs["cma_me"] / "archive.npz"
    run_dir = tmp_path / "warm"
    commands.search(**algorithm_flags(dask_cluster, algorithm, iterations=1),
              outdir=str(run_dir), from_archive=str(source))

    elites = len(saved_archive(tiny_runs["cma_me"]))
    metrics = run_metrics(run_dir)
    assert metrics[0]["iteration"] == 0 and metrics[0]["evaluations"] == elites
    assert metrics[0]["num_elites"] == elites  # same terrain, same grid: every elite lands again
    scheduler = read_checkpoint(run_dir / "checkpoint.pkl")["scheduler"]
    assert len(scheduler.archive) >= elites and len(scheduler.result_archive) >= elites


@pytest.mark.parametrize("algorithm", ["cma_mae", "map_elites", "me_es"])
def test_results_commands_work_for_every_algorithm(tmp_path, tiny_runs, algorithm):
    import shutil

    run_dir = tmp_path / algorithm
    shutil.copytree(tiny_runs[algorithm], run_dir)
    best = saved_archive(run_dir).best_elite

    commands.video(str(run_dir), best=True)
    commands.elites(str(run_dir), top=3)

    with open(run_dir / "videos" / "index.csv") as file:
        [row] = list(csv.DictReader(file))
    assert float(row["objective"]) == best["objective"] and row["reproduced"] == "True"
    assert (run_dir / "videos" / row["video"]).stat().st_size > 1000
    with open(run_dir / "elites.csv") as file:
        assert float(next(csv.DictReader(file))["objective"]) == best["objective"]


def test_checkpoint_from_before_learning_rate_still_resumes(tmp_path, tiny_runs):
    checkpoint = read_checkpoint(tiny_runs["cma_me"] / "checkpoint.pkl")
    del checkpoint["config"]["learning_rate"]
    write_checkpoint(tmp_path / "checkpoint.pkl", checkpoint)

    assert run_config.load_checkpoint(tmp_path / "checkpoint.pkl")["config"].learning_rate == 0.01


def test_unknown_algorithm_and_bad_learning_rate_are_one_line_errors(run_cli, tmp_path):
    result = run_cli("--algorithm", "cma_es", "--outdir", tmp_path / "run")
    assert_one_line_error(result, "--algorithm", "cma_es", "did you mean cma_me?")
    for value in (0, 1.5, "fast"):
        assert_one_line_error(run_cli("--algorithm", "cma_mae", f"--learning_rate={value}", "--outdir",
                                      tmp_path / "run"),
                              "--learning_rate", "(0, 1]")
    assert not (tmp_path / "run").exists()
