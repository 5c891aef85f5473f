"""A run's settings, declared once, in one place: a frozen dataclass per concern (the run, the task,
the policy, the episode, the archive, the algorithm, the output, the cluster), each flag a typed
field with its default, its --help line, its check and its part in experiments. A RunConfig
is all of them (made by run_config.py's two constructors); the commands' tables (SEARCH_FLAGS,
CLUSTER_FLAGS) are made from them, and so are --help and the commands' signatures.

Map:
- the bounds on sizes: MAX_ITERATIONS, MAX_EMITTERS, MAX_SOLUTIONS, MAX_ROLLOUTS, MAX_WORKERS, ...;
- the checks of their own (`layer_widths`, `even_samples`) and the help's words (`seed_nouns`,
  `default_measures`);
- the settings: RunSettings, TaskSettings, PolicySettings (its `network`, the policy they make,
  made once with them; `with_policy` and `for_policy`, its flags checked together),
  EpisodeSettings, ArchiveSettings, AlgorithmSettings, OutputSettings, ClusterSettings; the
  tables made from them: CLUSTER_FLAGS, SEARCH_FLAGS (the command line's), and what the search
  layer reads of them: SETTINGS, PASSED_ON, SWEEPS, LABELLED, `checked_settings`;
- `RunConfig`: all of them, then `RunRecords` (what a run notes about itself; RECORDS: the JSON
  type of each); `unchecked` (a config's typed view while its checks run).
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from typing import Any

from qdsearch.algorithms import (
    ALGORITHMS,
    ARCHIVES,
    CVT_SAMPLES,
)
from qdsearch.base.flags import (
    Flag,
    UsageError,
    boolean,
    check_flags,
    distinct_names,
    finite_number,
    flag,
    flags_of,
    fraction,
    named,
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
    family_measures,
)
from qdsearch.tasks.family import Family
from qdsearch.tasks.policies import POLICIES, STARTS, Policy

# The flags only some algorithms use (each row of ALGORITHMS names its own).
ROW_FLAGS = frozenset(flag for row in ALGORITHMS.values() for flag in row.flags)
POLICY_FLAGS = frozenset(flag for row in POLICIES.values() for flag in row.flags)  # so of the policies
BUDGETS = ("iterations", "evaluations")  # a run's two budgets: one is given, or neither

# Every size a user gives is bounded before anything is allocated or written (check_sizes and the
# flags' checks): each bound is far past what QD papers run (1,000s of solutions per iteration,
# 10,000s of iterations), and what it lets a run hold at once stays within a laptop's memory.
MAX_GRID_MEASURES = 4  # a grid's cells are --grid ** measures
MAX_MEASURES = 10  # a CVT archive's: k-means and the nearest centroid work in any dimension
DEFAULT_GRID, DEFAULT_CVT_CELLS = 50, 1024  # the tutorial's 50 x 50; QDax's 1,024 centroids
MAX_ITERATIONS = 1_000_000  # the checkpoint keeps a row of metrics (~1 KB in memory) per iteration
MAX_EMITTERS = 10_000  # each keeps its own CMA-ES state (a weights x weights covariance)
MAX_SOLUTIONS = 100_000  # asked per iteration (n_emitters * batch_size): 173 MB of 216 weights
MAX_BUFFER = 100_000_000  # transitions a learning row's replay buffer holds: 10.8 GB of Hopper's
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
MAX_DIM = 100_000  # a benchmark function's coordinates (a full CMA-ES covariance: check_memory)


def layer_widths(name: str, value: Any) -> list[int]:
    """Hidden layers' sizes: 128,128 (Fire may have made a number or a tuple of it already)."""
    parts = list(value) if isinstance(value, (tuple, list)) else str(value).split(",")
    try:
        widths = [int(str(part).strip()) for part in parts]
    except ValueError:
        widths = []
    if (isinstance(value, bool) or not 1 <= len(widths) <= MAX_LAYERS
            or not all(1 <= width <= MAX_UNITS for width in widths)):
        raise UsageError(f"{named(name)} takes 1 to {MAX_LAYERS} layer sizes from 1 to {MAX_UNITS:,}, such "
                         "as "
                         f"128,128; got {shown(value)}")
    return widths


def even_samples(name: str, value: Any) -> int:
    """Mirrored samples come in pairs: an even count, 2 at least."""
    if whole_number_up_to(MAX_ES_SAMPLES)(name, value) % 2 or value < 2:
        raise UsageError(f"{named(name)} must be even (mirrored pairs) and at least 2, got {shown(value)}")
    return value


def default_measures(family: Family) -> tuple[str, ...]:
    """The default measures of the family's first task (the tutorial's, for the lander)."""
    return next(task.measures for task in ENVIRONMENTS.values() if task.family is family)


def seed_nouns() -> str:
    """What one --env_seed value is, in each family's words: "the terrain for Lunar Lander,
    BipedalWalker; the reset seed for Hopper, ..." (the search's --help is every task's)."""
    titles: dict[str, list[str]] = {}
    scored = {task.family for task in ENVIRONMENTS.values() if task.function}  # no seed: points
    for family in (family for family in FAMILIES if family not in scored):
        titles.setdefault(family.seed_noun, []).append(family.title)
    return "; ".join(f"the {noun} for {', '.join(titled)}" for noun, titled in titles.items())


# A run's settings, each flag declared once, here, as a typed field of the class of its concern:
# its type (what its check returns), its default, its --help line, its check and its part in
# experiments (see flags.Flag). A RunConfig (run_config.py) is every one of these classes; the
# commands' tables below are made from them, and `takes` turns a table into a command's keyword
# arguments, so the signature, the docstring's Args and --help come from these fields.


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """The run: its budget, its seed and where its archive starts."""

    iterations: int = flag(
        300,
        f"Number of ask-evaluate-tell iterations (at most {MAX_ITERATIONS:,}).",
        whole_number_up_to(MAX_ITERATIONS),
    )
    evaluations: int | None = flag(
        None,
        "A budget in evaluations (solutions flown, a DQD row's gradient samples "
        "included) instead of --iterations. The run stops at the last "
        "iteration within it, so rows that fly different numbers per "
        "iteration compare at equal budgets.",
        whole_number_up_to(MAX_EVALUATIONS),
        sweep=True,
        label=13,
    )
    seed: int | None = flag(
        None,
        "Seed of the archive and emitters; drawn and recorded in config.json if "
        "omitted. The same seed gives the same archive whatever the number of "
        "workers.",
        seed_number,
        per_run=True,
    )
    from_archive: str | None = flag(
        None,
        "Warm start from an earlier run's archive.npz (or its run folder, or "
        "the archive.pkl the archive.npz lies beside; no pickle is loaded), "
        "whose elites are re-evaluated in this run's setting to fill the "
        "archive first; the emitters start from the best.",
        per_run=True,
    )


@dataclasses.dataclass(frozen=True)
class TaskSettings:
    """The task: which Gymnasium env, on which env seeds, in which copy of it."""

    env: str = flag(
        DEFAULT_ENV,
        "The Gymnasium task, a row of ENVIRONMENTS: " + ", ".join(ENVIRONMENTS) + " (docs/environments.md).",
        one_of(ENVIRONMENTS),
        before=DEFAULT_ENV,
    )
    env_seed: list[int] = flag(
        52,
        f"The env seed(s) every policy is flown on ({seed_nouns()}): one seed "
        "(52), a range (0-4), a list (3,5,8) or both (0-4,10). With several seeds "
        "the objective is the mean return over them, and each measure is its "
        "per-seed values averaged.",
        seed_list,
        label=1,
        text=True,
    )
    dim: int | None = flag(
        None,
        "A benchmark function's dimension (the arm's joints), a point's "
        f"coordinates, 2 to {MAX_DIM:,}; default: the function's own (sphere, "
        "rastrigin: 100; arm: 12). Gymnasium tasks take their size from their spaces.",
        whole_number_up_to(MAX_DIM),
        sweep=True,
        label=23,
    )
    fast_env: bool = flag(
        True,
        "Fly rollouts in the task's streamlined copy where it has one "
        "(LunarLander-v3: bitwise identical results, about a third less time "
        "per step); false uses gym.make's plain environment.",
        boolean,
    )


@dataclasses.dataclass(frozen=True)
class PolicySettings:
    """The policy a solution's numbers make, and where the emitters start."""

    policy: str = flag(
        "linear",
        "The policy a solution's numbers make, a row of POLICIES: "
        + "; ".join(f"{name} ({row.summary})" for name, row in POLICIES.items())
        + ".",
        one_of(POLICIES),
        sweep=True,
        label=14,
        before="linear",
    )
    start: str | None = flag(
        None,
        "Where the emitters start, a row of STARTS: zeros, or glorot (a Glorot "
        "uniform draw of each layer's weights, biases zero, seeded from --seed); "
        "default: the policy's own (linear: zeros; mlp: glorot).",
        one_of(STARTS),
        sweep=True,
        label=21,
        text=True,
    )
    hidden: list[int] | None = flag(
        None,
        f"--policy mlp: the hidden layers' sizes, comma-separated; default "
        f"{','.join(map(str, DEFAULT_HIDDEN))}.",
        layer_widths,
        label=15,
        text=True,
    )

    network: typing.ClassVar[Policy]  # (each instance's own, made by __post_init__; not a flag)

    def __post_init__(self) -> None:
        """`network`: the policy these settings make, made once with them, as every rollout flies
        it (linear: no hidden layers): its kind, its hidden layers and its start (a checked
        config: only a policy with hidden layers has them, `with_policy`). Runs from before
        --start start as their row does."""
        object.__setattr__(self, "network", Policy(self.policy, tuple(self.hidden or ()), self.start or ""))


def with_policy(config: dict[str, Any]) -> dict[str, Any]:
    """The config's --hidden: DEFAULT_HIDDEN for a network unless given, refused for a policy
    without hidden layers (it would be recorded and change nothing)."""
    kind, hidden = config.get("policy") or "linear", config.get("hidden")
    if "hidden" not in POLICIES[kind].flags:
        if hidden is not None:
            raise UsageError(f"{named('hidden')} is a flag of {named('policy')} mlp; {named('policy')} "
                             f"{kind} has no hidden layers")
        return config
    return {**config, "hidden": list(DEFAULT_HIDDEN if hidden is None else hidden)}


def for_policy(config: dict[str, Any]) -> dict[str, Any]:
    """The config less the flags its policy has no use for (each unset): an experiment's --hidden
    in its settings of a policy without hidden layers, which record what search alone does."""
    kind = config.get("policy") or "linear"
    return {**config, **{flag: None for flag in POLICY_FLAGS if flag not in POLICIES[kind].flags}}


@dataclasses.dataclass(frozen=True)
class EpisodeSettings:
    """An episode's rules: its length, its resets, when it ends, and the returns' offset."""

    episode_length: int | None = flag(
        None,
        "Steps an episode lasts at most (gym.make's max_episode_steps); "
        "default: the task's own (1,000; BipedalWalker's 1,600). QDax's "
        "examples fly 100 to 1,000 (docs/locomotion.md).",
        whole_number_up_to(MAX_EPISODE),
        sweep=True,
        label=16,
    )
    reset: str = flag(
        "fixed",
        "Each episode's reset: fixed (every evaluation flies from its --env_seed "
        "reset, a deterministic task) or each (every evaluation its own reset "
        "seed, drawn from --seed, the --env_seed and the solution's weights, as "
        "dqd-rl reset each evaluation; an elite is replayed on its own seed).",
        one_of(RESETS),
        sweep=True,
        label=20,
        text=True,
    )
    qd_offset: float | None = flag(
        None,
        "What QD score subtracts from each elite's objective (and CMA-MAE's "
        "threshold floor); default: the task's offset, per step times the "
        "episode's length for the robots (QDax's rule; docs/locomotion.md).",
        finite_number,
    )
    terminate_when_unhealthy: bool | None = flag(
        None,
        "Hopper-v5, Walker2d-v5, Ant-v5: whether a robot that "
        "falls ends its episode (Gymnasium's flag); default: "
        "the task's own (true).",
        boolean,
        label=17,
    )


@dataclasses.dataclass(frozen=True)
class ArchiveSettings:
    """The archive: its measures (axes) and its cells."""

    measures: list[str] | None = flag(
        None,
        f"1 to {MAX_GRID_MEASURES} rows (with --archive cvt up to {MAX_MEASURES}) "
        "of the MEASURES table of the task's family, "
        "comma-separated, as the archive's axes; default: the task's own. "
        + "; ".join(
            f"{family.title}: {', '.join(family_measures(family))} ("
            f"{','.join(default_measures(family))} by default)"
            for family in FAMILIES
        )
        + ".",
        distinct_names(MEASURES, "measures", MAX_MEASURES),
        label=2,
        text=True,
    )
    archive: str | None = flag(
        None,
        "The kind of archive, a row of ARCHIVES: grid (--grid cells along each "
        f"of at most {MAX_GRID_MEASURES} measures) or cvt (--cells centroids, "
        f"any number of measures up to {MAX_MEASURES}; pyribs' CVTArchive); "
        "default: the task's (a grid; Ant-v5's 4 feet: cvt).",
        one_of(ARCHIVES),
        label=8,
        before="grid",
    )
    grid: int | None = flag(
        None,
        f"Grid archive: cells along each measure; default {DEFAULT_GRID}.",
        positive_int,
        sweep=True,
        label=3,
        before=DEFAULT_GRID,
    )
    cells: int | None = flag(
        None,
        f"CVT archive: its cells (centroids, made once by k-means over "
        f"{CVT_SAMPLES:,} points and kept in the run); default {DEFAULT_CVT_CELLS}, "
        f"at least 2^measures, at most {CVT_SAMPLES:,}.",
        whole_number_up_to(CVT_SAMPLES),
        sweep=True,
        label=9,
    )


@dataclasses.dataclass(frozen=True)
class AlgorithmSettings:
    """The QD algorithm (a row of ALGORITHMS) and its emitters' settings; a row's own flags are
    used by that row alone."""

    algorithm: str = flag(
        "cma_me",
        "Which QD algorithm, a row of ALGORITHMS: "
        + ", ".join(f"{name} ({row.summary})" for name, row in ALGORITHMS.items())
        + "; each asks n_emitters * "
        "batch_size solutions per iteration (docs/algorithms.md).",
        one_of(ALGORITHMS),
        per_run=True,
    )
    n_emitters: int = flag(
        5,
        f"Number of emitters (at most {MAX_EMITTERS:,}).",
        whole_number_up_to(MAX_EMITTERS),
        sweep=True,
        label=4,
    )
    sigma0: float = flag(
        1.0,
        "Initial step size of each emitter (CMA-ES sigma); map_elites: the fixed "
        f"sigma of its Gaussian mutation (at most {MAX_STEP:g}).",
        number_up_to(MAX_STEP),
        sweep=True,
        label=6,
    )
    batch_size: int = flag(
        30,
        f"Solutions each emitter proposes per iteration (n_emitters * "
        f"batch_size: at most {MAX_SOLUTIONS:,}).",
        whole_number_up_to(MAX_SOLUTIONS),
        sweep=True,
        label=5,
    )
    learning_rate: float = flag(
        0.5,
        "The CMA-MAE rows: how fast a cell's threshold follows its "
        "improvements, in (0, 1]. 0.5 did best of 0.01, 0.1 and 0.5 over "
        "6 seeds of 300 iterations (docs/algorithms.md); pyribs' 0.01 is "
        "for far longer runs; 1 makes the archive CMA-ME's.",
        fraction,
        sweep=True,
        label=7,
        before=0.01,
    )
    line_sigma: float = flag(
        0.2,
        "The iso+line rows (line_map_elites, me_map_elites, dns): the step along "
        "the line between two elites (pyribs' IsoLineEmitter line_sigma; its "
        f"iso_sigma is --sigma0; at most {MAX_STEP:g}).",
        number_up_to(MAX_STEP),
        sweep=True,
        label=10,
    )
    novelty_threshold: float = flag(
        0.037,
        "ns_cma, nslc: the novelty (mean distance to the 15 nearest "
        "neighbours) a solution needs to enter the proximity archive, "
        "as a fraction of the measures' mean span (pyribs' ns_cma: "
        "0.037).",
        positive_float,
        sweep=True,
        label=11,
    )
    bandwidth: float = flag(
        0.05,
        "dds: the KDE's bandwidth, as a fraction of the measures' mean span "
        "(pyribs' dds: 25.6 of 512, 0.05).",
        positive_float,
        sweep=True,
        label=12,
    )
    es_samples: int = flag(
        100,
        "The DQD rows (cma_mega_es, cma_maega_es) and me_es: mirrored samples flown "
        "around each emitter's point per iteration to estimate its gradients (me_es: "
        "its ES step), an even number (dqd-rl's 100, its ME-ES 200; n_emitters * "
        f"(1 + es_samples): at most {MAX_SOLUTIONS:,}).",
        even_samples,
        sweep=True,
        label=18,
    )
    es_sigma: float = flag(
        0.02,
        "The DQD rows and me_es: the samples' standard deviation around the point "
        f"(dqd-rl's 0.02; at most {MAX_STEP:g}).",
        number_up_to(MAX_STEP),
        sweep=True,
        label=19,
    )
    buffer_size: int = flag(
        1_000_000,
        "The learning rows (pga_me, cma_mega_td3_es): the TD3 replay buffer's "
        "transitions, the oldest dropped first (dqd-rl's 1,000,000; a checkpoint "
        f"holds them all: docs/learning.md; at most {MAX_BUFFER:,}).",
        whole_number_up_to(MAX_BUFFER),
        sweep=True,
        label=22,
    )


@dataclasses.dataclass(frozen=True)
class OutputSettings:
    """What the run writes, and how often."""

    log_every: int = flag(
        25, "Log a line and refresh the run folder every this many iterations.", positive_int
    )
    pictures: bool = flag(
        True,
        "Draw heatmap.png, heatmaps/ and progress.png at each refresh; false "
        "writes the data alone (archive.csv, archive.npz, metrics.json), which "
        "every results command reads: the pictures are most of a refresh's CPU.",
        boolean,
    )
    archive_pkl: bool = flag(
        False,
        "Also write archive.pkl at each refresh: the pyribs archive pickled "
        "whole, a row per cell (a 32 x 32 grid of 128,128-MLP robots: ~160 MB "
        "however few its elites), for pyribs' own tools; every command reads "
        "archive.npz, which holds the elites alone.",
        boolean,
        before=True,
    )
    track: list[str] = flag(
        [],
        "Trackers to log the run to, comma-separated, of " + ", ".join(TRACKERS) + ": every "
        "iteration's metrics and the pictures of every save, offline unless the "
        "tracker's own settings say otherwise (pip install -r requirements-trackers.txt).",
        check_tracks,
        before=[],
    )
    outdir: str | None = flag(
        None, "Run folder; default outputs/<timestamp>_seed<seed>. Must be new or empty.", per_run=True
    )


@dataclasses.dataclass(frozen=True)
class ClusterSettings:
    """The Dask cluster the rollouts fly on (every command that flies policies takes these)."""

    workers: int = flag(
        2,
        "Number of Dask worker processes (one thread each) of the local cluster "
        f"flying the rollouts (at most {MAX_WORKERS:,}, and what memory holds); "
        "as many as the cores: each is pinned to a core of its own.",
        whole_number_up_to(MAX_WORKERS),
        per_run=True,
    )
    scheduler_address: str | None = flag(
        None,
        "Address of a running Dask scheduler (tcp://HOST:PORT) to "
        "evaluate on instead of starting a local cluster; --workers "
        "is then ignored.",
        per_run=True,
    )
    scheduler_file: str | None = flag(
        None,
        "A Dask scheduler file (written by dask scheduler "
        "--scheduler-file, dask-mpi or dask-jobqueue's SLURMRunner): "
        "wait for it to appear, then join the scheduler it names; "
        "instead of --scheduler_address.",
        per_run=True,
    )
    scheduler_timeout: float = flag(
        120,
        "Seconds to wait for --scheduler_file to appear; the "
        "scheduler must answer within this too (at most 20 s).",
        positive_float,
        per_run=True,
    )
    worker_timeout: float = flag(
        600,
        "Seconds to wait for the first worker of the cluster named by "
        "--scheduler_address or --scheduler_file to join (it says it waits).",
        positive_float,
        per_run=True,
    )


# The commands' tables, made from the settings classes: search takes every field of a run's
# settings as a flag, evaluate and explore the cluster's.
CLUSTER_FLAGS: dict[str, Flag] = flags_of(ClusterSettings)
SEARCH_FLAGS: dict[str, Flag] = flags_of(RunSettings, TaskSettings, PolicySettings, EpisodeSettings,
                                         ArchiveSettings, AlgorithmSettings, OutputSettings, ClusterSettings)

# A run's settings as the search layer reads them, from their entries: every setting's name in
# order, those an experiment passes on to every run (the others it sets per run) and those a list
# of values sweeps, the settings that label a run's setting (in label order), and a value's check.
SETTINGS: tuple[str, ...] = tuple(SEARCH_FLAGS)
PASSED_ON: tuple[str, ...] = tuple(name for name, entry in SEARCH_FLAGS.items() if not entry.per_run)
SWEEPS: frozenset[str] = frozenset(name for name, entry in SEARCH_FLAGS.items() if entry.sweep)
LABELLED: tuple[str, ...] = tuple(sorted((name for name, entry in SEARCH_FLAGS.items() if entry.label),
                                         key=lambda name: SEARCH_FLAGS[name].label))


def checked_settings(values: dict[str, Any]) -> dict[str, Any]:
    """A run's settings among `values` through their checks (others, and None, as they are)."""
    return check_flags(SEARCH_FLAGS, values)


@dataclasses.dataclass(frozen=True)
class RunRecords:
    """What a run's config.json notes about the run besides its flags, and what a run that did
    not note a field holds."""

    created: str | None = None  # when it was started
    command: list[str] = dataclasses.field(default_factory=list)  # the command line that started it
    versions: dict[str, str] = dataclasses.field(default_factory=dict)  # the libraries it ran with
    experiment: str | None = None  # the experiment folder it is a run of
    resumed: list[dict] = dataclasses.field(default_factory=list)  # each resumption: when, from and
    # to which iteration, on how many workers


def json_type(hint: Any) -> type:
    """The JSON type a record's annotation holds: str for `str | None`, list for `list[str]`."""
    arms = [arm for arm in typing.get_args(hint) if arm is not type(None)] if isinstance(
        hint, types.UnionType) else [hint]
    return typing.get_origin(arms[0]) or arms[0]


RECORDS: dict[str, type] = {name: json_type(hint) for name, hint in typing.get_type_hints(RunRecords).items()}


@dataclasses.dataclass(frozen=True)
class RunConfig(RunRecords, ClusterSettings, OutputSettings, AlgorithmSettings, ArchiveSettings,
                EpisodeSettings, PolicySettings, TaskSettings, RunSettings):
    """A run's settings, read everywhere as config.<flag>: every field of the settings classes
    above, from RunSettings to ClusterSettings in this order, then RunRecords, and the policy they
    make (`network`). Made by run_config.py, from a record (check_run_config) or a search's flags
    (search_config), every value checked (`unchecked`: while the checks run)."""

    def to_json(self) -> dict[str, Any]:
        """The config as config.json and the checkpoint hold it: a plain dict, flags first."""
        return {field.name: copy.deepcopy(getattr(self, field.name)) for field in dataclasses.fields(self)}

    def replace(self, **changes: Any) -> RunConfig:
        return dataclasses.replace(self, **changes)


def unchecked(values: dict[str, Any]) -> RunConfig:
    """The RunConfig of values being checked (a flag not among them: None; no records): the checks
    of what flags make together (options.py) read a config as its typed fields before it is
    whole."""
    return RunConfig(**{name: values.get(name) for name in SEARCH_FLAGS})
