"""The pictures of a run folder and of a comparison, drawn with matplotlib and ribs.visualize.

Map:
- `save_heatmap`: the tutorial's heatmap of an archive on its task's colour range (`draw_grid`: a
  strip for one measure; for more, the best elite over the others; `draw_cvt`: the Voronoi cells,
  or parallel axes past two measures);
- `save_progress_plot` and `save_metric_panels`: QD score, coverage and best objective (the
  PROGRESS_PANELS, laid out by `panel_figure`) against iterations or evaluations, one curve per
  run or the mean and its 95% bootstrap band (`mean_band`) per group of runs; a run's saves draw
  their thread's progress figure again.
Each figure has a fixed layout (drawn once, no tight_layout: these run in the search loop) and is
written whole (run_files.atomic_write).
"""

from __future__ import annotations

import threading
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

from qdsearch.base.run_files import atomic_write


def save_heatmap(archive, axes: list, path: Path, title: str, heat: tuple[float, float]) -> None:
    """The tutorial's heatmap: objective per cell, on the task's fixed colour range `heat` (the
    fastest impacts on top). A grid of one measure gives a strip; of more, each cell of the first
    two shows the best elite over the others. A CVT archive of one or two measures draws its
    Voronoi cells; of more, each elite is a line across the measures' axes (parallel axes)."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6))
    fig.subplots_adjust(left=0.1, right=0.99, bottom=0.09, top=0.94)  # a fixed layout draws once
    draw = draw_cvt if type(archive).__name__ == "CVTArchive" else draw_grid
    ax.set_title(title + draw(archive, ax, axes, heat))
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100))
    plt.close(fig)


def draw_grid(archive, ax, axes: list, heat: tuple[float, float]) -> str:
    from ribs.archives import GridArchive
    from ribs.visualize import grid_archive_heatmap

    note, shown = "", archive
    if archive.measure_dim > 2:
        data = archive.data(["solution", "objective", "measures"])
        shown = GridArchive(solution_dim=archive.solution_dim, dims=archive.dims[:2],
                            ranges=list(zip(archive.lower_bounds[:2], archive.upper_bounds[:2])))
        shown.add(data["solution"], data["objective"], data["measures"][:, :2])
        note = f" (best over {', '.join(axis.label.lower() for axis in axes[2:])})"
    grid_archive_heatmap(shown, ax=ax, vmin=heat[0], vmax=heat[1])
    label_axes(ax, axes)
    return note


def draw_cvt(archive, ax, axes: list, heat: tuple[float, float]) -> str:
    from ribs.visualize import cvt_archive_heatmap, parallel_axes_plot

    if archive.measure_dim <= 2:
        cvt_archive_heatmap(archive, ax=ax, vmin=heat[0], vmax=heat[1], lw=0.2)
        label_axes(ax, axes)
        return ""
    ax.figure.subplots_adjust(top=0.87)  # room for the axes' names under the title
    parallel_axes_plot(archive, ax=ax, vmin=heat[0], vmax=heat[1], linewidth=0.6, alpha=0.5,
                       measure_order=[(i, axis.short) for i, axis in enumerate(axes)])
    return f" ({archive.measure_dim} measures: an elite per line)"


def label_axes(ax, axes: list) -> None:
    ax.set_xlabel(axes[0].label)
    if len(axes) > 1:
        ax.set_ylabel(axes[1].label)
        if axes[1].descending:
            ax.invert_yaxis()


PROGRESS_PANELS = (("qd_score", "QD score"), ("coverage", "Coverage"),
                   ("best_objective", "Best objective"))


_PROGRESS_FIGURES = threading.local()  # each thread's progress figure (matplotlib is not thread-safe)


def save_progress_plot(metrics: list[dict], path: Path) -> None:
    """QD score, coverage and best objective over evaluations (as `compare` draws them: rows that
    fly different numbers per iteration read alike), side by side. A run's saves draw
    this figure again and again: each thread keeps one and moves its curves, for ~0.65x the CPU
    of a new one and the same picture (docs/performance.md#saves)."""
    from matplotlib.transforms import Bbox

    figure = getattr(_PROGRESS_FIGURES, "figure", None)
    if figure is None:
        figure, axes = panel_figure("Evaluations")
        for ax in axes:
            ax.plot([], [])
        _PROGRESS_FIGURES.figure = figure
    x = [row["evaluations"] for row in metrics]
    for ax, (key, _) in zip(figure.axes, PROGRESS_PANELS):
        ax.lines[0].set_data(x, [np.nan if row[key] is None else row[key] for row in metrics])
        # The limits a new panel would take: without this, a panel with no value yet (a best
        # objective still unknown) would keep the last picture's limits.
        ax.viewLim.set_points(Bbox.unit().get_points())
        ax.relim()
        ax.autoscale_view()
    atomic_write(path, lambda f: figure.savefig(f, format="png", dpi=100))


def panel_figure(x_label: str) -> tuple[Figure, np.ndarray]:
    """A figure of one panel per metric of PROGRESS_PANELS, titled, with no curve yet: (figure,
    its axes). Not pyplot's: nothing holds it but its caller."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    figure = Figure(figsize=(15, 4))
    axes = figure.subplots(1, len(PROGRESS_PANELS))
    # A fixed layout: tight_layout would cost more than the plotting (this runs in the search loop).
    figure.subplots_adjust(left=0.06, right=0.98, bottom=0.14, top=0.9, wspace=0.25)
    for ax, (_, label) in zip(axes, PROGRESS_PANELS):
        ax.set_xlabel(x_label)
        ax.xaxis.set_major_locator(MaxNLocator(5))  # evaluations run to 100,000s: labels apart
        ax.set_title(label)
        ax.grid(alpha=0.3)
    return figure, axes


def save_metric_panels(groups: dict[str, list[list[dict]]], x_key: str, x_label: str,
                       path: Path) -> None:
    """One panel per metric of PROGRESS_PANELS, one line per group of runs (labelled if it has a
    label): a run's own curve, or for several runs their mean and its 95% confidence band."""
    figure, axes = panel_figure(x_label)
    for ax, (key, _) in zip(axes, PROGRESS_PANELS):
        for group_label, runs in groups.items():
            length = min(len(metrics) for metrics in runs)
            values = np.array([[np.nan if row[key] is None else row[key] for row in metrics[:length]]
                               for metrics in runs], dtype=float)
            x = [row[x_key] for row in runs[0][:length]]
            line, = ax.plot(x, values.mean(axis=0), label=group_label or None)
            if len(runs) > 1:
                low, high = mean_band(values)
                ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
    labelled = any(groups)
    if labelled:  # beside the panels, where it hides no curve
        axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1), fontsize="small")
    atomic_write(path, lambda f: figure.savefig(f, format="png", dpi=100,
                                                bbox_inches="tight" if labelled else None))


def mean_band(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 95% bootstrap confidence band of the mean of the rows of `values`, point by point."""
    from scipy.stats import bootstrap

    with warnings.catch_warnings():  # points where every run has the same value: a band of width 0
        warnings.simplefilter("ignore")
        result = bootstrap((values,), np.mean, axis=0, vectorized=True, method="percentile",
                           n_resamples=2000, rng=np.random.default_rng(0))
    return result.confidence_interval.low, result.confidence_interval.high
