"""A learning row's part of a run (ALGORITHMS' `learns`: pga_me, cma_mega_td3_es): its TD3
learner (algorithms/td3.py), fed with every flown transition, and what the run does with it, as
dqd-rl's manager does (src/manager.py):

- the greedy actor is flown at the end of each iteration's last batch and inserted into the archive
  as it is, outside the emitters' ranking (`with_greedy`, `insert_greedy`);
- while that batch flies, the critic takes its steps (`train`) on the transitions of the
  iterations before: the driver would otherwise wait for the workers, so the learning costs a run
  no time while it is shorter than the flights (docs/learning.md);
- the batches' transitions (a DQD row's gradient samples' too) come back with their chunks and
  are held (`collect`) until the iteration is told, then added to the buffer in the batch's order
  (`commit`), whatever the number of workers;
- CMA-MEGA (TD3, ES) takes its points' objective gradients from the critic (`objective_gradients`).

The checkpoint holds the last completed iteration: the buffer changes only when an iteration is
told, at the moment the run snapshots its scheduler, so `snapshot` copies the learner's networks
and random state then (a few MB), and `checkpoint` adds the buffer's rows as they still are.

Map: `Learning` (`of`: a run's, or None; `restore`).
"""

from __future__ import annotations

import pickle
from typing import Any

import numpy as np

from qdsearch.algorithms import ALGORITHMS, Learns, RowConfig, task_of
from qdsearch.search.engine import in_pair_order


class Learning:
    """The learner of a run and the transitions of its iteration in flight."""

    def __init__(self, learns: Learns, learner: Any) -> None:
        self.learns, self.learner = learns, learner
        self.pending: list[np.ndarray] = []  # this iteration's transitions, in flight order
        self.greedy: np.ndarray | None = None  # the actor as flown in this iteration's last batch
        self.frozen = pickle.dumps(learner.state())  # as of the last told iteration

    @classmethod
    def of(cls, config: RowConfig, scheduler: Any, saved: dict | None = None) -> Learning | None:
        """A run's learning (None for a row that does not learn): new, from the emitters' start,
        or as a checkpoint `saved` it. Its learner is handed to the emitters that use one."""
        learns = ALGORITHMS[config.algorithm].learns
        if learns is None:
            return None
        from qdsearch.algorithms.td3 import Learner  # JAX, optional: only a learning run loads it

        if saved is None:
            x0 = scheduler.emitters[0].x0
            learner = Learner(config.network, task_of(config).shape, x0, config.buffer_size, config.seed)
        else:
            learner = Learner.restore(saved["learner"], saved["buffer"])
        for emitter in scheduler.emitters:
            if hasattr(emitter, "learner"):
                emitter.learner = learner
        return cls(learns, learner)

    def with_greedy(self, batch: np.ndarray) -> np.ndarray:
        """The iteration's last batch, the greedy actor after it (as it is now: the critic's steps
        while the batch flies move it on)."""
        self.greedy = self.learner.greedy()
        return np.concatenate([batch, self.greedy[None]])

    def train(self) -> None:
        """The critic's steps of an iteration, while its last batch flies."""
        self.learner.train(self.learns.critic_steps)

    def collect(self, chunks: list) -> list[np.ndarray]:
        """The chunks' rows of results; their transitions held for `commit`, in pair order."""
        self.pending.extend(in_pair_order([transitions for _, transitions in chunks]))
        return [rows for rows, _ in chunks]

    def objective_gradients(self, points: np.ndarray) -> np.ndarray:
        return self.learner.objective_gradients(points)

    def insert_greedy(self, scheduler: Any, objective: float, measures: np.ndarray) -> None:
        """The greedy actor into the archive (and the result archive, if apart), as dqd-rl inserts it."""
        for archive in {id(a): a for a in (scheduler.archive, scheduler.result_archive)}.values():
            archive.add(self.greedy[None], np.array([objective]), np.asarray(measures)[None])

    def commit(self) -> None:
        """The iteration is told: its transitions join the buffer, and the learner is frozen."""
        if self.pending:
            self.learner.buffer.add(np.concatenate(self.pending))
        self.pending = []
        self.frozen = pickle.dumps(self.learner.state())

    def checkpoint(self) -> dict[str, Any]:
        """The learner as of the last told iteration, and its buffer."""
        return {"learner": pickle.loads(self.frozen), "buffer": self.learner.buffer.state()}
