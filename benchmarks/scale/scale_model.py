#!/usr/bin/env python
"""A discrete-event model of an experiment on a Dask cluster: drivers, schedulers, workers, the
hops between them, the workers' result delay and real episode lengths, fed measured service
times. It predicts the efficiency bench_scale.py measures (the ideal makespan over the simulated
one) and each run-iteration's cycle split, for designs and sizes no machine here can run.

The model (every server serves one job at a time, first come first served):
- a driver per part (`parts`; runs dealt to parts as experiments.py deals them, run i to part
  i mod K): a run's iteration costs it `driver_iteration_s` (tell, ask, saving; scaled by a draw
  from `driver_spread`, the measured spread of the turns, where given) plus `client_task_s` per
  chunk it sends and per result it takes back. Its client's thread (Dask's event loop) sends the
  batches and takes the results in, and needs the GIL for it: at once while the main thread is
  idle, else when the main thread's work ends or after `gil_s`, whichever is sooner (on shared
  cores the main thread holds the GIL while it waits for one);
- each part's driver starts at `part_starts`, opens its runs one after another (`run_open_s`)
  and sends each run's first batch as it opens it; its scheduler takes no task in until
  `first_task_waits` after that (it unpickles the first graph, importing the tasks' code);
- a scheduler per `schedulers` (part p uses scheduler p mod S; the workers are shared out
  evenly): `scheduler_task_s` of CPU per task, half when it arrives, half when it ends (or, with
  `intake_s`, that long a batch when its graph arrives and all of it when a task ends); it keeps
  up to ceil(`saturation` x threads) tasks on a worker process (Dask's worker-saturation),
  handing them out in arrival order (the engine sends each batch as a generation of its own:
  engine.FIFO_TIMEOUT), each to the least busy worker process with a slot free (as Dask's
  decide_worker_rootish_queuing_enabled picks);
- a task handed out reaches its worker process no sooner than `reach_s` after (the message and
  the process's event loop, on shared cores); a worker process of `threads` threads runs a task
  on each free thread, `start_s` after both are there (its event loop), for the chunk's episodes
  (steps x `step_s`); its event loop then spends `worker_task_s` on the result, which it starts
  `result_delay_s` after the task's end when the thread goes straight on to another (GIL-holding
  rollouts make the loop wait); every message takes `hop_s`; a result reaches its driver no
  sooner than `landing_s` after its task's end (the reports and the client's fetch, measured end
  to end), and its scheduler no sooner than `report_s` (its worker process's slot is held until
  then); a driver idle when a result lands takes it `wake_s` later;
- Dask's batched streams (distributed's BatchedSend): a driver's messages to its scheduler (its
  batches, and the release of each result it takes) and a scheduler's to each worker process
  leave at once if the stream's last batch left `client_batch_s` / `scheduler_batch_s` ago, else
  together at that interval after it (the way back is in the measured landing);
- with `cores`, the drivers, schedulers and worker event loops share that many CPUs (processor
  sharing: a job is slowed by the processes busy when it starts), as on the benchmark's machine;
- chunks per batch: engine.submit_flights' own rule, with the runs on the scheduler as `sharing`
  (a run's first batch: those its driver has opened so far, and the other parts');
- a run's iteration is one batch, or several flown one after the other (`batch` a list: a DQD
  row's point and samples, then its branches; ME-ES's samples, then its offspring), each told
  before the next is sent, each a turn of `driver_iteration_s`; a learning row's driver then
  spends `learn_s` (its critic's steps) once an iteration's last batch is sent, while it flies;
- with `log_every`, a run saves after every log_every-th iteration (and its last): `save_s` of its
  driver's time, booked after the next batch is sent (the saver thread takes the driver's GIL);
  with `draw_s`, its CSV and pictures are a task on the cluster of that many seconds (a design
  tried and dropped: docs/performance.md), `first_draw_s` on a worker process that has not drawn
  before (its imports). The search ends with the last chunk, as bench_scale.py measures it: the
  last saves are left out. With `saver_s`, the time a part's saver processes (saving.Savers, each
  a core of its own) spend per save: reported as the processes it keeps busy (`saver_busy`),
  not simulated.

    python benchmarks/scale/scale_model.py predict --workers "[256, 512]" --runs "[60, 400]" \
        --parts "[1, 4, 16]"

Checked against the real benchmark by scale_validation.py.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import math
import sys
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np

HERE = Path(__file__).resolve().parent  # benchmarks/scale
sys.path.insert(0, str(HERE.parents[1]))  # the repository: the package

import qdsearch  # noqa: E402
from qdsearch.search import engine  # noqa: E402

qdsearch.hold_kernels()  # what the command line sets: numba off, the AVX2 kernels, drawing to files


@dataclasses.dataclass(frozen=True)
class Costs:
    """Service times, in seconds (measured: docs/performance.md)."""

    driver_iteration_s: float = 0.010
    # the driver's work just after it sends an iteration's last batch, while that batch flies (a
    # learning row's critic steps: search/learning.py); its next turn waits for it
    learn_s: float = 0.0
    client_task_s: float = 0.0004
    scheduler_task_s: float = 0.0005
    worker_task_s: float = 0.0007
    result_delay_s: float = 0.0
    # a result reaches its driver's process no sooner than this after its task's end (the worker's
    # report, the scheduler's, the client's fetch of the result from the worker: measured end to
    # end where a row has it; 0: only the hops and services modelled)
    landing_s: float = 0.0
    # a task's end reaches its scheduler (which frees its worker process's slot) no sooner than
    # this after it (the worker's event loop, its report: measured end to end where a row has it)
    report_s: float = 0.0
    # a task handed out reaches its worker process no sooner than this after (the scheduler's
    # message, the worker process's event loop waking: measured on shared cores; 0: hop_s alone)
    reach_s: float = 0.0
    # a worker process starts a task this long after both it and a free thread are there (its
    # event loop, which also hands the thread's last result over: measured on shared cores; 0 on a
    # core of its own)
    start_s: float = 0.0
    # a driver's main thread, idle (waiting for a chunk) when a result lands, wakes this much later
    # (the GIL and a core: measured on the benchmark's shared cores; 0 on a core of its own)
    wake_s: float = 0.0
    # a batch's graph taken in by its scheduler before it hands a task out: a wall time, as measured
    # (its update_graph), each task's scheduler_task_s then spent at its end; None: half of
    # scheduler_task_s a task here, the other half at the task's end
    intake_s: float | None = None
    hop_s: float = 0.0001
    # Dask's batched streams' intervals (distributed 2026.8.0: the client's to its scheduler,
    # the scheduler's to each worker)
    client_batch_s: float = 0.010
    scheduler_batch_s: float = 0.005
    step_s: float = 27e-6
    saturation: float = 1.1  # Dask's worker-saturation: tasks a worker process holds per thread
    run_open_s: float = 0.0  # the driver's work before a run's first batch (its folder, checkpoint)
    # when each part's driver starts, after the first (its process starts later: as measured)
    part_starts: tuple[float, ...] = ()
    # each part's wait, from its first batch's sending, before its scheduler starts a task: it
    # unpickles the first graph it is sent, importing the code the tasks name (as measured)
    first_task_waits: tuple[float, ...] = ()
    cores: int = 0  # CPUs the drivers and schedulers share (0: each has its own, as on a cluster)
    # the driver's times are its main thread's wall times measured on those shared CPUs: they are
    # not slowed by processor sharing again
    driver_wall: bool = False
    # the spread of the driver's turns: each run-iteration's driver_iteration_s is scaled by one of
    # these, drawn at random (a measured turn's quantiles over their mean; empty: every turn the mean)
    driver_spread: tuple[float, ...] = ()
    chunks_per_worker: int | None = None  # None: the engine's own rule (chunks_per_worker)
    log_every: int = 0  # 0: no saves (bench_scale.py's runs save only at their end)
    save_s: float = 0.0  # the driver's time per save
    draw_s: float = 0.0  # 0: the CSV and pictures are drawn in the driver (part of save_s)
    first_draw_s: float = 0.0
    saver_s: float = 0.0
    # the GIL a driver's main thread and its client's thread (its Dask event loop) share: a result
    # lands, and a batch leaves, only when the client's thread has the GIL. While the main thread
    # is at work, it gets it when that work ends or after gil_s, whichever is sooner. On a core of
    # its own the main thread hands the GIL over within Python's switch interval (0: not modelled);
    # on shared cores it holds it while it waits for one (measured: its wall time at work less
    # its CPU, per run-iteration)
    gil_s: float = 0.0

    def graph_intake(self, tasks: int) -> float:
        """A batch's graph of `tasks` tasks taken in by its scheduler: as measured, else half of
        each task's scheduler CPU."""
        return self.scheduler_task_s / 2 * tasks if self.intake_s is None else self.intake_s

    @property
    def task_end_s(self) -> float:
        """A scheduler's CPU at each task's end: what the graph's intake left of the task's CPU."""
        return self.scheduler_task_s / 2 if self.intake_s is None else self.scheduler_task_s


@dataclasses.dataclass
class Workload:
    """runs x iterations batches of `batch` episodes (a list: an iteration's batches in turn, so
    `iterations` counts batches); batch k's episode lengths are drawn from lengths[k] (a real
    search's, iteration by iteration; the last for later ones)."""

    runs: int
    iterations: int
    batch: int | tuple[int, ...]
    lengths: list[np.ndarray]
    seed: int = 0

    def size(self, k: int) -> int:
        """The episodes of a run's k-th batch."""
        return self.batch[k % len(self.batch)] if isinstance(self.batch, tuple) else self.batch

    def episodes(self) -> np.ndarray:
        """(runs, iterations, largest batch) episode lengths, fixed by the seed."""
        rng = np.random.default_rng(self.seed)
        largest = max(self.batch) if isinstance(self.batch, tuple) else self.batch
        out = np.empty((self.runs, self.iterations, largest), dtype=np.int64)
        for k in range(self.iterations):
            pool = self.lengths[min(k, len(self.lengths) - 1)]
            out[:, k, :] = rng.choice(pool, size=(self.runs, largest))
        return out


def chunk_sizes(batch: int, workers: int, sharing: int, per_worker: int | None = None) -> list[int]:
    """The engine's split of a batch (one terrain) into chunks: its own chunk_count."""
    count = engine.chunk_count(batch, workers, sharing, per_worker)
    return [len(c) for c in np.array_split(np.arange(batch), count)]


SPLIT = ("driver", "to_start", "flying", "back")  # a run-iteration's cycle, in order
BACK = ("back_landing", "back_waiting")  # back: its last result's landing, then its wait for the driver
# to the start's first parts: the way to the scheduler (the batch's graph taken in there), and for
# the chunk that starts first, to its handing out there (Dask's queue: worker-saturation) and to
# its worker process
OUT = ("to_scheduler", "to_assigned", "to_worker")
# the same parts for each run's first batch, sent while its driver opens the other runs
FIRST = tuple(f"{key}_first" for key in ("to_start", *OUT, "flying", *BACK))
IDLE = "last_result_lands_driver_idle"  # the share of batches whose last result finds the driver idle


class Server:
    """One process that serves one job at a time, in arrival order. With `machine` (the servers
    that share a machine's CPUs, and how many CPUs), a job is slowed as processor sharing slows
    it: by the other servers busy when it starts, over the CPUs. A server whose service times
    were measured as wall times on that machine (`slowed` False) is not slowed again, but still
    takes its share of the CPUs from the others."""

    def __init__(self, sim: Simulation, machine: tuple[list, int] | None = None, slowed: bool = True) -> None:
        self.sim, self.free_at, self.busy = sim, 0.0, 0.0
        self.machine = machine if slowed else None
        self.idle_hooks: list[Callable[[float], None]] = []  # called when its last job ends
        if machine is not None:
            machine[0].append(self)

    def serve(self, arrival: float, service: float, then: Callable[[float], None],
              wall: bool = False) -> float | None:
        """Take the job in when it arrives; when it starts if it arrives now (`then` is called
        when it ends). A `wall` job's service is a wall time measured on the shared machine: it
        is not slowed again. A job sent ahead of time (a result landing later, a message on its
        hop) is taken in on arrival: booked at once, it held the server idle until then, ahead of
        jobs that arrived sooner (a driver waited for a result still on its way instead of telling
        a run whose result was there)."""
        if arrival > self.sim.now:
            self.sim.at(arrival, lambda t: self.serve(t, service, then, wall))
            return None
        start = max(arrival, self.free_at)
        self.busy += service
        if self.machine is not None and not wall:
            servers, cpus = self.machine
            running = 1 + sum(1 for other in servers if other is not self and other.free_at > start)
            service *= max(1.0, running / cpus)
        self.free_at = start + service
        self.sim.at(self.free_at, self.ended(then) if self.idle_hooks else then)
        return start

    def ended(self, then: Callable[[float], None]) -> Callable[[float], None]:
        """`then`, followed by the idle hooks if no job is left."""
        def end(now: float) -> None:
            then(now)
            if self.free_at <= now:
                for hook in self.idle_hooks:
                    hook(now)
        return end


class GIL:
    """The GIL of a driver's process: its client's thread acts at once while the main thread (the
    driver's Server) is idle; while it is at work, when that work ends or after `wait`, whichever
    is sooner (Costs.gil_s; 0: at once, no GIL modelled)."""

    def __init__(self, sim: Simulation, main: Server, wait: float) -> None:
        self.sim, self.main, self.wait, self.pending = sim, main, wait, []
        if wait:  # else nothing ever waits for the main thread to go idle
            main.idle_hooks.append(self.release)

    def take(self, at: float, action: Callable[[float], None]) -> None:
        """Run `action` in the client's thread when it has the GIL, from `at` on."""
        if at > self.sim.now:
            self.sim.at(at, lambda t: self.take(t, action))
        elif not self.wait or self.main.free_at <= at:
            action(at)
        else:
            job = [action]
            self.pending.append(job)
            self.sim.at(at + self.wait, lambda t: self.fire(job, t))

    def fire(self, job: list, now: float) -> None:
        if job[0] is not None:
            action, job[0] = job[0], None
            action(now)

    def release(self, now: float) -> None:
        """The main thread has gone idle: every action waiting for the GIL runs."""
        pending, self.pending = self.pending, []
        for job in pending:
            self.fire(job, now)


class Simulation:
    """The event loop: callbacks at times, in time order (ties in scheduling order)."""

    def __init__(self) -> None:
        self.events: list = []
        self.counter = itertools.count()
        self.now = 0.0

    def at(self, time: float, callback: Callable[[float], None]) -> None:
        heapq.heappush(self.events, (time, next(self.counter), callback))

    def run(self) -> None:
        while self.events:
            self.now, _, callback = heapq.heappop(self.events)
            callback(self.now)


class Stream:
    """A Dask batched stream (distributed's BatchedSend): a message leaves at once if the last
    batch left `interval` ago or more, else with the next batch, `interval` after the last."""

    def __init__(self, interval: float) -> None:
        self.interval, self.last = interval, -math.inf

    def depart(self, now: float) -> float:
        """When a message sent now leaves."""
        if now <= self.last:  # a batch is waiting to leave: it goes with it
            return self.last
        self.last = max(now, self.last + self.interval)
        return self.last


class Worker:
    """A worker process of `threads` threads, each flying one task at a time from its queue."""

    def __init__(self, threads: int, saturation: float, loop: Server, stream: Stream) -> None:
        self.threads, self.queue, self.running, self.held = threads, deque(), 0, 0
        self.has_drawn = False
        self.slots = math.ceil(saturation * threads)  # Dask's worker-saturation
        self.loop = loop  # its event loop, which takes tasks in and hands results back
        self.stream = stream  # the scheduler's messages to it


def worker_processes(workers: int, threads: int, costs: Costs, sim: Simulation,
                     machine: tuple[list, int] | None) -> list[Worker]:
    """`workers` threads in processes of `threads` threads each (the last may have fewer)."""
    sizes = [threads] * (workers // threads) + ([workers % threads] if workers % threads else [])
    return [Worker(n, costs.saturation, Server(sim, machine), Stream(costs.scheduler_batch_s)) for n in sizes]


def simulate(workload: Workload, workers: int, costs: Costs, parts: int = 1, schedulers: int = 1,
             threads: int = 1) -> dict:
    """One experiment on the model: its makespan, the ideal, the efficiency, each server's
    utilisation and the mean split of a run-iteration's cycle (as bench_scale.py splits it: the
    driver from a tell to the next batch's sending, to the first chunk's start, flying, and back
    from the last chunk's end to the tell; back in two: the last result's landing at its driver,
    then its wait there; the way to the first start in three: to the scheduler, handed out there,
    at the worker process), how often that last result finds its driver idle, and each part's
    wait for its first task to start. Workers are processes of `threads` threads."""
    sim, episodes, c = Simulation(), workload.episodes(), costs
    machine = ([], c.cores) if c.cores else None
    drivers = [Server(sim, machine, slowed=not c.driver_wall) for _ in range(parts)]
    gils = [GIL(sim, driver, c.gil_s) for driver in drivers]
    streams = [Stream(c.client_batch_s) for _ in range(parts)]  # each driver's to its scheduler
    scheds = [Server(sim, machine) for _ in range(schedulers)]
    for p, wait in enumerate(c.first_task_waits[:schedulers]):  # its first graph's imports
        start = c.part_starts[p] if p < len(c.part_starts) else 0.0
        scheds[p].serve(start, wait, lambda t: None, wall=True)  # measured on the shared cores
    pools = [worker_processes(workers // schedulers + (i < workers % schedulers), threads, c, sim,
                              machine) for i in range(schedulers)]
    waiting: list[deque] = [deque() for _ in range(schedulers)]  # tasks ready, no slot yet
    # the runs a batch's chunks are sized for: its driver's own in flight (engine.ClusterShare)
    own = [sum(1 for r in range(workload.runs) if r % parts == p) for p in range(parts)]  # each driver's runs
    opened = np.zeros(parts, dtype=int)  # and how many it has opened so far
    split: dict[str, list[float]] = {key: [] for key in (*SPLIT, *OUT, *BACK, *FIRST)}
    # each part's first batch sent and first task started: its wait for its scheduler's first graph
    firsts = {"sent": np.full(parts, math.inf), "started": np.full(parts, math.inf)}
    state = {"first": math.inf, "last": 0.0, "work": 0.0, "paths": np.zeros(workload.runs),
             "told": np.zeros(workload.runs), "saves": np.zeros(parts), "idle_landings": [],
             "landings": [], "tasks": 0}
    spread = np.asarray(c.driver_spread or (1.0,)) / np.mean(c.driver_spread or (1.0,))
    turns = np.random.default_rng(workload.seed + 1)

    def note(batch: dict, key: str, value: float) -> None:
        """A part of a batch's cycle, noted also apart if it is its run's first batch."""
        split[key].append(value)
        if batch["k"] == 0:
            split[f"{key}_first"].append(value)

    def tell(run: int, done: dict | None, ready: float) -> None:
        """The driver tells the run its batch `done` (None: opens it) and sends the next one."""
        part, k = run % parts, (done["k"] + 1 if done else 0)
        pool = pools[part % schedulers]
        # a run's first batch is sized for the runs its driver has opened so far:
        # loop.Driver.start_more sends each as it opens it
        opened[part] += k == 0
        runs_in_flight = opened[part] if k == 0 else own[part]
        sizes = chunk_sizes(workload.size(k), sum(w.threads for w in pool), runs_in_flight,
                            c.chunks_per_worker) if k < workload.iterations else []
        service = (c.driver_iteration_s * turns.choice(spread) + c.client_task_s * len(sizes)
                   + (c.run_open_s if k == 0 else 0.0))
        told = drivers[part].serve(ready, service, lambda t: send(run, k, sizes, told, t) if sizes else None)
        state["told"][run] = told
        if done:
            split["back"].append(told - done["last_end"])
            note(done, "back_landing", done["landed"] - done["last_end"])
            note(done, "back_waiting", told - done["landed"])
        if k and c.log_every and (k % c.log_every == 0 or k == workload.iterations):
            state["saves"][part] += 1
            drivers[part].serve(ready, c.save_s, lambda t: draw(part % schedulers, t) if c.draw_s else None)

    def draw(sched: int, sent: float) -> None:
        """A save's CSV and pictures, as a task of no batch."""
        task = {"batch": None, "duration": c.draw_s}
        scheds[sched].serve(sent + c.hop_s, c.graph_intake(1), lambda t: queue(sched, [task], t),
                            wall=c.intake_s is not None)

    def send(run: int, k: int, sizes: list[int], told: float, sent: float) -> None:
        state["first"] = min(state["first"], sent)
        firsts["sent"][run % parts] = min(firsts["sent"][run % parts], sent)
        if k:
            split["driver"].append(sent - told)
        bounds = np.cumsum([0, *sizes])
        durations = [float(episodes[run, k, a:b].sum()) * c.step_s for a, b in zip(bounds[:-1], bounds[1:])]
        state["work"] += sum(durations)
        state["tasks"] += len(durations)
        state["paths"][run] += max(durations)
        batch = {"run": run, "k": k, "left": len(sizes), "sent": sent,
                 "first_start": math.inf, "last_end": 0.0, "landed": 0.0, "to_land": len(sizes)}
        sched = run % parts % schedulers
        tasks = [{"batch": batch, "duration": duration} for duration in durations]
        # the scheduler takes the batch's graph in whole before it hands any of its tasks out
        gils[run % parts].take(sent, lambda t: scheds[sched].serve(
            streams[run % parts].depart(t) + c.hop_s, c.graph_intake(len(tasks)),
            lambda t2: taken_in(batch, sched, tasks, t2), wall=c.intake_s is not None))
        # (the last batch's last release goes with it)
        per_iteration = len(workload.batch) if isinstance(workload.batch, tuple) else 1
        if c.learn_s and (k + 1) % per_iteration == 0:
            drivers[run % parts].serve(sent, c.learn_s, lambda t: None, wall=c.driver_wall)

    def taken_in(batch: dict, sched: int, tasks: list[dict], now: float) -> None:
        note(batch, "to_scheduler", now - batch["sent"])
        queue(sched, tasks, now)

    def queue(sched: int, tasks: list[dict], now: float) -> None:
        waiting[sched].extend(tasks)
        dispatch(sched, now)

    def dispatch(sched: int, now: float) -> None:
        while waiting[sched]:
            worker = min((w for w in pools[sched] if w.held < w.slots), key=lambda w: w.held / w.threads,
                         default=None)
            if worker is None:  # every slot held: the task waits in the scheduler's queue
                return
            task = waiting[sched].popleft()
            task["assigned"] = now
            worker.held += 1
            leaves = max(worker.stream.depart(now) + c.hop_s, now + c.reach_s)
            sim.at(leaves, lambda t, w=worker, task=task: arrive(sched, w, task, t))

    def arrive(sched: int, worker: Worker, task: dict, now: float) -> None:
        task["reached"] = now
        worker.queue.append(task)
        if worker.running < worker.threads:
            run_next(sched, worker, now)

    def run_next(sched: int, worker: Worker, now: float) -> None:
        """A thread is free and a task waits: the worker process's loop starts it `start_s` later."""
        task = worker.queue.popleft()
        worker.running += 1
        if c.start_s:
            sim.at(now + c.start_s, lambda t: start_task(sched, worker, task, t))
        else:
            start_task(sched, worker, task, now)

    def start_task(sched: int, worker: Worker, task: dict, now: float) -> None:
        duration, batch = task["duration"], task["batch"]
        if batch:
            if now < batch["first_start"]:  # the batch's first chunk to start
                batch["first_start"], batch["starter"] = now, task
                part = batch["run"] % parts
                firsts["started"][part] = min(firsts["started"][part], now)
        elif not worker.has_drawn:
            duration, worker.has_drawn = c.first_draw_s, True
        sim.at(now + duration, lambda t: finish(sched, worker, task, t))

    def finish(sched: int, worker: Worker, task: dict, now: float) -> None:
        worker.running -= 1
        if task["batch"]:
            state["last"] = max(state["last"], now)
            task["batch"]["last_end"] = max(task["batch"]["last_end"], now)
        task["end"] = now
        delay = c.result_delay_s if worker.queue else 0.0
        if worker.queue:
            run_next(sched, worker, now)
        worker.loop.serve(now + delay, c.worker_task_s, lambda t: scheds[sched].serve(
            max(t + c.hop_s, now + c.report_s), c.task_end_s,
            lambda t2: done(sched, worker, task, t2)))

    def done(sched: int, worker: Worker, task: dict, now: float) -> None:
        worker.held -= 1
        dispatch(sched, now)
        batch = task["batch"]
        if batch is None:  # a drawing: its files are written in the driver's saver thread
            return
        gils[batch["run"] % parts].take(max(now + c.hop_s, task["end"] + c.landing_s),
                                        lambda t: land(batch, task, t))

    def land(batch: dict, task: dict, lands: float) -> None:
        """The result in its driver's process (as_completed's queue), for the main thread to take."""
        state["landings"].append(lands - task["end"])
        batch["landed"], batch["to_land"] = max(batch["landed"], lands), batch["to_land"] - 1
        driver = drivers[batch["run"] % parts]
        idle = driver.free_at <= lands
        if not batch["to_land"]:  # its last result: does it find the driver idle?
            state["idle_landings"].append(idle)
        driver.serve(lands + (c.wake_s if idle else 0.0), c.client_task_s, lambda t: taken(batch, t))

    def taken(batch: dict, now: float) -> None:
        batch["left"] -= 1
        if batch["left"]:  # the client releases the result's key (the last one's after the next batch)
            streams[batch["run"] % parts].depart(now)
            return
        note(batch, "to_start", batch["first_start"] - batch["sent"])
        note(batch, "to_assigned", batch["starter"]["assigned"] - batch["sent"])
        note(batch, "to_worker", batch["starter"]["reached"] - batch["sent"])
        note(batch, "flying", batch["last_end"] - batch["first_start"])
        tell(batch["run"], batch, now)

    for run in range(workload.runs):
        start = c.part_starts[run % parts] if run % parts < len(c.part_starts) else 0.0
        sim.at(start, lambda t, run=run: tell(run, None, t))
    sim.run()
    search = state["last"] - state["first"]
    ideal = max(state["work"] / workers, float(state["paths"].max()))
    return {"workers": workers, "runs": workload.runs, "parts": parts, "schedulers": schedulers,
            "search_s": search, "ideal_s": ideal, "efficiency": ideal / search,
            "utilisation": state["work"] / (workers * search),
            "tasks_per_batch": state["tasks"] / (workload.runs * workload.iterations),
            "driver_busy": max(d.busy for d in drivers) / search,
            "scheduler_busy": max(s.busy for s in scheds) / search,
            "saver_busy": float(state["saves"].max()) * c.saver_s / search,
            IDLE: float(np.mean(state["idle_landings"])) if state["idle_landings"] else math.nan,
            "result_lands_ms_mean": 1000 * float(np.mean(state["landings"])),
            "first_task_starts_s": [float(x) for x in firsts["started"] - firsts["sent"]],
            **{f"cycle_{key}_ms": 1000 * float(np.mean(values)) if values else math.nan
               for key, values in split.items()}}


def load_lengths(path: str) -> tuple[list[np.ndarray], float]:
    """Episode lengths per iteration and the cost of a step, as episode_lengths.py
    wrote them."""
    with np.load(path) as data:
        keys = sorted(k for k in data.files if k.startswith("iteration_"))
        return [data[k] for k in keys], float(data["us_per_step"]) * 1e-6


def main(workers: tuple = (16, 64, 256, 512), runs: tuple = (60,), iterations: int = 300,
         batch: int | tuple = 150, parts: tuple = (1,), schedulers: tuple = (0,),
         lengths: str = str(HERE / "episode_lengths_lander.npz"), steps: int | None = None,
         **costs: float) -> None:
    """Print the model's prediction for each size, workload and design (`schedulers` 0: one per
    part): `lengths` (a real search's episodes, iteration by iteration: episode_lengths.py; or
    every episode `steps` long, a MuJoCo task that never ends early) and `costs` (the fields of
    Costs; step_s defaults to the lengths file's own). A `batch` list is an iteration's batches
    in turn: `iterations` iterations fly iterations x its length batches."""
    import json

    if costs.pop("help", None):  # fire hands --help on to a function that takes **costs
        print(__doc__)
        return
    fields = [field.name for field in dataclasses.fields(Costs)]
    if unknown := sorted(set(costs) - set(fields)):
        raise SystemExit(f"not a cost: {', '.join(unknown)}; the costs are {', '.join(fields)}")
    per_iteration, step_s = load_lengths(lengths)
    if steps is not None:
        per_iteration = [np.array([int(steps)])]
    batches = tuple(int(b) for b in batch) if isinstance(batch, (list, tuple)) else int(batch)
    turns = iterations * (len(batches) if isinstance(batches, tuple) else 1)
    model = Costs(**{"step_s": step_s, **costs})
    for n, r, k, s in itertools.product(workers, runs, parts, schedulers):
        row = simulate(Workload(int(r), turns, batches, per_iteration), int(n), model, parts=int(k),
                       schedulers=int(s) or int(k))
        print(json.dumps({key: round(value, 4) if isinstance(value, float) else value
                          for key, value in row.items()}))


if __name__ == "__main__":
    import fire

    fire.Fire({"predict": main} if sys.argv[1:2] == ["predict"] else main)
