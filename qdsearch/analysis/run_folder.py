"""What the results commands (video, elites, trajectories, evaluate, explore) read of a run
folder, in one place: its archive and config checked against each other, its elites in a fixed
order, and the terrain a command shows it on. They read archive.npz (archive_data.py), config.json
and metrics.json, never a pickle: a run folder from anyone is safe to open.

Map: `load_run` (`refuse_an_experiment`), `elite_rows`, `shown_terrain`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from qdsearch.base.flags import UsageError, named
from qdsearch.config.run_config import RunConfig, archive_source, load_archive, load_checked_config
from qdsearch.tasks import ENVIRONMENTS


def load_run(run_dir: Any) -> tuple[Any, RunConfig]:
    """A run folder's archive (archive.npz; a folder from before it: archive.csv) and config,
    checked against each other. Folders written before --measures and --grid existed load with the
    tutorial's measures on a 50x50 grid."""
    path = Path(str(run_dir))
    if not path.is_dir():
        raise UsageError(f"{path}: no such run folder")
    refuse_an_experiment(path)  # before the archive: its absence would send the user to resume
    archive_source(path)  # before the config: no archive is the fault to name
    config = load_checked_config(path)
    return load_archive(path / "archive.npz", config), config


SHOWN_RUNS = 3  # the run folders an experiment folder's refusal names


def refuse_an_experiment(path: Path) -> None:
    """An experiment folder (experiment.json) given for a run: one line that says so and names its
    run folders that have started, to pass one of instead."""
    if not (path / "experiment.json").is_file():
        return
    runs = sorted(run for run in path.iterdir() if (run / "config.json").is_file())
    if not runs:
        raise UsageError(f"{path}: an experiment folder, not a run folder, and none of its runs has "
                         f"started; start them with: python lunar_lander.py resume {path}")
    more = ", ..." if len(runs) > SHOWN_RUNS else ""
    raise UsageError(f"{path}: an experiment folder, not a run folder; give one of its {len(runs)} "
                     f"run folders: {', '.join(map(str, runs[:SHOWN_RUNS]))}{more}")


def elite_rows(archive) -> dict[str, np.ndarray]:
    """Every elite (solution, objective, measures, index), best first; ties by cell index."""
    data = archive.data(["solution", "objective", "measures", "index"])
    order = np.lexsort((data["index"], -data["objective"]))
    return {field: values[order] for field, values in data.items()}


def shown_terrain(config: RunConfig, env_seed: int | None) -> int:
    """The terrain (a seed, as the task's family calls it) a results command shows a run on:
    --env_seed, one of the run's (its elites' objectives and measures were flown there), by
    default the run's first (a Terrain's env_seed, checked)."""
    if (terrain := env_seed) is None:
        return config.env_seed[0]
    if terrain not in config.env_seed:
        terrains, noun = ",".join(map(str, config.env_seed)), ENVIRONMENTS[config.env].family.seed_noun
        raise UsageError(f"{named('env_seed')} {terrain} is not a {noun} of this run (it was flown on "
                         f"{terrains}); to fly its elites on other {noun}s, use: "
                         f"python lunar_lander.py evaluate RUN --env_seeds {terrain}")
    return terrain
