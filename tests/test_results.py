"""Looking at a run: videos of chosen cells, the elite table, trajectories, robustness on new terrains."""

import json
import re
import shutil

import imageio_ffmpeg
import numpy as np
import pandas as pd
import pytest
from matplotlib.image import imread

from qdsearch import tasks
from qdsearch.analysis import evaluation, results
from qdsearch.base.flags import UsageError, seed_list
from qdsearch.cli import app as ll
from qdsearch.cli import commands
from qdsearch.tasks import fast_lander, lander, policies
from util import LANDER, assert_one_line_error, folder_state, saved_archive, tiny_flags

TUTORIAL = list(tasks.TUTORIAL_MEASURES)  # the measures of the run the tests look at


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory, tiny_run):
    """A copy of the tiny run (a few dozen elites, most cells empty), for these commands to write in."""
    run_dir = tmp_path_factory.mktemp("results") / "run"
    shutil.copytree(tiny_run, run_dir)
    return run_dir


@pytest.fixture(scope="module")
def archive(run_dir):
    return saved_archive(run_dir)


def read_csv(path):
    return pd.read_csv(path)  # pandas 3 reads floats back bit for bit (round trip)


def grid_distance(archive, cell_a, cell_b):
    return np.linalg.norm(np.subtract(np.unravel_index(cell_a, archive.dims),
                                      np.unravel_index(cell_b, archive.dims)))


def empty_point_next_to_an_elite(archive):
    """The measures of an empty cell one column right of an elite's cell."""
    width = archive.interval_size / np.array(archive.dims)
    for x, v in archive.data("measures"):
        point = (x + width[0], v)
        inside = np.all((archive.lower_bounds <= point) & (point < archive.upper_bounds))
        if inside and not archive.retrieve_single(point)[0]:
            return point
    raise AssertionError("every elite has a right neighbour")


def test_video_of_a_cell_has_every_frame_and_reproduces_the_elite(run_dir, archive, capsys):
    data = archive.data()
    lengths = []
    for solution in data["solution"]:  # the shortest episode makes the quickest video
        path = []
        policies.rollout(solution, 52, tasks.make_env(env_name=LANDER), trajectory=path, env_name=LANDER)
        lengths.append(len(path))
    shortest = int(np.argmin(lengths))
    point = tuple(data["measures"][shortest])

    commands.video(str(run_dir), cells=[point])

    objective = data["objective"][shortest]
    name = f"cell_x{point[0]:.2f}_v{point[1]:.2f}_obj{objective:.0f}.mp4"
    video = run_dir / "videos" / name
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
    assert frames == lengths[shortest] + 1  # the reset's frame, then one per step
    reader = imageio_ffmpeg.read_frames(str(video))
    meta = next(reader)
    assert meta["size"] == (600, 400) and meta["fps"] == 50
    first = np.frombuffer(next(reader), np.uint8).reshape(400, 600, 3)
    assert first.std() > 10  # a picture (sky, ground, lander), not a blank frame
    reader.close()

    index = read_csv(run_dir / "videos" / "index.csv")
    assert index.to_dict("records") == [{
        "video": name, "env_seed": 52, "reset_seed": 52, "cell_index": data["index"][shortest],
        "objective": objective,
        "impact_x": point[0], "impact_y_velocity": point[1], "reflown_objective": objective,
        "reproduced": True}]
    out, err = capsys.readouterr()
    assert f"objective {objective:.2f}" in out and "warning" not in err
    assert not list((run_dir / "videos").glob(".*"))  # no recording folder left behind


def test_empty_cell_names_the_nearest_and_nearest_uses_it(archive):
    point = empty_point_next_to_an_elite(archive)
    cell = archive.index_of_single(point)
    occupied = archive.data("index")
    distances = [grid_distance(archive, cell, other) for other in occupied]
    assert min(distances) == 1
    nearest = min(occupied[np.flatnonzero(np.array(distances) == 1)])

    with pytest.raises(UsageError, match=f"is empty; the nearest occupied cell .*cell {nearest}"
                                            r"\); add --nearest"):
        results.select_elites(archive, cells=[point], measures=TUTORIAL)
    [elite] = results.select_elites(archive, cells=[point], nearest=True, measures=TUTORIAL)
    assert elite["index"] == nearest
    assert elite["name"].startswith(f"cell_x{point[0]:.2f}_v{point[1]:.2f}_nearest{nearest}_obj")


def test_selection_by_best_top_index_and_cells(archive):
    ranked = archive.data(return_type="pandas").sort_values("objective", ascending=False)["index"]
    chosen = results.select_elites(archive, cells="[(0.0, -0.1)]", best=True, top=3,
                                   index=int(ranked.iloc[-1]), nearest=True, measures=TUTORIAL)
    assert chosen[0]["name"].startswith("cell_x0.00_v-0.10_")
    assert [elite["index"] for elite in chosen[1:]] == ranked.iloc[[0, 0, 1, 2, -1]].tolist()
    assert [elite["name"].split("_")[0] for elite in chosen[1:]] == [
        "best", "top01", "top02", "top03", f"index{ranked.iloc[-1]}"]
    # --cells as Fire hands it over: parsed, one tuple alone, or raw text
    tutorial = list(tasks.TUTORIAL_MEASURES)
    assert results.parse_cells("[(-0.4, -0.1), (0.6, -0.1)]", tutorial) == [(-0.4, -0.1), (0.6, -0.1)]
    assert results.parse_cells((0.0, -0.1), tutorial) == [(0.0, -0.1)]
    assert results.parse_cells([(0, -0.1)], tutorial) == [(0.0, -0.1)]
    assert results.parse_cells("[(120,), (300,)]", ["fuel"]) == results.parse_cells((120, 300), ["fuel"]) == [
        (120.0,), (300.0,)]
    assert results.parse_cells("[(1, 2, 3)]", ["fuel", "flight_time", "max_tilt"]) == [(1.0, 2.0, 3.0)]


def test_elite_table_is_archive_data_sorted_and_filtered(run_dir, archive, capsys):
    data = archive.data(return_type="pandas")
    threshold = float(data["objective"].median())
    commands.elites(str(run_dir), min_objective=threshold, top=5)

    table = read_csv(run_dir / "elites.csv")
    expected = data[data["objective"] >= threshold].nlargest(5, "objective")
    assert list(table.columns) == ["objective", "impact_x", "impact_y_velocity", "cell_index"]
    assert table["cell_index"].tolist() == expected["index"].tolist()
    assert np.array_equal(table[["objective", "impact_x", "impact_y_velocity"]].to_numpy(),
                          expected[["objective", "measures_0", "measures_1"]].to_numpy())
    out = capsys.readouterr().out
    assert out.splitlines()[0].split() == ["objective", "impact_x", "impact_y_velocity", "cell_index"]
    assert f"{len(table)} of {len(data)} elites" in out


def test_trajectory_picture_of_the_top_elites(run_dir, archive):
    before = folder_state(run_dir)
    commands.trajectories(str(run_dir), top=3)

    image = imread(run_dir / "trajectories.png")
    assert image.shape[0] > 400 and image.shape[1] > 600 and image.std() > 0.05
    after = folder_state(run_dir)
    assert {name: after[name] for name in before if name in after} == before  # nothing else touched

    top = results.select_elites(archive, top=3, measures=TUTORIAL)
    paths = results.fly_paths(top, 52, tasks.DEFAULT_ENV)
    for elite, (path, step) in zip(top, paths):  # the drawn paths are their flights
        assert path[step, 0] == elite["measures"][0]  # the dot is at touchdown, where impact x is


def test_terrain_is_the_envs_ground():
    env = tasks.make_env(fast=False, env_name=LANDER)
    env.reset(seed=52)
    edges = [fixture.shape.vertices for fixture in env.unwrapped.moon.fixtures[1:]]
    ground = lander.terrain(52)
    expected = np.array([edges[0][0], *(end for _, end in edges)])
    assert np.allclose(ground[:, 0], (expected[:, 0] - fast_lander.HALF_W) / fast_lander.HALF_W)
    assert np.allclose(ground[:, 1], (expected[:, 1] - fast_lander.PAD_Y) / fast_lander.HALF_H)
    env.close()


def test_robustness_on_two_terrains_matches_direct_rollouts(run_dir, archive, dask_cluster, capsys):
    commands.evaluate(str(run_dir), env_seeds="3,4", top=4,
                           scheduler_address=dask_cluster.scheduler_address)

    table = read_csv(run_dir / "robustness.csv")
    top = archive.data(return_type="pandas").nlargest(4, "objective")
    assert sorted(table["cell_index"]) == sorted(top["index"])
    env, data = tasks.make_env(fast=False, env_name=LANDER), archive.data()
    solutions = dict(zip(data["index"], data["solution"]))
    for row in table.to_dict("records"):
        direct = np.array([policies.rollout(solutions[row["cell_index"]], seed, env, env_name=LANDER)[0]
                           for seed in (3, 4)])
        assert [row["objective_seed3"], row["objective_seed4"]] == direct.tolist()
        assert row["mean_objective"] == pytest.approx(direct.mean(), abs=1e-9)
        assert row["min_objective"] == direct.min()
        assert row["std_objective"] == pytest.approx(direct.std(), abs=1e-9)
        assert row["solved_share"] == np.mean(direct >= 200)
    assert table["mean_objective"].is_monotonic_decreasing
    assert imread(run_dir / "robustness_heatmap.png").std() > 0.05
    assert "4 elites on 2 terrains" in capsys.readouterr().out


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_corrected_metrics_of_a_run_searched_on_several_terrains(tmp_path, dask_cluster, kind):
    """A run searched on terrains 0-2, corrected on 4 seeds: the seeds are the first 4 it did
    not search on (3-6, not 3 alone), and its corrected QD score, coverage and cells equal a hand
    recomputation: each elite flown on each seed, placed by its mean measures in the run's own
    cells (a CVT run's: the nearest of centroids.npy), the best of a cell counted less the
    task's QD offset."""
    run_dir = tmp_path / "run"
    flags = dict(iterations=2, n_emitters=1, batch_size=4, env_seed="0-2", log_every=2,
                 **({"archive": "cvt", "cells": 16} if kind == "cvt" else {}))
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(run_dir))
    commands.evaluate(str(run_dir), corrected=True, repeats=4,
                        scheduler_address=dask_cluster.scheduler_address)

    summary = json.loads((run_dir / "corrected.json").read_text())
    assert summary["env_seeds"] == [3, 4, 5, 6] and summary["repeats"] == 4
    archive, task = saved_archive(run_dir), tasks.ENVIRONMENTS[LANDER]
    env, best = tasks.make_env(fast=False, env_name=LANDER), {}
    low, high = np.array(archive.lower_bounds), np.array(archive.upper_bounds)
    for solution in archive.data()["solution"]:
        flights = [policies.rollout(solution, seed, env, env_name=LANDER) for seed in range(3, 7)]
        mean = np.array(flights).mean(axis=0)
        if kind == "cvt":
            cell = int(np.argmin(np.linalg.norm(np.load(run_dir / "centroids.npy") - mean[1:], axis=1)))
        else:
            place = np.clip(np.floor((mean[1:] - low) / (high - low) * archive.dims).astype(int), 0, 49)
            cell = int(place[0] * 50 + place[1])
        best[cell] = max(best.get(cell, -np.inf), mean[0])
    assert summary["num_elites"] == len(best) > 1
    assert summary["qd_score"] == pytest.approx(sum(v - task.qd_offset for v in best.values()), rel=1e-12)
    assert summary["coverage"] == pytest.approx(len(best) / (16 if kind == "cvt" else 2500), rel=1e-12)
    assert summary["best_objective"] == pytest.approx(max(best.values()), rel=1e-12)
    assert summary["run"]["qd_score"] == json.loads((run_dir / "metrics.json").read_text())[-1]["qd_score"]


def test_corrected_archive_equals_a_hand_recomputation(run_dir, archive, dask_cluster):
    before = folder_state(run_dir)
    commands.evaluate(str(run_dir), corrected=True, repeats=2,
                        scheduler_address=dask_cluster.scheduler_address)

    summary = json.loads((run_dir / "corrected.json").read_text())
    seeds = [0, 1]  # the first two the run (terrain 52) did not search on
    assert summary["env_seeds"] == seeds and summary["repeats"] == 2
    # By hand: each elite flown on both seeds, placed by its mean measures; the best of a cell
    # counts, less the task's QD offset.
    env, data = tasks.make_env(fast=False, env_name=LANDER), archive.data()
    best: dict[int, float] = {}
    for solution in data["solution"]:
        flights = np.array([policies.rollout(solution, seed, env, env_name=LANDER) for seed in seeds])
        objective, measures = flights.mean(axis=0)[0], flights.mean(axis=0)[1:]
        # the grid cell, clipped to the edges as pyribs does for measures out of its ranges
        scaled = (measures - archive.lower_bounds) / (archive.upper_bounds - archive.lower_bounds)
        column, row = np.clip(np.floor(scaled * archive.dims).astype(int), 0, archive.dims - 1)
        cell = int(column * archive.dims[1] + row)
        best[cell] = max(best.get(cell, -np.inf), objective)
    assert summary["elites_flown"] == len(data["solution"])
    assert summary["num_elites"] == len(best)
    assert summary["qd_score"] == pytest.approx(sum(v - tasks.ENVIRONMENTS[LANDER].qd_offset
                                                    for v in best.values()), rel=1e-12)
    assert summary["coverage"] == pytest.approx(len(best) / archive.cells)
    assert summary["run"]["qd_score"] == pytest.approx(float(archive.stats.qd_score))
    corrected = saved_archive(run_dir, "corrected_archive")
    assert sorted(corrected.data()["index"].tolist()) == sorted(best)
    assert read_csv(run_dir / "corrected_archive.csv")["objective"].max() == pytest.approx(max(best.values()))
    assert imread(run_dir / "corrected_heatmap.png").std() > 0.05
    after = folder_state(run_dir)  # the run's own files are as they were; four files are new
    assert {name: after[name] for name in before} == before
    assert set(after) - set(before) == set(evaluation.CORRECTED_FILES) - {"corrected_archive.pkl"}


@pytest.mark.parametrize("value, seeds", [
    ("0-3", [0, 1, 2, 3]), ((3, 5), [3, 5]), (7, [7]), ("0-2,5", [0, 1, 2, 5]), ("4,4", [4])])
def test_env_seed_ranges(value, seeds):
    assert seed_list("env_seeds", value) == seeds


@pytest.mark.parametrize("value", ["3-1", "a", -1, True, "1-", ""])
def test_bad_env_seeds(value):
    with pytest.raises(UsageError, match="--env_seeds"):
        seed_list("env_seeds", value)


@pytest.mark.parametrize("args, fragments", [
    (["video", "{run}", "--cells", "[(2.0, -0.1)]"], ["outside the archive", "[-1, 1]", "[-3, 0]"]),
    (["trajectories", "{run}", "--cells", "[(0.1, -0.1"], ["--cells", "[(0.1, -0.1"]),
    (["elites", "{missing}"], ["no such run folder"]),
])
def test_bad_input_is_one_line_and_touches_nothing(run_cli, run_dir, tmp_path, args, fragments):
    names = {"run": run_dir, "missing": tmp_path / "missing"}
    before = folder_state(run_dir)
    assert_one_line_error(run_cli(*[arg.format(**names) for arg in args]), *fragments)
    assert folder_state(run_dir) == before


@pytest.mark.parametrize("command, kwargs, fragment", [
    (commands.video, dict(cells="[(a, b)]"), "--cells"),
    (commands.video, dict(cells=[(0.1, -0.1, 3)]), "--cells"),
    (commands.video, dict(cells=[(0.0, -3.5)]), "outside the archive"),
    (commands.video, {}, "--cells, --best, --top or --index"),
    (commands.video, dict(index=2500), "--index"),
    (commands.trajectories, dict(top=0), "--top"),
    (commands.trajectories, dict(best="maybe"), "--best"),
    (commands.elites, dict(top=-2), "--top"),
    (commands.elites, dict(min_objective="high"), "--min_objective"),
    (commands.evaluate, dict(env_seeds="5-2"), "--env_seeds"),
    (commands.evaluate, dict(workers=0), "--workers"),
    (commands.evaluate, dict(corrected=True, repeats=2, env_seeds="1-2"), "not both"),
    (commands.evaluate, dict(corrected=True, repeats=0), "--repeats"),
    (commands.evaluate, dict(corrected=True, top=3), "--top"),
    (commands.evaluate, dict(repeats=3), "--repeats is for --corrected"),
    (commands.evaluate, dict(corrected="perhaps"), "--corrected"),
])
def test_bad_flag_values_are_refused_before_writing(run_dir, command, kwargs, fragment):
    before = folder_state(run_dir)
    with pytest.raises(UsageError, match=re.escape(fragment)):
        command(str(run_dir), **kwargs)
    assert folder_state(run_dir) == before


def test_commands_and_their_flags_are_registered(tmp_path):
    assert {"video", "elites", "trajectories", "evaluate", "explore"} <= set(ll.COMMANDS)
    assert ll.command("evaluate") is commands.evaluate
    with pytest.raises(UsageError, match="--cell;"):
        ll.reject_unknown_flags(ll.command("video"), ["--cell", "[(0, 0)]"])
    (tmp_path / "run").mkdir()
    with pytest.raises(UsageError, match="archive.npz: no such file"):
        results.load_run(tmp_path / "run")
