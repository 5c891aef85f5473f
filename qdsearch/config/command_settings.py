"""The settings of the commands other than search: a frozen dataclass per command (or per concern
that several commands share), each flag a typed field with its default, help and check, as a
run's settings are declared (settings.py); each command's flag table is made from its class.

Map:
- `retold`: a shared flag's field with a command's own words for it (TOP);
- ResumeSettings and RESUME_FLAGS (resume: a budget to reach, the cluster, --trust);
- Selection (which elites video and trajectories show; SELECTION_FLAGS), Terrain (the env seed
  they and explore fly on; TERRAIN_FLAGS), EliteFilter (elites' table; ELITES_FLAGS);
- EvaluateSettings (EVALUATE_FLAGS), ExperimentSettings (EXPERIMENT_FLAGS), CompareSettings
  (COMPARE_FLAGS), WatchSettings (WATCH_FLAGS).

A command's values become its class through `base.flags.settings_from`, each checked by its
field's check once; a field whose value a file may give later (an experiment's plan) has no
check here, and is checked where the file's value is read.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from qdsearch.base.flags import (
    BadValue,
    Flag,
    boolean,
    finite_number,
    flag,
    flags_of,
    positive_int,
    seed_number,
    shown,
)
from qdsearch.config.settings import CLUSTER_FLAGS, SEARCH_FLAGS, ClusterSettings, seed_nouns

# The best elites, by objective: declared once for every command that picks them (video,
# trajectories, elites, evaluate), each with its own words.
TOP = Flag(None, "The K elites with the highest objectives.", positive_int)
MAX_PORT = 65535


def port_number(name: str, value: Any) -> int:
    """A TCP port: 1 to MAX_PORT."""
    if positive_int(name, value) > MAX_PORT:
        raise BadValue(name, value, f"must be at most {MAX_PORT}, got {shown(value)}")
    return value


def retold(entry: Flag, help: str | None = None, **parts: Any) -> Any:
    """A field that is the flag `entry`, with a command's own help (and default) for it."""
    told = {**parts, **({} if help is None else {"help": help})}
    return dataclasses.field(metadata={"flag": dataclasses.replace(entry, **told) if told else entry})


@dataclasses.dataclass(frozen=True)
class ResumeSettings:
    """resume: a run goes on as it was started unless told otherwise."""

    iterations: int | None = retold(
        SEARCH_FLAGS["iterations"], "Total iterations to reach; default: those the run was started with. "
        "A larger number extends a finished run.", default=None)
    evaluations: int | None = retold(
        SEARCH_FLAGS["evaluations"], "A total budget in evaluations to reach instead of --iterations: "
        "each run goes to its last iteration within it (an experiment's rows that fly different "
        "numbers per iteration meet at one budget).")
    workers: int | None = retold(CLUSTER_FLAGS["workers"], CLUSTER_FLAGS["workers"].help
                                 + " Default: as the run was started.", default=None)
    trust: bool = flag(False, "Resume from a checkpoint not signed with your key (another user's, or "
                              "from before checkpoints were signed) and sign it with yours; loading a "
                              "pickle may run any code it holds, so only for one you trust.", boolean)


RESUME_FLAGS: dict[str, Flag] = {
    **{name: entry for name, entry in flags_of(ResumeSettings).items() if name != "trust"},
    **{name: entry for name, entry in CLUSTER_FLAGS.items() if name != "workers"},
    "trust": flags_of(ResumeSettings)["trust"],
}


def resumed_cluster(settings: ResumeSettings, cluster: ClusterSettings) -> ClusterSettings:
    """The cluster a resume flies on: its own flags, and its --workers (None: the run's)."""
    return dataclasses.replace(cluster, workers=settings.workers)


@dataclasses.dataclass(frozen=True)
class Selection:
    """Which elites a results command shows (video, trajectories)."""

    cells: Any = flag(None, 'Points in the run\'s measures "[(m1, m2), ...]": the elite of each point\'s '
                            "cell (archive.retrieve_single); for the tutorial's impact x and impact "
                            'y-velocity, e.g. "[(-0.4, -0.1), (0.6, -0.1), (0.0, -0.1)]".')
    best: bool = flag(False, "The elite with the highest objective.", boolean)
    top: int | None = retold(TOP)
    index: Any = flag(None, "Archive cell indices (the cell_index column of the elites command).")
    nearest: bool = flag(False, "For an empty cell, use the nearest occupied cell instead of stopping.",
                         boolean)


@dataclasses.dataclass(frozen=True)
class Terrain:
    """Which of a run's env seeds a results command flies its elites on (video, trajectories,
    explore)."""

    env_seed: int | None = flag(None, f"The env seed to fly on ({seed_nouns()}), one of the run's; "
                                      "default: the run's first.", seed_number)


@dataclasses.dataclass(frozen=True)
class EliteFilter:
    """Which elites the elites command lists."""

    min_objective: float | None = flag(
        None, "Only elites scoring at least this; the last line counts those at the task's solved "
        "return (LunarLander-v3's 200: good landings; BipedalWalker-v3's 300).", finite_number)
    top: int | None = retold(TOP, "Only the K best of those.")


@dataclasses.dataclass(frozen=True)
class EvaluateSettings:
    """What evaluate flies the elites on, and what it builds."""

    env_seeds: Any = flag(None, "Env seeds (a lander's or walker's terrains, a robot's reset seeds) to fly "
                                "on: a range 0-19, a list 3,5,8, or both 0-4,10 (default: 0-19; with "
                                "--corrected, the first --repeats seeds the run did not search on).")
    corrected: bool = flag(False, "Build the corrected archive instead of the robustness table.", boolean)
    repeats: int | None = flag(None, "With --corrected: new seeds to fly every elite on (default 10).")
    top: int | None = retold(TOP, "Robustness only: the K elites with the highest objectives "
                                  "(default: all).")


@dataclasses.dataclass(frozen=True)
class ExperimentSettings:
    """An experiment's own flags (the others it passes on to every run). A plan file may give the
    grid's three (EXPERIMENT_OWN), so they are checked once the file is read."""

    algorithms: Any = flag(("cma_me",), "Rows of the ALGORITHMS table: cma_me, or a list "
                                        '"[cma_me, cma_mae]".')
    seeds: Any = flag("1-5", "The seeds of every setting: a range 1-5, a list 1,2,7 or both.")
    outdir: str | None = flag(None, "Experiment folder; default outputs/<timestamp>_experiment. Must be "
                                    "new or empty.")
    max_in_flight: int | None = flag(None, "Runs evaluated at once (default: all); the others wait their "
                                           "turn. Bounds memory with hundreds of runs.")
    part: str | None = flag(None, "I/K: drive only part I of the experiment split in K parts (run i "
                                  "belongs to part i mod K + 1), each part its own process, on its own "
                                  "cluster if wanted (a SLURM job array: docs/clusters.md). Every part "
                                  "is given the same flags and --outdir; the first writes the plan, each "
                                  "keeps its runs' states in parts/I_of_K/. Run again, a part continues "
                                  "where it stopped.")
    plan: str | None = flag(None, "A TOML file of the experiment (see the README's Experiments): its "
                                  "algorithms, seeds, max_in_flight and any flag it passes on, a list of "
                                  "values for an axis of the grid; and [[rows]] tables, each a grid of its "
                                  "own with its own algorithms and flags over the file's (dqd-rl's rows "
                                  "differ in emitters and batches: docs/presets/). A flag given beside it "
                                  "replaces the file's value and every row's, whatever its value (--seeds "
                                  "1-5 too). The file is copied into the experiment folder as plan.toml.")


# The keys of a plan file that are experiment's own flags (the others are flags it passes on).
EXPERIMENT_OWN = ("algorithms", "seeds", "max_in_flight")


@dataclasses.dataclass(frozen=True)
class CompareSettings:
    """What compare writes, and what it compares."""

    out: str | None = flag(None, "The PNG to write (the other files get the same name); default: a new "
                                 "compare.png in the experiment folder if one alone is compared, else a "
                                 "new outputs/compare_<timestamp>.png.")
    overwrite: bool = flag(False, "Replace those files if they already exist.", boolean)
    corrected: bool = flag(False, "Compare each run's corrected metrics and archive (corrected.json and "
                                  "corrected_archive.npz, written by `evaluate RUN --corrected`) instead "
                                  "of its own.", boolean)
    baseline: str | None = flag(None, "Test only this setting against each other one (its label as the "
                                      "tables show it, or its algorithm if only one setting has it, e.g. "
                                      "cma_me), instead of every pair: with many settings, Holm's "
                                      "adjustment over every pair leaves the tests little power.")
    at_evaluations: int | None = flag(
        None, "Compare each run as of its last iteration within this many evaluations (the metrics' "
        "`evaluations`, a DQD row's gradient samples included), so that rows that fly different "
        "numbers per iteration meet at one budget. The archive's figures (solved cells, CQD, the "
        "score distributions) are only of a run's end: a run cut short leaves them out.")


@dataclasses.dataclass(frozen=True)
class WatchSettings:
    """Where watch serves its page."""

    port: int = flag(5006, "The port to serve on.", port_number)
    host: str = flag("127.0.0.1", "The address to serve on (127.0.0.1: this machine only; the page shows "
                                  "the run to whoever can reach it).")


SELECTION_FLAGS: dict[str, Flag] = flags_of(Selection)
TERRAIN_FLAGS: dict[str, Flag] = flags_of(Terrain)
ELITES_FLAGS: dict[str, Flag] = flags_of(EliteFilter)
EVALUATE_FLAGS: dict[str, Flag] = flags_of(EvaluateSettings)
EXPERIMENT_FLAGS: dict[str, Flag] = flags_of(ExperimentSettings)
COMPARE_FLAGS: dict[str, Flag] = flags_of(CompareSettings)
WATCH_FLAGS: dict[str, Flag] = flags_of(WatchSettings)
