#!/usr/bin/env python
"""The episode lengths of a real search, iteration by iteration: what bench_scale.py's simulated
workers sleep for and scale_model.py flies. A CMA-ME search of the task's default setting runs
serially in this process (the same asks and tells as `search`, seed --seed), recording each
episode's steps; the file keeps one array per iteration and the search's mean cost of a step.

    python benchmarks/scale/episode_lengths.py --iterations 300 \
        --out benchmarks/scale/episode_lengths_lander.npz
    python benchmarks/scale/episode_lengths.py --iterations 60 --env BipedalWalker-v3 \
        --out benchmarks/scale/episode_lengths_walker.npz
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import qdsearch
from qdsearch import algorithms, tasks  # noqa: E402
from qdsearch.config import options, run_config  # noqa: E402
from qdsearch.search import engine  # noqa: E402
from qdsearch.tasks import policies  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def record(iterations: int, env_name: str, seed: int) -> tuple[list[np.ndarray], float]:
    """Per iteration, the steps of each of its episodes; and the seconds a step cost."""
    config = run_config.check_run_config(options.with_task(
        {**options.search_defaults(), "seed": seed, "env": env_name}))
    scheduler, env = algorithms.build_scheduler(config), engine.worker_env(env_name, config.fast_env)
    task, steps, seconds = tasks.ENVIRONMENTS[env_name], [], 0.0
    for _ in range(iterations):
        rows, lengths = [], []
        for solution in scheduler.ask():
            start = time.perf_counter()
            flight = policies.fly(solution, config.env_seed[0], env, env_name=env_name)
            seconds += time.perf_counter() - start
            lengths.append(flight.steps)
            rows.append([task.objective(flight), *(tasks.MEASURES[m].of(flight) for m in config.measures)])
        rows = np.array(rows)
        scheduler.tell(rows[:, 0], rows[:, 1:])
        steps.append(np.array(lengths, dtype=np.int32))
    return steps, seconds / sum(int(s.sum()) for s in steps)


def main(iterations: int = 300, env: str = tasks.DEFAULT_ENV, seed: int = 1,
         out: str = "benchmarks/scale/episode_lengths_lander.npz") -> None:
    steps, step_s = record(iterations, env, seed)
    np.savez_compressed(out, **{f"iteration_{k + 1:04d}": s for k, s in enumerate(steps)},
                        us_per_step=np.array(1e6 * step_s), env=np.array(env))
    every = np.concatenate(steps)
    print(f"{env}: {iterations} iterations, {len(every)} episodes, {every.mean():.0f} steps on average "
          f"(first 20 iterations {np.concatenate(steps[:20]).mean():.0f}, last 20 "
          f"{np.concatenate(steps[-20:]).mean():.0f}); {1e6 * step_s:.1f} us a step; wrote {out}")


if __name__ == "__main__":
    fire.Fire(main)
