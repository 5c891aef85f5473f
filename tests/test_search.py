"""The runner: a tiny search writes a complete, valid run folder; seeds make runs repeatable."""

import json
import math
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pandas as pd
import pytest
from matplotlib.image import imread
from ribs.archives import GridArchive
from ribs.schedulers import Scheduler

from qdsearch.base import plots
from qdsearch.base.kernels import cpu_flags
from qdsearch.cli import commands
from util import (
    TINY,
    archive_table,
    assert_same_run,
    launch,
    read_checkpoint,
    run_archive,
    run_metrics,
    saved_archive,
    tiny_flags,
)

RUN_FILES = ["config.json", "checkpoint.pkl", "archive.csv", "metrics.json",
             "heatmap.png", "progress.png", "run.log"]


def test_a_progress_plot_drawn_again_is_the_picture_of_a_new_figure(tmp_path):
    """A thread's saves draw its progress figure again (its curves moved): each picture must be
    the one a new figure gives, in a thread that has drawn none, whatever came before it (a
    longer run's curves, a best objective still unknown)."""
    rng = np.random.default_rng(0)
    rows = [{"iteration": i, "evaluations": 12 * i, "qd_score": float(q), "coverage": float(q) / 1e4,
             "best_objective": None if i < 3 else float(b)}
            for i, (q, b) in enumerate(zip(np.cumsum(rng.uniform(0, 500, 80)), rng.normal(0, 100, 80)), 1)]

    def drawn(metrics, name):
        plots.save_progress_plot(metrics, tmp_path / name)
        return (tmp_path / name).read_bytes()

    def drawn_anew(metrics, name):
        with ThreadPoolExecutor(1) as thread:
            return thread.submit(drawn, metrics, name).result()

    with ThreadPoolExecutor(1) as saver:
        again = [saver.submit(drawn, rows[:n], f"again{n}.png").result() for n in (80, 2, 40, 5)]
    anew = [drawn_anew(rows[:n], f"anew{n}.png") for n in (80, 2, 40, 5)]
    assert again == anew
    assert len(set(anew)) == 4  # four different pictures


def test_the_progress_plot_is_drawn_against_evaluations(tmp_path):
    """As compare draws runs: a DQD row's iteration flies 200 evaluations, a cma_me one's 150."""
    rows = [{"iteration": i, "evaluations": 200 * i, "qd_score": 10.0 * i, "coverage": 0.1 * i,
             "best_objective": 1.0} for i in (1, 2, 3)]

    def drawn() -> tuple[list[str], list]:
        plots.save_progress_plot(rows, tmp_path / "progress.png")
        figure = plots._PROGRESS_FIGURES.figure
        return [ax.get_xlabel() for ax in figure.axes], [list(ax.lines[0].get_xdata()) for ax in figure.axes]

    with ThreadPoolExecutor(1) as thread:  # (a thread of its own: its own figure)
        labels, xs = thread.submit(drawn).result()
    assert labels == ["Evaluations"] * 3 and xs == [[200, 400, 600]] * 3


def test_tiny_search_writes_a_complete_run_folder(tmp_path, dask_cluster, capsys):
    run_dir = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, log_every=2, pictures=True), outdir=str(run_dir))

    for name in RUN_FILES:
        assert (run_dir / name).is_file(), name
    assert sorted(p.name for p in (run_dir / "heatmaps").iterdir()) == [
        "heatmap_00002.png", "heatmap_00003.png"]
    assert not [p for p in run_dir.rglob(".*.tmp")]  # no temporary files left behind

    config = json.loads((run_dir / "config.json").read_text())
    assert config["seed"] == 7 and config["iterations"] == 3 and config["batch_size"] == 6
    assert set(config["versions"]) >= {"python", "ribs", "gymnasium", "dask", "numpy"}

    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert [row["iteration"] for row in metrics] == [1, 2, 3]
    assert [row["evaluations"] for row in metrics] == [12, 24, 36]
    for row in metrics:
        assert set(row) == {"iteration", "evaluations", "coverage", "num_elites", "qd_score",
                            "best_objective", "mean_objective", "elapsed_s"}
    assert 0 < metrics[-1]["coverage"] <= 1
    assert metrics[-1]["num_elites"] == round(metrics[-1]["coverage"] * 2500)

    archive = saved_archive(run_dir)
    assert isinstance(archive, GridArchive)
    assert len(archive) == metrics[-1]["num_elites"]
    # (archive.npz made back into an archive sums its stats in another order: the last bit may differ)
    assert archive.stats.qd_score == pytest.approx(metrics[-1]["qd_score"], rel=1e-12)
    assert math.fsum(archive.data("objective") + 600.0) == pytest.approx(metrics[-1]["qd_score"], rel=1e-12)
    assert archive.best_elite["objective"] == metrics[-1]["best_objective"]

    table = pd.read_csv(run_dir / "archive.csv")
    assert len(table) == len(archive)
    assert np.allclose(table.sort_values("index")["objective"], archive_table(archive)["objective"])

    checkpoint = read_checkpoint(run_dir / "checkpoint.pkl")
    assert checkpoint["iteration"] == 3 and checkpoint["metrics"] == metrics
    assert isinstance(checkpoint["scheduler"], Scheduler)
    assert archive_table(checkpoint["scheduler"].archive).equals(archive_table(archive))

    for name in ["heatmap.png", "progress.png", "heatmaps/heatmap_00002.png"]:
        image = imread(run_dir / name)
        assert image.ndim == 3 and image.shape[0] > 300 and image.shape[1] > 400
    log = (run_dir / "run.log").read_text()
    assert "iteration 2/3" in log and "Done." in log
    out = capsys.readouterr().out  # it ends saying where the results are and how to look at them
    assert out.rstrip().splitlines()[-3:] == [
        f"Results in {run_dir}: heatmap.png, progress.png, metrics.json, archive.csv. Look at them with:",
        f"  python lunar_lander.py explore {run_dir}      # a page to browse the archive and watch "
        f"any elite",
        f"  python lunar_lander.py video {run_dir} --best   # an mp4 of the best elite"]


def test_same_seed_same_archive_with_one_or_two_workers(tmp_path, tiny_run, run_cli):
    # tiny_run flew on the session's 2-worker cluster; this one starts a cluster of 1 worker.
    result = run_cli(*[f"--{k}={v}" for k, v in tiny_flags(workers=1).items()],
                     f"--outdir={tmp_path / 'one'}")
    assert result.returncode == 0, result.stderr

    one = run_archive(tmp_path / "one")
    assert len(one) > 0 and one.equals(run_archive(tiny_run))
    assert run_metrics(tmp_path / "one") == run_metrics(tiny_run)


def test_a_run_without_pictures_is_the_same_run_with_its_data_alone(tmp_path, tiny_run, run_cli,
                                                                  dask_cluster):
    """--pictures false, from the command line and kept by resume: the same archive, metrics and
    next asks as the run that draws, no picture anywhere in its folder, and the results commands
    read it."""
    run_dir = tmp_path / "plain"
    address = ["--scheduler_address", dask_cluster.scheduler_address]
    flags = [f"--{k}={v}" for k, v in tiny_flags(iterations=1).items() if k != "pictures"]
    started = run_cli(*flags, "--pictures", "false", "--outdir", run_dir, *address)
    resumed = run_cli("resume", run_dir, "--iterations", "3", *address)
    assert started.returncode == resumed.returncode == 0, (started.stderr, resumed.stderr)
    assert_same_run(run_dir, tiny_run)
    assert json.loads((run_dir / "config.json").read_text())["pictures"] is False
    assert sorted(p.name for p in run_dir.rglob("*.png")) == []
    assert {"heatmap.png", "progress.png"} <= {p.name for p in tiny_run.iterdir()}
    assert f"Results in {run_dir}: metrics.json, archive.csv. Look at them with:" in resumed.stdout
    assert run_cli("elites", run_dir, "--top", "2").returncode == 0
    assert len(pd.read_csv(run_dir / "elites.csv")) == 2


DRAWING_PROBE = ("import json, sys; from qdsearch.cli import commands; "
                 "commands.search(**json.loads(sys.argv[1])); "
                 "print('imported:', *sorted({'matplotlib', 'ribs.visualize'} & set(sys.modules)))")


@pytest.mark.slow  # a process of its own and its local cluster
def test_a_search_without_pictures_never_imports_the_drawing(tmp_path):
    """Its driver imports what the run needs while its local cluster starts (cluster.preloading):
    without pictures, that is not matplotlib, which a run that draws imports then."""
    from conftest import ROOT

    flags = {**tiny_flags(workers=1), "outdir": str(tmp_path / "run")}
    assert flags["pictures"] is False
    result = subprocess.run([sys.executable, "-c", DRAWING_PROBE, json.dumps(flags)], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == "imported:"
    assert (tmp_path / "run" / "archive.csv").exists()


def test_another_seed_gives_another_archive(tmp_path, dask_cluster, tiny_run):
    commands.search(**tiny_flags(dask_cluster, seed=8), outdir=str(tmp_path / "b"))
    assert not run_archive(tiny_run).equals(run_archive(tmp_path / "b"))


def test_without_a_seed_one_is_drawn_and_recorded(tmp_path, dask_cluster):
    commands.search(**tiny_flags(dask_cluster, seed=None, iterations=1), outdir=str(tmp_path / "r"))
    config = json.loads((tmp_path / "r" / "config.json").read_text())
    assert isinstance(config["seed"], int) and config["seed"] >= 0


# A tiny seed-3 lander search: its archive differed on AVX-512's kernels and AVX2's (2026-11-29),
# as the full-size one's does.
ON_KERNELS = dict(TINY, iterations=4, seed=3)


def searching_on_kernels(tmp_path, cluster, monkeypatch, name, **kernels):
    """That search started as a real process, with the environment variables `kernels` (it copies
    the environment as it starts): the process and its run folder."""
    for variable, value in kernels.items():
        monkeypatch.setenv(variable, value)
    folder = tmp_path / name
    return launch(**ON_KERNELS, outdir=folder, scheduler_address=cluster.scheduler_address), folder


AVX2 = {"OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": "X86_V4,AVX512_ICL,AVX512_SPR"}
AVX512 = {"OPENBLAS_CORETYPE": "SkylakeX", "NPY_DISABLE_CPU_FEATURES": ""}


def test_a_seed_gives_one_archive_whatever_kernels_the_cpu_offers(tmp_path, dask_cluster, monkeypatch):
    """An x86-64 CPU with AVX2 runs OpenBLAS's and numpy's AVX2 kernels, whatever more it has: a
    plain search's archive is the one of a search held to them by hand, and config.json says so;
    where the CPU has AVX-512, a search on its kernels gives other bits (why the hold is there).
    The searches fly at once, on one cluster; the plain one in this process, whose kernels are the
    command line's (the test below)."""
    settings = {"held": AVX2, **({"avx512": AVX512} if "avx512f" in cpu_flags() else {})}
    searches = {name: searching_on_kernels(tmp_path, dask_cluster, monkeypatch, name, **kernels)
                for name, kernels in settings.items()}
    commands.search(**ON_KERNELS, scheduler_address=dask_cluster.scheduler_address,
                    outdir=str(tmp_path / "plain"))
    archives = {"plain": (tmp_path / "plain" / "archive.csv").read_bytes()}
    for name, (search, folder) in searches.items():
        assert search.wait(timeout=300) == 0, search.communicate()
        archives[name] = (folder / "archive.csv").read_bytes()
    assert archives["plain"] == archives["held"]
    kernels = json.loads((tmp_path / "plain" / "config.json").read_text())["versions"]["kernels"]
    if {"avx2", "fma"} <= cpu_flags():
        assert kernels.endswith(" Haswell, X86_V3")
    if "avx512" in archives:
        assert archives["avx512"] != archives["plain"]


def test_the_test_processes_run_the_kernels_the_command_line_does():
    """conftest.py imports the package before anything loads numpy, so the searches run inside the
    tests compute the command line's bits."""
    from qdsearch.base.run_files import cpu_kernels

    if {"avx2", "fma"} <= cpu_flags():
        assert cpu_kernels().endswith(" Haswell, X86_V3")
