"""The run: ask -> evaluate -> tell, with metrics, checkpoints and outputs; `search` and `resume`.

Map:
- metrics: METRIC_FIELDS, `iteration_metrics`, `check_metrics`, `describe_progress`;
- `Saver` (the thread run folders are written in) and `Run` (one search between iterations: the
  one place a checkpoint is built and written); `run_loop` (ask -> evaluate -> tell);
- reading a run folder back: `load_metrics`, `load_run_config`, `load_checked_config`,
  `load_run_state`, `check_same_config`, `check_archive`, `load_archive`, `check_run_config`,
  `load_checkpoint`; writing its files: `save_outputs`;
- the commands `search` and `resume_run` (`resume` of a run folder), and what they share:
  `run_session`, `checkpoint_state`, `where_to_look`.
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import math
import pickle
import secrets
import shlex
import sys
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from qdsearch.algorithms import archive_grid, build_scheduler
from qdsearch.cluster import STOP, SchedulerLost, dask_client, scheduler_of
from qdsearch.engine import evaluate_batch
from qdsearch.flags import (
    UsageError,
    check_flags,
    seed_number,
    shown,
    takes,
)
from qdsearch.options import (
    CLUSTER_FLAGS,
    RESUME_FLAGS,
    SEARCH_FLAGS,
    before_the_flags,
    check_sizes,
    checked,
    search_defaults,
    with_task,
)
from qdsearch.plots import save_heatmap, save_progress_plot
from qdsearch.run_files import (
    RunError,
    atomic_write,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
    read_pickle,
    read_run_json,
    write_csv,
    write_json,
    write_pickle,
)
from qdsearch.tasks import MEASURES, check_spaces

CHECKPOINT_FORMAT = "lunar_lander.checkpoint/1"


# A row of metrics.json: each field and what it holds (None: no elite yet).
METRIC_FIELDS: dict[str, tuple[type, ...]] = {
    "iteration": (int,), "evaluations": (int,), "coverage": (float,), "num_elites": (int,),
    "qd_score": (float,), "best_objective": (float, type(None)),
    "mean_objective": (float, type(None)), "elapsed_s": (float,),
}


def iteration_metrics(archive, iteration: int, evaluations: int, elapsed: float) -> dict:
    """One row of metrics.json: the archive's state after `iteration` iterations."""
    stats = archive.stats
    return {
        "iteration": iteration,
        "evaluations": evaluations,
        "coverage": float(stats.coverage),
        "num_elites": int(stats.num_elites),
        "qd_score": float(stats.qd_score),
        "best_objective": float(stats.obj_max) if stats.num_elites else None,
        "mean_objective": float(stats.obj_mean) if stats.num_elites else None,
        "elapsed_s": round(elapsed, 3),
    }


class Saver(ThreadPoolExecutor):
    """The thread run folders are written in while the search goes on (one thread: the plots'
    matplotlib is not thread-safe). Leaving it waits for the writes and raises the first fault."""

    def __init__(self) -> None:
        super().__init__(1, thread_name_prefix="save")
        self.writes: list[Future] = []

    def submit(self, function: Callable, /, *args: Any) -> Future:
        self.writes.append(super().submit(function, *args))
        return self.writes[-1]

    def __exit__(self, *exc_info: Any) -> None:
        super().__exit__(*exc_info)
        if exc_info[0] is None:
            for write in self.writes:
                write.result()


class Run:
    """One search between two iterations, and the folder it is saved to.

    The checkpoint is built and written here only. It always holds the last completed iteration:
    ask() moves the emitters on, so the scheduler is snapshotted (pickled, ~1 ms) after every tell,
    and a stop or a fault while the cluster evaluates writes that snapshot. The iteration in flight
    is abandoned, never half-recorded. The scheduler is pickled as one object (its emitters share
    its archive; CMA-ES state and RNGs come along), so a resumed run asks exactly the same.

    The folder's files may be written in a thread while the search goes on (`save(saver)`):
    they are built from that snapshot, so nothing the run does next can change them.
    """

    def __init__(self, run_dir: Path, config: dict, scheduler, metrics: list[dict]) -> None:
        self.dir, self.config, self.scheduler, self.metrics = run_dir, config, scheduler, metrics
        self.snapshot = pickle.dumps(scheduler, protocol=pickle.HIGHEST_PROTOCOL)
        self.saved = self.iteration
        self.pending: Future | None = None  # a save being written by the saver thread
        self._asked_at = 0.0

    @classmethod
    def start(cls, run_dir: Path, config: dict, client, log: logging.Logger,
              seed_archive=None) -> Run:
        """Iteration 0 of a new run, checkpointed at once so the folder always holds one.

        With `seed_archive` (a warm start), its elites are first flown again in this run's setting
        (another terrain, say) and inserted, and the emitters start from the best of them.
        """
        if seed_archive is None:
            run = cls(run_dir, config, build_scheduler(config), [])
        else:
            elites = seed_archive.data(["solution"])["solution"]
            objectives, measures = evaluate_batch(client, elites, config)
            scheduler = build_scheduler(config, x0=elites[int(np.argmax(objectives))])
            for archive in {id(a): a for a in (scheduler.archive, scheduler.result_archive)}.values():
                archive.add(elites, objectives, measures)
            run = cls(run_dir, config, scheduler,
                      [iteration_metrics(scheduler.result_archive, 0, len(elites), 0.0)])
            log.info(f"Warm start: {len(elites)} elites re-evaluated, {len(scheduler.result_archive)} "
                     f"kept; emitters start from the best (objective {objectives.max():.1f})")
        run.save_checkpoint(force=True)
        return run

    @classmethod
    def from_checkpoint(cls, run_dir: Path, checkpoint: dict) -> Run:
        return cls(run_dir, checkpoint["config"], checkpoint["scheduler"], checkpoint["metrics"])

    @property
    def iteration(self) -> int:
        return self.metrics[-1]["iteration"] if self.metrics else 0  # a warm start has iteration 0

    def ask(self) -> np.ndarray:
        self._asked_at = time.perf_counter()
        return self.scheduler.ask()

    def tell(self, objectives: np.ndarray, measures: np.ndarray) -> dict:
        """Record the evaluated batch; returns the new row of metrics."""
        self.scheduler.tell(objectives, measures)
        self.snapshot = pickle.dumps(self.scheduler, protocol=pickle.HIGHEST_PROTOCOL)
        last = self.metrics[-1] if self.metrics else {"evaluations": 0, "elapsed_s": 0.0}
        self.metrics.append(iteration_metrics(
            self.scheduler.result_archive, self.iteration + 1, last["evaluations"] + len(objectives),
            last["elapsed_s"] + time.perf_counter() - self._asked_at))
        return self.metrics[-1]

    def checkpoint(self) -> dict:
        """Everything needed to continue the run, as of the last completed iteration."""
        return {"format": CHECKPOINT_FORMAT, "scheduler": pickle.loads(self.snapshot),
                "metrics": list(self.metrics), "iteration": self.iteration, "config": self.config}

    def save_checkpoint(self, force: bool = False) -> None:
        """Write the checkpoint if iterations were completed since the last save (after the save
        in the saver thread, whose fault, if any, is raised once the checkpoint is written)."""
        try:
            self.settle()
        finally:
            if force or self.iteration > self.saved:
                write_pickle(self.dir / "checkpoint.pkl", self.checkpoint())
                self.saved = self.iteration

    def save(self, saver: Saver | None = None) -> None:
        """Refresh every file of the run folder, the checkpoint first; with a `saver`, in its
        thread, so the workers are fed meanwhile."""
        self.settle()
        checkpoint = self.checkpoint()
        if saver is None:
            self.write(checkpoint)
        else:
            self.pending = saver.submit(self.write, checkpoint)

    def write(self, checkpoint: dict) -> None:
        write_pickle(self.dir / "checkpoint.pkl", checkpoint)
        self.saved = checkpoint["iteration"]
        save_outputs(self.dir, checkpoint)

    def settle(self, wait: bool = True) -> None:
        """Wait for the save in the saver thread (without `wait`: only if it is over); raise its
        fault, so a full disk stops the run at once."""
        if self.pending is not None and (wait or self.pending.done()):
            pending, self.pending = self.pending, None
            pending.result()


def run_loop(run: Run, client, iterations: int, log: logging.Logger, saver: Saver) -> None:
    """Iterate ask -> evaluate -> tell up to `iterations`, refreshing the run folder every
    log_every iterations and at the end, in the saver's thread: the workers fly the next
    iterations meanwhile, and the cluster shuts down during the last write. A stop or a fault
    keeps the last completed iteration."""
    from tqdm import tqdm

    bar = tqdm(range(run.iteration + 1, iterations + 1), initial=run.iteration, total=iterations,
               unit="it", desc="search", dynamic_ncols=True)
    try:
        for iteration in bar:
            STOP.check()
            solutions = run.ask()
            with STOP.interruptible():
                objectives, measures = evaluate_batch(client, solutions, run.config)
            row = run.tell(objectives, measures)
            run.settle(wait=False)  # a fault of the last write (a full disk) stops the run now
            bar.set_postfix(coverage=f"{row['coverage']:.3f}", qd=f"{row['qd_score']:.4g}",
                            best=f"{row['best_objective'] or float('nan'):.1f}", refresh=False)
            if iteration % run.config["log_every"] == 0 and iteration < iterations:
                log.info(describe_progress(row, iterations))
                run.save(saver)
    except BaseException as error:
        bar.close()
        try:
            run.save_checkpoint()
        except RunError:
            if not isinstance(error, RunError):  # a stop, or another fault: report this one
                raise
        raise
    bar.close()
    run.save(saver)
    if run.metrics:
        log.info("Done. " + describe_progress(run.metrics[-1], iterations))


def describe_progress(row: dict, iterations: int) -> str:
    best = row["best_objective"]
    return (f"iteration {row['iteration']}/{iterations}: {row['evaluations']} evaluations, "
            f"coverage {row['coverage']:.3f}, QD score {row['qd_score']:.0f}, "
            f"best {best if best is None else round(best, 1)}, "
            f"{row['elapsed_s'] / max(row['iteration'], 1):.2f} s/iteration")


def check_metrics(rows: Any, path: Path) -> list[dict]:
    """metrics.json's rows (at least one), each with every field of METRIC_FIELDS holding a value
    of its type (an int counts as a float; NaN and infinities do not), or a UsageError that names
    the first that does not."""
    if not isinstance(rows, list) or not rows:
        raise UsageError(f"{path}: no metrics (a list of one row per iteration)")
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise UsageError(f"{path}: row {i} is a {type(row).__name__}, not a row of metrics")
        for field, kinds in METRIC_FIELDS.items():
            if field not in row and field != "elapsed_s":  # older runs recorded no timings
                raise UsageError(f"{path}: row {i} has no {field}")
            if field in row and not holds(row[field], kinds):
                raise UsageError(f"{path}: row {i} has {field} = {shown(row[field])}, not "
                                 f"{' or '.join(kind.__name__ for kind in kinds)}")
    return rows


def holds(value: Any, kinds: tuple[type, ...]) -> bool:
    """Whether a JSON value is one of `kinds`: a whole number counts as a float; NaN, infinities
    and booleans count as nothing."""
    if value is None or isinstance(value, bool):
        return value is None and type(None) in kinds
    if float in kinds:
        return isinstance(value, (int, float)) and math.isfinite(value)
    return isinstance(value, int)


def load_metrics(run_dir: Path) -> list[dict]:
    """A run folder's metrics.json, checked (check_metrics)."""
    return check_metrics(read_run_json(run_dir, "metrics.json"), run_dir / "metrics.json")


def load_run_config(run_dir: Path) -> dict:
    """A run folder's config.json, every flag valid (check_run_config)."""
    recorded = read_run_json(run_dir, "config.json")  # its own error for a missing or bad file
    try:
        return check_run_config(recorded)
    except UsageError as error:
        raise UsageError(f"{run_dir / 'config.json'}: not a usable run config ({error})") from None


def load_checked_config(run_dir: Path) -> dict:
    """What the results commands read of a run: its config.json, checked, and checked against its
    checkpoint where it has one (an edit to another task of the same shape would go unseen by
    the archive's own checks)."""
    config = load_run_config(run_dir)
    if (run_dir / "checkpoint.pkl").is_file():
        check_same_config(config, load_checkpoint(run_dir / "checkpoint.pkl")["config"], run_dir)
    return config


# Flags that config.json may hold apart from its checkpoint: resume writes a larger --iterations
# into config.json before the run's next checkpoint records it.
MAY_DIFFER = ("iterations",)


def load_run_state(run_dir: Path) -> tuple[dict, dict | None]:
    """A run folder's config and checkpoint, which must agree (a hand edit of config.json is
    refused, not silently ignored). A run killed before its first checkpoint (while its cluster
    started) has only config.json: its checkpoint is None, and resume starts it afresh from that
    config, which records the seed, so it ends as the uninterrupted run would."""
    path = run_dir / "checkpoint.pkl"
    if path.is_file() or not (run_dir / "config.json").is_file():
        checkpoint = load_checkpoint(path)
        if (run_dir / "config.json").is_file():
            check_same_config(load_run_config(run_dir), checkpoint["config"], run_dir)
        return checkpoint["config"], checkpoint
    return load_run_config(run_dir), None


def check_same_config(recorded: dict, checkpointed: dict, run_dir: Path) -> None:
    """config.json must say what the checkpoint ran with: a run goes on as it started."""
    for name in SEARCH_FLAGS:
        if name not in MAY_DIFFER and name not in CLUSTER_FLAGS and recorded[name] != checkpointed[name]:
            raise UsageError(
                f"{run_dir / 'config.json'} says --{name} {shown(recorded[name])} but the run's "
                f"checkpoint ran with {shown(checkpointed[name])}: a run goes on with the settings "
                f"it started with; undo the edit, or start a new run with the flags you want")


def check_archive(archive: Any, path: Path, config: dict) -> None:
    """The archive must be the grid of the run's config: solution size, cells, measure ranges."""
    from ribs.archives import GridArchive

    if not isinstance(archive, GridArchive):
        raise UsageError(f"{path}: holds a {type(archive).__name__}, not a GridArchive")
    grid = archive_grid(config)
    shape = (archive.solution_dim, tuple(archive.dims), np.round(archive.lower_bounds, 9).tolist(),
             np.round(archive.upper_bounds, 9).tolist())
    lower, upper = zip(*grid["ranges"])
    expected = (grid["solution_dim"], tuple(grid["dims"]), np.round(lower, 9).tolist(),
                np.round(upper, 9).tolist())
    if shape[0] != expected[0]:
        raise UsageError(f"{path}: its solutions have {shape[0]} weights, but --env "
                         f"{config['env']}'s policy has {expected[0]}: an archive of another task's run")
    if shape != expected:
        raise UsageError(f"{path}: archive of another shape (solution size, grid, lower and upper "
                         f"bounds {shape}; the run's --measures {','.join(config['measures'])} and "
                         f"--grid {config['grid']} need {expected})")


def load_archive(path: Path, config: dict):
    """A saved archive, checked against the config of the run that uses it."""
    archive = read_pickle(path, "archive pickle")
    check_archive(archive, path, config)
    if len(archive) == 0:
        raise UsageError(f"{path}: the archive is empty; nothing to start from")
    return archive


def check_run_config(config: Any) -> dict:
    """A run's recorded config, every flag valid (a UsageError says which is not); a config from
    before a flag existed ran with what that flag now sets it to (its entry's `before`, or its
    default)."""
    if not isinstance(config, dict):
        raise UsageError(f"holds a {type(config).__name__}, not the flags of a run")
    config = {**search_defaults(), **before_the_flags(), **config}
    for name, flag in SEARCH_FLAGS.items():
        if config[name] is None and flag.default is not None:  # a check passes None: refuse it here
            raise UsageError(f"--{name} is null")
        if flag.check is None and not isinstance(config[name], (str, type(None))):
            raise UsageError(f"--{name} is {shown(config[name])}, not a path or an address")
    config.update(check_flags(SEARCH_FLAGS, {name: config[name] for name in SEARCH_FLAGS}))
    if not isinstance(config.get("resumed", []), list):
        raise UsageError(f"resumed is {shown(config['resumed'])}, not a list of resumptions")
    config = with_task(config)
    seed_number("seed", config["seed"])
    check_sizes(config)
    return config


def load_checkpoint(path: Path) -> dict:
    """A checkpoint written by this script and consistent with this script's problem."""
    if not path.is_file():
        raise UsageError(f"{path}: no checkpoint there (is {path.parent} a run folder of lunar_lander.py?)")
    checkpoint = read_pickle(path, "checkpoint")
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise UsageError(f"{path}: not a lunar_lander checkpoint (holds a {type(checkpoint).__name__})")
    from ribs.schedulers import Scheduler

    try:
        checkpoint["config"] = check_run_config(checkpoint["config"])
        metrics, iteration = checkpoint["metrics"], checkpoint["iteration"]
        if not isinstance(checkpoint["scheduler"], Scheduler):
            raise UsageError(f"holds a {type(checkpoint['scheduler']).__name__}, not a Scheduler")
    except (KeyError, TypeError, UsageError) as error:
        raise UsageError(f"{path}: checkpoint of an incompatible config ({error})") from None
    if metrics:
        check_metrics(metrics, path)
    if [row["iteration"] for row in metrics if row["iteration"] > 0] != list(range(1, iteration + 1)):
        raise UsageError(f"{path}: its metrics do not match its iteration {iteration}")
    check_archive(checkpoint["scheduler"].archive, path, checkpoint["config"])
    return checkpoint


def save_outputs(run_dir: Path, checkpoint: dict) -> None:
    """The run folder's files besides the checkpoint: metrics, archive, heatmaps, progress."""
    write_json(run_dir / "metrics.json", checkpoint["metrics"])
    archive = checkpoint["scheduler"].result_archive
    iteration = checkpoint["iteration"]
    write_pickle(run_dir / "archive.pkl", archive)
    table = archive.data(return_type="pandas")
    write_csv(run_dir / "archive.csv", table)
    title = f"{checkpoint['config']['algorithm']} after {iteration} iterations"
    snapshot = run_dir / "heatmaps" / f"heatmap_{iteration:05d}.png"
    save_heatmap(archive, [MEASURES[m] for m in checkpoint["config"]["measures"]], snapshot, title)
    atomic_write(run_dir / "heatmap.png", lambda f: f.write(snapshot.read_bytes()))
    save_progress_plot(checkpoint["metrics"], run_dir / "progress.png")


@takes(SEARCH_FLAGS)
def search(**flags: Any) -> None:
    """Search a task (--env; Lunar Lander's landings by default) with a QD algorithm and write a
    run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl, archive.pkl, archive.csv, metrics.json, heatmap.png, heatmaps/, progress.png,
    config.json and run.log. Other commands (each with --help): resume, experiment, video, elites,
    trajectories, evaluate, explore, compare.
    """
    flags = with_task(check_flags(SEARCH_FLAGS, flags))
    check_spaces(flags["env"])
    check_sizes(flags)
    from_archive = flags["from_archive"]
    seed_archive = load_archive(Path(from_archive), flags) if from_archive else None
    address = scheduler_of(flags)
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    with new_folder(flags["outdir"], f"seed{flags['seed']}") as run_dir:
        config = {**flags, "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
                  "command": sys.argv, "versions": library_versions()}
        if from_archive:
            config["from_archive"] = str(Path(from_archive).resolve())
        write_json(run_dir / "config.json", config)
        with run_session(run_dir, config["workers"], address) as (client, log, saver):
            run = Run.start(run_dir, config, client, log, seed_archive)
            run_loop(run, client, config["iterations"], log, saver)
    print(where_to_look(run_dir))


@takes(RESUME_FLAGS)
def resume_run(run_dir: str, **flags: Any) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped (the
    `resume` command of a run folder; experiments.resume hands it those).

    Args:
        run_dir: A run folder written by this script.
    """
    path, iterations, workers = Path(run_dir), flags["iterations"], flags["workers"]
    load_run_state(path)  # refuse a bad folder before anything is written in it
    scheduler_address = scheduler_of(flags)
    with folder_lock(path):
        config, checkpoint = load_run_state(path)  # as the last writer left it
        iterations = checked("iterations", config["iterations"] if iterations is None else iterations)
        workers = checked("workers", config["workers"] if workers is None else workers)
        done = checkpoint["iteration"] if checkpoint else 0
        if iterations < done:
            raise UsageError(f"{path} is already at iteration {done}; --iterations must be at least that")
        seed_archive = load_archive(Path(config["from_archive"]), config) if (
            checkpoint is None and config.get("from_archive")) else None
        config = {**config, "iterations": max(iterations, config["iterations"]),
                  "resumed": [*config.get("resumed", []), {
                      "at": datetime.datetime.now().isoformat(), "from_iteration": done,
                      "to_iteration": iterations, "workers": workers}]}
        write_json(path / "config.json", config)
        with run_session(path, workers, scheduler_address) as (client, log, saver):
            if checkpoint is None:
                run = Run.start(path, config, client, log, seed_archive)
            else:
                run = Run.from_checkpoint(path, {**checkpoint, "config": config})
            run_loop(run, client, iterations, log, saver)
    print(where_to_look(path))


def where_to_look(run_dir: Path) -> str:
    """The end of a finished search: where its results are, and the commands that show them."""
    folder = shlex.quote(str(run_dir))
    return (f"Results in {run_dir}: heatmap.png, progress.png, metrics.json, archive.csv. Look at "
            f"them with:\n  python lunar_lander.py explore {folder}      # a page to browse the "
            f"archive and watch any elite\n  python lunar_lander.py video {folder} --best   # an "
            f"mp4 of the best elite")


@contextlib.contextmanager
def run_session(run_dir: Path, workers: int, scheduler_address: str | None) -> Iterator[tuple]:
    """The Dask client, the log and the saver of a command writing `run_dir`, shut down however
    it ends: the cluster first, while the saver finishes writing the folder.

    A stop or a fault (a full disk, a lost cluster) ends with one line that says which iteration
    the folder's checkpoint holds and the command that continues from it.
    """
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(run_dir / "run.log")
    with logging_redirect_tqdm(loggers=[log]):
        log.info(f"Run folder: {run_dir}")
        try:
            with Saver() as saver, dask_client(workers, scheduler_address, log) as client:
                yield client, log, saver
        except KeyboardInterrupt:
            log.info(f"Stopped; {checkpoint_state(run_dir)}")
            raise
        except (RunError, OSError) as error:
            elsewhere = " --scheduler_file NEW_FILE" if isinstance(error, SchedulerLost) else ""
            raise RunError(f"{fault_text(error)}; {checkpoint_state(run_dir, elsewhere)}") from None


def checkpoint_state(run_dir: Path, flags: str = "") -> str:
    """What a stopped or failed run folder holds, and the command that continues it (with
    `flags`, such as a new cluster's)."""
    try:
        held = f"its checkpoint holds iteration {read_pickle(run_dir / 'checkpoint.pkl', '')['iteration']}"
    except (UsageError, KeyError, TypeError):
        held = "it holds no checkpoint yet (resume starts the run from its config.json)"
    return f"{held}; continue with: python lunar_lander.py resume {shlex.quote(str(run_dir))}{flags}"
