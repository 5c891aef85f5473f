"""Experiments: every combination of the listed settings with every seed, as ordinary run folders
inside one experiment folder, interleaved on one Dask cluster by one driving process.

A run's results depend on its own asks and tells only, so each run ends bit for bit as `search`
alone would end it, whatever the interleaving, the worker count or a stop and resume between.

Map:
- `experiment`: an experiment of its settings (ExperimentSettings) and the search flags it passes
  on, given or in a plan file (`read_plan`, and `with_plan`: a flag given beside the file wins);
  `experiment_grid` checks the grid's axes and the flags every run shares; `experiment_runs`
  names each run by its setting (`run_setting`, shared with compare);
- `run_experiment` and `Experiment`: the cluster, the log, and the runs driven through the one
  run loop (loop.py's Driver), their states recorded in experiment.json;
- `resume`: a run folder (run.resume_run) or an experiment folder (`resume_experiment`) taken
  on to a budget (ResumeSettings). experiment_folder.py reads experiment.json and labels settings.
An experiment may be split into parts (--part I/K), each driven by its own process: parts.py.
"""

from __future__ import annotations

import contextlib
import datetime
import itertools
import logging
import os
import re
import sys
import time
from pathlib import Path
from typing import Any, Collection

import numpy as np

from qdsearch.algorithms import ALGORITHMS
from qdsearch.base.flags import (
    UsageError,
    did_you_mean,
    listed,
    named,
    one_of,
    positive_int,
    seed_list,
    shown,
)
from qdsearch.base.run_files import (
    RunError,
    atomic_write,
    check_parent_folder,
    close_logger,
    fault_text,
    folder_lock,
    library_versions,
    make_logger,
    new_folder,
    read_regular,
    write_json,
)
from qdsearch.base.signing import adopt
from qdsearch.config.command_settings import (
    EXPERIMENT_OWN,
    ExperimentSettings,
    ResumeSettings,
    resumed_cluster,
)
from qdsearch.config.options import (
    check_learning,
    check_memory,
    check_sizes,
    checked,
    ignores,
    refuse_unused_row_flags,
    resumed_budget,
    search_defaults,
    with_budget,
    with_offset,
    with_task,
)
from qdsearch.config.run_config import check_run_config, load_run_state, upgrade, write_config
from qdsearch.config.settings import (
    BUDGETS,
    PASSED_ON,
    POLICY_FLAGS,
    SETTINGS,
    SWEEPS,
    ClusterSettings,
    checked_settings,
    for_policy,
    unchecked,
    with_policy,
)
from qdsearch.search.cluster import scheduler_of
from qdsearch.search.experiment_folder import (
    EXPERIMENT_FORMAT,
    read_experiment,
    resume_command,
    run_setting,
    shortened,
)
from qdsearch.search.loop import Driver
from qdsearch.search.parts import (
    claim_plan,
    parse_part,
    part_folder,
    part_of,
    runs_of_part,
    write_part_state,
)
from qdsearch.search.run import Run, resume_run, session, where_to_look
from qdsearch.tasks import check_spaces, scored_here

# Which settings an experiment passes on to every run (PASSED_ON; it sets the others per run) and
# which may take a list of values, one more axis of the grid (SWEEPS), is said by their entries in
# settings.py. (--env_seed and --measures take lists of their own: several terrains, several
# measures of every run.)


def experiment(own: ExperimentSettings, search_flags: dict[str, Any], cluster: ClusterSettings,
               given: Collection[str] = ()) -> None:
    """Run every combination of the settings `search_flags` list (values, or lists of values: axes
    of the grid) with every seed, interleaved on the cluster `cluster` names, into a new experiment
    folder (own.outdir), or drive one part of it (own.part). A plan file (own.plan) gives the
    experiment's flags and rows; each setting `given` beside it wins over the file's."""
    algorithms, seeds, outdir, max_in_flight = own.algorithms, own.seeds, own.outdir, own.max_in_flight
    part, plan = own.part, own.plan
    plan_text, rows = None, [{}]
    if plan is not None:
        plan_text, planned = read_plan(Path(str(plan)))
        rows = [without_given(row, given) for row in planned.pop(ROWS, [{}])]
        search_flags = with_plan(planned, {"algorithms": algorithms, "seeds": seeds,
                                           "max_in_flight": max_in_flight, **search_flags}, given)
        algorithms, seeds, max_in_flight = (search_flags.pop(name) for name in EXPERIMENT_OWN)
    own = [{k: v for k, v in row.items() if k != "algorithms"} for row in rows]
    grids = [experiment_grid(row.get("algorithms", algorithms), seeds, {**search_flags, **flags},
                             list(flags) if len(rows) > 1 else None) for row, flags in zip(rows, own)]
    if len(rows) > 1:  # the file's flags beside its rows: used by some row
        policies = [p for axes, common, _ in grids for p in axes.get("policy", [common["policy"]])]
        refuse_unused_row_flags([a for axes, _, _ in grids for a in axes["algorithm"]], list(search_flags),
                                policies)
    (axes, common, seeds), runs = grids[0], rows_runs(grids)
    workers = checked("workers", cluster.workers)
    limit = None if max_in_flight is None else positive_int("max_in_flight", max_in_flight)
    scheduler_address = scheduler_of(cluster)
    split = None if part is None else parse_part(part)

    def plan_of(parts: int | None) -> dict:
        return {"format": EXPERIMENT_FORMAT, "created": datetime.datetime.now().isoformat(),
                "command": sys.argv, "axes": axes, "seeds": seeds, "common": common,
                "workers": workers, "max_in_flight": limit, "versions": library_versions(),
                **({} if len(grids) == 1 else {ROWS: [{"axes": a, "common": c} for a, c, _ in grids]}),
                **({} if parts is None else {"parts": parts}), "runs": runs}

    if split is not None:
        if outdir is None:
            raise UsageError(f"{named('part')} needs {named('outdir')}: every part of an experiment names "
                             "the same folder")
        folder = Path(str(outdir))
        check_parent_folder(folder)
        if folder.exists() and not folder.is_dir():
            raise UsageError(f"{folder} exists and is not a folder; choose another {named('outdir')}")
        folder.mkdir(parents=True, exist_ok=True)
        claim_plan(folder, plan_of(split[1]))
        if plan_text is not None and not (folder / "plan.toml").exists():  # the first part's copy
            atomic_write(folder / "plan.toml", lambda f: f.write(plan_text), mode="w")
        return resume_experiment(folder, ResumeSettings(None, None, workers, False), cluster, split)
    with new_folder(outdir, "experiment") as folder:
        if plan_text is not None:
            atomic_write(folder / "plan.toml", lambda f: f.write(plan_text), mode="w")
        record = plan_of(None)
        write_json(folder / "experiment.json", record)
        run_experiment(folder, record, workers, scheduler_address)


ROWS = "rows"  # a plan's [[rows]]: grids of their own, each with its algorithms and flags


def without_given(row: dict[str, Any], given: Collection[str]) -> dict[str, Any]:
    """A plan's table (the file's, or a row's) less the flags given beside the file: they replace
    its values, and a budget given its budget."""
    dropped = {*given, *(BUDGETS if set(BUDGETS) & set(given) else ())}
    return {name: value for name, value in row.items() if name not in dropped}


def rows_runs(grids: list[tuple[dict, dict, list[int]]]) -> list[dict]:
    """The runs of every row's grid, in the rows' order; two rows that make one setting are
    refused (a run would be planned twice)."""
    runs: list[dict] = []
    for row, (axes, common, seeds) in enumerate(grids, 1):
        made = grid_runs(axes, common, seeds)
        if twice := {entry["setting"] for entry in made} & {entry["setting"] for entry in runs}:
            raise UsageError(f"{named('plan')}: row {row} makes the setting {min(twice)!r} that an earlier "
                             f"row makes too")
        runs += made
    return with_folder_names(runs)


def with_plan(planned: dict[str, Any], flags: dict[str, Any], given: Collection[str]) -> dict[str, Any]:
    """An experiment's flags (its own of EXPERIMENT_OWN and those it passes on) from its plan
    file: the file's, each flag `given` beside it in the file's place, whatever its value (a
    budget given, --iterations or --evaluations, in place of the file's budget)."""
    return {**flags, **without_given(planned, given)}


def read_plan(path: Path) -> tuple[str, dict[str, Any]]:
    """A plan file (TOML: Python reads it without a library, and its lists and numbers are typed
    as the flags are): its text, and its flags, each name known (the values are checked as
    flags typed on the command line are)."""
    import tomllib

    try:  # only a regular file within its bound: a link to a device is refused, unread
        text = read_regular(path, "plan").decode()
        planned = tomllib.loads(text)
    except UsageError as error:
        raise UsageError(f"{named('plan')} {error}") from None
    except UnicodeDecodeError as error:
        raise UsageError(f"{named('plan')} {path}: cannot read it ({fault_text(error)})") from None
    except tomllib.TOMLDecodeError as error:
        raise UsageError(f"{named('plan')} {path}: not TOML ({error})") from None
    check_plan_flags(path, planned, [*EXPERIMENT_OWN, *PASSED_ON, ROWS], "")
    rows = planned.get(ROWS, [{}])
    if not (isinstance(rows, list) and rows and all(isinstance(row, dict) for row in rows)):
        raise UsageError(f"{named('plan')} {path}: {ROWS} must be [[{ROWS}]] tables, each a grid's flags")
    for i, row in enumerate(rows, 1):
        check_plan_flags(path, row, ["algorithms", *PASSED_ON], f"[[{ROWS}]] {i}: ")
    return text, planned


def check_plan_flags(path: Path, flags: dict[str, Any], known: list[str], where: str) -> None:
    """Every name of a plan's table is a flag it may hold, with a value or a list of values."""
    for name, value in flags.items():
        if name not in known:
            raise UsageError(f"{named('plan')} {path}: {where}{shown(name)} is not a flag of experiment"
                             f"{' a row may set' if where else ''}; {did_you_mean(name, known)}")
        if isinstance(value, dict) or (name != ROWS and isinstance(value, list)
                                       and any(isinstance(v, dict) for v in value)):
            raise UsageError(f"{named('plan')} {path}: {where}{name} is a table; give a value or a list of "
                             "values")


def experiment_grid(algorithms: Any, seeds: Any, search_flags: dict,
                    own_flags: list[str] | None = None) -> tuple[dict, dict, list[int]]:
    """The grid's axes (algorithm first, then each swept flag), the flags every run shares and
    the seeds, each value checked as search checks it. A row's own flag (cma_mae's
    --learning_rate) must be of an algorithm of the grid: of `own_flags` (a plan's row's), or of
    every flag given."""
    if given := sorted(set(search_flags) - set(PASSED_ON) & set(SETTINGS)):
        raise UsageError(f"{named(given[0])} is set by the experiment for each run; use "
                         f"{named('algorithms')}, "
                         f"{named('seeds')}, {named('outdir')}, {named('workers')} and "
                         f"{named('scheduler_address')} (or {named('scheduler_file')}) "
                         f"of experiment")
    if unknown := sorted(set(search_flags) - set(search_defaults())):
        raise UsageError(f"unknown flag {named(unknown[0])}; "
                         f"{did_you_mean(unknown[0], PASSED_ON, named(''))}")
    names = listed(algorithms)
    if not names:
        raise UsageError(f"{named('algorithms')} is empty: the grid has no run")
    axes = {"algorithm": [one_of(ALGORITHMS)("algorithms", name) for name in names]}
    common = {name: search_defaults()[name] for name in PASSED_ON}
    for name, value in search_flags.items():
        if name in SWEEPS and isinstance(value, (list, tuple)):
            if not value:
                raise UsageError(f"{named(name)} is an empty list: the grid has no run")
            axes[name] = [checked_settings({name: v})[name] for v in value]
        else:
            common[name] = value
    checked_flags = checked_settings(common)
    # With --policy an axis, a policy's own flags (--hidden) are each setting's to take or leave
    # (for_policy), as an algorithm's own are each run's (ignores).
    swept = {flag: checked_flags[flag] for flag in POLICY_FLAGS} if "policy" in axes else {}
    common = {**with_policy(with_task({**checked_flags, **dict.fromkeys(swept)})), **swept}
    check_spaces(common["env"])
    for setting in itertools.product(*axes.values()):  # each run's archive and memory too (swept --cells)
        config = with_policy(with_task(for_policy({**common, **dict(zip(axes, setting))})))
        each = unchecked(config)  # its flags checked, its config whole but for the per-run flags
        check_sizes(each)
        check_memory(each)
        check_learning(each)
    refuse_unused_row_flags(axes["algorithm"],  # given here: flags the user set
                            list(search_flags) if own_flags is None else own_flags,
                            axes.get("policy", [common["policy"]]))
    return axes, common, seed_list("seeds", seeds)


def experiment_runs(axes: dict, common: dict, seeds: list[int]) -> list[dict]:
    """One entry per (setting, seed): its folder name, setting label, config and state."""
    return with_folder_names(grid_runs(axes, common, seeds))


def with_folder_names(runs: list[dict]) -> list[dict]:
    """The runs with their settings' labels shortened to what tells the settings apart
    (experiment_folder.shortened), and each its folder name: its setting's label and seed."""
    short = shortened([entry["setting"] for entry in runs])
    return [{"name": re.sub(r"[^A-Za-z0-9.]+", "_", short[entry["setting"]]) + f"_seed{entry['seed']}",
             **entry, "setting": short[entry["setting"]]} for entry in runs]


def grid_runs(axes: dict, common: dict, seeds: list[int]) -> list[dict]:
    """One entry per (setting, seed) of a grid: its setting's whole label, seed, config, state."""
    runs, settings = [], []
    for values in itertools.product(*axes.values()):
        setting = {flag: common.get(flag) if ignores(values[0], flag) else value
                   for flag, value in zip(axes, values)}
        if setting not in settings:  # cma_me at two learning rates is one setting
            settings.append(setting)
    for setting in settings:
        for seed in seeds:
            # its iterations, of --evaluations; none of the flags its policy ignores
            config = with_offset(with_budget(for_policy({**common, **setting, "seed": seed})))
            runs.append({"setting": run_setting(config), "seed": seed, "config": config, "state": "pending"})
    return runs


def run_experiment(folder: Path, plan: dict, workers: int, scheduler_address: str | None,
                   part: int | None = None) -> None:
    """The cluster and the log of an experiment (or of one part of it), shut down however it
    ends (run.session: a stop or a fault is one line that says how to continue)."""
    where = folder if part is None else part_folder(folder, part, plan["parts"])
    again = resume_command(folder, part, plan.get("parts"))
    owned = len(runs_of_part(plan, part))
    opening = (f"Experiment folder: {folder}: {len(plan['runs'])} runs "
               f"({len(plan['runs']) // len(plan['seeds'])} settings x {len(plan['seeds'])} seeds)"
               + ("" if part is None else f"; part {part} of {plan['parts']}: {owned} of them"))
    drawing = any(upgrade(entry["config"])["pictures"] for entry in runs_of_part(plan, part))
    local = all(scored_here(upgrade(entry["config"])["env"]) for entry in runs_of_part(plan, part))
    stopped = f"every run keeps its last checkpoint; continue with: {again}"
    log_path = where / ("experiment.log" if part is None else "part.log")
    with session(log_path, opening, workers, scheduler_address, lambda flags: stopped + flags, (RunsFailed,),
                 drawing=drawing, local=local) as (client, log):
        Experiment(folder, plan, client, log, part).drive()


class RunsFailed(RunError):
    """Some runs of an experiment failed (each recorded with its cause); the others finished."""


# How often at most the runs' states are written while they go on (experiment.json holds every
# run's entry: megabytes for thousands of runs, too much to write at each run's change).
STATES_EVERY_S = 5.0


class Experiment(Driver):
    """The runs of an experiment folder, driven on one client through the one run loop (loop.py):
    each opened from its checkpoint or its config, its state recorded in experiment.json (once
    per batch of runs opened, at most every STATES_EVERY_S while they go on, and at the end), a
    run's fault its own (recorded; the others go on), a line per setting every log_every
    iterations of every run. With `part`, only the runs of that part, their states in its own
    state file (parts.py).

    A state written late loses nothing after kill -9: a run's folder holds what it did (resume
    opens an unfinished run from its checkpoint, or from its config, in a folder made but not
    recorded, and closes a finished run not yet recorded done); only `done` makes resume skip a run,
    and it is noted once the run's last save is written."""

    desc, isolated = "experiment", True

    def __init__(self, folder: Path, plan: dict, client, log: logging.Logger,
                 part: int | None = None) -> None:
        self.parts = {entry["name"]: part_of(plan, index) for index, entry in enumerate(plan["runs"])}
        runs = runs_of_part(plan, part)
        super().__init__(
            client, log, [entry for entry in runs if entry["state"] != "done"],
            total=sum(entry["config"]["iterations"] for entry in runs),
            done=sum(entry["config"]["iterations"] for entry in runs if entry["state"] == "done"),
            limit=plan.get("max_in_flight"), every=plan["common"]["log_every"] * len(runs))
        self.folder, self.plan, self.part, self.runs = folder, plan, part, runs
        self.unsaved: set[int | None] = set()  # the parts whose noted states are not written yet
        self.saved_at = time.monotonic()

    def save_states(self, parts: set[int | None]) -> None:
        """The states of these parts' runs where they are kept: experiment.json, or (a split
        experiment) each part's own state file."""
        for part in parts:
            if part is None:
                write_json(self.folder / "experiment.json", self.plan)
            else:
                write_part_state(self.folder, self.plan, part)

    def drive(self) -> None:
        runs = self.runs
        wall, cpu = time.perf_counter(), time.process_time()
        super().drive()
        # The driving loop's own cost: how much of a core the main process took while it ran.
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        timing = {"drive_s": round(wall, 3), "main_cpu_s": round(cpu, 3), "iterations": self.told}
        parts = {self.parts[entry["name"]] for entry in runs}
        for part in parts:
            record = self.plan if part is None else self.plan.setdefault("part_records", {}).setdefault(
                str(part), {})
            record["timing"] = timing
        self.save_states(parts)
        failed = [e["name"] for e in runs if e["state"] == "failed"]
        self.log.info(f"Done: {len(runs) - len(failed)} of {len(runs)} runs finished in {self.folder} "
                      f"({wall:.1f} s, main process {cpu / max(wall, 1e-9):.0%} of a core)")
        if failed:
            which = (f"{len(failed)} of {len(runs)} runs failed ({', '.join(failed)})"
                     if len(failed) < len(runs) else
                     "its only run failed" if len(runs) == 1 else f"all {len(runs)} runs failed")
            others = "" if len(failed) == len(runs) else "; the others finished"
            where = self.folder / ("experiment.json" if self.part is None else
                                   part_folder(self.folder, self.part, self.plan["parts"]) / "state.json")
            again = resume_command(self.folder, self.part, self.plan.get("parts"))
            raise RunsFailed(f"{which}: their causes are in {where}{others}. "
                             f"Mend the cause and retry them with: {again}")

    def open(self, entry: dict) -> Run:
        """A run's folder (made on first use), locked, and its run from checkpoint or config."""
        run_dir = self.folder / entry["name"]
        run_dir.mkdir(exist_ok=True)
        leaving = contextlib.ExitStack()
        leaving.enter_context(folder_lock(run_dir))
        try:
            if not os.path.lexists(run_dir / "config.json"):  # one that is there but unreadable: refused
                write_config(run_dir, check_run_config({
                    **entry["config"], "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
                    "command": self.plan["command"], "experiment": str(self.folder),
                    "versions": library_versions()}))
            config, checkpoint = load_run_state(run_dir)
            if config.iterations < entry["config"]["iterations"]:  # the experiment was extended
                config = config.replace(iterations=entry["config"]["iterations"], evaluations=None)
                write_config(run_dir, config)
            log = make_logger(run_dir / "run.log", f"lunar_lander.run.{entry['name']}", console=False)
            leaving.callback(close_logger, log)
            run = (Run.start(run_dir, config, self.client, log) if checkpoint is None
                   else Run.from_checkpoint(run_dir, {**checkpoint, "config": config}, log))
        except BaseException:
            leaving.close()
            raise
        run.leaving = leaving
        return run

    def record(self, entry: dict, state: str, error: BaseException | None = None) -> None:
        """A run's new state, noted; `flush` writes it."""
        entry["state"] = state
        if error is not None:
            entry["error"] = fault_text(error) if isinstance(error, (OSError, RunError)) else (
                f"{type(error).__name__}: {fault_text(error)}")
        else:
            entry.pop("error", None)
        self.unsaved.add(self.parts[entry["name"]])

    def flush(self, due_only: bool = False) -> None:
        """The noted states, in experiment.json (or the parts' state files): with `due_only`, only
        once STATES_EVERY_S have passed since the last write."""
        if self.unsaved and not (due_only and time.monotonic() - self.saved_at < STATES_EVERY_S):
            self.save_states(self.unsaved)  # a write that fails leaves them noted
            self.unsaved, self.saved_at = set(), time.monotonic()

    def figures(self, row: dict) -> dict[str, str]:
        """The experiment's own figures on its bar: runs finished of its runs, and the best
        objective over every run told so far (not the figures of whichever run told last)."""
        finished = sum(entry["state"] == "done" or self.latest.get(entry["name"], {}).get("iteration", -1)
                       >= entry["config"]["iterations"] for entry in self.runs)
        bests = [r["best_objective"] for r in self.latest.values() if r.get("best_objective") is not None]
        best = max(bests, default=float("nan"))
        return {"runs_done": f"{finished}/{len(self.runs)}", "best": f"{best:.1f}"}

    def lines(self) -> list[str]:
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


def resume(path: Path, budget: ResumeSettings, cluster: ClusterSettings, part: str | None = None) -> None:
    """Continue the run in `path` from its checkpoint (run.resume_run), or, for an experiment
    folder, every unfinished run of the experiment (of its part `part`, I/K)."""
    if (path / "experiment.json").is_file():
        split = None if part is None else parse_part(part)
        return resume_experiment(path, budget, cluster, split)
    if part is not None:
        raise UsageError(f"{named('part')} is for an experiment folder; {path} is a run")
    print(where_to_look(path, resume_run(path, budget, cluster)))


def check_split(plan: dict, folder: Path, split: tuple[int, int] | None, iterations: int | None) -> None:
    """--part names a part of the experiment's own split; a split plan, written once, is fixed."""
    if split is not None and plan.get("parts") != split[1]:
        raise UsageError(f"{named('part')} {split[0]}/{split[1]}: {folder} is " + (
            f"split in {plan['parts']} parts" if plan.get("parts") else "not split in parts"))
    if plan.get("parts") and iterations is not None:
        raise UsageError(f"the plan of {folder}, split in parts, is fixed: {named('iterations')} cannot "
                         f"extend it; start a new experiment")


def resume_experiment(folder: Path, budget: ResumeSettings, cluster: ClusterSettings,
                      split: tuple[int, int] | None = None) -> None:
    """Continue every unfinished run of an experiment, or of one part of it (failed ones are
    tried again), on the cluster the `cluster` flags name (by default a local one). A part locks
    its own folder; the whole of a split experiment locks every part's. With --trust, the
    checkpoints of its unfinished runs are signed with the user's key first."""
    iterations, evaluations, workers = budget.iterations, budget.evaluations, budget.workers
    check_split(read_experiment(folder), folder, split, iterations or evaluations)  # before any write
    scheduler_address = scheduler_of(resumed_cluster(budget, cluster))
    with contextlib.ExitStack() as locks:
        plan = read_experiment(folder)
        parts = [split[0]] if split else list(range(1, plan["parts"] + 1)) if plan.get("parts") else []
        for part in parts:
            where = part_folder(folder, part, plan["parts"])
            where.mkdir(parents=True, exist_ok=True)
            locks.enter_context(folder_lock(where))
        if not parts:
            locks.enter_context(folder_lock(folder))
        plan = read_experiment(folder)  # as it is now that no other process writes it
        mine = runs_of_part(plan, split[0] if split else None)
        for entry in mine if budget.trust else []:
            if entry["state"] != "done":
                adopt(folder / entry["name"] / "checkpoint.pkl")
        workers = checked("workers", plan["workers"] if workers is None else workers)
        planned = max(entry["config"]["iterations"] for entry in plan["runs"])
        for entry in plan["runs"] if iterations is not None or evaluations is not None else []:
            budget = resumed_budget(upgrade(entry["config"]), iterations, evaluations)
            if budget["iterations"] < entry["config"]["iterations"]:
                given = (f"{named('evaluations')} {evaluations:,}" if evaluations
                         else f"{named('iterations')} {iterations:,}")
                raise UsageError(f"{entry['name']} of {folder} goes to iteration "
                                 f"{entry['config']['iterations']:,}; {given} would end it sooner")
            if budget["iterations"] > entry["config"]["iterations"]:
                entry["config"].update(iterations=budget["iterations"], evaluations=budget["evaluations"])
                entry["state"] = "pending"
        which = f"part {split[0]} of {split[1]} of {folder}" if split else str(folder)
        if all(entry["state"] == "done" for entry in mine):
            print(f"nothing to do: all {len(mine)} runs of {which} are done (iteration "
                  f"{planned})" + ("" if plan.get("parts") else f"; {named('iterations')} N extends them"))
            return
        resumed = {"at": datetime.datetime.now().isoformat(), "iterations": iterations, "workers": workers}
        if not plan.get("parts"):
            plan["resumed"] = [*plan.get("resumed", []), resumed]
            write_json(folder / "experiment.json", plan)
        for part in parts:
            record = plan["part_records"].setdefault(str(part), {})
            record["drives"] = [*record.get("drives", []), resumed]
            write_part_state(folder, plan, part)
        run_experiment(folder, plan, workers, scheduler_address, split[0] if split else None)
