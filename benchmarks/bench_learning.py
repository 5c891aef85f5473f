"""Where a learning row's generation spends its time, at dqd-rl's sizes (an MLP 128,128, 1,000-step
episodes, PGA-ME's 99 + 1 solutions, CMA-MEGA (TD3, ES)'s 600 critic steps): what docs/learning.md
quotes, and what the scale model's predictions take as the driver's turn.

- flight: episodes flown plainly and with their transitions recorded (tasks/transitions.py), in
  interleaved pairs: the recording's cost per step;
- transfer: an episode's transitions, their bytes and a pickle round trip (Dask's way back);
- learning (algorithms/td3.py, the package's own code): the critic's 300 and 600 steps, PGA-ME's
  variation of 49 parents, CMA-MEGA (TD3, ES)'s objective gradient over 65,536 states, after a
  first round that compiles;
- buffer: a generation's transitions added, and a full buffer's checkpoint copy and pickle.

Medians of --rounds, in seconds, measured in one process (quote the ratios, not the times, across
machines). One result file, benchmarks/learning_results.json:

    python benchmarks/bench_learning.py --env HalfCheetah-v5 --rounds 3
"""

from __future__ import annotations

import datetime
import json
import pickle
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from qdsearch import hold_kernels  # noqa: E402

hold_kernels()  # the command line's kernels (JAX's at AVX2 too), before numpy and JAX load

import fire  # noqa: E402
import numpy as np  # noqa: E402

from qdsearch.algorithms import td3  # noqa: E402
from qdsearch.base import compact_pickle  # noqa: E402
from qdsearch.tasks import ENVIRONMENTS, Episode, make_env, rollout  # noqa: E402
from qdsearch.tasks.policies import Policy  # noqa: E402
from qdsearch.tasks.transitions import Recorder  # noqa: E402

POLICY = Policy("mlp", (128, 128))
RESULTS = ROOT / "benchmarks" / "learning_results.json"


def timed(work) -> float:
    start = time.perf_counter()
    work()
    return time.perf_counter() - start


def median(values: list[float]) -> float:
    return float(np.median(values))


def flights(env_name: str, episodes: int, rounds: int) -> dict:
    """Seconds a step, plain and recorded, flown in interleaved pairs from the same resets."""
    shape = ENVIRONMENTS[env_name].shape
    solution = POLICY.start(shape, 1)
    env = make_env(env_name=env_name, episode=Episode(1000))
    recorder = Recorder(make_env(env_name=env_name, episode=Episode(1000)))
    plain, recorded, steps, rows = [], [], 0, None
    def fly(seed: int, where) -> float:
        return timed(lambda: rollout(solution, seed, where, env_name=env_name, policy=POLICY))

    for round_ in range(rounds):
        for seed in range(episodes):
            plain.append(fly(seed, env))
            recorded.append(fly(seed, recorder))
            rows = recorder.take()
            steps += len(rows) if round_ == 0 else 0
    per_step = steps / episodes
    return {"steps_per_episode": per_step, "plain_s_per_step": median(plain) / per_step,
            "recorded_s_per_step": median(recorded) / per_step,
            "recording_ratio": median(recorded) / median(plain), "episode_rows": rows}


def transfer(rows: np.ndarray, rounds: int) -> dict:
    """An episode's transitions: bytes and a pickle round trip."""
    trips = [timed(lambda: pickle.loads(pickle.dumps(rows, protocol=5))) for _ in range(rounds)]
    return {"episode_bytes": int(rows.nbytes), "generation_mb": rows.nbytes * 100 / 1e6,
            "episode_round_trip_s": median(trips)}


def learning(env_name: str, rounds: int, buffer_rows: int) -> dict:
    """The learner's work of a generation, on a buffer of random transitions (the arithmetic does
    not depend on their values), each blocked until its result is there."""
    shape = ENVIRONMENTS[env_name].shape
    learner = td3.Learner(POLICY, shape, POLICY.start(shape, 1), 1_000_000, seed=1)
    width = learner.buffer.rows.shape[1]
    learner.buffer.add(np.random.default_rng(0).normal(size=(buffer_rows, width)).astype(np.float32))
    parents = np.tile(POLICY.start(shape, 2), (49, 1))
    work = {"critic_300_steps": lambda: (learner.train(300), learner.greedy()),
            "critic_600_steps": lambda: (learner.train(600), learner.greedy()),
            "pg_variation_49_parents": lambda: learner.improve(parents),
            "objective_gradient_65536_states": lambda: learner.objective_gradients(parents[:1])}
    first = {f"{name}_first_s": timed(run) for name, run in work.items()}  # compiles
    settled = {f"{name}_s": median([timed(run) for _ in range(rounds)]) for name, run in work.items()}
    return {**first, **settled}


def buffer(env_name: str, rounds: int) -> dict:
    """A generation's 100,000 transitions added; a full buffer's checkpoint copy and pickle."""
    actions, observations = ENVIRONMENTS[env_name].shape
    full = td3.ReplayBuffer(1_000_000, observations, actions)
    generation = np.random.default_rng(0).normal(size=(100_000, full.rows.shape[1])).astype(np.float32)
    adds = [timed(lambda: full.add(generation)) for _ in range(10)]
    full.size = full.capacity  # as after 10 generations
    copies = [timed(lambda: full.state()) for _ in range(rounds)]
    size = len(compact_pickle.dumps(full.state()))
    dumps = [timed(lambda: compact_pickle.dumps(full.state())) for _ in range(rounds)]
    return {"add_generation_s": median(adds), "checkpoint_copy_s": median(copies),
            "checkpoint_pickle_s": median(dumps), "checkpoint_mb": size / 1e6}


def main(env: str = "HalfCheetah-v5", rounds: int = 3, episodes: int = 4, buffer_rows: int = 100_000) -> None:
    flown = flights(env, episodes, rounds)
    rows = flown.pop("episode_rows")
    results = {"env": env, "policy": "mlp 128,128", "flight": flown, "transfer": transfer(rows, rounds),
               "learning": learning(env, rounds, buffer_rows), "buffer": buffer(env, rounds)}
    machine = platform.processor() or platform.machine()
    record = {"date": datetime.date.today().isoformat(), "machine": machine,
              "command": f"python benchmarks/bench_learning.py --env {env} --rounds {rounds}", **results}
    RESULTS.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    fire.Fire(main)
