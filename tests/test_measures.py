"""Measures and terrains of the user's choosing: --measures, --grid and several --env_seed terrains
run end to end; results commands speak the run's measures; old run folders still load."""

import json
import pickle

import numpy as np
import pandas as pd
import pytest
from matplotlib.image import imread

from qdsearch import tasks
from qdsearch.base.flags import UsageError
from qdsearch.cli import commands
from qdsearch.tasks import policies
from util import (
    LANDER,
    assert_one_line_error,
    read_checkpoint,
    run_archive,
    run_metrics,
    saved_archive,
    tiny_flags,
)

RUN_FILES = {"config.json", "checkpoint.pkl", "archive.csv", "metrics.json",
             "heatmap.png", "progress.png", "run.log"}


def tiny(dask_cluster, **overrides):
    """The tiny run's flags, for 2 iterations, with the pictures that draw its measures."""
    return tiny_flags(dask_cluster, **{"iterations": 2, "pictures": True, **overrides})


@pytest.fixture(scope="module")
def fuel_run(tmp_path_factory, dask_cluster):
    """A search in fuel and flight time on five terrains, on a 20x20 grid."""
    run_dir = tmp_path_factory.mktemp("measures") / "fuel"
    commands.search(**tiny(dask_cluster, measures="fuel,flight_time", env_seed="0-4", grid=20),
              outdir=str(run_dir))
    return run_dir


def test_chosen_measures_and_terrains_write_a_complete_run_folder(fuel_run):
    assert RUN_FILES <= {p.name for p in fuel_run.iterdir()}
    config = json.loads((fuel_run / "config.json").read_text())
    assert config["measures"] == ["fuel", "flight_time"] and config["env_seed"] == [0, 1, 2, 3, 4]
    archive = saved_archive(fuel_run)
    assert tuple(archive.dims) == (20, 20)
    ranges = [tasks.MEASURES[name].range for name in ("fuel", "flight_time")]
    assert archive.lower_bounds.tolist() == [lo for lo, _ in ranges]
    assert [row["evaluations"] for row in run_metrics(fuel_run)] == [12, 24]  # policies, not rollouts
    assert imread(fuel_run / "heatmap.png").std() > 0.05


def test_the_archive_holds_the_mean_over_the_terrains(fuel_run):
    data = saved_archive(fuel_run).data()
    env = tasks.make_env(env_name=LANDER)
    for solution, objective, measures in list(zip(data["solution"], data["objective"], data["measures"]))[:3]:
        flights = np.array([policies.rollout(solution, seed, env, ["fuel", "flight_time"], env_name=LANDER)
                            for seed in range(5)])
        assert objective == pytest.approx(flights[:, 0].mean(), rel=1e-12)
        assert measures.tolist() == pytest.approx(flights[:, 1:].mean(axis=0).tolist(), rel=1e-12)


def test_results_commands_speak_the_runs_measures(fuel_run, capsys):
    archive = saved_archive(fuel_run)
    point = tuple(float(v) for v in archive.data("measures")[0])

    commands.video(str(fuel_run), cells=[point], env_seed=3)
    commands.elites(str(fuel_run), top=2)

    index = pd.read_csv(fuel_run / "videos" / "index.csv")
    [row] = index.to_dict("records")
    assert row["video"].startswith(f"cell_fuel{point[0]:.2f}_steps{point[1]:.2f}_obj")
    assert row["env_seed"] == 3 and row["reproduced"]  # flown again on all 5 terrains, averaged
    assert row["fuel"] == point[0] and row["flight_time"] == point[1]
    assert (fuel_run / "videos" / row["video"]).stat().st_size > 1000
    assert list(pd.read_csv(fuel_run / "elites.csv").columns) == [
        "objective", "fuel", "flight_time", "cell_index"]
    assert "fuel" in capsys.readouterr().out


@pytest.mark.parametrize("measures, grid", [("max_tilt", 30), ("impact_x,impact_angle,fuel", 8)])
def test_one_or_three_measures(tmp_path, dask_cluster, measures, grid):
    run_dir = tmp_path / "run"
    commands.search(**tiny(dask_cluster, measures=measures, grid=grid), outdir=str(run_dir))
    archive = saved_archive(run_dir)
    assert tuple(archive.dims) == (grid,) * len(measures.split(","))
    assert imread(run_dir / "heatmap.png").std() > 0.05
    commands.trajectories(str(run_dir), best=True)
    assert (run_dir / "trajectories.png").is_file()


def test_a_folder_from_before_measures_existed_still_resumes(tmp_path, dask_cluster):
    """Old config.json and checkpoint: no env, no measures, no grid, env_seed a plain number."""
    flags = tiny(dask_cluster, iterations=3, env_seed=52, pictures=False)
    commands.search(**flags, outdir=str(tmp_path / "whole"))
    old = tmp_path / "old"
    commands.search(**{**flags, "iterations": 1}, outdir=str(old))
    checkpoint = read_checkpoint(old / "checkpoint.pkl")
    for config in (checkpoint["config"], json.loads((old / "config.json").read_text())):
        for key in ("measures", "grid", "env"):
            del config[key]
        config["env_seed"] = 52
        (old / "config.json").write_text(json.dumps(config))
    (old / "checkpoint.pkl").write_bytes(pickle.dumps(checkpoint))  # unsigned, as then
    (old / "archive.npz").unlink()  # nor was there an archive.npz: archive.csv is read

    commands.elites(str(old))  # results commands read it as the tutorial's measures
    commands.resume(str(old), iterations=3, scheduler_address=dask_cluster.scheduler_address, trust=True)

    assert run_archive(old).equals(run_archive(tmp_path / "whole"))
    assert run_metrics(old) == run_metrics(tmp_path / "whole")


@pytest.mark.parametrize("args, fragments", [
    (["--measures", "fuel,speed"], ["--measures", "speed"]),
    (["--measures", "fuel,fuel"], ["--measures"]),
    (["--measures", "impact_x,fuel,max_tilt,flight_time"], ["6,250,000 cells"]),
    (["--measures", "impact_x,fuel,max_tilt,flight_time,impact_angle", "--grid", "5"],
     ["5 measures on a grid", "--archive cvt"]),
    (["--archive", "cvt", "--cells", "7", "--measures", "impact_x,fuel,max_tilt"], ["--cells 7", "2^3 = 8"]),
    (["--archive", "cvt", "--grid", "20"], ["--grid is for --archive grid"]),
    (["--cells", "20"], ["--cells is for --archive cvt"]),
    (["--grid", "0"], ["--grid"]),
    (["--grid", "200", "--measures", "impact_x,fuel,max_tilt"], ["8,000,000 cells"]),
    (["--env_seed", "5-2"], ["--env_seed"]),
])
def test_bad_measures_grid_and_terrains_are_refused(run_cli, tmp_path, args, fragments):
    assert_one_line_error(run_cli(*args, "--outdir", tmp_path / "run"), *fragments)
    assert not (tmp_path / "run").exists()


def test_cells_must_be_points_of_the_runs_measures(fuel_run):
    with pytest.raises(UsageError, match=r"points of \(fuel, flight_time\)"):
        commands.video(str(fuel_run), cells="[(0.1, -0.1, 3)]")
    with pytest.raises(UsageError, match="outside the archive: fuel in"):
        commands.video(str(fuel_run), cells="[(900, 100)]")
