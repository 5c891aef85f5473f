#!/usr/bin/env python
"""What a tracker costs a search: a 40-iteration search with and without `--track`.

    python benchmarks/bench_trackers.py                       # none, each tracker, all three; 5 rounds
    python benchmarks/bench_trackers.py --trackers "[tensorboard]" --repeats 3

Each round runs `lunar_lander.py --iterations 40 --workers 2 --seed 1` once without a tracker and
once with each tracker set, in turn, so every setting sees the same noise; W&B runs offline and
MLflow writes to its local store in the run folder, as they do by default. For each run: the wall
time from start to exit (it includes the tracker's import, its files and the wait at the end for
its last records) and the search loop (`elapsed_s` in metrics.json, first ask to last tell: what a
tracker working in its own thread may slow). Ratios are taken pair by pair against the untracked
run of the same round, and their median printed. Every tracked run's archive must equal the
untracked one's: a tracker only watches.

Prints and writes benchmarks/tracker_results.json. Run it on a quiet machine.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import fire

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_fixed_cost import SCRIPT, one_search  # noqa: E402


def median_ratio(rows: list[dict], base: list[dict], key: str) -> float:
    return round(statistics.median(row[key] / other[key] for row, other in zip(rows, base)), 3)


def main(trackers: tuple = ("tensorboard", "wandb", "mlflow", "tensorboard,wandb,mlflow"),
         repeats: int = 5, iterations: int = 40, out: str = "benchmarks/tracker_results.json") -> None:
    settings = {"none": (), **{name: ("--track", name) for name in trackers}}
    rows: dict[str, list[dict]] = {name: [] for name in settings}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(repeats):
            for name, extra in settings.items():
                folder = Path(tmp) / f"{name.replace(',', '+')}_{repeat}"
                rows[name].append(one_search(SCRIPT, folder, iterations, extra))
                untracked = Path(tmp) / f"none_{repeat}" / "archive.csv"
                if (folder / "archive.csv").read_bytes() != untracked.read_bytes():
                    raise SystemExit(f"{name}: the archive differs from the untracked run's")
                print(name, rows[name][-1], flush=True)
    result = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
              "search": f"--iterations {iterations} --workers 2 --seed 1 --log_every 25",
              "settings": {name: {"wall_median_s": round(statistics.median(r["wall_s"] for r in found), 2),
                                  "loop_median_s": round(statistics.median(r["loop_s"] for r in found), 2),
                                  "wall_ratio_median": median_ratio(found, rows["none"], "wall_s"),
                                  "loop_ratio_median": median_ratio(found, rows["none"], "loop_s"),
                                  "runs": found}
                           for name, found in rows.items()}}
    print("| tracker | wall s (median) | wall / untracked | search loop s (median) | loop / untracked |")
    print("| --- | --- | --- | --- | --- |")
    for name, figures in result["settings"].items():
        print(f"| {name} | {figures['wall_median_s']} | {figures['wall_ratio_median']} | "
              f"{figures['loop_median_s']} | {figures['loop_ratio_median']} |")
    Path(out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    fire.Fire(main)
