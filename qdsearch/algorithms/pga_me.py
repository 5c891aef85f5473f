"""PGA-ME (Nilsson & Cully 2021, "Policy Gradient Assisted MAP-Elites") as dqd-rl runs it
(icaros-usc/dqd-rl, config/algorithms/pga_me.gin, src/emitters/pga_emitter.py): each batch half
genetic, half policy gradient.

- The genetic half is pyribs' IsoLineEmitter (iso_sigma --sigma0, line_sigma --line_sigma;
  dqd-rl's 0.005 and 0.05): the larger half of the batch.
- The policy-gradient half: elites drawn uniformly from the archive, each taken PG_STEPS Adam
  steps up the TD3 critic (td3.py's `Learner.improve`). While the archive is empty (the first
  iteration), they are x0 plus Gaussian noise of PG_SIGMA0 (dqd-rl's PGAEmitter.sigma0).
- The TD3 greedy actor is flown beside the batch each iteration and inserted as it is
  (search/learning.py): dqd-rl's 50 + 50 batch is --batch_size 99 here, 50 genetic and 49 PG,
  plus the actor.

The learner lives in the run, not in the emitter: the run hands it over before each ask
(`learner`), and the emitter's pickle leaves it out (the checkpoint keeps it apart).

Map: PG_SIGMA0; `PGAMEEmitter`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from ribs.emitters import EmitterBase, IsoLineEmitter

PG_SIGMA0 = 0.02  # dqd-rl's PGAEmitter.sigma0: the first iteration's noise around x0


class PGAMEEmitter(EmitterBase):
    """A batch of `batch_size`: its larger half iso+line variation, the rest PG variation."""

    def __init__(self, archive: Any, *, x0: np.ndarray, batch_size: int, seed: int, iso_sigma: float,
                 line_sigma: float) -> None:
        super().__init__(archive, solution_dim=archive.solution_dim, bounds=None, lower_bounds=None,
                         upper_bounds=None)
        genetic_seed, own_seed = np.random.SeedSequence(seed).generate_state(2)
        self._batch_size = batch_size
        self.genetic = IsoLineEmitter(archive, iso_sigma=iso_sigma, line_sigma=line_sigma, x0=x0,
                                      batch_size=batch_size - batch_size // 2, seed=int(genetic_seed))
        self.x0 = np.asarray(x0, dtype=np.float64)
        self.rng = np.random.default_rng(int(own_seed))
        self.learner: Any = None  # the run's td3.Learner, handed over before each ask

    @property
    def batch_size(self) -> int:
        return self._batch_size

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "learner": None}

    def ask(self) -> np.ndarray:
        return np.concatenate([self.genetic.ask(), self.gradient_half(self._batch_size // 2)])

    def gradient_half(self, count: int) -> np.ndarray:
        """`count` elites improved by the critic (x0 plus noise while the archive is empty)."""
        if self.archive.empty:
            return self.x0 + self.rng.normal(scale=PG_SIGMA0, size=(count, len(self.x0)))
        return self.learner.improve(self.archive.sample_elites(count)["solution"])

    def tell(self, solution: np.ndarray, objective: np.ndarray, measures: np.ndarray, add_info: dict,
             **fields: Any) -> None:
        """Nothing to learn from the results here: the critic learns from the episodes."""
