#!/usr/bin/env python
"""What does a step of each task cost, and does the engine keep 2 workers busy on it?

    python benchmarks/bench_environments.py [--iterations 10] [--envs BipedalWalker-v3,LunarLander-v3]
        [--out benchmarks/environments_results.json]

For each row of ENVIRONMENTS, the same seeded CMA-ME search (the default 5 emitters x 30, the
task's default measures, terrain 52) runs for --iterations iterations twice:
- serially, in this process, in the env the workers use (`qdsearch.search.engine.worker_env`): the cost
  of a step, the mean episode length and rollouts per second on one core;
- through the engine (`evaluate_batch`) on a local cluster of --workers worker processes:
  seconds per iteration and the parallel efficiency, serial rollout time / (workers x search
  time), which counts everything the engine adds, idle workers at an iteration's end included.
Both must give the same archive. Prints a table and writes benchmarks/environments_results.json.
Ratios are what to read on a shared machine; run it when the machine is quiet.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import qdsearch
from qdsearch import algorithms, tasks  # noqa: E402
from qdsearch.base import run_files  # noqa: E402
from qdsearch.config import options, run_config  # noqa: E402
from qdsearch.search import engine  # noqa: E402
from qdsearch.tasks import policies  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def config_of(env_name: str) -> dict:
    return run_config.check_run_config(options.with_task({**options.search_defaults(), "seed": 1,
                                                          "env": env_name}))


def serial_search(env_name: str, iterations: int) -> dict:
    """The search with its rollouts in this process: seconds spent flying, steps, episodes."""
    config = config_of(env_name)
    scheduler, env = algorithms.build_scheduler(config), engine.worker_env(env_name)
    flying, steps, episodes = 0.0, 0, 0
    for _ in range(iterations):
        rows = []
        for solution in scheduler.ask():
            start = time.perf_counter()
            flight = policies.fly(solution, 52, env, env_name=env_name)
            flying += time.perf_counter() - start
            steps, episodes = steps + flight.steps, episodes + 1
            rows.append([tasks.ENVIRONMENTS[env_name].objective(flight),
                         *(tasks.MEASURES[m].of(flight) for m in config.measures)])
        rows = np.array(rows)
        scheduler.tell(rows[:, 0], rows[:, 1:])
    return {"fly_s": flying, "steps": steps, "episodes": episodes, "archive": archive_of(scheduler)}


def engine_search(env_name: str, iterations: int, client) -> dict:
    """The same search through the engine: its wall time (ask, evaluate, tell)."""
    config = config_of(env_name)
    scheduler = algorithms.build_scheduler(config)
    start = time.perf_counter()
    for _ in range(iterations):
        solutions = scheduler.ask()
        scheduler.tell(*engine.evaluate_batch(client, solutions, config))
    return {"search_s": time.perf_counter() - start, "archive": archive_of(scheduler)}


def archive_of(scheduler) -> list:
    data = scheduler.result_archive.data(["index", "objective"])
    return sorted(zip(data["index"].tolist(), data["objective"].tolist()))


def main(iterations: int = 10, workers: int = 2, envs: str = ",".join(tasks.ENVIRONMENTS),
         out: str = "benchmarks/environments_results.json") -> None:
    from dask.distributed import Client, LocalCluster

    envs = [name.strip() for name in str(envs).split(",")]
    rows = []
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=None, silence_logs=logging.ERROR)
    with cluster, Client(cluster) as client:
        for env_name in envs:
            nothing = np.zeros((1, tasks.ENVIRONMENTS[env_name].solution_dim))
            warm = engine.Chunk(nothing, np.array([52]), (), env_name)
            client.gather(client.map(engine.fly_chunk, [warm] * workers, pure=False))  # warm
            serial, engined = serial_search(env_name, iterations), engine_search(env_name, iterations, client)
            rows.append({
                "env": env_name, "iterations": iterations, "episodes": serial["episodes"],
                "mean_steps": round(serial["steps"] / serial["episodes"], 1),
                "us_per_step": round(1e6 * serial["fly_s"] / serial["steps"], 1),
                "rollouts_per_s_one_core": round(serial["episodes"] / serial["fly_s"], 1),
                "engine_s_per_iteration": round(engined["search_s"] / iterations, 3),
                "efficiency": round(serial["fly_s"] / (workers * engined["search_s"]), 3),
                "same_archive": serial["archive"] == engined["archive"]})
            print(rows[-1], flush=True)
    result = {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
              "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
              "workers": workers, "rows": rows, "versions": run_files.library_versions()}
    out = Path(out)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"| env | mean steps | us/step | rollouts/s (1 core) | s/iteration ({workers} workers) | "
          f"efficiency | same archive |\n| --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['env']} | {row['mean_steps']} | {row['us_per_step']} | "
              f"{row['rollouts_per_s_one_core']} | {row['engine_s_per_iteration']} | "
              f"{row['efficiency']} | {row['same_archive']} |")
    print(f"wrote {out}")


if __name__ == "__main__":
    fire.Fire(main)
