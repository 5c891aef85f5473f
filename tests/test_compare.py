"""compare: the table of final values and the pictures, the labels that group runs into settings,
and the statistics across seeds (BCa intervals per metric, Mann-Whitney with Holm, A12; rliable's
IQM and P(A>B) with stratified bootstrap intervals), each checked against its definition; runs of
two tasks compared at once, and the corrected metrics (--corrected). (An experiment's folder
through compare: test_experiment.py.)"""

import csv
import json
import re
import shutil
import warnings

import matplotlib.image
import numpy as np
import pandas as pd
import pytest
from scipy.stats import bootstrap, mannwhitneyu, trim_mean

from qdsearch import tasks
from qdsearch.analysis import comparison, stats
from qdsearch.base.flags import UsageError
from qdsearch.cli import commands
from qdsearch.config import options
from qdsearch.search import experiments
from util import (
    LANDER,
    assert_one_line_error,
    folder_state,
    run_metrics,
    saved_archive,
    tiny_flags,
)

WALKER = "BipedalWalker-v3"


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory, dask_cluster, tiny_run):
    """The tiny run (cma_me) and its cma_mae twin."""
    mae = tmp_path_factory.mktemp("compare") / "cma_mae"
    commands.search(**tiny_flags(dask_cluster, algorithm="cma_mae"), outdir=str(mae))
    return [tiny_run, mae]


def test_compare_writes_png_and_table(run_cli, tmp_path, two_runs):
    result = run_cli("compare", *two_runs)

    assert result.returncode == 0, result.stderr
    pngs = [png for png in (tmp_path / "outputs").glob("compare_*.png") if not png.stem.endswith("_scores")]
    assert len(pngs) == 1 and pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert_real_picture(pngs[0].with_name(f"{pngs[0].stem}_scores.png"))
    with open(pngs[0].with_suffix(".csv")) as file:
        rows = list(csv.DictReader(file))
    labels = ["cma_me seed 7", "cma_mae learning_rate=0.5 seed 7"]  # less the flags both share
    assert [row["run"] for row in rows] == labels
    for row, run_dir in zip(rows, two_runs):
        final = run_metrics(run_dir)[-1]
        assert int(row["evaluations"]) == final["evaluations"] == 36
        assert float(row["qd_score"]) == pytest.approx(final["qd_score"])
        assert float(row["coverage"]) == pytest.approx(final["coverage"])
        assert float(row["best_objective"]) == pytest.approx(final["best_objective"])
        objectives = saved_archive(run_dir).data("objective")
        assert int(row["solved_cells"]) == int((objectives >= 200).sum())
    assert labels[0] in result.stdout and labels[1] in result.stdout
    assert f"{final['qd_score']:,.0f}" in result.stdout

    before = folder_state(tmp_path / "outputs")
    assert_one_line_error(run_cli("compare", *two_runs, "--out", pngs[0]), "already exist", "--overwrite")
    assert folder_state(tmp_path / "outputs") == before
    assert run_cli("compare", *two_runs, "--out", pngs[0], "--overwrite").returncode == 0


def test_compare_refuses_bad_run_folders(run_cli, tmp_path, tiny_run):
    (tmp_path / "empty").mkdir()
    (tmp_path / "no_metrics").mkdir()
    (tmp_path / "no_metrics" / "config.json").write_text("{}")
    (tmp_path / "no_metrics" / "metrics.json").write_text("[]")
    for bad, words in [("missing", "no such run folder"), ("empty", "metrics.json: no such file"),
                       ("no_metrics", "no metrics")]:
        assert_one_line_error(run_cli("compare", tiny_run, tmp_path / bad), bad, words)
    assert_one_line_error(run_cli("compare"), "at least one run folder")
    assert not (tmp_path / "outputs").exists()


def test_runs_are_labelled_by_the_flags_that_shape_them():
    defaults, label = options.search_defaults(), experiments.run_setting
    # An algorithm's own flag is always named: the label does not change with the default.
    assert label({**defaults, "algorithm": "cma_mae"}) == f"cma_mae learning_rate={defaults['learning_rate']}"
    assert label({**defaults, "algorithm": "cma_me"}) == "cma_me"
    assert label({**defaults, "algorithm": "cma_mae", "learning_rate": 0.3, "seed": 3,
                  "iterations": 9}) == "cma_mae learning_rate=0.3"
    assert label({"algorithm": "cma_me", "seed": 1}) == "cma_me"  # older config.json
    # from before --learning_rate: it ran at 0.01, not at today's default
    assert label({"algorithm": "cma_mae", "seed": 1}) == "cma_mae learning_rate=0.01"
    # the flags keep the order labels have always had
    assert label({**defaults, "sigma0": 0.5, "batch_size": 6, "grid": 20, "env_seed": "0-1"}) == (
        "cma_me env_seed=0,1 grid=20 batch_size=6 sigma0=0.5")


def runs_table(settings: dict[str, dict[str, list[float]]]) -> pd.DataFrame:
    """A comparison table (a row per run) with the given values of each metric per setting."""
    rows = []
    for setting, metrics in settings.items():
        count = len(next(iter(metrics.values())))
        rows += [{"task": LANDER, "setting": setting,
                  **{metric: values[i] for metric, values in metrics.items()}} for i in range(count)]
    return pd.DataFrame(rows)


def a12(x, y) -> float:
    """Vargha-Delaney A12 by its definition: wins count 1, ties count a half."""
    return float(np.mean([(a > b) + 0.5 * (a == b) for a in x for b in y]))


def test_a12_counts_ties_as_half_a_win():
    metrics = {"qd_score": [1.0, 2.0], comparison.QD_AUC: [1.0, 2.0], comparison.CQD_SCORE: [5.0, 5.0]}
    table = runs_table({"A": metrics, "B": {**metrics, "qd_score": [1.0, 3.0]},
                        "C": metrics})  # C: the same runs as A
    tests = comparison.pairwise_tests(table)
    qd = tests[tests["metric"] == "qd_score"].set_index(["setting_a", "setting_b"])
    assert qd.loc[("A", "B"), "A12"] == pytest.approx(0.375) == a12([1, 2], [1, 3])
    assert qd.loc[("A", "B"), "p_improvement"] == pytest.approx(0.375)  # one task: P(A>B) is A12
    assert qd.loc[("A", "C"), "A12"] == 0.5 and qd.loc[("A", "C"), "p"] == 1.0
    tied = tests[tests["metric"] == comparison.CQD_SCORE]
    assert (tied["A12"] == 0.5).all()  # every run of every setting ties


def test_pairwise_tests_are_mann_whitney_with_holm():
    rng = np.random.default_rng(3)
    table = runs_table({name: {metric: list(rng.normal(shift, 1, 6)) for metric in comparison.TESTED}
                        for name, shift in (("A", 0.0), ("B", 1.5), ("C", 3.0))})
    tests = comparison.pairwise_tests(table)
    assert len(tests) == 3 * len(comparison.TESTED)
    for metric in comparison.TESTED:
        block = tests[tests["metric"] == metric]
        for row in block.to_dict("records"):
            x = table.loc[table["setting"] == row["setting_a"], metric]
            y = table.loc[table["setting"] == row["setting_b"], metric]
            assert row["p"] == pytest.approx(mannwhitneyu(x, y, alternative="two-sided").pvalue)
            assert row["A12"] == pytest.approx(a12(x, y)) == pytest.approx(row["p_improvement"])
            assert 0 <= row["p_improvement_low"] <= row["A12"] <= row["p_improvement_high"] <= 1
        assert block["p_holm"].tolist() == pytest.approx(stats.holm(block["p"].tolist()))


def test_a_baseline_is_tested_against_each_other_setting_alone():
    rng = np.random.default_rng(3)
    table = runs_table({name: {metric: list(rng.normal(shift, 1, 6)) for metric in comparison.TESTED}
                        for name, shift in (("A", 0.0), ("B", 1.5), ("C", 3.0), ("D", 0.5))})
    every, against = comparison.pairwise_tests(table), comparison.pairwise_tests(table, baseline="B")
    block = against[against["metric"] == "qd_score"]
    assert list(zip(block["setting_a"], block["setting_b"])) == [("B", "A"), ("B", "C"), ("B", "D")]
    assert block["p_holm"].tolist() == pytest.approx(stats.holm(block["p"].tolist()))  # over 3, not 6
    same = every[every["metric"] == "qd_score"].set_index(["setting_a", "setting_b"])
    assert block["p"].tolist() == pytest.approx([same.loc[("A", "B"), "p"], same.loc[("B", "C"), "p"],
                                                 same.loc[("B", "D"), "p"]])
    with pytest.raises(UsageError, match="--baseline 'E' is not a setting of these runs"):
        comparison.check_baseline("E", ["A", "B"])
    # an algorithm names its setting when one setting has it, and only then
    labels = ["cma_me n_emitters=2", "cma_mae n_emitters=2 learning_rate=0.5",
              "cma_mae n_emitters=2 learning_rate=0.1"]
    assert comparison.check_baseline("cma_me", labels) == "cma_me n_emitters=2"
    with pytest.raises(UsageError, match="is not a setting of these runs"):
        comparison.check_baseline("cma_mae", labels)


def test_every_metrics_interval_is_bootstrapped_from_its_own_values():
    rng = np.random.default_rng(5)
    # Each metric on its own scale: an interval from another metric's column cannot fit.
    scales = {metric: 10.0 ** (2 * i) for i, metric in enumerate(comparison.SUMMARISED)}
    table = runs_table({"A": {m: list(rng.uniform(1, 2, 6) * s) for m, s in scales.items()},
                        "B": {m: list(rng.uniform(2, 3, 5) * s) for m, s in scales.items()}})
    stats = comparison.setting_statistics(table)
    assert len(stats) == 2 * len(comparison.SUMMARISED)
    for row in stats.to_dict("records"):
        values = table.loc[table["setting"] == row["setting"], row["metric"]].to_numpy()
        assert row["runs"] == len(values) and row["mean"] == pytest.approx(values.mean())
        assert row["median"] == pytest.approx(np.median(values))
        expected = bootstrap((values,), np.mean, confidence_level=0.95, n_resamples=9999,
                             method="BCa", rng=np.random.default_rng(0)).confidence_interval
        assert (row["ci95_low"], row["ci95_high"]) == pytest.approx((expected.low, expected.high))
        assert values.min() <= row["ci95_low"] <= row["mean"] <= row["ci95_high"] <= values.max()
        assert row["iqm"] == pytest.approx(trim_mean(values, 0.25))
        assert values.min() <= row["iqm_low"] <= row["iqm"] <= row["iqm_high"] <= values.max()


def test_holm_and_auc_by_hand():
    assert stats.holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    metrics = [{"evaluations": 10, "qd_score": 100.0}, {"evaluations": 20, "qd_score": 300.0}]
    assert comparison.qd_auc(metrics) == pytest.approx((0.5 * 10 * 100 + 10 * 200) / 20)
    five_each = pd.DataFrame([{"metric": "qd_score", "runs_a": 5, "runs_b": 5}] * 10)
    assert stats.holm_floor(five_each) == pytest.approx(10 * 2 / 252)  # 5 seeds, 5 settings: 0.079


def test_the_holm_floor_is_at_most_one():
    """Five settings of one run each: a complete separation's p of 1 (2 / C(2, 1)), ten pairs."""
    one_each = pd.DataFrame([{"metric": "qd_score", "runs_a": 1, "runs_b": 1}] * 10)
    assert stats.holm_floor(one_each) == 1.0
    # the pairs of the table's first metric (a metric without values in a setting has fewer)
    fewer = pd.DataFrame([{"metric": "qd_score", "runs_a": 3, "runs_b": 3}]
                         + [{"metric": "coverage", "runs_a": 3, "runs_b": 3}] * 3)
    assert stats.holm_floor(fewer) == pytest.approx(2 / 20)


def test_two_runs_a_setting_have_an_interval():
    """Two runs a task are resampled (one is not): every interval is there, around its point."""
    for point, low, high in (stats.mean_interval([[1.0, 3.0]]), stats.iqm_interval([[1.0, 3.0]]),
                             stats.improvement_interval([[1.0, 3.0]], [[2.0, 2.5]])):
        assert low <= point <= high and low < high
    assert stats.bootstrap_interval(np.array([4.0, 4.0])) == (4.0, 4.0)


def test_a_task_one_setting_has_no_runs_of_is_left_out_of_its_improvement():
    with_empty = stats.improvement_interval([[1.0, 5.0], [3.0, 4.0]], [[2.0, 3.0], []])
    assert with_empty == stats.improvement_interval([[1.0, 5.0]], [[2.0, 3.0]])


def test_the_iqm_of_no_runs_is_nan_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(stats.iqm([])) and np.isnan(stats.iqm([[]]))


def assert_real_picture(path) -> None:
    """A PNG that matplotlib reads back as an image with something drawn on it."""
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100, image.shape
    assert image[..., :3].std() > 0.05  # not a blank canvas


def test_iqm_is_the_mean_of_the_middle_half():
    # scipy's trim_mean cuts int(0.25 n) scores from each end: 2 of 8, 2 of 10, 1 of 7
    assert stats.iqm(np.arange(1, 9)) == pytest.approx(np.mean([3, 4, 5, 6])) == 4.5
    assert stats.iqm(np.arange(1, 11)) == pytest.approx(np.mean([3, 4, 5, 6, 7, 8]))
    assert stats.iqm([5, 1, 7, 3, 2, 6, 4]) == pytest.approx(np.mean([2, 3, 4, 5, 6]))
    assert stats.iqm([1, 2, 3, 4, 5, 6, 7, 10_000]) == 4.5  # a run that flew off moves it not at all
    assert stats.iqm([np.array([1, 2, 3, 4]), np.array([5, 6, 7, 8])]) == 4.5  # tasks pooled
    assert stats.task_mean([np.array([0.0, 0.0, 0.0]), np.array([1.0])]) == 0.5  # of the tasks' means


def test_the_stratified_bootstrap_never_resamples_across_tasks():
    zeros, ones = np.zeros(4), np.ones(6)
    # Every resample keeps 4 runs of the first task (all 0) and 6 of the second (all 1): the IQM
    # of the 10, 2 cut from each end, is that of 0 0 1 1 1 1, 2/3, in every resample. Drawn from
    # the pool of 10, the resamples' counts would vary, and so would their IQM.
    assert stats.iqm_interval([zeros, ones]) == pytest.approx((2 / 3, 2 / 3, 2 / 3))
    assert stats.mean_interval([zeros, ones]) == pytest.approx((0.5, 0.5, 0.5))
    first, second = stats.stratified_resamples([np.arange(4.0), 10 + np.arange(6.0)],
                                               np.random.default_rng(0), 500)
    assert first.shape == (500, 4) and second.shape == (500, 6)
    assert set(np.unique(first)) == {0, 1, 2, 3} and set(np.unique(second)) == {10, 11, 12, 13, 14, 15}
    pooled = np.random.default_rng(0).choice(np.r_[zeros, ones], size=(500, 10))
    assert np.ptp(trim_mean(pooled, 0.25, axis=1)) > 0  # what stratifying prevents


def test_the_iqm_interval_is_rliables_percentile_bootstrap():
    rng = np.random.default_rng(9)
    per_task = [rng.normal(0, 1, 5), rng.normal(3, 2, 8)]
    point, low, high = stats.iqm_interval(per_task, resamples=300)
    resamples = stats.stratified_resamples(per_task, np.random.default_rng(stats.SEED), 300)
    by_hand = [trim_mean(np.concatenate([task[r] for task in resamples]), 0.25) for r in range(300)]
    assert point == pytest.approx(trim_mean(np.concatenate(per_task), 0.25))
    assert (low, high) == pytest.approx(tuple(np.percentile(by_hand, [2.5, 97.5])))
    assert low < point < high
    assert np.isnan(stats.iqm_interval([[3.0], [4.0]])[1])  # one run a task: nothing to resample


def test_probability_of_improvement_counts_ties_as_half():
    # wins: 2 > 1; ties: 1 = 1 (a half); of 4 pairs: 1.5 / 4
    assert stats.probability_of_improvement([[1, 2]], [[1, 3]]) == 0.375 == a12([1, 2], [1, 3])
    assert stats.probability_of_improvement([[4, 4]], [[4, 4]]) == 0.5  # all tied
    # averaged over tasks: every run of A beats B's in the first, all tie in the second
    assert stats.probability_of_improvement([[5, 6], [1, 1]], [[1, 2], [1, 1]]) == 0.75
    x, y = np.array([3.0, 1.0, 4.0, 1.0, 5.0]), np.array([1.0, 2.0, 6.0])
    assert stats.probability_of_improvement([x], [y]) == pytest.approx(
        mannwhitneyu(x, y).statistic / (len(x) * len(y)))
    assert stats.improvement_interval([[5, 6, 7]], [[1, 2]]) == (1.0, 1.0, 1.0)  # always ahead
    point, low, high = stats.improvement_interval([x, [1, 1]], [y, [1, 1]])
    assert point == pytest.approx((a12(x, y) + 0.5) / 2) and low < point < high


def config_of(run_dir) -> dict:
    return json.loads((run_dir / "config.json").read_text())


def normalised(row: dict, run_dir) -> float:
    """QD score / (cells x (objective_max - qd_offset)), by hand from the run's config.json."""
    config, task = config_of(run_dir), tasks.ENVIRONMENTS[config_of(run_dir)["env"]]
    cells = config["grid"] ** len(config["measures"]) if config["archive"] == "grid" else config["cells"]
    return float(row["qd_score"]) / (cells * (task.objective_max - task.qd_offset))


@pytest.fixture(scope="module")
def walker_run(tmp_path_factory, dask_cluster):
    """A tiny run (1 iteration) of another task: the walker, with the tiny run's setting (and
    its task's own episodes: a setting that names the same flags as the lander's)."""
    folder = tmp_path_factory.mktemp("walker") / "cma_me"
    commands.search(**tiny_flags(dask_cluster, env=WALKER, iterations=1, log_every=1, episode_length=None),
               outdir=str(folder))
    return folder


def test_compare_pools_two_tasks_per_setting(run_cli, tmp_path, two_runs, walker_run):
    result = run_cli("compare", *two_runs, walker_run, "--out", tmp_path / "both")

    assert result.returncode == 0, result.stderr
    table = pd.read_csv(tmp_path / "both.csv")
    me, mae = "cma_me", "cma_mae learning_rate=0.5"  # less what every setting shares
    assert table["task"].tolist() == [LANDER, LANDER, WALKER]
    assert table["run"].tolist() == [f"{LANDER}: {me} seed 7", f"{LANDER}: {mae} seed 7",
                                     f"{WALKER}: {me} seed 7"]
    for row, run_dir in zip(table.to_dict("records"), [*two_runs, walker_run]):
        assert row["qd_score"] == pytest.approx(run_metrics(run_dir)[-1]["qd_score"])
        assert row["normalised_qd_score"] == pytest.approx(normalised(row, run_dir))
        assert 0 < row["normalised_qd_score"] <= 1
    settings, tests = pd.read_csv(tmp_path / "both_settings.csv"), pd.read_csv(tmp_path / "both_tests.csv")
    assert settings.groupby("task")["setting"].nunique().to_dict() == {LANDER: 2, WALKER: 1}
    assert set(tests["task"]) == {LANDER}  # the walker has one setting: nothing to test
    assert {"iqm", "iqm_low", "iqm_high"} <= set(settings) and "p_improvement" in tests

    aggregate = pd.read_csv(tmp_path / "both_aggregate.csv")
    per_setting = aggregate[aggregate["statistic"] != "p_improvement"].set_index(
        ["setting", "metric", "statistic"])
    assert per_setting.loc[(me, "normalised_qd_score", "iqm"), ["tasks", "runs"]].tolist() == [2, 2]
    assert per_setting.loc[(mae, "coverage", "mean"), ["tasks", "runs"]].tolist() == [1, 1]
    mine = table.loc[table["setting"] == me, "normalised_qd_score"]
    # two runs, one of each task: nothing cut, the IQM and the mean of the tasks' means are their mean
    assert per_setting.loc[(me, "normalised_qd_score", "iqm"), "value"] == pytest.approx(mine.mean())
    assert per_setting.loc[(me, "coverage", "mean"), "value"] == pytest.approx(
        table.loc[table["setting"] == me, "coverage"].mean())
    assert aggregate["value"].between(0, 1).all()
    [versus] = aggregate[aggregate["statistic"] == "p_improvement"].to_dict("records")
    lander = table[table["task"] == LANDER].set_index("setting")["normalised_qd_score"]
    assert (versus["setting"], versus["versus"], versus["tasks"]) == (me, mae, 1)  # the task both have
    assert versus["value"] == a12([lander[me]], [lander[mae]])

    report = (tmp_path / "both.md").read_text()
    assert f"## {LANDER}" in report and f"## {WALKER}" in report and "## All tasks" in report
    assert f"{mae} has no runs of {WALKER}: aggregated over the tasks it has" in report
    assert "IQM [95% stratified bootstrap interval]" in report and "P(A>B)" in report
    assert_real_picture(tmp_path / "both_scores.png")
    assert_real_picture(tmp_path / "both.png")
    height, width, _ = matplotlib.image.imread(tmp_path / "both_scores.png").shape
    assert width > 1.5 * height  # a panel per task, side by side


CORRECTED = {"qd_score": 12345.0, "coverage": 0.25, "num_elites": 625, "best_objective": 111.5,
             "mean_objective": -42.0, "repeats": 10, "env_seeds": list(range(10))}


def corrected_copy(run_dir, where, numbers: dict, solved: int | None):
    """A copy of a run with corrected.json holding `numbers`; with `solved` set, a corrected
    archive too: archive.npz as it is, archive.csv with `solved` elites at 250 and the rest at -50."""
    shutil.copytree(run_dir, where)
    iteration = run_metrics(run_dir)[-1]["iteration"]
    (where / "corrected.json").write_text(json.dumps({"iteration": iteration, **numbers}))
    if solved is not None:
        shutil.copy(where / "archive.npz", where / "corrected_archive.npz")
        archive = pd.read_csv(where / "archive.csv")
        archive["objective"] = [250.0] * solved + [-50.0] * (len(archive) - solved)
        archive.to_csv(where / "corrected_archive.csv", index=False)
    return where


def test_compare_corrected_uses_each_runs_corrected_metrics(run_cli, tmp_path, tiny_run):
    first = corrected_copy(tiny_run, tmp_path / "a", CORRECTED, solved=3)
    second = corrected_copy(tiny_run, tmp_path / "b", {**CORRECTED, "qd_score": 20000.0, "coverage": 0.5},
                            solved=None)
    plain = run_cli("compare", first, second, "--out", tmp_path / "plain")
    result = run_cli("compare", first, second, "--corrected", "--out", tmp_path / "fixed")

    assert plain.returncode == 0 and result.returncode == 0, result.stderr
    table, own = pd.read_csv(tmp_path / "fixed.csv"), pd.read_csv(tmp_path / "plain.csv")
    assert table["qd_score"].tolist() == [12345.0, 20000.0] and table["coverage"].tolist() == [0.25, 0.5]
    row = table.iloc[0].to_dict()
    assert (row["num_elites"], row["best_objective"], row["mean_objective"]) == (625, 111.5, -42.0)
    assert row["normalised_qd_score"] == pytest.approx(normalised({"qd_score": 12345.0}, tiny_run))
    assert row["solved_cells"] == 3  # from corrected_archive.csv
    assert row["cqd_score"] == pytest.approx(own["cqd_score"][0])  # corrected_archive.npz: a copy
    assert table["qd_auc"].tolist() == pytest.approx(own["qd_auc"].tolist())  # still metrics.json's curve
    assert own["qd_score"].tolist() == [run_metrics(tiny_run)[-1]["qd_score"]] * 2
    assert np.isnan(table["cqd_score"][1]) and np.isnan(table["solved_cells"][1])  # no corrected archive
    assert f"{second}: no readable corrected_archive.npz; left out of the score" in result.stdout
    stats_table = pd.read_csv(tmp_path / "fixed_settings.csv").set_index("metric")
    assert stats_table.loc["qd_score", "mean"] == pytest.approx((12345.0 + 20000.0) / 2)
    assert "corrected metrics (corrected.json: its elites flown again on 10 new seeds)" in (
        tmp_path / "fixed.md").read_text()
    assert "last row of metrics.json" in (tmp_path / "plain.md").read_text()
    assert_real_picture(tmp_path / "fixed_scores.png")


def test_compare_corrected_refuses_a_run_without_corrected_metrics(run_cli, tmp_path, tiny_run):
    fixed = corrected_copy(tiny_run, tmp_path / "a", CORRECTED, solved=1)
    assert_one_line_error(run_cli("compare", fixed, tiny_run, "--corrected", "--out", tmp_path / "c"),
                          f"{tiny_run} has no corrected.json",
                          f"run `python lunar_lander.py evaluate {tiny_run} --corrected` first")
    (fixed / "corrected.json").write_text(json.dumps({**CORRECTED, "coverage": "high"}))
    assert_one_line_error(run_cli("compare", fixed, "--corrected", "--out", tmp_path / "c"),
                          "corrected.json: coverage is 'high', not float")
    (fixed / "corrected.json").write_text(json.dumps({**CORRECTED, "iteration": 2}))
    assert_one_line_error(run_cli("compare", fixed, "--corrected", "--out", tmp_path / "c"),
                          "corrected.json is of iteration 2, the run is at 3", "--corrected` again")
    assert not list(tmp_path.glob("c*"))


def test_at_evaluations_keeps_the_row_at_exactly_that_budget(run_cli, tmp_path, tiny_run):
    """A budget that a row reached exactly is met by that row, not the one before it."""
    rows = run_metrics(tiny_run)
    at = rows[1]["evaluations"]
    result = run_cli("compare", tiny_run, "--at_evaluations", str(at), "--out", tmp_path / "cut")
    assert result.returncode == 0, result.stderr
    [row] = pd.read_csv(tmp_path / "cut.csv").to_dict("records")
    assert (row["evaluations"], row["iterations"]) == (at, 2)
    assert row["qd_score"] == pytest.approx(rows[1]["qd_score"], rel=1e-12)


def written_run(folder, evaluations=(12, 24, 36)):
    """A run folder of the lander's config and metrics rows of a real (empty) grid archive, one per
    budget in `evaluations`, written as the search writes them: what compare reads of a run."""
    from qdsearch import algorithms
    from qdsearch.base.run_files import write_json
    from qdsearch.config import run_config
    from qdsearch.store import metrics

    config = run_config.check_run_config(options.with_task({**options.search_defaults(), "seed": 7}))
    folder.mkdir(parents=True)
    run_config.write_config(folder, config)
    archive = algorithms.ARCHIVES["grid"]["make"](config)(seed=1)
    rows = [metrics.iteration_metrics(archive, i + 1, spent, 0.5 * i) for i, spent in enumerate(evaluations)]
    write_json(folder / "metrics.json", rows)
    return folder, rows


def test_a_budget_cuts_each_runs_metrics_at_its_last_row_within_it(tmp_path):
    from qdsearch.analysis import compared_runs

    (one, rows), (two, _) = written_run(tmp_path / "one"), written_run(tmp_path / "two", (10, 20))
    config, read = compared_runs.load_run_metrics(one)
    assert read == rows and config.seed == 7
    runs = [rows, run_metrics(two)]
    assert compared_runs.cut_at(runs, [one, two], None, False) == (runs, [False, False])
    kept, short = compared_runs.cut_at(runs, [one, two], 24, False)
    assert kept == [rows[:2], runs[1]] and short == [True, False]
    with pytest.raises(UsageError, match=re.escape(f"{one}: its first iteration flew 12 evaluations, "
                                                   f"more than --at_evaluations 11")):
        compared_runs.cut_at(runs, [one, two], 11, False)
    assert compared_runs.cut_at([rows], [one], 12, False) == ([rows[:1]], [True])  # the first, exactly
    assert compared_runs.cut_at([rows], [one], 10**12, False) == ([rows], [False])
    for budget, said in ((0, "--at_evaluations must be a positive whole number, got 0"),
                         (10**12 + 1, "--at_evaluations must be at most 1,000,000,000,000, got 10000")):
        with pytest.raises(UsageError, match=re.escape(said)):
            compared_runs.cut_at([rows], [one], budget, False)
    with pytest.raises(UsageError, match="^--at_evaluations and --corrected: corrected figures are of a "
                                         "run's end$"):
        compared_runs.cut_at(runs, [one, two], 24, True)
    # A warm start's row 0 (its elites flown again) is not its first iteration; a run of it alone is
    warm = [{**rows[0], "iteration": 0, "evaluations": 30}, {**rows[1], "evaluations": 42}]
    for metrics, flew, budget in ((warm, 42, 35), (warm[:1], 30, 25)):
        with pytest.raises(UsageError, match=f"its first iteration flew {flew} evaluations"):
            compared_runs.cut_at([metrics], [one], budget, False)


def test_an_experiment_is_its_runs_with_metrics_each_counted_once(tmp_path, capsys):
    from qdsearch.analysis import compared_runs
    from qdsearch.base.run_files import write_json
    from qdsearch.search.experiment_folder import EXPERIMENT_FORMAT

    folder = tmp_path / "exp"
    done, _ = written_run(folder / "done")
    (folder / "pending").mkdir()
    runs = [{"name": name, "config": {"iterations": 3, "seed": 7}, "state": state, "setting": "cma_me"}
            for name, state in (("done", "done"), ("pending", "pending"))]
    write_json(folder / "experiment.json", {"format": EXPERIMENT_FORMAT, "runs": runs, "workers": 1})
    alone, _ = written_run(tmp_path / "alone")
    again = tmp_path / "exp" / ".." / "alone"
    assert compared_runs.expand_folders([folder, alone, done, again]) == [done, alone]
    said = capsys.readouterr().out.splitlines()
    assert said[0].startswith(f"note: {folder}: 1 of 2 runs of its plan are not done: pending (pending)")
    assert said[1:] == [f"note: {done} is given twice (the same run as {done}); counted once",
                        f"note: {again} is given twice (the same run as {alone}); counted once"]


def test_corrected_metrics_are_read_checked_and_of_the_runs_last_iteration(tmp_path):
    from qdsearch.analysis import compared_runs
    from qdsearch.base.run_files import write_json

    run_dir, rows = written_run(tmp_path / "run")
    with pytest.raises(UsageError, match=re.escape(f"{run_dir} has no corrected.json: run `python "
                                                   f"lunar_lander.py evaluate {run_dir} --corrected` first")):
        compared_runs.read_corrected(run_dir)
    path = run_dir / "corrected.json"
    again = f"run `python lunar_lander.py evaluate {run_dir} --corrected` again"
    for recorded, said in ((["a"], f"{path}: holds a list, not corrected metrics"),
                           ({**CORRECTED, "repeats": 1.5}, f"{path}: repeats is 1.5, not int; {again}"),
                           ({**CORRECTED, "repeats": None}, f"{path}: repeats is None, not int;"),
                           ({"coverage": 0.5}, f"{path}: qd_score is "),
                           ({**CORRECTED, "coverage": "high"}, f"{path}: coverage is 'high', not float;"),
                           ({**CORRECTED, "best_objective": "x"},
                            f"{path}: best_objective is 'x', not float or NoneType;")):
        write_json(path, recorded)
        with pytest.raises(UsageError, match="^" + re.escape(said)):
            compared_runs.read_corrected(run_dir)
    fix = {**CORRECTED, "repeats": 3, "iteration": 3, "best_objective": None}
    write_json(path, fix)
    assert compared_runs.read_corrected(run_dir) == fix
    compared_runs.check_fresh([fix], [rows], [run_dir])
    with pytest.raises(UsageError, match=re.escape(f"{path} is of iteration 2, the run is at 3: run `python "
                                                   f"lunar_lander.py evaluate {run_dir} --corrected` again")):
        compared_runs.check_fresh([{**fix, "iteration": 2}], [rows], [run_dir])
