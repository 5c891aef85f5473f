"""The flag tables: every flag of every command, declared once (its default, its --help line, its
check, and its part in experiments; see flags.Flag), and the bounds on the sizes they make.

Map:
- sizes: MAX_CELLS, MAX_ITERATIONS, MAX_EMITTERS, MAX_SOLUTIONS, MAX_ROLLOUTS, MAX_WORKERS;
  `check_sizes` (`solutions_per_iteration`) and `check_rollouts` (what flags make together);
- the tables: CLUSTER_FLAGS, SEARCH_FLAGS, RESUME_FLAGS, SELECTION_FLAGS, TERRAIN_FLAGS;
- `seed_nouns` (what an env seed is to each family, for --help); `own_flags` and `ignores` (the
  flags an algorithm alone uses), `refuse_unused_row_flags` (an algorithm's or a policy's own
  flag given where no row uses it), `checked` (a value through its flag's check), `with_task` (a
  config's measures, checked against its task; `for_policy`: less what its policy ignores),
  `search_defaults` and `before_the_flags` (what runs recorded before a flag existed ran with).
"""

from __future__ import annotations

import dataclasses
import os
from types import SimpleNamespace
from typing import Any

from qdsearch.algorithms import (
    ALGORITHMS,
    ARCHIVES,
    CVT_SAMPLES,
    MAX_CELLS,
    evaluations_per_iteration,
    memory_needed,
)
from qdsearch.base.flags import (
    Flag,
    UsageError,
    boolean,
    distinct_names,
    finite_number,
    fraction,
    number_up_to,
    one_of,
    positive_float,
    positive_int,
    seed_list,
    seed_number,
    shown,
    whole_number_up_to,
)
from qdsearch.store.trackers import TRACKERS, check_tracks
from qdsearch.tasks import (
    DEFAULT_ENV,
    ENVIRONMENTS,
    FAMILIES,
    MEASURES,
    RESETS,
    check_episode,
    episode_of,
    family_measures,
)
from qdsearch.tasks.family import Family
from qdsearch.tasks.policies import POLICIES, STARTS, policy_of

# Every size a user gives is bounded before anything is allocated or written (check_sizes and the
# flags' checks): each bound is far past what QD papers run (1,000s of solutions per iteration,
# 10,000s of iterations), and what it lets a run hold at once stays within a laptop's memory.
MAX_GRID_MEASURES = 4  # a grid's cells are --grid ** measures
MAX_MEASURES = 10  # a CVT archive's: k-means and the nearest centroid work in any dimension
# The flags only some algorithms use (each row of ALGORITHMS names its own).
ROW_FLAGS = frozenset(flag for row in ALGORITHMS.values() for flag in row.flags)
POLICY_FLAGS = frozenset(flag for row in POLICIES.values() for flag in row.flags)  # so of the policies
BUDGETS = ("iterations", "evaluations")  # a run's two budgets: one is given, or neither
DEFAULT_GRID, DEFAULT_CVT_CELLS = 50, 1024  # the tutorial's 50 x 50; QDax's 1,024 centroids
MAX_ITERATIONS = 1_000_000  # the checkpoint keeps a row of metrics (~1 KB in memory) per iteration
MAX_EMITTERS = 10_000  # each keeps its own CMA-ES state (a weights x weights covariance)
MAX_SOLUTIONS = 100_000  # asked per iteration (n_emitters * batch_size): 173 MB of 216 weights
MAX_ROLLOUTS = 10_000_000  # solutions x terrains flown in one batch: ~32 bytes of results each
MAX_WORKERS = 1_024  # worker processes of a local cluster (and what memory holds: check_local_memory)
# A step size (--sigma0, --line_sigma) moves weights by that many times the policy's starting
# scale (zeros, steps of 1); 1e300 overflows the first ask, and iso+line steps compound from
# elite to elite, so a step far past any useful one is refused before a run starts.
MAX_STEP = 1_000.0
DEFAULT_HIDDEN = (128, 128)  # dqd-rl's MLP (QDax's examples: 64,64)
MAX_LAYERS, MAX_UNITS = 8, 4_096  # hidden layers, and units in each
MAX_EPISODE = 100_000  # steps in an episode (the tasks' own: 1,000 to 2,000)
MAX_ES_SAMPLES = 10_000  # gradient samples per emitter and iteration
MAX_EVALUATIONS = 10**12  # --evaluations: solutions flown in a run


def layer_widths(name: str, value: Any) -> list[int]:
    """Hidden layers' sizes: 128,128 (Fire may have made a number or a tuple of it already)."""
    parts = list(value) if isinstance(value, (tuple, list)) else str(value).split(",")
    try:
        widths = [int(str(part).strip()) for part in parts]
    except ValueError:
        widths = []
    if (isinstance(value, bool) or not 1 <= len(widths) <= MAX_LAYERS
            or not all(1 <= width <= MAX_UNITS for width in widths)):
        raise UsageError(f"--{name} takes 1 to {MAX_LAYERS} layer sizes from 1 to {MAX_UNITS:,}, such as "
                         f"128,128; got {shown(value)}")
    return widths


def even_samples(name: str, value: Any) -> int:
    """Mirrored samples come in pairs: an even count, 2 at least."""
    if whole_number_up_to(MAX_ES_SAMPLES)(name, value) % 2 or value < 2:
        raise UsageError(f"--{name} must be even (mirrored pairs) and at least 2, got {shown(value)}")
    return value


def default_measures(family: Family) -> tuple[str, ...]:
    """The default measures of the family's first task (the tutorial's, for the lander)."""
    return next(task.measures for task in ENVIRONMENTS.values() if task.family is family)


def seed_nouns() -> str:
    """What one --env_seed value is, in each family's words: "the terrain for Lunar Lander,
    BipedalWalker; the reset seed for Hopper, ..." (the search's --help is every task's)."""
    titles: dict[str, list[str]] = {}
    for family in FAMILIES:
        titles.setdefault(family.seed_noun, []).append(family.title)
    return "; ".join(f"the {noun} for {', '.join(named)}" for noun, named in titles.items())


def own_flags(algorithm: str) -> tuple[str, ...]:
    """The flags only some algorithms use that this one does (cma_mae: learning_rate), as its
    row of ALGORITHMS declares."""
    return ALGORITHMS[algorithm].flags


def ignores(algorithm: str, flag: str) -> bool:
    """Whether the algorithm ignores the flag (another algorithm's own, like cma_mae's rate)."""
    return flag in ROW_FLAGS and flag not in own_flags(algorithm)


def refuse_unused_row_flags(algorithms: list[str], given: list[str], policies: list[str]) -> None:
    """A row's own flag (cma_mae's --learning_rate, the mlp policy's --hidden) given to rows none
    of which use it (of `algorithms`, of `policies`) is refused, as an unknown flag is: it would
    be recorded and silently change nothing. So are two budgets: --evaluations sets the
    iterations."""
    if set(BUDGETS) <= set(given):
        raise UsageError("--iterations and --evaluations are two budgets; give one")
    for table, rows, one, several in ((ALGORITHMS, algorithms, "--algorithm", "--algorithms"),
                                      (POLICIES, policies, "--policy", "--policy")):
        named = list(dict.fromkeys(row for row in rows if row in table))  # others: refused later
        for flag in given:
            users = [name for name, row in table.items() if flag in row.flags]
            if named and users and not set(named) & set(users):
                who = (f"{one} {named[0]} does not" if len(named) == 1
                       else f"none of {several} {', '.join(named)}")
                raise UsageError(f"--{flag} is a flag of {', '.join(users)} only; {who} use it")


def check_sizes(config: dict) -> None:
    """The sizes that flags make together are bounded too: the archive's cells, the solutions
    asked per iteration (a DQD row's gradient batch too) and the rollouts they are flown in."""
    solutions, made_by = solutions_per_iteration(config)
    if config["archive"] == "grid" and (cells := config["grid"] ** len(config["measures"])) > MAX_CELLS:
        raise UsageError(f"--grid {config['grid']} with {len(config['measures'])} measures makes "
                         f"{cells:,} cells; at most {MAX_CELLS:,}")
    if solutions > MAX_SOLUTIONS:
        raise UsageError(f"{made_by} asks {solutions:,} solutions per iteration; at most {MAX_SOLUTIONS:,}")
    check_rollouts(solutions, len(config["env_seed"]), "per iteration")


def solutions_per_iteration(config: dict) -> tuple[int, str]:
    """The solutions an iteration asks, and the flags that make the number: n_emitters x
    batch_size, or a DQD row's emitters each with its point and gradient samples if more, so
    that a refusal names the flag to lower."""
    n_emitters, batch = config["n_emitters"], config["batch_size"]
    made = {f"--n_emitters {n_emitters} x --batch_size {batch}": n_emitters * batch}
    if ALGORITHMS[config["algorithm"]].dqd:
        samples = config["es_samples"]
        made[f"--n_emitters {n_emitters} x (1 + --es_samples {samples})"] = n_emitters * (1 + samples)
    made_by = max(made, key=made.get)  # the first of equals: the batch
    return made[made_by], made_by


def check_rollouts(solutions: int, terrains: int, when: str) -> None:
    """At most MAX_ROLLOUTS rollouts in one batch: their results are held at once."""
    if solutions * terrains > MAX_ROLLOUTS:
        raise UsageError(f"{solutions:,} solutions on {terrains:,} env seed(s) make "
                         f"{solutions * terrains:,} rollouts {when}; at most {MAX_ROLLOUTS:,}")


# Each flag is declared once, here: its default, its --help line, its check, and its part in
# experiments (see flags.Flag). `takes` turns a table into a command's keyword arguments, so the
# signature, the docstring's Args and --help come from these entries.

CLUSTER_FLAGS: dict[str, Flag] = {  # every command that flies policies on a cluster
    "workers": Flag(2, "Number of Dask worker processes (one thread each) of the local cluster "
                       f"flying the rollouts (at most {MAX_WORKERS:,}, and what memory holds); "
                       "as many as the cores: each is pinned to a core of its own.",
                    whole_number_up_to(MAX_WORKERS), per_run=True),
    "scheduler_address": Flag(None, "Address of a running Dask scheduler (tcp://HOST:PORT) to "
                                    "evaluate on instead of starting a local cluster; --workers "
                                    "is then ignored.", per_run=True),
    "scheduler_file": Flag(None, "A Dask scheduler file (written by dask scheduler "
                                 "--scheduler-file, dask-mpi or dask-jobqueue's SLURMRunner): "
                                 "wait for it to appear, then join the scheduler it names; "
                                 "instead of --scheduler_address.", per_run=True),
    "scheduler_timeout": Flag(120, "Seconds to wait for --scheduler_file to appear; the "
                                   "scheduler must answer within this too (at most 20 s).",
                              positive_float, per_run=True),
    "worker_timeout": Flag(600, "Seconds to wait for the first worker of the cluster named by "
                                "--scheduler_address or --scheduler_file to join (it says it waits).",
                           positive_float, per_run=True),
}

SEARCH_FLAGS: dict[str, Flag] = {
    "iterations": Flag(300, f"Number of ask-evaluate-tell iterations (at most {MAX_ITERATIONS:,}).",
                       whole_number_up_to(MAX_ITERATIONS)),
    "evaluations": Flag(None, "A budget in evaluations (solutions flown, a DQD row's gradient samples "
                              "included) instead of --iterations. The run stops at the last "
                              "iteration within it, so rows that fly different numbers per "
                              "iteration compare at equal budgets.", whole_number_up_to(MAX_EVALUATIONS),
                        sweep=True, label=13),
    "workers": CLUSTER_FLAGS["workers"],
    "seed": Flag(None, "Seed of the archive and emitters; drawn and recorded in config.json if "
                       "omitted. The same seed gives the same archive whatever the number of "
                       "workers.", seed_number, per_run=True),
    "env": Flag(DEFAULT_ENV, "The Gymnasium task, a row of ENVIRONMENTS: " + ", ".join(ENVIRONMENTS)
                + " (docs/environments.md).", one_of(ENVIRONMENTS), before=DEFAULT_ENV),
    "env_seed": Flag(52, f"The env seed(s) every policy is flown on ({seed_nouns()}): one seed "
                         "(52), a range (0-4), a list (3,5,8) or both (0-4,10). With several seeds "
                         "the objective is the mean return over them, and each measure is its "
                         "per-seed values averaged.", seed_list, label=1, text=True),
    "policy": Flag("linear", "The policy a solution's numbers make, a row of POLICIES: " + "; ".join(
        f"{name} ({row.summary})" for name, row in POLICIES.items()) + ".", one_of(POLICIES),
        sweep=True, label=14, before="linear"),
    "start": Flag(None, "Where the emitters start, a row of STARTS: zeros, or glorot (a Glorot "
                        "uniform draw of each layer's weights, biases zero, seeded from --seed); "
                        "default: the policy's own (linear: zeros; mlp: glorot).", one_of(STARTS),
                  sweep=True, label=21, text=True),
    "hidden": Flag(None, f"--policy mlp: the hidden layers' sizes, comma-separated; default "
                         f"{','.join(map(str, DEFAULT_HIDDEN))}.", layer_widths, label=15, text=True),
    "episode_length": Flag(None, "Steps an episode lasts at most (gym.make's max_episode_steps); "
                                 "default: the task's own (1,000; BipedalWalker's 1,600). QDax's "
                                 "examples fly 100 to 1,000 (docs/locomotion.md).",
                           whole_number_up_to(MAX_EPISODE), sweep=True, label=16),
    "reset": Flag("fixed", "Each episode's reset: fixed (every evaluation flies from its --env_seed "
                           "reset, a deterministic task) or each (every evaluation its own reset "
                           "seed, drawn from --seed, the --env_seed and the solution's weights, as "
                           "dqd-rl reset each evaluation; an elite is replayed on its own seed).",
                  one_of(RESETS), sweep=True, label=20, text=True),
    "qd_offset": Flag(None, "What QD score subtracts from each elite's objective (and CMA-MAE's "
                            "threshold floor); default: the task's offset, per step times the "
                            "episode's length for the robots (QDax's rule; docs/locomotion.md).",
                      finite_number),
    "terminate_when_unhealthy": Flag(None, "Hopper-v5, Walker2d-v5, Ant-v5: whether a robot that "
                                           "falls ends its episode (Gymnasium's flag); default: "
                                           "the task's own (true).", boolean, label=17),
    "measures": Flag(None, f"1 to {MAX_GRID_MEASURES} rows (with --archive cvt up to {MAX_MEASURES}) "
                           "of the MEASURES table of the task's family, "
                           "comma-separated, as the archive's axes; default: the task's own. "
                           + "; ".join(f"{family.title}: {', '.join(family_measures(family))} ("
                                       f"{','.join(default_measures(family))} by default)"
                                       for family in FAMILIES) + ".",
                     distinct_names(MEASURES, "measures", MAX_MEASURES), label=2, text=True),
    "archive": Flag(None, "The kind of archive, a row of ARCHIVES: grid (--grid cells along each "
                          f"of at most {MAX_GRID_MEASURES} measures) or cvt (--cells centroids, "
                          f"any number of measures up to {MAX_MEASURES}; pyribs' CVTArchive); "
                          "default: the task's (a grid; Ant-v5's 4 feet: cvt).",
                    one_of(ARCHIVES), label=8, before="grid"),
    "grid": Flag(None, f"Grid archive: cells along each measure; default {DEFAULT_GRID}.", positive_int,
                 sweep=True, label=3, before=DEFAULT_GRID),
    "cells": Flag(None, f"CVT archive: its cells (centroids, made once by k-means over "
                        f"{CVT_SAMPLES:,} points and kept in the run); default {DEFAULT_CVT_CELLS}, "
                        f"at least 2^measures, at most {CVT_SAMPLES:,}.",
                  whole_number_up_to(CVT_SAMPLES), sweep=True, label=9),
    "algorithm": Flag("cma_me", "Which QD algorithm, a row of ALGORITHMS: " + ", ".join(
        f"{name} ({row.summary})" for name, row in ALGORITHMS.items()) + "; each asks n_emitters * "
        "batch_size solutions per iteration (docs/algorithms.md).", one_of(ALGORITHMS), per_run=True),
    "n_emitters": Flag(5, f"Number of emitters (at most {MAX_EMITTERS:,}).",
                       whole_number_up_to(MAX_EMITTERS), sweep=True, label=4),
    "sigma0": Flag(1.0, "Initial step size of each emitter (CMA-ES sigma); map_elites: the fixed "
                        f"sigma of its Gaussian mutation (at most {MAX_STEP:g}).",
                   number_up_to(MAX_STEP), sweep=True, label=6),
    "batch_size": Flag(30, f"Solutions each emitter proposes per iteration (n_emitters * "
                           f"batch_size: at most {MAX_SOLUTIONS:,}).", whole_number_up_to(MAX_SOLUTIONS),
                       sweep=True, label=5),
    "learning_rate": Flag(0.5, "The CMA-MAE rows: how fast a cell's threshold follows its "
                               "improvements, in (0, 1]. 0.5 did best of 0.01, 0.1 and 0.5 over "
                               "6 seeds of 300 iterations (docs/algorithms.md); pyribs' 0.01 is "
                               "for far longer runs; 1 makes the archive CMA-ME's.", fraction,
                          sweep=True, label=7, before=0.01),
    "line_sigma": Flag(0.2, "The iso+line rows (line_map_elites, me_map_elites, dns): the step along "
                            "the line between two elites (pyribs' IsoLineEmitter line_sigma; its "
                            f"iso_sigma is --sigma0; at most {MAX_STEP:g}).", number_up_to(MAX_STEP),
                      sweep=True, label=10),
    "novelty_threshold": Flag(0.037, "ns_cma, nslc: the novelty (mean distance to the 15 nearest "
                                     "neighbours) a solution needs to enter the proximity archive, "
                                     "as a fraction of the measures' mean span (pyribs' ns_cma: "
                                     "0.037).", positive_float, sweep=True, label=11),
    "bandwidth": Flag(0.05, "dds: the KDE's bandwidth, as a fraction of the measures' mean span "
                            "(pyribs' dds: 25.6 of 512, 0.05).", positive_float, sweep=True, label=12),
    "es_samples": Flag(100, "The DQD rows (cma_mega_es, cma_maega_es): mirrored samples flown around "
                            "each emitter's point per iteration to estimate its gradients, an even "
                            f"number (dqd-rl's 100; n_emitters * (1 + es_samples): at most "
                            f"{MAX_SOLUTIONS:,}).", even_samples, sweep=True, label=18),
    "es_sigma": Flag(0.02, "The DQD rows: the samples' standard deviation around the point (dqd-rl's "
                           f"0.02; at most {MAX_STEP:g}).", number_up_to(MAX_STEP), sweep=True, label=19),
    "log_every": Flag(25, "Log a line and refresh the run folder every this many iterations.",
                      positive_int),
    "pictures": Flag(True, "Draw heatmap.png, heatmaps/ and progress.png at each refresh; false "
                           "writes the data alone (archive.csv, archive.npz, metrics.json), which "
                           "every results command reads: the pictures are most of a refresh's CPU.",
                     boolean),
    "archive_pkl": Flag(False, "Also write archive.pkl at each refresh: the pyribs archive pickled "
                               "whole, a row per cell (a 32 x 32 grid of 128,128-MLP robots: ~160 MB "
                               "however few its elites), for pyribs' own tools; every command reads "
                               "archive.npz, which holds the elites alone.", boolean, before=True),
    "outdir": Flag(None, "Run folder; default outputs/<timestamp>_seed<seed>. Must be new or "
                         "empty.", per_run=True),
    "scheduler_address": CLUSTER_FLAGS["scheduler_address"],
    "scheduler_file": CLUSTER_FLAGS["scheduler_file"],
    "scheduler_timeout": CLUSTER_FLAGS["scheduler_timeout"],
    "worker_timeout": CLUSTER_FLAGS["worker_timeout"],
    "from_archive": Flag(None, "Warm start from an earlier run's archive.npz (or its run folder, or "
                               "the archive.pkl the archive.npz lies beside; no pickle is loaded), "
                               "whose elites are re-evaluated in this run's setting to fill the "
                               "archive first; the emitters start from the best.", per_run=True),
    "track": Flag([], "Trackers to log the run to, comma-separated, of " + ", ".join(TRACKERS) + ": every "
                      "iteration's metrics and the pictures of every save, offline unless the "
                      "tracker's own settings say otherwise (pip install -r requirements-trackers.txt).",
                  check_tracks, before=[]),
    "fast_env": Flag(True, "Fly rollouts in the task's streamlined copy where it has one "
                           "(LunarLander-v3: bitwise identical results, about a third less time "
                           "per step); false uses gym.make's plain environment.", boolean),
}

# resume: a run goes on as it was started unless told otherwise.
RESUME_FLAGS: dict[str, Flag] = {
    "iterations": dataclasses.replace(
        SEARCH_FLAGS["iterations"], default=None, help="Total iterations to reach; default: those "
        "the run was started with. A larger number extends a finished run."),
    "evaluations": dataclasses.replace(
        SEARCH_FLAGS["evaluations"], help="A total budget in evaluations to reach instead of "
        "--iterations: each run goes to its last iteration within it (an experiment's rows that fly "
        "different numbers per iteration meet at one budget)."),
    "workers": dataclasses.replace(CLUSTER_FLAGS["workers"], default=None, help=(
        CLUSTER_FLAGS["workers"].help + " Default: as the run was started.")),
    **{name: flag for name, flag in CLUSTER_FLAGS.items() if name != "workers"},
    "trust": Flag(False, "Resume from a checkpoint not signed with your key (another user's, or "
                         "from before checkpoints were signed) and sign it with yours; loading a "
                         "pickle may run any code it holds, so only for one you trust.", boolean),
}

# Which elites a results command shows (video, trajectories), and on which terrain (explore too).
SELECTION_FLAGS: dict[str, Flag] = {
    "cells": Flag(None, 'Points in the run\'s measures "[(m1, m2), ...]": the elite of each '
                        "point's cell (archive.retrieve_single); for the tutorial's impact x and "
                        'impact y-velocity, e.g. "[(-0.4, -0.1), (0.6, -0.1), (0.0, -0.1)]".'),
    "best": Flag(False, "The elite with the highest objective.", boolean),
    "top": Flag(None, "The K elites with the highest objectives.", positive_int),
    "index": Flag(None, "Archive cell indices (the cell_index column of the elites command)."),
    "nearest": Flag(False, "For an empty cell, use the nearest occupied cell instead of "
                           "stopping.", boolean),
}
TERRAIN_FLAGS: dict[str, Flag] = {
    "env_seed": Flag(None, f"The env seed to fly on ({seed_nouns()}), one of the run's; default: "
                           "the run's first.", seed_number),
}


def checked(name: str, value: Any) -> Any:
    """A value checked as the flag `name` of SEARCH_FLAGS checks it (None included: refused)."""
    return SEARCH_FLAGS[name].check(name, value)


def with_task(config: dict[str, Any]) -> dict[str, Any]:
    """The config with its task's default measures if it names none, its measures checked against
    its task (a walker has no impact x), and its archive's cells: --grid for a grid (at most
    MAX_GRID_MEASURES measures), --cells for a CVT (at least 2^measures: fewer cells can't tell
    apart even the two halves of each measure's range)."""
    env = config["env"]
    task = ENVIRONMENTS[env]
    measures = list(task.measures if config.get("measures") is None else config["measures"])
    if wrong := [name for name in measures if task.family not in MEASURES[name].families]:
        raise UsageError(f"--measures {wrong[0]} is not a measure of --env {env}; its measures: "
                         + ", ".join(family_measures(task.family)))
    archive, grid, cells = config.get("archive") or task.archive, config.get("grid"), config.get("cells")
    if archive == "grid":
        if cells is not None:
            raise UsageError("--cells is for --archive cvt; a grid archive has --grid cells along "
                             "each measure")
        if len(measures) > MAX_GRID_MEASURES:
            raise UsageError(f"--measures: {len(measures)} measures on a grid archive; a grid takes "
                             f"at most {MAX_GRID_MEASURES} (its cells grow as --grid^measures): use "
                             f"--archive cvt")
        grid = DEFAULT_GRID if grid is None else grid
    else:
        if grid is not None:
            raise UsageError("--grid is for --archive grid; a CVT archive has --cells centroids")
        cells = DEFAULT_CVT_CELLS if cells is None else cells
        if cells < 2 ** len(measures):
            raise UsageError(f"--cells {cells} is too few for {len(measures)} measures: a CVT archive "
                             f"needs at least 2^{len(measures)} = {2 ** len(measures)} cells")
    config = {**config, "env": env, "measures": measures, "archive": archive, "grid": grid, "cells": cells}
    check_episode(env, episode_of(config))
    return with_budget(with_policy(config))


def with_offset(config: dict[str, Any]) -> dict[str, Any]:
    """The config's --qd_offset: its task's for its episode's length unless given or recorded
    (each run of an experiment its own: a swept --episode_length has offsets of its own)."""
    if config.get("qd_offset") is not None:
        return config
    return {**config, "qd_offset": ENVIRONMENTS[config["env"]].returns(episode_of(config).length).offset}


def legacy_offset(recorded: dict[str, Any]) -> dict[str, Any]:
    """What a run recorded before --qd_offset ran with: its task's offset at the task's own
    episode length, whatever its --episode_length (the offsets did not follow the episode then)."""
    env = recorded.get("env", DEFAULT_ENV)  # (a recorded qd_offset is laid over this: upgrade)
    return {"qd_offset": ENVIRONMENTS[env].returns().offset} if env in ENVIRONMENTS else {}


def with_policy(config: dict[str, Any]) -> dict[str, Any]:
    """The config's --hidden: DEFAULT_HIDDEN for a network unless given, refused for a policy
    without hidden layers (it would be recorded and change nothing)."""
    kind, hidden = config.get("policy") or "linear", config.get("hidden")
    if "hidden" not in POLICIES[kind].flags:
        if hidden is not None:
            raise UsageError(f"--hidden is a flag of --policy mlp; --policy {kind} has no hidden layers")
        return config
    return {**config, "hidden": list(DEFAULT_HIDDEN if hidden is None else hidden)}


def for_policy(config: dict[str, Any]) -> dict[str, Any]:
    """The config less the flags its policy has no use for (each unset): an experiment's --hidden
    in its settings of a policy without hidden layers, which record what search alone does."""
    kind = config.get("policy") or "linear"
    return {**config, **{flag: None for flag in POLICY_FLAGS if flag not in POLICIES[kind].flags}}


def resumed_budget(config: dict[str, Any], iterations: int | None, evaluations: int | None) -> dict[str, Any]:
    """A run's iterations and evaluations once resumed to `iterations` or `evaluations` (one of
    them, or neither: its own): a budget in iterations past its own drops its evaluations."""
    if iterations is not None and evaluations is not None:
        raise UsageError("--iterations and --evaluations are two budgets; give one")
    if evaluations is not None:
        return with_budget({**config, "evaluations": checked("evaluations", evaluations)})
    if iterations is None:
        return config
    iterations = checked("iterations", iterations)
    return {**config, "iterations": iterations,
            "evaluations": None if iterations > config["iterations"] else config.get("evaluations")}


def with_budget(config: dict[str, Any]) -> dict[str, Any]:
    """With --evaluations, the iterations are the most whose evaluations fit in it (every
    iteration of a row flies as many: evaluations_per_iteration)."""
    if config.get("evaluations") is None or config.get("algorithm") is None:  # (an experiment's
        return config  # flags common to its algorithms: each run's config has its own)
    per_iteration = evaluations_per_iteration(SimpleNamespace(**config))
    if config["evaluations"] < per_iteration:
        raise UsageError(f"--evaluations {config['evaluations']:,} is less than one iteration of "
                         f"--algorithm {config['algorithm']}, which flies {per_iteration:,}")
    return {**config, "iterations": min(config["evaluations"] // per_iteration, MAX_ITERATIONS)}


def check_memory(config: dict[str, Any]) -> None:
    """Refuse, before anything is written, a row whose emitters and archives would not fit in the
    machine's memory with this policy (a full CMA-ES covariance grows as the weights squared:
    ~3.5 GB at Ant-v5's 21,000 weights of a 128x128 network), naming the rows that fit."""
    weights = policy_of(config).size(ENVIRONMENTS[config["env"]].shape)
    room = MEMORY_SHARE * physical_memory()

    def needs(algorithm: str) -> float:
        return memory_needed(SimpleNamespace(**{**config, "algorithm": algorithm}), weights)

    if (needed := needs(config["algorithm"])) <= room:
        return
    fits = [name for name in ALGORITHMS if needs(name) <= room]
    raise UsageError(f"--algorithm {config['algorithm']} would hold ~{needed / 1e9:,.1f} GB for "
                     f"{weights:,} weights ({config['n_emitters']} emitters), more than "
                     f"{MEMORY_SHARE:.0%} of this machine's {room / MEMORY_SHARE / 1e9:.1f} GB; rows "
                     f"that fit: {', '.join(fits) or 'none'} (or fewer emitters, a smaller --hidden)")


MEMORY_SHARE = 0.5  # of the machine's memory a run's driver may plan to hold


def physical_memory() -> float:
    """The machine's memory in bytes."""
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def search_defaults() -> dict[str, Any]:
    return {name: flag.default for name, flag in SEARCH_FLAGS.items()}


def before_the_flags() -> dict[str, Any]:
    """What runs recorded before a flag existed ran with, where that is not today's default."""
    return {name: flag.before for name, flag in SEARCH_FLAGS.items() if flag.before is not None}
