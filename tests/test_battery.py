"""The faults a reliability battery found in the newest surfaces, each kept from coming back:
values that would fail a run late are refused before anything is written (cells past k-means'
samples, a swept --cells, absurd step sizes, a row's flag given to a row that ignores it); an
edited centroids.npy stops resume; compare names the runs an unfinished plan lacks; evaluate
--corrected pairs the archive with its own iteration's metrics while a run is being written; and
the parts of a split experiment drive every run of the plan once."""

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from qdsearch.cli import commands
from qdsearch.config import options
from qdsearch.search import experiments
from qdsearch.search.parts import runs_of_part
from util import assert_one_line_error, folder_state, saved_archive, tiny_flags

# ---- bad values, refused up front ------------------------------------------------------------

REFUSED = [
    (["--archive", "cvt", "--cells", "100001"], "--cells must be at most 100,000"),
    (["experiment", "--archive", "cvt", "--cells", "[64, 200000]", "--seeds", "1"],
     "--cells must be at most 100,000, got 200000"),
    (["experiment", "--archive", "cvt", "--measures", "impact_x,impact_y_velocity,fuel",
      "--cells", "[64, 4]", "--seeds", "1"], "--cells 4 is too few for 3 measures"),
    (["--sigma0", "1e300"], "--sigma0 must be at most 1000"),
    (["--env", "Hopper-v5", "--algorithm", "line_map_elites", "--line_sigma", "1e300"],
     "--line_sigma must be at most 1000"),
    (["experiment", "--sigma0", "[0.5, 1e300]", "--seeds", "1"], "--sigma0 must be at most 1000"),
    (["--novelty_threshold", "0.1"], "--novelty_threshold is a flag of ns_cma, nslc only; "
                                     "--algorithm cma_me does not use it"),
    (["--algorithm", "map_elites", "--learning_rate", "0.1"], "--learning_rate is a flag of cma_mae"),
    (["experiment", "--algorithms", "[cma_me, map_elites]", "--learning_rate", "[0.1, 0.5]"],
     "none of --algorithms cma_me, map_elites use it"),
]


@pytest.mark.parametrize("args, words", REFUSED, ids=[" ".join(a) for a, _ in REFUSED])
def test_values_that_would_fail_late_are_refused_before_anything_is_written(run_cli, tmp_path, args, words):
    assert_one_line_error(run_cli(*args, "--outdir", tmp_path / "out"), words)
    assert not (tmp_path / "out").exists() and not (tmp_path / "outputs").exists()


def test_a_rows_own_flag_is_taken_where_a_row_uses_it(run_cli, tmp_path, dask_cluster):
    """The refusal is of flags typed for rows that ignore them: cma_mae takes --learning_rate;
    an experiment of rows one of which uses it takes it too (the other runs ignore it); and a
    run's recorded config, every flag in it, starts its twin (search called with it)."""
    address = dask_cluster.scheduler_address
    result = run_cli("--algorithm=cma_mae", "--learning_rate", "0.2", "--iterations", "1",
                     "--n_emitters", "1", "--batch_size", "2", "--pictures", "false",
                     "--scheduler_address", address, "--outdir", tmp_path / "mae")
    assert result.returncode == 0, result.stderr
    recorded = json.loads((tmp_path / "mae" / "config.json").read_text())
    flags = {k: v for k, v in recorded.items() if k in options.search_defaults()}
    commands.search(**{**flags, "algorithm": "cma_me", "outdir": str(tmp_path / "me"),
                  "scheduler_address": address})
    assert json.loads((tmp_path / "me" / "config.json").read_text())["learning_rate"] == 0.2
    assert experiments.experiment_grid("cma_me,cma_mae", "1", {"learning_rate": [0.1]})[0] == {
        "algorithm": ["cma_me", "cma_mae"], "learning_rate": [0.1]}


# ---- a CVT run's centroids -------------------------------------------------------------------

@pytest.fixture(scope="module")
def cvt_run(tmp_path_factory, dask_cluster):
    run_dir = tmp_path_factory.mktemp("cvt") / "run"
    commands.search(**tiny_flags(dask_cluster, archive="cvt", cells=16, iterations=2, log_every=2),
               outdir=str(run_dir))
    return run_dir


@pytest.mark.parametrize("edit", ["truncated", "another shape", "other values"])
def test_resume_refuses_an_edited_centroids_file_and_writes_a_deleted_one_again(
        cvt_run, tmp_path, run_cli, dask_cluster, edit):
    run_dir = tmp_path / "run"
    shutil.copytree(cvt_run, run_dir)
    path, centroids = run_dir / "centroids.npy", np.load(cvt_run / "centroids.npy")
    if edit == "truncated":
        path.write_bytes(path.read_bytes()[:100])
    else:
        np.save(path, centroids[:8] if edit == "another shape" else centroids + 0.01)
    before = folder_state(run_dir)
    assert_one_line_error(run_cli("resume", run_dir, "--iterations", "3"), str(path))
    assert folder_state(run_dir) == before
    path.unlink()
    result = run_cli("resume", run_dir, "--iterations", "3",
                     "--scheduler_address", dask_cluster.scheduler_address)
    assert result.returncode == 0, result.stderr
    assert np.array_equal(np.load(path), centroids)
    assert np.array_equal(saved_archive(run_dir).centroids, centroids)


# ---- compare of an unfinished plan -----------------------------------------------------------

def test_compare_of_a_half_finished_split_experiment_names_the_runs_it_lacks(tmp_path, dask_cluster,
                                                                              run_cli):
    folder = tmp_path / "exp"
    commands.experiment(algorithms="cma_me", seeds="1-4", outdir=str(folder), part="1/2",
                           iterations=2, n_emitters=1, batch_size=4, log_every=2, pictures=False,
                           scheduler_address=dask_cluster.scheduler_address)
    plan = json.loads((folder / "experiment.json").read_text())
    missing = [entry["name"] for entry in runs_of_part(plan, 2)]
    result = run_cli("compare", folder, "--out", tmp_path / "c")
    assert result.returncode == 0, result.stderr
    note = next(line for line in result.stdout.splitlines() if line.startswith(f"note: {folder}"))
    assert "2 of 4 runs of its plan are not done" in note and "2 of them have no metrics" in note
    assert all(f"{name} (pending)" in note for name in missing)
    assert f"python lunar_lander.py resume {folder} --part 2/2" in note
    assert len(pd.read_csv(tmp_path / "c.csv")) == 2  # the runs part 1 finished


# ---- evaluate --corrected while a run is being written ---------------------------------------

def test_corrected_metrics_pair_the_archive_with_its_own_iteration(tmp_path, tiny_run, reference,
                                                                   dask_cluster):
    """A run being written saves metrics.json, then archive.pkl: between the two, metrics.json is
    ahead. Here the tiny run's archive (iteration 3) lies beside the metrics of the same seed
    carried on to iteration 12; corrected.json must be of iteration 3, with iteration 3's figures."""
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    shutil.copy(reference / "metrics.json", run_dir / "metrics.json")
    own = json.loads((tiny_run / "metrics.json").read_text())[-1]
    commands.evaluate(str(run_dir), corrected=True, repeats=1,
                        scheduler_address=dask_cluster.scheduler_address)
    summary = json.loads((run_dir / "corrected.json").read_text())
    assert summary["iteration"] == own["iteration"] == 3 and summary["evaluations"] == own["evaluations"]
    assert summary["run"] == {key: own[key] for key in summary["run"]}


# ---- the parts of a plan ---------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(st.integers(1, 4), st.integers(1, 5), st.integers(1, 12))
def test_the_parts_of_a_plan_drive_every_run_once(settings_count, seeds, parts):
    """Parts 1..K of any plan (real runs of experiment_runs) hold every run once and no run twice,
    and each part a share of every setting as even as K allows."""
    rates = [round(0.1 * (i + 1), 1) for i in range(settings_count)]
    axes, common, seed_list = experiments.experiment_grid("cma_mae", f"1-{seeds}", {"learning_rate": rates})
    plan = {"runs": experiments.experiment_runs(axes, common, seed_list), "parts": parts}
    driven = [entry["name"] for part in range(1, parts + 1) for entry in runs_of_part(plan, part)]
    assert sorted(driven) == sorted(entry["name"] for entry in plan["runs"])
    assert len(set(driven)) == len(driven) == settings_count * seeds
    assert runs_of_part({**plan, "parts": None}, None) == plan["runs"]
    sizes = [len(runs_of_part(plan, part)) for part in range(1, parts + 1)]
    assert max(sizes) - min(sizes) <= 1

