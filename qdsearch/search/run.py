"""The commands of one run: `search` starts one, `resume_run` continues one (the `resume` of a run
folder), both driving it through the one run loop (loop.py's OneRun).

Map:
- `search`, `resume_run`; `search_config`, the config a search runs with, and with --config
  `settings_of` (the run's settings, a flag given beside its file in their place: NOT_FROM_CONFIG,
  FOLLOWS) and `typed_setting` (the command line's check of a row's own flags typed beside it);
- what they share with experiments: `session` (the Dask client and the log, and the one line a
  stop or a fault ends with), `run_session` (a run folder's: `checkpoint_state`), `where_to_look`
  (the end of a finished search).
"""

from __future__ import annotations

import contextlib
import datetime
import os
import secrets
import shlex
import sys
from pathlib import Path
from typing import Any, Callable, Collection, Iterator

from qdsearch.base.flags import UsageError, boolean, check_flags, named, takes
from qdsearch.base.run_files import (
    RunError,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
    read_run_json,
)
from qdsearch.base.signing import adopt, read_signed_pickle
from qdsearch.base.stopping import Stopped
from qdsearch.config.options import RESUME_FLAGS, check_memory, checked, resumed_budget, with_task
from qdsearch.config.run_config import RunConfig, check_run_config, load_archive, load_run_state, write_config
from qdsearch.config.settings import BUDGETS, CLUSTER_FLAGS, SEARCH_FLAGS
from qdsearch.search.cluster import SchedulerLost, dask_client, scheduler_of
from qdsearch.search.loop import OneRun, Run
from qdsearch.tasks import check_spaces


@takes(SEARCH_FLAGS)
def search(config: str | None = None, *, given: frozenset[str] = frozenset(), **flags: Any) -> None:
    """Search a task (--env; Lunar Lander's landings by default) with a QD algorithm and write a
    run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl (signed with your key), archive.npz, archive.csv, metrics.json,
    heatmap.png, heatmaps/, progress.png, config.json and run.log. The other commands: COMMANDS
    in --help.

    Args:
        config: A run's config.json (or its run folder): a new run with exactly that run's
            settings, its seed too, so its archive is the same bit for bit. A flag given beside
            it replaces the file's value, whatever its value, and takes along what the file's
            value made: another --env its own measures and archive, another --archive its own
            cells, another --policy its own --hidden, a budget (--iterations or --evaluations)
            the file's budget. Where the new run goes and the cluster it flies on are never the
            file's.
    """
    config = search_config(flags, given, None if config is None else Path(str(config)))
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


def search_config(flags: dict[str, Any], given: Collection[str] = (), path: Path | None = None) -> RunConfig:
    """The checked config a search runs with (nothing is written): its flags, or with --config
    (`path`) the file's settings with the flags `given` beside it in their place (settings_of);
    a seed drawn if none is set."""
    if path is not None:
        flags = settings_of(path, flags, given)
    flags = with_task(check_flags(SEARCH_FLAGS, flags))
    check_spaces(flags["env"])
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    # Fire reads a folder named 2024 as a number: a path flag is the text as typed.
    config = check_run_config({name: value if value is None or SEARCH_FLAGS[name].check else str(value)
                               for name, value in flags.items()})
    check_memory(config.to_json())  # after the sizes' own bounds (check_run_config's)
    return config


# What --config does not take from its file: where the new run goes and the cluster it flies on.
NOT_FROM_CONFIG = ("outdir", *CLUSTER_FLAGS)
# What a flag given beside --config takes along when its value is not the file's: the values the
# file's value made or alone used, each back to the flag's (its default, unless given too), so
# another task gets its own measures and archive, not the file's task's.
FOLLOWS: dict[str, tuple[str, ...]] = {
    "env": ("measures", "archive", "grid", "cells", "terminate_when_unhealthy", "qd_offset"),
    "episode_length": ("qd_offset",),
    "archive": ("grid", "cells"),
    "policy": ("hidden",),
}


def settings_of(path: Path, flags: dict[str, Any], given: Collection[str]) -> dict[str, Any]:
    """search's flags from a run's config.json (--config): the file's, with each flag `given`
    beside it (whatever its value) in place of the file's and what it takes along (FOLLOWS,
    BUDGETS); where the run goes and its cluster (NOT_FROM_CONFIG) are never the file's."""
    recorded = recorded_settings(path)
    merged = {flag: flags[flag] if flag in given or flag in NOT_FROM_CONFIG else recorded[flag]
              for flag in SEARCH_FLAGS}
    for flag, along in FOLLOWS.items():
        if flag in given and check_flags(SEARCH_FLAGS, {flag: flags[flag]})[flag] != recorded[flag]:
            merged.update({name: flags[name] for name in along})
    if set(BUDGETS) & set(given):  # a budget given replaces the file's, whatever its value
        merged.update({name: flags[name] for name in BUDGETS})
    return merged


def recorded_settings(path: Path) -> dict[str, Any]:
    """The settings of the run whose config.json (or run folder) --config names, checked; an
    experiment's experiment.json (or folder) is refused naming how to give one of its runs."""
    folder, name = (path, "config.json") if path.is_dir() else (path.parent, path.name)
    if name in ("config.json", "experiment.json") and (folder / "experiment.json").is_file() and not (
            os.path.lexists(folder / "config.json")):
        runs: list[str] = []
        with contextlib.suppress(OSError):  # (a run to name is a help, not a need)
            runs = sorted(run.name for run in folder.iterdir() if (run / "config.json").is_file())
        example = f" (such as {named('config')} {folder / runs[0]})" if runs else ""
        raise UsageError(f"{named('config')} {path}: an experiment's file, not a run's: give one of its "
                         "runs, "
                         f"{named('config')} {folder}/RUN_NAME{example}")
    try:
        return check_run_config(read_run_json(folder, name)).to_json()
    except UsageError as error:
        raise UsageError(f"{named('config')} {path}: {error}") from None


def typed_setting(typed: dict[str, str | None], flag: str) -> str:
    """What a search typed so runs with for `flag` (its algorithm, its policy): the value typed,
    else that of the run --config names, else the default (the command line's check of a row's
    own flags typed)."""
    if typed.get(flag) is not None:
        return str(typed[flag]).strip("'\"")
    if typed.get("config") is None:
        return SEARCH_FLAGS[flag].default
    return recorded_settings(Path(str(typed["config"])))[flag]


@takes(RESUME_FLAGS)
def resume_run(run_dir: str, **flags: Any) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped (the
    `resume` command of a run folder; experiments.resume hands it those).

    A checkpoint not signed with your key is refused unless --trust is given (which signs it
    with your key).

    Args:
        run_dir: A run folder written by this script.
    """
    path, workers = Path(run_dir), flags["workers"]
    trust = boolean("trust", flags["trust"])
    found, _ = load_run_state(path, trust)  # refuse a bad folder, or budget, before anything is
    resumed_budget(found.to_json(), flags["iterations"], flags["evaluations"])  # written in it
    scheduler_address = scheduler_of(flags)
    with folder_lock(path):
        if trust:
            adopt(path / "checkpoint.pkl")
        config, checkpoint = load_run_state(path)  # as the last writer left it
        budget = resumed_budget(config.to_json(), flags["iterations"], flags["evaluations"])
        iterations = budget["iterations"]
        workers = checked("workers", config.workers if workers is None else workers)
        done = checkpoint["iteration"] if checkpoint else 0
        if iterations < done:
            raise UsageError(f"{path} is already at iteration {done}; "
                             f"{named('evaluations' if flags['evaluations'] else 'iterations')} must reach "
                             "that")
        seed_archive = load_archive(Path(config.from_archive), config) if (
            checkpoint is None and config.from_archive) else None
        config = config.replace(iterations=max(iterations, config.iterations),
                                evaluations=budget["evaluations"] if iterations >= config.iterations
                                else config.evaluations, resumed=[
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
            elsewhere = f" {named('scheduler_file')} NEW_FILE" if isinstance(error, SchedulerLost) else ""
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
