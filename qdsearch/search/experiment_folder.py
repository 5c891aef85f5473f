"""An experiment folder as `compare`, `evaluate` and `resume` read it, apart from the runner that
writes it (experiments.py): experiment.json's format, its run states, and the label that names a
run's setting.

Map: EXPERIMENT_FORMAT, RUN_STATES; `run_setting` (a setting's label, shared by the
runs of an experiment and compare's groups), `shortened` (labels less what all settings share);
`read_experiment` (experiment.json checked, with its parts' states merged); `unfinished_note`
(what a reader of an unfinished plan is told).
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path
from typing import Any

from qdsearch.algorithms import ALGORITHMS
from qdsearch.base.flags import UsageError, shown
from qdsearch.base.run_files import read_run_json
from qdsearch.config.options import checked, ignores, own_flags, search_defaults, with_task
from qdsearch.config.run_config import upgrade
from qdsearch.config.settings import LABELLED, checked_settings, with_policy
from qdsearch.search.parts import merge_part_states, part_of

EXPERIMENT_FORMAT = "lunar_lander.experiment/1"


def run_setting(recorded: dict[str, Any]) -> str:
    """The label of a run's settings as recorded (config.json, or an experiment's plan): the
    algorithm with its own flags, and the other flags shaping it that differ from their
    defaults: runs of one setting with different seeds are repeats of one experiment. An
    algorithm's own flags are always named (cma_mae at 0.01 and at 0.5 are different algorithms
    in effect), so a label means the same whatever the defaults become."""
    defaults, changed = checked_settings(search_defaults()), []
    config = upgrade(recorded)  # a config.json from before a flag: what it ran with
    with contextlib.suppress(KeyError, TypeError, UsageError):  # measures: the task's default
        defaults = with_policy(with_task({**defaults, "env": config["env"]}))
        config = with_policy(with_task(config))
    algorithm = config.get("algorithm")
    own = own_flags(algorithm) if algorithm in ALGORITHMS else ()
    for flag in (flag for flag in LABELLED if flag in config):
        if algorithm in ALGORITHMS and ignores(algorithm, flag):
            continue
        with contextlib.suppress(UsageError):
            value = checked_settings({flag: config[flag]})[flag]  # 52 and [52]: one terrain
            if value is None:  # a flag of another archive kind (--grid of a CVT run)
                continue
            if value != defaults[flag] or flag in own:
                changed.append(f"{flag}={','.join(map(str, value)) if isinstance(value, list) else value}")
    return " ".join([str(config.get("algorithm", "?")), *changed])


def shortened(labels: list[str]) -> dict[str, str]:
    """Each of the settings' `labels` (run_setting's) less the flags every one of them names
    alike: the algorithm with its own flags, and what tells the settings apart (an experiment's
    folder names, compare's legend). Labels that differ keep a flag that tells them apart, so
    the short ones differ too."""
    settings = [label.split(" ") for label in dict.fromkeys(labels)]
    shared = set.intersection(*(set(words[1:]) for words in settings)) if settings else set()

    def kept(algorithm: str, word: str) -> bool:
        own = own_flags(algorithm) if algorithm in ALGORITHMS else ()
        return word not in shared or word.split("=", 1)[0] in own

    return {" ".join(words): " ".join([words[0], *(w for w in words[1:] if kept(words[0], w))])
            for words in settings}


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
                checked_settings({"seed": config.get("seed")})
        except UsageError as error:
            fits, why = False, f": {error}"
        else:
            why = ""
        if not fits:
            raise UsageError(f"{path}: run {i} is not a run of this experiment's plan{why}")
    if isinstance(plan.get("workers"), bool) or not isinstance(plan.get("workers"), int):
        raise UsageError(f"{path}: workers is {shown(plan.get('workers'))}, not a number of workers")
    if "parts" in plan:
        if isinstance(plan["parts"], bool) or not isinstance(plan["parts"], int) or not plan["parts"] >= 1:
            raise UsageError(f"{path}: parts is {shown(plan['parts'])}, not a number of parts")
        return merge_part_states(folder, plan, RUN_STATES)
    return plan


def unfinished_note(folder: Path, plan: dict) -> str | None:
    """What a comparison of an unfinished experiment should be told: its runs not done (and the
    parts that drive them), which of them are left out for want of metrics, and how to finish."""
    unfinished = [(index, entry) for index, entry in enumerate(plan["runs"]) if entry["state"] != "done"]
    if not unfinished:
        return None
    absent = [entry for _, entry in unfinished if not (folder / entry["name"] / "metrics.json").is_file()]
    named = ", ".join(f"{entry['name']} ({entry['state']})" for _, entry in unfinished[:6])
    parts = sorted({part_of(plan, index) for index, _ in unfinished} - {None})
    finish = (" and ".join(resume_command(folder, part, plan["parts"]) for part in parts) if parts
              else resume_command(folder))
    return (f"note: {folder}: {len(unfinished)} of {len(plan['runs'])} runs of its plan are not done: "
            f"{named}{', ...' if len(unfinished) > 6 else ''}; {len(absent)} of them have no metrics "
            f"and are left out, the others are compared as far as they got; finish with: {finish}")


def resume_command(folder: Path, part: int | None = None, parts: int | None = None) -> str:
    """The command that continues an experiment, or one part of it (`part` of `parts`)."""
    return f"python lunar_lander.py resume {folder}" + ("" if part is None else f" --part {part}/{parts}")
