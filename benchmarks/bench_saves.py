#!/usr/bin/env python
"""What a run's save costs its driver's process: the run folder refreshed from a real checkpoint,
its CSV and pictures drawn in the driver's saver thread (a run on a local cluster) and in a saver
process (a run on a cluster joined by its address: saving.Savers).

    python benchmarks/bench_saves.py --run outputs/seed42 --saves 10

For each way it prints the driver process's CPU per save (all its threads: the main thread and
the saver thread) and the wall time of a save (its call to its end), medians over --saves saves,
after a first save that is left out (imports). Writes benchmarks/save_results.json. Run it on a
quiet machine.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import fire
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import qdsearch  # noqa: E402
from qdsearch.config import run_config  # noqa: E402
from qdsearch.search.run import Run  # noqa: E402
from qdsearch.store import saving  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def timed_saves(run: Run, saves: int, processes: int) -> dict[str, float]:
    """The driver process's CPU and the wall time per save, in ms, medians over `saves` (after
    one left out), with a saver process or none."""
    cpu, wall = [], []
    savers = saving.Savers(processes)
    try:
        for _ in range(saves + 1):
            tic, cpu_tic = time.perf_counter(), time.process_time()
            run.save(savers)
            run.settle()
            wall.append(time.perf_counter() - tic)
            cpu.append(time.process_time() - cpu_tic)
    finally:
        savers.close()
    return {"driver_cpu_ms": round(1000 * float(np.median(cpu[1:])), 1),
            "wall_ms": round(1000 * float(np.median(wall[1:])), 1)}


def main(run: str = "outputs/seed42", saves: int = 10, out: str = "benchmarks/save_results.json") -> None:
    checkpoint = run_config.load_checkpoint(Path(run) / "checkpoint.pkl")  # signed with your key
    config = checkpoint["config"]
    with tempfile.TemporaryDirectory() as tmp:
        saved = Run.from_checkpoint(Path(tmp), {**checkpoint, "config": config},
                                         logging.getLogger("bench_saves"))
        in_thread = timed_saves(saved, saves, processes=0)
        in_process = timed_saves(saved, saves, processes=1)
    result = {
        "date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "run": Path(run).name, "iteration": checkpoint["iteration"],
        "elites": len(checkpoint["scheduler"].result_archive), "saves": saves,
        "saver_thread": in_thread, "saver_process": in_process,
    }
    print(json.dumps(result, indent=2))
    Path(out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    fire.Fire(main)
