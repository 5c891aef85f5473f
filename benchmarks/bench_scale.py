#!/usr/bin/env python
"""How far does one experiment scale? The real driver on clusters of up to 512 simulated workers.

    python benchmarks/bench_scale.py                          # 60 runs x 20 iterations; N = 16..512
    python benchmarks/bench_scale.py --workers "[16, 256]" --runs 60 --iterations 40
    python benchmarks/bench_scale.py --env BipedalWalker-v3 --measured 6 --iterations 10 \
        --workers "[64, 256, 512]" --out benchmarks/scale_results_walker.json   # long episodes

A real experiment (`experiments.experiment`: the real driver, real pyribs ask and tell, real run
folders) runs on a real Dask cluster: a `dask scheduler` process of its own, as on an HPC
cluster, and worker processes with many threads each. Each thread is a simulated worker: its task
sleeps as long as the real chunk would take and returns made-up objectives and measures (a
smooth function of each policy). How long a rollout takes comes from real ones: a real search of
--measured iterations in the task of --env, flown first in this process, gives each episode's
steps and the cost of a step; each simulated policy is given one of those episode lengths (by a
hash of its weights).

For each number of simulated workers N it prints, from one experiment:
- the driver's main-process CPU per task and per iteration (everything the driving process did:
  ask, tell, Dask's client side, saving);
- the time from a batch's submission to its first task starting (median and 90th percentile);
- the efficiency against an ideal cluster: the ideal makespan over the measured search phase (from
  the first batch's submission to the last chunk's end; the runs' first checkpoints and last
  saves, which a real 300-iteration run spreads thin, are left out and the whole drive is
  reported beside it). The ideal cluster has no overhead: it needs the total work divided by N,
  and no run can be faster than the sum of its iterations' longest chunks.
Writes benchmarks/scale_results.json. Run it on a quiet machine.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import fire
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from qdsearch import algorithms, engine, experiments, loop, run_config, run_files, tasks  # noqa: E402

TASK_LOG: dict[str, tuple[float, float]] = {}  # on a worker: task key -> (start, end), time.time()


def measure_rollouts(iterations: int, env_name: str) -> tuple[list[int], float]:
    """Episode lengths of a real CMA-ME search's rollouts (the default setting of the task,
    serial, in this process), and the seconds a step costs, from the same rollouts."""
    config = run_config.check_run_config({"seed": 1, "env": env_name})
    scheduler, env = algorithms.build_scheduler(config), engine.worker_env(env_name)
    lengths, steps_time = [], 0.0
    for _ in range(iterations):
        solutions, rows = scheduler.ask(), []
        for solution in solutions:
            start = time.perf_counter()
            flight = tasks.fly(solution, 52, env, env_name=env_name)
            steps_time += time.perf_counter() - start
            lengths.append(flight.steps)
            rows.append([tasks.ENVIRONMENTS[env_name].objective(flight),
                         *(tasks.MEASURES[m].of(flight) for m in config.measures)])
        rows = np.array(rows)
        scheduler.tell(rows[:, 0], rows[:, 1:])
    return lengths, steps_time / sum(lengths)


def simulated_chunk(lengths: list[int], step_s: float):
    """The stand-in for qdsearch.engine.fly_chunk on the simulated workers."""
    def fly_chunk(solutions, env_seeds, measures, fast_env, env_name):
        from distributed.worker import thread_state

        start = time.time()
        steps = [lengths[zlib.crc32(np.asarray(s).tobytes()) % len(lengths)] for s in solutions]
        time.sleep(sum(steps) * step_s)
        TASK_LOG[thread_state.key] = (start, time.time())
        objective = 300 - 100 * np.sum(np.square(solutions), axis=1)
        values = [lo + (hi - lo) * (np.tanh(solutions[:, i]) + 1) / 2 for i, (lo, hi) in
                  enumerate(tasks.MEASURES[name].range for name in measures)]
        return np.column_stack([objective, *values])
    return fly_chunk


def duration_of(chunk_solutions: np.ndarray, lengths: list[int], step_s: float) -> float:
    return sum(lengths[zlib.crc32(np.asarray(s).tobytes()) % len(lengths)]
               for s in chunk_solutions) * step_s


class Recorder:
    """Wraps submit_flights in the driving process: each batch's submission time, its tasks and
    their simulated durations, and the run it belongs to."""

    def __init__(self, lengths: list[int], step_s: float) -> None:
        self.lengths, self.step_s, self.batches, self.run = lengths, step_s, [], ""
        self.original, self.launch = engine.submit_flights, loop.Driver.send
        recorder = self

        def launch(driver, run) -> None:  # which run the next batch is of
            recorder.run = run.name
            recorder.launch(driver, run)
        self.patched_launch = launch

    def __call__(self, client, solutions, env_seeds, measures, *args, **kwargs):
        submitted, cpu = time.time(), time.process_time()
        futures = self.original(client, solutions, env_seeds, measures, *args, **kwargs)
        # the chunks of a batch, as submit_flights splits it (one terrain: rows of solutions)
        sizes = [len(c) for c in np.array_split(np.arange(len(solutions)), len(futures))]
        bounds = np.cumsum([0, *sizes])
        self.batches.append({"submitted": submitted, "cpu": cpu, "keys": [f.key for f in futures],
                             "durations": [duration_of(solutions[a:b], self.lengths, self.step_s)
                                           for a, b in zip(bounds[:-1], bounds[1:])],
                             "run": self.run})
        return futures


def start_cluster(folder: Path, workers: int, processes: int):
    """A `dask scheduler` process and `processes` worker processes of workers/processes threads."""
    scheduler_file = folder / "scheduler.json"
    # The code is importable everywhere, as on a cluster's shared filesystem: nothing is uploaded
    # (an upload would re-import the package on the workers and undo the simulation).
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{ROOT / 'benchmarks'}"}
    started = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1",
                                 "--port", "0", "--no-dashboard", "--scheduler-file", str(scheduler_file)],
                                cwd=folder, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    while not scheduler_file.exists():
        time.sleep(0.1)
    for i in range(processes):
        threads = workers // processes + (i < workers % processes)
        started.append(subprocess.Popen(
            [sys.executable, "-m", "dask", "worker", "--scheduler-file", str(scheduler_file),
             "--nthreads", str(threads), "--nworkers", "1", "--no-dashboard", "--no-nanny",
             "--local-directory", str(folder / f"w{i}")], cwd=folder,
            env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
    return started, scheduler_file


def one_size(workers: int, runs: int, iterations: int, processes: int, lengths: list[int],
             step_s: float, env_name: str) -> dict:
    from dask.distributed import Client

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        started, scheduler_file = start_cluster(folder, workers, processes)
        try:
            with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
                client.wait_for_workers(processes, timeout=120)
                client.run(install_simulation, lengths, step_s)
                recorder = Recorder(lengths, step_s)
                loop.submit_flights = recorder  # the driver's engine call, recorded
                loop.Driver.send = recorder.patched_launch
                try:
                    experiments.experiment(algorithms="cma_me", seeds=f"1-{runs}", iterations=iterations,
                                           log_every=iterations, outdir=str(folder / "exp"), env=env_name,
                                           scheduler_file=str(scheduler_file))
                finally:
                    loop.submit_flights = recorder.original
                    loop.Driver.send = recorder.launch
                log = {}
                for worker_log in client.run(lambda: __import__("bench_scale").TASK_LOG).values():
                    log.update(worker_log)
                plan = json.loads((folder / "exp" / "experiment.json").read_text())
        finally:
            for process in started:
                process.kill()  # the cluster's work is done; its threads may still be asleep
            for process in started:
                process.wait(timeout=60)
    return summarise(workers, runs, iterations, recorder.batches, log, plan)


def install_simulation(lengths: list[int], step_s: float) -> None:
    """On each worker process: the engine's fly_chunk becomes the simulated chunk."""
    import bench_scale

    from qdsearch import engine

    engine.fly_chunk = bench_scale.simulated_chunk(lengths, step_s)


def summarise(workers: int, runs: int, iterations: int, batches: list[dict], log: dict,
              plan: dict) -> dict:
    """The figures of one experiment. Its search phase runs from the first batch's submission to
    the last chunk's end: before it, each run's first checkpoint; after it, each run's last save
    (plots, pickles: ~0.5 s a run, which a real 300-iteration run spreads over its iterations)."""
    tasks = sum(len(b["keys"]) for b in batches)
    latencies = [min(log[k][0] for k in b["keys"] if k in log) - b["submitted"]
                 for b in batches if any(k in log for k in b["keys"])]
    search_s = max(end for _, end in log.values()) - batches[0]["submitted"]
    loop_cpu = batches[-1]["cpu"] - batches[0]["cpu"]  # the driver's CPU between first and last ask
    loop_tasks = tasks - len(batches[-1]["keys"])
    work = sum(sum(b["durations"]) for b in batches)
    # no run can be faster than its iterations' longest chunks, one after another
    paths: dict[str, float] = {}
    for batch in batches:
        paths[batch["run"]] = paths.get(batch["run"], 0.0) + max(batch["durations"])
    critical = max(paths.values())
    ideal = max(work / workers, critical)
    drive, cpu = plan["timing"]["drive_s"], plan["timing"]["main_cpu_s"]
    return {"workers": workers, "runs": runs, "iterations": iterations, "tasks": tasks,
            "tasks_per_batch": round(tasks / len(batches), 2), "work_s": round(work, 2),
            "ideal_s": round(ideal, 3), "search_s": round(search_s, 3),
            "efficiency": round(ideal / search_s, 3), "drive_s": drive, "main_cpu_s": cpu,
            "main_cpu_ms_per_task": round(1000 * loop_cpu / loop_tasks, 3),
            "main_cpu_ms_per_iteration": round(1000 * loop_cpu / (len(batches) - 1), 3),
            "first_start_ms_median": round(1000 * float(np.median(latencies)), 1),
            "first_start_ms_p90": round(1000 * float(np.percentile(latencies, 90)), 1)}


def main(workers: tuple = (16, 64, 256, 512), runs: int = 60, iterations: int = 20,
         processes: int = 4, env: str = tasks.DEFAULT_ENV, measured: int = 20,
         out: str = str(ROOT / "benchmarks" / "scale_results.json")) -> None:
    lengths, step_s = measure_rollouts(measured, env)
    print(f"real rollouts: {len(lengths)} episodes, {np.mean(lengths):.0f} steps on average "
          f"(median {np.median(lengths):.0f}, max {max(lengths)}), {1e6 * step_s:.1f} us a step")
    rows = []
    for n in workers:
        rows.append(one_size(int(n), runs, iterations, processes, lengths, step_s, env))
        print(json.dumps(rows[-1]))
    print("| simulated workers | tasks per batch | ideal s | search s | efficiency | main CPU ms "
          "per task | per iteration | submission to first start, median (p90) ms |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['workers']} | {r['tasks_per_batch']} | {r['ideal_s']} | {r['search_s']} | "
              f"{r['efficiency']} | {r['main_cpu_ms_per_task']} | {r['main_cpu_ms_per_iteration']} | "
              f"{r['first_start_ms_median']} ({r['first_start_ms_p90']}) |")
    run_files.write_json(Path(out), {
        "date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv), "env": env,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "episodes": {"count": len(lengths), "mean_steps": float(np.mean(lengths)),
                     "us_per_step": round(1e6 * step_s, 2)}, "rows": rows})


if __name__ == "__main__":
    fire.Fire(main)
