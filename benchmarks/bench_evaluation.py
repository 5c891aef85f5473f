#!/usr/bin/env python
"""How fast does a search evaluate its rollouts? One seeded search, three ways, same results.

    python benchmarks/bench_evaluation.py [--iterations 20] [--workers "[1, 2]"] [--repeats 3]

Runs the same seeded CMA-ME search (the tutorial's 5 emitters x 30) for a fixed number of
iterations:
- serial: rollouts in this process, once with the tutorial's rollout on gym.make's env and once
  with the project's rollout on the streamlined env: the serial rollout times and per-step costs;
- baseline: the tutorial's Dask evaluation, one task per solution, gym.make per rollout,
  client.map + gather, on a local cluster of N workers;
- engine: the project's `evaluate` (chunks, env kept per worker, streamlined env) on N workers.

It prints a table and writes JSON with seconds per iteration, rollouts per second, parallel
efficiency (serial rollout time / (workers x search time)), the main process's CPU share of the
search's wall time, and whether every variant produced the same archive: medians over --repeats
rounds of all variants, since a shared machine's speed wanders. Cluster start-up is not timed
(each cluster first runs one warm-up task per worker); the search loop is.
"""

from __future__ import annotations

import functools
import logging
import os
import platform
import sys
import time
from pathlib import Path
from typing import Callable

import fire
import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import qdsearch
from qdsearch import algorithms, tasks  # noqa: E402
from qdsearch.base import run_files  # noqa: E402
from qdsearch.config import run_config  # noqa: E402
from qdsearch.config.options import search_defaults, with_task  # noqa: E402
from qdsearch.search import engine  # noqa: E402
from qdsearch.tasks import (
    fast_lander,  # noqa: E402
    policies,
)

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files

CONFIG = run_config.check_run_config(with_task(dict(
    search_defaults(), algorithm="cma_me", seed=1, n_emitters=5, sigma0=1.0, batch_size=30,
    measures=list(tasks.TUTORIAL_MEASURES), grid=50, env_seed=[52], fast_env=True, env=tasks.DEFAULT_ENV)))


def tutorial_simulate(model: np.ndarray, seed: int) -> tuple[float, float, float]:
    """The tutorial's evaluation, as written there (gym.make per call, v3 for gymnasium 1.x)."""
    env = gym.make("LunarLander-v3")
    model = model.reshape((env.action_space.n, env.observation_space.shape[0]))
    total_reward, impact_x_pos, impact_y_vel, all_y_vels = 0.0, None, None, []
    obs, _ = env.reset(seed=seed)
    done = False
    while not done:
        action = np.argmax(model @ obs)
        obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        total_reward += reward
        x_pos, y_vel = obs[0], obs[3]
        all_y_vels.append(y_vel)
        if impact_x_pos is None and (bool(obs[6]) or bool(obs[7])):
            impact_x_pos, impact_y_vel = x_pos, y_vel
    if impact_x_pos is None:
        impact_x_pos, impact_y_vel = x_pos, min(all_y_vels)
    env.close()
    return float(total_reward), float(impact_x_pos), float(impact_y_vel)


def tutorial_evaluate(client, solutions: np.ndarray, env_seed: int):
    """One Dask task per solution, as in the tutorial's Dask version."""
    futures = client.map(lambda model: tutorial_simulate(model, env_seed), solutions)
    results = np.array(client.gather(futures))
    return results[:, 0], results[:, 1:]


def serial_evaluate(rollout: Callable) -> Callable:
    def evaluate(_client, solutions: np.ndarray, env_seed: int):
        results = np.array([rollout(solution, env_seed) for solution in solutions])
        return results[:, 0], results[:, 1:]
    return evaluate


def streamlined_rollout(solution: np.ndarray, seed: int, env) -> tuple[float, ...]:
    return policies.rollout(solution, seed, env, env_name=CONFIG.env)


def engine_evaluate(client, solutions: np.ndarray, env_seed: int):
    return engine.evaluate_batch(client, solutions, CONFIG.replace(env_seed=[env_seed]))


def run_search(evaluate: Callable, client, iterations: int) -> dict:
    """The search loop, timed: wall time, this process's CPU time (all its threads, the Dask
    scheduler's included), and time spent inside `evaluate`."""
    scheduler = algorithms.build_scheduler(CONFIG)
    wall, cpu, evaluating = time.perf_counter(), time.process_time(), 0.0
    for _ in range(iterations):
        solutions = scheduler.ask()
        tic = time.perf_counter()
        objectives, measures = evaluate(client, solutions, 52)
        evaluating += time.perf_counter() - tic
        scheduler.tell(objectives, measures)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {"archive": scheduler.archive, "wall_s": wall, "main_cpu_s": cpu, "evaluate_s": evaluating}


def count_steps(iterations: int) -> int:
    """Environment steps the benchmark's search takes (counted once, untimed)."""
    scheduler, env, steps = algorithms.build_scheduler(CONFIG), fast_lander.FastLunarLander(), 0
    for _ in range(iterations):
        solutions, results = scheduler.ask(), []
        for solution in solutions:
            path: list = []
            results.append(policies.rollout(solution, 52, env, trajectory=path, env_name=CONFIG.env))
            steps += len(path)
        results = np.array(results)
        scheduler.tell(results[:, 0], results[:, 1:])
    return steps


def local_client(workers: int):
    from dask.distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR)
    client = Client(cluster)
    client.wait_for_workers(workers)
    # Warm-up, untimed: every worker imports the product and gymnasium once.
    warm = engine.Chunk(np.zeros((1, 32)), np.array([52]), tuple(tasks.TUTORIAL_MEASURES), CONFIG.env)
    client.gather(client.map(engine.fly_chunk, [warm] * workers, pure=False))
    return cluster, client


def archive_table(archive):
    return archive.data(return_type="pandas").sort_values("index").reset_index(drop=True)


def run_variants(iterations: int, workers: tuple) -> dict[tuple[str, int], dict]:
    """Every variant once: {(name, workers): timings and archive}; workers 0 is in-process."""
    runs = {
        ("serial tutorial rollout, gym.make env", 0):
            run_search(serial_evaluate(tutorial_simulate), None, iterations),
        ("serial project rollout, streamlined env", 0): run_search(
            serial_evaluate(functools.partial(streamlined_rollout, env=fast_lander.FastLunarLander())),
            None, iterations),
    }
    for n in workers:
        for name, evaluate in [("baseline: task per solution (tutorial)", tutorial_evaluate),
                               ("engine: qdsearch.search.engine.evaluate_batch", engine_evaluate)]:
            cluster, client = local_client(n)
            try:
                runs[name, n] = run_search(evaluate, client, iterations)
            finally:
                client.close()
                cluster.close()
    return runs


def main(iterations: int = 20, workers: tuple = (1, 2), repeats: int = 3,
         out: str = "benchmarks/evaluation_results.json") -> None:
    """Median of `repeats` rounds of every variant: a shared machine's speed wanders by ~10%."""
    steps = count_steps(iterations)
    rollouts = iterations * CONFIG.n_emitters * CONFIG.batch_size
    rounds = [run_variants(iterations, tuple(workers)) for _ in range(repeats)]
    def median(key, field):
        return float(np.median([r[key][field] for r in rounds]))

    serial = {"baseline": median(("serial tutorial rollout, gym.make env", 0), "evaluate_s"),
              "engine": median(("serial project rollout, streamlined env", 0), "evaluate_s")}
    rows = []
    for name, n in rounds[0]:
        wall = median((name, n), "wall_s")
        row = {"variant": name, "workers": n, "search_s": round(wall, 2),
               "s_per_iteration": round(wall / iterations, 3),
               "rollouts_per_s": round(rollouts / wall, 1),
               "main_cpu_share": round(float(np.median([r[name, n]["main_cpu_s"] / r[name, n]["wall_s"]
                                                        for r in rounds])), 3),
               "search_s_all_rounds": [round(r[name, n]["wall_s"], 2) for r in rounds]}
        if n:
            serial_time = serial["baseline" if name.startswith("baseline") else "engine"]
            row["serial_rollout_s"] = round(serial_time, 2)
            row["efficiency"] = round(serial_time / (n * wall), 3)
        rows.append(row)
    tables = [archive_table(result["archive"]) for r in rounds for result in r.values()]
    identical = all(table.equals(tables[0]) for table in tables[1:])
    by_key = {(r["variant"].split(":")[0], r["workers"]): r for r in rows}
    engine_x2, base_x2 = by_key.get(("engine", 2)), by_key.get(("baseline", 2))
    summary = {
        "iterations": iterations, "rollouts": rollouts, "steps": steps, "repeats": repeats,
        "us_per_step_tutorial_gym_make": round(serial["baseline"] / steps * 1e6, 2),
        "us_per_step_streamlined": round(serial["engine"] / steps * 1e6, 2),
        "per_step_ratio": round(serial["engine"] / serial["baseline"], 3),
        "engine_speedup_vs_baseline_at_2_workers":
            round(base_x2["search_s"] / engine_x2["search_s"], 2) if engine_x2 and base_x2 else None,
        "identical_archives": identical,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
    }
    print_table(rows, summary)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    run_files.write_json(Path(out), {"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
                                      "summary": summary, "rows": rows})
    print(f"written: {out}")


def print_table(rows: list[dict], summary: dict) -> None:
    print(f"{summary['iterations']} iterations, {summary['rollouts']} rollouts, {summary['steps']} steps; "
          f"medians of {summary['repeats']} rounds")
    header = ("variant", "workers", "search s", "s/iter", "rollouts/s", "efficiency", "main CPU")
    print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for r in rows:
        print(f"| {r['variant']} | {r['workers'] or 'in-process'} | {r['search_s']} | "
              f"{r['s_per_iteration']} | {r['rollouts_per_s']} | {r.get('efficiency', '')} | "
              f"{r['main_cpu_share']:.1%} |")
    print(f"per step: tutorial on gym.make {summary['us_per_step_tutorial_gym_make']} us, "
          f"streamlined {summary['us_per_step_streamlined']} us "
          f"(ratio {summary['per_step_ratio']}); engine vs baseline at 2 workers: "
          f"{summary['engine_speedup_vs_baseline_at_2_workers']}x; "
          f"identical archives: {summary['identical_archives']}")


if __name__ == "__main__":
    fire.Fire(main)
