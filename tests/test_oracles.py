"""An independent oracle for every number that `compare` and metrics.json report (issue 45): each
test computes a figure another way on a small case (plain loops and numpy over the values put in,
pyribs' or scipy's own function called directly) and compares values, exactly or to 1e-12 where
the arithmetic runs in another order.

The archives are real pyribs archives made by the project's builders (algorithms.py) and filled
with hand-chosen elites; the statistics' intervals are recomputed from the same seeded draws
(stats.SEED, A's tasks then B's from one generator) with a loop per resample.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pandas as pd
import pytest
from ribs.archives import cqd_score
from scipy.stats import bootstrap, mannwhitneyu

from qdsearch import algorithms, tasks
from qdsearch.analysis import comparison, evaluation, stats
from qdsearch.base.run_files import write_csv
from qdsearch.config import options, run_config
from qdsearch.store import metrics

TOL = 1e-12  # where the oracle adds in another order than the code
LANDER = "LunarLander-v3"
OFFSET, OBJECTIVE_MAX = -600.0, 350.0  # the lander's QD offset and CQD top (lander.py, family.py)
LOWER, UPPER = np.array([-1.0, -3.0]), np.array([1.0, 0.0])  # impact_x, impact_y_velocity
GRID = 4  # cells along each measure of the small grid
CELLS = {"grid": GRID * GRID, "cvt": 8}
SOLUTION_DIM = 32  # the lander's 4 x 8 weights

# Hand-chosen elites (objective, measures), added in two batches: in the grid, 150.5 beats -20.25
# in its cell and is then replaced by 250.0; 10.0 loses to 300.75; -650.0 (below the QD offset:
# it counts -50) is replaced by -300.0; exactly 200.0 solves the lander, 199.75 does not.
BATCHES: list[list[tuple[float, tuple[float, float]]]] = [
    [(150.5, (-0.9, -2.9)), (-20.25, (-0.85, -2.8)), (300.75, (0.3, -0.1)), (-650.0, (0.9, -1.6)),
     (-100.5, (-0.1, -1.2)), (200.0, (0.6, -2.0)), (199.75, (-0.6, -0.4))],
    [(10.0, (0.35, -0.2)), (250.0, (-0.95, -2.95)), (-300.0, (0.8, -1.7)), (420.5, (0.1, -1.0)),
     (-5.5, (-0.3, -0.6))],
]
Elites = dict[int, tuple[float, tuple[float, ...]]]  # cell: (objective, measures) of its elite
Maker = Callable[[str], Any]  # an empty real archive of a kind ("grid", "cvt")


def close(value: Any, expected: Any) -> bool:
    """Equal to TOL (relative or absolute), NaN equal to NaN."""
    return value == pytest.approx(expected, rel=TOL, abs=TOL, nan_ok=True)


def lander_config(kind: str, algorithm: str = "cma_me", **flags: Any):
    """A checked RunConfig of the lander on its two tutorial measures: a 4 x 4 grid, or 8 CVT cells."""
    size = {"grid": GRID} if kind == "grid" else {"archive": "cvt", "cells": CELLS["cvt"], "grid": None}
    return run_config.check_run_config(options.with_task(
        {**options.search_defaults(), "algorithm": algorithm, "seed": 3, **size, **flags}))


@pytest.fixture(scope="module")
def make_archive() -> Maker:
    """Empty archives of the grid run and of the CVT run, as the project's builders make them
    (ARCHIVES[kind]["make"], whose CVT centroids come from k-means once per run)."""
    makers = {kind: algorithms.ARCHIVES[kind]["make"](lander_config(kind)) for kind in CELLS}
    return lambda kind: makers[kind](seed=1)


def hand_cell(kind: str, archive: Any, measures: Sequence[float]) -> int:
    """The cell a point falls in, computed here: a grid's row-major index of each measure's
    interval, or the CVT's nearest centroid by Euclidean distance."""
    if kind == "grid":
        index = [min(GRID - 1, max(0, math.floor((m - lo) / (hi - lo) * GRID)))
                 for m, lo, hi in zip(measures, LOWER, UPPER)]
        return index[0] * GRID + index[1]
    distances = [math.dist(measures, centroid) for centroid in archive.centroids.tolist()]
    return distances.index(min(distances))


def fill(kind: str, archive: Any, batches=BATCHES) -> Elites:
    """Add the hand-chosen batches to `archive`; the elites it must then hold, by a loop: in each
    cell, the first solution, replaced only by a strictly better one."""
    best: Elites = {}
    for batch in batches:
        solutions = np.arange(len(batch) * SOLUTION_DIM, dtype=float).reshape(len(batch), SOLUTION_DIM)
        archive.add(solutions, np.array([obj for obj, _ in batch]), np.array([m for _, m in batch]))
        for objective, measures in batch:
            cell = hand_cell(kind, archive, measures)
            if cell not in best or objective > best[cell][0]:
                best[cell] = (objective, measures)
    return best


def test_the_hand_values_are_the_lander_rows() -> None:
    """The constants the oracles use are the task's and the measures' (read once, here)."""
    task = tasks.ENVIRONMENTS[LANDER]
    assert (task.qd_offset, task.objective_max, task.solved) == (OFFSET, OBJECTIVE_MAX, 200.0)
    assert [tasks.MEASURES[m].range for m in task.measures] == list(zip(LOWER, UPPER))


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_iteration_metrics_are_the_hand_sums_of_the_elites(kind: str, make_archive: Maker) -> None:
    """QD score, coverage, num_elites, best and mean objective of metrics.json against sums over
    the elites that a loop says the archive keeps (plain Python over the values put in)."""
    archive = make_archive(kind)
    empty = metrics.iteration_metrics(archive, 0, 0, 0.0)
    assert (empty["coverage"], empty["num_elites"], empty["qd_score"]) == (0.0, 0, 0.0)
    assert empty["best_objective"] is None and empty["mean_objective"] is None

    best = fill(kind, archive)
    assert sorted(archive.data("index").tolist()) == sorted(best)  # the oracle's cells are pyribs'
    assert len(best) < sum(map(len, BATCHES))  # some solutions lost their cell: the oracle matters
    objectives = [objective for objective, _ in best.values()]
    row = metrics.iteration_metrics(archive, 7, 84, 1.23456)
    assert (row["iteration"], row["evaluations"], row["elapsed_s"]) == (7, 84, 1.235)
    assert row["num_elites"] == len(best)
    assert row["coverage"] == len(best) / CELLS[kind]
    assert close(row["qd_score"], math.fsum(objective - OFFSET for objective in objectives))
    assert row["best_objective"] == max(objectives)
    assert close(row["mean_objective"], math.fsum(objectives) / len(objectives))


def test_the_result_archive_of_cma_mae_is_measured_by_the_same_sums() -> None:
    """CMA-MAE's metrics come from its result archive (a plain copy of the run's): built by
    build_scheduler, filled by hand, summed by hand."""
    scheduler = algorithms.build_scheduler(lander_config("grid", "cma_mae"))
    assert scheduler.result_archive is not scheduler.archive
    best = fill("grid", scheduler.result_archive)
    row = metrics.iteration_metrics(scheduler.result_archive, 1, 12, 0.0)
    assert row["num_elites"] == len(best) and row["coverage"] == len(best) / CELLS["grid"]
    assert close(row["qd_score"], math.fsum(objective - OFFSET for objective, _ in best.values()))


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_an_empty_copy_keeps_the_cells_bounds_and_offset(kind: str, make_archive: Maker) -> None:
    """ARCHIVES[kind]["empty_like"] (evaluate's means and corrected archive): the same class,
    cells, bounds, grid or centroids and QD offset, empty; a QD score computed on it after adding
    elites is their hand sum minus the offset (not counted from 0)."""
    archive = make_archive(kind)
    fill(kind, archive)
    copy = algorithms.ARCHIVES[kind]["empty_like"](archive)
    assert type(copy) is type(archive) and copy is not archive and len(copy) == 0 and len(archive) > 0
    assert copy.qd_score_offset == archive.qd_score_offset == OFFSET
    assert copy.cells == archive.cells == CELLS[kind]
    assert (copy.solution_dim, copy.measure_dim) == (archive.solution_dim, archive.measure_dim) == (32, 2)
    assert np.array_equal(copy.lower_bounds, LOWER) and np.array_equal(copy.upper_bounds, UPPER)
    if kind == "grid":
        assert np.array_equal(copy.dims, archive.dims)
        assert all(np.array_equal(a, b) for a, b in zip(copy.boundaries, archive.boundaries))
    else:
        assert np.array_equal(copy.centroids, archive.centroids)
    best = fill(kind, copy, [BATCHES[1]])
    row = metrics.iteration_metrics(copy, 0, 0, 0.0)
    assert close(row["qd_score"], math.fsum(objective - OFFSET for objective, _ in best.values()))
    assert row["coverage"] == len(best) / CELLS[kind]


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_corrected_metrics_are_the_hand_means_of_the_flights(kind: str, make_archive: Maker) -> None:
    """evaluate --corrected's archive and corrected.json: each elite at its mean objective and
    mean measures over the new seeds (averaged by hand), in an empty archive of the run's cells."""
    archive = make_archive(kind)
    fill(kind, archive)
    rng = np.random.default_rng(4)
    solutions = rng.normal(size=(6, SOLUTION_DIM))
    flights = np.stack([rng.uniform([-700, -1, -3], [400, 1, 0], size=(3, 3)) for _ in solutions])
    corrected = evaluation.corrected_archive(archive, lander_config(kind), solutions, flights)
    means = [(math.fsum(f[:, 0]) / 3, (math.fsum(f[:, 1]) / 3, math.fsum(f[:, 2]) / 3)) for f in flights]
    best: Elites = {}
    for objective, measures in means:
        cell = hand_cell(kind, corrected, measures)
        if cell not in best or objective > best[cell][0]:
            best[cell] = (objective, measures)
    objectives = [objective for objective, _ in best.values()]
    run_row = {"iteration": 5, "evaluations": 60, "qd_score": 1.0, "coverage": 0.5, "num_elites": 8,
               "best_objective": 2.0, "mean_objective": 1.5}
    summary = evaluation.corrected_summary(corrected, run_row, [100, 101, 102], 6)
    assert (summary["iteration"], summary["evaluations"], summary["repeats"]) == (5, 60, 3)
    assert summary["num_elites"] == len(best) and summary["coverage"] == len(best) / CELLS[kind]
    assert close(summary["qd_score"], math.fsum(objective - OFFSET for objective in objectives))
    assert close(summary["best_objective"], max(objectives))
    assert close(summary["mean_objective"], math.fsum(objectives) / len(objectives))


def hand_cqd(elites: Sequence[tuple[float, Sequence[float]]], targets: Sequence[Sequence[float]],
             penalties: Sequence[float], obj_min: float, obj_max: float, dist_max: float) -> float:
    """One iteration of CQD as pyribs' cqd_score defines it (after Kent 2022): for each target and
    penalty theta, the best over the elites of objective / (obj_max - obj_min) - theta x distance
    to the target / dist_max; summed. (pyribs divides by the range without subtracting obj_min.)"""
    return math.fsum(max(objective / (obj_max - obj_min) - theta * math.dist(measures, target) / dist_max
                         for objective, measures in elites)
                     for target in targets for theta in penalties)


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_cqd_is_pyribs_cqd_score_on_the_tasks_objective_range(kind: str, make_archive: Maker) -> None:
    """comparison.cqd against pyribs' cqd_score called directly with the documented settings
    (1,000 targets uniform in the box from seed 0, 10 penalties, [QD offset, objective_max], the
    box's diagonal), and against a loop over the elites put in."""
    archive = make_archive(kind)
    best = fill(kind, archive)
    task = tasks.ENVIRONMENTS[LANDER]
    value = comparison.cqd(archive, task.returns())

    targets = np.random.default_rng(0).uniform(LOWER, UPPER, size=(1, 1000, 2))
    diagonal = math.hypot(2.0, 3.0)
    direct = cqd_score(archive, iterations=1, target_points=targets, penalties=10, obj_min=OFFSET,
                       obj_max=OBJECTIVE_MAX, dist_max=diagonal)
    assert value == float(direct.mean)
    by_hand = hand_cqd(list(best.values()), targets[0].tolist(), [k / 9 for k in range(10)], OFFSET,
                       OBJECTIVE_MAX, diagonal)
    assert close(value, by_hand)
    # Kent's normalisation (objective - obj_min) / (obj_max - obj_min) adds a constant per target
    # and penalty: the "[offset, max]" of the report is the range divided by, not a shift.
    kent = hand_cqd([(objective - OFFSET, m) for objective, m in best.values()], targets[0].tolist(),
                    [k / 9 for k in range(10)], OFFSET, OBJECTIVE_MAX, diagonal)
    assert kent == pytest.approx(value + 1000 * 10 * -OFFSET / (OBJECTIVE_MAX - OFFSET), rel=TOL)


def test_cqd_score_by_hand_on_a_tiny_archive(make_archive: Maker) -> None:
    """pyribs' cqd_score (what comparison.cqd calls) against Kent's definition computed here: 3
    elites, 4 targets, 3 penalties (0, 0.5, 1), 1 iteration."""
    archive = make_archive("grid")
    elites = [(250.0, (-0.5, -2.5)), (-100.0, (0.5, -0.5)), (-590.0, (0.9, -2.9))]
    archive.add(np.zeros((3, SOLUTION_DIM)), np.array([objective for objective, _ in elites]),
                np.array([measures for _, measures in elites]))
    targets = [(-0.5, -2.5), (0.0, -1.5), (1.0, 0.0), (0.9, -2.8)]
    result = cqd_score(archive, iterations=1, target_points=np.array([targets]), penalties=3,
                       obj_min=OFFSET, obj_max=OBJECTIVE_MAX, dist_max=math.sqrt(13.0))
    by_hand = 0.0
    for target in targets:
        for theta in (0.0, 0.5, 1.0):
            by_hand += max(objective / 950.0 - theta * math.dist(m, target) / math.sqrt(13.0)
                           for objective, m in elites)
    assert close(float(result.mean), by_hand) and close(float(result.scores[0]), by_hand)
    # at theta 0 every target takes the best elite: 4 x 250 / 950 of the sum
    assert close(hand_cqd(elites, targets, [0.0], OFFSET, OBJECTIVE_MAX, 1.0), 4 * 250 / 950)


def test_qd_auc_is_the_trapezoid_from_the_origin() -> None:
    """QD-score AUC against trapezoids summed by hand from (0, 0), over the last evaluations."""
    rows = [{"evaluations": 12, "qd_score": 100.5}, {"evaluations": 24, "qd_score": 100.5},
            {"evaluations": 60, "qd_score": 900.25}, {"evaluations": 72, "qd_score": 1000.0}]
    points = [(0, 0.0), *((row["evaluations"], row["qd_score"]) for row in rows)]
    area = math.fsum((x1 - x0) * (y0 + y1) / 2 for (x0, y0), (x1, y1) in zip(points, points[1:]))
    assert close(comparison.qd_auc(rows), area / 72)
    assert comparison.qd_auc([{"evaluations": 30, "qd_score": 640.0}]) == 320.0  # a triangle: half


def test_normalised_qd_score_and_archive_cells_by_hand() -> None:
    """Cells: grid^measures or a CVT's --cells; the normalised QD score: QD score over cells x
    (350 - (-600)) for the lander, written out."""
    grid, cvt = lander_config("grid"), lander_config("cvt")
    three = lander_config("grid", measures=["impact_x", "impact_y_velocity", "fuel"], grid=3)
    assert [comparison.archive_cells(c) for c in (grid, cvt, three)] == [16, 8, 27]
    assert comparison.normalised_qd_score(5_000.0, grid) == 5_000.0 / (16 * 950.0)
    assert comparison.normalised_qd_score(5_000.0, cvt) == 5_000.0 / (8 * 950.0)
    assert comparison.normalised_qd_score(16 * 950.0, grid) == 1.0  # every cell at objective_max


def test_solved_cells_counts_elites_of_200_or_more(tmp_path: Path, make_archive: Maker) -> None:
    """solved_cells against a count by hand of the elites put in (200.0 counts, 199.75 does not),
    from the archive's CSV as a run writes it; None without the CSV."""
    archive = make_archive("grid")
    best = fill("grid", archive)
    write_csv(tmp_path / "archive.csv", archive.data(return_type="pandas"))
    solved = sum(1 for objective, _ in best.values() if objective >= 200.0)
    assert solved == 4  # 250.0, 300.75, 200.0 and 420.5
    assert comparison.solved_cells(tmp_path / "archive.csv", tasks.ENVIRONMENTS[LANDER]) == solved
    assert comparison.solved_cells(tmp_path / "missing.csv", tasks.ENVIRONMENTS[LANDER]) is None


# The statistics, by hand.
def hand_iqm(values: Sequence[float]) -> float:
    """Sort, drop floor(n / 4) from each end, mean of the rest."""
    ordered = sorted(values)
    cut = len(ordered) // 4
    middle = ordered[cut:len(ordered) - cut]
    return math.fsum(middle) / len(middle)


def hand_a12(x: Sequence[float], y: Sequence[float]) -> float:
    """Wins plus half the ties over every pair of a run of x and a run of y, by a double loop."""
    wins = ties = 0
    for a in x:
        for b in y:
            wins += a > b
            ties += a == b
    return (wins + ties / 2) / (len(x) * len(y))


def draws(task_runs: Sequence[Sequence[float]], rng: np.random.Generator, resamples: int) -> list[np.ndarray]:
    """The documented draws: per task in order, `resamples` rows of as many indices as it has runs."""
    return [rng.integers(0, len(runs), size=(resamples, len(runs))) for runs in task_runs]


def percentiles(point: float, samples: list[float]) -> tuple[float, float, float]:
    low, high = np.percentile(samples, [2.5, 97.5])
    return point, float(low), float(high)


def hand_iqm_interval(task_runs: Sequence[Sequence[float]], resamples: int = stats.RESAMPLES):
    task_runs = [list(runs) for runs in task_runs if len(runs)]
    pooled = [value for runs in task_runs for value in runs]
    if all(len(runs) < 2 for runs in task_runs):
        return hand_iqm(pooled), math.nan, math.nan
    picks = draws(task_runs, np.random.default_rng(stats.SEED), resamples)
    samples = [hand_iqm([runs[i] for runs, p in zip(task_runs, picks) for i in p[r]])
               for r in range(resamples)]
    return percentiles(hand_iqm(pooled), samples)


def hand_mean_interval(task_runs: Sequence[Sequence[float]], resamples: int = stats.RESAMPLES):
    task_runs = [list(runs) for runs in task_runs if len(runs)]

    def mean_of_means(per_task: list[list[float]]) -> float:
        return math.fsum(math.fsum(runs) / len(runs) for runs in per_task) / len(per_task)

    picks = draws(task_runs, np.random.default_rng(stats.SEED), resamples)
    return percentiles(mean_of_means(task_runs), [mean_of_means([[runs[i] for i in p[r]] for runs, p in
                                                                 zip(task_runs, picks)])
                                                  for r in range(resamples)])


def hand_improvement_interval(a_tasks: Sequence[Sequence[float]], b_tasks: Sequence[Sequence[float]],
                              resamples: int = stats.RESAMPLES, paired: bool = False):
    """P(A > B) averaged over the tasks both have runs of, its interval from A's draws then B's,
    from one generator (paired: B's from a fresh generator of the same seed, the known bug)."""
    pairs = [(list(a), list(b)) for a, b in zip(a_tasks, b_tasks) if len(a) and len(b)]
    a_tasks, b_tasks = [a for a, _ in pairs], [b for _, b in pairs]
    point = math.fsum(hand_a12(a, b) for a, b in pairs) / len(pairs)
    if all(len(runs) < 2 for runs in a_tasks + b_tasks):
        return point, math.nan, math.nan
    rng = np.random.default_rng(stats.SEED)
    a_picks = draws(a_tasks, rng, resamples)
    b_picks = draws(b_tasks, np.random.default_rng(stats.SEED) if paired else rng, resamples)
    samples = [math.fsum(hand_a12([a[i] for i in pa[r]], [b[i] for i in pb[r]])
                         for a, b, pa, pb in zip(a_tasks, b_tasks, a_picks, b_picks)) / len(pairs)
               for r in range(resamples)]
    return percentiles(point, samples)


def hand_holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down: the i-th smallest p times (m - i), capped at 1, never below the one before."""
    order = sorted(range(len(p_values)), key=lambda i: p_values[i])
    adjusted, running = [0.0] * len(p_values), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (len(p_values) - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def hand_mann_whitney_p(x: Sequence[float], y: Sequence[float]) -> float:
    """Two-sided Mann-Whitney p as scipy's method='auto' documents it: without ties and unless both
    samples exceed 8, exact (here by enumerating every split of the ranks); else the normal
    approximation with the tie correction and the continuity correction."""
    n1, n2 = len(x), len(y)
    u = hand_a12(x, y) * n1 * n2
    u_max = max(u, n1 * n2 - u)
    pooled = [*x, *y]
    if len(set(pooled)) == len(pooled) and not (n1 > 8 and n2 > 8):
        splits = list(itertools.combinations(range(n1 + n2), n1))  # x's ranks, 0-based
        at_least = sum(1 for ranks in splits if sum(ranks) - n1 * (n1 - 1) / 2 >= u_max)
        return min(1.0, 2 * at_least / len(splits))
    n = n1 + n2
    tie_term = sum(t ** 3 - t for t in Counter(pooled).values())
    sd = math.sqrt(n1 * n2 / 12 * ((n + 1) - tie_term / (n * (n - 1))))
    z = (u_max - n1 * n2 / 2 - 0.5) / sd
    return min(1.0, math.erfc(z / math.sqrt(2)))  # twice the normal's upper tail at z


def test_bootstrap_interval_is_scipys_bca_with_the_calls_settings() -> None:
    """The BCa interval against scipy.stats.bootstrap called directly (9,999 resamples, 95%,
    rng seeded 0), exactly; the mean lies inside; one run: no interval; all equal: that value."""
    rng = np.random.default_rng(11)
    for values in (np.array([3.0, 5.0]), rng.normal(1000, 200, 5), np.array([1.0, 1.0, 2.0, 7.0, 7.0, 30.0])):
        expected = bootstrap((values,), np.mean, confidence_level=0.95, n_resamples=9999, method="BCa",
                             rng=np.random.default_rng(0)).confidence_interval
        low, high = stats.bootstrap_interval(values)
        assert (low, high) == (float(expected.low), float(expected.high))
        assert low <= math.fsum(values) / len(values) <= high
    assert all(math.isnan(v) for v in stats.bootstrap_interval(np.array([4.0])))
    assert stats.bootstrap_interval(np.array([2.5, 2.5, 2.5])) == (2.5, 2.5)


def test_iqm_drops_a_quarter_from_each_end() -> None:
    """stats.iqm against sort, drop floor(n / 4) from each end, mean; tasks pooled."""
    rng = np.random.default_rng(12)
    for n in range(1, 14):
        values = rng.normal(0, 100, n)
        assert close(stats.iqm(values), hand_iqm(values.tolist()))
    first, second = [5.0, 1.0, 9.0], [2.0, 8.0, 3.0, 7.0, 4.0]
    assert close(stats.iqm([np.array(first), np.array(second)]), hand_iqm(first + second))
    assert stats.iqm([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 1e9]) == hand_iqm([3, 4, 5, 6, 2, 7, 1, 8]) == 4.5


def test_iqm_and_mean_intervals_from_the_same_draws() -> None:
    """iqm_interval and mean_interval against their statistic by a loop over each of the same
    seeded draws (per task, in order, from one generator), then the 2.5th and 97.5th percentiles."""
    task_runs = [[3.0, -1.5, 4.0, 10.0, 2.5], [20.0, 18.0, 25.5, 19.0, 30.0, 22.0, 21.5, 40.0]]
    for resamples in (200, stats.RESAMPLES):
        assert close(stats.iqm_interval(task_runs, resamples), hand_iqm_interval(task_runs, resamples))
        assert close(stats.mean_interval(task_runs, resamples), hand_mean_interval(task_runs, resamples))
    assert close(stats.iqm_interval([[], [1.0, 3.0, 2.0]], 200), hand_iqm_interval([[1.0, 3.0, 2.0]], 200))
    assert close(stats.iqm_interval([[3.0], [4.0]]), (3.5, math.nan, math.nan))


def test_improvement_interval_draws_a_then_b_from_one_generator() -> None:
    """P(A > B)'s interval for two settings of equal size (so paired draws would share indices),
    against a loop over the same draws: A's tasks, then B's, from one generator seeded stats.SEED."""
    a_tasks = [[3.0, 1.0, 4.0, 1.0, 5.0, 9.0], [2.0, 6.0, 5.0, 3.0]]
    b_tasks = [[2.0, 7.0, 1.0, 8.0, 2.0, 8.0], [1.0, 8.0, 2.0, 8.0]]
    for resamples in (200, stats.RESAMPLES):
        expected = hand_improvement_interval(a_tasks, b_tasks, resamples)
        assert close(stats.improvement_interval(a_tasks, b_tasks, resamples), expected)
        # drawn paired, the interval would differ: the check above can tell
        assert not close(hand_improvement_interval(a_tasks, b_tasks, resamples, paired=True), expected)
    assert close(stats.improvement_interval([a_tasks[0]], [b_tasks[0]], 200),
                 hand_improvement_interval([a_tasks[0]], [b_tasks[0]], 200))
    assert close(stats.improvement_interval([[5.0]], [[4.0]]), (1.0, math.nan, math.nan))  # nothing to draw


def test_a12_is_wins_and_half_ties_and_scipys_u() -> None:
    """P(A > B) of one task (A12) by a double loop against scipy's mannwhitneyu(x, y).statistic
    over n_a n_b, and the module's probability_of_improvement."""
    cases = [([1.0, 2.0], [1.0, 3.0]), ([3.0, 1.0, 4.0, 1.0, 5.0], [1.0, 2.0, 6.0]),
             ([4.0, 4.0, 4.0], [4.0, 4.0]), ([9.0, 8.0, 7.5], [1.0, 2.0, 3.0, 4.0]),
             ([0.5, 2.5, 2.5, 3.0, 7.0, 7.0, 8.0], [2.5, 7.0, 1.0, 9.0])]
    for x, y in cases:
        a12 = hand_a12(x, y)
        assert a12 == float(mannwhitneyu(x, y).statistic) / (len(x) * len(y))
        assert close(stats.probability_of_improvement([x], [y]), a12)
    assert close(stats.probability_of_improvement([cases[1][0], cases[4][0]], [cases[1][1], cases[4][1]]),
                 (hand_a12(*cases[1]) + hand_a12(*cases[4])) / 2)


def test_holm_by_hand_and_the_textbook_example() -> None:
    """Holm's adjustment against the textbook example and a hand implementation (ties, caps at 1)."""
    assert stats.holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02], rel=TOL)
    rng = np.random.default_rng(13)
    for p_values in ([0.2, 0.2, 0.01, 0.5], [0.9, 0.6, 0.001], [0.04], rng.uniform(0, 0.3, 9).tolist()):
        assert stats.holm(p_values) == hand_holm(p_values)
    # 3 x 0.3, then max(0.9, 2 x 0.4), then max(0.9, 0.5): a later p never adjusts below an earlier one
    assert stats.holm([0.3, 0.4, 0.5]) == pytest.approx([0.9, 0.9, 0.9], rel=TOL)
    assert stats.holm([0.6, 0.5]) == [1.0, 1.0]


# A small comparison table of one task: three settings (A and B of equal size), the summarised
# metrics with ties (qd_auc, cqd_score) and missing values (cqd_score: C keeps one run).
RUNS = {
    "A": {"qd_score": [1200.5, 980.0, 1500.25, 1100.0, 1320.0, 1010.5],
          "qd_auc": [500.0, 520.0, 500.0, 610.0, 480.0, 520.0],
          "cqd_score": [806.1, 790.4, 812.9, 799.0, math.nan, 805.5],
          "coverage": [0.5, 0.5625, 0.625, 0.5, 0.4375, 0.5625],
          "best_objective": [250.5, 270.0, 231.25, 288.0, 240.0, 266.5],
          "mean_objective": [40.5, 12.0, 66.25, 30.0, 51.0, 20.5],
          "solved_cells": [3, 5, 2, 6, 2, 4]},
    "B": {"qd_score": [900.0, 1250.0, 870.5, 1005.0, 940.0, 1190.0],
          "qd_auc": [500.0, 450.0, 470.0, 520.0, 430.0, 505.0],
          "cqd_score": [780.2, 801.7, 770.0, 795.3, 788.8, 790.4],
          "coverage": [0.375, 0.5, 0.4375, 0.5, 0.375, 0.3125],
          "best_objective": [200.0, 190.5, 230.0, 185.0, 201.0, 212.25],
          "mean_objective": [-10.0, 5.5, 3.0, -2.25, 8.0, 1.0],
          "solved_cells": [1, 0, 2, 0, 1, 1]},
    "C": {"qd_score": [1600.0, 1450.0, 1380.0, 1700.0],
          "qd_auc": [600.0, 600.0, 640.0, 590.0],
          "cqd_score": [math.nan, math.nan, math.nan, 820.0],
          "coverage": [0.75, 0.6875, 0.625, 0.8125],
          "best_objective": [301.0, 295.5, 310.0, 299.0],
          "mean_objective": [70.0, 70.0, 81.5, 64.0],
          "solved_cells": [3, 3, 3, 3]},
}


def runs_table(runs: dict[str, dict[str, list[float]]], task: str = LANDER) -> pd.DataFrame:
    """A comparison table (comparison_table's columns that the statistics read): a row per run."""
    return pd.DataFrame([{"task": task, "setting": setting, **{m: values[i] for m, values in columns.items()}}
                         for setting, columns in runs.items() for i in range(len(columns["qd_score"]))])


def present(values: Sequence[float]) -> list[float]:
    return [float(v) for v in values if not math.isnan(v)]


def test_pairwise_tests_every_column_by_hand() -> None:
    """Every column of compare's tests: runs, U and A12 by a double loop, p as scipy's method
    documents it (exact by enumeration, or normal with corrections), Holm by hand over each
    metric's pairs, P(A > B)'s interval from the same draws by a loop."""
    tests = comparison.pairwise_tests(runs_table(RUNS))
    expected = []
    for metric in comparison.TESTED:
        block = []
        for a, b in itertools.combinations(RUNS, 2):
            x, y = present(RUNS[a][metric]), present(RUNS[b][metric])
            a12 = hand_a12(x, y)
            block.append({"task": LANDER, "metric": metric, "setting_a": a, "setting_b": b, "runs_a": len(x),
                          "runs_b": len(y), "U": a12 * len(x) * len(y), "p": hand_mann_whitney_p(x, y),
                          "A12": a12, **dict(zip(("p_improvement", "p_improvement_low", "p_improvement_high"),
                                                 hand_improvement_interval([x], [y])))})
        for row, adjusted in zip(block, hand_holm([row["p"] for row in block])):
            row["p_holm"] = adjusted
        expected += block
    assert list(tests.columns) == comparison.TEST_COLUMNS and len(tests) == len(expected) == 9
    assert [row["runs_b"] for row in expected if row["metric"] == "cqd_score"] == [6, 1, 1]
    assert any(row["p"] < 0.05 for row in expected) and any(row["p_holm"] > row["p"] for row in expected)
    for row, want in zip(tests.to_dict("records"), expected):
        for column in comparison.TEST_COLUMNS:
            assert close(row[column], want[column]) if isinstance(want[column], float) else (
                row[column] == want[column]), (column, row, want)


def test_setting_statistics_every_column_by_hand() -> None:
    """Every column of compare's per-setting table: runs, mean and median by hand, the BCa
    interval of scipy.stats.bootstrap called directly, IQM and its interval by a loop over the
    same seeded draws; one run (C's CQD): no interval; all equal (C's solved cells): that value."""
    table = comparison.setting_statistics(runs_table(RUNS))
    expected = []
    for setting, columns in RUNS.items():
        for metric in comparison.SUMMARISED:
            values = present(columns[metric])
            ordered, n = sorted(values), len(values)
            if n < 2:
                low = high = math.nan
            elif len(set(values)) == 1:
                low = high = values[0]
            else:
                interval = bootstrap((np.array(values),), np.mean, confidence_level=0.95, n_resamples=9999,
                                     method="BCa", rng=np.random.default_rng(0)).confidence_interval
                low, high = float(interval.low), float(interval.high)
            iqm, iqm_low, iqm_high = hand_iqm_interval([values])
            expected.append({"task": LANDER, "setting": setting, "metric": metric, "runs": n,
                             "mean": math.fsum(values) / n,
                             "median": (ordered[(n - 1) // 2] + ordered[n // 2]) / 2,
                             "ci95_low": low, "ci95_high": high, "iqm": iqm, "iqm_low": iqm_low,
                             "iqm_high": iqm_high})
    assert len(table) == len(expected) == 3 * len(comparison.SUMMARISED)
    for row, want in zip(table.to_dict("records"), expected):
        assert set(row) == set(want)
        for column, value in want.items():
            assert close(row[column], value) if isinstance(value, float) else row[column] == value, (
                column, row, want)
        if row["runs"] > 1:
            assert row["ci95_low"] <= row["mean"] <= row["ci95_high"]


def test_aggregate_statistics_by_hand() -> None:
    """compare's statistics across tasks, on 2 tasks with unequal run counts: per setting the IQM
    of every run and the mean of the tasks' means with stratified intervals, and P(A > B) averaged
    over the shared tasks, all recomputed by loops over the same seeded draws; C has no runs of the
    second task, and B one coverage missing."""
    normalised, coverage = comparison.NORMALISED, "coverage"
    data = {  # setting: task: (normalised QD scores, coverages)
        "A": {"T1": ([0.31, 0.28, 0.35, 0.30, 0.33], [0.50, 0.45, 0.55, 0.50, 0.60]),
              "T2": ([0.12, 0.15, 0.10], [0.20, 0.25, 0.22])},
        "B": {"T1": ([0.29, 0.27, 0.36, 0.25], [0.40, 0.50, 0.42, 0.47]),
              "T2": ([0.14, 0.11, 0.16, 0.09, 0.15, 0.13], [0.30, math.nan, 0.26, 0.21, 0.28, 0.24])},
        "C": {"T1": ([0.40, 0.38, 0.41], [0.65, 0.70, 0.62])},
    }
    table = pd.DataFrame([{"task": task, "setting": setting, normalised: n, coverage: c}
                          for setting, per_task in data.items() for task, (ns, cs) in per_task.items()
                          for n, c in zip(ns, cs)])
    aggregate, notes = comparison.aggregate_statistics(table)

    def runs(setting: str, index: int) -> list[list[float]]:  # per task T1, T2; [] where none
        return [present(data[setting][task][index]) if task in data[setting] else [] for task in ("T1", "T2")]

    expected = []
    for setting in data:
        for index, metric in enumerate(comparison.AGGREGATED):
            per_task = runs(setting, index)
            for statistic, interval in (("iqm", hand_iqm_interval), ("mean", hand_mean_interval)):
                expected.append((statistic, metric, setting, "",
                                 sum(1 for r in per_task if r), sum(map(len, per_task)), None,
                                 *interval(per_task)))
    for a, b in itertools.combinations(data, 2):
        shared = [(x, y) for x, y in zip(runs(a, 0), runs(b, 0)) if x and y]
        expected.append(("p_improvement", normalised, a, b, len(shared), sum(len(x) for x, _ in shared),
                         sum(len(y) for _, y in shared),
                         *hand_improvement_interval([x for x, _ in shared], [y for _, y in shared])))
    assert notes == ["C has no runs of T2: aggregated over the tasks it has"]
    assert list(aggregate.columns) == comparison.AGGREGATE_COLUMNS and len(aggregate) == len(expected) == 15
    assert expected[6][4:6] == (2, 9)  # B's coverage: one missing
    for row, want in zip(aggregate.itertuples(index=False), expected):
        assert tuple(row[:6]) == want[:6], (row, want)
        assert (pd.isna(row[6]) and want[6] is None) or row[6] == want[6], (row, want)
        assert close(tuple(row[7:]), want[7:]), (row, want)
