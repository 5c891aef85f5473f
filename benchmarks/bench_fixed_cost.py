#!/usr/bin/env python
"""The fixed cost of a search: what a short run spends outside its search loop, and the part of it
that no change to this script can remove (importing the libraries a search needs).

    python benchmarks/bench_fixed_cost.py                           # this checkout, 5 runs
    python benchmarks/bench_fixed_cost.py --baseline OLD/lunar_lander.py --repeats 5

Each run is `lunar_lander.py --iterations 20 --workers 2`, with its pictures and without them
(SEARCHES), timed from start to exit as a user runs it. Its search loop is the `elapsed_s` its
metrics.json records (first ask to last tell); the fixed cost is the rest: imports, the cluster's
start, the final outputs and the shutdown. With --baseline, the other script's runs alternate
with this checkout's, so both see the same noise.

The import floor is a fresh process importing what a search imports before its first ask (this
script, its run imports and dask.distributed), with nothing else running: the search's start
cannot be shorter than that on this machine.

Prints and writes benchmarks/fixed_cost_results.json. Run it on a quiet machine.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import fire

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "lunar_lander.py"


def one_search(script: Path, folder: Path, iterations: int = 20, extra: tuple[str, ...] = ()) -> dict:
    """Wall, search loop and fixed cost (seconds) of one search (`extra`: more flags), start to
    exit."""
    tic = time.perf_counter()
    subprocess.run([sys.executable, str(script), "--iterations", str(iterations), "--workers", "2",
                    "--seed", "1", "--log_every", "25", "--outdir", str(folder), *extra],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=script.parent)
    wall = time.perf_counter() - tic
    loop = json.loads((folder / "metrics.json").read_text())[-1]["elapsed_s"]
    return {"wall_s": round(wall, 2), "loop_s": round(loop, 2), "fixed_s": round(wall - loop, 2)}


def import_floor() -> float:
    """Wall seconds of a fresh process that only imports what a search imports."""
    code = ("import importlib, lunar_lander, qdsearch.search.run\n"
            "from qdsearch.search.cluster import DRAWING_IMPORTS, RUN_IMPORTS\n"
            "for name in (*RUN_IMPORTS, *DRAWING_IMPORTS, 'dask.distributed'):\n"
            "    importlib.import_module(name)\n")
    tic = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    return time.perf_counter() - tic


def summary(rows: list[dict]) -> dict:
    fixed = [row["fixed_s"] for row in rows]
    return {"fixed_median_s": round(statistics.median(fixed), 2),
            "fixed_range_s": [min(fixed), max(fixed)],
            "wall_median_s": round(statistics.median(row["wall_s"] for row in rows), 2),
            "runs": rows}


# The searches timed: as the README runs it, and one that writes its data alone (its driver never
# imports matplotlib).
SEARCHES = {"pictures": (), "data_alone": ("--pictures", "false")}


def main(repeats: int = 5, baseline: str | None = None,
         out: str = "benchmarks/fixed_cost_results.json") -> None:
    scripts = {"now": SCRIPT, **({"baseline": Path(baseline).resolve()} if baseline else {})}
    rows: dict[str, dict[str, list[dict]]] = {name: {search: [] for search in SEARCHES} for name in scripts}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(repeats):
            for search, extra in SEARCHES.items():
                for name, script in scripts.items():
                    found = one_search(script, Path(tmp) / f"{name}_{search}_{repeat}", extra=extra)
                    rows[name][search].append(found)
                    print(name, search, found, flush=True)
    floors = [import_floor() for _ in range(repeats)]
    result = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
              "search": "--iterations 20 --workers 2 --seed 1", "searches": SEARCHES,
              **{name: {search: summary(found) for search, found in by_search.items()}
                 for name, by_search in rows.items()},
              "import_floor_median_s": round(statistics.median(floors), 2),
              "import_floor_s": [round(f, 2) for f in floors]}
    if baseline:
        for search in SEARCHES:
            pairs = [now["wall_s"] / old["wall_s"] for now, old in zip(rows["now"][search],
                                                                         rows["baseline"][search])]
            result[f"{search}_wall_ratio_now_over_baseline_median"] = round(statistics.median(pairs), 3)
            result[f"{search}_fixed_ratio_now_over_baseline"] = round(
                result["now"][search]["fixed_median_s"] / result["baseline"][search]["fixed_median_s"], 3)
    shown = {name: {search: {k: v for k, v in found.items() if k != "runs"}
                    for search, found in result[name].items()} for name in rows}
    print(json.dumps({k: v for k, v in result.items() if k not in rows} | shown, indent=2))
    Path(out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    fire.Fire(main)
