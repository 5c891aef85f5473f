"""Experiments: many runs interleaved on one cluster, each equal to its lone `search` twin; stop
and resume; a failing run; bad input; statistics across seeds with `compare`."""

import json
import os
import shutil
import signal

import numpy as np
import pandas as pd
import pytest
from scipy.stats import mannwhitneyu

from qdsearch import algorithms
from qdsearch.analysis import comparison, run_folder
from qdsearch.cli import app as ll
from qdsearch.cli import commands
from qdsearch.config import options
from qdsearch.search import experiments, loop
from util import (
    Replacements,
    Result,
    assert_one_line_error,
    checkpoint_iteration,
    folder_state,
    launch,
    run_archive,
    run_metrics,
    wait_for,
)

pytestmark = pytest.mark.slow  # real processes, signals, clusters: not in the quick subset

TINY = dict(iterations=4, n_emitters=2, batch_size=6, log_every=4)  # each run saved at its end


@pytest.fixture(scope="module")
def experiment_dir(tmp_path_factory, dask_cluster):
    """cma_me, map_elites and cma_mae at two learning rates, two seeds each: 8 runs in one go,
    their data alone (an experiment's pictures are the kill -9 test's)."""
    folder = tmp_path_factory.mktemp("experiment") / "exp"
    commands.experiment(algorithms="cma_me,map_elites,cma_mae", seeds="1-2", learning_rate=[0.01, 0.5],
                           outdir=str(folder), scheduler_address=dask_cluster.scheduler_address,
                           pictures=False, **TINY)
    return folder


def plan_of(folder):
    return json.loads((folder / "experiment.json").read_text())


def test_the_grid_runs_every_setting_with_every_seed(experiment_dir):
    plan = plan_of(experiment_dir)
    settings = [entry["setting"] for entry in plan["runs"]]
    assert list(dict.fromkeys(settings)) == [  # learning_rate is cma_mae's own: no duplicates
        "cma_me", "map_elites", "cma_mae learning_rate=0.01", "cma_mae learning_rate=0.5"]
    # (n_emitters=2 batch_size=6, which every setting shares, is left out of the labels and names)
    names = [entry["name"] for entry in plan["runs"]]
    assert names[:3] == ["cma_me_seed1", "cma_me_seed2", "map_elites_seed1"]
    assert [entry["seed"] for entry in plan["runs"]] == [1, 2] * 4
    assert all(entry["state"] == "done" for entry in plan["runs"])
    assert plan["axes"] == {"algorithm": ["cma_me", "map_elites", "cma_mae"], "learning_rate": [0.01, 0.5]}
    for entry in plan["runs"]:
        run_dir = experiment_dir / entry["name"]
        written = {p.name for p in run_dir.iterdir() if not p.name.startswith(".")}  # not its .lock
        assert written == {"config.json", "checkpoint.pkl", "archive.npz", "archive.csv",
                           "metrics.json", "run.log"}  # and no picture: none was asked for
        assert [row["iteration"] for row in run_metrics(run_dir)] == [1, 2, 3, 4]
    assert "Done: 8 of 8 runs" in (experiment_dir / "experiment.log").read_text()


@pytest.mark.parametrize("which", [1, 6])
def test_each_run_equals_its_lone_search_twin(experiment_dir, tmp_path, dask_cluster, which):
    entry = plan_of(experiment_dir)["runs"][which]
    flags = {k: v for k, v in entry["config"].items() if k in options.search_defaults()}
    commands.search(**flags, outdir=str(tmp_path / "twin"), scheduler_address=dask_cluster.scheduler_address)
    assert run_archive(experiment_dir / entry["name"]).equals(run_archive(tmp_path / "twin"))
    assert run_metrics(experiment_dir / entry["name"]) == run_metrics(tmp_path / "twin")


def test_every_row_runs_and_sweeps_only_its_own_flags(tmp_path, dask_cluster):
    folder = tmp_path / "rows"
    # every row of episodes (those of exact gradients run on the functions: tests/test_functions.py)
    episode_rows = [name for name, row in algorithms.ALGORITHMS.items() if not row.exact]
    commands.experiment(algorithms=episode_rows, seeds="1-2", iterations=1,
                           env="LunarLanderContinuous-v3",  # a box of actions: the learning rows' too
                           novelty_threshold=[0.02, 0.05], bandwidth=[0.1], outdir=str(folder),
                           scheduler_address=dask_cluster.scheduler_address, n_emitters=2, batch_size=6,
                           log_every=1, pictures=False)  # 30 runs: their pictures are not what is checked
    runs = plan_of(folder)["runs"]
    settings = list(dict.fromkeys(entry["setting"] for entry in runs))
    assert len(settings) == len(episode_rows) + 2  # ns_cma and nslc at two thresholds each
    assert "ns_cma novelty_threshold=0.02" in settings
    assert "dds bandwidth=0.1" in settings
    assert "dns line_sigma=0.2" in settings
    assert "cma_me" in settings  # no flag of another row in its label
    assert all(entry["state"] == "done" for entry in runs) and len(runs) == 2 * len(settings)
    entry = next(e for e in runs if e["setting"].startswith("nslc") and "0.05" in e["setting"])
    flags = {k: v for k, v in entry["config"].items() if k in options.search_defaults()}
    commands.search(**flags, outdir=str(tmp_path / "twin"), scheduler_address=dask_cluster.scheduler_address)
    assert run_archive(folder / entry["name"]).equals(run_archive(tmp_path / "twin"))
    assert run_metrics(folder / entry["name"]) == run_metrics(tmp_path / "twin")

    commands.compare(str(folder), out=str(tmp_path / "rows"), baseline="cma_me")
    report = (tmp_path / "rows.md").read_text()
    assert "IQM [95% stratified bootstrap interval]" in report
    stats = pd.read_csv(tmp_path / "rows_settings.csv")
    assert set(stats["setting"]) == set(settings) and stats["iqm"].notna().all()
    tests = pd.read_csv(tmp_path / "rows_tests.csv")
    assert (tests["setting_a"] == "cma_me").all()
    assert len(tests) == (len(settings) - 1) * len(comparison.TESTED)
    assert (tmp_path / "rows_scores.png").stat().st_size > 20_000


def test_one_run_at_a_time_gives_the_same_runs(experiment_dir, tmp_path, dask_cluster):
    commands.experiment(algorithms="cma_mae", seeds="2", learning_rate=[0.5], max_in_flight=1,
                           outdir=str(tmp_path / "exp"), scheduler_address=dask_cluster.scheduler_address,
                           **TINY)
    [entry] = plan_of(tmp_path / "exp")["runs"]
    assert run_archive(tmp_path / "exp" / entry["name"]).equals(run_archive(experiment_dir / entry["name"]))


def test_stopped_experiment_resumes_to_the_uninterrupted_result(tmp_path, dask_cluster, experiment_dir):
    folder = tmp_path / "exp"
    # Its data alone: with pictures, drawn before each checkpoint is written, the checkpoints the
    # test reads lagged the loop and the stop landed iterations after it saw iteration 2.
    process = launch("experiment", algorithms="cma_me,map_elites", seeds="1", iterations=8,
                     n_emitters=2, batch_size=6, log_every=2, outdir=folder, pictures=False,
                     scheduler_address=dask_cluster.scheduler_address)
    wait_for(lambda: (folder / "experiment.json").exists() and all(
        checkpoint_iteration(folder / entry["name"]) >= 2 for entry in plan_of(folder)["runs"]),
        process, "every run past iteration 2")
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert f"resume {folder}" in out and "Traceback" not in err
    states = {entry["state"] for entry in plan_of(folder)["runs"]}
    assert states <= {"stopped", "done"} and "stopped" in states
    held = {entry["name"]: checkpoint_iteration(folder / entry["name"]) for entry in plan_of(folder)["runs"]}
    assert all(2 <= iteration <= 8 for iteration in held.values())

    commands.resume(str(folder), scheduler_address=dask_cluster.scheduler_address)

    # The resumed drive flew only what the checkpoints lacked: no run started again from 0.
    assert plan_of(folder)["timing"]["iterations"] == sum(8 - iteration for iteration in held.values())

    whole = tmp_path / "whole"
    commands.experiment(algorithms="cma_me,map_elites", seeds="1", iterations=8, n_emitters=2,
                  batch_size=6, log_every=2, outdir=str(whole), pictures=False,
                  scheduler_address=dask_cluster.scheduler_address)
    for entry in plan_of(folder)["runs"]:
        assert entry["state"] == "done"
        assert run_archive(folder / entry["name"]).equals(run_archive(whole / entry["name"]))
        assert run_metrics(folder / entry["name"]) == run_metrics(whole / entry["name"])


def test_resume_of_an_experiment_being_driven_is_refused(tmp_path, dask_cluster, capsys):
    folder = tmp_path / "exp"
    process = launch("experiment", algorithms="cma_me", seeds="1", iterations=200, n_emitters=2,
                     batch_size=6, log_every=2, outdir=folder,
                     scheduler_address=dask_cluster.scheduler_address)
    try:
        wait_for(lambda: (folder / "experiment.json").exists() and all(
            checkpoint_iteration(folder / entry["name"]) >= 2 for entry in plan_of(folder)["runs"]),
            process, "a run past iteration 2")

        code = ll.main(["resume", str(folder), "--scheduler_address", dask_cluster.scheduler_address])

        assert_one_line_error(Result(code, "", capsys.readouterr().err), str(folder),
                              f"is being written by another lunar_lander.py process (pid {process.pid})")
        assert "resumed" not in plan_of(folder)  # experiment.json is the driver's alone
    finally:
        process.send_signal(signal.SIGTERM)
        process.communicate(timeout=60)
    assert process.returncode == 130


def test_a_failing_run_is_recorded_and_the_others_go_on(tmp_path, dask_cluster, experiment_dir, capsys):
    folder = tmp_path / "exp"
    shutil.copytree(experiment_dir, folder)
    broken = plan_of(folder)["runs"][2]["name"]
    (folder / broken / "archive.csv").unlink()
    (folder / broken / "archive.csv").mkdir()  # its next save cannot write there

    code = ll.main(["resume", str(folder), "--iterations", "6",
                    "--scheduler_address", dask_cluster.scheduler_address])

    assert_one_line_error(Result(code, "", capsys.readouterr().err), "1 of 8 runs failed", broken, code=1)
    runs = plan_of(folder)["runs"]
    assert runs[2]["state"] == "failed" and "archive.csv" in runs[2]["error"]
    for entry in runs[:2] + runs[3:]:
        assert entry["state"] == "done" and run_metrics(folder / entry["name"])[-1]["iteration"] == 6
    assert checkpoint_iteration(folder / broken) >= 4  # its checkpoint is intact


@pytest.mark.parametrize("args, fragments", [
    (["--algorithms", "cma_me,cma_es"], ["--algorithms", "cma_es"]),
    (["--algorithms", "[]"], ["empty"]),
    (["--seeds", "5-2"], ["--seeds"]),
    (["--learning_rate", "[]"], ["empty"]),
    (["--learning_rate", "[0.1, 2]"], ["--learning_rate"]),
    (["--seed", "3"], ["--seed", "--seeds"]),
    (["--iteratons", "3"], ["--iteratons"]),
    (["--part", "0/2"], ["--part 0/2", "from 1 to K"]),
    (["--part", "3/2"], ["--part 3/2"]),
    (["--part", "1/2/3"], ["--part must be I/K", "'1/2/3'"]),
    (["--part", "half"], ["--part must be I/K"]),
])
def test_bad_experiments_are_refused_before_writing(run_cli, tmp_path, args, fragments):
    assert_one_line_error(run_cli("experiment", *args, "--outdir", tmp_path / "exp"), *fragments)
    assert not (tmp_path / "exp").exists()


def test_an_existing_folder_is_not_touched(run_cli, tmp_path):
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp" / "notes.txt").write_text("mine")
    before = folder_state(tmp_path / "exp")
    assert_one_line_error(run_cli("experiment", "--outdir", tmp_path / "exp"), "not empty")
    assert folder_state(tmp_path / "exp") == before


def test_parts_refuse_what_would_mix_two_experiments(run_cli, tmp_path, tiny_run, dask_cluster):
    assert_one_line_error(run_cli("experiment", "--part", "1/2"), "--part needs --outdir")
    flags = ["--seeds", "1-2", "--iterations", "2", "--n_emitters", "2", "--batch_size", "6",
             "--pictures", "false", "--scheduler_address", dask_cluster.scheduler_address,
             "--outdir", tmp_path / "exp"]
    assert run_cli("experiment", *flags, "--part", "1/2").returncode == 0
    before = folder_state(tmp_path / "exp")
    other = [*flags[:3], "3", *flags[4:]]  # --iterations 3: another plan
    assert_one_line_error(run_cli("experiment", *other, "--part", "2/2"), "holds another experiment",
                          "the same flags")
    assert_one_line_error(run_cli("resume", tmp_path / "exp", "--part", "1/3"), "is split in 2 parts")
    assert_one_line_error(run_cli("resume", tmp_path / "exp", "--iterations", "5"), "is fixed")
    assert_one_line_error(run_cli("resume", tiny_run, "--part", "1/2"), "--part is for an experiment")
    assert folder_state(tmp_path / "exp") == before
    result = run_cli("resume", tmp_path / "exp", "--part", "1/2")
    assert result.returncode == 0 and "nothing to do: all 1 runs of part 1 of 2" in result.stdout


@pytest.mark.parametrize("command", [["video", "--best"], ["elites"], ["trajectories", "--best"],
                                     ["explore"]])
def test_a_results_command_given_an_experiment_names_its_runs(run_cli, experiment_dir, command):
    """Not "archive.npz: no such file ... resume --trust writes it again": the folder is an
    experiment's, and the line names run folders to pass instead, which are runs."""
    before = folder_state(experiment_dir)
    result = run_cli(command[0], experiment_dir, *command[1:])
    assert_one_line_error(result)
    names = sorted(entry["name"] for entry in plan_of(experiment_dir)["runs"])
    first = [experiment_dir / name for name in names[:3]]
    assert result.stderr.strip() == (f"error: {experiment_dir}: an experiment folder, not a run folder; give "
                                     f"one of its 8 run folders: {', '.join(map(str, first))}, ...")
    assert folder_state(experiment_dir) == before
    assert len(run_folder.load_run(first[0])[0]) > 0  # what it names is a run folder


def test_compare_gives_statistics_per_setting(experiment_dir, tmp_path, capsys):
    commands.compare(str(experiment_dir), out=str(tmp_path / "cmp"))

    table = pd.read_csv(tmp_path / "cmp.csv")
    stats = pd.read_csv(tmp_path / "cmp_settings.csv")
    tests = pd.read_csv(tmp_path / "cmp_tests.csv")
    assert len(table) == 8 and table["setting"].nunique() == 4
    qd = stats[stats["metric"] == "qd_score"]
    for row in qd.to_dict("records"):
        values = table.loc[table["setting"] == row["setting"], "qd_score"]
        assert row["runs"] == 2 and row["mean"] == pytest.approx(values.mean())
        assert row["ci95_low"] <= row["mean"] <= row["ci95_high"]
    assert len(tests) == 3 * 6  # three metrics, every pair of 4 settings
    assert list(tests["metric"].unique()) == ["qd_score", "qd_auc", "cqd_score"]
    first = tests.iloc[0]
    x, y = (table.loc[table["setting"] == first[side], "qd_score"] for side in ("setting_a", "setting_b"))
    assert first["p"] == pytest.approx(mannwhitneyu(x, y, alternative="two-sided").pvalue)
    assert first["A12"] == pytest.approx(np.mean([(a > b) + 0.5 * (a == b) for a in x for b in y]))
    assert (tests["p_holm"] >= tests["p"]).all()
    assert table["cqd_score"].notna().all() and table["qd_auc"].gt(0).all()
    out = capsys.readouterr().out
    assert "fewer than 5 runs" in out and "| setting | runs |" in out
    # 2 runs a setting, 6 pairs: a complete separation has p = 2 / C(4, 2), times 6 after Holm
    assert "smallest adjusted p possible here is 1 " in out
    assert (tmp_path / "cmp.md").read_text().startswith("| setting | runs |")
    assert (tmp_path / "cmp.png").read_bytes()[:4] == b"\x89PNG"


def test_a_resumed_runs_earlier_iterations_do_not_count_in_the_bar_rate():
    import io
    import time

    from tqdm import tqdm

    bar = tqdm(total=1000, initial=10, file=io.StringIO(), mininterval=0)
    loop.count_as_done_before(bar, 500)
    time.sleep(0.05)
    bar.update(1)
    assert bar.n == 511 and bar.format_dict["initial"] == 510
    assert bar.format_dict["rate"] < 100  # one iteration in 0.05 s, not 501
    bar.close()


def test_kill_9_of_an_experiment_then_resume(tmp_path, dask_cluster):
    folder = tmp_path / "exp"
    process = launch("experiment", algorithms="cma_me", seeds="1-2", iterations=8, n_emitters=2,
                     batch_size=6, log_every=2, outdir=folder,
                     scheduler_address=dask_cluster.scheduler_address)
    wait_for(lambda: (folder / "experiment.json").exists() and any(
        checkpoint_iteration(folder / entry["name"]) >= 2 for entry in plan_of(folder)["runs"]),
        process, "a run past iteration 2")
    os.killpg(process.pid, signal.SIGKILL)
    process.communicate(timeout=60)

    commands.resume(str(folder), scheduler_address=dask_cluster.scheduler_address)
    assert all(entry["state"] == "done" for entry in plan_of(folder)["runs"])
    for entry in plan_of(folder)["runs"]:
        assert run_metrics(folder / entry["name"])[-1]["iteration"] == 8
        drawn = {p.name for p in (folder / entry["name"]).iterdir()}
        assert {"heatmap.png", "progress.png", "heatmaps"} <= drawn


# Runs that each take a moment to open and one iteration to fly: thousands of them take minutes
# to open, most of it before the first is told.
MANY_TINY_RUNS = dict(algorithms="cma_me", iterations=1, n_emitters=1, batch_size=2, pictures="false")


def run_folders(folder) -> set[str]:
    return {p.name for p in folder.iterdir() if p.is_dir()}


def test_ctrl_c_while_runs_are_opened_stops_at_once_and_their_states_are_written_once(
        tmp_path, dask_cluster):
    """2,000 runs: Ctrl-C while they are opened is acted on before the next one is, and the
    states of the runs opened are written once, not once a run (experiment.json holds every
    run's entry: each write of it grows with the plan)."""
    folder = tmp_path / "exp"
    folder.mkdir()  # empty, as the experiment takes it: watched from its first write
    writes = Replacements(folder, "experiment.json")
    process = launch("experiment", seeds="1-2000", outdir=folder, **MANY_TINY_RUNS,
                     scheduler_address=dask_cluster.scheduler_address)
    try:
        wait_for(lambda: len(run_folders(folder)) >= 20, process, "runs being opened")
        process.send_signal(signal.SIGINT)
        opened = run_folders(folder)
        out, err = process.communicate(timeout=60)  # before: it went on opening all 2,000
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.communicate()
    assert process.returncode == 130, err
    said = [line for line in out.splitlines() if "Stopped" in line]
    assert said == [f"Stopped; every run keeps its last checkpoint; continue with: "
                    f"python lunar_lander.py resume {folder}"] and "Traceback" not in err
    made = run_folders(folder)
    assert opened <= made and len(made - opened) <= 1, (  # at most the run being opened as it stopped
        f"{len(made)} runs opened, {len(opened)} when it was stopped")
    states = {entry["name"]: entry["state"] for entry in experiments.read_experiment(folder)["runs"]}
    assert {name for name, state in states.items() if state == "stopped"} == made
    assert set(states.values()) == {"stopped", "pending"}
    assert writes.count() == 2  # the plan, then the states of the runs it opened
    writes.close()


def test_kill_9_while_runs_are_opened_then_resume(tmp_path, dask_cluster):
    """Killed while its runs are opened, before their states are written: resume takes each run
    folder as it finds it (made, with or without its config and checkpoint) and finishes them all."""
    folder = tmp_path / "exp"
    process = launch("experiment", seeds="1-120", outdir=folder, **MANY_TINY_RUNS,
                     scheduler_address=dask_cluster.scheduler_address)
    wait_for(lambda: folder.exists() and len(run_folders(folder)) >= 5, process, "runs being opened")
    os.killpg(process.pid, signal.SIGKILL)
    process.communicate(timeout=60)
    runs = plan_of(folder)["runs"]
    assert {entry["state"] for entry in runs} == {"pending"} and 5 <= len(run_folders(folder)) < 120

    commands.resume(str(folder), scheduler_address=dask_cluster.scheduler_address)

    assert all(entry["state"] == "done" for entry in plan_of(folder)["runs"])
    assert all(run_metrics(folder / entry["name"])[-1]["iteration"] == 1 for entry in runs)
