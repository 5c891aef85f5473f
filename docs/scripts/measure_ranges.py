#!/usr/bin/env python
"""Do the MEASURES ranges hold what real policies reach? The figures of docs/terrains.md.

    python docs/scripts/measure_ranges.py outputs/seed42 --random 1000        # values outside each range
    python docs/scripts/measure_ranges.py outputs/ranges_fuel outputs/ranges_vx_angle   # edge cells
    python docs/scripts/measure_ranges.py outputs/walker_300/* --env BipedalWalker-v3 --random 300 --good 0

For the policies given (the elites of each run folder's archive, plus --random policies with
weights drawn from N(0, 1), seeded), each flown on terrain 52 of --env: the share of each of the
task's measures' values that fall outside its range, among all of them and among those scoring
over --good. For each run
folder: the share of its elites on the two edge cells of each of its axes (a uniform spread over
a 50-cell axis puts 4% there).
"""

from __future__ import annotations

import sys
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import qdsearch
from qdsearch import tasks  # noqa: E402
from qdsearch.analysis.results import load_run  # noqa: E402
from qdsearch.search import engine  # noqa: E402
from qdsearch.tasks import policies

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


def main(*run_dirs: str, random: int = 0, env_seed: int = 52, env: str = tasks.DEFAULT_ENV,
         good: float = 100.0) -> None:
    archives = [load_run(run_dir) for run_dir in run_dirs]
    for run_dir, (archive, config) in zip(run_dirs, archives):
        cells = archive.int_to_grid_index(archive.data("index"))
        edges = ", ".join(f"{name} {np.isin(cells[:, i], (0, archive.dims[i] - 1)).mean():.1%}"
                          for i, name in enumerate(config.measures))
        print(f"{run_dir}: {len(archive)} elites; on an axis's two edge cells: {edges}")
    solutions = [archive.data("solution") for archive, _ in archives]
    task = tasks.ENVIRONMENTS[env]
    solutions.append(np.random.default_rng(0).normal(size=(random, task.solution_dim)))
    solutions = np.concatenate(solutions)
    names = tuple(tasks.family_measures(task.family))
    flown = np.array([policies.rollout(solution, env_seed, engine.worker_env(env), names, env_name=env)
                      for solution in solutions])
    best = flown[:, 0] > good
    print(f"{len(flown)} policies on terrain {env_seed} of {env} ({best.sum()} scoring over "
          f"{good:g}): share outside each range, all / over {good:g}; lowest return {flown[:, 0].min():.1f}")
    for i, name in enumerate(names):
        low, high = tasks.MEASURES[name].range
        outside = (flown[:, 1 + i] < low) | (flown[:, 1 + i] > high)
        print(f"  {name:18s} [{low:g}, {high:g}]: {outside.mean():.1%} / {outside[best].mean():.1%}; "
              f"values from {flown[:, 1 + i].min():.3g} to {flown[:, 1 + i].max():.3g}")


if __name__ == "__main__":
    fire.Fire(main)
