"""ME-ES (Colas et al. 2020, "Scaling MAP-Elites to deep neuroevolution") as dqd-rl runs it
(icaros-usc/dqd-rl, src/me_es/, adapted from Uber's code): one chain of ES steps per emitter,
each step's offspring offered to the archive, the chain moving to a new parent from the archive
every STEPS_PER_PARENT steps, its phases alternating between exploiting the return and exploring
novelty, exploit first.

An iteration is two batches (search/loop.py): the samples theta +- sigma * eps around each
emitter's current theta (`es_point`, flown apart: no sample enters the archive), from which
`es_step` takes one Adam step on the return's or the novelty's ES gradient; then the stepped
theta itself (`ask`), told to the archive as any solution (`tell`). The first iteration flies x0
alone. The gradient is dqd-rl's: sum_j eps_j (rank(+j) - rank(-j)) / pairs over the centred ranks
of the samples' scores, not divided by sigma, followed by Adam (lr 0.01) on it with L2 0.005
(pyribs' AdamOpt is Uber's optimiser), its moments reset at each new parent.

Novelty is the mean squared distance to the K_NEAREST nearest measures among every offspring the
emitter has flown (the archive's elites are among them), each measure scaled to its range
(dqd-rl's measures all lie in [0, 1]). A new parent is drawn with the emitter's own generator:
- explore: dqd-rl's `novelty_bias`: the EXPLORE_TOP most novel elites share 0.9 of the draw in
  proportion to their novelty, every elite 0.1 evenly;
- exploit: dqd-rl's `best2inlast5_or_best`: a cell's score is the best sample return of the ES
  step whose offspring made it; half the time, or with fewer than 5 elites, the best cell, else
  one of the 2 best of the 5 cells discovered last (the last half of them, under 10), in
  proportion to their scores shifted to start at 1.

A network's chain normalises its observations as dqd-rl's ME-ES does (the linear policy, which
has no bias, cannot): by running statistics of the observations of the episodes of a share
(OBS_COLLECT_PROB) of its negative samples, flown again in the driver (episodes are
deterministic), the statistics growing once the step's offspring is told. What is flown and
stored is the network that acts so on raw observations: theta with the normaliser folded into
its first layer (`fold`), so every command flies an elite as the search flew it; a parent drawn
from the archive goes on as the theta that, with the statistics of the moment, folds back to it
(`unfold`), where dqd-rl goes on from the parent's raw theta under the new statistics.

All of it is the emitter's state, pickled with the scheduler, so a run resumes exactly.

Map: K_NEAREST, EXPLORE_TOP, STEPS_PER_PARENT, LEARNING_RATE, L2_COEFF, OBS_COLLECT_PROB,
OBS_FLOOR; `novelty`, `es_gradient`, `novelty_bias`, `best_recent_or_best`; `fold`, `unfold`;
`MEESEmitter`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from ribs.emitters import EmitterBase
from ribs.emitters.opt import AdamOpt

from qdsearch.algorithms.gradients import centred_ranks

K_NEAREST = 10  # dqd-rl's k for novelty
EXPLORE_TOP = 5  # the most novel elites that share 0.9 of an explore phase's draw
STEPS_PER_PARENT = 10  # dqd-rl's nb_consecutive_steps
LEARNING_RATE = 0.01  # dqd-rl's Adam step
L2_COEFF = 0.005  # dqd-rl's l2_coeff
OBS_COLLECT_PROB = 0.001  # dqd-rl's obs_collect_prob: a negative sample's episode feeds the normaliser
OBS_FLOOR = 1e-2  # dqd-rl's RunningStat: squares and count start at it (mean 0, std 1); the variance's floor


def novelty(points: np.ndarray, against: np.ndarray, skip_self: bool = False) -> np.ndarray:
    """Each point's mean squared distance to its K_NEAREST nearest rows of `against` (fewer if
    `against` has fewer); with `skip_self`, one exact match (the point itself) is left out."""
    from scipy.spatial import cKDTree

    k = min(K_NEAREST + skip_self, len(against))
    distances = cKDTree(against).query(points, k=k)[0].reshape(len(points), k)
    if skip_self and k > 1:  # a zero first is the point itself; else the farthest is one too many
        distances = np.where(distances[:, :1] == 0.0, distances[:, 1:], distances[:, :-1])
    return (distances[:, :K_NEAREST] ** 2).mean(axis=1)


def es_gradient(scores: np.ndarray, eps: np.ndarray) -> np.ndarray:
    """dqd-rl's ES gradient of `scores` (the samples' in sample_points' order: +eps, then -eps):
    sum_j eps_j (rank(+j) - rank(-j)) / pairs, over the scores' centred ranks."""
    ranks = centred_ranks(scores)
    pairs = len(eps)
    return (ranks[:pairs] - ranks[pairs:]) @ eps / pairs


def novelty_bias(novelties: np.ndarray) -> np.ndarray:
    """dqd-rl's explore draw: the EXPLORE_TOP most novel share 0.9 by their novelty, all 0.1."""
    weights = np.full(len(novelties), 0.1 / len(novelties))
    top = np.argsort(-novelties, kind="stable")[:EXPLORE_TOP]
    total = novelties[top].sum()
    weights[top] += 0.9 * (novelties[top] / total if total > 0 else np.full(len(top), 1 / len(top)))
    return weights


def best_recent_or_best(cells: np.ndarray, scores: np.ndarray, discovered: list[int],
                        rng: np.random.Generator) -> int:
    """dqd-rl's exploit draw: the position in `cells` of the best score half the time (always
    under 5 cells), else of one of the 2 best of the last discovered cells still held."""
    if rng.random() < 0.5 or len(cells) < 5:
        return int(np.argmax(scores))
    recent = discovered[-5:] if len(discovered) >= 10 else discovered[-max(1, len(discovered) // 2):]
    place = {int(cell): i for i, cell in enumerate(cells)}
    held = [place[cell] for cell in dict.fromkeys(recent) if cell in place]
    if not held:
        return int(np.argmax(scores))
    best = sorted(held, key=lambda i: -scores[i])[:2]
    weights = scores[best] - scores[best].min() + 1.0
    return best[int(rng.choice(len(best), p=weights / weights.sum()))]


def fold(thetas: np.ndarray, first_layer: tuple[int, int], mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """Networks acting on raw observations as `thetas` (rows) act on normalised ones: the first
    layer's W / std (each input's column), its bias b - (W / std) @ mean."""
    out, inputs = first_layer
    folded = np.array(thetas, dtype=float, ndmin=2)
    weights = folded[:, :out * inputs].reshape(-1, out, inputs) / std
    folded[:, :out * inputs] = weights.reshape(len(folded), -1)
    folded[:, out * inputs:out * inputs + out] -= weights @ mean
    return folded


def unfold(solution: np.ndarray, first_layer: tuple[int, int], mean: np.ndarray,
           std: np.ndarray) -> np.ndarray:
    """The theta that `fold` makes `solution` with this normaliser."""
    out, inputs = first_layer
    theta = np.array(solution, dtype=float)
    weights = theta[:out * inputs].reshape(out, inputs)
    theta[out * inputs:out * inputs + out] += weights @ mean
    theta[:out * inputs] = (weights * std).ravel()
    return theta


class MEESEmitter(EmitterBase):
    """One ME-ES chain (see the module's docstring). `batch_size` is not used: each step makes
    one offspring. Its samples (mirrored, even) are drawn by the loop (gradients.noise).
    `first_layer` (a network's first layer, (outputs, observations)): its observations are
    normalised; None (the linear policy): they are not."""

    def __init__(self, archive: Any, *, x0: np.ndarray, batch_size: int, seed: int,
                 first_layer: tuple[int, int] | None = None) -> None:
        super().__init__(archive, solution_dim=len(x0), bounds=None, lower_bounds=None, upper_bounds=None)
        self.rng = np.random.default_rng(seed)
        self.opt = AdamOpt(np.array(x0, dtype=float), lr=LEARNING_RATE, l2_coeff=L2_COEFF)
        self.started = False  # x0 flown
        self.explore = True  # toggled before each new parent: the first phase exploits
        self.steps = 0  # ES steps from the current parent
        self.offspring = np.empty((0, archive.measure_dim))  # every offspring's scaled measures
        self.best_train: dict[int, float] = {}  # a cell's score: its step's best sample return
        self.discovered: list[int] = []  # cells in the order offspring first filled them
        self.step_best: float | None = None  # the last step's best sample return
        self.first_layer = first_layer
        if first_layer is not None:
            self.obs_sum, self.obs_squares = np.zeros(first_layer[1]), np.full(first_layer[1], OBS_FLOOR)
            self.obs_count = OBS_FLOOR
            self.collect_rng = np.random.default_rng([seed, 0x0B5])  # apart from the parents' draws
        self.observed: np.ndarray | None = None  # this step's observations, counted after its tell

    def normaliser(self) -> tuple[np.ndarray, np.ndarray]:
        """The observations' running mean and standard deviation (its variance at least OBS_FLOOR)."""
        mean = self.obs_sum / self.obs_count
        return mean, np.sqrt(np.maximum(self.obs_squares / self.obs_count - mean ** 2, OBS_FLOOR))

    def flown(self, thetas: np.ndarray) -> np.ndarray:
        """The networks flown for `thetas` (rows): each with the normaliser folded in."""
        return np.asarray(thetas) if self.first_layer is None else fold(thetas, self.first_layer,
                                                                        *self.normaliser())

    def collecting(self, samples: int) -> np.ndarray:
        """Which of a step's samples (sample_points' order: +eps, then -eps) have their episodes'
        observations counted: each negative sample with probability OBS_COLLECT_PROB."""
        if self.first_layer is None:
            return np.empty(0, dtype=int)
        pairs = samples // 2
        return pairs + np.flatnonzero(self.collect_rng.random(pairs) < OBS_COLLECT_PROB)

    def observe(self, observations: np.ndarray) -> None:
        """Observations of this step's collected episodes: counted once its offspring is told."""
        self.observed = np.asarray(observations, dtype=float)

    def scaled(self, measures: np.ndarray) -> np.ndarray:
        """Measures as fractions of the archive's ranges."""
        low, high = self.archive.lower_bounds, self.archive.upper_bounds
        return (np.asarray(measures, dtype=float) - low) / (high - low)

    def es_point(self) -> np.ndarray | None:
        """The theta whose samples this iteration flies (None: the first, which flies x0 alone);
        a new parent drawn first when the last one has had its steps."""
        if not self.started:
            return None
        if self.steps % STEPS_PER_PARENT == 0:
            self.explore = not self.explore
            self.opt.reset(self.parent())
        return self.opt.theta.copy()

    def parent(self) -> np.ndarray:
        """An elite of the archive, drawn as the phase draws (explore: novelty, exploit: scores)."""
        elites = self.archive.data(["index", "measures", "solution"])
        if self.explore:
            novelties = novelty(self.scaled(elites["measures"]), self.offspring, skip_self=True)
            chosen = int(self.rng.choice(len(novelties), p=novelty_bias(novelties)))
        else:
            # an elite no step of the chain made (a warm start's) has no score: never the best
            scores = np.array([self.best_train.get(int(cell), -np.inf) for cell in elites["index"]])
            chosen = best_recent_or_best(elites["index"], scores, self.discovered, self.rng)
        if self.first_layer is None:
            return elites["solution"][chosen]
        # a stored network goes on as the theta that the statistics of the moment fold back to it
        return unfold(elites["solution"][chosen], self.first_layer, *self.normaliser())

    def es_step(self, objectives: np.ndarray, measures: np.ndarray, eps: np.ndarray) -> None:
        """One Adam step of theta on the ES gradient of the samples' returns (exploit) or novelty
        (explore); the samples flown at theta + sigma * eps, then theta - sigma * eps."""
        scores = novelty(self.scaled(measures), self.offspring) if self.explore else objectives
        self.opt.step(es_gradient(np.asarray(scores, dtype=float), eps))
        self.steps += 1
        self.step_best = float(np.max(objectives))

    def ask(self) -> np.ndarray:
        """The network of the chain's theta: x0 at first (the optimiser starts there), then each
        step's."""
        return self.flown(self.opt.theta[None]).copy()

    def tell(self, solution: np.ndarray, objective: np.ndarray, measures: np.ndarray,
             add_info: dict, **fields: Any) -> None:
        """The offspring told: its measures join the novelty set; a cell it made or improved takes
        its step's best sample return as its score (x0: its own return)."""
        self.offspring = np.concatenate([self.offspring, self.scaled(measures)])
        best = float(objective[0]) if not self.started else self.step_best
        self.started = True
        if add_info["status"][0] > 0:
            cell = int(self.archive.index_of(np.asarray(measures))[0])
            self.best_train[cell] = best
            if add_info["status"][0] == 2:
                self.discovered.append(cell)
        if self.observed is not None and len(self.observed):  # dqd-rl: after the offspring's insert
            self.obs_sum = self.obs_sum + self.observed.sum(axis=0)
            self.obs_squares = self.obs_squares + (self.observed ** 2).sum(axis=0)
            self.obs_count += len(self.observed)
        self.observed = None
