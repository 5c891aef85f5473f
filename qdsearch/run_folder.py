"""What the results commands (video, elites, trajectories, evaluate, explore) read of a run
folder, in one place: its archive and config checked against each other, its elites in a fixed
order, and the terrain a command shows it on. They read archive.npz (archive_data.py), config.json
and metrics.json, never a pickle: a run folder from anyone is safe to open.

Map: `load_run`, `elite_rows`, `shown_terrain`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from qdsearch.flags import UsageError, check_flags
from qdsearch.options import TERRAIN_FLAGS
from qdsearch.run_config import RunConfig, archive_source, load_archive, load_checked_config


def load_run(run_dir: Any) -> tuple[Any, RunConfig]:
    """A run folder's archive (archive.npz; a folder from before it: archive.csv) and config,
    checked against each other. Folders written before --measures and --grid existed load with the
    tutorial's measures on a 50x50 grid."""
    path = Path(str(run_dir))
    if not path.is_dir():
        raise UsageError(f"{path}: no such run folder")
    archive_source(path)  # before the config: no archive is the fault to name
    config = load_checked_config(path)
    return load_archive(path / "archive.npz", config), config


def elite_rows(archive) -> dict[str, np.ndarray]:
    """Every elite (solution, objective, measures, index), best first; ties by cell index."""
    data = archive.data(["solution", "objective", "measures", "index"])
    order = np.lexsort((data["index"], -data["objective"]))
    return {field: values[order] for field, values in data.items()}


def shown_terrain(config: RunConfig, env_seed: Any) -> int:
    """The terrain a results command shows a run on: --env_seed, one of the run's terrains (its
    elites' objectives and measures were flown there), by default the run's first."""
    if env_seed is None:
        return config.env_seed[0]
    terrain = check_flags(TERRAIN_FLAGS, {"env_seed": env_seed})["env_seed"]
    if terrain not in config.env_seed:
        terrains = ",".join(map(str, config.env_seed))
        raise UsageError(f"--env_seed {terrain} is not a terrain of this run (it was flown on "
                         f"{terrains}); to fly its elites on other terrains, use: "
                         f"python lunar_lander.py evaluate RUN --env_seeds {terrain}")
    return terrain
