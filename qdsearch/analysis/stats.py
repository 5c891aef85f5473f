"""Statistics across seeds: what a comparison of settings reports of the runs of each.

Runs of one setting are repeats of one experiment (other seeds); a comparison reports the mean
with its BCa interval, and what deep-RL papers report after Agarwal et al. 2021 ("Deep RL at the
edge of the statistical precipice", the rliable library): the interquartile mean (IQM) and the
probability of improvement P(A > B), each with a stratified bootstrap interval. rliable itself
cannot be installed beside our pandas (its dependency arch < 8 breaks with pandas 3), so its
statistics are computed here with numpy and scipy, following its definitions; tests check them
by hand.

Map:
- `bootstrap_interval`: a 95% BCa interval of a mean;
- rliable's statistics: `iqm`, `task_mean`, `probability_of_improvement`; their vectorised forms
  over bootstrap resamples (`iqm_of`, `task_mean_of`, `improvement_of`);
- the stratified bootstrap: `stratified_resamples`, `percentile_interval`, `iqm_interval`,
  `mean_interval`, `improvement_interval`, each `(point, low, high)`;
- Holm's adjustment: `holm`, `holm_floor`.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

RESAMPLES = 2_000  # rliable's default is 50,000; 2,000 puts the 2.5% ends within a few resamples
SEED = 0  # every interval is seeded: the same runs give the same report
Estimate = tuple[float, float, float]  # (point, low, high)


def bootstrap_interval(values: np.ndarray) -> tuple[float, float]:
    """95% BCa bootstrap confidence interval of the mean (seeded, so repeatable)."""
    from scipy.stats import bootstrap

    if len(values) < 2:
        return math.nan, math.nan
    if np.ptp(values) == 0:
        return float(values[0]), float(values[0])
    result = bootstrap((values,), np.mean, confidence_level=0.95, n_resamples=9999, method="BCa",
                       rng=np.random.default_rng(0))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def iqm(values) -> float:
    """rliable's interquartile mean: scipy's trim_mean with 25% cut from each end, over every
    score flattened (a list of per-task arrays is pooled). trim_mean cuts int(0.25 n) scores from
    each end: of 1..8, 3..6. Robust to a run that failed or flew off, unlike the mean; less noisy
    than the median with few runs."""
    from scipy.stats import trim_mean

    flat = np.concatenate([np.ravel(np.asarray(v, dtype=float)) for v in values]) if len(values) else []
    return float(trim_mean(flat, 0.25)) if len(flat) else math.nan


def task_mean(tasks: Sequence[np.ndarray]) -> float:
    """rliable's aggregate mean: the mean over tasks of each task's mean over its runs (with as
    many runs in every task, the mean of them all)."""
    return float(task_mean_of([np.asarray(t, dtype=float) for t in tasks]))


def probability_of_improvement(a_tasks: Sequence[np.ndarray], b_tasks: Sequence[np.ndarray]) -> float:
    """rliable's P(A > B): per task, the Mann-Whitney U of A's runs over B's divided by
    n_a n_b (the chance that a run of A beats a run of B, ties counting half: Vargha-Delaney's
    A12), averaged over the tasks. `a_tasks[i]` and `b_tasks[i]` are runs of one task."""
    return float(improvement_of([np.asarray(a, dtype=float) for a in a_tasks],
                                [np.asarray(b, dtype=float) for b in b_tasks]))


# The vectorised forms: each task's scores in the last axis, resamples in the first.
def iqm_of(tasks: list[np.ndarray]) -> np.ndarray:
    from scipy.stats import trim_mean

    return trim_mean(np.concatenate(tasks, axis=-1), 0.25, axis=-1)


def task_mean_of(tasks: list[np.ndarray]) -> np.ndarray:
    return np.mean([t.mean(axis=-1) for t in tasks], axis=0)


def improvement_of(a_tasks: list[np.ndarray], b_tasks: list[np.ndarray]) -> np.ndarray:
    """Wins plus half the ties over all n_a n_b pairs of each task: exactly scipy's
    mannwhitneyu(a, b).statistic / (n_a n_b), which rliable computes, without a call per
    resample."""
    per_task = [(a[..., :, None] > b[..., None, :]).mean(axis=(-2, -1))
                + 0.5 * (a[..., :, None] == b[..., None, :]).mean(axis=(-2, -1))
                for a, b in zip(a_tasks, b_tasks)]
    return np.mean(per_task, axis=0)


def stratified_resamples(tasks: list[np.ndarray], rng: np.random.Generator,
                         resamples: int = RESAMPLES) -> list[np.ndarray]:
    """rliable's StratifiedBootstrap: each task's runs drawn with replacement from that task's
    own runs (never another task's), as many as it has: a (resamples, n_task) array per task.
    (rliable needs as many runs in every task; drawing each task's own count lifts that.)"""
    return [np.asarray(t, dtype=float)[rng.integers(0, len(t), size=(resamples, len(t)))] for t in tasks]


def percentile_interval(point: float, samples: np.ndarray) -> Estimate:
    """The point and the 2.5th and 97.5th percentiles of its bootstrap samples (rliable's
    default method, 'percentile')."""
    low, high = np.percentile(samples, [2.5, 97.5])
    return float(point), float(low), float(high)


def nonempty(tasks: Sequence) -> list[np.ndarray]:
    return [np.asarray(t, dtype=float) for t in tasks if len(t)]


def stratified_interval(statistic: Callable[[list[np.ndarray]], np.ndarray], tasks: Sequence,
                        resamples: int = RESAMPLES) -> Estimate:
    """A statistic of per-task scores with its 95% stratified bootstrap interval (seeded)."""
    tasks = nonempty(tasks)
    if not tasks:
        return math.nan, math.nan, math.nan
    if all(len(t) < 2 for t in tasks):  # nothing to resample: no interval, as for the BCa one
        return float(statistic(tasks)), math.nan, math.nan
    samples = statistic(stratified_resamples(tasks, np.random.default_rng(SEED), resamples))
    return percentile_interval(statistic(tasks), samples)


def iqm_interval(tasks: Sequence, resamples: int = RESAMPLES) -> Estimate:
    """The IQM of every run of every task, with its 95% stratified bootstrap interval."""
    return stratified_interval(iqm_of, tasks, resamples)


def mean_interval(tasks: Sequence, resamples: int = RESAMPLES) -> Estimate:
    """rliable's mean (of the tasks' means), with its 95% stratified bootstrap interval."""
    return stratified_interval(task_mean_of, tasks, resamples)


def improvement_interval(a_tasks: Sequence, b_tasks: Sequence, resamples: int = RESAMPLES) -> Estimate:
    """P(A > B) over the tasks both have runs of, with a 95% stratified bootstrap interval: A's
    and B's runs each drawn from their own runs of the task. (rliable draws one set of indices for
    both, its matrices having one shape; runs of two settings are not paired, and may differ in
    number, so here each setting's are drawn apart.)"""
    pairs = [(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
             for a, b in zip(a_tasks, b_tasks) if len(a) and len(b)]
    if not pairs:
        return math.nan, math.nan, math.nan
    a_tasks, b_tasks = [a for a, _ in pairs], [b for _, b in pairs]
    if all(len(t) < 2 for t in a_tasks + b_tasks):
        return float(improvement_of(a_tasks, b_tasks)), math.nan, math.nan
    rng = np.random.default_rng(SEED)
    a_samples, b_samples = (stratified_resamples(a_tasks, rng, resamples),
                            stratified_resamples(b_tasks, rng, resamples))
    return percentile_interval(improvement_of(a_tasks, b_tasks), improvement_of(a_samples, b_samples))


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of p-values for testing them all at once."""
    adjusted, running = [0.0] * len(p_values), 0.0
    for rank, i in enumerate(np.argsort(p_values)):
        running = max(running, min(1.0, (len(p_values) - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def holm_floor(tests) -> float:
    """The smallest Holm-adjusted p-value any pair of a metric could reach: the exact two-sided
    Mann-Whitney p of a complete separation, 2 / C(n_a + n_b, n_a), times the number of pairs."""
    pairs = tests[tests["metric"] == tests["metric"].iloc[0]]
    return min(1.0, len(pairs) * min(2 / math.comb(int(a + b), int(a))
                                     for a, b in zip(pairs["runs_a"], pairs["runs_b"])))
