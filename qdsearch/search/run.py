"""One run: `search` starts the run a checked RunConfig describes (run_config.search_config makes
it), `resume_run` continues one to a budget (the `resume` of a run folder), both driving it
through the one run loop (loop.py's OneRun).

Map:
- `search`, `resume_run`;
- what they share with experiments: `session` (the Dask client and the log, and the one line a
  stop or a fault ends with), `run_session` (a run folder's: `checkpoint_state`), `where_to_look`
  (the end of a finished search).
"""

from __future__ import annotations

import contextlib
import datetime
import shlex
import sys
from pathlib import Path
from typing import Callable, Iterator

from qdsearch.base.flags import UsageError, named
from qdsearch.base.run_files import (
    RunError,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
)
from qdsearch.base.signing import adopt, read_signed_pickle
from qdsearch.base.stopping import Stopped
from qdsearch.config.command_settings import ResumeSettings, resumed_cluster
from qdsearch.config.options import check_learning, checked, resumed_budget
from qdsearch.config.run_config import RunConfig, load_archive, load_run_state, write_config
from qdsearch.config.settings import ClusterSettings
from qdsearch.search.cluster import SchedulerLost, dask_client, scheduler_of
from qdsearch.search.loop import OneRun, Run
from qdsearch.tasks import scored_here


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
    check_learning(found.to_json())
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
