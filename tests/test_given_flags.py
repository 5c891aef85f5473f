"""Flags given beside a file: `search --config RUN` and `experiment --plan FILE` take the file's
settings, and a flag typed beside the file wins whatever its value (its default too). The merged
config is checked where it is computed (run_config.search_config, experiments.with_plan and
experiment_grid) against what the command alone makes of the same flags, flag by flag; one
command line each shows the command goes through it."""

import inspect
import json
from pathlib import Path

import fire
import pytest

from qdsearch.base.flags import Flag, UsageError
from qdsearch.cli import parsing
from qdsearch.cli.signatures import takes
from qdsearch.config import options, run_config, settings
from qdsearch.search import experiments
from qdsearch.store import trackers
from util import assert_one_line_error, folder_state

DEFAULTS = options.search_defaults()
TRACKER = next((name for name, kind in trackers.TRACKERS.items() if trackers.installed(kind.module)), None)

# For every flag a file can hold: a valid value other than its default, and the flags it needs
# beside it to mean something (none of them a flag it takes along: run_config.FOLLOWS).
ROWS = {
    "iterations": (5, {}),
    "evaluations": (300, {}),
    "seed": (8, {}),
    "env": ("BipedalWalker-v3", {}),
    "env_seed": ("0-2", {}),
    "policy": ("mlp", {"algorithm": "map_elites", "grid": 5}),  # no covariance of 18,000 weights
    "hidden": ("4", {"policy": "mlp", "algorithm": "map_elites", "grid": 5}),
    "episode_length": (100, {}),
    "reset": ("each", {}),
    "start": ("glorot", {}),
    "qd_offset": (-50.0, {}),
    "terminate_when_unhealthy": (False, {"env": "Hopper-v5"}),
    "measures": ("fuel,flight_time", {}),
    "archive": ("cvt", {}),
    "grid": (10, {}),
    "cells": (64, {"archive": "cvt"}),
    "algorithm": ("cma_mega_es", {}),
    "n_emitters": (2, {}),
    "sigma0": (0.5, {}),
    "batch_size": (6, {}),
    "learning_rate": (0.1, {"algorithm": "cma_mae"}),
    "line_sigma": (0.3, {"algorithm": "line_map_elites"}),
    "novelty_threshold": (0.05, {"algorithm": "ns_cma"}),
    "bandwidth": (0.1, {"algorithm": "dds"}),
    "es_samples": (6, {"algorithm": "cma_mega_es"}),
    "es_sigma": (0.05, {"algorithm": "cma_mega_es"}),
    "buffer_size": (5_000, {"algorithm": "pga_me", "env": "Hopper-v5"}),
    "log_every": (5, {}),
    "pictures": (False, {}),
    "archive_pkl": (True, {}),
    "from_archive": ("elsewhere/archive.npz", {}),
    "track": (TRACKER, {}),
    "fast_env": (False, {}),
    "dim": (20, {"env": "sphere"}),
}
FROM_CONFIG = [flag for flag in settings.SEARCH_FLAGS if flag not in run_config.NOT_FROM_CONFIG]
SEED = 7  # every file's: a run's seed is in its config


def test_a_command_is_told_the_flags_given_on_the_command_line_as_in_a_call():
    """Fire passes a positional parameter's default as if given: `takes` makes the flags of a
    command that asks which were given keyword-only, so only those typed are."""
    @takes({"policy": Flag("linear", "a flag"), "iterations": Flag(300, "another")})
    def command(config: str | None = None, *, given: frozenset[str] = frozenset(), **flags):
        return sorted(given), flags

    typed = fire.Fire(command, command=["--config", "RUN", "--policy", "linear"])
    assert typed == command(config="RUN", policy="linear") == (
        ["config", "policy"], {"policy": "linear", "iterations": 300})
    assert fire.Fire(command, command=[]) == command() == ([], {"policy": "linear", "iterations": 300})


def test_a_command_with_many_folders_gets_them_by_place_and_its_flags_by_name():
    """compare's *run_dirs: the folders reach the command as its *args (none: an empty tuple), the
    table's flags as keywords, each defaulted."""
    @takes({"out": Flag(None, "a flag"), "overwrite": Flag(False, "another")})
    def command(first, *folders, **flags):
        return first, folders, flags

    assert command("a", "b", "c", out="x") == ("a", ("b", "c"), {"out": "x", "overwrite": False})
    assert command("a") == ("a", (), {"out": None, "overwrite": False})
    assert inspect.signature(command).parameters["out"].kind is inspect.Parameter.KEYWORD_ONLY


def test_a_word_no_argument_takes_is_refused_before_the_command_runs(run_cli, tmp_path):
    """The flags of search and experiment are keyword-only: Fire would run the command, then
    look a stray word up in what it returned."""
    tiny = ["--iterations", "1", "--n_emitters", "1", "--batch_size", "2", "--workers", "1", "--pictures",
            "false"]  # were it run
    for args, word in ([[*tiny, "RUN"], "RUN"], [["experiment", "cma_me", "--seeds", "1", *tiny], "cma_me"]):
        assert_one_line_error(run_cli(*args, "--outdir", tmp_path / "out"), f"unexpected argument '{word}'")
    assert list(tmp_path.iterdir()) == []


def test_the_table_holds_every_flag_a_file_gives():
    assert sorted(ROWS) == sorted(FROM_CONFIG)
    assert set(settings.PASSED_ON) <= set(ROWS)


def cases(flags):
    """(flag, the file's value, the value given beside it): a value other than the file's, and
    the default where the file holds another (a seed's default, none, is drawn: not given)."""
    for flag in flags:
        other, _ = ROWS[flag]
        yield flag, DEFAULTS[flag], other
        if flag != "seed":
            yield flag, other, DEFAULTS[flag]


def config_file(tmp_path: Path, **settings) -> Path:
    """A run's config.json as a search with these settings records it (nothing flown)."""
    folder = tmp_path / "recorded"
    folder.mkdir(exist_ok=True)
    config = run_config.search_config({**DEFAULTS, "seed": SEED, **settings})
    (folder / "config.json").write_text(json.dumps(config.to_json()))
    return folder / "config.json"


def beside(path, **given):
    """The config `search --config path` makes with `given` typed beside it."""
    return run_config.search_config({**DEFAULTS, **given}, set(given), path).to_json()


def alone(**flags):
    """The config search makes of these flags alone (the file's seed)."""
    return run_config.search_config({**DEFAULTS, "seed": SEED, **flags}).to_json()


@pytest.mark.parametrize("flag, recorded, given", list(cases(FROM_CONFIG)),
                         ids=lambda value: repr(value)[:20])
def test_a_flag_given_beside_config_wins_whatever_its_value(tmp_path, flag, recorded, given):
    """The whole config is what search makes of the file's settings with the flag given in
    place of the file's: its value, and what it takes along (another task's own measures)."""
    if flag == "track" and TRACKER is None:
        pytest.skip("no tracker is installed")
    _, needs = ROWS[flag]
    path = config_file(tmp_path, **needs, **{flag: recorded})
    merged = beside(path, **{flag: given})
    assert merged == alone(**needs, **{flag: given})
    assert merged[flag] != json.loads(path.read_text())[flag]


def test_a_budget_given_beside_config_replaces_the_files(tmp_path):
    path = config_file(tmp_path, evaluations=150)  # 1 iteration of cma_me's 150 solutions
    assert json.loads(path.read_text())["iterations"] == 1
    assert beside(path, iterations=5)["iterations"] == 5
    assert beside(path, iterations=5)["evaluations"] is None
    assert beside(path, iterations=1)["evaluations"] is None  # the file's own number too
    doubled = beside(path, evaluations=300, batch_size=15)  # 75 solutions an iteration
    assert (doubled["evaluations"], doubled["iterations"]) == (300, 4)
    assert beside(config_file(tmp_path, iterations=5), evaluations=300)["iterations"] == 2


def test_the_file_gives_neither_where_the_run_goes_nor_its_cluster(tmp_path):
    recorded = {"outdir": str(tmp_path / "theirs"), "workers": 3, "scheduler_address": "tcp://10.0.0.9:8786",
                "scheduler_file": str(tmp_path / "their_scheduler.json"), "scheduler_timeout": 7,
                "worker_timeout": 9}
    path = config_file(tmp_path, **recorded)
    assert {flag: json.loads(path.read_text())[flag] for flag in recorded} == recorded
    merged = beside(path)
    assert {flag: merged[flag] for flag in run_config.NOT_FROM_CONFIG} == {
        flag: DEFAULTS[flag] for flag in run_config.NOT_FROM_CONFIG}
    mine = {"outdir": str(tmp_path / "mine"), "workers": 1, "scheduler_timeout": 30}
    assert {flag: beside(path, **mine)[flag] for flag in mine} == mine


def test_a_flag_given_at_the_files_value_keeps_what_the_file_made(tmp_path):
    """Only another value takes along what the file's made: the run's own measures and cells
    stay beside its own --env and --archive."""
    path = config_file(tmp_path, measures="fuel,flight_time", archive="cvt", cells=64)
    merged = beside(path, env=options.DEFAULT_ENV, archive="cvt")
    assert (merged["measures"], merged["cells"]) == (["fuel", "flight_time"], 64)
    assert beside(path, env="LunarLanderContinuous-v3")["measures"] == list(
        options.ENVIRONMENTS["LunarLanderContinuous-v3"].measures)


def test_a_runs_own_row_flags_are_taken_beside_its_config(tmp_path):
    """The command line's check of a row's own flags reads the row of the run --config names
    (lunar_lander.main calls it so): a cma_mae run's --learning_rate is taken, and refused once
    --algorithm names a row that ignores it."""
    path = config_file(tmp_path, algorithm="cma_mae", learning_rate=0.1)
    typed = {"config": str(path), "learning_rate": "0.2"}

    def check(typed):
        options.refuse_unused_row_flags([parsing.typed_setting(typed, "algorithm")], list(typed),
                                        [parsing.typed_setting(typed, "policy")])

    check(typed)
    assert beside(path, learning_rate=0.2)["learning_rate"] == 0.2
    with pytest.raises(UsageError, match="--learning_rate is a flag of .*--algorithm cma_me does not use it"):
        check({**typed, "algorithm": "cma_me"})
    with pytest.raises(UsageError, match="--hidden is a flag of mlp only; --policy linear does not use it"):
        check({**typed, "hidden": "8"})


def test_config_refuses_a_field_of_a_later_version_and_an_experiments_file(run_cli, tmp_path):
    path = config_file(tmp_path, iterations=2)
    config = json.loads(path.read_text())
    experiment = tmp_path / "exp"  # an experiment folder of one run
    (experiment / "cma_me_seed1").mkdir(parents=True)
    (experiment / "cma_me_seed1" / "config.json").write_text(json.dumps(config))
    (experiment / "experiment.json").write_text(json.dumps({"runs": [{"name": "cma_me_seed1"}]}))
    path.write_text(json.dumps({**config, "future_flag": 3, "created": "then", "resumed": []}))
    before = folder_state(tmp_path)
    assert_one_line_error(run_cli("--config", path, "--outdir", tmp_path / "new"), f"--config {path}",
                          "'future_flag'", "not a field of this version's runs")
    with pytest.raises(UsageError, match="'future_flag'"):  # every reader: resume, results
        run_config.load_run_config(path.parent)
    for given in (experiment / "experiment.json", experiment):
        result = run_cli("--config", given, "--outdir", tmp_path / "new")
        assert_one_line_error(result, "an experiment's file, not a run's", f"--config {experiment}/RUN_NAME",
                              f"--config {experiment / 'cma_me_seed1'}")
    assert folder_state(tmp_path) == before


def test_config_with_flags_beside_it_on_the_command_line(run_cli, tmp_path, dask_cluster):
    """An MLP cma_mega_es run's file with a budget in evaluations: --policy linear (the default)
    flies a linear policy, --iterations 1 replaces its budget, --es_samples (its row's own) is
    taken beside it and still refused for a row that ignores it; the cluster and the folder are
    the command's."""
    path = config_file(tmp_path, algorithm="cma_mega_es", policy="mlp", hidden="4", es_samples=4,
                       n_emitters=1, batch_size=2, evaluations=50, log_every=1, pictures=False,
                       scheduler_file=str(tmp_path / "their_scheduler.json"), worker_timeout=9)
    assert json.loads(path.read_text())["iterations"] == 7  # of 7: its point, 4 samples, a batch of 2
    address = dask_cluster.scheduler_address
    refused = run_cli("--config", path, "--algorithm", "cma_me", "--es_samples", 6,
                      "--outdir", tmp_path / "x")
    assert_one_line_error(refused,
                          "--es_samples is a flag of cma_mega_es, cma_maega_es, me_es, cma_mega_td3_es only",
                          "--algorithm cma_me does not use it")
    assert_one_line_error(run_cli("--config", path, "--hidden", "8", "--policy", "linear", "--outdir",
                                  tmp_path / "x"), "--hidden", "--policy linear does not use it")
    assert not (tmp_path / "x").exists()
    result = run_cli("--config", path, "--policy", "linear", "--iterations", 1, "--es_samples", 6,
                     "--scheduler_address", address, "--outdir", tmp_path / "new")
    assert result.returncode == 0, result.stderr
    written = json.loads((tmp_path / "new" / "config.json").read_text())
    assert {flag: written[flag] for flag in ("algorithm", "policy", "hidden", "iterations", "evaluations",
                                            "es_samples", "seed")} == {
        "algorithm": "cma_mega_es", "policy": "linear", "hidden": None, "iterations": 1, "evaluations": None,
        "es_samples": 6, "seed": SEED}
    assert {flag: written[flag] for flag in run_config.NOT_FROM_CONFIG} == {
        **{flag: DEFAULTS[flag] for flag in run_config.NOT_FROM_CONFIG}, "scheduler_address": address,
        "outdir": str(tmp_path / "new")}
    rows = json.loads((tmp_path / "new" / "metrics.json").read_text())
    assert [(row["iteration"], row["evaluations"]) for row in rows] == [(1, 9)]  # flew 6 samples


# ---- experiment --plan -----------------------------------------------------------------------

PLAN_OWN = {"algorithms": ("map_elites", "cma_me"), "seeds": ("7", "1-5"), "max_in_flight": (1, None)}


def planned_grid(planned: dict, **given):
    """What experiment makes of a plan with `given` beside it (its own flags at their defaults
    unless given): its own flags and its grid."""
    own = {"algorithms": ("cma_me",), "seeds": "1-5", "max_in_flight": None}
    flags = experiments.with_plan(planned, {**own, **given}, set(given))
    mine = {name: flags.pop(name) for name in experiments.EXPERIMENT_OWN}
    return mine, experiments.experiment_grid(mine["algorithms"], mine["seeds"], flags)


def grid_of(**flags):
    """The grid experiment makes of these flags alone."""
    own = {"algorithms": flags.pop("algorithms", ("cma_me",)), "seeds": flags.pop("seeds", "1-5")}
    return experiments.experiment_grid(own["algorithms"], own["seeds"], flags)


@pytest.mark.parametrize("flag, planned, given", [
    *((flag, value, other) for flag, (value, other) in PLAN_OWN.items()),
    *((flag, other, value) for flag, (value, other) in PLAN_OWN.items()),
    *cases(settings.PASSED_ON)], ids=lambda value: repr(value)[:20])
def test_a_flag_given_beside_a_plan_wins_whatever_its_value(flag, planned, given):
    if flag == "track" and TRACKER is None:
        pytest.skip("no tracker is installed")
    needs = {} if flag in PLAN_OWN else dict(ROWS[flag][1])
    if "algorithm" in needs:  # an experiment's rows are its --algorithms
        needs["algorithms"] = needs.pop("algorithm")
    mine, grid = planned_grid({**needs, flag: planned}, **{flag: given})
    if flag in PLAN_OWN:
        assert mine[flag] == given
    assert grid == grid_of(**needs, **({} if flag == "max_in_flight" else {flag: given}))


def test_a_budget_given_beside_a_plan_replaces_the_plans():
    assert planned_grid({"evaluations": 300}, iterations=5)[1] == grid_of(iterations=5)
    assert planned_grid({"iterations": 5}, evaluations=300)[1] == grid_of(evaluations=300)


def test_the_policies_own_flag_follows_the_rule_of_a_rows_own(run_cli, tmp_path):
    """--hidden beside a policy axis is taken where some setting uses it: its linear settings
    ignore it (recorded as search alone records a linear run); with no setting that uses it, it
    is refused, as a row's own flag is."""
    axes, common, seeds = experiments.experiment_grid("cma_me", "1", {"policy": ["linear", "mlp"],
                                                                       "hidden": "8", "n_emitters": 1})
    runs = experiments.experiment_runs(axes, common, seeds)
    assert [entry["config"]["hidden"] for entry in runs] == [None, [8]]
    linear = {k: v for k, v in runs[0]["config"].items() if k != "seed"}
    assert linear == {k: v for k, v in alone(policy="linear", n_emitters=1).items()
                      if k in linear and k != "seed"}
    tiny = ["--iterations", "1", "--n_emitters", "1", "--batch_size", "2", "--workers", "1"]  # if run
    for args in (["--policy", "[linear, linear]"], ["--policy", "linear"], []):
        assert_one_line_error(run_cli("experiment", *args, "--hidden", "8", "--seeds", "1", *tiny,
                                      "--outdir", tmp_path / "exp"), "--hidden", "--policy linear")
    assert_one_line_error(run_cli("--policy", "linear", "--hidden", "8", *tiny, "--outdir", tmp_path / "run"),
                          "--hidden", "--policy linear does not use it")
    assert not (tmp_path / "exp").exists() and not (tmp_path / "run").exists()


PLAN = """algorithms = ["map_elites"]
seeds = "7"
max_in_flight = 2
iterations = 3
n_emitters = 2
batch_size = 6
pictures = false
"""


def test_a_plan_with_flags_beside_it_on_the_command_line(run_cli, tmp_path, dask_cluster):
    """--algorithms cma_me and --seeds 1-5, each its default, win over the plan's, as does
    --iterations; the plan's other flags stay, its own --max_in_flight too."""
    (tmp_path / "plan.toml").write_text(PLAN)
    result = run_cli("experiment", "--plan", tmp_path / "plan.toml", "--algorithms", "cma_me",
                     "--seeds", "1-5", "--iterations", 1, "--batch_size", 2, "--log_every", 1,
                     "--scheduler_address", dask_cluster.scheduler_address, "--outdir", tmp_path / "exp")
    assert result.returncode == 0, result.stderr
    plan = json.loads((tmp_path / "exp" / "experiment.json").read_text())
    assert plan["axes"] == {"algorithm": ["cma_me"]} and plan["seeds"] == [1, 2, 3, 4, 5]
    assert plan["max_in_flight"] == 2
    made = {(entry["config"]["iterations"], entry["config"]["batch_size"], entry["config"]["n_emitters"],
             entry["config"]["pictures"], entry["state"]) for entry in plan["runs"]}
    assert made == {(1, 2, 2, False, "done")}
