"""Flying a finished run's elites again (`evaluate`): on other terrains, to see which styles
generalise, or on new seeds, to correct the archive for noisy evaluation. Neither changes any of
the run's own files: each writes files of its own beside them.

A search scores each solution once per terrain of the run, so an elite may hold its cell by
luck: a landing that works on terrain 52 may crash on the next. The corrected archive (Flageat &
Cully 2023, "Uncertain Quality-Diversity"; QDax's corrected metrics) flies every elite again on
N new seeds and inserts it, by its mean measures and mean objective there, into an empty archive
of the same cells; its QD score and coverage are the run's corrected metrics.

Map:
- `new_seeds` (the first seeds the run did not search on), `fly_elites` (every elite on every
  seed, on Dask: objectives and measures per seed);
- robustness: `robustness_table`, `write_robustness`;
- the corrected archive: `corrected_archive`, `archive_metrics` (the run's row of the archive's
  iteration), `corrected_summary`, `write_corrected`;
- `evaluate` (the command: a run, or each run of an experiment on one cluster), `evaluate_run`.
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Any

import numpy as np

from qdsearch.algorithms import ARCHIVES, task_of
from qdsearch.analysis.run_folder import elite_rows, load_run
from qdsearch.base.flags import UsageError, named, seed_list, whole_number_up_to
from qdsearch.base.plots import save_heatmap
from qdsearch.base.run_files import check_writable, console_log, write_csv, write_json, write_pickle
from qdsearch.config.command_settings import EvaluateSettings
from qdsearch.config.options import check_rollouts, checked
from qdsearch.config.run_config import RunConfig, upgrade
from qdsearch.config.settings import ClusterSettings
from qdsearch.search.cluster import dask_client, scheduler_of
from qdsearch.search.engine import averaged, gather_with_progress, per_terrain, submit_flights
from qdsearch.search.experiment_folder import read_experiment
from qdsearch.store.archive_data import write_archive_data
from qdsearch.store.metrics import iteration_metrics, load_metrics
from qdsearch.tasks import MEASURES, episode_of, evaluate_points, returns_of, scored_here

ROBUSTNESS_SEEDS = "0-19"  # the terrains `evaluate` flies on by default
DEFAULT_REPEATS = 10  # seeds of a corrected archive (QDax's examples re-evaluate 10 to 100 times)
MAX_REPEATS = 1_000
CORRECTED_FILES = ("corrected.json", "corrected_archive.npz", "corrected_archive.pkl",
                   "corrected_archive.csv", "corrected_heatmap.png")


def new_seeds(config: RunConfig, count: int) -> list[int]:
    """The first `count` whole numbers the run did not search on: seeds new to its elites, the
    same for every run of a terrain, so that corrected metrics of two runs compare."""
    seen = set(config.env_seed)
    return [seed for seed in range(count + len(seen)) if seed not in seen][:count]


def fly_elites(solutions: np.ndarray, seeds: list[int], measures: tuple[str, ...], config: RunConfig,
               cluster: ClusterSettings, client: Any = None) -> np.ndarray:
    """Every solution flown on every seed, on `client` (an experiment's runs share one) or the
    Dask cluster `cluster` names (or a local one): (solutions, seeds, 1 + measures), the
    objective first. A benchmark function's points are scored here, the same on every seed."""
    if scored_here(config.env):
        rows = evaluate_points(solutions, measures, env_name=config.env)
        return np.repeat(rows[:, None, :], len(seeds), axis=1)
    if client is None:
        with dask_client(checked("workers", cluster.workers), scheduler_of(cluster), console_log()) as own:
            return fly_elites(solutions, seeds, measures, config, cluster, own)
    futures = submit_flights(client, solutions, seeds, measures, config.fast_env, env_name=config.env,
                             policy=config.network, episode=episode_of(config))
    return per_terrain(gather_with_progress(client, futures), seeds)


def robustness_table(rows: dict[str, np.ndarray], measures: list[str], seeds: list[int],
                     objectives: np.ndarray, solved: float):
    """Per elite (rows), its objectives on each seed (columns of `objectives`) summed up; the
    elites that generalise best first."""
    import pandas as pd

    table = pd.DataFrame({"cell_index": rows["index"], "objective": rows["objective"],
                          **{name: rows["measures"][:, i] for i, name in enumerate(measures)},
                          "mean_objective": objectives.mean(axis=1), "min_objective": objectives.min(axis=1),
                          "std_objective": objectives.std(axis=1),
                          "solved_share": (objectives >= solved).mean(axis=1)})
    table = pd.concat([table, pd.DataFrame(objectives, columns=[f"objective_seed{s}" for s in seeds])],
                      axis=1)
    return table.sort_values(["mean_objective", "cell_index"], ascending=[False, True], ignore_index=True)


def write_robustness(run: Path, archive: Any, config: RunConfig, rows: dict[str, np.ndarray],
                     seeds: list[int], objectives: np.ndarray, seeds_text: str) -> None:
    """robustness.csv and robustness_heatmap.png (the elites where they were, coloured by their
    mean objective on the new terrains), and a summary line."""
    task, returns = task_of(config), returns_of(config)
    noun = task.family.seed_noun  # the lander's terrains, a robot's reset seeds
    table = robustness_table(rows, config.measures, seeds, objectives, returns.solved)
    write_csv(run / "robustness.csv", table)
    means = ARCHIVES[config.archive]["empty_like"](archive)
    means.add(rows["solution"], objectives.mean(axis=1), rows["measures"])
    save_heatmap(means, [MEASURES[m] for m in config.measures], run / "robustness_heatmap.png",
                 f"Mean objective of {len(table)} elites on {len(seeds)} {noun}(s) ({seeds_text})",
                 returns.heat)
    solves = table["solved_share"]
    print(f"{len(table)} elites on {len(seeds)} {noun}s: "
          f"mean objective {table['mean_objective'].mean():.1f}; "
          f"{(solves == 1).sum()} solve it (>= {returns.solved:g}) on every {noun}, {(solves >= 0.5).sum()} "
          f"on at least half. Best: {table['mean_objective'][0]:.1f} mean, cell {table['cell_index'][0]}.")
    print(f"written to {run / 'robustness.csv'} and {run / 'robustness_heatmap.png'}")


def corrected_archive(archive: Any, config: RunConfig, solutions: np.ndarray, flights: np.ndarray) -> Any:
    """An empty archive of the run's cells (and QD offset) holding each elite by its mean
    objective and mean measures over the new seeds; of elites landing in one cell, the best."""
    objectives, measures = averaged(flights)
    corrected = ARCHIVES[config.archive]["empty_like"](archive)
    corrected.add(solutions, objectives, measures)
    return corrected


def corrected_summary(corrected: Any, run_metrics: dict, seeds: list[int], elites: int) -> dict:
    """corrected.json: the corrected archive's metrics (the fields of a metrics.json row), the
    run's own beside them, and what was flown."""
    fields = iteration_metrics(corrected, run_metrics["iteration"], run_metrics["evaluations"], 0.0)
    del fields["elapsed_s"]
    return {**fields, "repeats": len(seeds), "env_seeds": seeds, "elites_flown": elites,
            "run": {key: run_metrics[key] for key in ("qd_score", "coverage", "num_elites",
                                                      "best_objective", "mean_objective")}}


def write_corrected(run: Path, corrected: Any, summary: dict, config: RunConfig) -> None:
    """The corrected archive beside the run's own: its data (what compare reads), CSV, heatmap,
    corrected.json, and with --archive_pkl its pickle (for pyribs' users)."""
    write_archive_data(run / "corrected_archive.npz", corrected, config.to_json())
    if config.archive_pkl:
        write_pickle(run / "corrected_archive.pkl", corrected)
    write_csv(run / "corrected_archive.csv", corrected.data(return_type="pandas"))
    save_heatmap(corrected, [MEASURES[m] for m in config.measures], run / "corrected_heatmap.png",
                 f"Corrected archive: {summary['elites_flown']} elites, mean of {summary['repeats']} "
                 f"new seeds", returns_of(config).heat)
    write_json(run / "corrected.json", summary)
    own = summary["run"]
    print(f"corrected archive of {summary['elites_flown']} elites on {summary['repeats']} new seeds: "
          f"QD score {summary['qd_score']:,.0f} (the run's {own['qd_score']:,.0f}), coverage "
          f"{summary['coverage']:.4f} ({own['coverage']:.4f}), {summary['num_elites']} cells "
          f"({own['num_elites']})")
    written = [name for name in CORRECTED_FILES if config.archive_pkl or not name.endswith(".pkl")]
    print(f"written to {', '.join(str(run / name) for name in written)}")


def archive_metrics(archive: Any, metrics: list[dict], run: Path) -> dict:
    """The row of metrics.json of the iteration the archive is of. A run still being written saves
    metrics.json before archive.npz, so metrics read after the archive hold its row, and maybe
    later ones: the last row that says what the archive holds (a row is made from the archive;
    the archive made again from its file sums its objectives in another order, so the QD scores
    agree to rounding)."""
    stats = archive.stats
    for row in reversed(metrics):
        if row["num_elites"] == int(stats.num_elites) and math.isclose(
                row["qd_score"], float(stats.qd_score), rel_tol=1e-9, abs_tol=1e-6):
            return row
    raise UsageError(f"{run / 'metrics.json'} has no row of the iteration {run / 'archive.npz'} is of "
                     f"({int(stats.num_elites)} elites, QD score {float(stats.qd_score):,.0f}); "
                     f"if the run is being written, try again")


def corrected_seeds(config: RunConfig, env_seeds: Any, repeats: Any) -> list[int]:
    """The seeds a corrected archive is flown on: --env_seeds, or --repeats new ones."""
    if env_seeds is not None and repeats is not None:
        raise UsageError(f"give {named('env_seeds')} or {named('repeats')}, not both")
    if env_seeds is not None:
        return seed_list("env_seeds", env_seeds)
    return new_seeds(config, whole_number_up_to(MAX_REPEATS)(
        "repeats", DEFAULT_REPEATS if repeats is None else repeats))


def evaluate(path: Path, settings: EvaluateSettings, cluster: ClusterSettings) -> None:
    """Fly the elites of the run in `path` again, on the cluster `cluster` names: the robustness
    table on other terrains, or (settings.corrected) the corrected archive on new seeds; of an
    experiment folder, every run's, on one cluster."""
    if not (path / "experiment.json").is_file():
        return evaluate_run(path, settings, cluster)
    entries = read_experiment(path)["runs"]
    runs = [path / entry["name"] for entry in entries]
    missing = [run.name for run in runs if not (run / "config.json").is_file()]
    if missing:
        raise UsageError(f"{path}: run(s) {', '.join(missing[:5])} not started yet; resume the "
                         f"experiment first (python lunar_lander.py resume {path})")
    local = all(scored_here(upgrade(entry["config"])["env"]) for entry in entries)  # no cluster needed
    with (contextlib.nullcontext() if local else
          dask_client(checked("workers", cluster.workers), scheduler_of(cluster), console_log())) as client:
        for run in runs:
            print(f"{run.name}:")
            evaluate_run(run, settings, cluster, client)


def evaluate_run(run: Path, settings: EvaluateSettings, cluster: ClusterSettings,
                 client: Any = None) -> None:
    """evaluate of one run folder, on `client` if given (else a cluster of its own)."""
    env_seeds, corrected, repeats, top = (settings.env_seeds, settings.corrected, settings.repeats,
                                          settings.top)
    archive, config = load_run(run)
    own = archive_metrics(archive, load_metrics(run), run) if corrected else None  # read after it
    if not corrected and repeats is not None:
        raise UsageError(f"{named('repeats')} is for {named('corrected')} (the robustness table takes "
                         f"{named('env_seeds')})")
    if corrected and top is not None:
        raise UsageError(f"{named('top')} is for the robustness table: a corrected archive flies every elite")
    seeds = (corrected_seeds(config, env_seeds, repeats) if corrected
             else seed_list("env_seeds", ROBUSTNESS_SEEDS if env_seeds is None else env_seeds))
    checked("workers", cluster.workers)
    rows = elite_rows(archive)
    if top is not None:
        rows = {field: values[:top] for field, values in rows.items()}
    check_rollouts(len(rows["solution"]), len(seeds), "to fly")
    check_writable(run)  # before any elite is flown
    # (a --reset each run flew resets of its own, hashed from its env seeds: none of them is one)
    if config.reset == "fixed" and (seen := sorted(set(seeds) & set(config.env_seed))):
        print(f"note: the run searched on {task_of(config).family.seed_noun}(s) {seen} too; they are not "
              f"new to its elites")
    if not corrected:
        objectives = fly_elites(rows["solution"], seeds, (), config, cluster, client)[:, :, 0]
        write_robustness(run, archive, config, rows, seeds, objectives, str(env_seeds or ROBUSTNESS_SEEDS))
        return
    flights = fly_elites(rows["solution"], seeds, tuple(config.measures), config, cluster, client)
    fixed = corrected_archive(archive, config, rows["solution"], flights)
    summary = corrected_summary(fixed, own, seeds, len(rows["solution"]))
    write_corrected(run, fixed, summary, config)
