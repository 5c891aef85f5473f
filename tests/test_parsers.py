"""Property tests of the one door for input: every flag parser and file loader, fed generated
strings, numbers, lists and JSON, gives a valid value or a UsageError of one line, never another
exception (Hypothesis)."""

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from ribs.archives import GridArchive

from qdsearch import algorithms, tasks
from qdsearch.analysis import results
from qdsearch.base import flags
from qdsearch.base.flags import (
    MAX_SEED,
    MAX_SEEDS,
    UsageError,
    boolean,
    distinct_names,
    fraction,
    one_of,
    positive_float,
    positive_int,
    seed_list,
    seed_number,
)
from qdsearch.base.run_files import read_run_json
from qdsearch.cli.parsing import as_typed
from qdsearch.config import run_config
from qdsearch.search import experiments
from qdsearch.search.parts import MAX_PARTS, parse_part
from qdsearch.store import archive_data, metrics, trackers

QUICK = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# What Fire may hand a command (numbers, text, tuples, lists, booleans, None), and the text typed.
SCALARS = (st.none() | st.booleans() | st.integers() | st.integers(-2**70, 2**70)
           | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=30))
SEED_TEXT = st.lists(st.one_of(st.from_regex(r"\s*\d{1,12}\s*(-\s*\d{1,12}\s*)?", fullmatch=True),
                               st.text(max_size=6)), min_size=1, max_size=4).map(",".join)
VALUES = st.recursive(SCALARS | SEED_TEXT, lambda inner: st.lists(inner, max_size=4)
                      | st.lists(inner, max_size=4).map(tuple), max_leaves=8)
JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
                    lambda inner: st.lists(inner, max_size=4)
                    | st.dictionaries(st.text(max_size=12), inner, max_size=5), max_leaves=12)


def one_line(error: UsageError) -> None:
    """A short message, printed (main) on one line."""
    assert str(error) and len(str(error)) < 1000 and len(flags.one_line(str(error)).splitlines()) == 1


def refused_in_one_line_or(check, *args):
    """Call check; a UsageError must be one line. Anything else propagates (the test fails)."""
    try:
        return check(*args)
    except UsageError as error:
        one_line(error)
        return UsageError


def parse_part_check(name, value):
    """--part I/K as a check of the same shape as the others."""
    return parse_part(value)


CHECKS = [positive_int, seed_number, positive_float, fraction, boolean, one_of(algorithms.ALGORITHMS),
          seed_list, distinct_names(tasks.MEASURES, "measures", 3), trackers.check_tracks, parse_part_check]


@pytest.mark.parametrize("check", CHECKS, ids=lambda check: getattr(check, "__name__", "check"))
@QUICK
@given(value=VALUES)
def test_every_flag_check_gives_a_valid_value_or_one_line(check, value):
    checked = refused_in_one_line_or(check, "flag", value)
    if checked is UsageError:
        return
    if check in (positive_int, seed_number):
        assert isinstance(checked, int) and not isinstance(checked, bool)
        assert checked >= 1 if check is positive_int else 0 <= checked <= MAX_SEED
    elif check in (positive_float, fraction):
        assert isinstance(checked, float) and math.isfinite(checked) and checked > 0
    elif check is trackers.check_tracks:
        assert isinstance(checked, list) and set(checked) <= set(trackers.TRACKERS)
    elif check is parse_part_check:
        part, parts = checked
        assert 1 <= part <= parts <= MAX_PARTS
    elif check is seed_list:
        assert 1 <= len(checked) <= MAX_SEEDS and len(set(checked)) == len(checked)
        assert all(isinstance(seed, int) and 0 <= seed <= MAX_SEED for seed in checked)


@QUICK
@given(first=st.integers(0, MAX_SEED), count=st.integers(1, 3 * MAX_SEEDS))
def test_a_seed_range_is_checked_before_it_is_built(first, count):
    text = f"{first}-{first + count - 1}"
    checked = refused_in_one_line_or(seed_list, "env_seed", text)
    if count > MAX_SEEDS or first + count - 1 > MAX_SEED:
        assert checked is UsageError
    else:
        assert checked == list(range(first, first + count))


@QUICK
@given(names=st.lists(st.sampled_from([*tasks.MEASURES, "", "speed", " fuel"]), max_size=5),
       trailing=st.sampled_from(["", ",", ", ", ",,"]))
def test_measures_as_typed(names, trailing):
    text = ",".join(names) + trailing
    checked = refused_in_one_line_or(distinct_names(tasks.MEASURES, "measures", 3), "measures", text)
    stripped = [name.strip() for name in names]
    valid = (not trailing and 1 <= len(names) <= 3 and len(set(stripped)) == len(stripped)
             and all(name in tasks.MEASURES for name in stripped))
    assert (checked is not UsageError) == valid
    if valid:
        assert checked == stripped


@QUICK
@given(args=st.lists(st.sampled_from(["--measures", "--env_seed", "--iterations", "fuel,", "0-4",
                                      "--measures=a,b", "3", "--", "'x'", "--env-seed=7"]), max_size=8))
def test_text_flags_reach_their_check_as_typed(args):
    import ast

    typed = as_typed(args, {"measures", "env_seed"})
    assert len(typed) == len(args)
    for before, after in zip(args, typed):
        if after != before:  # a value of a text flag: Fire reads it back as the very text
            value = after.partition("=")[2] if after.startswith("--") else after
            original = before.partition("=")[2] if before.startswith("--") else before
            assert ast.literal_eval(value) == original


LANDER_DIM = tasks.ENVIRONMENTS[tasks.DEFAULT_ENV].solution_dim
ARCHIVE = GridArchive(solution_dim=LANDER_DIM, dims=(10, 10), ranges=[(-1, 1), (-3, 0)])
ARCHIVE.add(np.zeros((3, LANDER_DIM)), np.array([1.0, 2.0, 3.0]),
            np.array([[0.0, -1.0], [0.5, -2.0], [-0.5, -0.5]]))


@QUICK
@given(cells=VALUES | st.lists(st.tuples(SCALARS, SCALARS), max_size=3))
def test_cell_points(cells):
    points = refused_in_one_line_or(results.parse_cells, cells, list(tasks.TUTORIAL_MEASURES))
    if points is not UsageError:
        assert points and all(len(p) == 2 and all(math.isfinite(v) for v in p) for p in points)
        for point in points:  # each then is found in the archive, or refused in one line
            refused_in_one_line_or(results.check_in_archive, ARCHIVE, point, list(tasks.TUTORIAL_MEASURES))


@QUICK
@given(index=VALUES)
def test_cell_indices(index):
    cells = refused_in_one_line_or(results.parse_indices, index, ARCHIVE)
    if cells is not UsageError:
        assert all(0 <= cell < 100 for cell in cells)


@QUICK
@given(config=JSON | st.fixed_dictionaries({}, optional={
    name: VALUES for name in ["seed", "env_seed", "measures", "grid", "algorithm", "iterations",
                              "learning_rate", "batch_size", "fast_env", "outdir"]}))
def test_run_configs(config):
    checked = refused_in_one_line_or(run_config.check_run_config, config)
    if checked is not UsageError:
        assert checked["algorithm"] in algorithms.ALGORITHMS
        assert set(checked["measures"]) <= set(tasks.MEASURES)
        assert isinstance(checked["seed"], int) and checked["grid"] >= 1


ROW = st.fixed_dictionaries({}, optional={field: SCALARS for field in metrics.METRIC_FIELDS})


@QUICK
@given(rows=JSON | st.lists(ROW, max_size=3))
def test_metrics_files(rows):
    checked = refused_in_one_line_or(metrics.check_metrics, rows, Path("metrics.json"))
    if checked is not UsageError:
        for row in checked:
            assert isinstance(row["iteration"], int) and not isinstance(row["iteration"], bool)
            assert math.isfinite(row["qd_score"]) and math.isfinite(row["coverage"])


@QUICK
@given(content=st.binary(max_size=64) | JSON.map(lambda value: json.dumps(value).encode()))
def test_run_files_on_disk(content):
    """Whatever bytes a run folder's files hold, the loaders answer in one line."""
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        for name in ("config.json", "metrics.json", "experiment.json", "checkpoint.pkl", "archive.npz"):
            (folder / name).write_bytes(content)
        for load in (lambda: read_run_json(folder, "config.json"), lambda: run_config.load_run_config(folder),
                     lambda: metrics.load_metrics(folder), lambda: experiments.read_experiment(folder),
                     lambda: archive_data.read_archive_data(folder / "archive.npz"),
                     lambda: run_config.load_checkpoint(folder / "checkpoint.pkl")):
            refused_in_one_line_or(load)


@QUICK
@given(plan=st.fixed_dictionaries({"format": st.just(experiments.EXPERIMENT_FORMAT),
                                   "workers": SCALARS, "runs": JSON | st.lists(JSON, max_size=2)}),
       name=st.text(max_size=12))
def test_experiment_plans(plan, name):
    with tempfile.TemporaryDirectory() as folder:
        entry = {"name": name, "setting": "cma_me", "state": "done", "seed": 1,
                 "config": {"iterations": 2, "seed": 1}}
        for runs in (plan["runs"], [entry]):
            (Path(folder) / "experiment.json").write_text(json.dumps({**plan, "runs": runs}))
            checked = refused_in_one_line_or(experiments.read_experiment, Path(folder))
            if checked is not UsageError:  # every run's folder is a plain name inside the experiment
                for run in checked["runs"]:
                    assert (Path(folder) / run["name"]).resolve().parent == Path(folder).resolve()
