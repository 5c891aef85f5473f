"""What compare reads of the runs it is given: experiment folders expanded into their runs, each
run's config and metrics, its corrected metrics (compare --corrected), and its metrics cut at a
budget of evaluations (compare --at_evaluations).

Map: `expand_folders`, `load_run_metrics`, CORRECTED and `read_corrected`, `check_fresh`, `cut_at`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from qdsearch.base.flags import UsageError, named, shown, whole_number_up_to
from qdsearch.base.run_files import check_present, read_run_json
from qdsearch.config.run_config import RunConfig, load_checked_config
from qdsearch.search.experiment_folder import read_experiment, unfinished_note
from qdsearch.store.metrics import METRIC_FIELDS, holds, load_metrics

CORRECTED = ("qd_score", "coverage", "num_elites", "best_objective", "mean_objective")  # --corrected's
# What compare reads of a run besides its config and metrics, where there is one (name: kind of
# run_files.FILE_BOUNDS); corrected_*: evaluate --corrected's, read with compare --corrected.
COMPARED_FILES = {"archive.npz": "archive.npz", "archive.csv": "archive.csv", "corrected.json": "JSON",
                  "corrected_archive.npz": "archive.npz", "corrected_archive.csv": "archive.csv"}


def load_run_metrics(run_dir: Path) -> tuple[RunConfig, list[dict]]:
    """A run's config and its metrics rows (at least one, each field of its type), both checked
    as every command checks them, and the files compare reads of it (COMPARED_FILES) regular
    files within their bounds."""
    metrics = load_metrics(run_dir)
    config = load_checked_config(run_dir)
    # a file that is there but no readable one (a link to a device) is refused, not left out
    check_present(run_dir, COMPARED_FILES)
    return config, metrics


def read_corrected(run_dir: Path) -> dict:
    """A run's corrected metrics (corrected.json, written by `evaluate RUN --corrected`: its
    elites flown again on new seeds), each of CORRECTED of its metrics.json type, and `repeats`."""
    path = run_dir / "corrected.json"
    if not path.is_file():
        raise UsageError(f"{run_dir} has no corrected.json: run `python lunar_lander.py evaluate "
                         f"{run_dir} --corrected` first")
    recorded = read_run_json(run_dir, "corrected.json")
    if not isinstance(recorded, dict):
        raise UsageError(f"{path}: holds a {type(recorded).__name__}, not corrected metrics")
    for field in (*CORRECTED, "repeats"):
        kinds = METRIC_FIELDS.get(field, (int,))
        if field not in recorded or not holds(recorded[field], kinds):
            raise UsageError(f"{path}: {field} is {shown(recorded.get(field))}, not "
                             f"{' or '.join(kind.__name__ for kind in kinds)}; run `python "
                             f"lunar_lander.py evaluate {run_dir} --corrected` again")
    return recorded


def expand_folders(paths: list[Path]) -> list[Path]:
    """Run folders, each experiment folder replaced by its runs that have metrics; a run given
    twice (a folder named twice, or a run and its experiment) is counted once, and a note says so."""
    expanded: dict[Path, Path] = {}
    for path in paths:
        # lexists: a file that is there but no readable one is refused as such, not passed over
        if os.path.lexists(path / "experiment.json"):
            plan = read_experiment(path)
            runs = [path / entry["name"] for entry in plan["runs"]]
            runs = [run for run in runs if os.path.lexists(run / "metrics.json")]
            if note := unfinished_note(path, plan):
                print(note)
        else:
            runs = [path]
        for run in runs:
            if (key := run.resolve()) in expanded:
                print(f"note: {run} is given twice (the same run as {expanded[key]}); counted once")
            else:
                expanded[key] = run
    return list(expanded.values())


def check_fresh(fixes: list[dict], runs: list[list[dict]], paths: list[Path]) -> None:
    """A run's corrected.json must be of its last iteration: a run extended since needs it again."""
    for fix, metrics, path in zip(fixes, runs, paths):
        if fix.get("iteration") != metrics[-1]["iteration"]:
            raise UsageError(f"{path / 'corrected.json'} is of iteration {shown(fix.get('iteration'))}, "
                             f"the run is at {metrics[-1]['iteration']}: run `python lunar_lander.py "
                             f"evaluate {path} --corrected` again")


def cut_at(runs: list[list[dict]], paths: list[Path], budget: Any,
           corrected: bool) -> tuple[list[list[dict]], list[bool]]:
    """Each run's metrics up to its last row within `budget` evaluations (None: whole), and
    whether that cut it short. A run whose first iteration is past the budget is refused."""
    if budget is None:
        return runs, [False] * len(runs)
    budget = whole_number_up_to(10**12)("at_evaluations", budget)
    if corrected:
        raise UsageError(f"{named('at_evaluations')} and {named('corrected')}: corrected figures are of a "
                         "run's end")
    kept = []
    for path, metrics in zip(paths, runs):
        first = next((row for row in metrics if row["iteration"] > 0), metrics[-1])
        if first["evaluations"] > budget:
            raise UsageError(f"{path}: its first iteration flew {first['evaluations']:,} evaluations, "
                             f"more than {named('at_evaluations')} {budget:,}")
        kept.append([row for row in metrics if row["evaluations"] <= budget])
    return kept, [len(k) < len(m) for k, m in zip(kept, runs)]
