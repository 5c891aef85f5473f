"""An experiment split into parts, each driven by its own process and, if wanted, its own Dask
scheduler: the elements of a SLURM job array, say (docs/clusters.md).

Which runs a part owns is fixed by the plan, never by timing: run i of the plan belongs to part
i mod K + 1, so every part gets its share of every setting (the settings differ in cost). The
plan, experiment.json, is written once, by whichever part comes first, with a hard link: that
creates a file only if it is absent, atomically, on a local disk and on NFS alike (where flock
may not hold). Each part records its runs' states in its own file, parts/I_of_K/state.json, and
logs to parts/I_of_K/part.log, so no two processes ever write one file. Reading an experiment
merges the parts' states into its plan, so `resume` and `compare` see the whole experiment.

Map:
- `parse_part` (--part I/K), `part_of` (the part a run belongs to), `runs_of_part`, `part_folder`;
- `claim_plan`: experiment.json created once, or the same plan found there;
- `write_part_state`, `merge_part_states`.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

from qdsearch.base.flags import UsageError, named, shown
from qdsearch.base.run_files import read_run_json, write_json

MAX_PARTS = 10_000
PART_FORMAT = "lunar_lander.experiment-part/1"
# What two parts' plans must agree on to be parts of one experiment (with each run's name and
# config); the command, the time and the library versions may differ.
PLAN_IDENTITY = ("format", "axes", "seeds", "common", "rows", "parts", "max_in_flight")


def parse_part(value: Any) -> tuple[int, int]:
    """--part I/K: part I of K, 1 <= I <= K."""
    match = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", str(value))
    if isinstance(value, bool) or not match:
        raise UsageError(f"{named('part')} must be I/K (part I of K), e.g. 3/15; got {shown(value)}")
    part, parts = int(match[1]), int(match[2])
    if not 1 <= part <= parts <= MAX_PARTS:
        raise UsageError(f"{named('part')} {part}/{parts}: I must be from 1 to K, and K at most "
                         f"{MAX_PARTS:,}")
    return part, parts


def part_of(plan: dict, index: int) -> int | None:
    """The part that drives run `index` of the plan (None: an experiment not split)."""
    return index % plan["parts"] + 1 if plan.get("parts") else None


def runs_of_part(plan: dict, part: int | None) -> list[dict]:
    """The runs of the plan that `part` drives (None: the whole experiment, unsplit)."""
    return [entry for index, entry in enumerate(plan["runs"]) if part in (None, part_of(plan, index))]


def part_folder(folder: Path, part: int, parts: int) -> Path:
    """A part's own folder: its state file, its log, its lock."""
    return folder / "parts" / f"{part}_of_{parts}"


def identity(plan: dict) -> dict:
    """What makes two plans one experiment, as JSON reads it back (lists, not tuples)."""
    return json.loads(json.dumps({**{key: plan.get(key) for key in PLAN_IDENTITY},
                                  "runs": [(entry["name"], entry["config"]) for entry in plan["runs"]]}))


def claim_plan(folder: Path, plan: dict) -> None:
    """experiment.json holds `plan`: written now if absent (by a hard link from a whole temporary
    file, so a reader never sees half of it and two parts starting at once write it once), or
    found there, made with the same flags, by another part."""
    target = folder / "experiment.json"
    if not target.exists():
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".experiment.json.", suffix=".tmp")
        try:
            with os.fdopen(fd, "w") as file:
                json.dump(plan, file, indent=2)
                file.flush()
                os.fsync(file.fileno())
            with contextlib.suppress(FileExistsError):
                os.link(tmp, target)
        finally:
            os.unlink(tmp)
    found = read_run_json(folder, "experiment.json")
    try:
        same = identity(found) == identity(plan)
    except (AttributeError, KeyError, TypeError):  # not a plan at all
        same = False
    if not same:
        raise UsageError(f"{folder} holds another experiment (another plan than these flags make); "
                         f"give every part the same flags, or choose another {named('outdir')}")


def write_part_state(folder: Path, plan: dict, part: int) -> None:
    """The states of the runs `part` owns (and its timing and drives), in its own state file."""
    runs = {entry["name"]: {key: entry[key] for key in ("state", "error") if key in entry}
            for entry in runs_of_part(plan, part)}
    record = plan.setdefault("part_records", {}).get(str(part), {})
    write_json(part_folder(folder, part, plan["parts"]) / "state.json",
               {"format": PART_FORMAT, "part": part, "parts": plan["parts"], "runs": runs, **record})


def merge_part_states(folder: Path, plan: dict, states: tuple[str, ...]) -> dict:
    """The plan with each part's recorded states (a part not started yet: its runs pending), each
    state file checked: of this plan's parts, naming only runs its part owns, in known states."""
    owner = {entry["name"]: part_of(plan, index) for index, entry in enumerate(plan["runs"])}
    entries = {entry["name"]: entry for entry in plan["runs"]}
    plan["part_records"] = {}
    for part in range(1, plan["parts"] + 1):
        path = part_folder(folder, part, plan["parts"]) / "state.json"
        if not path.is_file():
            continue
        recorded = read_run_json(path.parent, path.name)
        runs = recorded.get("runs") if isinstance(recorded, dict) else None
        if not (isinstance(runs, dict) and recorded.get("format") == PART_FORMAT
                and recorded.get("part") == part and recorded.get("parts") == plan["parts"]
                and all(owner.get(name) == part and isinstance(state, dict) and state.get("state") in states
                        for name, state in runs.items())):
            raise UsageError(f"{path}: not the state of part {part} of {plan['parts']} of this experiment")
        for name, state in runs.items():
            entries[name]["state"] = state["state"]
            entries[name].pop("error", None)
            if isinstance(state.get("error"), str):
                entries[name]["error"] = state["error"]
        plan["part_records"][str(part)] = {key: recorded[key] for key in ("timing", "drives")
                                           if key in recorded}
    return plan
