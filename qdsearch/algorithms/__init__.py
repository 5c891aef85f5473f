"""qdsearch.algorithms: the algorithms: an archive of elites, emitters that propose solutions, a
scheduler tying them. This module is the layer's table of them.

The layer's modules, imports going down the list only (this table last):
- gradients: the DQD rows' gradients, estimated from mirrored samples flown around a point;
- me_es: ME-ES's emitter, a chain of ES steps on the return or on novelty (dqd-rl's);
- pga_me: PGA-ME's emitter, half iso+line variation, half policy-gradient steps on a TD3 critic;
- td3: the TD3 learner of the learning rows, in JAX (optional: imported by a learning run alone).

Map:
- the ALGORITHMS table (--algorithm): each row's archive kwargs, result archive and emitters;
- the ARCHIVES table (--archive): how each kind of archive is made (`grid_archives`,
  `cvt_archives`: a CVT's centroids made once per run by `k_means` from the run's seed), where its
  cells lie (`cell_positions`) and an empty archive of the same cells (`empty_like`); MAX_CELLS;
- the DQD rows (`gradient_arborescence`), ME-ES, the learning rows (`Learns`: PGA-ME, CMA-MEGA (TD3,
  ES)), `evaluations_per_iteration`, and what a row's emitters, archives and replay buffer hold in
  memory (ES_BYTES, `memory_needed`, `buffer_bytes`);
- `RowConfig`: what the layer reads of a run's settings;
- `task_of`, `derive_seeds` (the archive's and each emitter's seed, from the run's),
  `archive_shape` and `build_scheduler` (a run's pyribs Scheduler, from its config).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, Protocol

import numpy as np

from qdsearch.algorithms.me_es import MEESEmitter
from qdsearch.algorithms.pga_me import PGAMEEmitter
from qdsearch.tasks import ENVIRONMENTS, TaskConfig, measure_bounds, returns_of, shape_of
from qdsearch.tasks.family import Environment
from qdsearch.tasks.policies import Policy
from qdsearch.tasks.transitions import transition_width


class RowConfig(TaskConfig, Protocol):
    """What this layer reads of a run's settings (the config layer's RunConfig is one): the task's
    (tasks.TaskConfig), the row and its emitters' settings, the archive's cells and the policy."""

    algorithm: str
    archive: str
    grid: int | None
    cells: int | None
    n_emitters: int
    batch_size: int
    sigma0: float
    learning_rate: float
    line_sigma: float
    novelty_threshold: float
    bandwidth: float
    es_samples: int
    es_sigma: float
    buffer_size: int
    network: Policy  # the policy its settings make


@dataclasses.dataclass(frozen=True)
class Emitters:
    """A group of pyribs emitters of one class: `kind` names it in ribs.emitters (or is the class,
    one of ours), `kwargs` gives its keyword arguments from the run's config (the archive, x0,
    batch size and seed come from build_scheduler)."""

    kind: str | type
    kwargs: Callable[[RowConfig], dict[str, Any]]
    es: str | None = None  # the evolution strategy each keeps over the solution's weights, if any


@dataclasses.dataclass(frozen=True)
class Learns:
    """How a learning row uses its TD3 learner (td3.py, driven by search/learning.py): the critic
    steps it takes while each iteration's last batch flies, and whether the critic gives a DQD
    row's objective gradient. Every learning row flies the greedy actor beside its batch."""

    critic_steps: int  # dqd-rl's train_critics_itrs
    objective_gradient: bool = False


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """A row of ALGORITHMS: the pyribs objects of one QD algorithm, each a small function of the
    run's config, so that every row asks n_emitters * batch_size solutions per iteration.

    The run's own archive (grid or CVT, --archive) is the one measured, saved and shown. A row
    either searches in it (`archive`: its extra kwargs, such as CMA-MAE's learning rate) or in an
    archive of another kind (`search_archive`: a proximity, DNS or density archive, made from the
    config, the run's archive and a seed), the run's archive then being pyribs' result archive.
    """

    summary: str  # what --help and docs/algorithms.md call it
    emitters: tuple[Emitters, ...]  # one group: n_emitters of it; several: a bandit's pool
    archive: Callable[[RowConfig], dict[str, Any]] = lambda config: {}
    result_archive: bool = False  # a plain copy of the run's archive keeps the best (CMA-MAE)
    search_archive: Callable[..., Any] | None = None
    emitters_on_result: bool = False  # the search archive keeps no elites to sample (DDS)
    bandit: bool = False  # pyribs' BanditScheduler picks n_emitters of the pool (UCB1)
    flags: tuple[str, ...] = ()  # the flags of SEARCH_FLAGS only this row (and others) use
    dqd: bool = False  # its emitters need gradients: ask_dqd and tell_dqd, estimated (gradients.py)
    exact: bool = False  # a DQD row's gradients are the task's own (a benchmark function's)
    es_steps: bool = False  # its emitters step on their own ES samples first (ME-ES: me_es.py)
    learns: Learns | None = None  # it learns a TD3 critic from every flown transition (td3.py)

    @property
    def samples(self) -> bool:
        """Whether an iteration flies ES samples (--es_samples) before its batch."""
        return (self.dqd and not self.exact) or self.es_steps


def evolution_strategy(ranker: str, selection_rule: str = "filter", restart_rule: str = "no_improvement",
                       es: str | None = None, sigma_scale: float = 1.0) -> Emitters:
    """EvolutionStrategyEmitters (CMA-ES by default) starting at sigma_scale * --sigma0."""
    extra = {} if es is None else {"es": es}
    return Emitters("EvolutionStrategyEmitter", es=es or "cma_es", kwargs=lambda config: {
        "sigma0": sigma_scale * config.sigma0, "ranker": ranker, "selection_rule": selection_rule,
        "restart_rule": restart_rule, **extra})


def iso_line(iso_scale: float = 1.0, line_scale: float = 1.0) -> Emitters:
    """IsoLineEmitters: iso_sigma iso_scale * --sigma0, line_sigma line_scale * --line_sigma."""
    return Emitters("IsoLineEmitter", kwargs=lambda config: {"iso_sigma": iso_scale * config.sigma0,
                                                      "line_sigma": line_scale * config.line_sigma})


def soft_archive(config: RowConfig) -> dict[str, Any]:
    """CMA-MAE's archive: thresholds follow improvements at --learning_rate, from the QD offset."""
    return {"learning_rate": config.learning_rate, "threshold_min": returns_of(config).offset}


def measure_span(config: RowConfig) -> float:
    """The mean width of the measures' ranges: distances in measure space are fractions of it
    (pyribs' sphere.py sets its thresholds as fractions of its one width, 512)."""
    return float(np.mean([high - low for low, high in archive_shape(config)["ranges"]]))


def proximity_archive(local_competition: bool) -> Callable[..., Any]:
    """Novelty search's archive: a solution enters if its mean distance to its 15 nearest
    neighbours in measure space is at least --novelty_threshold of the measures' span."""
    def make(config: RowConfig, archive: Any, seed: int) -> Any:
        from ribs.archives import ProximityArchive

        return ProximityArchive(solution_dim=archive.solution_dim, measure_dim=archive.measure_dim,
                                k_neighbors=15,
                                novelty_threshold=config.novelty_threshold * measure_span(config),
                                local_competition=local_competition,
                                qd_score_offset=archive.qd_score_offset, seed=seed)
    return make


DNS_NEIGHBOURS = 3  # the DNS paper's k (Bahlous-Boldi et al. 2025)


def dns_archive(config: RowConfig, archive: Any, seed: int) -> Any:
    """Dominated Novelty Search's population: as many solutions as the run's archive has cells,
    the survivors those farthest from their 3 nearest fitter neighbours."""
    from ribs.archives import DNSArchive

    return DNSArchive(solution_dim=archive.solution_dim, measure_dim=archive.measure_dim,
                      capacity=archive.cells, k_neighbors=DNS_NEIGHBOURS,
                      qd_score_offset=archive.qd_score_offset, seed=seed)


def density_archive(config: RowConfig, archive: Any, seed: int) -> Any:
    """Density Descent Search's KDE over a reservoir of 10,000 measures, its bandwidth
    --bandwidth of the measures' span."""
    from ribs.archives import DensityArchive

    return DensityArchive(measure_dim=archive.measure_dim, buffer_size=10_000, density_method="kde",
                          bandwidth=config.bandwidth * measure_span(config), seed=seed)


# One row per algorithm, in the spirit of pyribs' examples/sphere.py (its row names in brackets
# where ours differ), with its step sizes scaled to ours: sphere.py's rows start at sigma 0.5,
# ours at --sigma0. All rows share the run's archive, seeds, x0 (zeros) and batch, so equal flags
# give equal budgets. docs/algorithms.md tells the rows, their sources and their measured ranks.
ALGORITHMS: dict[str, Algorithm] = {
    # The tutorial's CMA-ME (sphere.py's cma_me_imp).
    "cma_me": Algorithm("CMA-ME", (evolution_strategy("2imp"),)),
    # pyribs' CMA-MAE tutorial and sphere.py: a soft archive (learning rate 0.01 there, 0.5 here:
    # docs/algorithms.md; threshold_min 0 there for objectives in [0, 100], here the QD offset,
    # below almost every episode's return), and a result archive keeping the best.
    "cma_mae": Algorithm("CMA-MAE", (evolution_strategy("imp", "mu", "basic"),), archive=soft_archive,
                         result_archive=True, flags=("learning_rate",)),
    # GaussianEmitters mutating random elites with a fixed sigma. (Lunar Lander's policy
    # argmax(W @ obs) ignores W's scale, so there only sigma relative to the elites' weights
    # matters; tanh(W @ obs) does not ignore it.)
    "map_elites": Algorithm("MAP-Elites", (
        Emitters("GaussianEmitter", kwargs=lambda config: {"sigma": config.sigma0}),)),
    # Iso+line variation (Vassiliades & Mouret 2018), line_sigma 0.2 as in sphere.py.
    "line_map_elites": Algorithm("MAP-Elites (line)", (iso_line(),), flags=("line_sigma",)),
    # Multi-emitter MAP-Elites (sphere.py's me_map_elites): a BanditScheduler keeps n_emitters
    # active out of a pool of four kinds, n_emitters of each; the iso+line emitters' steps are
    # sphere.py's (0.01 and 0.1) relative to its sigma0 0.5 and line_sigma 0.2.
    "me_map_elites": Algorithm("ME-MAP-Elites (bandit)", (
        evolution_strategy("obj"), evolution_strategy("2rd"), evolution_strategy("2imp"),
        iso_line(0.02, 0.5)),
        bandit=True, flags=("line_sigma",)),
    # CMA-ME with mu selection (cma_me_imp_mu), and with the random-direction ranker (cma_me_rd).
    "cma_me_mu": Algorithm("CMA-ME (mu)", (evolution_strategy("2imp", "mu"),)),
    "cma_me_rd": Algorithm("CMA-ME (random direction)", (evolution_strategy("2rd"),)),
    # Novelty search with CMA-ES (ns_cma, from the DDS paper): a proximity archive, objectives
    # ignored; the run's archive keeps what it finds. NSLC ranks by novelty and local competition;
    # sphere.py's own nslc threshold is marked untuned, so both rows share ns_cma's.
    "ns_cma": Algorithm("Novelty search (CMA-ES)", (evolution_strategy("nov", "mu", "basic"),),
                        search_archive=proximity_archive(False), result_archive=True,
                        flags=("novelty_threshold",)),
    "nslc": Algorithm("NSLC (CMA-ES)", (evolution_strategy("nslc"),), search_archive=proximity_archive(True),
                      result_archive=True, flags=("novelty_threshold",)),
    # Dominated Novelty Search (not in sphere.py): pyribs' DNSArchive with the paper's iso+line
    # variation and k; its population as large as the run's archive.
    "dns": Algorithm("Dominated Novelty Search", (iso_line(),), search_archive=dns_archive,
                     result_archive=True, flags=("line_sigma",)),
    # Density Descent Search (dds, Lee et al. 2024): a KDE of the measures, CMA-ES descending it
    # from 3 * --sigma0 (sphere.py: 1.5 where its other rows take 0.5), sampling the run's archive.
    "dds": Algorithm("Density Descent Search",
                     (evolution_strategy("density", "mu", "basic", sigma_scale=3.0),),
                     search_archive=density_archive, result_archive=True, emitters_on_result=True,
                     flags=("bandwidth",)),
}
# The scalable CMA-MAE rows (Tjanaka et al. 2023): cma_mae with an ES whose cost grows linearly in
# the solution's size (a diagonal covariance; a limited memory) instead of quadratically.
for _name, _es in (("sep_cma_mae", "sep_cma_es"), ("lm_ma_mae", "lm_ma_es")):
    ALGORITHMS[_name] = dataclasses.replace(ALGORITHMS["cma_mae"], summary=f"CMA-MAE ({_es})",
                                            emitters=(evolution_strategy("imp", "mu", "basic", es=_es),))


def gradient_arborescence(ranker: str, restart_rule: str, selection_rule: str) -> Emitters:
    """GradientArborescenceEmitters (CMA-MEGA): a CMA-ES over the coefficients of the objective's
    and measures' normalised gradients, at --sigma0 (dqd-rl's sigma_g 1.0), branching the point
    that then steps by plain gradient ascent at lr 1.0 (dqd-rl's and sphere.py's)."""
    return Emitters("GradientArborescenceEmitter", kwargs=lambda config: {
        "sigma0": config.sigma0, "lr": 1.0, "ranker": ranker, "grad_opt": "gradient_ascent",
        "selection_rule": selection_rule, "restart_rule": restart_rule})


# The DQD rows, their gradients estimated from episodes (gradients.py: --es_samples mirrored
# samples at --es_sigma around each emitter's point). cma_mega_es is dqd-rl's CMA-MEGA (ES):
# selection "mu", restarts when no elite improves; cma_maega_es is sphere.py's cma_maega (ranker
# "imp", basic restarts, a soft archive and a result archive), its gradients estimated alike.
ALGORITHMS["cma_mega_es"] = Algorithm(
    "CMA-MEGA (ES gradients)", (gradient_arborescence("2imp", "no_improvement", "mu"),),
    flags=("es_samples", "es_sigma"), dqd=True)
ALGORITHMS["cma_maega_es"] = Algorithm(
    "CMA-MAEGA (ES gradients)", (gradient_arborescence("imp", "basic", "filter"),), archive=soft_archive,
    result_archive=True, flags=("learning_rate", "es_samples", "es_sigma"), dqd=True)
# sphere.py's cma_mega and cma_maega themselves: the same emitters on the task's exact gradients
# (a benchmark function's: tasks.point_gradients), each point scored and told before the batch.
ALGORITHMS["cma_mega"] = dataclasses.replace(
    ALGORITHMS["cma_mega_es"], summary="CMA-MEGA (exact gradients)", flags=(), exact=True)
ALGORITHMS["cma_maega"] = dataclasses.replace(
    ALGORITHMS["cma_maega_es"], summary="CMA-MAEGA (exact gradients)", flags=("learning_rate",), exact=True)


def first_layer(config: RowConfig) -> tuple[int, int] | None:
    """A network's first layer, (outputs, observations), whose inputs ME-ES normalises; None for
    the linear policy (no bias to fold the mean into)."""
    policy = config.network
    return None if not policy.hidden else (policy.hidden[0], task_of(config).shape[1])


# ME-ES (Colas et al. 2020) with dqd-rl's settings (me_es.py): a chain of ES steps per emitter,
# each on --es_samples mirrored samples at --es_sigma (dqd-rl: 200 at 0.02), its one offspring a
# step offered to the archive (--batch_size is not used).
ALGORITHMS["me_es"] = Algorithm(
    "ME-ES (explore-exploit)",
    (Emitters(MEESEmitter, es="adam", kwargs=lambda config: {"first_layer": first_layer(config)}),),
    flags=("es_samples", "es_sigma"), es_steps=True)


# The learning rows (dqd-rl's), with a TD3 learner (td3.py; JAX: requirements-learning.txt) whose
# greedy actor is flown beside each batch. PGA-ME: iso+line variation (--sigma0 as iso_sigma,
# --line_sigma; dqd-rl: 0.005 and 0.05) and policy-gradient variation, half each (pga_me.py), 300
# critic steps an iteration. CMA-MEGA (TD3, ES): dqd-rl's CMA-MEGA (ES) whose objective gradient is
# the critic's (600 critic steps: its batches are twice PGA-ME's), the measures' still ES's.
ALGORITHMS["pga_me"] = Algorithm(
    "PGA-ME (TD3 policy gradients)",
    (Emitters(PGAMEEmitter, kwargs=lambda config: {"iso_sigma": config.sigma0,
                                                   "line_sigma": config.line_sigma}),),
    flags=("line_sigma", "buffer_size"), learns=Learns(critic_steps=300))
ALGORITHMS["cma_mega_td3_es"] = dataclasses.replace(
    ALGORITHMS["cma_mega_es"], summary="CMA-MEGA (TD3 objective gradient, ES measure gradients)",
    flags=("es_samples", "es_sigma", "buffer_size"), learns=Learns(critic_steps=600, objective_gradient=True))


def evaluations_per_iteration(config: RowConfig) -> int:
    """The solutions an iteration flies: every emitter's batch, for a DQD row each emitter's point
    and its gradient samples too, and for ME-ES each emitter's samples and offspring (what
    metrics.json's `evaluations` counts; ME-ES's first iteration flies x0 alone), and a learning
    row's greedy actor."""
    row, emitters = ALGORITHMS[config.algorithm], config.n_emitters
    if row.es_steps:
        return emitters * (1 + config.es_samples)
    return (emitters * config.batch_size + (emitters * (1 + config.es_samples) if row.samples else 0)
            + (emitters if row.exact else 0) + (row.learns is not None))


# Bytes of memory an emitter's evolution strategy holds at its peak, as a function of the
# solution's weights n: tracemalloc's peak over two iterations at n = 1,000 and batch 30 (pyribs
# 0.12): CMA-ES keeps n x n matrices (7.2 n^2 doubles at the peak), sep-CMA-ES and LM-MA-ES a few
# vectors (170 n and 260 n doubles, the batch's included).
ES_BYTES: dict[str, Callable[[int], float]] = {"cma_es": lambda n: 8 * 7.2 * n * n,
                                               "sep_cma_es": lambda n: 8 * 180 * n,
                                               "lm_ma_es": lambda n: 8 * 270 * n,
                                               "adam": lambda n: 8 * 6 * n}  # ME-ES: theta, m, v, x0


def memory_needed(config: RowConfig, solution_dim: int) -> float:
    """Bytes the driver holds for a run: each emitter's evolution strategy (ES_BYTES; the other
    emitters keep a batch), each archive's solutions (its cells, at most, times the weights) and a
    learning row's replay buffer (twice: a checkpoint copies it)."""
    row = ALGORITHMS[config.algorithm]
    emitters = sum(ES_BYTES[group.es](solution_dim) if group.es else 8.0 * config.batch_size * solution_dim
                   for group in row.emitters) * config.n_emitters
    cells = config.grid ** len(config.measures) if config.archive == "grid" else config.cells
    return emitters + 8.0 * cells * solution_dim * (1 + row.result_archive) + buffer_bytes(config) * 2


def buffer_bytes(config: RowConfig) -> float:
    """A learning row's replay buffer when full: --buffer_size float32 transition rows (its
    observation twice, the action, the reward and the end); 0 for the other rows."""
    if ALGORITHMS[config.algorithm].learns is None:
        return 0.0
    actions, observations = task_of(config).shape
    return 4.0 * config.buffer_size * transition_width(observations, actions)


def task_of(config: RowConfig) -> Environment:
    """The run's row of ENVIRONMENTS."""
    return ENVIRONMENTS[config.env]


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent seeds for the archive and each emitter, all fixed by the one run seed."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(count)]


def archive_shape(config: RowConfig) -> dict[str, Any]:
    """What every archive of the run shares: the solution size (its policy's weights), the
    measures' ranges, the offset."""
    return dict(solution_dim=config.network.size(shape_of(config)), ranges=measure_bounds(config),
                qd_score_offset=returns_of(config).offset)


def grid_archives(config: RowConfig) -> Callable[..., Any]:
    """Empty grid archives of the run: --grid cells along each of its measures."""
    from ribs.archives import GridArchive

    shape, dims = archive_shape(config), (config.grid,) * len(config.measures)
    return lambda **kwargs: GridArchive(**shape, dims=dims, **kwargs)


CVT_SAMPLES = 100_000  # points k-means clusters into the centroids (pyribs' default)


def cvt_archives(config: RowConfig) -> Callable[..., Any]:
    """Empty CVT archives of the run: --cells centroids, made once by k-means over points drawn
    uniformly in the measures' ranges (pyribs' k_means_centroids), seeded from the run's seed
    apart from the archive's and emitters' seeds (a grid run's seeds stay as they were)."""
    from ribs.archives import CVTArchive

    shape = archive_shape(config)
    seed = int(np.random.SeedSequence([config.seed, 0xC07]).generate_state(1)[0])
    centroids = k_means(config.cells, tuple(map(tuple, shape["ranges"])), seed).copy()
    return lambda **kwargs: CVTArchive(**shape, centroids=centroids, **kwargs)


@functools.lru_cache(maxsize=16)
def k_means(cells: int, ranges: tuple, seed: int) -> np.ndarray:
    """pyribs' k-means centroids, kept for the runs of one process that share their seed, task
    and cells (a second of CPU each: an experiment's settings of one seed, a driver's resumes)."""
    from ribs.archives import k_means_centroids

    centroids, _ = k_means_centroids(centroids=cells, ranges=list(ranges), samples=CVT_SAMPLES, seed=seed)
    return centroids


def cvt_making(config: RowConfig) -> str:
    """What a run says before its CVT's k-means, which takes seconds at QD-RL's 1,024 cells."""
    return f"Making the CVT archive's {config.cells:,} centroids (k-means over {CVT_SAMPLES:,} points)..."


def grid_positions(archive: Any, indices: np.ndarray) -> np.ndarray:
    return archive.int_to_grid_index(indices).astype(float)


def cvt_positions(archive: Any, indices: np.ndarray) -> np.ndarray:
    """A CVT cell's place: its centroid, in units of its measures' ranges."""
    return (archive.centroids[indices] - archive.lower_bounds) / (archive.upper_bounds - archive.lower_bounds)


def empty_grid(archive: Any) -> Any:
    from ribs.archives import GridArchive

    return GridArchive(solution_dim=archive.solution_dim, dims=archive.dims,
                       ranges=list(zip(archive.lower_bounds, archive.upper_bounds)),
                       qd_score_offset=archive.qd_score_offset)


def empty_cvt(archive: Any) -> Any:
    from ribs.archives import CVTArchive

    return CVTArchive(solution_dim=archive.solution_dim, centroids=archive.centroids,
                      ranges=list(zip(archive.lower_bounds, archive.upper_bounds)),
                      qd_score_offset=archive.qd_score_offset)


MAX_CELLS = 1_000_000  # the most cells an archive may have: each keeps one solution


# The kinds of archive (--archive): the flag that sizes it, how a run makes its archives (and the
# line it says first, if making them takes a while), where a cell lies (to find the nearest occupied
# one), and an empty archive of the same cells and QD offset (evaluate's means, the corrected
# archive). A grid grows as cells^measures, so it takes at most MAX_GRID_MEASURES; a CVT archive
# has --cells cells whatever the number of measures (QDax's default for QD-RL: 1,024).
ARCHIVES: dict[str, dict[str, Any]] = {
    "grid": {"class": "GridArchive", "size": "grid", "make": grid_archives, "making": None,
             "positions": grid_positions, "empty_like": empty_grid},
    "cvt": {"class": "CVTArchive", "size": "cells", "make": cvt_archives, "making": cvt_making,
            "positions": cvt_positions, "empty_like": empty_cvt},
}


def kind_of(archive: Any) -> str | None:
    """The ARCHIVES name of an archive object's kind (None: not one of ours)."""
    return next((name for name, row in ARCHIVES.items() if type(archive).__name__ == row["class"]), None)


def emitter_class(kind: str | type) -> type:
    """An emitter group's class: ours as it is, else pyribs' of that name."""
    from ribs import emitters as ribs_emitters

    return kind if isinstance(kind, type) else getattr(ribs_emitters, kind)


def build_scheduler(config: RowConfig, x0: np.ndarray | None = None):
    """The archives, emitters and scheduler of `config.algorithm`, seeded from `config.seed`.

    The emitters start from `x0` (default: the policy's start, zeros for the linear policy as in
    the tutorial).
    """
    from ribs.schedulers import BanditScheduler, Scheduler

    row = ALGORITHMS[config.algorithm]
    # A result archive's seed comes last, so the other seeds are those of a run without one.
    archive_seed, *emitter_seeds, result_seed = derive_seeds(
        config.seed, len(row.emitters) * config.n_emitters + 2)
    make = ARCHIVES[config.archive]["make"](config)
    if row.search_archive is None:
        archive = make(seed=archive_seed, **row.archive(config))
        result_archive = make(seed=result_seed) if row.result_archive else None
    else:
        result_archive = make(seed=result_seed)
        archive = row.search_archive(config, result_archive, archive_seed)
    start = config.network.start(shape_of(config), config.seed) if x0 is None else x0
    sampled = result_archive if row.emitters_on_result else archive
    seeds = iter(emitter_seeds)
    emitters = [emitter_class(group.kind)(sampled, x0=start, batch_size=config.batch_size,
                                          seed=next(seeds), **group.kwargs(config))
                for group in row.emitters for _ in range(config.n_emitters)]
    if row.bandit:
        return BanditScheduler(archive, emitters, result_archive, num_active=config.n_emitters,
                               reselect="terminated")
    return Scheduler(archive, emitters, result_archive=result_archive)
