"""A plan's [[rows]] each give their own flags (one experiment, one SLURM array, holds a whole
comparison), the papers' settings are such plans (docs/presets/), and the SLURM recipe takes its
number of parts from the array."""

import json
import shutil
import subprocess
import tomllib

import pytest

from conftest import ROOT
from qdsearch.base.flags import UsageError
from qdsearch.config import options
from qdsearch.search import experiments
from qdsearch.search.experiment_folder import shortened
from util import assert_one_line_error, folder_state, run_archive, run_metrics

PRESETS = sorted((ROOT / "docs" / "presets").glob("*.toml"))
ROWS_PLAN = """\
seeds = "1"
iterations = 2
n_emitters = 1
log_every = 2
pictures = false
es_sigma = 0.05

[[rows]]
algorithms = "cma_mega_es"
batch_size = 3
es_samples = 4

[[rows]]
algorithms = ["map_elites", "cma_me"]
batch_size = 5
"""


@pytest.mark.slow  # real runs
def test_each_row_of_a_plan_runs_with_its_own_flags_as_search_alone_would(tmp_path, run_cli, dask_cluster):
    (tmp_path / "plan.toml").write_text(ROWS_PLAN)
    on_cluster = ["--scheduler_address", dask_cluster.scheduler_address]
    result = run_cli("experiment", "--plan", tmp_path / "plan.toml", *on_cluster,
                     "--outdir", tmp_path / "exp")
    assert result.returncode == 0, result.stderr
    plan = json.loads((tmp_path / "exp" / "experiment.json").read_text())
    made = [(entry["config"]["algorithm"], entry["config"]["batch_size"], entry["config"]["es_samples"],
             entry["config"]["es_sigma"]) for entry in plan["runs"]]
    assert made == [("cma_mega_es", 3, 4, 0.05), ("map_elites", 5, 100, 0.05), ("cma_me", 5, 100, 0.05)]
    assert [row["axes"]["algorithm"] for row in plan["rows"]] == [["cma_mega_es"], ["map_elites", "cma_me"]]
    for entry in plan["runs"]:  # each run is bit for bit its lone twin's
        config = entry["config"]
        flags = ["--algorithm", config["algorithm"], "--batch_size", config["batch_size"], "--seed", 1,
                 "--iterations", 2, "--n_emitters", 1, "--log_every", 2, "--pictures", "false"]
        flags += ["--es_samples", 4, "--es_sigma", 0.05] if config["algorithm"] == "cma_mega_es" else []
        alone = tmp_path / f"alone_{config['algorithm']}"
        result = run_cli(*flags, *on_cluster, "--outdir", alone)
        assert result.returncode == 0, result.stderr
        assert run_archive(tmp_path / "exp" / entry["name"]).equals(run_archive(alone))
        assert run_metrics(tmp_path / "exp" / entry["name"]) == run_metrics(alone)


@pytest.mark.slow  # real runs
def test_a_flag_given_beside_a_plan_replaces_every_rows_value(tmp_path, run_cli, dask_cluster):
    (tmp_path / "plan.toml").write_text(ROWS_PLAN)
    result = run_cli("experiment", "--plan", tmp_path / "plan.toml", "--batch_size", 2, "--iterations", 1,
                     "--scheduler_address", dask_cluster.scheduler_address, "--outdir", tmp_path / "exp")
    assert result.returncode == 0, result.stderr
    plan = json.loads((tmp_path / "exp" / "experiment.json").read_text())
    assert {(e["config"]["batch_size"], e["config"]["iterations"]) for e in plan["runs"]} == {(2, 1)}
    assert [e["config"]["es_samples"] for e in plan["runs"]] == [4, 100, 100]


@pytest.mark.slow  # real runs
def test_an_experiment_resumed_to_a_budget_in_evaluations_takes_each_row_to_its_own_iteration(
        tmp_path, run_cli, dask_cluster):
    """cma_mega_es here flies 8 evaluations an iteration (the point, 4 samples, 3 branches),
    cma_me 5: resumed from 40 to 80 evaluations, they go from 5 and 8 to 10 and 16 iterations,
    each run bit for bit its lone twin started with --evaluations 80."""
    plan = ROWS_PLAN.replace("iterations = 2", "evaluations = 40")
    (tmp_path / "plan.toml").write_text(plan.replace('["map_elites", "cma_me"]', '"cma_me"'))
    on_cluster = ["--scheduler_address", dask_cluster.scheduler_address]
    result = run_cli("experiment", "--plan", tmp_path / "plan.toml", *on_cluster,
                     "--outdir", tmp_path / "exp")
    assert result.returncode == 0, result.stderr
    result = run_cli("resume", tmp_path / "exp", "--evaluations", 80, *on_cluster)
    assert result.returncode == 0, result.stderr
    entries = json.loads((tmp_path / "exp" / "experiment.json").read_text())["runs"]
    assert [(e["config"]["iterations"], e["config"]["evaluations"], e["state"]) for e in entries] == [
        (10, 80, "done"), (16, 80, "done")]
    for entry, per_iteration in zip(entries, (8, 5)):
        rows = run_metrics(tmp_path / "exp" / entry["name"])
        assert rows[-1]["evaluations"] == 80 and len(rows) == 80 // per_iteration
        twin = tmp_path / f"twin_{entry['config']['algorithm']}"
        flags = ["--algorithm", entry["config"]["algorithm"], "--batch_size", entry["config"]["batch_size"],
                 "--seed", 1, "--evaluations", 80, "--n_emitters", 1, "--log_every", 2, "--pictures", "false"]
        flags += ["--es_samples", 4, "--es_sigma", 0.05] if per_iteration == 8 else []
        assert run_cli(*flags, *on_cluster, "--outdir", twin).returncode == 0
        assert run_archive(tmp_path / "exp" / entry["name"]).equals(run_archive(twin))
        assert run_metrics(tmp_path / "exp" / entry["name"]) == run_metrics(twin)
    assert_one_line_error(run_cli("resume", tmp_path / "exp", "--evaluations", 40, *on_cluster),
                          "goes to iteration 10", "--evaluations 40 would end it sooner")


def test_a_resumed_budget_is_the_last_iteration_within_it():
    """cma_mega_es with 1 emitter, 4 samples and 3 branches flies 8 evaluations an iteration."""
    config = {"algorithm": "cma_mega_es", "n_emitters": 1, "batch_size": 3, "es_samples": 4,
              "iterations": 5, "evaluations": 40}
    assert options.resumed_budget(config, None, 85) == {**config, "iterations": 10, "evaluations": 85}
    assert options.resumed_budget(config, None, None) == config
    assert options.resumed_budget(config, 9, None) == {**config, "iterations": 9, "evaluations": None}
    assert options.resumed_budget(config, 5, None) == config  # its own budget: its evaluations kept
    with pytest.raises(UsageError, match="^--iterations and --evaluations are two budgets; give one$"):
        options.resumed_budget(config, 9, 85)
    with pytest.raises(UsageError, match="less than one iteration"):
        options.resumed_budget(config, None, 7)


@pytest.mark.slow  # processes of their own (a lock file holds its writer's pid)
def test_a_resume_to_a_bad_budget_is_one_line_and_touches_nothing(tiny_run, tmp_path, run_process):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    before = folder_state(run_dir)  # its lock file too: refused before the folder is locked
    assert_one_line_error(run_process("resume", run_dir, "--evaluations", 10),
                          "--evaluations 10 is less than one iteration of --algorithm cma_me, which flies 12")
    assert_one_line_error(run_process("resume", run_dir, "--evaluations", 100, "--iterations", 9),
                          "two budgets")
    assert folder_state(run_dir) == before


def test_a_label_keeps_what_tells_the_settings_apart_and_an_algorithms_own_flags():
    labels = ["cma_mae grid=32 n_emitters=2 learning_rate=0.5",
              "cma_mae grid=32 n_emitters=2 learning_rate=0.1",
              "cma_me grid=32 n_emitters=4", "cma_mae grid=32 n_emitters=2 learning_rate=0.5"]
    assert shortened(labels) == {labels[0]: "cma_mae n_emitters=2 learning_rate=0.5",
                                 labels[1]: "cma_mae n_emitters=2 learning_rate=0.1",
                                 labels[2]: "cma_me n_emitters=4"}
    assert shortened(["cma_mae grid=32 learning_rate=0.5"]) == {
        "cma_mae grid=32 learning_rate=0.5": "cma_mae learning_rate=0.5"}  # alone: its own flag stays
    assert shortened([]) == {}
    firsts = ["dds bandwidth=0.1 grid=32", "dds bandwidth=0.2 grid=32"]  # the first flag tells them apart
    assert list(shortened(firsts).values()) == ["dds bandwidth=0.1", "dds bandwidth=0.2"]
    assert shortened(["? grid=32", "? grid=64"]) == {"? grid=32": "? grid=32", "? grid=64": "? grid=64"}


def test_a_flag_given_beside_a_plan_is_dropped_from_each_row_a_budget_with_its_budget():
    row = {"evaluations": 5, "batch_size": 3, "sigma0": 0.5}
    assert experiments.without_given(row, {"iterations"}) == {"batch_size": 3, "sigma0": 0.5}
    assert experiments.without_given(row, {"sigma0"}) == {"evaluations": 5, "batch_size": 3}
    assert experiments.without_given(row, set()) == row


def test_the_runs_of_a_plans_rows_are_every_rows_in_order():
    grids = [experiments.experiment_grid(algorithm, "1-2", {"n_emitters": n, "iterations": 1}, None)
             for algorithm, n in (("cma_me", 1), ("map_elites", 2))]
    runs = experiments.rows_runs(grids)
    assert [entry["name"] for entry in runs] == [
        "cma_me_n_emitters_1_seed1", "cma_me_n_emitters_1_seed2", "map_elites_n_emitters_2_seed1",
        "map_elites_n_emitters_2_seed2"]


@pytest.mark.parametrize("text, words", [
    ('[[rows]]\nalgorithms = "cma_me"\nseeds = "1-2"\n',
     ["[[rows]] 1: 'seeds' is not a flag of experiment a row may set; did you mean"]),
    ('learning_rat = 0.5\n', ["'learning_rat' is not a flag of experiment; did you mean learning_rate?"]),
    ('[[rows]]\nalgorithms = "cma_me"\nbatch_sise = 3\n',
     ["[[rows]] 1: 'batch_sise'", "did you mean batch_size?"]),
    ('rows = 3\n', ["rows must be [[rows]] tables"]),
    ('n_emitters = [{x = 1}]\n', ["n_emitters is a table; give a value or a list of values"]),
    ('[[rows]]\nbatch_size = {x = 1}\n', ["[[rows]] 1: batch_size is a table"]),
    ('[[rows]]\nalgorithms = "cma_me"\n[[rows]]\nalgorithms = "cma_me"\n',
     ["row 2 makes the setting 'cma_me'"]),
    ('[[rows]]\nalgorithms = "map_elites"\nlearning_rate = 0.1\n', ["--learning_rate", "map_elites"]),
])
def test_a_rows_mistakes_are_one_line(tmp_path, run_cli, text, words):
    (tmp_path / "plan.toml").write_text(text)
    result = run_cli("experiment", "--plan", tmp_path / "plan.toml", "--outdir", tmp_path / "exp")
    assert_one_line_error(result, *words)
    assert ("a row may set" in result.stderr) == ("[[rows]]" in words[0] and "'" in words[0])
    assert not (tmp_path / "exp").exists()


@pytest.mark.parametrize("path", PRESETS, ids=[path.stem for path in PRESETS])
def test_each_preset_is_a_plan_of_its_papers_settings(path, run_cli, tmp_path):
    """Every preset is planned as it stands (checked, each run's config made; --evaluations 1 is
    below one iteration, so nothing is flown), and says in its comments what still differs."""
    planned = tomllib.loads(path.read_text())
    assert "What still differs" in path.read_text()
    # the papers' budgets: 1,000,000 evaluations (QD-RL), 10,000 iterations (pyribs' sphere.py)
    assert planned.get("evaluations", 0) >= 100_000 or planned.get("iterations", 0) >= 10_000
    assert planned["seeds"] in ("1-5", "1-20")
    result = run_cli("experiment", "--plan", path, "--evaluations", 1, "--outdir", tmp_path / "exp")
    assert_one_line_error(result, "--evaluations 1 is less than one iteration")


@pytest.mark.slow  # MuJoCo runs of 19,590-weight networks
def test_dqd_rls_preset_runs_a_tiny_budget_given_beside_it(tmp_path, run_cli, dask_cluster):
    path = ROOT / "docs" / "presets" / "dqd_rl_walker.toml"
    result = run_cli("experiment", "--plan", path, "--evaluations", 201, "--seeds", 1, "--episode_length", 5,
                     "--scheduler_address", dask_cluster.scheduler_address, "--outdir", tmp_path / "exp")
    assert result.returncode == 0, result.stderr
    plan = json.loads((tmp_path / "exp" / "experiment.json").read_text())
    rows = [(e["config"]["algorithm"], e["config"]["batch_size"], e["config"]["grid"], e["config"]["reset"],
             e["config"]["hidden"], e["state"]) for e in plan["runs"]]
    assert rows == [("cma_mega_es", 99, 32, "each", [128, 128], "done"),
                    ("map_elites", 100, 32, "each", [128, 128], "done"),
                    ("me_es", 30, 32, "each", [128, 128], "done"),  # (its batch unused)
                    ("pga_me", 99, 32, "each", [128, 128], "done"),
                    ("cma_mega_td3_es", 99, 32, "each", [128, 128], "done")]
    # each to its last iteration within 201: ME-ES's first (of 201 a budget counts) flies x0 alone;
    # the learning rows' greedy actor besides (PGA-ME: 99 + 1; CMA-MEGA (TD3, ES): 99 + 1 + 101)
    spent = [run_metrics(tmp_path / "exp" / e["name"])[-1]["evaluations"] for e in plan["runs"]]
    assert spent == [200, 200, 1, 200, 201]


def slurm_parts(environment: dict[str, str]) -> str:
    """The number of parts the SLURM recipe's PARTS line makes in this environment, run by bash."""
    line = next(line for line in (ROOT / "docs" / "slurm_parts.sbatch").read_text().splitlines()
                if line.startswith("PARTS="))
    shown = subprocess.run(["bash", "-c", f'{line}\necho "$PARTS"'], capture_output=True, text=True,
                           env={"PATH": "/usr/bin:/bin", **environment}, check=True)
    return shown.stdout.strip()


def test_the_slurm_recipe_takes_its_parts_from_the_array():
    assert slurm_parts({"SLURM_ARRAY_TASK_COUNT": "12"}) == "12"
    assert slurm_parts({"SLURM_ARRAY_TASK_COUNT": "2", "PARTS": "8"}) == "8"  # a rerun of two parts
