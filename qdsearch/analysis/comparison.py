"""Comparing runs: QD score, coverage and best objective against evaluations on one picture, the
final archives' score distributions on another, a table of final values, and statistics across
seeds between settings.

Runs of one setting (the same algorithm and flags, other seeds: `experiment_folder.run_setting`) are
repeats of one experiment; returns of different tasks share no scale, so every statistic is per
(task, setting). Per setting: the mean with a 95% BCa bootstrap interval, the median, and the
interquartile mean (IQM) with a 95% stratified bootstrap interval of each summarised metric.
Between settings: two-sided Mann-Whitney U tests, Holm-adjusted over the pairs, with
Vargha-Delaney A12 as the effect size, which is also rliable's probability of improvement
P(A > B), here with its interval. Runs of several tasks are also pooled per setting on scales
that every task shares (the QD score normalised by the archive's cells and the task's objective
range, coverage), as rliable aggregates over tasks (qdsearch/analysis/stats.py).

Map:
- reading runs: compared_runs.py's (an experiment folder is its runs, corrected.json, a cut at a
  budget), `final_archive`;
- a run's figures: `solved_cells`, `qd_auc`, `cqd` (pyribs' cqd_score with fixed settings, CQD),
  `archive_cells`, `normalised_qd_score`;
- `comparison_table` (a row per run), `setting_statistics`, `pairwise_tests` (per task),
  `aggregate_statistics` (across tasks);
- output: `comparison_outputs` (file names), `format_table`, `markdown_report` (`task_section`,
  `settings_table`, `aggregate_section`), `save_score_distributions`;
- `compare`: the command.
"""

from __future__ import annotations

import datetime
import io
import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np

from qdsearch.analysis.compared_runs import (
    CORRECTED,
    check_fresh,
    cut_at,
    expand_folders,
    load_run_metrics,
    read_corrected,
)
from qdsearch.analysis.stats import (
    RESAMPLES,
    bootstrap_interval,
    holm,
    holm_floor,
    improvement_interval,
    iqm_interval,
    mean_interval,
)
from qdsearch.base.flags import UsageError, named, shown
from qdsearch.base.plots import save_metric_panels
from qdsearch.base.run_files import atomic_write, check_parent_folder, read_regular, write_csv
from qdsearch.config.command_settings import CompareSettings
from qdsearch.config.run_config import RunConfig, saved_archive
from qdsearch.search.experiment_folder import run_setting, shortened
from qdsearch.tasks import returns_of
from qdsearch.tasks.family import Returns

COMPARED = ("evaluations", "coverage", "num_elites", "qd_score", "best_objective", "mean_objective")
SOLVED_CELLS = "solved_cells"  # the table's column of cells whose elite solves the task
NORMALISED = "normalised_qd_score"  # QD score over its most: comparable between tasks
# The files a run's final figures come from: its own, or (--corrected) those `evaluate --corrected` wrote.
ARCHIVE_FILES = {False: ("archive.npz", "archive.csv"),
                 True: ("corrected_archive.npz", "corrected_archive.csv")}


def solved_cells(path: Path, returns: Returns) -> int | None:
    """Cells of the final archive (its CSV at `path`) whose elite solves the task, a return of at
    least the run's `returns.solved` (200 for Lunar Lander: a good landing); None without the
    CSV. QD score and coverage count crashes too; this counts only the solutions."""
    import pandas as pd

    try:  # (within its bound: compared_runs refused one that is no regular file)
        objectives = pd.read_csv(io.BytesIO(read_regular(path, "archive.csv")), usecols=["objective"])
        return int((objectives["objective"] >= returns.solved).sum())
    except (UsageError, ValueError):
        return None


def run_settings(configs: list[RunConfig]) -> list[str]:
    """Each run's setting, labelled by what tells the compared settings apart (the algorithm and
    the flags the settings do not all share: experiment_folder.shortened)."""
    labels = [run_setting(config.to_json()) for config in configs]
    short = shortened(labels)
    return [short[label] for label in labels]


def run_labels(run_dirs: list[Path], configs: list[RunConfig], settings: list[str]) -> list[str]:
    """'setting seed N' for each run ('TASK: setting seed N' with several tasks), or the folders
    as given when that would be ambiguous."""
    several = len({config.env for config in configs}) > 1
    labels = [f"{config.env + ': ' if several else ''}{setting} seed {config.seed}"
              for config, setting in zip(configs, settings)]
    return labels if len(set(labels)) == len(labels) else [str(run_dir) for run_dir in run_dirs]


def comparison_outputs(out: str | None, overwrite: bool, home: Path | None = None) -> dict[str, Path]:
    """The files of a comparison, all named after the PNG: by default new files in `home` (the
    one experiment compared: compare.png, compare_2.png, ...) or under outputs/; never an
    existing file unless --overwrite."""
    def files_of(png: Path) -> dict[str, Path]:
        return {"png": png, "csv": png.with_suffix(".csv"), "md": png.with_suffix(".md"),
                "settings": png.with_name(f"{png.stem}_settings.csv"),
                "tests": png.with_name(f"{png.stem}_tests.csv"),
                "aggregate": png.with_name(f"{png.stem}_aggregate.csv"),
                "scores": png.with_name(f"{png.stem}_scores.png")}

    if out is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        first = home / "compare" if home is not None else Path("outputs") / f"compare_{stamp}"
        candidates = [Path(f"{first}{suffix}.png") for suffix in ["", *(f"_{i}" for i in range(2, 1000))]]
        files = next(files_of(p) for p in candidates if not any(f.exists() for f in files_of(p).values()))
    else:
        files = files_of(Path(out) if Path(out).suffix.lower() == ".png" else Path(f"{out}.png"))
    check_parent_folder(files["png"])
    existing = [str(p) for p in files.values() if p.exists()]
    if existing and not overwrite:
        raise UsageError(f"{' and '.join(existing)} already exist(s); choose another {named('out')} "
                         f"or pass {named('overwrite')}")
    return files


def experiment_home(run_dirs: tuple) -> Path | None:
    """The experiment folder a comparison of it alone is written into, if that is what it is."""
    folder = Path(str(run_dirs[0])) if len(run_dirs) == 1 else None
    return folder if folder is not None and (folder / "experiment.json").is_file() else None


QD_AUC, CQD_SCORE = "qd_auc", "cqd_score"
# CQD score (Kent 2022, ribs.archives.cqd_score) with fixed settings, so that a number means the
# same in every table: target points drawn uniformly in the archive's measure box with this seed,
# penalties spread evenly over [0, 1], objectives divided by obj_max - obj_min (pyribs 0.12 does
# not subtract obj_min first, unlike Kent 2022's [0, 1] scale: tests/test_oracles.py pins it),
# distances over the box's diagonal (obj_min is the run's QD offset, obj_max its task's
# `objective_max` for its episode's length: family.Returns). Written next to every comparison.
CQD = {"iterations": 1, "targets": 1000, "penalties": 10, "target_seed": 0}
SUMMARISED = ("qd_score", "mean_objective", "coverage", "best_objective", SOLVED_CELLS, QD_AUC, CQD_SCORE)
TESTED = ("qd_score", QD_AUC, CQD_SCORE)  # pairwise between settings: final, anytime, spread
AGGREGATED = (NORMALISED, "coverage")  # across tasks: on scales every task shares
FEW_RUNS = 5


def final_archive(path: Path):
    """A run's final archive (archive.npz, or corrected_archive.npz; of a folder from before them,
    the CSV), or None where there is no readable archive of ours. No pickle is read."""
    try:
        return saved_archive(path.parent, path.stem)
    except UsageError:
        return None


def cqd(archive, returns: Returns) -> float:
    """The CQD score of a run's final archive."""
    from ribs.archives import cqd_score

    lower, upper = archive.lower_bounds, archive.upper_bounds
    targets = np.random.default_rng(CQD["target_seed"]).uniform(
        lower, upper, size=(CQD["iterations"], CQD["targets"], len(lower)))
    return float(cqd_score(archive, iterations=CQD["iterations"], target_points=targets,
                           penalties=CQD["penalties"], obj_min=returns.offset, obj_max=returns.top,
                           dist_max=float(np.linalg.norm(upper - lower))).mean)


def qd_auc(metrics: list[dict]) -> float:
    """Area under QD score against evaluations, from (0, 0), divided by the evaluations: the
    run's QD score averaged over its budget, which rewards reaching a score early."""
    evaluations = [0, *(row["evaluations"] for row in metrics)]
    return float(np.trapezoid([0, *(row["qd_score"] for row in metrics)], evaluations) / evaluations[-1])


def archive_cells(config: RunConfig) -> int:
    """The cells of a run's archive: --grid along each measure, or a CVT's --cells."""
    return config.grid ** len(config.measures) if config.archive == "grid" else config.cells


def normalised_qd_score(qd_score: float, config: RunConfig) -> float:
    """QD score over the most it could be, every cell holding an elite of the task's
    objective_max (for the run's episode length): in [0, 1] (objective_max is above almost every
    return) whatever the task and the archive's size, so tasks pool."""
    returns = returns_of(config)
    return qd_score / (archive_cells(config) * (returns.top - returns.offset))


def comparison_table(labels: list[str], run_dirs: list[Path], configs: list[RunConfig],
                     runs: list[list[dict]], settings: list[str], corrected: list[dict] | None = None,
                     cut: list[bool] | None = None):
    """One row per run: its final metrics (or its `corrected` ones), with the task, algorithm and
    seed that produced them; and each run's final objectives (None without a readable archive),
    for the score distributions. QD-score AUC is always from metrics.json: a curve. A run `cut`
    short of its end (compare --at_evaluations) has no archive of that row: its archive's figures
    are left out (NaN)."""
    import pandas as pd

    data_name, csv_name = ARCHIVE_FILES[corrected is not None]
    rows, objectives = [], []
    for i, (label, run_dir, config, metrics, setting) in enumerate(zip(labels, run_dirs, configs, runs,
                                                                         settings)):
        final = metrics[-1] if corrected is None else {**metrics[-1], **{
            key: corrected[i][key] for key in CORRECTED}}
        returns = returns_of(config)
        archive = None if cut and cut[i] else final_archive(run_dir / data_name)
        objectives.append(None if archive is None else archive.data("objective"))
        rows.append({"run": label, "folder": str(run_dir), "task": config.env,
                     "setting": setting, "seed": config.seed,
                     "iterations": metrics[-1]["iteration"], "qd_offset": returns.offset,
                     **{key: final[key] for key in COMPARED},
                     NORMALISED: normalised_qd_score(final["qd_score"], config),
                     SOLVED_CELLS: None if cut and cut[i] else solved_cells(run_dir / csv_name, returns),
                     QD_AUC: qd_auc(metrics),
                     CQD_SCORE: None if archive is None else cqd(archive, returns)})
    table = pd.DataFrame(rows)
    for column in (SOLVED_CELLS, CQD_SCORE):
        table[column] = pd.to_numeric(table[column])  # None (no archive): NaN
    return table, objectives


def setting_statistics(table):
    """Per task, setting and summarised metric: runs, mean, median and the 95% BCa interval of
    the mean; the IQM and its 95% (stratified: one task) bootstrap interval."""
    import pandas as pd

    rows = []
    for (task, setting), group in table.groupby(["task", "setting"], sort=False):
        for metric in SUMMARISED:
            values = group[metric].dropna().to_numpy(dtype=float)
            low, high = bootstrap_interval(values)
            iqm, iqm_low, iqm_high = iqm_interval([values])
            rows.append({"task": task, "setting": setting, "metric": metric, "runs": len(values),
                         "mean": values.mean() if len(values) else math.nan,
                         "median": float(np.median(values)) if len(values) else math.nan,
                         "ci95_low": low, "ci95_high": high,
                         "iqm": iqm, "iqm_low": iqm_low, "iqm_high": iqm_high})
    return pd.DataFrame(rows)


TEST_COLUMNS = ["task", "metric", "setting_a", "setting_b", "runs_a", "runs_b", "U", "p", "p_holm", "A12",
                "p_improvement", "p_improvement_low", "p_improvement_high"]


def setting_pairs(settings: list[str], baseline: str | None) -> list[tuple[str, str]]:
    """The pairs of settings tested: every pair, or (--baseline) the baseline against each other
    setting: fewer tests, so Holm's adjustment costs less power."""
    if baseline is None:
        return list(itertools.combinations(settings, 2))
    return [(baseline, setting) for setting in settings if setting != baseline and baseline in settings]


def pairwise_tests(table, baseline: str | None = None):
    """The pairs of settings of a task (`setting_pairs`), on each TESTED metric: two-sided
    Mann-Whitney U, Holm-adjusted over the pairs, and Vargha-Delaney A12 (the chance that a run
    of A beats a run of B; 0.5: even), which is rliable's P(A > B) of one task, with its 95%
    bootstrap interval."""
    import pandas as pd
    from scipy.stats import mannwhitneyu

    rows = []
    for task, runs in table.groupby("task", sort=False):
        settings = list(dict.fromkeys(runs["setting"]))
        for metric in TESTED:
            block = []
            for a, b in setting_pairs(settings, baseline):
                x = runs.loc[runs["setting"] == a, metric].dropna().to_numpy(dtype=float)
                y = runs.loc[runs["setting"] == b, metric].dropna().to_numpy(dtype=float)
                if len(x) and len(y):
                    test = mannwhitneyu(x, y, alternative="two-sided")
                    improvement = improvement_interval([x], [y])
                    block.append({"task": task, "metric": metric, "setting_a": a, "setting_b": b,
                                  "runs_a": len(x), "runs_b": len(y), "U": float(test.statistic),
                                  "p": float(test.pvalue), "A12": float(test.statistic) / (len(x) * len(y)),
                                  **dict(zip(TEST_COLUMNS[-3:], improvement))})
            for row, adjusted in zip(block, holm([row["p"] for row in block])):
                row["p_holm"] = adjusted
            rows += block
    return pd.DataFrame(rows, columns=TEST_COLUMNS)


AGGREGATE_COLUMNS = ["statistic", "metric", "setting", "versus", "tasks", "runs", "runs_versus",
                     "value", "low", "high"]


def aggregate_statistics(table, baseline: str | None = None):
    """Across tasks, per setting: the IQM and mean of each AGGREGATED metric over all its runs of
    all tasks, each with a 95% stratified bootstrap interval (strata: the tasks); between settings,
    P(A > B) on the normalised QD score averaged over the tasks both have runs of. A setting
    missing from a task is aggregated over the tasks it has: the notes say which."""
    import pandas as pd

    tasks, settings = list(dict.fromkeys(table["task"])), list(dict.fromkeys(table["setting"]))

    def scores(setting: str, metric: str) -> list[np.ndarray]:  # per task ([] where it has none)
        return [table.loc[(table["task"] == task) & (table["setting"] == setting), metric]
                .dropna().to_numpy(dtype=float) for task in tasks]

    rows, notes = [], []
    for setting in settings:
        if missing := [task for task, runs in zip(tasks, scores(setting, NORMALISED)) if not len(runs)]:
            notes.append(f"{setting} has no runs of {', '.join(missing)}: aggregated over the "
                         f"tasks it has")
        for metric in AGGREGATED:
            per_task = scores(setting, metric)
            for statistic, interval in (("iqm", iqm_interval), ("mean", mean_interval)):
                rows.append(dict(zip(AGGREGATE_COLUMNS, (
                    statistic, metric, setting, "", sum(1 for runs in per_task if len(runs)),
                    sum(map(len, per_task)), None, *interval(per_task)))))
    for a, b in setting_pairs(settings, baseline):
        shared = [(x, y) for x, y in zip(scores(a, NORMALISED), scores(b, NORMALISED)) if len(x) and len(y)]
        if shared:
            rows.append(dict(zip(AGGREGATE_COLUMNS, (
                "p_improvement", NORMALISED, a, b, len(shared), sum(len(x) for x, _ in shared),
                sum(len(y) for _, y in shared),
                *improvement_interval([x for x, _ in shared], [y for _, y in shared])))))
    aggregate = pd.DataFrame(rows, columns=AGGREGATE_COLUMNS)
    aggregate["runs_versus"] = aggregate["runs_versus"].astype("Int64")
    return aggregate, notes


METRIC_FORMATS = {"evaluations": "{:.0f}", "num_elites": "{:.0f}", "coverage": "{:.4f}",
                  "qd_score": "{:,.0f}", "best_objective": "{:.1f}", "mean_objective": "{:.1f}",
                  NORMALISED: "{:.4f}", SOLVED_CELLS: "{:.0f}", QD_AUC: "{:,.0f}", CQD_SCORE: "{:.2f}"}
# A statistic of counts over runs (a mean, an IQM, their bounds) is no count: 0 and 1 average 0.5.
SUMMARY_FORMATS = {**METRIC_FORMATS, SOLVED_CELLS: "{:,.1f}"}


def format_table(table) -> str:
    """The table as aligned text, with as many digits as a reader compares."""
    shown_table = table.drop(columns=["folder"], errors="ignore")
    return shown_table.to_string(index=False, formatters={
        k: v.format for k, v in METRIC_FORMATS.items() if k in shown_table})


def with_interval(number, point: float, low: float, high: float) -> str:
    """'point [low, high]', or the point alone where there is no interval (one run)."""
    return number(point) + ("" if math.isnan(low) else f" [{number(low)}, {number(high)}]")


def settings_table(stats, point: str, low: str, high: str) -> list[str]:
    """A Markdown table: a row per setting, a column per SUMMARISED metric with its `point`
    statistic [`low`, `high`]."""
    lines = ["| setting | runs | " + " | ".join(SUMMARISED) + " |",
             "| --- | --- |" + " --- |" * len(SUMMARISED)]
    for setting, group in stats.groupby("setting", sort=False):
        cells = {row["metric"]: with_interval(SUMMARY_FORMATS[row["metric"]].format, row[point], row[low],
                                              row[high]) for row in group.to_dict("records")}
        lines.append(f"| {setting} | {group['runs'].max()} | "
                     + " | ".join(cells[m] for m in SUMMARISED) + " |")
    return lines


def task_section(stats, tests, env: str, ranges: list[Returns]) -> list[str]:
    """One task's statistics as Markdown tables: the mean and the IQM per setting, the tests
    (`ranges`: its runs' ranges of objectives, one unless their episodes differ in length)."""
    one = ranges[0]
    if len(ranges) == 1:
        scale = (f"QD score: the sum of each elite's objective less the offset {one.offset:g}; "
                 f"mean_objective: the elites' mean objective. solved_cells: cells whose elite "
                 f"returns at least {one.solved:g}.")
        divided = (f"{one.top:g} - ({one.offset:g}) (pyribs' cqd_score with obj_min {one.offset:g}, "
                   f"obj_max {one.top:g}")
    else:
        scale = ("Its runs' episodes differ in length, and with them their QD offsets, solved "
                 "returns and CQD's ranges (the table's qd_offset column): their QD scores do not compare.")
        divided = "each run's objective_max - QD offset (pyribs' cqd_score"
    lines = [*settings_table(stats, "mean", "ci95_low", "ci95_high"),
             "", f"{env}. Mean [95% bootstrap confidence interval of the mean, BCa] over each "
                 f"setting's runs. {scale}",
             f"CQD score: {CQD['targets']:,} target points drawn uniformly in the measure box "
             f"(seed {CQD['target_seed']}), {CQD['penalties']} distance penalties, objectives "
             f"divided by {divided}: not shifted by obj_min).", "",
             "IQM [95% stratified bootstrap interval]:", "",
             *settings_table(stats, "iqm", "iqm_low", "iqm_high"),
             "", f"IQM: the interquartile mean (the mean of the middle half of the runs, rliable's); "
                 f"its interval: the 2.5th and 97.5th percentiles of {RESAMPLES:,} resamples of the "
                 f"runs.", ""]
    if len(tests):
        lines += ["| metric | A | B | U | p (Holm) | A12 = P(A>B) [95% interval] |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for t in tests.to_dict("records"):
            improvement = with_interval("{:.2f}".format, t["A12"], t["p_improvement_low"],
                                        t["p_improvement_high"])
            lines.append(f"| {t['metric']} | {t['setting_a']} | {t['setting_b']} | {t['U']:.1f} | "
                         f"{t['p_holm']:.3g} | {improvement} |")
        lines += ["", "Two-sided Mann-Whitney U tests, Holm-adjusted over the pairs of each metric; "
                  "A12: the chance that a run of A beats a run of B (0.5: even; 0.71 or more, or "
                  "0.29 or less: a large effect), rliable's probability of improvement P(A>B), with "
                  "its bootstrap interval (A's and B's runs resampled apart)."]
        floor = holm_floor(tests)
        if floor > 0.05:
            lines += ["", f"With so few runs per setting, no pair can reach p < 0.05 after Holm's "
                          f"adjustment: the smallest adjusted p possible here is {floor:.3g} (a "
                          f"complete separation, A12 of 0 or 1). Read the effect sizes and the "
                          f"intervals; more seeds give the tests power."]
    return lines


def aggregate_section(aggregate, notes: list[str], tasks: list[str]) -> list[str]:
    """The statistics across tasks as Markdown: per setting, then P(A > B) between settings."""
    per_setting = aggregate[aggregate["statistic"] != "p_improvement"]
    columns = [(metric, statistic) for metric in AGGREGATED for statistic in ("iqm", "mean")]
    lines = [f"## All tasks ({', '.join(tasks)})", "",
             "| setting | tasks | runs | " + " | ".join(f"{m} {s.upper() if s == 'iqm' else s}"
                                                     for m, s in columns) + " |",
             "| --- | --- | --- |" + " --- |" * len(columns)]
    for setting, group in per_setting.groupby("setting", sort=False):
        found = group.set_index(["metric", "statistic"])
        cells = [with_interval("{:.4f}".format, *found.loc[column, ["value", "low", "high"]])
                 for column in columns]
        lines.append(f"| {setting} | {group['tasks'].iloc[0]} | {group['runs'].iloc[0]} | "
                     + " | ".join(cells) + " |")
    lines += ["", f"IQM and mean [95% stratified bootstrap interval: each task's runs resampled "
                  f"within the task, {RESAMPLES:,} times] over every run of every task. "
                  f"{NORMALISED}: QD score / (cells x (objective_max - QD offset)), 1 when every "
                  f"cell holds an elite of the task's objective_max. The mean is rliable's: the "
                  f"mean of the tasks' means.", *(f"Note: {note}." for note in notes), ""]
    tests = aggregate[aggregate["statistic"] == "p_improvement"]
    if len(tests):
        lines += [f"| A | B | tasks | P(A>B) on {NORMALISED} [95% interval] |", "| --- | --- | --- | --- |"]
        lines += [f"| {t['setting']} | {t['versus']} | {t['tasks']} | "
                  f"{with_interval('{:.2f}'.format, t['value'], t['low'], t['high'])} |"
                  for t in tests.to_dict("records")]
        lines += ["", "P(A>B): per task, the chance that a run of A beats a run of B (ties count "
                      "half), averaged over the tasks both have runs of (rliable's probability of "
                      "improvement).", ""]
    return lines


def markdown_report(stats, tests, aggregate, notes: list[str], used: str,
                    ranges: dict[str, list[Returns]]) -> str:
    """The statistics as Markdown, ready for a README or a paper: each task's own (a section per
    task when there are several; `ranges`: its runs' ranges of objectives), then with several
    tasks the aggregate, and which final values they are of (`used`)."""
    tasks, lines = list(dict.fromkeys(stats["task"])), []
    for env in tasks:
        section = task_section(stats[stats["task"] == env], tests[tests["task"] == env], env, ranges[env])
        lines += section if len(tasks) == 1 else [f"## {env}", "", *section, ""]
    if aggregate is not None:
        lines += aggregate_section(aggregate, notes, tasks)
    while lines and not lines[-1]:
        lines.pop()
    return "\n".join([*lines, "", used]) + "\n"


def save_score_distributions(table, objectives: list, archive_name: str, path: Path) -> None:
    """A panel per task, a line per setting: pyribs' aggregate_cdf of its runs' final archives,
    complementary (Vassiliades 2018): the mean number of cells holding at least each objective,
    with a band of one standard deviation, on one objective range per task (from its QD offset
    up). Runs without a readable archive are left out, with a note."""
    import matplotlib.pyplot as plt
    from ribs.visualize import aggregate_cdf

    if missing := [folder for folder, found in zip(table["folder"], objectives) if found is None]:
        print(f"note: {', '.join(missing)}: no readable {archive_name}; left out of the score distributions")
    runs = [row for row, found in zip(table.to_dict("records"), objectives) if found is not None]
    tasks = list(dict.fromkeys(table["task"]))
    fig, axes = plt.subplots(1, len(tasks), figsize=(7 * len(tasks), 4.5), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        found = [objs for row, objs in zip(table.to_dict("records"), objectives)
                 if objs is not None and row["task"] == task]
        values = np.concatenate(found) if found else np.empty(0)
        # from the task's QD offset up: below it lie crashes that count for nothing in the QD score
        offset = min(row["qd_offset"] for row in runs if row["task"] == task) if len(values) else None
        low = max(float(values.min()), offset) if len(values) else None
        vmin, vmax = (low, max(float(values.max()), low + 1.0)) if len(values) else (None, None)
        settings = list(dict.fromkeys(row["setting"] for row in runs if row["task"] == task))
        # each setting its colour: tab10's distinct ones, tab20's (pairs of shades) past ten
        ax.set_prop_cycle(color=plt.get_cmap("tab10" if len(settings) <= 10 else "tab20").colors)
        for setting in settings:
            archives = [final_archive(Path(row["folder"]) / archive_name) for row in runs
                        if row["task"] == task and row["setting"] == setting]
            line, _ = aggregate_cdf(archives, ax=ax, cumulative=-1, vmin=vmin, vmax=vmax)
            line.set_label(f"{setting} ({len(archives)} run{'s' if len(archives) > 1 else ''})")
        kind = "corrected archives" if archive_name.startswith("corrected") else "final archives"
        ax.set_title(f"{task}: {kind}" if found else f"{task}: no readable {archive_name}")
        ax.set_xlabel("Objective")
        ax.set_ylabel("Cells with at least that objective (mean, ±1 sd)")
        ax.grid(alpha=0.3)
        if found:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100, bbox_inches="tight"))
    plt.close(fig)


def values_used(corrected: list[dict] | None) -> str:
    """The one line that says which final values the comparison is of."""
    if corrected is None:
        return "Final values: each run's last row of metrics.json, and its archive.npz and archive.csv."
    repeats = sorted({fix["repeats"] for fix in corrected})
    seeds = f"{repeats[0]}" if len(repeats) == 1 else f"{repeats[0]} to {repeats[-1]}"
    return (f"Final values: each run's corrected metrics (corrected.json: its elites flown again on "
            f"{seeds} new seeds), corrected_archive.npz and corrected_archive.csv; {QD_AUC} from "
            f"metrics.json (a curve).")


def check_baseline(baseline: Any, settings: list[str]) -> str | None:
    """--baseline names one of the compared settings: as the tables label it, or by its
    algorithm alone when one setting has it (`cma_me` for 'cma_me n_emitters=2')."""
    if baseline is None or str(baseline) in settings:
        return None if baseline is None else str(baseline)
    by_algorithm = [setting for setting in settings if setting.split(" ")[0] == str(baseline)]
    if len(by_algorithm) == 1:
        return by_algorithm[0]
    raise UsageError(f"{named('baseline')} {shown(baseline)} is not a setting of these runs; they are: "
                     + ", ".join(repr(setting) for setting in settings))


def compare(run_dirs: list[Path], settings: CompareSettings) -> None:
    """Compare the runs in `run_dirs` (run or experiment folders): their curves, score
    distributions and final values, and per setting their statistics and tests, written where
    `settings.out` says (the command's --help says what each file holds)."""
    out, overwrite, corrected = settings.out, settings.overwrite, settings.corrected
    baseline, at_evaluations = settings.baseline, settings.at_evaluations
    if not run_dirs:
        raise UsageError("compare needs at least one run folder: "
                         "python lunar_lander.py compare RUN_A RUN_B ...")
    paths = expand_folders(run_dirs)
    if not paths:
        raise UsageError(f"no run with metrics in {', '.join(map(str, run_dirs))}")
    configs, runs = zip(*(load_run_metrics(path) for path in paths))
    runs, cut = cut_at(list(runs), paths, at_evaluations, corrected)
    fixes = [read_corrected(path) for path in paths] if corrected else None
    if fixes is not None:
        check_fresh(fixes, list(runs), paths)
    settings = run_settings(list(configs))
    baseline = check_baseline(baseline, list(dict.fromkeys(settings)))
    files = comparison_outputs(None if out is None else str(out), overwrite, experiment_home(tuple(run_dirs)))
    labels = run_labels(paths, list(configs), settings)
    table, objectives = comparison_table(labels, paths, list(configs), runs, settings, fixes, cut)
    several = table["task"].nunique() > 1
    keys = table["task"] + ": " + table["setting"] if several else table["setting"]
    grouped = several or keys.duplicated().any()
    groups: dict[str, list] = {}
    for label, key, metrics in zip(labels, keys, runs):
        groups.setdefault(key if grouped else label, []).append(metrics)
    save_metric_panels(groups, "evaluations", "Evaluations", files["png"])
    save_score_distributions(table, objectives, ARCHIVE_FILES[corrected][0], files["scores"])
    write_csv(files["csv"], table)
    print(format_table(table.drop(columns=["task", "setting"])))  # the run's label names them
    if (table.groupby("task")["evaluations"].nunique() > 1).any():
        print("note: the runs of a task end at different numbers of evaluations; compare them at an "
              f"equal budget with {named('at_evaluations')} N")
    used = values_used(fixes)
    if not grouped:  # else the report says it
        print(used)
    written = [files["png"], files["scores"], files["csv"]]
    if grouped:
        stats, tests = setting_statistics(table), pairwise_tests(table, baseline)
        aggregate, notes = aggregate_statistics(table, baseline) if several else (None, [])
        ranges: dict[str, list[Returns]] = {}
        for config in configs:
            ranges.setdefault(config.env, [])
            if (returns := returns_of(config)) not in ranges[config.env]:
                ranges[config.env].append(returns)
        report = markdown_report(stats, tests, aggregate, notes, used, ranges)
        write_csv(files["settings"], stats)
        write_csv(files["tests"], tests)
        written += [files["settings"], files["tests"]]
        if several:
            write_csv(files["aggregate"], aggregate)
            written.append(files["aggregate"])
        atomic_write(files["md"], lambda f: f.write(report), mode="w")
        print("\nper setting: mean [95% bootstrap interval of the mean] over its runs\n" + report)
        sizes = keys.value_counts(sort=False)
        if (few := sizes[sizes < FEW_RUNS]).size:
            print(f"note: {', '.join(f'{s} ({n} runs)' for s, n in few.items())}: fewer than "
                  f"{FEW_RUNS} runs; the intervals are wide and the tests can hardly reject anything")
        written.append(files["md"])
    print(f"wrote {', '.join(map(str, written))}")
