"""A run's configuration: the typed RunConfig (settings.py) made from flags or a record, the one
`upgrade` of old folders, and config.json, the checkpoint and the archive read back, checked
against the flags, each other and the archive. Nothing here unpickles a file that is not signed
with the user's key (signing.py): the results commands read the archive as data (archive_data.py).

Map:
- the two constructors of a RunConfig (settings.py's), each checking every value once:
  `check_run_config` from a record (`upgrade` of old folders first) and `search_config` from a
  search's flags, or with --config from a run's recorded settings (`recorded_settings`) with the
  flags given beside it in their place (`settings_of`: NOT_FROM_CONFIG, FOLLOWS); what they
  share: `refuse_nulls`, `completed` (what the flags make together); `write_config`;
- CHECKPOINT_FORMAT; `load_checkpoint` (signed, or trusted: resume --trust);
- `load_run_config`, `load_checked_config` (what the results commands read: config.json checked
  against archive.npz's config), `load_run_state` (what resume reads), `check_same_config`,
  `check_centroids`;
- `check_archive`, `saved_archive` (a folder's archive.npz, or the archive.csv of a folder from
  before it) and `load_archive` (an archive must be the grid of its run's config).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import secrets
from pathlib import Path
from typing import Any, Collection

import numpy as np

from qdsearch.algorithms import ARCHIVES, archive_shape, kind_of
from qdsearch.base.flags import UsageError, check_flags, named, seed_number, shown
from qdsearch.base.run_files import read_regular, read_run_json, write_json
from qdsearch.base.signing import read_signed_pickle
from qdsearch.config.options import (
    before_the_flags,
    check_learning,
    check_memory,
    check_sizes,
    legacy_offset,
    search_defaults,
    with_offset,
    with_task,
)
from qdsearch.config.settings import (
    BUDGETS,
    CLUSTER_FLAGS,
    RECORDS,
    SEARCH_FLAGS,
    RunConfig,
    RunRecords,
    with_policy,
)
from qdsearch.store.archive_data import archive_from_csv, empty_archive, read_archive_data, recorded_config
from qdsearch.store.metrics import check_metrics
from qdsearch.tasks import check_spaces


def upgrade(recorded: dict) -> dict:
    """A recorded config of any age in today's form: a run from before a flag existed ran with
    what its entry's `before` says (--learning_rate 0.01, before it was a flag) or its default
    (--env LunarLander-v3 and --grid 50, the tutorial's); one from before --measures, with its
    task's own measures (with_task: the tutorial's); one from before --qd_offset, with its task's
    offset at the task's own length (legacy_offset). No flag has ever been removed or renamed:
    every field a folder of any age holds is a flag of SEARCH_FLAGS or one of RECORDS."""
    return {**search_defaults(), **before_the_flags(), **legacy_offset(recorded), **recorded}


def write_config(run_dir: Path, config: RunConfig) -> None:
    write_json(run_dir / "config.json", config.to_json())


CHECKPOINT_FORMAT = "lunar_lander.checkpoint/1"


def load_run_config(run_dir: Path) -> RunConfig:
    """A run folder's config.json, every flag valid (check_run_config)."""
    recorded = read_run_json(run_dir, "config.json")  # its own error for a missing or bad file
    try:
        return check_run_config(recorded)
    except UsageError as error:
        raise UsageError(f"{run_dir / 'config.json'}: not a usable run config ({error})") from None


def load_checked_config(run_dir: Path) -> RunConfig:
    """What the results commands read of a run: its config.json, checked, and checked against the
    config its archive.npz was saved with, where it has one (an edit to another task of the same
    shape would go unseen by the archive's own checks). No pickle is read: the folder may be
    anyone's."""
    config = load_run_config(run_dir)
    if os.path.lexists(data := run_dir / "archive.npz"):
        recorded = recorded_config(data)  # an unreadable file says so itself
        try:
            saved = check_run_config(recorded)
        except UsageError as error:
            raise UsageError(f"{data}: archive data of an incompatible config ({error})") from None
        check_same_config(config, saved, run_dir, "archive.npz")
    return config


# Flags that config.json may hold apart from its checkpoint: resume writes a larger --iterations
# (and no --evaluations, which set the old ones) into config.json before the run's next
# checkpoint records it.
MAY_DIFFER = ("iterations", "evaluations")  # (--evaluations: the budget that set the iterations)


def load_run_state(run_dir: Path, trust: bool = False) -> tuple[RunConfig, dict | None]:
    """A run folder's config and checkpoint, which must agree (a hand edit of config.json is
    refused, not silently ignored). A run killed before its first checkpoint (while its cluster
    started) has only config.json: its checkpoint is None, and resume starts it afresh from that
    config, which records the seed, so it ends as the uninterrupted run would. The checkpoint is
    unpickled only if signed with the user's key, or `trust`ed (resume --trust)."""
    path, has_config = run_dir / "checkpoint.pkl", os.path.lexists(run_dir / "config.json")
    # lexists: a checkpoint (or config) that is there but no readable file, a link to nowhere or
    # to a device, is refused as such, never taken for none
    if os.path.lexists(path) or not has_config:
        checkpoint = load_checkpoint(path, trust)
        if has_config:
            check_same_config(load_run_config(run_dir), checkpoint["config"], run_dir)
        check_centroids(run_dir, checkpoint["scheduler"].result_archive)
        return checkpoint["config"], checkpoint
    return load_run_config(run_dir), None


def check_centroids(run_dir: Path, archive: Any) -> None:
    """A CVT run's centroids.npy must hold its archive's centroids: readers place its cells by
    that file, so a run whose file was edited or cut short is not continued."""
    path = run_dir / "centroids.npy"
    if not hasattr(archive, "centroids") or not os.path.lexists(path):
        return
    try:
        found = np.load(io.BytesIO(read_regular(path, "centroids.npy")), allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise UsageError(f"{path}: unreadable ({error}); it must hold the run's centroids") from None
    if found.shape != archive.centroids.shape or not np.array_equal(found, archive.centroids):
        raise UsageError(f"{path}: holds {'x'.join(map(str, found.shape))} values that are not the "
                         f"centroids of the run's archive ({archive.centroids.shape[0]} cells); "
                         f"delete it, and resume writes it again from the checkpoint")


def check_same_config(recorded: RunConfig, checkpointed: RunConfig, run_dir: Path,
                      source: str = "checkpoint") -> None:
    """config.json must say what the checkpoint (or the archive.npz: `source`) ran with: a run goes
    on as it started."""
    for name in SEARCH_FLAGS:
        said, ran = getattr(recorded, name), getattr(checkpointed, name)
        if name not in MAY_DIFFER and name not in CLUSTER_FLAGS and said != ran:
            raise UsageError(
                f"{run_dir / 'config.json'} says {named(name)} {shown(said)} but the run's "
                f"{source} ran with {shown(ran)}: a run goes on with the settings "
                f"it started with; undo the edit, or start a new run with the flags you want")


def check_archive(archive: Any, path: Path, config: RunConfig) -> None:
    """The archive must be the run's: its kind (--archive), solution size, cells and measure
    ranges."""
    kind = kind_of(archive)
    if kind != config.archive:
        raise UsageError(f"{path}: holds a {type(archive).__name__}, not the "
                         f"{ARCHIVES[config.archive]['class']} of the run's {named('archive')} "
                         f"{config.archive}")
    shape = archive_shape(config)
    if archive.solution_dim != shape["solution_dim"]:
        raise UsageError(f"{path}: its solutions have {archive.solution_dim} weights, but {named('env')} "
                         f"{config.env}'s policy has {shape['solution_dim']}: an archive of another "
                         f"task's run")
    lower, upper = zip(*shape["ranges"])
    cells = tuple(archive.dims) if kind == "grid" else archive.cells
    found = (cells, np.round(archive.lower_bounds, 9).tolist(), np.round(archive.upper_bounds, 9).tolist())
    expected = ((config.grid,) * len(config.measures) if kind == "grid" else config.cells,
                np.round(lower, 9).tolist(), np.round(upper, 9).tolist())
    if found != expected:
        size = f"{named('grid')} {config.grid}" if kind == "grid" else f"{named('cells')} {config.cells}"
        raise UsageError(f"{path}: archive of another shape (cells, lower and upper bounds {found}; "
                         f"the run's {named('measures')} {','.join(config.measures)} and {size} need "
                         f"{expected})")


def rewrite_hint(folder: Path, stem: str) -> str:
    """The command that writes a folder's stem.npz again: resume (from the run's checkpoint: a
    finished run is saved again) or evaluate --corrected."""
    if stem == "corrected_archive":
        return f"python lunar_lander.py evaluate {folder} --corrected writes it again"
    return (f"python lunar_lander.py resume {folder} --trust writes it again from the run's "
            f"checkpoint, if you trust that file")


def archive_source(folder: Path, stem: str = "archive") -> Path:
    """The file a run folder's archive is read from (stem: "archive", or evaluate's
    "corrected_archive"): stem.npz, or in a folder from before it, stem.csv; never stem.pkl."""
    for source in (folder / f"{stem}.npz", folder / f"{stem}.csv"):
        if os.path.lexists(source):  # one that is there but no readable file is refused as such
            return source
    why = (f"its {stem}.pkl is not opened (loading a pickle may run any code it holds); "
           if os.path.lexists(folder / f"{stem}.pkl") else f"is {folder} a run folder of lunar_lander.py? ")
    raise UsageError(f"{folder / stem}.npz: no such file, nor {stem}.csv; {why}"
                     + rewrite_hint(folder, stem))


def saved_archive(folder: Path, stem: str = "archive") -> Any:
    """A run folder's archive, made from its data file (archive_source), never from a pickle: a
    .csv on the cells of the folder's config.json (a CVT's: centroids.npy)."""
    source = archive_source(folder, stem)
    if source.suffix == ".npz":
        return read_archive_data(source)[0]
    config = load_run_config(folder)
    if config.archive == "cvt" and not os.path.lexists(folder / "centroids.npy"):
        raise UsageError(f"{folder / 'centroids.npy'}: no such file (the cells of the run's CVT "
                         f"archive); " + rewrite_hint(folder, stem))
    return archive_from_csv(source, empty_archive(config, folder / "centroids.npy"))


def load_archive(path: Path, config: RunConfig):
    """A saved archive, checked against the config of the run that uses it: a run folder's, or
    the one whose file is named (its archive.npz; an archive.pkl or .csv names the archive.npz
    beside it, or in a folder from before archive.npz, that folder's archive.csv)."""
    folder, stem = (path, "archive") if path.is_dir() else (path.parent, path.stem)
    archive = saved_archive(folder, stem)
    check_archive(archive, path, config)
    if len(archive) == 0:
        raise UsageError(f"{path}: the archive is empty; nothing to start from")
    return archive


def check_run_config(recorded: Any) -> RunConfig:
    """A run's config from what was recorded (config.json, a checkpoint, an archive's data),
    upgraded (`upgrade`) and with every value checked once (a UsageError says which is not)."""
    if not isinstance(recorded, dict):
        raise UsageError(f"holds a {type(recorded).__name__}, not the flags of a run")
    # A field this version does not know (a later version's flag) may change what the run flies:
    # refused, not dropped, so no command runs or reads a run other than the one recorded.
    if unknown := [name for name in recorded if name not in SEARCH_FLAGS and name not in RECORDS]:
        more = f" and {len(unknown) - 3} more" if len(unknown) > 3 else ""
        raise UsageError(f"holds {', '.join(map(shown, unknown[:3]))}{more}, not a field of this "
                         f"version's runs (written by a later version?)")
    config = upgrade(recorded)
    refuse_nulls(config)
    config.update(check_flags(SEARCH_FLAGS, {name: config[name] for name in SEARCH_FLAGS}))
    # A record names its archive and its cells (upgrade: those from before the flags); a search's
    # flags may leave them to the task (with_task).
    if config["archive"] is None or config[size := ARCHIVES[config["archive"]]["size"]] is None:
        raise UsageError(f"{named('archive' if config['archive'] is None else size)} is null")
    for field in dataclasses.fields(RunRecords):
        if config.get(field.name) is not None and not isinstance(config[field.name], RECORDS[field.name]):
            raise UsageError(f"{field.name} is {shown(config[field.name])}, not a {field.type}")
    return completed(config)


def refuse_nulls(config: dict[str, Any]) -> None:
    """A flag's value may be None only where None is its default (a check passes None on), and a
    path or an address (a flag with no check) is text."""
    for name, flag in SEARCH_FLAGS.items():
        if config[name] is None and flag.default is not None:
            raise UsageError(f"{named(name)} is null")
        if flag.check is None and not isinstance(config[name], (str, type(None))):
            raise UsageError(f"{named(name)} is {shown(config[name])}, not a path or an address")


def completed(config: dict[str, Any]) -> RunConfig:
    """The RunConfig of checked values, with what the flags make together made and checked once:
    the task's measures and archive, the policy's layers, the offset, the budget and the sizes."""
    config = with_offset(with_policy(with_task(config)))
    seed_number("seed", config["seed"])
    made = RunConfig(**{name: config[name] for name in SEARCH_FLAGS},
                     **{name: config[name] for name in RECORDS if config.get(name) is not None})
    check_sizes(made)
    return made


def load_checkpoint(path: Path, trust: bool = False) -> dict:
    """A checkpoint written by this script and consistent with this script's problem, unpickled
    only once its signature is found to be the user's (or they `trust` it: resume --trust)."""
    if not os.path.lexists(path):  # one that is there but no readable file is refused as such
        raise UsageError(f"{path}: no checkpoint there (is {path.parent} a run folder of lunar_lander.py?)")
    checkpoint = read_signed_pickle(path, "checkpoint", trust)
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise UsageError(f"{path}: not a lunar_lander checkpoint (holds a {type(checkpoint).__name__})")
    from ribs.schedulers import BanditScheduler, Scheduler

    try:
        checkpoint["config"] = check_run_config(checkpoint["config"])
        metrics, iteration = checkpoint["metrics"], checkpoint["iteration"]
        if not isinstance(checkpoint["scheduler"], (Scheduler, BanditScheduler)):
            raise UsageError(f"holds a {type(checkpoint['scheduler']).__name__}, not a Scheduler")
    except (KeyError, TypeError, UsageError) as error:
        raise UsageError(f"{path}: checkpoint of an incompatible config ({error})") from None
    if metrics:
        check_metrics(metrics, path)
    if [row["iteration"] for row in metrics if row["iteration"] > 0] != list(range(1, iteration + 1)):
        raise UsageError(f"{path}: its metrics do not match its iteration {iteration}")
    check_archive(checkpoint["scheduler"].result_archive, path, checkpoint["config"])
    return checkpoint


def search_config(flags: dict[str, Any], given: Collection[str] = (), path: Path | None = None) -> RunConfig:
    """The checked config a search runs with (nothing is written): its flags, or with --config
    (`path`) the file's settings with the flags `given` beside it in their place (settings_of);
    a seed drawn if none is set. Each value is checked once."""
    if path is not None:
        flags = settings_of(path, flags, given)
    # Fire reads a folder named 2024 as a number: a path flag is the text as typed.
    typed = {name: value if value is None or SEARCH_FLAGS[name].check else str(value)
             for name, value in flags.items()}
    flags = check_flags(SEARCH_FLAGS, typed)
    refuse_nulls(flags)
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    config = completed(flags)
    check_spaces(config.env)
    check_memory(config)  # after the sizes' own bounds (completed's)
    check_learning(config)
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
