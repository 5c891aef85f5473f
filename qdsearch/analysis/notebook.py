"""Run folders as pandas tables, for a notebook: the package's public API (`qdsearch.read_run`,
`qdsearch.read_experiment`, `qdsearch.fly_elite`). Nothing here unpickles: a run is read from its
config.json, archive.csv and metrics.json, so a folder from anyone is safe to open.

Map: `RunData` (a run's config, archive and metrics), `read_run`, `read_experiment`;
`EliteFlight`, `fly_elite` (an elite's policy rebuilt and flown as its search flew it).
"""

from __future__ import annotations

import dataclasses
import io
import os
from pathlib import Path
from typing import Any

from qdsearch.base.flags import UsageError
from qdsearch.base.run_files import read_regular
from qdsearch.config.run_config import check_run_config, load_run_config
from qdsearch.search.experiment_folder import read_experiment as read_plan
from qdsearch.store.metrics import load_metrics
from qdsearch.tasks import episode_of, make_env, reset_seeds
from qdsearch.tasks.policies import rollout


@dataclasses.dataclass
class RunData:
    """A run folder, read: its settings (config.json, every flag, as the run recorded them), its
    archive (pyribs' ArchiveDataFrame of archive.csv: one row per elite, with its index,
    objective, measures_* and solution_* columns, and each measure's column again under the
    measure's name, as `run.archive["fuel"]`) and its metrics (one row per iteration logged:
    QD score, coverage, evaluations, ...). `setting` labels an experiment's run as compare does."""

    folder: Path
    config: dict[str, Any]
    archive: Any
    metrics: Any
    setting: str | None = None


def read_run(folder: Any) -> RunData:
    """A run folder written by lunar_lander.py, as tables: `run.archive.get_field("objective")`,
    `run.metrics.plot(x="evaluations", y="qd_score")`, `run.config["algorithm"]`."""
    import pandas as pd
    from ribs.archives import ArchiveDataFrame

    path = Path(str(folder))
    config = load_run_config(path).to_json()  # a missing folder or config is a UsageError saying so
    if not os.path.lexists(table := path / "archive.csv"):
        raise UsageError(f"{table}: no such file; has the run saved yet?")
    try:  # a link to a device, a folder or a file beyond any run's is refused as such, unread
        archive = ArchiveDataFrame(pd.read_csv(io.BytesIO(read_regular(table, "archive.csv"))))
    except ValueError as error:
        raise UsageError(f"{table}: unreadable ({error}); has the run saved yet?") from None
    # each measure by its name, after pyribs' own columns (its fields), joined at once: added one
    # at a time to a point's hundred columns and more, they would fragment the frame
    named = pd.DataFrame({name: archive[f"measures_{i}"] for i, name in enumerate(config["measures"])})
    archive = ArchiveDataFrame(pd.concat([archive, named], axis=1))
    return RunData(path, config, archive, pd.DataFrame(load_metrics(path)))


def read_experiment(folder: Any) -> list[RunData]:
    """Every run of an experiment folder that has saved (in the plan's order), each with its
    setting: `pd.concat([r.metrics.assign(setting=r.setting, seed=r.config["seed"]) for r in
    runs])` is every curve of the experiment in one table."""
    path = Path(str(folder))
    if (path / "config.json").is_file() and not (path / "experiment.json").is_file():
        raise UsageError(f"{path}: a run folder, not an experiment folder (it has config.json, no "
                         f"experiment.json); read it with qdsearch.read_run({str(path)!r})")
    runs = []
    for entry in read_plan(path)["runs"]:
        if os.path.lexists(path / entry["name"] / "archive.csv"):  # there: read, or refused as what it is
            run = read_run(path / entry["name"])
            runs.append(dataclasses.replace(run, setting=entry["setting"]))
    return runs


@dataclasses.dataclass(frozen=True)
class EliteFlight:
    """An elite flown again: its objective and each measure (by name) as the archive holds them,
    the mean over its episodes, and each episode's own (a row per reset seed)."""

    objective: float
    measures: dict[str, float]
    episodes: Any  # a pandas DataFrame: reset_seed, objective, then a column per measure


def fly_elite(run: Any, elite: int) -> EliteFlight:
    """Rebuild the policy of the elite in row `elite` of `run.archive` (a RunData, or its folder)
    and fly it as its search did: on each of the run's resets, by its episode's rules. Every task
    here is deterministic, so its objective and measures are the archive's, bit for bit:
    `qdsearch.fly_elite(run, run.archive["objective"].idxmax())`."""
    import numpy as np
    import pandas as pd

    data = run if isinstance(run, RunData) else read_run(run)
    config = check_run_config(data.config)
    solution = np.asarray(data.archive.get_field("solution")[elite], dtype=np.float64)
    measures = tuple(config.measures)
    env = make_env(config.fast_env, env_name=config.env, episode=episode_of(config))
    seeds = [int(seed) for seed in reset_seeds(solution[None], config)[0]]
    rows = [rollout(solution, seed, env, measures, env_name=config.env, policy=config.network)
            for seed in seeds]
    env.close()
    episodes = pd.DataFrame(rows, columns=["objective", *measures]).assign(reset_seed=seeds)
    means = np.asarray(rows).mean(axis=0)  # as the search averaged them (engine.averaged)
    return EliteFlight(float(means[0]), dict(zip(measures, map(float, means[1:]))),
                       episodes[["reset_seed", "objective", *measures]])
