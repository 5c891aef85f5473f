"""`watch`: a live page of a run, served with Bokeh (installed with Dask for its dashboard) on a
port of its own: the archive's elites coloured by objective and the QD score so far, redrawn as
the run's folder is refreshed (every --log_every iterations). It reads the run's files only (its
config.json, checked against archive.npz's, archive.csv and metrics.json; never a pickle), so it
watches a run of any machine (or anyone) whose folder it sees, and never slows or stops the search.

Map:
- `elite_columns`, `metric_columns`: the run's files as the page's data;
- `live_document`: the page (a Bokeh document), refreshed every REFRESH_MS;
- `watch`: the command.
"""

from __future__ import annotations

import html
import io
import os
from pathlib import Path

from qdsearch.base.flags import UsageError
from qdsearch.base.run_files import check_present, read_regular
from qdsearch.base.stopping import STOP
from qdsearch.config.command_settings import WatchSettings
from qdsearch.config.run_config import RunConfig, load_checked_config
from qdsearch.store.metrics import load_metrics
from qdsearch.tasks import MEASURES, measure_bounds, returns_of

REFRESH_MS = 2000  # how often the page looks at the folder's files
# The files the page shows (name: kind of run_files.FILE_BOUNDS)
WATCHED = {"archive.csv": "archive.csv", "metrics.json": "metrics.json"}


def elite_columns(run_dir: Path, config: RunConfig) -> dict[str, list]:
    """archive.csv as the page's elites: x and y (the first two measures; one measure: y = 0)
    and the objective. An archive being replaced reads as the one before."""
    import pandas as pd

    try:  # read within its bound: a link to a device or a huge file is never read whole
        table = pd.read_csv(io.BytesIO(read_regular(run_dir / "archive.csv", "archive.csv")))
    except (UsageError, ValueError):  # none yet (or none any more), or not one: no elites
        return {"x": [], "y": [], "objective": []}
    y = table["measures_1"] if len(config.measures) > 1 else 0.0 * table["measures_0"]
    return {"x": table["measures_0"].tolist(), "y": list(y), "objective": table["objective"].tolist()}


def metric_columns(run_dir: Path) -> dict[str, list]:
    """metrics.json as the page's curve: QD score and coverage by iteration."""
    try:
        rows = load_metrics(run_dir)
    except UsageError:
        return {"iteration": [], "qd_score": [], "coverage": []}
    return {key: [row[key] for row in rows] for key in ("iteration", "qd_score", "coverage")}


def file_stat(path: Path) -> os.stat_result | None:
    """The file's stat, or None if it is not there (yet, or any more)."""
    try:
        return path.stat()
    except OSError:
        return None


def headline(run_dir: Path, config: RunConfig, metrics: dict[str, list], elites: int) -> str:
    """The page's first line (HTML: the folder's name escaped, as any name a user gives)."""
    name = f"<b>{html.escape(run_dir.name)}</b>"
    if not metrics["iteration"]:
        return f"{name}: no iteration yet"
    return (f"{name}: iteration {metrics['iteration'][-1]} of {config.iterations}, {elites} elites, "
            f"coverage {metrics['coverage'][-1]:.3f}, QD score {metrics['qd_score'][-1]:,.0f}")


def live_document(run_dir: Path, config: RunConfig):
    """The page's Bokeh document maker: elites on the measures' ranges, coloured on the task's
    heat range, beside the QD-score curve; both refreshed from the files every REFRESH_MS."""
    from bokeh.layouts import column, row
    from bokeh.models import ColorBar, ColumnDataSource, Div, LinearColorMapper
    from bokeh.palettes import Magma256
    from bokeh.plotting import figure

    heat, axes = returns_of(config).heat, [MEASURES[name] for name in config.measures]

    def make(doc) -> None:
        # the files as this page last showed them: each page (each tab, each session) keeps its own,
        # or a page refreshed first would leave the others stale
        stamps: dict[str, tuple] = {}
        elites = ColumnDataSource(elite_columns(run_dir, config), name="elites")
        curve = ColumnDataSource(metric_columns(run_dir), name="metrics")
        title = Div(text=headline(run_dir, config, curve.data, len(elites.data["x"])), name="headline")
        colours = LinearColorMapper(palette=Magma256, low=heat[0], high=heat[1])
        ranges = measure_bounds(config)  # (a benchmark function's grow with its --dim)
        x_range = ranges[0]
        y_range = ranges[1] if len(axes) > 1 else (-1.0, 1.0)
        if len(axes) > 1 and axes[1].descending:  # as heatmap.png and the explorer draw it
            y_range = y_range[::-1]
        archive = figure(title="Archive: elites by objective", width=560, height=460, x_range=x_range,
                         name="archive",
                         y_range=y_range, x_axis_label=axes[0].label,
                         y_axis_label=axes[1].label if len(axes) > 1 else "")
        archive.scatter("x", "y", source=elites, marker="square", size=7,
                        color={"field": "objective", "transform": colours})
        archive.add_layout(ColorBar(color_mapper=colours, title="objective"), "right")
        scores = figure(title="QD score", width=460, height=460, x_axis_label="iteration")
        scores.line("iteration", "qd_score", source=curve, line_width=2)

        def refresh() -> None:
            # A file is replaced whole (a new inode) at each save: two saves within one tick of
            # the file system's clock share an mtime, never an inode.
            changed = {name: (stat.st_ino, stat.st_mtime_ns, stat.st_size)
                       for name in WATCHED
                       if (stat := file_stat(run_dir / name)) is not None}
            if changed == stamps:
                return
            elites.data = elite_columns(run_dir, config)
            curve.data = metric_columns(run_dir)
            title.text = headline(run_dir, config, curve.data, len(elites.data["x"]))
            stamps.update(changed)  # only once shown: a refresh that failed is tried again

        doc.add_root(column(title, row(archive, scores)))
        doc.title = f"{run_dir.name}: live"
        doc.add_periodic_callback(refresh, REFRESH_MS)
    return make


def watch(path: Path, settings: WatchSettings) -> None:
    """Serve a live page of the run in `path` (running or not) where `settings` says, redrawn as
    its folder is refreshed, until Ctrl-C."""
    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler
    from bokeh.server.server import Server

    port, host = settings.port, settings.host
    config = load_checked_config(path)
    check_present(path, WATCHED)  # one that is there but no readable file: refused, not shown empty
    try:
        server = Server({"/": Application(FunctionHandler(live_document(path, config)))}, port=port,
                        address=str(host), allow_websocket_origin=[f"{host}:{port}", f"localhost:{port}"])
    except OSError as error:
        raise UsageError(f"cannot serve on {host}:{port}: {error.strerror or error}") from None
    server.start()
    print(f"watching {path}: http://{host}:{port}/ (Ctrl-C ends it)", flush=True)
    with STOP.interruptible():  # Ctrl-C or SIGTERM ends the serving at once
        server.io_loop.start()

