"""Gradients estimated from episodes, for the DQD rows (cma_mega_es, cma_maega_es): an episode
gives no derivative, so the Jacobian of the objective and of each measure around a point is
estimated from mirrored Gaussian samples flown beside it, as dqd-rl does (Tjanaka et al. 2022,
after OpenAI-ES: Salimans et al. 2017).

Each emitter's point theta is flown with n mirrored samples theta +- sigma * eps (eps ~ N(0, I),
n / 2 draws). For each of the objective and the measures, the samples' values are replaced by
their centred ranks (in [-0.5, 0.5]: a sample's rank among the n, over n - 1, less one half;
equal values share their mean rank), and the gradient estimate is sum_j eps_j * (rank(+j) -
rank(-j)) / (n / 2 * sigma), dqd-rl's formula. dqd-rl's ranks break ties by position, which
gives a measure equal on every sample (a foot's contact share moves in steps of 1 / T, so a flat
one is common) the direction -sum(eps) as long as a real gradient; shared ranks give it none.
Ranks make the estimate blind to the values' scale, and pyribs' emitter normalises each
gradient anyway (normalize_grad), so returns of thousands and measures in [0, 1] step alike. The
points are flown apart from their samples: their own objective and measures go to tell_dqd, and
only they, not the samples, may enter the archive (dqd-rl's setting).

The draws come from the run's seed and the iteration alone (no random state to checkpoint), so a
resumed run draws the same samples as a straight one, on any number of workers.

Map:
- `sample_points` (what a gradient batch flies: the points, then each point's samples);
- `centred_ranks`, `estimate` (the points' values and Jacobians from the flown batch).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

ES_SEED_KEY = 0xE5  # keeps the samples' draws apart from the run's other seeds


def noise(seed: int, iteration: int, points: int, samples: int, dim: int) -> np.ndarray:
    """The samples' directions eps: (points, samples / 2, dim), from the run's seed and the
    iteration only."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, ES_SEED_KEY, iteration]))
    return rng.standard_normal((points, samples // 2, dim))


def sample_points(points: np.ndarray, eps: np.ndarray, sigma: float) -> np.ndarray:
    """The gradient batch: the points first, then each point's samples, theta + sigma * eps_j for
    every draw j and then theta - sigma * eps_j (mirrored)."""
    offsets = np.concatenate([eps, -eps], axis=1) * sigma  # (points, samples, dim)
    return np.concatenate([points, (points[:, None, :] + offsets).reshape(-1, points.shape[1])])


def centred_ranks(values: np.ndarray) -> np.ndarray:
    """Each value's rank along the last axis, from 0, scaled to [-0.5, 0.5]; equal values share
    their mean rank, so values all equal are all 0."""
    ranks = stats.rankdata(values, method="average", axis=-1) - 1.0
    return ranks / (values.shape[-1] - 1) - 0.5


def estimate(flown: np.ndarray, eps: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From the gradient batch's rows of (objective, *measures), in `sample_points`' order: the
    points' objectives (points,), measures (points, m) and Jacobians (points, 1 + m, dim), the
    objective's gradient first."""
    points, half, dim = eps.shape
    at_points, sampled = flown[:points], flown[points:].reshape(points, 2 * half, -1)
    ranks = centred_ranks(np.moveaxis(sampled, 1, 2))  # (points, 1 + m, samples)
    directions = np.concatenate([eps, -eps], axis=1)  # (points, samples, dim)
    jacobian = np.einsum("pks,psd->pkd", ranks, directions) / (half * sigma)
    return at_points[:, 0], at_points[:, 1:], jacobian
