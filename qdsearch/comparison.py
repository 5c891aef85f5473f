"""Comparing runs: QD score, coverage and best objective against evaluations on one picture, a
table of final values, and statistics across seeds between settings.

Runs of one setting (the same algorithm and flags, other seeds: `experiments.run_setting`) are
repeats of one experiment. Per setting: the mean with a 95% BCa bootstrap interval of each
summarised metric. Between settings: two-sided Mann-Whitney U tests, Holm-adjusted over the
pairs, with Vargha-Delaney A12 as the effect size.

Map:
- reading runs: `expand_folders` (an experiment folder is its runs), `load_run_metrics`;
- a run's figures: `solved_cells`, `qd_auc`, `cqd` (pyribs' cqd_score with fixed settings, CQD);
- `comparison_table` (a row per run), `setting_statistics`, `bootstrap_interval`,
  `pairwise_tests`, `holm`, `holm_floor`;
- output: `comparison_outputs` (file names), `format_table`, `markdown_report`;
- `compare`: the command.
"""

from __future__ import annotations

import datetime
import itertools
import math
from pathlib import Path

import numpy as np

from qdsearch.algorithms import task_of
from qdsearch.experiments import read_experiment, run_setting
from qdsearch.family import Environment
from qdsearch.flags import UsageError, boolean
from qdsearch.metrics import load_metrics
from qdsearch.plots import save_metric_panels
from qdsearch.run_config import RunConfig, load_checked_config
from qdsearch.run_files import atomic_write, check_parent_folder, read_pickle, write_csv
from qdsearch.tasks import ENVIRONMENTS

COMPARED = ("evaluations", "coverage", "num_elites", "qd_score", "best_objective", "mean_objective")
SOLVED_CELLS = "solved_cells"  # the table's column of cells whose elite solves the task


def solved_cells(run_dir: Path, task: Environment) -> int | None:
    """Cells of the final archive whose elite solves the task, a return of at least task.solved
    (200 for Lunar Lander: a good landing); None without archive.csv. QD score and coverage count
    crashes too; this counts only the solutions."""
    import pandas as pd

    try:
        objectives = pd.read_csv(run_dir / "archive.csv", usecols=["objective"])["objective"]
        return int((objectives >= task.solved).sum())
    except (OSError, ValueError):
        return None


def load_run_metrics(run_dir: Path) -> tuple[RunConfig, list[dict]]:
    """A run's config and its metrics rows (at least one, each field of its type), both checked
    as every command checks them."""
    metrics = load_metrics(run_dir)
    return load_checked_config(run_dir), metrics


def run_labels(run_dirs: list[Path], configs: list[RunConfig]) -> list[str]:
    """'setting seed N' for each run, or the folders as given when that would be ambiguous."""
    labels = [f"{run_setting(config.to_json())} seed {config.seed}" for config in configs]
    return labels if len(set(labels)) == len(labels) else [str(run_dir) for run_dir in run_dirs]


def comparison_outputs(out: str | None, overwrite: bool) -> dict[str, Path]:
    """The files of a comparison, all named after the PNG: by default new files under outputs/;
    never an existing file unless --overwrite."""
    def named(png: Path) -> dict[str, Path]:
        return {"png": png, "csv": png.with_suffix(".csv"), "md": png.with_suffix(".md"),
                "settings": png.with_name(f"{png.stem}_settings.csv"),
                "tests": png.with_name(f"{png.stem}_tests.csv")}

    if out is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        candidates = [Path("outputs") / f"compare_{stamp}{suffix}.png" for suffix in
                      ["", *(f"_{i}" for i in range(2, 1000))]]
        files = next(named(p) for p in candidates if not any(f.exists() for f in named(p).values()))
    else:
        files = named(Path(out) if Path(out).suffix.lower() == ".png" else Path(f"{out}.png"))
    check_parent_folder(files["png"])
    existing = [str(p) for p in files.values() if p.exists()]
    if existing and not overwrite:
        raise UsageError(f"{' and '.join(existing)} already exist(s); choose another --out "
                         f"or pass --overwrite")
    return files


QD_AUC, CQD_SCORE = "qd_auc", "cqd_score"
# CQD score (Kent 2022, ribs.archives.cqd_score) with fixed settings, so that a number means the
# same in every table: target points drawn uniformly in the archive's measure box with this seed,
# penalties spread evenly over [0, 1], objectives normalised over [obj_min, obj_max], distances
# over the box's diagonal (obj_min is the task's QD offset, obj_max its `objective_max`). Written
# next to every comparison.
CQD = {"iterations": 1, "targets": 1000, "penalties": 10, "target_seed": 0}
SUMMARISED = ("qd_score", "coverage", "best_objective", SOLVED_CELLS, QD_AUC, CQD_SCORE)
TESTED = ("qd_score", QD_AUC, CQD_SCORE)  # pairwise between settings: final, anytime, spread
FEW_RUNS = 5


def cqd(run_dir: Path, task: Environment) -> float | None:
    """The CQD score of a run's final archive (None without a readable archive.pkl)."""
    from ribs.archives import cqd_score

    try:
        archive = read_pickle(run_dir / "archive.pkl", "archive pickle")
        lower, upper = archive.lower_bounds, archive.upper_bounds
    except (UsageError, AttributeError):
        return None
    targets = np.random.default_rng(CQD["target_seed"]).uniform(
        lower, upper, size=(CQD["iterations"], CQD["targets"], len(lower)))
    return float(cqd_score(archive, iterations=CQD["iterations"], target_points=targets,
                           penalties=CQD["penalties"], obj_min=task.qd_offset, obj_max=task.objective_max,
                           dist_max=float(np.linalg.norm(upper - lower))).mean)


def qd_auc(metrics: list[dict]) -> float:
    """Area under QD score against evaluations, from (0, 0), divided by the evaluations: the
    run's QD score averaged over its budget, which rewards reaching a score early."""
    evaluations = [0, *(row["evaluations"] for row in metrics)]
    return float(np.trapezoid([0, *(row["qd_score"] for row in metrics)], evaluations) / evaluations[-1])


def comparison_table(labels: list[str], run_dirs: list[Path], configs: list[RunConfig],
                     runs: list[list[dict]]):
    """One row per run: its final metrics, with the algorithm and seed that produced them."""
    import pandas as pd

    table = pd.DataFrame([
        {"run": label, "folder": str(run_dir), "setting": run_setting(config.to_json()),
         "seed": config.seed, "iterations": metrics[-1]["iteration"],
         **{key: metrics[-1][key] for key in COMPARED}, SOLVED_CELLS: solved_cells(run_dir, task_of(config)),
         QD_AUC: qd_auc(metrics), CQD_SCORE: cqd(run_dir, task_of(config))}
        for label, run_dir, config, metrics in zip(labels, run_dirs, configs, runs)
    ])
    for column in (SOLVED_CELLS, CQD_SCORE):
        table[column] = pd.to_numeric(table[column])  # None (no archive): NaN
    return table


def bootstrap_interval(values: np.ndarray) -> tuple[float, float]:
    """95% BCa bootstrap confidence interval of the mean (seeded, so repeatable)."""
    from scipy.stats import bootstrap

    if len(values) < 2:
        return math.nan, math.nan
    if np.ptp(values) == 0:
        return float(values[0]), float(values[0])
    result = bootstrap((values,), np.mean, confidence_level=0.95, n_resamples=9999, method="BCa",
                       rng=np.random.default_rng(0))
    return float(result.confidence_interval.low), float(result.confidence_interval.high)


def setting_statistics(table):
    """Per setting and summarised metric: runs, mean, median and the 95% interval of the mean."""
    import pandas as pd

    rows = []
    for setting, group in table.groupby("setting", sort=False):
        for metric in SUMMARISED:
            values = group[metric].dropna().to_numpy(dtype=float)
            low, high = bootstrap_interval(values)
            rows.append({"setting": setting, "metric": metric, "runs": len(values),
                         "mean": values.mean() if len(values) else math.nan,
                         "median": float(np.median(values)) if len(values) else math.nan,
                         "ci95_low": low, "ci95_high": high})
    return pd.DataFrame(rows)


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of p-values for testing them all at once."""
    adjusted, running = [0.0] * len(p_values), 0.0
    for rank, i in enumerate(np.argsort(p_values)):
        running = max(running, min(1.0, (len(p_values) - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def pairwise_tests(table):
    """Every pair of settings, on each TESTED metric: two-sided Mann-Whitney U, Holm-adjusted over
    the pairs, and Vargha-Delaney A12 (the chance that a run of A beats a run of B; 0.5: even)."""
    import pandas as pd
    from scipy.stats import mannwhitneyu

    settings, rows = list(dict.fromkeys(table["setting"])), []
    for metric in TESTED:
        block = []
        for a, b in itertools.combinations(settings, 2):
            x = table.loc[table["setting"] == a, metric].dropna().to_numpy(dtype=float)
            y = table.loc[table["setting"] == b, metric].dropna().to_numpy(dtype=float)
            if len(x) and len(y):
                test = mannwhitneyu(x, y, alternative="two-sided")
                block.append({"metric": metric, "setting_a": a, "setting_b": b, "runs_a": len(x),
                              "runs_b": len(y), "U": float(test.statistic), "p": float(test.pvalue),
                              "A12": float(test.statistic) / (len(x) * len(y))})
        for row, adjusted in zip(block, holm([row["p"] for row in block])):
            row["p_holm"] = adjusted
        rows += block
    return pd.DataFrame(rows, columns=["metric", "setting_a", "setting_b", "runs_a", "runs_b", "U",
                                       "p", "p_holm", "A12"])


METRIC_FORMATS = {"evaluations": "{:.0f}", "num_elites": "{:.0f}", "coverage": "{:.4f}",
                  "qd_score": "{:,.0f}", "best_objective": "{:.1f}", "mean_objective": "{:.1f}",
                  SOLVED_CELLS: "{:.0f}", QD_AUC: "{:,.0f}", CQD_SCORE: "{:.2f}"}


def format_table(table) -> str:
    """The table as aligned text, with as many digits as a reader compares."""
    shown = table.drop(columns=["folder"], errors="ignore")
    return shown.to_string(index=False, formatters={k: v.format for k, v in METRIC_FORMATS.items()
                                                    if k in shown})


def markdown_report(stats, tests, env: str) -> str:
    """The statistics as Markdown tables, ready for a README or a paper."""
    def cell(row) -> str:
        number = METRIC_FORMATS[row["metric"]].format
        interval = ("" if math.isnan(row["ci95_low"]) else
                    f" [{number(row['ci95_low'])}, {number(row['ci95_high'])}]")
        return f"{number(row['mean'])}{interval}"

    lines = ["| setting | runs | " + " | ".join(SUMMARISED) + " |",
             "| --- | --- |" + " --- |" * len(SUMMARISED)]
    for setting, group in stats.groupby("setting", sort=False):
        cells = {row["metric"]: cell(row) for row in group.to_dict("records")}
        lines.append(f"| {setting} | {group['runs'].max()} | "
                     + " | ".join(cells[m] for m in SUMMARISED) + " |")
    task = ENVIRONMENTS[env]
    lines += ["", f"{env}. Mean [95% bootstrap confidence interval of the mean, BCa] over each "
                  f"setting's runs. solved_cells: cells whose elite returns at least {task.solved:g}.",
              f"CQD score: {CQD['targets']:,} target points drawn uniformly in the measure box "
              f"(seed {CQD['target_seed']}), {CQD['penalties']} distance penalties, objectives "
              f"normalised over [{task.qd_offset:g}, {task.objective_max:g}].", ""]
    if len(tests):
        lines += ["| metric | A | B | U | p (Holm) | A12 |", "| --- | --- | --- | --- | --- | --- |"]
        lines += [f"| {t['metric']} | {t['setting_a']} | {t['setting_b']} | {t['U']:.1f} | "
                  f"{t['p_holm']:.3g} | {t['A12']:.2f} |" for t in tests.to_dict("records")]
        lines += ["", "Two-sided Mann-Whitney U tests, Holm-adjusted over the pairs of each metric; "
                  "A12: the chance that a run of A beats a run of B (0.5: even; 0.71 or more, or "
                  "0.29 or less: a large effect)."]
        floor = holm_floor(tests)
        if floor > 0.05:
            lines += ["", f"With so few runs per setting, no pair can reach p < 0.05 after Holm's "
                          f"adjustment: the smallest adjusted p possible here is {floor:.3g} (a "
                          f"complete separation, A12 of 0 or 1). Read the effect sizes and the "
                          f"intervals; more seeds give the tests power."]
    return "\n".join(lines) + "\n"


def holm_floor(tests) -> float:
    """The smallest Holm-adjusted p-value any pair of a metric could reach: the exact two-sided
    Mann-Whitney p of a complete separation, 2 / C(n_a + n_b, n_a), times the number of pairs."""
    pairs = tests[tests["metric"] == tests["metric"].iloc[0]]
    return min(1.0, len(pairs) * min(2 / math.comb(int(a + b), int(a))
                                     for a, b in zip(pairs["runs_a"], pairs["runs_b"])))


def expand_folders(paths: list[Path]) -> list[Path]:
    """Run folders, each experiment folder replaced by its runs that have metrics; a run given
    twice (a folder named twice, or a run and its experiment) is counted once, and a note says so."""
    expanded: dict[Path, Path] = {}
    for path in paths:
        if (path / "experiment.json").is_file():
            runs = [path / entry["name"] for entry in read_experiment(path)["runs"]]
            runs = [run for run in runs if (run / "metrics.json").is_file()]
        else:
            runs = [path]
        for run in runs:
            if (key := run.resolve()) in expanded:
                print(f"note: {run} is given twice (the same run as {expanded[key]}); counted once")
            else:
                expanded[key] = run
    return list(expanded.values())


def one_task(paths: list[Path], configs: list[RunConfig]) -> str:
    """The task every run flew: returns of different tasks share no scale, so they are not
    pooled in one table."""
    tasks = {config.env: path for path, config in zip(paths, configs)}
    if len(tasks) > 1:
        raise UsageError("these runs flew different tasks (" + ", ".join(
            f"{path}: {env}" for env, path in tasks.items()) + "); compare each task's runs apart")
    return next(iter(tasks))


def compare(*run_dirs: str, out: str | None = None, overwrite: bool = False) -> None:
    """Compare runs: QD score, coverage and best objective against evaluations on one PNG, and a
    table of their final values (printed, and written as CSV next to the PNG).

    Runs of one setting (the same algorithm and flags, other seeds; an experiment's runs) are
    grouped: the PNG shows their mean with a 95% confidence band, and per setting the number of
    runs, mean, median and 95% bootstrap interval of QD score, coverage, best objective, solved
    cells, QD-score AUC and CQD score are printed and written (OUT_settings.csv); between
    settings, Mann-Whitney U tests on final QD score, QD-score AUC (how soon it got there) and
    CQD score, Holm-adjusted, with Vargha-Delaney A12 (OUT_tests.csv); and both as Markdown
    (OUT.md). Runs of the same batch, iterations and env seed give an equal-budget comparison.

    Args:
        run_dirs: Run folders or experiment folders written by this script.
        out: The PNG to write (the other files get the same name); default: a new
            outputs/compare_<timestamp>.png.
        overwrite: Replace those files if they already exist.
    """
    if not run_dirs:
        raise UsageError("compare needs at least one run folder: "
                         "python lunar_lander.py compare RUN_A RUN_B ...")
    overwrite = boolean("overwrite", overwrite)
    paths = expand_folders([Path(str(run_dir)) for run_dir in run_dirs])
    if not paths:
        raise UsageError(f"no run with metrics in {', '.join(map(str, run_dirs))}")
    configs, runs = zip(*(load_run_metrics(path) for path in paths))
    env = one_task(paths, configs)
    files = comparison_outputs(None if out is None else str(out), overwrite)
    labels = run_labels(paths, list(configs))
    table = comparison_table(labels, paths, list(configs), list(runs))
    grouped = table["setting"].duplicated().any()
    groups: dict[str, list] = {}
    for label, setting, metrics in zip(labels, table["setting"], runs):
        groups.setdefault(setting if grouped else label, []).append(metrics)
    save_metric_panels(groups, "evaluations", "Evaluations", files["png"])
    write_csv(files["csv"], table)
    print(format_table(table.drop(columns=["setting"])))  # the run's label names its setting
    if table["evaluations"].nunique() > 1:
        print("note: the runs end at different numbers of evaluations; compare at an equal budget")
    written = [files["png"], files["csv"]]
    if grouped:
        stats, tests = setting_statistics(table), pairwise_tests(table)
        write_csv(files["settings"], stats)
        write_csv(files["tests"], tests)
        atomic_write(files["md"], lambda f: f.write(markdown_report(stats, tests, env)), mode="w")
        print("\nper setting: mean [95% bootstrap interval of the mean] over its runs\n"
              + markdown_report(stats, tests, env))
        sizes = table["setting"].value_counts()
        if (few := sizes[sizes < FEW_RUNS]).size:
            print(f"note: {', '.join(f'{s} ({n} runs)' for s, n in few.items())}: fewer than "
                  f"{FEW_RUNS} runs; the intervals are wide and the tests can hardly reject anything")
        written += [files["settings"], files["tests"], files["md"]]
    print(f"wrote {', '.join(map(str, written))}")
