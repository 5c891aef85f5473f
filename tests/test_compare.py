"""compare: the table of final values and the picture, the labels that group runs into settings,
and the statistics across seeds (BCa intervals per metric, Mann-Whitney with Holm, A12), each
checked against its definition. (An experiment's folder through compare: test_experiment.py.)"""

import csv

import numpy as np
import pandas as pd
import pytest
from scipy.stats import bootstrap, mannwhitneyu

from qdsearch import comparison, experiments, options, run
from util import assert_one_line_error, folder_state, load_pickle, run_metrics, tiny_flags


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory, dask_cluster, tiny_run):
    """The tiny run (cma_me) and its cma_mae twin."""
    mae = tmp_path_factory.mktemp("compare") / "cma_mae"
    run.search(**tiny_flags(dask_cluster, algorithm="cma_mae"), outdir=str(mae))
    return [tiny_run, mae]


def test_compare_writes_png_and_table(run_cli, tmp_path, two_runs):
    result = run_cli("compare", *two_runs)

    assert result.returncode == 0, result.stderr
    pngs = list((tmp_path / "outputs").glob("compare_*.png"))
    assert len(pngs) == 1 and pngs[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(pngs[0].with_suffix(".csv")) as file:
        rows = list(csv.DictReader(file))
    labels = ["cma_me n_emitters=2 batch_size=6 seed 7",
              "cma_mae n_emitters=2 batch_size=6 learning_rate=0.5 seed 7"]
    assert [row["run"] for row in rows] == labels
    for row, run_dir in zip(rows, two_runs):
        final = run_metrics(run_dir)[-1]
        assert int(row["evaluations"]) == final["evaluations"] == 36
        assert float(row["qd_score"]) == pytest.approx(final["qd_score"])
        assert float(row["coverage"]) == pytest.approx(final["coverage"])
        assert float(row["best_objective"]) == pytest.approx(final["best_objective"])
        objectives = load_pickle(run_dir / "archive.pkl").data("objective")
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
        rows += [{"setting": setting, **{metric: values[i] for metric, values in metrics.items()}}
                 for i in range(count)]
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
            assert row["A12"] == pytest.approx(a12(x, y))
        assert block["p_holm"].tolist() == pytest.approx(comparison.holm(block["p"].tolist()))


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


def test_holm_and_auc_by_hand():
    assert comparison.holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    metrics = [{"evaluations": 10, "qd_score": 100.0}, {"evaluations": 20, "qd_score": 300.0}]
    assert comparison.qd_auc(metrics) == pytest.approx((0.5 * 10 * 100 + 10 * 200) / 20)
    five_each = pd.DataFrame([{"metric": "qd_score", "runs_a": 5, "runs_b": 5}] * 10)
    assert comparison.holm_floor(five_each) == pytest.approx(10 * 2 / 252)  # 5 seeds, 5 settings: 0.079
