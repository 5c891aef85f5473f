"""Careless and hostile input, each kind through its one parser: a page that can't be hijacked by a
run's name, terrains that must be the run's, a hand-edited config, a finished experiment, huge
numbers, metrics of the wrong types, a run given twice, and the wording of the refusals."""

import json
import shutil

import pandas as pd
import pytest

from qdsearch.cli import app as ll
from qdsearch.cli import commands
from util import Result, assert_one_line_error, checkpoint_iteration, folder_state

INJECTION = "p</script><img src=x onerror=document.title=1337>"  # a folder p< holding script><img...
TITLE = "LunarLander-v3 archive explorer"


@pytest.fixture(scope="module")
def tiny_experiment(tmp_path_factory, dask_cluster):
    """A finished experiment of two tiny runs (cma_me, seeds 1 and 2)."""
    folder = tmp_path_factory.mktemp("hostile") / "exp"
    commands.experiment(algorithms="cma_me", seeds="1-2", iterations=2, n_emitters=2, batch_size=6,
                           log_every=2, outdir=str(folder), scheduler_address=dask_cluster.scheduler_address)
    return folder


def copy_of(run_dir, where):
    where.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(run_dir, where)
    return where


@pytest.mark.parametrize("name", [INJECTION, "a<!--<script>", "q&lt;\u2028\u2029'\"`${x}"])
def test_a_hostile_run_name_runs_nothing_and_the_page_works(browser, tiny_run, tmp_path, dask_cluster,
                                                           name):
    run_dir = copy_of(tiny_run, tmp_path / name)
    commands.explore(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    html = (run_dir / "explorer.html").read_text()
    assert "<img src=x" not in html and "<!--<script>" not in html  # written as JSON escapes

    page = browser.new_page()
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("console", lambda message: message.type == "error" and errors.append(message.text))
    page.goto((run_dir / "explorer.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    assert page.title() == TITLE and errors == []
    subtitle = page.evaluate("document.getElementById('subtitle').textContent")
    assert subtitle.startswith(str(run_dir) + ": cma_me, ")  # the name shown as text, as it is
    assert page.locator("img").count() == 0 and page.locator("#elites tbody tr").count() > 0
    page.close()


def test_the_page_lets_only_its_own_script_run(browser, tiny_run, tmp_path, dask_cluster):
    """Even markup that got into the page could run nothing: the policy allows one script, by hash."""
    run_dir = copy_of(tiny_run, tmp_path / "run")
    commands.explore(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    html = (run_dir / "explorer.html").read_text()
    planted = html.replace("</body>", "<img src=x onerror=\"document.title='1337'\">"
                                      "<script>document.title='1338'</script></body>")
    (run_dir / "planted.html").write_text(planted)
    page = browser.new_page()
    page.goto((run_dir / "planted.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    assert page.title() == TITLE
    page.close()


@pytest.mark.parametrize("command", ["video", "trajectories", "explore"])
def test_a_terrain_that_is_not_the_runs_is_refused(run_cli, tiny_run, tmp_path, command):
    run_dir = copy_of(tiny_run, tmp_path / "run")
    before = folder_state(run_dir)
    extra = ["--best"] if command != "explore" else []
    assert_one_line_error(run_cli(command, run_dir, *extra, "--env_seed", "7"),
                          "--env_seed 7 is not a terrain of this run", "flown on 52")
    assert folder_state(run_dir) == before


@pytest.mark.parametrize("field, value", [("measures", ["fuel", "flight_time"]), ("grid", 20),
                                          ("seed", 8), ("env_seed", [52, 53])])
def test_resume_refuses_a_hand_edited_config(run_cli, tiny_run, tmp_path, field, value):
    run_dir = copy_of(tiny_run, tmp_path / "run")
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, field: value}))
    before = folder_state(run_dir)
    assert_one_line_error(run_cli("resume", run_dir, "--iterations", 5), "config.json says",
                          f"--{field}", "the run's checkpoint ran with")
    assert folder_state(run_dir) == before


def test_resuming_a_finished_experiment_changes_nothing(run_cli, tiny_experiment, tmp_path):
    folder = copy_of(tiny_experiment, tmp_path / "exp")
    before = folder_state(folder)
    result = run_cli("resume", folder)
    assert result.returncode == 0 and "nothing to do: all 2 runs" in result.stdout
    assert_one_line_error(run_cli("resume", folder, "--iterations", 1),
                          "goes to iteration 2; --iterations 1 would end it sooner")
    assert folder_state(folder) == before  # the recorded timing and every run kept


@pytest.mark.parametrize("args, fragments", [
    (["--env_seed", "99999999999999999999"], ["--env_seed", "4294967295"]),
    (["--env_seed", "0-99999999999999999999"], ["--env_seed", "4294967295"]),
    (["--env_seed", "0-999999999"], ["1,000,000,000 seeds", "at most 10,000"]),
    (["--seed", "99999999999999999999"], ["--seed", "4294967295"]),
    (["experiment", "--seeds", "1-99999999999999999999"], ["--seeds"]),
    (["experiment", "--seeds", "0-20000"], ["20,001 seeds", "at most 10,000"]),
    (["--measures", "fuel,"], ["--measures", "'fuel,'"]),
    (["--env_seed", "3,"], ["--env_seed", "'3,'"]),
])
def test_huge_numbers_and_stray_commas_are_one_line_and_write_nothing(run_cli, tmp_path, args, fragments):
    assert_one_line_error(run_cli(*args, "--outdir", tmp_path / "out"), *fragments)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("row", [{"qd_score": "high"}, {"coverage": None}, {"evaluations": 1.5},
                                 {"best_objective": "NaN"}, {"iteration": True}])
def test_compare_refuses_metrics_of_the_wrong_types(run_cli, tiny_run, tmp_path, row):
    run_dir = copy_of(tiny_run, tmp_path / "run")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    (run_dir / "metrics.json").write_text(json.dumps([{**metrics[0], **row}, *metrics[1:]]))
    field = next(iter(row))
    assert_one_line_error(run_cli("compare", run_dir, "--out", tmp_path / "cmp"), "metrics.json",
                          f"row 0 has {field}")
    assert not list(tmp_path.glob("cmp*"))


def test_compare_counts_a_run_given_twice_once(run_cli, tiny_experiment, tmp_path):
    one = tiny_experiment / json.loads((tiny_experiment / "experiment.json").read_text())["runs"][0]["name"]
    result = run_cli("compare", tiny_experiment, one, "--out", tmp_path / "cmp")
    assert result.returncode == 0, result.stderr
    assert f"note: {one} is given twice" in result.stdout
    table = pd.read_csv(tmp_path / "cmp.csv")
    assert len(table) == 2 and sorted(table["seed"]) == [1, 2]


def test_explore_refuses_corrupt_metrics_before_flying(run_cli, tiny_run, tmp_path, dask_cluster):
    run_dir = copy_of(tiny_run, tmp_path / "run")
    (run_dir / "metrics.json").write_text('[{"iteration": "one"}]')
    result = run_cli("explore", run_dir, "--scheduler_address", dask_cluster.scheduler_address)
    assert_one_line_error(result, "metrics.json", "row 0 has")
    assert "Dask cluster" not in result.stdout and not (run_dir / "explorer.html").exists()


def test_the_wording_of_refusals(run_cli, tiny_run, tmp_path):
    (tmp_path / "afile").write_text("mine")
    assert_one_line_error(run_cli("experiment", "--outdir", tmp_path / "afile"),
                          "afile exists and is not a folder")
    assert_one_line_error(run_cli("compare", tiny_run, "--out", tmp_path / "afile" / "x.png"),
                          "cannot write", "afile is not a folder")
    assert (tmp_path / "afile").read_text() == "mine"


def test_when_every_run_fails_nobody_says_the_others_finished(tiny_experiment, tmp_path, dask_cluster,
                                                              capsys):
    folder = copy_of(tiny_experiment, tmp_path / "exp")
    for run in json.loads((folder / "experiment.json").read_text())["runs"]:
        shutil.rmtree(folder / run["name"] / "heatmaps")
        (folder / run["name"] / "heatmaps").write_text("not a folder")  # its next save fails
    code = ll.main(["resume", str(folder), "--iterations", "3",
                    "--scheduler_address", dask_cluster.scheduler_address])
    err = capsys.readouterr().err
    assert_one_line_error(Result(code, "", err), "all 2 runs failed", code=1)
    assert "the others finished" not in err
    for run in json.loads((folder / "experiment.json").read_text())["runs"]:
        assert run["state"] == "failed" and checkpoint_iteration(folder / run["name"]) >= 2
