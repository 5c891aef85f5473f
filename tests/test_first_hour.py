"""A researcher's first hour: results commands that add to what earlier calls wrote, evaluate and
compare of a whole experiment, summaries of counts that keep their decimals, and the package
installed with pip into a fresh environment."""

import json
import os
import shutil
import subprocess
import sys

import pandas as pd
import pytest

from conftest import ROOT
from qdsearch.analysis import comparison
from qdsearch.cli import commands
from qdsearch.config.settings import SEARCH_FLAGS
from util import run_archive, tiny_flags


@pytest.fixture(scope="module")
def small_experiment(tmp_path_factory, dask_cluster):
    """cma_me at two seeds, two iterations each."""
    folder = tmp_path_factory.mktemp("first_hour") / "exp"
    flags = {k: v for k, v in tiny_flags(dask_cluster, iterations=2, log_every=2).items()
             if k not in ("seed", "algorithm")}
    commands.experiment(algorithms="cma_me", seeds="1-2", outdir=str(folder), **flags)
    return folder


def test_a_second_video_call_adds_to_the_index(tiny_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    commands.video(str(run_dir), best=True)
    first = pd.read_csv(run_dir / "videos" / "index.csv")
    commands.video(str(run_dir), top=2)  # the best again (named as one of the top 2), and the second
    commands.video(str(run_dir), top=2)  # the same videos again: their rows replaced, not repeated
    index = pd.read_csv(run_dir / "videos" / "index.csv")
    best_two = run_archive(run_dir).sort_values(["objective", "index"], ascending=[False, True]).head(2)
    assert index.iloc[0].equals(first.iloc[0]) and len(first) == 1  # the first call's row is kept
    assert sorted(index["cell_index"]) == sorted([*best_two["index"][:1], *best_two["index"]])
    assert sorted(index["video"]) == sorted(p.name for p in (run_dir / "videos").glob("*.mp4"))


def test_each_trajectories_drawing_is_kept_and_listed(tiny_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    commands.trajectories(str(run_dir), best=True)
    commands.trajectories(str(run_dir), top=3)
    kept = sorted(p.name for p in (run_dir / "trajectories").glob("*.png"))
    assert kept == ["trajectories_001.png", "trajectories_002.png"]
    assert (run_dir / "trajectories" / kept[1]).read_bytes() == (run_dir / "trajectories.png").read_bytes()
    index = pd.read_csv(run_dir / "trajectories" / "index.csv")
    assert index.groupby("picture").size().to_dict() == {kept[0]: 1, kept[1]: 3}
    top = run_archive(run_dir).sort_values(["objective", "index"], ascending=[False, True]).head(3)
    assert index[index["picture"] == kept[1]]["cell_index"].tolist() == top["index"].tolist()


def test_evaluate_corrected_of_an_experiment_corrects_every_run_on_one_cluster(small_experiment, tmp_path,
                                                                              run_cli):
    folder = tmp_path / "exp"
    shutil.copytree(small_experiment, folder)
    result = run_cli("evaluate", folder, "--corrected", "--repeats", "2", "--workers", "1")
    assert result.returncode == 0, result.stderr
    assert (result.stdout + result.stderr).count("Starting a local Dask cluster") == 1
    names = [entry["name"] for entry in json.loads((folder / "experiment.json").read_text())["runs"]]
    for name in names:
        summary = json.loads((folder / name / "corrected.json").read_text())
        assert summary["repeats"] == 2 and summary["elites_flown"] == len(run_archive(folder / name))
    assert all(f"{name}:" in result.stdout for name in names)


def test_compare_of_an_experiment_writes_into_it(small_experiment, tmp_path, run_cli):
    folder = tmp_path / "exp"
    shutil.copytree(small_experiment, folder)
    for written in ("compare", "compare_2"):
        result = run_cli("compare", folder)
        assert result.returncode == 0, result.stderr
        assert (folder / f"{written}.png").is_file() and (folder / f"{written}.md").is_file()
    assert not (tmp_path / "outputs").exists()


def test_a_summary_of_counts_keeps_its_decimals():
    values = [10.0, 3.0, 0.5, 1.0, 0.5, 5.0, 0.25]
    stats = pd.DataFrame([{"setting": "a", "runs": 2, "metric": name, "mean": value, "low": 0.0, "high": 1.0}
                          for name, value in zip(comparison.SUMMARISED, values)])
    [row] = comparison.settings_table(stats, "mean", "low", "high")[2:]
    solved = row.split(" | ")[2 + comparison.SUMMARISED.index(comparison.SOLVED_CELLS)]
    assert solved == "0.5 [0.0, 1.0]"  # (0 and 1 solved cells: not "0 [0, 1]")


@pytest.mark.slow  # a virtual environment and pip
def test_pip_install_e_gives_the_package_to_a_notebook_elsewhere(tmp_path):
    venv, had = tmp_path / "venv", set(ROOT.glob("*.egg-info"))
    # Without a pip of its own: the system's, seen through --system-site-packages, installs into the
    # venv (its sys.prefix), and a copy of pip would add ~5 s of install that tests nothing of ours.
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)],
                   check=True)
    python = venv / "bin" / "python"
    install = subprocess.run([str(python), "-m", "pip", "install", "-q", "-e", str(ROOT)],
                             capture_output=True, text=True, cwd=tmp_path)
    assert install.returncode == 0, install.stderr
    shown = subprocess.run([str(python), "-c", "import qdsearch, importlib.metadata as m; "
                            "print(qdsearch.__file__); print(m.requires('qdsearch'))"],
                           capture_output=True, text=True, cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.startswith(str(ROOT / "qdsearch"))
    assert "ribs[visualize]==0.12.0" in shown.stdout  # the pins of requirements.txt
    for leftover in set(ROOT.glob("*.egg-info")) - had:  # setuptools' metadata of the install
        shutil.rmtree(leftover)


def test_search_config_reruns_a_run_bit_for_bit_and_takes_flags_beside_it(tiny_run, tmp_path, run_cli,
                                                                         dask_cluster):
    on_cluster = ["--scheduler_address", dask_cluster.scheduler_address]
    result = run_cli("--config", tiny_run / "config.json", *on_cluster, "--outdir", tmp_path / "again")
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "again" / "archive.csv").read_bytes() == (tiny_run / "archive.csv").read_bytes()
    result = run_cli("--config", tiny_run, "--iterations", 4, *on_cluster, "--outdir", tmp_path / "longer")
    assert result.returncode == 0, result.stderr
    original, longer = (json.loads((d / "config.json").read_text()) for d in (tiny_run, tmp_path / "longer"))
    assert longer["iterations"] == 4 and longer["seed"] == original["seed"]
    kept = [name for name in SEARCH_FLAGS if name not in ("iterations", "outdir", "scheduler_address")]
    assert [longer[name] for name in kept] == [original[name] for name in kept]
    result = run_cli("--config", tmp_path / "nowhere.json", "--outdir", tmp_path / "none")
    assert result.returncode == 2 and "nowhere.json" in result.stderr and not (tmp_path / "none").exists()


PLAN = """# two algorithms, two seeds, a tiny grid
algorithms = ["cma_me", "cma_mae"]
seeds = "1-2"
learning_rate = [0.5]
iterations = 2
n_emitters = 2
batch_size = 6
log_every = 2
pictures = false
"""


def test_an_experiment_runs_from_a_plan_file_as_from_its_flags(tmp_path, run_cli, dask_cluster):
    (tmp_path / "plan.toml").write_text(PLAN)
    on_cluster = ["--scheduler_address", dask_cluster.scheduler_address]
    result = run_cli("experiment", "--plan", tmp_path / "plan.toml", *on_cluster, "--outdir", tmp_path / "a")
    assert result.returncode == 0, result.stderr
    result = run_cli("experiment", "--algorithms", "[cma_me, cma_mae]", "--seeds", "1-2", "--learning_rate",
                     "[0.5]", "--iterations", 2, "--n_emitters", 2, "--batch_size", 6, "--log_every", 2,
                     "--pictures", "false", *on_cluster, "--outdir", tmp_path / "b")
    assert result.returncode == 0, result.stderr
    planned, typed = (json.loads((tmp_path / d / "experiment.json").read_text()) for d in "ab")
    def runs(plan):
        return [(entry["name"], entry["config"]) for entry in plan["runs"]]
    assert runs(planned) == runs(typed)
    assert len(planned["runs"]) == 4 and (tmp_path / "a" / "plan.toml").read_text() == PLAN
    for entry in planned["runs"]:
        assert run_archive(tmp_path / "a" / entry["name"]).equals(run_archive(tmp_path / "b" / entry["name"]))


def test_a_plan_files_mistakes_are_one_line(tmp_path, run_cli):
    for text, words in [("learning_rat = [0.5]\n", ["learning_rat", "did you mean learning_rate?"]),
                        ("algorithms = [\n", ["not TOML"]),
                        ('algorithms = ["cma_me", "cma-mae"]\n', ["'cma-mae'", "did you mean cma_mae?"]),
                        ("seed = 3\n", ["seed", "not a flag of experiment"])]:
        (tmp_path / "plan.toml").write_text(text)
        result = run_cli("experiment", "--plan", tmp_path / "plan.toml", "--outdir", tmp_path / "exp")
        assert result.returncode == 2 and all(w in result.stderr for w in words), (text, result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "exp").exists()


def test_the_notebook_example_reads_a_run_and_an_experiment_from_elsewhere(tiny_run, small_experiment,
                                                                            tmp_path):
    text = (ROOT / "docs" / "notebooks.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    code = code.replace('"outputs/seed42"', repr(str(tiny_run))).replace(
        '"outputs/my_experiment"', repr(str(small_experiment)))
    shown = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                           env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert shown.returncode == 0, shown.stderr
    config = json.loads((tiny_run / "config.json").read_text())
    archive = pd.read_csv(tiny_run / "archive.csv")
    best = archive.loc[archive["objective"].idxmax()]
    last = json.loads((tiny_run / "metrics.json").read_text())[-1]
    lines = shown.stdout.splitlines()
    assert lines[0] == f"{config['algorithm']} {config['seed']} {len(archive)} elites"
    assert lines[1] == f"best elite: {best['objective']} in cell {int(best['index'])}"
    assert lines[2] == f"QD score {last['qd_score']:,.0f}, coverage {last['coverage']:.3f}"
    finals = [json.loads((small_experiment / e["name"] / "metrics.json").read_text())[-1]["qd_score"]
              for e in json.loads((small_experiment / "experiment.json").read_text())["runs"]]
    mean = sum(finals) / len(finals)  # the setting's mean final QD score
    assert lines[3] == f"cma_me: mean final QD score {mean:,.1f}"  # its one setting: the algorithm


def test_read_run_gives_pyribs_archive_data_frame_and_refuses_a_non_run(tiny_run, tmp_path):
    import qdsearch

    run = qdsearch.read_run(tiny_run)
    archive = pd.read_csv(tiny_run / "archive.csv")
    assert type(run.archive).__name__ == "ArchiveDataFrame"
    assert (run.archive.get_field("objective") == archive["objective"].to_numpy()).all()
    assert (run.archive.get_field("solution") == archive.filter(like="solution_").to_numpy()).all()
    assert run.metrics["qd_score"].tolist() == [r["qd_score"] for r in json.loads(
        (tiny_run / "metrics.json").read_text())]
    with pytest.raises(qdsearch.analysis.notebook.UsageError, match="no such run folder"):
        qdsearch.read_run(tmp_path / "nothing")
