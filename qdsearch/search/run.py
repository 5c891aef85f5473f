"""One run: `Run`, a run between two iterations (what it asks, flies and tells, and its folder),
and the commands that start one and continue one, driving it through the one run loop
(loop.py's OneRun; experiments.py drives many).

The checkpoint is built and written here only, signed with the user's key (signing.py). A run's
policy and episode rules are read from its config once (`Run.__init__`) and travel with every
chunk of its batch to the workers (engine.py's `submit_flights`).

Map:
- `Run`: `start` (iteration 0, or a warm start), `from_checkpoint`, `ask`, `send` (its batch to
  the cluster), `take` (a chunk back), `tell_batch` (a DQD row's gradients: `tell_gradients`,
  `tell_exact_gradients`; ME-ES's samples: `chains_networks`, `es_steps`, their collected
  episodes flown again here: `observations`; a learning row's learner: learning.py), the
  checkpoint and `save` (its folder's files: saving.py's `save_outputs`);
- `search` (the run a checked RunConfig describes: run_config.search_config makes it),
  `resume_run` (a run folder continued to a budget);
- what they share with experiments: `session` (the Dask client and the log, and the one line a
  stop or a fault ends with), `run_session` (a run folder's: `checkpoint_state`), `where_to_look`
  (the end of a finished search).
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import pickle
import shlex
import sys
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from qdsearch.algorithms import ALGORITHMS, ARCHIVES, build_scheduler
from qdsearch.algorithms.gradients import estimate, noise, sample_points
from qdsearch.base import compact_pickle
from qdsearch.base.flags import UsageError, named
from qdsearch.base.run_files import (
    RunError,
    atomic_write,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
)
from qdsearch.base.signing import adopt, read_signed_pickle, write_signed
from qdsearch.base.stopping import Stopped
from qdsearch.config.command_settings import ResumeSettings, resumed_cluster
from qdsearch.config.options import check_learning, checked, resumed_budget
from qdsearch.config.run_config import (
    CHECKPOINT_FORMAT,
    RunConfig,
    load_archive,
    load_run_state,
    write_config,
)
from qdsearch.config.settings import ClusterSettings
from qdsearch.search.cluster import SchedulerLost, dask_client, scheduler_of
from qdsearch.search.engine import averaged, evaluate_batch, per_terrain, submit_flights
from qdsearch.search.learning import Learning
from qdsearch.search.loop import OneRun
from qdsearch.store.metrics import iteration_metrics
from qdsearch.store.saving import Savers
from qdsearch.store.trackers import Tracking
from qdsearch.tasks import (
    episode_of,
    evaluate_points,
    make_env,
    point_gradients,
    reset_seeds,
    returns_of,
    scored_here,
)
from qdsearch.tasks.policies import fly


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
                             self.config, checkpoint["iteration"], returns_of(self.config).heat)
        with savers.one_at_a_time:
            self.tracking.save(checkpoint["metrics"])

    def settle(self, wait: bool = True) -> None:
        """Wait for the save in the saver thread (without `wait`: only if it is over); raise its
        fault, so a full disk stops the run at once."""
        if self.pending is not None and (wait or self.pending.done()):
            pending, self.pending = self.pending, None
            pending.result()


def search(config: RunConfig) -> Path:
    """Start the run `config` describes (a checked config: search_config) on the cluster its
    cluster settings name, drive it to its budget and return its folder."""
    seed_archive = load_archive(Path(config.from_archive), config) if config.from_archive else None
    address = None if scored_here(config.env) else scheduler_of(config)
    with new_folder(config.outdir, f"seed{config.seed}") as run_dir:
        config = config.replace(
            outdir=str(run_dir), created=datetime.datetime.now().isoformat(), command=sys.argv,
            versions=library_versions(),
            from_archive=str(Path(config.from_archive).resolve()) if config.from_archive else None)
        write_config(run_dir, config)
        local = scored_here(config.env)
        with run_session(run_dir, config.workers, address, config.pictures, local) as (client, log):
            OneRun(client, log, run_dir, config.iterations,
                   lambda: Run.start(run_dir, config, client, log, seed_archive)).drive()
    return run_dir


def resume_run(path: Path, budget: ResumeSettings, cluster: ClusterSettings) -> RunConfig:
    """Continue the run in `path` from its checkpoint, exactly as if it had never stopped, to the
    budget `budget` gives (None: the run's own), on the cluster `cluster` names (workers None: as
    the run was started); return its config as it now stands. A checkpoint not signed with the user's key is
    refused unless `budget.trust` (which signs it with the user's key)."""
    workers, trust = budget.workers, budget.trust
    found, _ = load_run_state(path, trust)  # refuse a bad folder, or budget, before anything is
    resumed_budget(found.to_json(), budget.iterations, budget.evaluations)  # written in it
    check_learning(found)
    local = scored_here(found.env)
    scheduler_address = None if local else scheduler_of(resumed_cluster(budget, cluster))
    with folder_lock(path):
        if trust:
            adopt(path / "checkpoint.pkl")
        config, checkpoint = load_run_state(path)  # as the last writer left it
        reached = resumed_budget(config.to_json(), budget.iterations, budget.evaluations)
        iterations = reached["iterations"]
        workers = checked("workers", config.workers if workers is None else workers)
        done = checkpoint["iteration"] if checkpoint else 0
        if iterations < done:
            raise UsageError(f"{path} is already at iteration {done}; "
                             f"{named('evaluations' if budget.evaluations else 'iterations')} must reach "
                             "that")
        seed_archive = load_archive(Path(config.from_archive), config) if (
            checkpoint is None and config.from_archive) else None
        config = config.replace(iterations=max(iterations, config.iterations),
                                evaluations=reached["evaluations"] if iterations >= config.iterations
                                else config.evaluations, resumed=[
            *config.resumed, {"at": datetime.datetime.now().isoformat(), "from_iteration": done,
                              "to_iteration": iterations, "workers": workers}])
        write_config(path, config)
        with run_session(path, workers, scheduler_address, config.pictures, local) as (client, log):
            def make() -> Run:
                run = (Run.start(path, config, client, log, seed_archive) if checkpoint is None
                       else Run.from_checkpoint(path, {**checkpoint, "config": config}, log))
                run.target = iterations  # --iterations below the run's own stops it there
                return run
            OneRun(client, log, path, iterations, make).drive()
    return config


def where_to_look(run_dir: Path, config: RunConfig) -> str:
    """The end of a finished search: where its results are, and the commands that show them (a
    benchmark function's points have no episode to watch: its best elites)."""
    folder = shlex.quote(str(run_dir))
    drawn = "heatmap.png, progress.png, " if config.pictures else ""
    if scored_here(config.env):
        return (f"Results in {run_dir}: {drawn}metrics.json, archive.csv. Its best points:\n"
                f"  python lunar_lander.py elites {folder} --top 10")
    return (f"Results in {run_dir}: {drawn}metrics.json, archive.csv. Look at "
            f"them with:\n  python lunar_lander.py explore {folder}      # a page to browse the "
            f"archive and watch any elite\n  python lunar_lander.py video {folder} --best   # an "
            f"mp4 of the best elite")


@contextlib.contextmanager
def session(log_path: Path, opening: str, workers: int, scheduler_address: str | None,
            state: Callable[[str], str], passing: tuple[type[BaseException], ...] = (), *,
            drawing: bool, local: bool = False) -> Iterator[tuple]:
    """The Dask client and the log of a command that writes run folders (search, resume,
    experiment), shut down however it ends (`drawing`: whether a run of it draws its pictures).
    With `local` (runs scored in this process: scored_here), no cluster: the client is None.

    A stop or a fault (a full disk, a lost cluster) ends with one line: `state(flags)` says what
    the folders hold and the command that continues them (with `flags`, such as a new cluster's).
    Faults of `passing` kinds have said their own line already and go through as they are.
    """
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(log_path)
    with logging_redirect_tqdm(loggers=[log]):
        log.info(opening)
        try:
            with (contextlib.nullcontext() if local else dask_client(workers, scheduler_address, log,
                                                                      drawing)) as client:
                if local:
                    log.info("Scoring the points in this process: a benchmark function needs no cluster")
                yield client, log
        except KeyboardInterrupt:
            log.info(f"Stopped; {state('')}")
            raise Stopped from None
        except passing:
            raise
        except (RunError, OSError) as error:
            elsewhere = f" {named('scheduler_file')} NEW_FILE" if isinstance(error, SchedulerLost) else ""
            raise RunError(f"{fault_text(error)}; {state(elsewhere)}") from None


def run_session(run_dir: Path, workers: int, scheduler_address: str | None, pictures: bool,
                local: bool = False):
    """A run folder's session: its log is run.log, and a stop or a fault says which iteration its
    checkpoint holds and how to continue (`local`: scored in this process, session's)."""
    return session(run_dir / "run.log", f"Run folder: {run_dir}", workers, scheduler_address,
                   lambda flags: checkpoint_state(run_dir, flags), drawing=pictures, local=local)


def checkpoint_state(run_dir: Path, flags: str = "") -> str:
    """What a stopped or failed run folder holds, and the command that continues it (with
    `flags`, such as a new cluster's)."""
    path = run_dir / "checkpoint.pkl"
    try:
        held = f"its checkpoint holds iteration {read_signed_pickle(path, 'checkpoint')['iteration']}"
    except (UsageError, KeyError, TypeError):
        held = ("its checkpoint is not readable as this run's" if path.exists() else
                "it holds no checkpoint yet (resume starts the run from its config.json)")
    return f"{held}; continue with: python lunar_lander.py resume {shlex.quote(str(run_dir))}{flags}"
