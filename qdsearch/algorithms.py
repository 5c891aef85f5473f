"""The algorithms: an archive of elites, emitters that propose solutions, a scheduler tying them.

Map:
- the ALGORITHMS table (--algorithm): each row's archive kwargs, result archive and emitters;
- `task_of`, `derive_seeds` (the archive's and each emitter's seed, from the run's),
  `archive_grid` and `build_scheduler` (a run's pyribs Scheduler, from its config).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from qdsearch.family import Environment
from qdsearch.tasks import ENVIRONMENTS, MEASURES

# One row per algorithm, in the spirit of pyribs' examples/sphere.py: the archive's extra kwargs,
# whether a separate result archive keeps the elites, and the emitter class with its kwargs, each
# a small function of the run's config. All rows share the grid, the seeds, x0 and the batch
# size, so every algorithm asks n_emitters * batch_size solutions per iteration. (A flag only some
# algorithms use says so in its entry of SEARCH_FLAGS: an experiment sweeps it for them alone, and
# labels name it for them alone.)
# - cma_me: the tutorial's CMA-ME (EvolutionStrategyEmitter, two-stage improvement ranker).
# - cma_mae: pyribs' CMA-MAE tutorial and sphere.py's "cma_mae" row: a soft archive with
#   learning_rate (--learning_rate; 0.01 there, 0.5 here: docs/algorithms.md) and threshold_min (0
#   there for objectives in [0, 100]; here the task's QD offset, below almost every episode's
#   return), a plain result archive of the same grid that keeps the best solutions (metrics,
#   heatmaps and archive.pkl come from it), and emitters with the "imp" ranker, "mu" selection
#   and "basic" restarts.
# - map_elites: sphere.py's "map_elites" row: GaussianEmitters that mutate random elites with a
#   fixed sigma (--sigma0). (Lunar Lander's policy argmax(W @ obs) ignores W's scale, so there
#   only sigma relative to the elites' weights matters; tanh(W @ obs) does not ignore it.)
ALGORITHMS: dict[str, dict[str, Any]] = {
    "cma_me": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config.sigma0, "ranker": "2imp"},
    },
    "cma_mae": {
        "archive": lambda config: {"learning_rate": config.learning_rate,
                                   "threshold_min": task_of(config).qd_offset},
        "result_archive": True,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config.sigma0, "ranker": "imp",
                                          "selection_rule": "mu", "restart_rule": "basic"},
    },
    "map_elites": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "GaussianEmitter",
        "emitter_kwargs": lambda config: {"sigma": config.sigma0},
    },
}


def task_of(config: Any) -> Environment:
    """The run's row of ENVIRONMENTS (config: a RunConfig, run_config.py)."""
    return ENVIRONMENTS[config.env]


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent seeds for the archive and each emitter, all fixed by the one run seed."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(count)]


def archive_grid(config: Any) -> dict[str, Any]:
    """The archive's cells: --grid of them along each of the run's --measures, over its range."""
    measures = config.measures
    task = task_of(config)
    return dict(solution_dim=task.solution_dim, dims=(config.grid,) * len(measures),
                ranges=[MEASURES[name].range for name in measures], qd_score_offset=task.qd_offset)


def build_scheduler(config: Any, x0: np.ndarray | None = None):
    """The archive, emitters and scheduler of `config.algorithm`, seeded from `config.seed`.

    The emitters start from `x0` (default: zeros, as in the tutorial).
    """
    from ribs import emitters as ribs_emitters
    from ribs.archives import GridArchive
    from ribs.schedulers import Scheduler

    spec = ALGORITHMS[config.algorithm]
    # A result archive's seed comes last, so the other seeds are those of a run without one.
    archive_seed, *emitter_seeds, result_seed = derive_seeds(config.seed, config.n_emitters + 2)
    grid = archive_grid(config)
    archive = GridArchive(**grid, seed=archive_seed, **spec["archive"](config))
    result_archive = GridArchive(**grid, seed=result_seed) if spec["result_archive"] else None
    emitter_class = getattr(ribs_emitters, spec["emitter"])
    emitters = [
        emitter_class(
            archive,
            x0=np.zeros(task_of(config).solution_dim) if x0 is None else x0,
            batch_size=config.batch_size,
            seed=emitter_seed,
            **spec["emitter_kwargs"](config),
        )
        for emitter_seed in emitter_seeds
    ]
    return Scheduler(archive, emitters, result_archive=result_archive)
