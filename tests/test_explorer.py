"""The explorer page: the poses it packs are the rollouts' flights, and a real headless Chromium
loads it from file:// without errors, shows a cell's numbers on hover, plays a landing on click
(the lander drawn where the poses put it) and plays a table row."""

import base64
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest

from qdsearch import tasks
from qdsearch.base import run_files
from qdsearch.cli import commands
from qdsearch.store import archive_data
from qdsearch.tasks import fast_lander, lander, policies
from util import DATA_BLOCK, LANDER, folder_state, page_data, saved_archive, small_disk

LANDER_FILL = [128, 102, 230]  # the page's lander colour, #8066e6


@pytest.fixture(scope="module")
def explored(tmp_path_factory, dask_cluster, tiny_run):
    """A copy of the tiny run (a few dozen elites) and its explorer page."""
    run_dir = tmp_path_factory.mktemp("explorer") / "run"
    shutil.copytree(tiny_run, run_dir)
    commands.explore(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    return run_dir





def test_the_page_is_one_file_with_every_elite_and_its_flight(explored):
    html = (explored / "explorer.html").read_text()
    page = html.split(DATA_BLOCK)[0]
    assert "<script src" not in html and "http://" not in page and "https://" not in page  # nothing fetched
    assert "default-src 'none'; script-src 'sha256-" in page  # and nothing but its own script runs
    data = page_data(explored)
    archive = saved_archive(explored)
    assert len(data["elites"]) == len(archive)
    scale = np.array(lander.LANDER.pose_scale)
    poses = np.frombuffer(base64.b64decode(data["poses"]), dtype="<i2").reshape(-1, len(scale))
    assert len(poses) == sum(e["steps"] + 1 for e in data["elites"])
    solutions = dict(zip(archive.data("index"), archive.data("solution")))
    env = tasks.make_env(fast=False, env_name=LANDER)
    for elite in data["elites"][:5]:
        trajectory = []
        objective, *measures = policies.rollout(solutions[elite["index"]], 52, env, trajectory=trajectory,
                                               env_name=LANDER)
        assert elite["objective"] == objective and elite["measures"] == measures
        assert elite["steps"] == len(trajectory)
        flown = poses[elite["offset"] + 1:elite["offset"] + 1 + elite["steps"]] / scale
        # the observation's x and y, from the body's pose
        x = (flown[:, 0] - fast_lander.HALF_W) / fast_lander.HALF_W
        y = (flown[:, 1] - fast_lander.PAD_Y) / fast_lander.HALF_H
        assert np.abs(x - np.array(trajectory)[:, 0]).max() < 1e-4  # 1 mm of quantisation
        assert np.abs(y - np.array(trajectory)[:, 1]).max() < 1e-4


@pytest.mark.parametrize("case", ["no archive", "empty archive", "read-only folder"])
def test_bad_folders_are_refused_and_untouched(explored, tmp_path, run_cli, case):
    from ribs.archives import GridArchive

    run_dir = tmp_path / "run"
    if case == "no archive":
        run_dir.mkdir()
        (run_dir / "notes.txt").write_text("mine")
        words = "archive.npz: no such file"
    elif case == "empty archive":
        shutil.copytree(explored, run_dir)
        empty = GridArchive(solution_dim=32, dims=(50, 50), ranges=[(-1, 1), (-3, 0)])
        archive_data.write_archive_data(run_dir / "archive.npz", empty,
                                        run_files.read_run_json(run_dir, "config.json"))
        words = "empty"
    else:
        with small_disk(tmp_path, "8m") as disk:
            run_dir = disk / "run"
            shutil.copytree(explored, run_dir)
            (run_dir / "explorer.html").unlink()
            subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
            result = run_cli("explore", run_dir)
            assert result.returncode == 2 and "cannot write" in result.stderr
            assert not (run_dir / "explorer.html").exists()
        return
    before = folder_state(run_dir)
    result = run_cli("explore", run_dir)
    assert result.returncode == 2 and words in result.stderr and result.stderr.count("\n") == 1
    assert folder_state(run_dir) == before


@pytest.fixture
def page(browser, explored):
    page = browser.new_page(viewport={"width": 1300, "height": 1000})
    errors = []
    page.on("console", lambda message: message.type == "error" and errors.append(message.text))
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto((explored / "explorer.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    page.errors = errors
    yield page
    page.close()


def cell_centre(page, elite_index: int) -> tuple[float, float]:
    box = page.locator("#heatmap").bounding_box()
    gx, row, size, pad = page.evaluate(f"""(() => {{
        const e = DATA.elites.find(e => e.index === {elite_index});
        return [e.gx, cellRow(e.gy), CELL, PAD]; }})()""")
    return box["x"] + pad + (gx + 0.5) * size, box["y"] + (row + 0.5) * size


def best_elite(explored) -> dict:
    return max(page_data(explored)["elites"], key=lambda e: e["objective"])


def test_loads_without_errors_and_hover_shows_the_cells_numbers(page, explored):
    assert page.errors == []
    elite = best_elite(explored)
    page.mouse.move(*cell_centre(page, elite["index"]))
    tip = page.inner_text("#tip")
    assert f"cell {elite['index']}" in tip and f"objective {elite['objective']:.2f}" in tip
    assert f"impact_x {elite['measures'][0]:.3f}" in tip


def canvas_pixels(page) -> str:
    return page.evaluate("document.getElementById('flight').toDataURL()")


def test_a_click_plays_the_landing_where_the_poses_put_the_lander(page, explored):
    elite = best_elite(explored)
    page.mouse.click(*cell_centre(page, elite["index"]))
    first = canvas_pixels(page)
    page.wait_for_function(f"() => step >= {min(20, elite['steps'])}")  # 20 steps at 50 per second
    assert canvas_pixels(page) != first  # it moves
    if page.evaluate("playing"):  # (a loaded machine may have played it to its end already)
        page.click("#play")  # pause
    step = page.evaluate("step")
    assert 0 < step <= elite["steps"]
    x, y = page.evaluate("(() => { const p = pose(current, step); return [toX(p[0]), toY(p[1])]; })()")
    pixel = page.evaluate(f"Array.from(fg.getImageData({round(x)}, {round(y)}, 1, 1).data)")
    assert pixel[:3] == LANDER_FILL  # the lander's body at the recorded pose
    assert f"cell {elite['index']}" in page.inner_text("#info")
    assert page.errors == []


def test_the_table_sorts_and_a_row_plays_its_elite(page, explored):
    rows = page.locator("#elites tbody tr")
    objectives = [float(rows.nth(i).locator("td").nth(1).inner_text()) for i in range(rows.count())]
    assert objectives == sorted(objectives, reverse=True)
    page.click("#elites th:nth-child(1)")  # sort by cell
    cells = [int(rows.nth(i).locator("td").nth(0).inner_text()) for i in range(rows.count())]
    assert cells == sorted(cells, reverse=True)
    rows.nth(2).click()
    assert page.evaluate("current.index") == cells[2]
    assert f"cell {cells[2]}" in page.inner_text("#info")
    assert "playing" in rows.nth(2).get_attribute("class")


def test_after_evaluate_hover_shows_other_terrains_and_the_switch_recolours(
        browser, explored, tmp_path, dask_cluster):
    run_dir = tmp_path / "run"
    shutil.copytree(explored, run_dir)
    commands.evaluate(str(run_dir), env_seeds="3,4",
                                scheduler_address=dask_cluster.scheduler_address)
    commands.explore(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    robust = {int(r["cell_index"]): r for r in pd.read_csv(run_dir / "robustness.csv").to_dict("records")}

    page = browser.new_page(viewport={"width": 1300, "height": 1000})
    page.goto((run_dir / "explorer.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    elite = best_elite(run_dir)
    page.mouse.move(*cell_centre(page, elite["index"]))
    row = robust[elite["index"]]
    assert (f"other terrains: mean {row['mean_objective']:.2f}, solved {100 * row['solved_share']:.0f}%"
            in page.inner_text("#tip"))
    before = page.evaluate("document.getElementById('heatmap').toDataURL()")
    page.check("input[value=robust]")
    assert page.evaluate("document.getElementById('heatmap').toDataURL()") != before
    page.close()


@pytest.fixture(scope="module")
def explored_points(tmp_path_factory):
    """An arm run and a sphere run, each explored: a point has no episode, so no cluster."""
    from util import tiny_flags

    folders = {}
    for env, dim in (("arm", 7), ("sphere", 10)):
        run_dir = tmp_path_factory.mktemp("points") / env
        commands.search(**tiny_flags(env=env, dim=dim, iterations=8, sigma0=1.0), outdir=str(run_dir))
        commands.explore(str(run_dir))
        folders[env] = run_dir
    return folders


def point_page(browser, run_dir):
    page = browser.new_page(viewport={"width": 1300, "height": 1000})
    page.errors = []
    page.on("pageerror", lambda error: page.errors.append(str(error)))
    page.on("console", lambda message: message.type == "error" and page.errors.append(message.text))
    page.goto((run_dir / "explorer.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    return page


def solution_of(run_dir, index: int) -> np.ndarray:
    archive = saved_archive(run_dir)
    return dict(zip(archive.data("index"), archive.data("solution")))[index]


def pixel_at(page, x: float, y: float) -> list[int]:
    return page.evaluate(f"Array.from(fg.getImageData({round(x)}, {round(y)}, 1, 1).data)")[:3]


@pytest.mark.parametrize("env", ["arm", "sphere"])
def test_a_function_page_holds_each_elites_point_and_no_episode(explored_points, env):
    run_dir = explored_points[env]
    data, archive = page_data(run_dir), saved_archive(run_dir)
    assert data["poses"] == "" and data["point"]["dim"] == archive.solution_dim
    assert data["point"]["kind"] == ("arm" if env == "arm" else "bars")
    packed = np.frombuffer(base64.b64decode(data["point"]["values"]), dtype="<f4")
    points = packed.reshape(-1, archive.solution_dim)
    assert len(points) == len(data["elites"]) == len(archive) > 5
    for elite in data["elites"]:
        assert elite["steps"] == 0
        expected = solution_of(run_dir, elite["index"]).astype("<f4")
        np.testing.assert_array_equal(points[elite["offset"]], expected)


def test_a_click_draws_the_arm_with_its_hand_where_the_angles_put_it(browser, explored_points):
    """The hand's place computed here from the elite's angles (a link of 1 per joint, each turning
    by its angle from the last): the page's hand colour is there."""
    run_dir = explored_points["arm"]
    page = point_page(browser, run_dir)
    elite = best_elite(run_dir)
    page.mouse.click(*cell_centre(page, elite["index"]))
    angles = np.cumsum(solution_of(run_dir, elite["index"]))
    hand = page.evaluate(f"armXY({np.cos(angles).sum()}, {np.sin(angles).sum()})")
    assert pixel_at(page, *hand) == [214, 39, 40]  # the hand, #d62728
    info = page.inner_text("#info")
    assert f"cell {elite['index']}" in info and "joint angles: 7 values" in info
    headers = page.locator("#elites th").all_inner_texts()
    assert not any(header.startswith("steps") for header in headers) and page.errors == []
    assert not page.locator("#play").is_visible()  # nothing to play
    page.close()


def test_a_click_draws_the_spheres_point_as_bars_of_its_halves(browser, explored_points):
    run_dir = explored_points["sphere"]
    page = point_page(browser, run_dir)
    elite = best_elite(run_dir)
    page.locator("#elites tbody tr").nth(0).click()  # the best
    point = solution_of(run_dir, elite["index"])
    top = max(5.12, float(np.abs(point).max()))
    for i in (0, 4, 5, 9):  # each half's first and last coordinate: its colour halfway up its bar
        x, y = page.evaluate(f"barXY({i}, {point[i] / 2}, {top})")
        assert pixel_at(page, x, y) == ([31, 119, 180] if i < 5 else [255, 127, 14])  # blue, orange
    assert page.evaluate("current.index") == elite["index"] and page.errors == []
    page.close()


def test_a_narrow_curve_keeps_its_ends_apart(browser, explored_points):
    """A function's best objective climbs from below 100 to 100: its axis reads two numbers, not
    "100" twice."""
    page = point_page(browser, explored_points["sphere"])
    curve = [row["best_objective"] for row in page_data(explored_points["sphere"])["metrics"]]
    assert max(curve) - min(curve) < 10
    labels = page.evaluate("""(() => {
        const seen = [], g = document.getElementById('curves').getContext('2d'), text = g.fillText.bind(g);
        g.fillText = (t, ...rest) => { seen.push(String(t)); text(t, ...rest); };
        drawCurves(); return seen; })()""")
    assert f"{max(curve):.2f}" in labels and f"{min(curve):.2f}" in labels
    page.close()
