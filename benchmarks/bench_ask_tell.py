#!/usr/bin/env python
"""pyribs' ask + tell with numba's JIT on and off, for the policy sizes of the tasks: what the
comment on NUMBA_DISABLE_JIT in qdsearch/__init__.py rests on.

Each setting runs in a process of its own (numba reads NUMBA_DISABLE_JIT when it is imported):
the default CMA-ME scheduler (5 emitters x 30) with `dim` weights, fed random objectives and
measures, timed over `--rounds` warm rounds after a first one (which, with the JIT on, compiles).
It prints ms per ask+tell and the first round's seconds, and whether both settings asked the very
same solutions.

    python benchmarks/bench_ask_tell.py --dims "[32, 96, 216]" --rounds 200
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import fire

ROOT = Path(__file__).resolve().parent.parent


def one_setting(dim: int, rounds: int) -> None:
    """In the child process: time the rounds, print them and a digest of every ask as JSON."""
    import dataclasses
    import hashlib

    import gymnasium as gym
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from qdsearch import algorithms, tasks

    # A lander row with a policy of `dim` weights: the scheduler is the search's own.
    from qdsearch.config import options, run_config

    # A lander row with a policy of `dim` weights: the scheduler is the search's own.
    lander = tasks.ENVIRONMENTS["LunarLander-v3"]
    bench = dataclasses.replace(lander)
    bench.__dict__["spaces"] = (gym.spaces.Box(-1.0, 1.0, (dim,)), gym.spaces.Box(-1.0, 1.0, (1,)))
    tasks.ENVIRONMENTS["bench"] = bench
    flags = {**options.search_defaults(), "env": "bench", "seed": 1, "measures": list(lander.measures)}
    config = run_config.check_run_config(options.with_task(flags))
    scheduler = algorithms.build_scheduler(config)
    rng, digest = np.random.default_rng(0), hashlib.sha256()
    times = []
    for _ in range(rounds + 1):
        start = time.perf_counter()
        solutions = scheduler.ask()
        n = len(solutions)
        scheduler.tell(rng.normal(size=n), np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-3, 0, n)]))
        times.append(time.perf_counter() - start)
        digest.update(solutions.tobytes())
    print(json.dumps({"first_s": times[0], "ms": 1000 * float(np.median(times[1:])),
                      "asks": digest.hexdigest()}))


def main(dims: tuple[int, ...] = (32, 96, 216), rounds: int = 200) -> None:
    print(f"{'weights':>8} {'JIT off ms':>11} {'JIT on ms':>10} {'first, on (s)':>14}  same asks")
    for dim in dims:
        found = {}
        for jit_off in ("1", "0"):
            env = {**os.environ, "NUMBA_DISABLE_JIT": jit_off}
            out = subprocess.run([sys.executable, __file__, "--child", str(dim), str(rounds)], env=env,
                                 capture_output=True, text=True, check=True).stdout
            found[jit_off] = json.loads(out.strip().splitlines()[-1])
        off, on = found["1"], found["0"]
        print(f"{dim:>8} {off['ms']:>11.2f} {on['ms']:>10.2f} {on['first_s']:>14.1f}  "
              f"{off['asks'] == on['asks']}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        one_setting(int(sys.argv[2]), int(sys.argv[3]))
    else:
        fire.Fire(main)
