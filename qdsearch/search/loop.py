"""The one run loop: runs ask, have their batches flown on the cluster, and tell, any number of
them at once on one Dask client. `search` and `resume` drive one run through it, `experiment`
many.

A run's results depend on its own asks and tells only, so a run ends bit for bit the same
whether it is driven alone or among others, whatever the order its chunks come back in.
The driver runs in a process's main thread: its saves start saver processes with the stop
signals ignored (saving.py's `Savers`), which only the main thread may set.

Map:
- `Run`: one run between two iterations: `ask`, `send` (its batch to the cluster), `take` (a
  chunk back), `tell` (a DQD row's gradients: `tell_gradients`; ME-ES's samples:
  `chains_networks`, `es_steps`, their collected episodes flown again here: `observations`; a
  learning row's learner: learning.py), the checkpoint (built and written here only, signed
  with the user's key: signing.py) and `save` (its folder's files: saving.py's `save_outputs`);
- `Driver`: the loop. Chunks come back in whatever order they finish (Dask's as_completed); a run
  goes on as soon as its own batch is whole: it tells, saves at its log interval, and sends its
  next batch or finishes. Its subclasses say how runs are opened and recorded (experiments.py's
  `Experiment`; `OneRun` for search and resume), and whether a run's fault stops it alone. Its
  saves are written by saving.py's `Savers`;
- `count_as_done_before`: a resumed run's earlier iterations on the progress bar.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import pickle
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Callable

import numpy as np

from qdsearch.algorithms import ALGORITHMS, ARCHIVES, build_scheduler
from qdsearch.algorithms.gradients import estimate, noise, sample_points
from qdsearch.base import compact_pickle
from qdsearch.base.flags import UsageError, clipped
from qdsearch.base.run_files import RunError, atomic_write, fault_text
from qdsearch.base.signing import user_key, write_signed
from qdsearch.base.stopping import STOP
from qdsearch.config.run_config import CHECKPOINT_FORMAT, RunConfig
from qdsearch.search.cluster import SchedulerLost, shares_this_machine
from qdsearch.search.engine import ClusterShare, averaged, evaluate_batch, per_terrain, submit_flights
from qdsearch.search.learning import Learning
from qdsearch.store.metrics import describe_progress, iteration_metrics
from qdsearch.store.saving import SAVER_PROCESSES, Savers
from qdsearch.store.trackers import Tracking, wait_for_trackers
from qdsearch.tasks import (
    episode_of,
    evaluate_points,
    fly,
    make_env,
    point_gradients,
    reset_seeds,
    returns_of,
    scored_here,
)


class Run:
    """One run between two iterations, and the folder it is saved to.

    The checkpoint is built and written here only. It always holds the last completed iteration:
    ask() moves the emitters on, so the scheduler is snapshotted (pickled, ~1 ms) after every tell,
    and a stop or a fault while the cluster evaluates writes that snapshot. The iteration in flight
    is abandoned, never half-recorded. The scheduler is pickled as one object (its emitters share
    its archive; CMA-ES state and RNGs come along), so a resumed run asks exactly the same.

    The folder's files may be written in a thread while the run goes on (`save(saver)`): they are
    built from that snapshot, so nothing the run does next can change them.
    """

    def __init__(self, run_dir: Path, config: RunConfig, scheduler, metrics: list[dict],
                 log: logging.Logger, learned: dict | None = None) -> None:
        self.dir, self.config, self.scheduler, self.metrics = run_dir, config, scheduler, metrics
        self.name, self.log = run_dir.name, log
        # A run scored here (a benchmark function) is asked, scored and told in one step, and a
        # stop is acted on between steps only: its scheduler itself is the last told iteration
        # whenever a checkpoint is taken (`here`), and pickling it after every tell would cost as
        # much as pyribs' ask and tell.
        self.here = scored_here(config.env)
        self.snapshot = None if self.here else compact_pickle.dumps(scheduler)
        self.open = False  # a run scored here: asked and not yet told (no checkpoint is taken)
        self.saved = self.iteration
        self.pending: Future | None = None  # a save being written by the saver thread
        self.chunks: list = []  # the batch on the cluster: its chunks' results, in order
        self.seeds: np.ndarray | None = None  # its solutions' reset seeds (tasks.reset_seeds)
        self.waiting = 0  # chunks of that batch not back yet
        self.leaving = contextlib.ExitStack()  # what the run holds while it is driven (lock, log)
        self.target = config.iterations  # where this drive stops (resume may stop it sooner)
        self.tracking = Tracking(run_dir, config, log)  # --track: fed after each save (trackers.py)
        self._asked_at = 0.0
        self.policy, self.episode = config.network, episode_of(config)
        self.gradients: np.ndarray | None = None  # a DQD row's sample draws, while its gradients fly
        self.sampled = 0  # solutions flown for this iteration's gradients (told: its branches fly)
        self.flown: np.ndarray | None = None  # ME-ES: the networks its samples flew
        self.points: np.ndarray | None = None  # a DQD row's points, while their gradients fly
        self.learning = Learning.of(config, scheduler, learned)  # a learning row's (learning.py)

    @classmethod
    def start(cls, run_dir: Path, config: RunConfig, client, log: logging.Logger,
              seed_archive=None) -> Run:
        """Iteration 0 of a new run, checkpointed at once so the folder always holds one.

        With `seed_archive` (a warm start), its elites are first flown again in this run's setting
        (another terrain, say) and inserted, and the emitters start from the best of them.
        """
        if making := ARCHIVES[config.archive]["making"]:  # a CVT's k-means: seconds, said first
            log.info(making(config))
        if seed_archive is None:
            run = cls(run_dir, config, build_scheduler(config), [], log)
        else:
            elites = seed_archive.data(["solution"])["solution"]
            objectives, measures = evaluate_batch(client, elites, config)
            scheduler = build_scheduler(config, x0=elites[int(np.argmax(objectives))])
            for archive in {id(a): a for a in (scheduler.archive, scheduler.result_archive)}.values():
                archive.add(elites, objectives, measures)
            run = cls(run_dir, config, scheduler,
                      [iteration_metrics(scheduler.result_archive, 0, len(elites), 0.0)], log)
            log.info(f"Warm start: {len(elites)} elites re-evaluated, {len(scheduler.result_archive)} "
                     f"kept; emitters start from the best (objective {objectives.max():.1f})")
        run.write_centroids()
        run.save_checkpoint(force=True)
        return run

    @classmethod
    def from_checkpoint(cls, run_dir: Path, checkpoint: dict, log: logging.Logger) -> Run:
        run = cls(run_dir, checkpoint["config"], checkpoint["scheduler"], checkpoint["metrics"], log,
                  checkpoint.get("learning"))
        if not (run_dir / "centroids.npy").exists():  # deleted: resume's check refused an edited one
            run.write_centroids()
        return run

    def write_centroids(self) -> None:
        """A CVT archive's cells in centroids.npy, for a reader to see (a grid's need no file)."""
        kept = self.scheduler.result_archive
        if hasattr(kept, "centroids"):
            atomic_write(self.dir / "centroids.npy", lambda f: np.save(f, kept.centroids))

    @property
    def iteration(self) -> int:
        return self.metrics[-1]["iteration"] if self.metrics else 0  # a warm start has iteration 0

    def ask(self) -> np.ndarray:
        """The next batch to fly. A DQD row's iteration has two: first its emitters' points with
        the samples that estimate their gradients (gradients.py), then the solutions branched
        along those gradients (pyribs' ask_dqd, tell_dqd, then ask and tell). ME-ES's too: first
        the samples around each chain's theta, as the networks its normaliser makes them
        (me_es.py: its ES step), then the stepped thetas (its first iteration flies x0 alone)."""
        row = ALGORITHMS[self.config.algorithm]
        if not self.sampled:  # the iteration's first batch
            self._asked_at = time.perf_counter()  # elapsed_s counts from here to the tell
            if row.exact:
                self.tell_exact_gradients()
        if not self.sampled and row.samples:
            points = (self.scheduler.ask_dqd() if row.dqd else
                      [emitter.es_point() for emitter in self.scheduler.emitters])
            if not any(point is None for point in points):
                points = np.asarray(points)
                self.gradients = noise(self.config.seed, self.iteration, len(points),
                                       self.config.es_samples, points.shape[1])
                batch = sample_points(points, self.gradients, self.config.es_sigma)
                if row.dqd:
                    self.points = points
                    return batch
                self.flown = self.chains_networks(batch[len(points):])  # ME-ES flies no point
                return self.flown
        batch = self.scheduler.ask()
        return batch if self.learning is None else self.learning.with_greedy(batch)

    def send(self, client, sharing: int = 1, threads: int | None = None) -> list:
        """Ask the next batch and send it to the cluster; the futures of its chunks, in order. A
        benchmark function's batch is scored here at once (no futures: the batch is whole)."""
        config = self.config
        solutions = self.ask()
        if self.here:  # a point has no resets: a row per solution, whatever --env_seed and --reset
            self.open, self.seeds = True, np.zeros((len(solutions), 1), dtype=np.int64)
            self.chunks, self.waiting = [evaluate_points(solutions, config.measures, env_name=config.env)], 0
            return []
        self.seeds = reset_seeds(solutions, config)
        futures = submit_flights(client, solutions, self.seeds, config.measures,
                                 config.fast_env, sharing=sharing, threads=threads,
                                 env_name=config.env, policy=self.policy, episode=self.episode,
                                 transitions=self.learning is not None)
        self.chunks, self.waiting = [None] * len(futures), len(futures)
        if self.learning is not None and self.gradients is None:  # the iteration's last batch
            self.learning.train()  # while it flies
        return futures

    def take(self, position: int, result: Any) -> bool:
        """A chunk of the batch is back (or its exception); whether the batch is whole."""
        self.chunks[position] = result
        self.waiting -= 1
        return self.waiting == 0

    def tell_batch(self) -> dict | None:
        """Tell the whole batch, each solution averaged over its terrains (a chunk that failed
        raises its fault); the new row of metrics, or None where the iteration has a batch to go
        (a DQD row's gradients are told)."""
        chunks, self.chunks = self.chunks, []
        if failed := next((chunk for chunk in chunks if isinstance(chunk, BaseException)), None):
            raise failed
        if self.learning is not None:
            chunks = self.learning.collect(chunks)
        objectives, measures = averaged(per_terrain(chunks, self.seeds))
        if self.gradients is not None:
            if ALGORITHMS[self.config.algorithm].dqd:
                self.tell_gradients(objectives, measures)
            else:  # ME-ES: each chain's samples, in its emitter's order
                self.es_steps(objectives, measures)
            self.gradients, self.sampled = None, len(objectives)
            return None
        return self.tell(objectives, measures)

    def tell_gradients(self, objectives: np.ndarray, measures: np.ndarray) -> None:
        """A DQD row's points and their gradients, estimated from the samples (gradients.py); a
        learning row's objective gradient is its critic's (learning.py)."""
        flown = np.column_stack([objectives, measures])
        values, points_measures, jacobians = estimate(flown, self.gradients, self.config.es_sigma)
        if self.learning is not None and self.learning.learns.objective_gradient:
            jacobians[:, 0] = self.learning.objective_gradients(self.points)
        self.scheduler.tell_dqd(values, points_measures, jacobians)
        self.points = None

    def tell_exact_gradients(self) -> None:
        """A DQD row of exact gradients (a benchmark function's, scored here): its points, their
        values and Jacobians told at once, counted as the iteration's first evaluations."""
        config, points = self.config, self.scheduler.ask_dqd()
        flown = evaluate_points(points, config.measures, env_name=config.env)
        jacobians = point_gradients(points, config.measures, env_name=config.env)
        self.scheduler.tell_dqd(flown[:, 0], flown[:, 1:], jacobians)
        self.sampled = len(points)

    def chains_networks(self, samples: np.ndarray) -> np.ndarray:
        """ME-ES: each chain's samples (in its emitter's order) as the networks its normaliser
        makes them."""
        chains = np.split(samples, len(self.scheduler.emitters))
        return np.concatenate([emitter.flown(part) for emitter, part in zip(self.scheduler.emitters, chains)])

    def es_steps(self, objectives: np.ndarray, measures: np.ndarray) -> None:
        """ME-ES: each chain's step on its samples' results, and the observations of the samples
        it collects (me_es.py), their episodes flown again here."""
        count = len(self.gradients)
        parts = zip(self.scheduler.emitters, np.split(objectives, count), np.split(measures, count),
                    self.gradients, np.split(self.flown, count), np.split(self.seeds, count))
        for emitter, chain_objectives, chain_measures, eps, networks, seeds in parts:
            emitter.es_step(chain_objectives, chain_measures, eps)
            if len(chosen := emitter.collecting(len(networks))):
                emitter.observe(self.observations(networks[chosen], seeds[chosen]))

    def observations(self, networks: np.ndarray, seeds: np.ndarray) -> np.ndarray:
        """Every observation of the episodes of `networks` on their reset seeds, flown here."""
        config, seen = self.config, []
        env = make_env(config.fast_env, env_name=config.env, episode=self.episode)
        try:
            for network, own in zip(networks, seeds):
                for seed in own:
                    fly(network, int(seed), env, on_step=lambda action, obs: seen.append(np.array(obs)),
                        env_name=config.env, policy=self.policy)
        finally:
            env.close()
        return np.array(seen)

    def tell(self, objectives: np.ndarray, measures: np.ndarray) -> dict:
        """Record the evaluated batch; returns the new row of metrics, whose evaluations count
        the iteration's every solution flown (a DQD row's gradient samples too, a learning row's
        greedy actor, inserted first: learning.py)."""
        if self.learning is not None:
            self.learning.insert_greedy(self.scheduler, objectives[-1], measures[-1])
            self.scheduler.tell(objectives[:-1], measures[:-1])
            self.learning.commit()
        else:
            self.scheduler.tell(objectives, measures)
        if not self.here:
            self.snapshot = compact_pickle.dumps(self.scheduler)
        self.open = False
        last = self.metrics[-1] if self.metrics else {"evaluations": 0, "elapsed_s": 0.0}
        spent, self.sampled = len(objectives) + self.sampled, 0
        self.metrics.append(iteration_metrics(
            self.scheduler.result_archive, self.iteration + 1, last["evaluations"] + spent,
            last["elapsed_s"] + time.perf_counter() - self._asked_at))
        return self.metrics[-1]

    def due(self, row: dict) -> bool:
        """Whether the folder is refreshed after this row (every log_every iterations; the last
        iteration's save is the run's end)."""
        return row["iteration"] % self.config.log_every == 0 and row["iteration"] < self.target

    def checkpoint(self) -> dict:
        """Everything needed to continue the run, as of the last completed iteration."""
        scheduler = compact_pickle.dumps(self.scheduler) if self.here else self.snapshot  # a copy
        return {"format": CHECKPOINT_FORMAT, "scheduler": pickle.loads(scheduler),
                "metrics": list(self.metrics), "iteration": self.iteration,
                "config": self.config.to_json(),
                **({} if self.learning is None else {"learning": self.learning.checkpoint()})}

    def save_checkpoint(self, force: bool = False) -> None:
        """Write the checkpoint if iterations were completed since the last save (after the save
        in the saver thread, whose fault, if any, is raised once the checkpoint is written)."""
        try:
            self.settle()
        finally:
            if (force or self.iteration > self.saved) and not self.open:  # (open: a fault mid-step)
                write_signed(self.dir / "checkpoint.pkl", compact_pickle.dumps(self.checkpoint()))
                self.saved = self.iteration

    def save(self, savers: Savers) -> None:
        """Refresh every file of the run folder, the checkpoint first, in a saver thread (and
        process), so the workers are fed meanwhile."""
        self.settle()
        self.pending = savers.submit(self.write, self.checkpoint(), savers)

    def write(self, checkpoint: dict, savers: Savers) -> None:
        write_signed(self.dir / "checkpoint.pkl", compact_pickle.dumps(checkpoint))
        self.saved = checkpoint["iteration"]
        savers.write_outputs(self.dir, checkpoint["scheduler"].result_archive, checkpoint["metrics"],
                             checkpoint["config"], checkpoint["iteration"], returns_of(self.config).heat)
        with savers.one_at_a_time:
            self.tracking.save(checkpoint["metrics"])

    def settle(self, wait: bool = True) -> None:
        """Wait for the save in the saver thread (without `wait`: only if it is over); raise its
        fault, so a full disk stops the run at once."""
        if self.pending is not None and (wait or self.pending.done()):
            pending, self.pending = self.pending, None
            pending.result()


def count_as_done_before(bar, iterations: int) -> None:
    """Put a resumed run's earlier iterations on the tqdm bar as its starting point, not as work
    done now, so its rate and time left reflect only this drive (a bar not drawn: nothing)."""
    if bar.disable:
        return
    bar.n, bar.last_print_n, bar.initial = (
        count + iterations for count in (bar.n, bar.last_print_n, bar.initial))
    bar.refresh()


STOP_CHECKPOINTS_S = 2.0  # how long a stop writes the live runs' checkpoints (Driver.checkpoint_on_stop)


class Driver:
    """Drives runs on one client until each reaches its target: the one loop of search, resume
    and experiment.

    `entries` are the runs to drive, each a dict with at least its "name"; `open` (a subclass's)
    makes an entry's Run, `record` notes each change of its state ("running", "done", "stopped",
    "failed"). With `isolated` runs a run's fault stops it alone; otherwise it ends the drive.
    Every `every` iterations told, `lines()` are logged. The runs' states noted by `record` are
    kept by `flush`: once the runs of a batch are opened, at most every so often while they go
    on, and at the drive's end, however many runs change at once.
    """

    desc = "runs"  # the progress bar's label
    isolated = False

    def __init__(self, client, log: logging.Logger, entries: list[dict], total: int, done: int = 0,
                 limit: int | None = None, every: int | None = None) -> None:
        from dask.distributed import as_completed

        user_key()  # the key checkpoints are signed with, made (or refused) before any run opens
        self.client, self.log, self.total, self.done, self.every = client, log, total, done, every
        self.todo = collections.deque(entries)
        self.entries = {entry["name"]: entry for entry in entries}
        self.limit = limit or len(entries)
        self.live: dict[str, Run] = {}
        self.owner: dict[str, tuple[Run, int]] = {}  # future key -> its run, chunk position
        self.latest: dict[str, dict] = {}  # run name -> its last metrics row
        self.told = 0  # iterations told in this drive
        self.closing: list[Run] = []  # finished runs whose last save is being written
        # Run folders are written while the runs go on. A cluster whose workers are elsewhere
        # runs on cores of its own, and so may saver processes. On a cluster it starts itself
        # (--workers), or one joined whose workers all listen on loopback, the driver shares the
        # machine's cores with the workers: a saver process would gain nothing (measured on 2
        # cores: docs/performance.md) and cost its fork server's start (its imports: 3.2-4.0 s of
        # CPU here, 2026-11-28): one thread draws.
        self.savers = Savers(0 if client is None or shares_this_machine(client)
                             else min(SAVER_PROCESSES, self.limit))
        self.ready: collections.deque[Run] = collections.deque()  # runs whose batch was scored here
        # Results come with their futures (no second round trip to fetch them); a chunk that
        # failed comes as its exception, and is its run's fault alone.
        self.finished = None if client is None else as_completed(with_results=True, raise_errors=False)
        self.share = ClusterShare(client)  # the worker threads and the runs sharing them

    # ---- what subclasses say ----
    def open(self, entry: dict) -> Run:
        raise NotImplementedError

    def record(self, entry: dict, state: str, error: BaseException | None = None) -> None:
        """A run's new state (an experiment writes it to experiment.json)."""

    def flush(self, due_only: bool = False) -> None:
        """Keep the states `record` noted (with `due_only`, only if they are due)."""

    def lines(self) -> list[str]:
        """Lines logged every `every` iterations told."""
        return []

    def log_lines(self) -> None:
        for line in self.lines():
            self.log.info(line)

    # ---- the loop ----
    def drive(self) -> None:
        """Drive every entry's run to its target; a stop or a fault keeps each run's last
        completed iteration in its checkpoint."""
        from tqdm import tqdm

        # disable=None: no bar where stderr is not a terminal (a pipe, a batch job's log), whose
        # frames would be written there one after another; the log's lines say the progress.
        self.bar = tqdm(total=self.total, initial=self.done, unit="it", desc=self.desc,
                        dynamic_ncols=True, disable=None)
        logged, stopping = 0, False
        try:
            self.start_more()
            self.flush()  # the states of the runs just opened, written once
            self.bar.unpause()  # its rate counts from here: opening runs (a CVT's k-means) is no iteration's
            while self.live:
                if self.ready:  # a run scored in this process: its next iteration, a stop acted on first
                    STOP.check()
                    if (run := self.ready.popleft()).name in self.live:
                        self.step_here(run)
                else:
                    with STOP.interruptible():
                        future, result = self.next_chunk()
                    run, position = self.owner.pop(future.key, (None, 0))
                    if run is not None and run.name in self.live and run.take(position, result):
                        self.advance(run)  # else a chunk of a run that has failed meanwhile
                if not self.live:  # the closing lines go under the finished bar, not redrawn after them
                    self.bar.close()
                self.reap(wait=False)
                self.flush(due_only=True)
                if self.every and self.live and self.told - logged >= self.every:
                    logged = self.told
                    self.log_lines()
            self.reap(wait=True)
            self.flush()
            if self.every:
                self.log_lines()
        except BaseException:
            self.todo.clear()  # nothing more is opened
            stopping = True
            self.checkpoint_on_stop()
            for run in list(self.live.values()):
                self.close(run, "stopped")
            with contextlib.suppress(Exception):
                self.reap(wait=True)
            with contextlib.suppress(Exception):  # the fault or the stop under way is the one said
                self.flush()
            raise
        finally:
            self.savers.close(stopping)
            self.bar.close()
            wait_for_trackers(self.log)

    def checkpoint_on_stop(self) -> None:
        """At a stop or a fault, the live runs' checkpoints, those with the most iterations since
        their last one first, for STOP_CHECKPOINTS_S at most once the first is written: a stop
        comes within seconds however many runs are live (each checkpoint takes milliseconds), and
        a run not reached keeps its last checkpoint, which resume goes on from as exactly."""
        deadline = None
        for run in sorted(self.live.values(), key=lambda run: run.saved - run.iteration):
            if deadline is not None and time.monotonic() > deadline:
                return
            with contextlib.suppress(Exception):
                run.save_checkpoint()
            deadline = deadline or time.monotonic() + STOP_CHECKPOINTS_S

    def next_chunk(self) -> tuple[Any, Any]:
        """The next chunk back, as as_completed hands it. A client that has lost its scheduler
        leaves the futures sent since pending, and as_completed would wait on them for ever: the
        wait looks at the client as it goes (check_connected), as as_completed's own wait does (a
        condition woken by each result, or every 0.1 s)."""
        while not self.finished.has_ready():
            self.check_connected()
            with self.finished.thread_condition:
                self.finished.thread_condition.wait(timeout=0.1)
        return next(self.finished)

    def start_more(self) -> None:
        """Open waiting runs until `limit` are in flight. A stop is acted on between two runs:
        opening thousands takes minutes."""
        while self.todo and len(self.live) < self.limit:
            STOP.check()
            entry = self.todo.popleft()
            try:
                run = self.open(entry)
            except (UsageError, RunError, OSError) as error:  # a bad folder, a full disk
                self.fail(entry, None, error)
                continue
            self.live[run.name] = run
            self.latest[run.name] = run.metrics[-1] if run.metrics else {}
            count_as_done_before(self.bar, run.iteration)
            self.record(entry, "running")
            if run.iteration >= run.target:
                self.finish(run)
            else:
                self.send(run)

    def send(self, run: Run) -> None:
        """The run's next batch, to the cluster (a run scored here waits its turn: `ready`)."""
        if run.here:
            self.ready.append(run)
            return
        self.check_connected()
        threads, sharing = self.share(len(self.live))
        for position, future in enumerate(run.send(self.client, sharing, threads)):
            self.owner[future.key] = (run, position)
            self.finished.add(future)

    def step_here(self, run: Run) -> None:
        """A run scored in this process: its next iteration (a DQD row's two batches) asked,
        scored and told in one step. A fault on the way is its own (`fail`): its checkpoint keeps
        the last iteration saved."""
        try:
            run.send(self.client)
            while (row := run.tell_batch()) is None:
                run.send(self.client)
            self.after_tell(run, row)
        except Exception as error:
            self.fail(self.entries[run.name], run, error)

    def figures(self, row: dict) -> dict[str, str]:
        """What the progress bar shows beside its count, after a run told `row`: that run's
        coverage, QD score and best objective (a driver of many runs shows its own figures)."""
        best = float("nan") if row["best_objective"] is None else row["best_objective"]
        return {"coverage": f"{row['coverage']:.3f}", "qd": f"{row['qd_score']:.4g}", "best": f"{best:.1f}"}

    def advance(self, run: Run) -> None:
        """The run's batch is whole: tell it, save it at its log interval, send again or finish."""
        try:
            row = run.tell_batch()
            if row is None:  # the iteration's next batch (a DQD row's branched solutions)
                self.send(run)
                return
            self.after_tell(run, row)
        except Exception as error:  # a task that failed, a write
            self.check_scheduler(error)
            self.fail(self.entries[run.name], run, error)

    def after_tell(self, run: Run, row: dict) -> None:
        """The run has told an iteration (`row`, its metrics): save it at its log interval, send
        again or finish."""
        run.settle(wait=False)  # a fault of the last save (a full disk) stops the run now
        self.latest[run.name] = row
        self.told += 1
        self.bar.update(1)
        self.bar.set_postfix(self.figures(row), refresh=False)
        if row["iteration"] >= run.target:
            self.finish(run)
        else:
            self.send(run)
            if run.due(row):
                run.log.info(describe_progress(row, run.target))
                run.save(self.savers)

    def check_connected(self) -> None:
        """Stop at once when the client has lost its scheduler. While it tries to reconnect
        ("connecting", for up to HANDSHAKE_TIMEOUT) it has already cancelled every future in
        flight, so no run can go on; a batch sent or a question asked then (the chunks' worker
        count) would wait out the whole reconnection, or the closed client's futures for ever."""
        if self.client is not None and self.client.status != "running":
            self.check_scheduler(RunError(f"the Dask client is {self.client.status}"))

    def check_scheduler(self, error: BaseException) -> None:
        """A task lost with the scheduler is no run's fault: the whole drive stops (every run
        keeps its checkpoint) rather than failing its runs one by one."""
        if isinstance(error, SchedulerLost):
            raise error
        if self.client is None:  # a run scored here has no scheduler to lose
            return
        status = self.client.status
        if status != "running":  # while it reconnects, every fault is the loss's: one cause said
            why = "its connection closed" if status == "connecting" else clipped(fault_text(error))
            raise SchedulerLost(f"lost the Dask scheduler at {self.client.scheduler.address} "
                                f"({why})") from None

    def fail(self, entry: dict, run: Run | None, error: BaseException) -> None:
        """A run's fault: with `isolated` runs, it stops that run alone (its checkpoint kept, its
        state and cause recorded) and another takes its place; otherwise it ends the drive, as a
        fault of the machine (a RunError) unless it is one already."""
        if not self.isolated:
            if isinstance(error, (UsageError, RunError, OSError)):
                raise error
            raise RunError(f"{type(error).__name__}: {fault_text(error)}") from error
        if run is not None:
            with contextlib.suppress(Exception):
                run.save_checkpoint()
            self.close(run, "failed", error)
        else:
            self.record(entry, "failed", error)
        self.log.info(f"run {entry['name']} failed: {fault_text(error)}")
        self.start_more()

    def finish(self, run: Run) -> None:
        """The run is complete: its folder is written in the saver thread (reap() closes it)
        while another run takes its place."""
        run.save(self.savers)
        self.live.pop(run.name, None)
        self.closing.append(run)
        self.start_more()

    def reap(self, wait: bool) -> None:
        """Close the finished runs whose last save is written (with `wait`, all of them)."""
        for run in [run for run in self.closing if wait or run.pending.done()]:
            self.closing.remove(run)
            try:
                run.settle()
            except Exception as error:
                self.fail(self.entries[run.name], run, error)
                continue
            if run.metrics:
                run.log.info("Done. " + describe_progress(run.metrics[-1], run.target))
            self.close(run, "done")

    def close(self, run: Run, state: str, error: BaseException | None = None) -> None:
        self.live.pop(run.name, None)
        run.tracking.close()
        run.leaving.close()
        self.record(self.entries[run.name], state, error)


class OneRun(Driver):
    """search and resume: one run, made by `make` once the drive begins; its fault ends the drive."""

    desc = "search"

    def __init__(self, client, log: logging.Logger, run_dir: Path, iterations: int,
                 make: Callable[[], Run]) -> None:
        super().__init__(client, log, [{"name": run_dir.name}], total=iterations)
        self.make = make

    def open(self, entry: dict) -> Run:
        return self.make()
