"""The commands as the command line (and a Python caller who wants its flags) sees them: each a
function whose flags come from the settings classes' tables (`takes`), whose docstring is its
--help, and which makes those classes from the values given and calls the core with them.

Map: `search`, `resume`, `experiment` (the search layer's); `video`, `elites`, `trajectories`,
`evaluate`, `explore`, `compare`, `watch` (the analysis layer's). Each core module is imported
when its command runs: --help and bad input answer without loading pyribs, pandas or Dask.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from qdsearch.base.flags import named, settings_from
from qdsearch.cli.signatures import takes
from qdsearch.config.command_settings import (
    COMPARE_FLAGS,
    ELITES_FLAGS,
    EVALUATE_FLAGS,
    EXPERIMENT_FLAGS,
    RESUME_FLAGS,
    SELECTION_FLAGS,
    TERRAIN_FLAGS,
    WATCH_FLAGS,
    CompareSettings,
    EliteFilter,
    EvaluateSettings,
    ExperimentSettings,
    ResumeSettings,
    Selection,
    Terrain,
    WatchSettings,
)
from qdsearch.config.run_config import search_config
from qdsearch.config.settings import CLUSTER_FLAGS, SEARCH_FLAGS, ClusterSettings


@takes(SEARCH_FLAGS)
def search(config: str | None = None, *, given: frozenset[str] = frozenset(), **flags: Any) -> None:
    """Search a task (--env; Lunar Lander's landings by default) with a QD algorithm and write a
    run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl (signed with your key), archive.npz, archive.csv, metrics.json,
    heatmap.png, heatmaps/, progress.png, config.json and run.log. The other commands: COMMANDS
    in --help.

    Args:
        config: A run's config.json (or its run folder): a new run with exactly that run's
            settings, its seed too, so its archive is the same bit for bit. A flag given beside
            it replaces the file's value, whatever its value, and takes along what the file's
            value made: another --env its own measures and archive, another --archive its own
            cells, another --policy its own --hidden, a budget (--iterations or --evaluations)
            the file's budget. Where the new run goes and the cluster it flies on are never the
            file's.
    """
    from qdsearch.search import run

    settings = search_config(flags, given, None if config is None else Path(str(config)))
    print(run.where_to_look(run.search(settings), settings))


@takes(RESUME_FLAGS)
def resume(run_dir: str, part: str | None = None, **flags: Any) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped; or,
    for an experiment folder, every unfinished run of the experiment (of one part of it).

    A checkpoint not signed with your key is refused unless --trust is given (which signs it
    with your key).

    Args:
        run_dir: A run folder (or an experiment folder) written by this script.
        part: I/K: of an experiment split in K parts (experiment --part), only part I.
    """
    from qdsearch.search import experiments

    experiments.resume(Path(str(run_dir)), settings_from(ResumeSettings, flags),
                       settings_from(ClusterSettings, flags), part)


@takes(EXPERIMENT_FLAGS, CLUSTER_FLAGS)
def experiment(*, given: frozenset[str] = frozenset(), **search_flags: Any) -> None:
    """Run every combination of the listed settings with every seed, interleaved on one cluster.

    Each run is an ordinary run folder inside the experiment folder (every command works on it),
    bit for bit what `search` writes alone with the same flags. One process drives all runs: when
    a run's batch is back it is told, saved every log_every iterations, and its next batch is
    asked and sent, so the other runs' batches keep the workers busy while one waits for its
    slowest chunk. experiment.json records the grid, the command and each run's state. Ctrl-C,
    SIGTERM or kill -9 lose at most what each run did since its last checkpoint: continue with
    `resume EXPERIMENT_DIR`. A failing run is reported and recorded; the others go on.

    Args:
        search_flags: Any flag of search that it passes to every run (see: lunar_lander.py --help):
            {passed_on}. A list of values of {sweeps}, e.g. --learning_rate "[0.01, 0.1]", is one
            more axis of the grid.
    """
    from qdsearch.search import experiments

    own = settings_from(ExperimentSettings, search_flags)
    cluster = settings_from(ClusterSettings, search_flags)
    passed = {name: value for name, value in search_flags.items()
              if name not in EXPERIMENT_FLAGS and name not in CLUSTER_FLAGS}
    experiments.experiment(own, passed, cluster, given)


experiment.__doc__ = experiment.__doc__.format(
    passed_on=", ".join(named(name) for name, entry in SEARCH_FLAGS.items() if not entry.per_run),
    sweeps=", ".join(named(name) for name, entry in SEARCH_FLAGS.items() if entry.sweep))


@takes(SELECTION_FLAGS, TERRAIN_FLAGS)
def video(run_dir: str, **flags: Any) -> None:
    """Render an mp4 per chosen elite, flown on one of the run's env seeds, into RUN_DIR/videos/.

    Each elite is also flown again in its run's setting and must score exactly its stored
    objective and measures (a warning says if not). videos/index.csv lists the videos with the
    elites' objectives and measures, earlier calls' videos too.

    Args:
        run_dir: A run folder written by this script.
    """
    from qdsearch.analysis import results

    results.video(Path(str(run_dir)), settings_from(Selection, flags), settings_from(Terrain, flags))


@takes(ELITES_FLAGS)
def elites(run_dir: str, **flags: Any) -> None:
    """Print the run's elites sorted by objective, and write them to RUN_DIR/elites.csv.

    Args:
        run_dir: A run folder written by this script.
    """
    from qdsearch.analysis import results

    results.elites(Path(str(run_dir)), settings_from(EliteFilter, flags))


@takes(SELECTION_FLAGS, TERRAIN_FLAGS)
def trajectories(run_dir: str, **flags: Any) -> None:
    """Draw the paths of the chosen elites, as their task's family draws them (the lander's flights
    over its terrain, a walker's or a robot's torso): RUN_DIR/trajectories.png.

    The elites are chosen as for the video command. Each drawing is also kept in
    RUN_DIR/trajectories/, and trajectories/index.csv lists the elites of every drawing.

    Args:
        run_dir: A run folder written by this script.
    """
    from qdsearch.analysis import results

    results.trajectories(Path(str(run_dir)), settings_from(Selection, flags), settings_from(Terrain, flags))


@takes(EVALUATE_FLAGS, CLUSTER_FLAGS)
def evaluate(run_dir: str, **flags: Any) -> None:
    """Fly the run's elites again (on Dask): on other terrains, or (--corrected) on new seeds. Of
    an experiment folder, every run's, on one cluster.

    Robustness (the default) writes RUN_DIR/robustness.csv (per elite: its objective in the run,
    i.e. its mean over the run's terrains; mean, min and standard deviation of its objective over
    the new terrains, share of terrains where it solves the task (a landing >= 200, a walk >=
    300), and each terrain's objective) and RUN_DIR/robustness_heatmap.png (the archive coloured
    by the mean objective on the new terrains).

    --corrected builds the corrected archive: every elite flown on --repeats new seeds and
    inserted by its mean measures and mean objective into an empty archive of the run's cells.
    Writes corrected.json (its QD score, coverage, cells, best and mean objective, beside the
    run's), corrected_archive.npz (and .pkl, .csv) and corrected_heatmap.png; `compare
    --corrected` reads them.

    Args:
        run_dir: A run folder written by this script, or an experiment folder (each of its runs).
    """
    from qdsearch.analysis import evaluation

    evaluation.evaluate(Path(str(run_dir)), settings_from(EvaluateSettings, flags),
                        settings_from(ClusterSettings, flags))


@takes(CLUSTER_FLAGS, TERRAIN_FLAGS)
def explore(run_dir: str, **flags: Any) -> None:
    """Write RUN_DIR/explorer.html: one self-contained page to browse the archive and watch any
    elite's episode. It opens offline in any current browser (no server, nothing fetched): the
    heatmap (hover a cell for its numbers, click it to watch its elite), a sortable table of the
    best elites, and the run's progress curves. Every elite is flown again on the cluster to record
    its poses, so the page plays exactly the episode that `video` renders.

    Args:
        run_dir: A run folder written by this script.
    """
    from qdsearch.analysis import explorer

    explorer.explore(Path(str(run_dir)), settings_from(Terrain, flags), settings_from(ClusterSettings, flags))


@takes(COMPARE_FLAGS)
def compare(*run_dirs: str, **flags: Any) -> None:
    """Compare runs: QD score, coverage and best objective against evaluations on one PNG, the
    final archives' score distributions on another (OUT_scores.png), and a table of their final
    values (printed, and written as CSV next to the PNG).

    Runs of one setting (the same algorithm and flags, other seeds; an experiment's runs) are
    grouped, task by task: the PNG shows their mean with a 95% confidence band, and per setting
    the number of runs, mean, median and 95% bootstrap interval, and IQM with its stratified
    bootstrap interval, of QD score, coverage, best objective, solved cells, QD-score AUC and CQD
    score are printed and written (OUT_settings.csv); between settings, Mann-Whitney U tests on
    final QD score, QD-score AUC (how soon it got there) and CQD score, Holm-adjusted, with
    Vargha-Delaney A12 = P(A>B) and its interval (OUT_tests.csv); and both as Markdown (OUT.md).
    Runs of several tasks are also aggregated per setting on the normalised QD score and coverage
    (OUT_aggregate.csv). Runs that end at equal evaluations (--evaluations) give an equal-budget
    comparison; --at_evaluations cuts longer runs to one.

    Args:
        run_dirs: Run folders or experiment folders written by this script.
    """
    from qdsearch.analysis import comparison

    comparison.compare([Path(str(run_dir)) for run_dir in run_dirs], settings_from(CompareSettings, flags))


@takes(WATCH_FLAGS)
def watch(run_dir: str, **flags: Any) -> None:
    """Serve a live page of a run (running or not): its archive and QD score, redrawn as its folder
    is refreshed. Open the printed address in a browser; Ctrl-C ends it.

    Args:
        run_dir: A run folder written by this script.
    """
    from qdsearch.analysis import live

    live.watch(Path(str(run_dir)), settings_from(WatchSettings, flags))
