#!/usr/bin/env python
"""How far does one experiment scale? The real driver on clusters of up to 512 simulated workers.

    python benchmarks/scale/bench_scale.py --workers "[16, 64]" --parts "[1, 2, 4]" --repeats 3 \
        --iterations 20 --lengths benchmarks/scale/episode_lengths_lander.npz   # scale_results.json
    python benchmarks/scale/bench_scale.py --out outputs/scale.json   # 60 runs x 20 iterations; N = 16..512
    python benchmarks/scale/bench_scale.py --env BipedalWalker-v3 --measured 6 --iterations 10 \
        --workers "[64, 256, 512]" --out outputs/scale_walker.json   # long episodes
    python benchmarks/scale/bench_scale.py --workers "[64]" --log_every "[20, 10]" --savers "[0, 2]" \
        --lengths benchmarks/scale/episode_lengths_lander.npz --out outputs/scale_saves.json   # saves
    python benchmarks/scale/bench_scale.py --workers "[17]" --runs 4 --processes 17 --chunks "[2, 3]" \
        --iterations 100 --lengths benchmarks/scale/episode_lengths_lander.npz \
        --out outputs/scale_chunks.json   # one of 15 parts of 256 workers
    python benchmarks/scale/bench_scale.py --workers "[64]" --switch "[None, 0.0005]" \
        --lengths benchmarks/scale/episode_lengths_lander.npz --out outputs/scale_switch.json

A real experiment (`commands.experiment`: the real driver, real pyribs ask and tell, real run
folders) runs on a real Dask cluster: a `dask scheduler` process of its own, as on an HPC
cluster, and worker processes with many threads each. Each thread is a simulated worker: its task
sleeps as long as the real chunk would take and returns made-up objectives and measures (a
smooth function of each policy). Each simulated policy is given an episode length (by a hash of
its weights) from --lengths (every iteration of a real search, episode_lengths.py) or
from a real search of --measured iterations flown first here, which also gives the cost of a step.
With --parts K, the experiment is split in K parts (experiment --part), each driven by its own
process on its own `dask scheduler`, the workers shared out among them.

For each number of simulated workers N and of parts it prints, from one experiment (its records
summed up by scale_records.py):
- the efficiency against an ideal cluster: the ideal makespan over the measured search phase (from
  the first batch's submission to the last chunk's end; the runs' first checkpoints and last
  saves, which a real 300-iteration run spreads thin, are left out). The ideal cluster has no
  overhead: it needs the total work divided by N, and no run can be faster than the sum of its
  iterations' longest chunks;
- the utilisation (work / (N x search time)), over the whole search and over its steady state
  (from the moment every run has sent its first batch to the first run's last tell);
- the drivers' CPU and their main thread's wall time at work (not blocked waiting for a chunk)
  per run-iteration, the schedulers' and the worker processes' CPU per task (every second of
  those processes in the search phase, over the tasks), when the last run opens (and when each
  driver sent its first batch, how long a driver takes to open a run, and how long each driver
  waited for its first task to start: its scheduler's first graph), and each run-iteration's
  cycle split: the driver (previous tell to submission), to the first chunk's start (and on the
  way, from the scheduler's and the workers' own logs: its graph taken in by the scheduler, the
  chunk handed out there, at its worker process), flying (first start to last end), back (last
  end to the tell: the last result's landing in the driver's process, then its wait for the main
  thread, also over the batches told once a run has ended, whose last save its driver writes
  meanwhile), and the same for each run's first batch apart (sent while its driver opens the
  other runs);
- the time from a batch's submission to its first task starting (median and 90th percentile), and
  a result's landing: from its task's end to the result in its driver's process (mean, median),
  and to its scheduler (its report), the share of batches whose last result landed while the
  driver's main thread was idle, and how long that idle thread took to wake;
- over every task, its way from its handing out to its worker process and its wait there, once
  both it and a free thread are there, for the process's event loop to start it (each task's
  thread is recorded); and a batch's graph taken in by its scheduler (Dask's own timing of its
  update_graph, each scheduler's first graph, which imports the tasks' code, left out);
- the time from the first batch's submission to the end of the last driver, its runs' last saves
  written (`all_saved_s`).
Writes benchmarks/scale/scale_results.json (--out). Run it on a quiet machine.
"""

from __future__ import annotations

import itertools
import json
import os
import platform
import queue
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path

import fire
import numpy as np

HERE = Path(__file__).resolve().parent  # benchmarks/scale: this script, scale_records.py
ROOT = HERE.parents[1]  # the repository: the package
sys.path.insert(0, str(ROOT))

from scale_records import OUT, summarise  # noqa: E402

import qdsearch  # noqa: E402
from qdsearch import algorithms, tasks  # noqa: E402
from qdsearch.base import run_files  # noqa: E402
from qdsearch.cli import commands  # noqa: E402
from qdsearch.config import run_config  # noqa: E402
from qdsearch.search import engine, loop  # noqa: E402
from qdsearch.search import run as one_run  # noqa: E402
from qdsearch.tasks import policies  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files

VARIANTS = ("log_every", "savers", "chunks", "switch")  # the drive command's options a row may set
# on a worker: task key -> (start, end, its thread), time.time(); the thread as "pid-ident"
TASK_LOG: dict[str, tuple[float, float, str]] = {}


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
            flight = policies.fly(solution, 52, env, env_name=env_name)
            steps_time += time.perf_counter() - start
            lengths.append(flight.steps)
            rows.append([tasks.ENVIRONMENTS[env_name].objective(flight),
                         *(tasks.MEASURES[m].of(flight) for m in config.measures)])
        rows = np.array(rows)
        scheduler.tell(rows[:, 0], rows[:, 1:])
    return lengths, steps_time / sum(lengths)


def simulated_chunk(lengths: list[int], step_s: float):
    """The stand-in for qdsearch.search.engine.fly_chunk on the simulated workers."""
    def fly_chunk(chunk):
        from distributed.worker import thread_state

        solutions, measures = chunk.solutions, chunk.measures
        start = time.time()
        steps = [lengths[zlib.crc32(np.asarray(s).tobytes()) % len(lengths)] for s in solutions]
        time.sleep(sum(steps) * step_s)
        TASK_LOG[thread_state.key] = (start, time.time(), f"{os.getpid()}-{threading.get_ident()}")
        objective = 300 - 100 * np.sum(np.square(solutions), axis=1)
        values = [lo + (hi - lo) * (np.tanh(solutions[:, i]) + 1) / 2 for i, (lo, hi) in
                  enumerate(tasks.MEASURES[name].range for name in measures)]
        return np.column_stack([objective, *values])
    return fly_chunk


def duration_of(chunk_solutions: np.ndarray, lengths: list[int], step_s: float) -> float:
    return sum(lengths[zlib.crc32(np.asarray(s).tobytes()) % len(lengths)]
               for s in chunk_solutions) * step_s


class TimedCondition(threading.Condition):
    """as_completed's condition with its waits recorded: the driver's main thread blocked, no
    chunk ready (it is idle then). Time spent taking a ready chunk (as_completed's lock, the GIL
    its client's event loop holds while it hands results over) is work, as the model counts it."""

    def __init__(self, waits: list) -> None:
        super().__init__()
        self.waits = waits

    def wait(self, timeout: float | None = None) -> bool:
        start = time.time()
        try:
            return super().wait(timeout)
        finally:
            self.waits.append((start, time.time()))


class LandingQueue(queue.Queue):
    """as_completed's queue of results with the time each lands in it (its key's): the driver's
    process has it then, and its main thread takes it when it gets to it."""

    def __init__(self, landed: dict) -> None:
        super().__init__()
        self.landed = landed

    def put_nowait(self, item) -> None:
        future = item[0] if isinstance(item, tuple) else item
        self.landed[future.key] = time.time()
        super().put_nowait(item)


class Recorder:
    """In a driving process: each batch's submission (time, the process's CPU, its tasks and their
    simulated durations, its run), each batch's tell (time, CPU, run), the main thread's waits for
    a chunk and when each result lands, by wrapping the run loop's engine call, Driver.send and
    Run.tell."""

    def __init__(self, pool: list[int], step_s: float) -> None:
        self.pool, self.step_s, self.batches, self.tells, self.run = pool, step_s, [], [], ""
        self.original, self.launch, self.tell = engine.submit_flights, loop.Driver.send, one_run.Run.tell
        self.waits, self.landed = [], {}
        recorder = self

        def launch(driver, run) -> None:  # which run the next batch is of
            finished = driver.finished  # before its first batch: its waits and results timed
            if not isinstance(finished.queue, LandingQueue):
                finished.queue, finished.thread_condition = (LandingQueue(recorder.landed),
                                                             TimedCondition(recorder.waits))
            recorder.run = run.name
            recorder.launch(driver, run)

        def tell(run, objectives, measures):
            recorder.tells.append({"run": run.name, "at": time.time(), "cpu": time.process_time()})
            return recorder.tell(run, objectives, measures)
        self.patched_launch, self.patched_tell = launch, tell

    def __call__(self, client, solutions, env_seeds, measures, *args, **kwargs):
        submitted, cpu = time.time(), time.process_time()
        futures = self.original(client, solutions, env_seeds, measures, *args, **kwargs)
        # the chunks of a batch, as submit_flights deals them out (one terrain: solutions)
        chunks = engine.chunk_pairs(len(solutions), len(futures))
        self.batches.append({"submitted": submitted, "cpu": cpu, "keys": [f.key for f in futures],
                             "durations": [duration_of(solutions[chunk], self.pool, self.step_s)
                                           for chunk in chunks],
                             "run": self.run})
        return futures

    def __enter__(self) -> Recorder:
        one_run.submit_flights, loop.Driver.send = self, self.patched_launch
        one_run.Run.tell = self.patched_tell
        return self

    def __exit__(self, *exc) -> None:
        one_run.submit_flights, loop.Driver.send, one_run.Run.tell = self.original, self.launch, self.tell


def start_cluster(folder: Path, workers: int, processes: int):
    """A `dask scheduler` process and `processes` worker processes of workers/processes threads."""
    folder.mkdir(parents=True, exist_ok=True)
    scheduler_file = folder / "scheduler.json"
    # The code is importable everywhere, as on a cluster's shared filesystem: nothing is uploaded
    # (an upload would re-import the package on the workers and undo the simulation).
    # Workers as docs/slurm.sbatch starts them: without Dask's statistical profiler.
    # The schedulers and workers keep every transition (Dask keeps the last 1,000): the way of
    # each task, read off them (scheduler_times, worker_arrivals).
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{HERE}",
           "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
           "DASK_DISTRIBUTED__ADMIN__LOW_LEVEL_LOG_LENGTH": "1000000"}
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


def drive(folder: str, scheduler_file: str, simulation: str, runs: int, iterations: int, env: str,
          part: str | None = None, record: str = "record.json", log_every: int | None = None,
          savers: int | None = None, chunks: int | None = None, switch: float | None = None) -> None:
    """A driving process (a subcommand, run by one_size): the experiment (or its --part), its
    batches and tells recorded, written to `record`; with `savers`, at most that many saver
    processes (0: the saver thread draws, as with a local cluster); with `chunks`, that many
    chunks per worker, whatever the runs (else engine.chunks_per_worker's); with `switch`, that
    switch interval (sys.setswitchinterval: how long a thread waits for the GIL before it asks the
    holder to drop it; Python's own is 5 ms)."""
    pool, step_s = json.loads(Path(simulation).read_text())
    if switch is not None:
        sys.setswitchinterval(switch)
    if savers is not None:
        loop.SAVER_PROCESSES = savers
    if chunks is not None:
        engine.CHUNKS_PER_WORKER = engine.CHUNKS_PER_WORKER_FEW_RUNS = chunks
    with Recorder(pool, step_s) as recorder:
        commands.experiment(algorithms="cma_me", seeds=f"1-{runs}", iterations=iterations,
                               log_every=log_every or iterations, outdir=folder, env=env, part=part,
                               scheduler_file=scheduler_file)
    run_files.write_json(Path(record), {"batches": recorder.batches, "tells": recorder.tells,
                                        "cpu_s": time.process_time(), "waits": recorder.waits,
                                        "landed": recorder.landed, "ended": time.time()})


def process_cpu(pid: int) -> float:
    """The CPU seconds a process has used (user and system)."""
    import psutil

    times = psutil.Process(pid).cpu_times()
    return times.user + times.system


class CpuSampler(threading.Thread):
    """Every 50 ms, the CPU seconds the schedulers and the worker processes have used, with the
    time: their CPU over the search phase alone can then be read off (`between`). Over the whole
    drive it would include their fixed cost per second (heartbeats, monitors) through the runs'
    opening and last saves, when there are few tasks or none."""

    def __init__(self, schedulers: list[int], workers: list[int]) -> None:
        super().__init__(daemon=True)
        self.pids, self.samples, self.stop = (schedulers, workers), [], threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.05):
            self.samples.append((time.time(), *(sum(process_cpu(pid) for pid in pids) for pids in self.pids)))

    def between(self, start: float, end: float) -> tuple[float, float]:
        """The schedulers' and the workers' CPU seconds from `start` to `end` (interpolated)."""
        times, *cpus = np.array(self.samples).T
        return tuple(float(np.interp(end, times, cpu) - np.interp(start, times, cpu)) for cpu in cpus)


def one_size(workers: int, runs: int, iterations: int, processes: int, parts: int, pool: list[int],
             step_s: float, env_name: str, variant: tuple[float | None, ...] = (None,) * 4,
             raw: Path | None = None) -> dict:
    """One experiment of `runs` runs on `workers` simulated workers: one driving process and one
    `dask scheduler` per part, the workers shared out among the schedulers; `variant`: the drive
    command's log_every, savers, chunks and switch interval (None: its own); with `raw`, every
    record it was summed up from written there (the drivers' records, each task's times)."""
    from dask.distributed import Client

    with tempfile.TemporaryDirectory() as tmp:
        folder, started, clusters, worker_pids = Path(tmp), [], [], []
        try:
            count = max(1, processes // parts)  # worker processes per part
            for p in range(parts):
                share = workers // parts + (p < workers % parts)
                procs, scheduler_file = start_cluster(folder / f"cluster{p}", share, count)
                started += procs
                clusters.append((procs[0].pid, scheduler_file, count))
                worker_pids += [process.pid for process in procs[1:]]
            for _, scheduler_file, count in clusters:
                with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
                    client.wait_for_workers(count, timeout=120)
                    client.run(install_simulation, pool, step_s)
                    client.run_on_scheduler(record_graph_intakes)
            simulation = folder / "simulation.json"
            simulation.write_text(json.dumps([pool, step_s]))
            sampler = CpuSampler([pid for pid, _, _ in clusters], worker_pids)
            sampler.start()
            drivers = [subprocess.Popen(
                [sys.executable, __file__, "drive", str(folder / "exp"), str(scheduler_file), str(simulation),
                 str(runs), str(iterations), env_name, *([f"--part={p + 1}/{parts}"] if parts > 1 else []),
                 f"--record={folder / f'record{p}.json'}",
                 *[f"--{name}={value}" for name, value in zip(VARIANTS, variant) if value is not None]],
                stdout=subprocess.DEVNULL)
                for p, (_, scheduler_file, _) in enumerate(clusters)]
            for process in drivers:
                if process.wait() != 0:
                    raise RuntimeError(f"a driving process failed ({process.args})")
            sampler.stop.set()
            sampler.join()
            log, arrived, assigned, reached, reported, intakes = {}, {}, {}, {}, {}, []
            for _, scheduler_file, _ in clusters:
                with Client(scheduler_file=str(scheduler_file), timeout="60s") as client:
                    for worker_log in client.run(lambda: __import__("bench_scale").TASK_LOG).values():
                        log.update(worker_log)
                    for times, got in zip((arrived, assigned, reported),
                                          client.run_on_scheduler(scheduler_times)):
                        times.update(got)
                    intakes.append(client.run_on_scheduler(graph_intakes))
                    for worker_times in client.run(worker_arrivals).values():
                        reached.update(worker_times)
            records = [json.loads((folder / f"record{p}.json").read_text()) for p in range(parts)]
        finally:
            for process in started:
                process.kill()  # the cluster's work is done; its threads may still be asleep
            for process in started:
                process.wait(timeout=60)
    way_out = (arrived, assigned, reached)  # each task's times, by OUT
    if raw is not None:
        run_files.write_json(raw, {"records": records, "log": log, "reported": reported, "intakes": intakes,
                                   **dict(zip(OUT, way_out))})
    return {**summarise(workers, runs, iterations, parts, records, log, sampler.between, way_out, reported,
                        intakes),
            "log_every": variant[0] or iterations, "saver_processes": variant[1],
            "chunks_per_worker": variant[2],  # None: engine.chunks_per_worker's
            "driver_switch_s": variant[3]}  # None: Python's own


def scheduler_times(dask_scheduler) -> tuple[dict[str, float], ...]:
    """On a scheduler, by task (time.time()): when its graph was taken in (its first transition),
    when it was handed to a worker process (to processing: Dask queues a task while every worker
    process holds its worker-saturation's worth), and when its end was reported (to memory: its
    worker process's slot is free again)."""
    arrived: dict[str, float] = {}
    assigned: dict[str, float] = {}
    reported: dict[str, float] = {}
    for transition in dask_scheduler.transition_log:
        arrived.setdefault(transition.key, transition.timestamp)
        for finish, times in (("processing", assigned), ("memory", reported)):
            if transition.finish == finish:
                times.setdefault(transition.key, transition.timestamp)
    return arrived, assigned, reported


def record_graph_intakes(dask_scheduler) -> None:
    """On a scheduler: each graph's intake (its update_graph handler, a wall time as Dask times
    it) kept on the scheduler, in order; Dask keeps only their sum. (Nothing is imported there:
    the scheduler's first graph imports the tasks' code, as it does without the benchmark.)"""
    intakes = dask_scheduler.bench_graph_intakes = []
    digest = dask_scheduler.digest_metric

    def recording(name, value) -> None:
        if name == "update-graph-duration":
            intakes.append(value)
        digest(name, value)
    dask_scheduler.digest_metric = recording


def graph_intakes(dask_scheduler) -> list[float]:
    """On a scheduler: each graph's intake so far, in seconds (record_graph_intakes)."""
    return list(dask_scheduler.bench_graph_intakes)


def worker_arrivals(dask_worker) -> dict[str, float]:
    """On a worker process: when each task reached it (its compute-task message handled)."""
    return {entry[0]: entry[-1] for entry in dask_worker.state.log
            if len(entry) == 5 and entry[1] == "compute-task"}


def install_simulation(pool: list[int], step_s: float) -> None:
    """On each worker process: the engine's fly_chunk becomes the simulated chunk."""
    import bench_scale

    from qdsearch.search import engine

    engine.fly_chunk = bench_scale.simulated_chunk(pool, step_s)


def lengths_pool(lengths: str | None, measured: int, env: str) -> tuple[list[int], float, str]:
    """The episode lengths the simulated workers draw from, the cost of a step (from real
    rollouts here, now), and where the lengths come from: a file of a real search's lengths
    (episode_lengths.py: every iteration of it pooled), or the first `measured`
    iterations of a search flown here."""
    real, step_s = measure_rollouts(measured, env)
    if lengths is None:
        return real, step_s, f"the first {measured} iterations of a search"
    with np.load(lengths) as data:
        pool = np.concatenate([data[k] for k in sorted(data.files) if k.startswith("iteration_")])
        iterations = sum(1 for k in data.files if k.startswith("iteration_"))
    return [int(x) for x in pool], step_s, f"{lengths} ({iterations} iterations)"


def main(workers: tuple = (16, 64, 256, 512), runs: int = 60, iterations: int = 20,
         processes: int = 4, env: str = tasks.DEFAULT_ENV, measured: int = 20, parts: tuple = (1,),
         repeats: int = 1, lengths: str | None = None, log_every: tuple = (None,),
         savers: tuple = (None,), chunks: tuple = (None,), switch: tuple = (None,),
         out: str = str(HERE / "scale_results.json"), raw: str | None = None) -> None:
    """`log_every`: the runs' saves (None: at their end only); `savers`: at most that many saver
    processes a driver (None: the code's own, loop.SAVER_PROCESSES; 0: its saver thread draws);
    `chunks`: chunks per worker (None: the engine's own, engine.chunks_per_worker); `switch`: the
    driving processes' switch interval in seconds (None: Python's own, 5 ms); `raw`: a folder
    to write each row's records in (raw/row<i>.json: each batch, tell, wait and landing, and each
    task's times on its way), for a closer look than the summary's means."""
    pool, step_s, source = lengths_pool(lengths, measured, env)
    print(f"episode lengths: {source}: {len(pool)} episodes, {np.mean(pool):.0f} steps on average "
          f"(median {np.median(pool):.0f}, max {max(pool)}); {1e6 * step_s:.1f} us a step (measured now)")
    rows = []
    if raw:
        Path(raw).mkdir(parents=True, exist_ok=True)
    for _ in range(repeats):
        for n in workers:
            for k, variant in itertools.product(parts, itertools.product(log_every, savers, chunks, switch)):
                rows.append(one_size(int(n), runs, iterations, processes, int(k), pool, step_s, env,
                                     variant, Path(raw) / f"row{len(rows)}.json" if raw else None))
                print(json.dumps(rows[-1]))
    print("| simulated workers | parts | tasks per batch | ideal s | search s | efficiency | utilisation "
          "(steady) | driver CPU ms per iteration | scheduler CPU ms per task | cycle: driver, to start, "
          "flying, back ms |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        split = ", ".join(str(r[f"cycle_{key}_ms"]) for key in ("driver", "to_start", "flying", "back"))
        print(f"| {r['workers']} | {r['parts']} | {r['tasks_per_batch']} | {r['ideal_s']} | "
              f"{r['search_s']} | {r['efficiency']} | {r['utilisation']} ({r['steady_utilisation']}) | "
              f"{r['driver_cpu_ms_per_iteration']} | {r['scheduler_cpu_ms_per_task']} | {split} |")
    run_files.write_json(Path(out), {
        "date": time.strftime("%Y-%m-%d"), "command": " ".join(sys.argv), "env": env,
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "chunks": {"per_worker": None},  # None: the engine's rule
        "episodes": {"source": source, "lengths": lengths, "count": len(pool),
                     "mean_steps": float(np.mean(pool)),
                     "us_per_step": round(1e6 * step_s, 2)}, "rows": rows})


if __name__ == "__main__":
    fire.Fire({"main": main, "drive": drive} if len(sys.argv) > 1 and sys.argv[1] == "drive" else main)
