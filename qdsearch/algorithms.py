"""The algorithms: an archive of elites, emitters that propose solutions, a scheduler tying them.

Map:
- the ALGORITHMS table (--algorithm): each row's archive kwargs, result archive and emitters;
- the ARCHIVES table (--archive): how each kind of archive is made (`grid_archives`,
  `cvt_archives`: a CVT's centroids made once per run, by k-means from the run's seed), where its
  cells lie (`cell_positions`) and an empty archive of the same cells (`empty_like`);
- `task_of`, `derive_seeds` (the archive's and each emitter's seed, from the run's),
  `archive_shape` and `build_scheduler` (a run's pyribs Scheduler, from its config).
"""

from __future__ import annotations

from typing import Any, Callable

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
# - line_map_elites: sphere.py's row of the same name: IsoLineEmitters (Vassiliades & Mouret
#   2018) with iso_sigma --sigma0 and line_sigma --line_sigma (0.2, as there).
# - cma_me_mu, cma_me_rd: sphere.py's "cma_me_imp_mu" and "cma_me_rd": CMA-ME with mu
#   selection, and with the random-direction ranker ("2rd"); cma_me is its "cma_me_imp".
# - sep_cma_mae, lm_ma_mae: sphere.py's scalable CMA-MAE rows (Tjanaka et al. 2023): cma_mae
#   with Sep-CMA-ES or LM-MA-ES, for policies of thousands of weights.
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
    "line_map_elites": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "IsoLineEmitter",
        "emitter_kwargs": lambda config: {"iso_sigma": config.sigma0, "line_sigma": config.line_sigma},
    },
    "cma_me_mu": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config.sigma0, "ranker": "2imp",
                                          "selection_rule": "mu", "restart_rule": "no_improvement"},
    },
    "cma_me_rd": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config.sigma0, "ranker": "2rd",
                                          "selection_rule": "filter", "restart_rule": "no_improvement"},
    },
}
# The scalable CMA-MAE rows: cma_mae's archive and emitters with an ES whose cost grows linearly in
# the solution's size (a diagonal covariance; a limited memory) instead of quadratically.
for _name, _es in (("sep_cma_mae", "sep_cma_es"), ("lm_ma_mae", "lm_ma_es")):
    ALGORITHMS[_name] = {**ALGORITHMS["cma_mae"], "emitter_kwargs": lambda config, es=_es: {
        **ALGORITHMS["cma_mae"]["emitter_kwargs"](config), "es": es}}


def task_of(config: Any) -> Environment:
    """The run's row of ENVIRONMENTS (config: a RunConfig, run_config.py)."""
    return ENVIRONMENTS[config.env]


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent seeds for the archive and each emitter, all fixed by the one run seed."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(count)]


def archive_shape(config: Any) -> dict[str, Any]:
    """What every archive of the run shares: the solution size, the measures' ranges, the offset."""
    task = task_of(config)
    return dict(solution_dim=task.solution_dim, ranges=[MEASURES[name].range for name in config.measures],
                qd_score_offset=task.qd_offset)


def grid_archives(config: Any) -> Callable[..., Any]:
    """Empty grid archives of the run: --grid cells along each of its measures."""
    from ribs.archives import GridArchive

    shape, dims = archive_shape(config), (config.grid,) * len(config.measures)
    return lambda **kwargs: GridArchive(**shape, dims=dims, **kwargs)


CVT_SAMPLES = 100_000  # points k-means clusters into the centroids (pyribs' default)


def cvt_archives(config: Any) -> Callable[..., Any]:
    """Empty CVT archives of the run: --cells centroids, made once by k-means over points drawn
    uniformly in the measures' ranges (pyribs' k_means_centroids), seeded from the run's seed
    apart from the archive's and emitters' seeds (a grid run's seeds stay as they were)."""
    from ribs.archives import CVTArchive, k_means_centroids

    shape = archive_shape(config)
    seed = int(np.random.SeedSequence([config.seed, 0xC07]).generate_state(1)[0])
    centroids, _ = k_means_centroids(centroids=config.cells, ranges=shape["ranges"],
                                     samples=CVT_SAMPLES, seed=seed)
    return lambda **kwargs: CVTArchive(**shape, centroids=centroids, **kwargs)


def grid_positions(archive: Any, indices: np.ndarray) -> np.ndarray:
    return archive.int_to_grid_index(indices).astype(float)


def cvt_positions(archive: Any, indices: np.ndarray) -> np.ndarray:
    """A CVT cell's place: its centroid, in units of its measures' ranges."""
    return (archive.centroids[indices] - archive.lower_bounds) / (archive.upper_bounds - archive.lower_bounds)


def empty_grid(archive: Any) -> Any:
    from ribs.archives import GridArchive

    return GridArchive(solution_dim=archive.solution_dim, dims=archive.dims,
                       ranges=list(zip(archive.lower_bounds, archive.upper_bounds)))


def empty_cvt(archive: Any) -> Any:
    from ribs.archives import CVTArchive

    return CVTArchive(solution_dim=archive.solution_dim, centroids=archive.centroids,
                      ranges=list(zip(archive.lower_bounds, archive.upper_bounds)))


# The kinds of archive (--archive): the flag that sizes it, how a run makes its archives, where a
# cell lies (to find the nearest occupied one), and an empty archive of the same cells (evaluate's
# means). A grid grows
# as cells^measures, so it takes at most MAX_GRID_MEASURES; a CVT archive has --cells cells
# whatever the number of measures (QDax's default for QD-RL: 1,024).
ARCHIVES: dict[str, dict[str, Any]] = {
    "grid": {"class": "GridArchive", "size": "grid", "make": grid_archives,
             "positions": grid_positions, "empty_like": empty_grid},
    "cvt": {"class": "CVTArchive", "size": "cells", "make": cvt_archives,
            "positions": cvt_positions, "empty_like": empty_cvt},
}


def kind_of(archive: Any) -> str | None:
    """The ARCHIVES name of an archive object's kind (None: not one of ours)."""
    return next((name for name, row in ARCHIVES.items() if type(archive).__name__ == row["class"]), None)


def build_scheduler(config: Any, x0: np.ndarray | None = None):
    """The archive, emitters and scheduler of `config.algorithm`, seeded from `config.seed`.

    The emitters start from `x0` (default: zeros, as in the tutorial).
    """
    from ribs import emitters as ribs_emitters
    from ribs.schedulers import Scheduler

    spec = ALGORITHMS[config.algorithm]
    # A result archive's seed comes last, so the other seeds are those of a run without one.
    archive_seed, *emitter_seeds, result_seed = derive_seeds(config.seed, config.n_emitters + 2)
    make = ARCHIVES[config.archive]["make"](config)
    archive = make(seed=archive_seed, **spec["archive"](config))
    result_archive = make(seed=result_seed) if spec["result_archive"] else None
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
