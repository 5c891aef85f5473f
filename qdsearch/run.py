"""The commands of one run: `search` starts one, `resume_run` continues one (the `resume` of a run
folder), both driving it through the one run loop (loop.py's OneRun).

Map:
- `search`, `resume_run`;
- what they share with experiments: `session` (the Dask client and the log, and the one line a
  stop or a fault ends with), `run_session` (a run folder's: `checkpoint_state`), `where_to_look`
  (the end of a finished search).
"""

from __future__ import annotations

import contextlib
import datetime
import secrets
import shlex
import sys
from pathlib import Path
from typing import Any, Callable, Iterator

from qdsearch.cluster import SchedulerLost, dask_client, scheduler_of
from qdsearch.flags import UsageError, boolean, check_flags, takes
from qdsearch.loop import OneRun, Run
from qdsearch.options import CLUSTER_FLAGS, RESUME_FLAGS, SEARCH_FLAGS, check_memory, checked, with_task
from qdsearch.run_config import check_run_config, load_archive, load_run_state, write_config
from qdsearch.run_files import (
    RunError,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
    read_run_json,
)
from qdsearch.signing import adopt, read_signed_pickle
from qdsearch.stopping import Stopped
from qdsearch.tasks import check_spaces


@takes(SEARCH_FLAGS)
def search(config: str | None = None, **flags: Any) -> None:
    """Search a task (--env; Lunar Lander's landings by default) with a QD algorithm and write a
    run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl (signed with your key), archive.npz, archive.pkl, archive.csv, metrics.json,
    heatmap.png, heatmaps/, progress.png, config.json and run.log. The other commands: COMMANDS
    in --help.

    Args:
        config: A run's config.json (or its run folder): a new run with exactly that run's
            settings, its seed too, so its archive is the same bit for bit; a flag given beside
            it (other than its default) replaces the file's value.
    """
    if config is not None:
        flags = settings_of(Path(str(config)), flags)
    flags = with_task(check_flags(SEARCH_FLAGS, flags))
    check_spaces(flags["env"])
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    # Fire reads a folder named 2024 as a number: a path flag is the text as typed.
    config = check_run_config({name: value if value is None or SEARCH_FLAGS[name].check else str(value)
                               for name, value in flags.items()})
    check_memory(config.to_json())  # after the sizes' own bounds (check_run_config's)
    seed_archive = load_archive(Path(config.from_archive), config) if config.from_archive else None
    address = scheduler_of(flags)
    with new_folder(config.outdir, f"seed{config.seed}") as run_dir:
        config = config.replace(
            outdir=str(run_dir), created=datetime.datetime.now().isoformat(), command=sys.argv,
            versions=library_versions(),
            from_archive=str(Path(config.from_archive).resolve()) if config.from_archive else None)
        write_config(run_dir, config)
        with run_session(run_dir, config.workers, address, config.pictures) as (client, log):
            OneRun(client, log, run_dir, config.iterations,
                   lambda: Run.start(run_dir, config, client, log, seed_archive)).drive()
    print(where_to_look(run_dir, config.pictures))


# What --config does not take from its file: where the new run goes and the cluster it flies on.
NOT_FROM_CONFIG = ("outdir", *CLUSTER_FLAGS)


def settings_of(path: Path, given: dict[str, Any]) -> dict[str, Any]:
    """search's flags from a run's config.json (--config), with the flags given beside it that
    differ from their defaults in place of the file's."""
    folder, name = (path, "config.json") if path.is_dir() else (path.parent, path.name)
    try:
        recorded = check_run_config(read_run_json(folder, name)).to_json()
    except UsageError as error:
        raise UsageError(f"--config {path}: {error}") from None
    return {flag: given[flag] if flag in NOT_FROM_CONFIG or given[flag] != SEARCH_FLAGS[flag].default
            else recorded[flag] for flag in SEARCH_FLAGS}


@takes(RESUME_FLAGS)
def resume_run(run_dir: str, **flags: Any) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped (the
    `resume` command of a run folder; experiments.resume hands it those).

    A checkpoint not signed with your key is refused unless --trust is given (which signs it
    with your key).

    Args:
        run_dir: A run folder written by this script.
    """
    path, iterations, workers = Path(run_dir), flags["iterations"], flags["workers"]
    trust = boolean("trust", flags["trust"])
    load_run_state(path, trust)  # refuse a bad folder before anything is written in it
    scheduler_address = scheduler_of(flags)
    with folder_lock(path):
        if trust:
            adopt(path / "checkpoint.pkl")
        config, checkpoint = load_run_state(path)  # as the last writer left it
        iterations = checked("iterations", config.iterations if iterations is None else iterations)
        workers = checked("workers", config.workers if workers is None else workers)
        done = checkpoint["iteration"] if checkpoint else 0
        if iterations < done:
            raise UsageError(f"{path} is already at iteration {done}; --iterations must be at least that")
        seed_archive = load_archive(Path(config.from_archive), config) if (
            checkpoint is None and config.from_archive) else None
        extended = iterations > config.iterations  # a budget in evaluations no longer holds it
        config = config.replace(iterations=max(iterations, config.iterations),
                                evaluations=None if extended else config.evaluations, resumed=[
            *config.resumed, {"at": datetime.datetime.now().isoformat(), "from_iteration": done,
                              "to_iteration": iterations, "workers": workers}])
        write_config(path, config)
        with run_session(path, workers, scheduler_address, config.pictures) as (client, log):
            def make() -> Run:
                run = (Run.start(path, config, client, log, seed_archive) if checkpoint is None
                       else Run.from_checkpoint(path, {**checkpoint, "config": config}, log))
                run.target = iterations  # --iterations below the run's own stops it there
                return run
            OneRun(client, log, path, iterations, make).drive()
    print(where_to_look(path, config.pictures))


def where_to_look(run_dir: Path, pictures: bool) -> str:
    """The end of a finished search: where its results are, and the commands that show them."""
    folder = shlex.quote(str(run_dir))
    drawn = "heatmap.png, progress.png, " if pictures else ""
    return (f"Results in {run_dir}: {drawn}metrics.json, archive.csv. Look at "
            f"them with:\n  python lunar_lander.py explore {folder}      # a page to browse the "
            f"archive and watch any elite\n  python lunar_lander.py video {folder} --best   # an "
            f"mp4 of the best elite")


@contextlib.contextmanager
def session(log_path: Path, opening: str, workers: int, scheduler_address: str | None,
            state: Callable[[str], str], passing: tuple[type[BaseException], ...] = (), *,
            drawing: bool) -> Iterator[tuple]:
    """The Dask client and the log of a command that writes run folders (search, resume,
    experiment), shut down however it ends (`drawing`: whether a run of it draws its pictures).

    A stop or a fault (a full disk, a lost cluster) ends with one line: `state(flags)` says what
    the folders hold and the command that continues them (with `flags`, such as a new cluster's).
    Faults of `passing` kinds have said their own line already and go through as they are.
    """
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(log_path)
    with logging_redirect_tqdm(loggers=[log]):
        log.info(opening)
        try:
            with dask_client(workers, scheduler_address, log, drawing) as client:
                yield client, log
        except KeyboardInterrupt:
            log.info(f"Stopped; {state('')}")
            raise Stopped from None
        except passing:
            raise
        except (RunError, OSError) as error:
            elsewhere = " --scheduler_file NEW_FILE" if isinstance(error, SchedulerLost) else ""
            raise RunError(f"{fault_text(error)}; {state(elsewhere)}") from None


def run_session(run_dir: Path, workers: int, scheduler_address: str | None, pictures: bool):
    """A run folder's session: its log is run.log, and a stop or a fault says which iteration its
    checkpoint holds and how to continue."""
    return session(run_dir / "run.log", f"Run folder: {run_dir}", workers, scheduler_address,
                   lambda flags: checkpoint_state(run_dir, flags), drawing=pictures)


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
