#!/usr/bin/env python
"""What a policy costs per step against the simulator's step (the MLP's share of an episode).

For each task and policy, one seeded start (the policy's own: a Glorot draw for an MLP) is flown
for whole episodes through the engine's episode function (tasks.fly), and its act is timed alone
on the same episodes' observations. Both are timed in turns, `rounds` times, and the medians
give the step's cost with the policy and the policy's share of it. Written to
benchmarks/policies_results.json with the date and the command.

    python benchmarks/bench_policies.py --envs Walker2d-v5,HalfCheetah-v5,Hopper-v5 --rounds 5
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import qdsearch
from qdsearch import tasks  # noqa: E402
from qdsearch.tasks import policies  # noqa: E402
from qdsearch.tasks.policies import Policy  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files

POLICIES = {"linear": Policy(), "mlp 64,64": Policy("mlp", (64, 64)),
            "mlp 128,128": Policy("mlp", (128, 128))}


def time_policy(env_name: str, policy: Policy, episodes: int, rounds: int, length: int) -> dict:
    """Median us per step of whole episodes, and of the policy's act alone on their observations."""
    task = tasks.ENVIRONMENTS[env_name]
    falls = False if tasks.has_unhealthy_state(env_name) else None  # full-length episodes
    env = tasks.make_env(env_name=env_name, episode=tasks.Episode(length, falls))
    solution = (policy.start(task.shape, 1) if policy.kind != "linear"  # the linear start is zeros
                else np.random.default_rng(1).normal(0.0, 0.1, policy.size(task.shape)))
    act, observations = policy.act(solution, task.shape, task.continuous), []
    policies.fly(solution, 0, env, on_step=lambda action, obs: observations.append(obs), env_name=env_name,
              policy=policy)
    flown, acting = [], []
    for _ in range(rounds):
        start = time.perf_counter()
        steps = sum(policies.fly(solution, seed, env, env_name=env_name, policy=policy).steps
                    for seed in range(episodes))
        flown.append((time.perf_counter() - start) / steps)
        start = time.perf_counter()
        for obs in observations:
            act(obs)
        acting.append((time.perf_counter() - start) / len(observations))
    step, policy_s = statistics.median(flown), statistics.median(acting)
    return {"env": env_name, "weights": policy.size(task.shape), "us_per_step": round(1e6 * step, 2),
            "policy_us_per_step": round(1e6 * policy_s, 2), "policy_share": round(policy_s / step, 4)}


def main(envs: str = "Walker2d-v5,HalfCheetah-v5,Hopper-v5,Ant-v5", episodes: int = 3, rounds: int = 5,
         length: int = 1000, out: str = "benchmarks/policies_results.json") -> None:
    rows = []
    for env_name in str(envs).split(","):
        for name, policy in POLICIES.items():
            row = {"policy": name, **time_policy(env_name, policy, episodes, rounds, length)}
            rows.append(row)
            print(json.dumps(row))
    Path(out).write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv),
                                     "episode_length": length, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    fire.Fire(main)
