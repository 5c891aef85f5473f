"""A run's metrics: a row per iteration in metrics.json, and what each row must hold.

Map:
- METRIC_FIELDS (the row's fields and types), `iteration_metrics` (a row, from the archive);
- `describe_progress` (a row as a log line);
- reading them back: `check_metrics` (with `holds`), `load_metrics`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from qdsearch.base.flags import UsageError, shown
from qdsearch.base.run_files import read_run_json

# A row of metrics.json: each field and what it holds (None: no elite yet).
METRIC_FIELDS: dict[str, tuple[type, ...]] = {
    "iteration": (int,), "evaluations": (int,), "coverage": (float,), "num_elites": (int,),
    "qd_score": (float,), "best_objective": (float, type(None)),
    "mean_objective": (float, type(None)), "elapsed_s": (float,),
}


def iteration_metrics(archive, iteration: int, evaluations: int, elapsed: float) -> dict:
    """One row of metrics.json: the archive's state after `iteration` iterations."""
    stats = archive.stats
    return {
        "iteration": iteration,
        "evaluations": evaluations,
        "coverage": float(stats.coverage),
        "num_elites": int(stats.num_elites),
        "qd_score": float(stats.qd_score),
        "best_objective": float(stats.obj_max) if stats.num_elites else None,
        "mean_objective": float(stats.obj_mean) if stats.num_elites else None,
        "elapsed_s": round(elapsed, 3),
    }


def describe_progress(row: dict, iterations: int) -> str:
    best = row["best_objective"]
    return (f"iteration {row['iteration']}/{iterations}: {row['evaluations']} evaluations, "
            f"coverage {row['coverage']:.3f}, QD score {row['qd_score']:.0f}, "
            f"best {best if best is None else round(best, 1)}, "
            f"{row['elapsed_s'] / max(row['iteration'], 1):.2f} s/iteration")


def check_metrics(rows: Any, path: Path) -> list[dict]:
    """metrics.json's rows (at least one), each with every field of METRIC_FIELDS holding a value
    of its type (an int counts as a float; NaN and infinities do not), or a UsageError that names
    the first that does not."""
    if not isinstance(rows, list) or not rows:
        raise UsageError(f"{path}: no metrics (a list of one row per iteration)")
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise UsageError(f"{path}: row {i} is a {type(row).__name__}, not a row of metrics")
        for field, kinds in METRIC_FIELDS.items():
            if field not in row and field != "elapsed_s":  # older runs recorded no timings
                raise UsageError(f"{path}: row {i} has no {field}")
            if field in row and not holds(row[field], kinds):
                raise UsageError(f"{path}: row {i} has {field} = {shown(row[field])}, not "
                                 f"{' or '.join(kind.__name__ for kind in kinds)}")
    return rows


def holds(value: Any, kinds: tuple[type, ...]) -> bool:
    """Whether a JSON value is one of `kinds`: a whole number counts as a float; NaN, infinities
    and booleans count as nothing."""
    if value is None or isinstance(value, bool):
        return value is None and type(None) in kinds
    if float in kinds:
        return isinstance(value, (int, float)) and math.isfinite(value)
    return isinstance(value, int)


def load_metrics(run_dir: Path) -> list[dict]:
    """A run folder's metrics.json, checked (check_metrics)."""
    return check_metrics(read_run_json(run_dir, "metrics.json"), run_dir / "metrics.json")
