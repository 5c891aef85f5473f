"""Experiments: every combination of the listed settings with every seed, as ordinary run folders
inside one experiment folder, interleaved on one Dask cluster by one driving process.

A run's results depend on its own asks and tells only, so each run ends bit for bit as `search`
alone would end it, whatever the interleaving, the worker count or a stop and resume between.

Map:
- `experiment`: the command; `experiment_grid` checks the grid's axes and the flags every run
  shares; `experiment_runs` names each run by its setting (`run_setting`, shared with compare);
- `run_experiment` and `Experiment`: the cluster, the log and the driving loop (as_completed);
  `LiveRun` is a run in flight;
- `resume`: the command, for a run folder (run.resume_run) or an experiment folder
  (`resume_experiment`); `read_experiment` reads experiment.json.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import datetime
import itertools
import logging
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from qdsearch.algorithms import ALGORITHMS
from qdsearch.cluster import STOP, SchedulerLost, dask_client, scheduler_of
from qdsearch.engine import averaged, per_terrain, submit_flights
from qdsearch.flags import UsageError, check_flags, clipped, one_of, positive_int, seed_list, shown, takes
from qdsearch.options import (
    CLUSTER_FLAGS,
    RESUME_FLAGS,
    SEARCH_FLAGS,
    before_the_flags,
    check_sizes,
    checked,
    ignores,
    own_flags,
    search_defaults,
    with_task,
)
from qdsearch.run import Run, Saver, describe_progress, load_run_state, resume_run
from qdsearch.run_files import (
    RunError,
    close_logger,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
    read_run_json,
    write_json,
)
from qdsearch.tasks import DEFAULT_ENV, check_spaces

EXPERIMENT_FORMAT = "lunar_lander.experiment/1"
# Which search flags an experiment sets itself (per_run) and which may take a list of values,
# one more axis of the grid (sweep), is said by their entries in SEARCH_FLAGS. (--env_seed and
# --measures take lists of their own: several terrains, several measures of every run.)


def passed_on() -> list[str]:
    """The search flags an experiment passes to every run."""
    return [name for name, flag in SEARCH_FLAGS.items() if not flag.per_run]


def experiment(algorithms: Any = ("cma_me",), seeds: Any = "1-5", outdir: str | None = None,
               max_in_flight: int | None = None, **search_flags: Any) -> None:
    """Run every combination of the listed settings with every seed, interleaved on one cluster.

    Each run is an ordinary run folder inside the experiment folder (every command works on it),
    bit for bit what `search` writes alone with the same flags. One process drives all runs: when
    a run's batch is back it is told, saved every log_every iterations, and its next batch is
    asked and sent, so the other runs' batches keep the workers busy while one waits for its
    slowest chunk. experiment.json records the grid, the command and each run's state. Ctrl-C,
    SIGTERM or kill -9 lose at most what each run did since its last checkpoint: continue with
    `resume EXPERIMENT_DIR`. A failing run is reported and recorded; the others go on.

    Args:
        algorithms: Rows of the ALGORITHMS table: cma_me, or a list "[cma_me, cma_mae]".
        seeds: The seeds of every setting: a range 1-5, a list 1,2,7 or both.
        outdir: Experiment folder; default outputs/<timestamp>_experiment. Must be new or empty.
        max_in_flight: Runs evaluated at once (default: all); the others wait their turn. Bounds
            memory with hundreds of runs.
        search_flags: Any flag of search that it passes to every run (see: lunar_lander.py --help):
            {passed_on}. A list of values of {sweeps}, e.g. --learning_rate "[0.01, 0.1]", is one
            more axis of the grid.
    """
    cluster = {name: search_flags.pop(name) for name in CLUSTER_FLAGS}
    axes, common, seeds = experiment_grid(algorithms, seeds, search_flags)
    workers = checked("workers", cluster["workers"])
    limit = None if max_in_flight is None else positive_int("max_in_flight", max_in_flight)
    scheduler_address = scheduler_of(cluster)
    with new_folder(outdir, "experiment") as folder:
        plan = {"format": EXPERIMENT_FORMAT, "created": datetime.datetime.now().isoformat(),
                "command": sys.argv, "axes": axes, "seeds": seeds, "common": common,
                "workers": workers, "max_in_flight": limit, "versions": library_versions(),
                "runs": experiment_runs(axes, common, seeds)}
        write_json(folder / "experiment.json", plan)
        run_experiment(folder, plan, workers, scheduler_address)


experiment.__doc__ = experiment.__doc__.format(
    passed_on=", ".join(f"--{name}" for name in passed_on()),
    sweeps=", ".join(f"--{name}" for name, flag in SEARCH_FLAGS.items() if flag.sweep))
experiment = takes(CLUSTER_FLAGS)(experiment)


def experiment_grid(algorithms: Any, seeds: Any, search_flags: dict) -> tuple[dict, dict, list[int]]:
    """The grid's axes (algorithm first, then each swept flag), the flags every run shares and
    the seeds, each value checked as search checks it."""
    if given := sorted(set(search_flags) - set(passed_on()) & set(SEARCH_FLAGS)):
        raise UsageError(f"--{given[0]} is set by the experiment for each run; use --algorithms, "
                         f"--seeds, --outdir, --workers and --scheduler_address (or --scheduler_file) "
                         f"of experiment")
    if unknown := sorted(set(search_flags) - set(search_defaults())):
        raise UsageError(f"unknown flag --{unknown[0]}")
    names = [n.strip() for n in algorithms.split(",")] if isinstance(algorithms, str) else list(algorithms)
    if not names:
        raise UsageError("--algorithms is empty: the grid has no run")
    axes = {"algorithm": [one_of(ALGORITHMS)("algorithms", name) for name in names]}
    common = {name: search_defaults()[name] for name in passed_on()}
    for name, value in search_flags.items():
        if SEARCH_FLAGS[name].sweep and isinstance(value, (list, tuple)):
            if not value:
                raise UsageError(f"--{name} is an empty list: the grid has no run")
            axes[name] = [check_flags(SEARCH_FLAGS, {name: v})[name] for v in value]
        else:
            common[name] = value
    common = with_task(check_flags(SEARCH_FLAGS, common))
    check_spaces(common["env"])
    for setting in itertools.product(*axes.values()):
        check_sizes({**common, **dict(zip(axes, setting))})
    return axes, common, seed_list("seeds", seeds)


def label_flags() -> list[str]:
    """The flags that name a run's setting when they differ from their defaults, in label order."""
    return sorted((name for name, flag in SEARCH_FLAGS.items() if flag.label),
                  key=lambda name: SEARCH_FLAGS[name].label)


def run_setting(config: dict) -> str:
    """The algorithm with its own flags, and the other flags shaping it that differ from their
    defaults: runs of one setting with different seeds are repeats of one experiment. An
    algorithm's own flags are always named (cma_mae at 0.01 and at 0.5 are different algorithms
    in effect), so a label means the same whatever the defaults become."""
    defaults, changed = check_flags(SEARCH_FLAGS, search_defaults()), []
    config = {**before_the_flags(), **config}  # a config.json from before a flag: what it ran with
    with contextlib.suppress(KeyError, TypeError, UsageError):  # measures: the task's default
        defaults = with_task({**defaults, "env": config.get("env", DEFAULT_ENV)})
        config = with_task(config)
    algorithm = config.get("algorithm")
    own = own_flags(algorithm) if algorithm in ALGORITHMS else ()
    for flag in (flag for flag in label_flags() if flag in config):
        if algorithm in ALGORITHMS and ignores(algorithm, flag):
            continue
        with contextlib.suppress(UsageError):
            value = check_flags(SEARCH_FLAGS, {flag: config[flag]})[flag]  # 52 and [52]: one terrain
            if value != defaults[flag] or flag in own:
                changed.append(f"{flag}={','.join(map(str, value)) if isinstance(value, list) else value}")
    return " ".join([str(config.get("algorithm", "?")), *changed])


def experiment_runs(axes: dict, common: dict, seeds: list[int]) -> list[dict]:
    """One entry per (setting, seed): its folder name, setting label, config and state."""
    runs, settings = [], []
    for values in itertools.product(*axes.values()):
        setting = {flag: common.get(flag) if ignores(values[0], flag) else value
                   for flag, value in zip(axes, values)}
        if setting not in settings:  # cma_me at two learning rates is one setting
            settings.append(setting)
    for setting in settings:
        for seed in seeds:
            config = {**common, **setting, "seed": seed}
            label = run_setting(config)
            name = re.sub(r"[^A-Za-z0-9.]+", "_", label) + f"_seed{seed}"
            runs.append({"name": name, "setting": label, "seed": seed, "config": config,
                         "state": "pending"})
    return runs


def run_experiment(folder: Path, plan: dict, workers: int, scheduler_address: str | None) -> None:
    """The cluster and the log of an experiment, shut down however it ends."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(folder / "experiment.log")
    with logging_redirect_tqdm(loggers=[log]):
        log.info(f"Experiment folder: {folder}: {len(plan['runs'])} runs "
                 f"({len(plan['runs']) // len(plan['seeds'])} settings x {len(plan['seeds'])} seeds)")
        try:
            with dask_client(workers, scheduler_address, log) as client:
                Experiment(folder, plan, client, log).drive()
        except KeyboardInterrupt:
            log.info(f"Stopped; every run keeps its last completed iteration; continue with: "
                     f"python lunar_lander.py resume {folder}")
            raise
        except RunsFailed:
            raise
        except (RunError, OSError) as error:  # of the experiment itself (experiment.json, cluster)
            new = " --scheduler_file NEW_FILE" if isinstance(error, SchedulerLost) else ""
            raise RunError(f"{fault_text(error)}; every run keeps its last checkpoint; continue "
                           f"with: python lunar_lander.py resume {folder}{new}") from None


class RunsFailed(RunError):
    """Some runs of an experiment failed (each recorded with its cause); the others finished."""


@dataclasses.dataclass
class LiveRun:
    """A run of the experiment in flight: its state, log, folder lock and batch on the cluster."""

    entry: dict
    run: Run
    log: logging.Logger
    lock: contextlib.ExitStack
    results: list = dataclasses.field(default_factory=list)  # the current batch's chunks, in order
    waiting: int = 0  # chunks of the current batch not back yet

    @property
    def target(self) -> int:
        return self.run.config["iterations"]


def count_as_done_before(bar, iterations: int) -> None:
    """Put a resumed run's earlier iterations on the tqdm bar as its starting point, not as work
    done now, so its rate and time left reflect only this drive."""
    bar.n, bar.last_print_n, bar.initial = (
        count + iterations for count in (bar.n, bar.last_print_n, bar.initial))
    bar.refresh()


THREADS_EVERY = 2.0  # seconds between two counts of the cluster's worker threads


class Experiment:
    """Drives many runs on one client: Dask's as_completed hands back chunks in whatever order
    they finish, and each run goes on as soon as its own batch is whole. A run's results depend on
    its own asks and tells only, so it ends as it would alone, whatever the interleaving."""

    def __init__(self, folder: Path, plan: dict, client, log: logging.Logger) -> None:
        from dask.distributed import as_completed

        self.folder, self.plan, self.client, self.log = folder, plan, client, log
        self.todo = collections.deque(e for e in plan["runs"] if e["state"] != "done")
        self.live: dict[str, LiveRun] = {}
        self.owner: dict[str, tuple[str, int]] = {}  # future key -> run name, chunk position
        self.latest: dict[str, dict] = {}  # run name -> its last metrics row
        self.told = 0  # iterations done in this drive
        self.closing: list[LiveRun] = []  # finished runs whose last save is being written
        self.saver = Saver()  # each run's faults are its own: see reap()
        # Results come with their futures (no second round trip to fetch them); a chunk that
        # failed comes as its exception, and fails its run alone.
        self.finished = as_completed(with_results=True, raise_errors=False)
        self.limit = plan.get("max_in_flight") or len(plan["runs"])
        self.threads_asked = (-math.inf, 1)  # when the worker threads were last counted, and how many

    def drive(self) -> None:
        from tqdm import tqdm

        runs = self.plan["runs"]
        total = sum(e["config"]["iterations"] for e in runs)
        done = sum(e["config"]["iterations"] for e in runs if e["state"] == "done")
        self.bar = tqdm(total=total, initial=done, unit="it", desc="experiment", dynamic_ncols=True)
        every, logged = self.plan["common"]["log_every"] * len(runs), done
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            self.start_more()
            while self.live:
                with STOP.interruptible():
                    future, result = next(self.finished)
                name, position = self.owner.pop(future.key, ("", 0))
                live = self.live.get(name)
                if live is not None:  # else a chunk of a run that has failed meanwhile
                    live.results[position] = result
                    live.waiting -= 1
                    if live.waiting == 0:
                        self.advance(live)
                self.reap(wait=False)
                if self.bar.n - logged >= every or not self.live:
                    logged = self.bar.n
                    for line in self.describe_settings():
                        self.log.info(line)
            self.reap(wait=True)
        except BaseException:
            for live in list(self.live.values()):
                with contextlib.suppress(Exception):
                    live.run.save_checkpoint()
                self.close(live, "stopped")
            self.reap(wait=True)
            raise
        finally:
            self.saver.shutdown()
            self.bar.close()
        # The driving loop's own cost: how much of a core the main process took while it ran.
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        self.plan["timing"] = {"drive_s": round(wall, 3), "main_cpu_s": round(cpu, 3),
                               "iterations": self.told}
        write_json(self.folder / "experiment.json", self.plan)
        failed = [e["name"] for e in runs if e["state"] == "failed"]
        self.log.info(f"Done: {len(runs) - len(failed)} of {len(runs)} runs finished in {self.folder} "
                      f"({wall:.1f} s, main process {cpu / max(wall, 1e-9):.0%} of a core)")
        if failed:
            which = (f"{len(failed)} of {len(runs)} runs failed ({', '.join(failed)})"
                     if len(failed) < len(runs) else
                     "its only run failed" if len(runs) == 1 else f"all {len(runs)} runs failed")
            others = "" if len(failed) == len(runs) else "; the others finished"
            raise RunsFailed(f"{which}: their causes are in {self.folder / 'experiment.json'}{others}. "
                             f"Mend the cause and retry them with: python lunar_lander.py resume "
                             f"{self.folder}")

    def threads(self) -> int:
        """The cluster's worker threads, asked of the scheduler at most every THREADS_EVERY seconds
        rather than for every batch (workers come and go; a stale count only sizes the chunks,
        never changes a result)."""
        if time.monotonic() - self.threads_asked[0] > THREADS_EVERY:
            self.threads_asked = (time.monotonic(), sum(self.client.nthreads().values()))
        return self.threads_asked[1]

    def start_more(self) -> None:
        """Open waiting runs until `limit` are in flight."""
        while self.todo and len(self.live) < self.limit:
            entry = self.todo.popleft()
            try:
                live = self.open(entry)
            except (UsageError, RunError, OSError) as error:
                self.record(entry, "failed", error)
                continue
            self.live[entry["name"]] = live
            self.latest[entry["name"]] = live.run.metrics[-1] if live.run.metrics else {}
            count_as_done_before(self.bar, live.run.iteration)
            self.record(entry, "running")
            if live.run.iteration >= live.target:
                self.finish(live)
            else:
                self.launch(live)

    def open(self, entry: dict) -> LiveRun:
        """A run's folder (made on first use), locked, and its run from checkpoint or config."""
        run_dir = self.folder / entry["name"]
        run_dir.mkdir(exist_ok=True)
        lock = contextlib.ExitStack()
        lock.enter_context(folder_lock(run_dir))
        try:
            if not (run_dir / "config.json").is_file():
                write_json(run_dir / "config.json", {
                    **entry["config"], "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
                    "command": self.plan["command"], "experiment": str(self.folder),
                    "versions": library_versions()})
            config, checkpoint = load_run_state(run_dir)
            if config["iterations"] < entry["config"]["iterations"]:  # the experiment was extended
                config = {**config, "iterations": entry["config"]["iterations"]}
                write_json(run_dir / "config.json", {**read_run_json(run_dir, "config.json"),
                                                     "iterations": config["iterations"]})
            log = make_logger(run_dir / "run.log", f"lunar_lander.run.{entry['name']}", console=False)
            run = (Run.start(run_dir, config, self.client, log) if checkpoint is None
                   else Run.from_checkpoint(run_dir, {**checkpoint, "config": config}))
        except BaseException:
            lock.close()
            raise
        return LiveRun(entry, run, log, lock)

    def launch(self, live: LiveRun) -> None:
        """Ask the run's next batch and send it to the cluster."""
        config = live.run.config
        futures = submit_flights(self.client, live.run.ask(), config["env_seed"], config["measures"],
                                 config["fast_env"], sharing=len(self.live), threads=self.threads(),
                                 env_name=config["env"])
        live.results, live.waiting = [None] * len(futures), len(futures)
        for position, future in enumerate(futures):
            self.owner[future.key] = (live.entry["name"], position)
            self.finished.add(future)

    def advance(self, live: LiveRun) -> None:
        """The run's batch is whole: tell it, save it at its log interval, ask again or finish."""
        try:
            if failed := next((r for r in live.results if isinstance(r, BaseException)), None):
                raise failed
            row = live.run.tell(*averaged(per_terrain(live.results, live.run.config["env_seed"])))
            live.run.settle(wait=False)
            self.latest[live.entry["name"]] = row
            self.told += 1
            self.bar.update(1)
            if row["iteration"] >= live.target:
                self.finish(live)
            else:
                self.launch(live)
                if row["iteration"] % live.run.config["log_every"] == 0:
                    live.log.info(describe_progress(row, live.target))
                    live.run.save(self.saver)
        except Exception as error:  # this run's fault (a task that failed, a write): it alone stops
            self.check_scheduler(error)
            self.fail(live, error)
            self.start_more()

    def check_scheduler(self, error: BaseException) -> None:
        """A task lost with the scheduler is no run's fault: the whole experiment stops (every run
        keeps its checkpoint) rather than failing its runs one by one."""
        if self.client.status != "running":
            raise SchedulerLost(f"lost the Dask scheduler at {self.client.scheduler.address} "
                                f"({clipped(fault_text(error))})") from None

    def fail(self, live: LiveRun, error: BaseException) -> None:
        with contextlib.suppress(Exception):
            live.run.save_checkpoint()
        self.close(live, "failed", error)
        self.log.info(f"run {live.entry['name']} failed: {fault_text(error)}")

    def finish(self, live: LiveRun) -> None:
        """The run is complete: its folder is written in the saver thread (reap() closes it)
        while another run takes its place."""
        live.run.save(self.saver)
        self.live.pop(live.entry["name"], None)
        self.closing.append(live)
        self.start_more()

    def reap(self, wait: bool) -> None:
        """Close the finished runs whose last save is written (with `wait`, all of them)."""
        for live in [live for live in self.closing if wait or live.run.pending.done()]:
            self.closing.remove(live)
            try:
                live.run.settle()
            except Exception as error:
                self.fail(live, error)
                continue
            live.log.info("Done. " + describe_progress(live.run.metrics[-1], live.target))
            self.close(live, "done")

    def close(self, live: LiveRun, state: str, error: BaseException | None = None) -> None:
        self.live.pop(live.entry["name"], None)
        close_logger(live.log)
        live.lock.close()
        self.record(live.entry, state, error)

    def record(self, entry: dict, state: str, error: BaseException | None = None) -> None:
        """A run's new state, in experiment.json at once."""
        entry["state"] = state
        if error is not None:
            entry["error"] = fault_text(error) if isinstance(error, (OSError, RunError)) else (
                f"{type(error).__name__}: {fault_text(error)}")
        else:
            entry.pop("error", None)
        write_json(self.folder / "experiment.json", self.plan)

    def describe_settings(self) -> list[str]:
        """A line per setting: its runs' progress, mean QD score and coverage, best objective."""
        lines = []
        for setting in dict.fromkeys(e["setting"] for e in self.plan["runs"]):
            rows = [self.latest[e["name"]] for e in self.plan["runs"]
                    if e["setting"] == setting and self.latest.get(e["name"])]
            if rows:
                best = max((r["best_objective"] for r in rows if r["best_objective"] is not None),
                           default=float("nan"))
                lines.append(f"{setting}: {len(rows)} run(s) at iteration "
                             f"{min(r['iteration'] for r in rows)}-{max(r['iteration'] for r in rows)}, "
                             f"QD score {np.mean([r['qd_score'] for r in rows]):.0f} (mean), coverage "
                             f"{np.mean([r['coverage'] for r in rows]):.3f} (mean), best {best:.1f}")
        return lines


@takes(RESUME_FLAGS)
def resume(run_dir: str, **flags: Any) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped; or,
    for an experiment folder, every unfinished run of the experiment.

    Args:
        run_dir: A run folder (or an experiment folder) written by this script.
    """
    path = Path(str(run_dir))
    if (path / "experiment.json").is_file():
        return resume_experiment(path, flags["iterations"], flags["workers"], flags)
    return resume_run(run_dir, **flags)


def resume_experiment(folder: Path, iterations: int | None, workers: int | None,
                      cluster: dict[str, Any]) -> None:
    """Continue every unfinished run of an experiment (failed ones are tried again), on the
    cluster the `cluster` flags name (by default a local one)."""
    read_experiment(folder)  # refuse a bad folder before anything is written in it
    scheduler_address = scheduler_of(cluster)
    with folder_lock(folder):
        plan = read_experiment(folder)
        workers = checked("workers", plan["workers"] if workers is None else workers)
        planned = max(entry["config"]["iterations"] for entry in plan["runs"])
        if iterations is not None:
            iterations = checked("iterations", iterations)
            if iterations < planned:
                raise UsageError(f"the runs of {folder} go to iteration {planned}; --iterations must "
                                 f"be at least that")
            for entry in plan["runs"]:
                if iterations > entry["config"]["iterations"]:
                    entry["config"]["iterations"] = iterations
                    entry["state"] = "pending"
        if all(entry["state"] == "done" for entry in plan["runs"]):
            print(f"nothing to do: all {len(plan['runs'])} runs of {folder} are done (iteration "
                  f"{planned}); --iterations N extends them")
            return
        plan["resumed"] = [*plan.get("resumed", []), {"at": datetime.datetime.now().isoformat(),
                                                      "iterations": iterations, "workers": workers}]
        write_json(folder / "experiment.json", plan)
        run_experiment(folder, plan, workers, scheduler_address)


RUN_STATES = ("pending", "running", "done", "stopped", "failed")


def read_experiment(folder: Path) -> dict:
    """experiment.json, checked: every run has a plain folder name (no path: a run folder is
    always inside its experiment), a known state, and a config with a seed and iterations."""
    plan = read_run_json(folder, "experiment.json")
    path = folder / "experiment.json"
    if not (isinstance(plan, dict) and plan.get("format") == EXPERIMENT_FORMAT
            and isinstance(plan.get("runs"), list) and plan["runs"]):
        raise UsageError(f"{path}: not an experiment of lunar_lander.py")
    for i, entry in enumerate(plan["runs"]):
        config = entry.get("config") if isinstance(entry, dict) else None
        fits = (isinstance(config, dict) and isinstance(entry.get("name"), str)
                and re.fullmatch(r"[A-Za-z0-9._-]+", entry["name"]) and entry["name"].strip(".")
                and entry.get("state") in RUN_STATES and isinstance(entry.get("setting"), str))
        try:
            if fits:
                checked("iterations", config.get("iterations"))
                check_flags(SEARCH_FLAGS, {"seed": config.get("seed")})
        except UsageError as error:
            fits, why = False, f": {error}"
        else:
            why = ""
        if not fits:
            raise UsageError(f"{path}: run {i} is not a run of this experiment's plan{why}")
    if isinstance(plan.get("workers"), bool) or not isinstance(plan.get("workers"), int):
        raise UsageError(f"{path}: workers is {shown(plan.get('workers'))}, not a number of workers")
    return plan
