"""Run folders as pandas tables, for a notebook: the package's public API (`qdsearch.read_run`,
`qdsearch.read_experiment`). Nothing here unpickles: a run is read from its config.json,
archive.csv and metrics.json, so a folder from anyone is safe to open.

Map: `RunData` (a run's config, archive and metrics), `read_run`, `read_experiment`.
"""

from __future__ import annotations

import dataclasses
import io
import os
from pathlib import Path
from typing import Any

from qdsearch.base.flags import UsageError
from qdsearch.base.run_files import read_regular
from qdsearch.config.run_config import load_run_config
from qdsearch.search.experiment_folder import read_experiment as read_plan
from qdsearch.store.metrics import load_metrics


@dataclasses.dataclass
class RunData:
    """A run folder, read: its settings (config.json, every flag, as the run recorded them), its
    archive (pyribs' ArchiveDataFrame of archive.csv: one row per elite, with its index,
    objective, measures_* and solution_* columns) and its metrics (one row per iteration logged:
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
