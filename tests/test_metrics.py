"""metrics.json: a row as the log tells it, and each kind of bad file refused in one line that
names its first bad row and field (real files)."""

import json

import pytest

from qdsearch.base.flags import UsageError
from qdsearch.store.metrics import describe_progress, load_metrics

ROW = {"iteration": 4, "evaluations": 48, "coverage": 0.1234, "num_elites": 5, "qd_score": 1234.56,
       "best_objective": 87.654, "mean_objective": -3.5, "elapsed_s": 2.0}


def test_a_row_is_told_in_one_line():
    assert describe_progress(ROW, 10) == ("iteration 4/10: 48 evaluations, coverage 0.123, QD score 1235, "
                                          "best 87.7, 0.50 s/iteration")
    assert describe_progress({**ROW, "iteration": 0, "best_objective": None}, 10).endswith(
        "best None, 2.00 s/iteration")


def test_metrics_json_is_read_and_each_bad_row_refused(tmp_path):
    path = tmp_path / "metrics.json"
    old = {key: value for key, value in ROW.items() if key != "elapsed_s"}  # runs before timings
    path.write_text(json.dumps([ROW, old]))
    assert load_metrics(tmp_path) == [ROW, old]
    for rows, said in (({}, "no metrics (a list of one row per iteration)"),
                       ([], "no metrics (a list of one row per iteration)"),
                       ([ROW, [1]], "row 1 is a list, not a row of metrics"),
                       ([{**ROW, "qd_score": None}], "row 0 has qd_score = None, not float"),
                       ([ROW, {**ROW, "best_objective": "x"}],
                        "row 1 has best_objective = 'x', not float or NoneType"),
                       ([{**ROW, "elapsed_s": True}], "row 0 has elapsed_s = True, not float"),
                       ([old, {k: v for k, v in ROW.items() if k != "num_elites"}],
                        "row 1 has no num_elites")):
        path.write_text(json.dumps(rows))
        with pytest.raises(UsageError) as caught:
            load_metrics(tmp_path)
        assert str(caught.value) == f"{path}: {said}"
