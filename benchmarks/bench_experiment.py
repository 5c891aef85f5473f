#!/usr/bin/env python
"""Many runs at once: the same N seeded searches one after another with `search`, and as one
`experiment` on one cluster, each timed from start to exit, in one invocation on one machine.

    python benchmarks/bench_experiment.py                  # 4 seeds x 20 iterations, 2 workers
    python benchmarks/bench_experiment.py --runs 8 --iterations 30

Prints and writes benchmarks/experiment_results.json:
- both wall times and their ratio;
- the experiment's parallel efficiency: the serial rollout time of its rollouts (the same runs
  flown again in one process, timing only the rollouts) / (workers x its search time, the driving
  loop's wall time as experiment.json records it);
- the ceiling of that efficiency on this machine: the same serial rollouts run in two processes
  at once are slower than in one alone (two busy cores share caches, or are hyperthreads);
- the main process's CPU share while it drove the runs;
- whether every experiment run equals its lone `search` twin (archive and metrics).
Run it on a quiet machine: another heavy job spoils both timings.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import fire
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "lunar_lander.py"
sys.path.insert(0, str(ROOT))

import qdsearch  # noqa: E402
from qdsearch import algorithms, tasks  # noqa: E402
from qdsearch.config import run_config  # noqa: E402
from qdsearch.tasks import policies  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def timed(*args: str) -> float:
    """Wall seconds of the script run as a user runs it, start to exit."""
    tic = time.perf_counter()
    subprocess.run([sys.executable, str(SCRIPT), *args], check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    return time.perf_counter() - tic


def serial_rollout_seconds(configs: list[dict]) -> float:
    """The runs again, in this process: only their rollouts are timed, one after another."""
    total = 0.0
    for config in map(run_config.check_run_config, configs):
        env = tasks.make_env(env_name=config.env)
        scheduler = algorithms.build_scheduler(config)
        for _ in range(config.iterations):
            solutions = scheduler.ask()
            tic = time.perf_counter()
            rows = np.array([policies.rollout(s, config.env_seed[0], env, config.measures,
                                           env_name=config.env) for s in solutions])
            total += time.perf_counter() - tic
            scheduler.tell(rows[:, 0], rows[:, 1:])
    return total


def two_at_once_seconds(configs: list[dict]) -> float:
    """The same serial rollouts in two processes at once: the slower one's rollout seconds. Two
    busy processes on two cores each run slower than one alone (shared caches, hyperthreads):
    serial / this is the most any 2-worker evaluation can reach here."""
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import bench_experiment as b; "
            "print(b.serial_rollout_seconds(json.loads(sys.argv[2])))")
    args = [sys.executable, "-c", code, str(Path(__file__).parent), json.dumps(configs)]
    processes = [subprocess.Popen(args, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    return max(float(process.communicate()[0]) for process in processes)


def same_run(a: Path, b: Path) -> bool:
    def archive(run):
        table = run_config.saved_archive(run).data(return_type="pandas")
        return table.sort_values("index").reset_index(drop=True)

    def metrics(run):
        return [{k: v for k, v in row.items() if k != "elapsed_s"}
                for row in json.loads((run / "metrics.json").read_text())]
    return archive(a).equals(archive(b)) and metrics(a) == metrics(b)


def main(runs: int = 4, iterations: int = 20, workers: int = 2,
         out: str = "benchmarks/experiment_results.json") -> None:
    seeds = list(range(1, runs + 1))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        common = ["--iterations", str(iterations), "--workers", str(workers),
                  "--log_every", str(iterations)]
        serial = [timed(*common, "--seed", str(seed), "--outdir", str(folder / f"search_{seed}"))
                  for seed in seeds]
        experiment = timed("experiment", "--algorithms", "cma_me", "--seeds", f"1-{runs}", *common,
                           "--outdir", str(folder / "experiment"))
        plan = json.loads((folder / "experiment" / "experiment.json").read_text())
        equal = all(same_run(folder / "experiment" / run["name"], folder / f"search_{run['seed']}")
                    for run in plan["runs"])
        configs = [run["config"] for run in plan["runs"]]
        rollout_s = serial_rollout_seconds(configs)
        two_s = two_at_once_seconds(configs)
    timing = plan["timing"]
    result = {
        "date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "runs": runs, "iterations": iterations, "workers": workers,
        "searches_one_after_another_s": round(sum(serial), 2),
        "search_each_s": [round(s, 2) for s in serial],
        "experiment_s": round(experiment, 2),
        "speedup": round(sum(serial) / experiment, 2),
        "experiment_search_s": timing["drive_s"],
        "serial_rollout_s": round(rollout_s, 2),
        "parallel_efficiency": round(rollout_s / (workers * timing["drive_s"]), 3),
        "serial_rollout_two_at_once_s": round(two_s, 2),
        "efficiency_ceiling_two_processes": round(rollout_s / two_s, 3),
        "main_cpu_share": round(timing["main_cpu_s"] / timing["drive_s"], 3),
        "every_run_equals_its_lone_twin": equal,
    }
    print(json.dumps(result, indent=2))
    Path(out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    fire.Fire(main)
