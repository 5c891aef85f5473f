"""Guards against small bugs the rest of the suite let through: the hardcore walker flies its own
course (with obstacles), the continuous lander's side flame is drawn where Gymnasium blows the
exhaust, --scheduler_timeout is obeyed by every command that joins a cluster (and bounds the wait
for a scheduler file still being written), a multi-terrain run's results are shown on its first
terrain by default, and an experiment's run named `.`, `..` or `...` is refused."""

import base64
import json
import math
import shutil
import time
from pathlib import Path

import Box2D
import numpy as np
import pandas as pd
import pytest

from qdsearch import tasks
from qdsearch.analysis import results
from qdsearch.cli import commands
from qdsearch.tasks import policies, walker
from util import assert_one_line_error, folder_state, page_data, tiny_flags

HARDCORE, WALKER = "BipedalWalkerHardcore-v3", "BipedalWalker-v3"
CONTINUOUS = "LunarLanderContinuous-v3"


# ---- the hardcore walker's course ----------------------------------------------------------

def obstacles(env) -> int:
    """The course's stumps, pit walls and stair steps: Gymnasium makes them polygon bodies; the
    ground itself is a chain of edges."""
    return sum(isinstance(fixture.shape, Box2D.b2PolygonShape)
               for body in env.unwrapped.terrain for fixture in body.fixtures)


def test_the_hardcore_walker_flies_a_course_with_obstacles_the_plain_one_lacks():
    """Each row's own env, after episodes of its own episode function: the hardcore course has
    obstacles, the plain one none; on the same env seed the same policies walk differently there,
    and the explorer draws another ground, with the obstacles."""
    solutions = np.random.default_rng(3).normal(size=(3, tasks.ENVIRONMENTS[HARDCORE].solution_dim)) * 0.5
    walks, counts = {}, {}
    for name in (HARDCORE, WALKER):
        env = tasks.make_env(env_name=name)
        walks[name] = []
        for solution in solutions:
            path: list = []
            walk = policies.fly(solution, 52, env, path, env_name=name)
            walks[name].append((walk.reward, walk.steps, path))
        counts[name] = obstacles(env)
    assert counts[WALKER] == 0 and counts[HARDCORE] >= 3, counts
    assert all(hard != plain for hard, plain in zip(walks[HARDCORE], walks[WALKER]))
    courses = {name: walker.course(52, tasks.ENVIRONMENTS[name]) for name in (HARDCORE, WALKER)}
    assert courses[HARDCORE][0] != courses[WALKER][0]  # the ground
    assert len(courses[HARDCORE][1]) == counts[HARDCORE] and courses[WALKER][1] == []  # obstacles
    # the explorer draws the obstacles the walker meets, where they stand
    drawn = [static["points"] for static in walker.scene(52, tasks.ENVIRONMENTS[HARDCORE])["statics"]]
    assert drawn == courses[HARDCORE][0] + courses[HARDCORE][1]


# ---- the continuous lander's side engines, in the episode and on the page --------------------

@pytest.fixture(scope="module")
def continuous_explored(tmp_path_factory, dask_cluster) -> Path:
    """A tiny run of the continuous lander and its explorer page."""
    run_dir = tmp_path_factory.mktemp("continuous") / "run"
    commands.search(**tiny_flags(dask_cluster, env=CONTINUOUS), outdir=str(run_dir))
    commands.explore(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    return run_dir


def body_x(lander, x: float, y: float) -> float:
    """The x of a world point in the lander's own frame (> 0: its right side, upright)."""
    dx, dy = x - lander.position.x, y - lander.position.y
    return dx * math.cos(lander.angle) + dy * math.sin(lander.angle)


def exhaust_sides(solution: np.ndarray) -> list[tuple[float, float]]:
    """Per step of the episode (rendered, so Gymnasium makes its exhaust particles): the action's
    side throttle, and on which side of the lander that step's side exhaust is (0: none)."""
    env = tasks.make_env(False, "rgb_array", env_name=CONTINUOUS)
    steps: list[tuple[float, float]] = []

    def on_step(action, obs):
        lander = env.unwrapped.lander
        side = 0.0
        if abs(action[1]) > 0.5:  # the side particle is made last in the step
            particle = env.unwrapped.particles[-1].position
            side = float(np.sign(body_x(lander, particle.x, particle.y)))
        steps.append((float(action[1]), side))
    policies.fly(solution, 52, env, on_step=on_step, env_name=CONTINUOUS)
    env.close()
    return steps


FLAME_PIXELS = """() => {  // flame-coloured pixels beside the lander, left and right in its own frame
  const [x, y, angle] = pose(current, step), W = flight.width, H = flight.height;
  const image = fg.getImageData(0, 0, W, H).data, counts = [0, 0];
  for (let py = 0; py < H; py++) for (let px = 0; px < W; px++) {
    const i = 4 * (py * W + px), [r, g, b] = [image[i], image[i + 1], image[i + 2]];
    if (!(r > 180 && g > 50 && g < 180 && b < 90)) continue;  // #ff9a1f, #ff5a00 and their edges
    const dx = (px + 0.5) / PX - x, dy = (H - py - 0.5) / PX - y;
    const bx = dx * Math.cos(angle) + dy * Math.sin(angle), by = dy * Math.cos(angle) - dx * Math.sin(angle);
    if (by < -0.1 || Math.hypot(bx, by) > 1.5) continue;  // the main engine's flame is below
    if (bx > 0.3) counts[1]++; else if (bx < -0.3) counts[0]++;
  }
  return counts;
}"""


def test_the_continuous_landers_side_flame_is_drawn_where_gymnasium_blows_the_exhaust(
        continuous_explored, browser):
    """Gymnasium: action[1] < -0.5 fires the left engine, whose exhaust leaves the lander's right
    side (pushing it left), > 0.5 the right one. The recorded poses say which engine fired, and
    the page draws the flame on the exhaust's side, not the mirror image."""
    data = page_data(continuous_explored)
    scale = np.array(data["pose_scale"])
    poses = np.frombuffer(base64.b64decode(data["poses"]), "<i2").reshape(-1, len(scale)) / scale

    def sides(elite):
        return poses[elite["offset"] + 1:elite["offset"] + 1 + elite["steps"], 6]
    elite = max(data["elites"], key=lambda e: min((sides(e) < 0).sum(), (sides(e) > 0).sum()))
    assert (sides(elite) < 0).any() and (sides(elite) > 0).any()  # both engines fire in it
    archive, _ = results.load_run(continuous_explored)
    solution = dict(zip(*archive.data(["index", "solution"]).values()))[elite["index"]]

    flown = exhaust_sides(solution)
    throttles, exhaust = np.array(flown).T
    assert len(flown) == elite["steps"]
    assert (exhaust[throttles < -0.5] == 1).all() and (exhaust[throttles > 0.5] == -1).all()
    assert (exhaust[np.abs(throttles) <= 0.5] == 0).all()
    # the pose's side power: negative (the left engine) exactly when the exhaust is on the right
    assert ((sides(elite) < 0) == (exhaust == 1)).all() and ((sides(elite) > 0) == (exhaust == -1)).all()

    page = browser.new_page(viewport={"width": 1300, "height": 1000})
    errors: list = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto((continuous_explored / "explorer.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    page.evaluate(f"watch(DATA.elites.find(e => e.index === {elite['index']})); play(false)")
    for side in (1, -1):  # the exhaust on the lander's right, then on its left
        counts = []
        for step in 1 + np.flatnonzero(exhaust == side)[:10]:
            page.evaluate(f"show({step})")
            counts.append(page.evaluate(FLAME_PIXELS))
        left, right = np.array(counts).T
        drawn, mirrored = (right, left) if side == 1 else (left, right)
        assert drawn.min() > 0 and mirrored.max() == 0, (side, counts)  # at each of those steps
    assert errors == []
    page.close()


# ---- --scheduler_timeout ---------------------------------------------------------------------

def test_a_scheduler_file_that_never_appears_fails_after_the_timeout_asked(run_cli, tiny_run, tmp_path):
    """--scheduler_timeout 0.5, not the default 120 s: every command that joins a cluster gives
    up within seconds, in one line, and writes nothing."""
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    before = folder_state(run_dir)
    never = tmp_path / "never.json"
    for command in (["--outdir", tmp_path / "out"], ["experiment", "--outdir", tmp_path / "out"],
                    ["resume", run_dir, "--iterations", "4"], ["explore", run_dir],
                    ["evaluate", run_dir, "--env_seeds", "3"]):
        start = time.monotonic()
        result = run_cli(*command, "--scheduler_file", never, "--scheduler_timeout", "0.5")
        elapsed = time.monotonic() - start
        assert elapsed < 10, (command, elapsed)  # a fixed 120 s wait would be far longer
        assert_one_line_error(result, "never.json: no scheduler file appeared in 0.5 s")
    assert not (tmp_path / "out").exists() and folder_state(run_dir) == before


def test_a_scheduler_file_being_written_is_read_once_finished_and_a_garbled_one_within_the_timeout(
        tmp_path, monkeypatch):
    """A scheduler file found half-written is read again for a moment (as a scheduler may be
    writing it); one that stays garbled is refused after that moment (here 0.4 s), or the timeout
    if shorter."""
    import threading

    from qdsearch.base.flags import UsageError
    from qdsearch.search import cluster
    from qdsearch.search.cluster import read_scheduler_file

    monkeypatch.setattr(cluster, "UNFINISHED_FILE_WAIT", 0.4)

    path = tmp_path / "scheduler.json"
    path.write_text('{"type": "Sched')
    finish = threading.Timer(0.2, path.write_text, [json.dumps({"address": "tcp://127.0.0.1:8786"})])
    finish.start()
    try:
        assert read_scheduler_file(path, timeout=60) == "tcp://127.0.0.1:8786"
    finally:
        finish.join()
    path.write_text("{not json")
    for timeout, waits in ((0.1, 0.1), (60, 0.4)):
        start = time.monotonic()
        with pytest.raises(UsageError, match="not a Dask scheduler file"):
            read_scheduler_file(path, timeout=timeout)
        assert waits <= time.monotonic() - start < waits + 1.0


# ---- a multi-terrain run's results -----------------------------------------------------------

TERRAINS = [3, 52]  # a run on two terrains: results show the first unless told


@pytest.fixture(scope="module")
def two_terrain_run(tmp_path_factory, dask_cluster) -> Path:
    run_dir = tmp_path_factory.mktemp("terrains") / "run"
    commands.search(**tiny_flags(dask_cluster, iterations=2, log_every=2, env_seed="3,52"),
                    outdir=str(run_dir))
    assert json.loads((run_dir / "config.json").read_text())["env_seed"] == TERRAINS
    return run_dir


def test_results_show_a_multi_terrain_run_on_its_first_terrain(two_terrain_run, run_cli, dask_cluster):
    """video, trajectories and explore fly the elites on terrain 3 (the first) by default, and on
    52 when asked."""
    run = two_terrain_run
    cluster = ["--scheduler_address", dask_cluster.scheduler_address]
    pictures = {}
    for terrain in (None, *TERRAINS):
        chosen = [] if terrain is None else ["--env_seed", terrain]
        for command in (["video", run, "--best"], ["trajectories", run, "--top", "3"],
                        ["explore", run, *cluster]):
            result = run_cli(*command, *chosen)
            assert result.returncode == 0, result.stderr
        shown = TERRAINS[0] if terrain is None else terrain
        assert pd.read_csv(run / "videos" / "index.csv")["env_seed"].tolist() == [shown]
        assert page_data(run)["env_seed"] == shown
        pictures[terrain] = (run / "trajectories.png").read_bytes()
    assert pictures[None] == pictures[3] != pictures[52]  # paths and ground of terrain 3


# ---- an experiment's run names ---------------------------------------------------------------

@pytest.fixture(scope="module")
def one_run_experiment(tmp_path_factory, dask_cluster) -> Path:
    folder = tmp_path_factory.mktemp("guards") / "exp"
    commands.experiment(algorithms="cma_me", seeds="1", iterations=2, n_emitters=2, batch_size=6,
                           log_every=2, outdir=str(folder), scheduler_address=dask_cluster.scheduler_address)
    return folder


@pytest.mark.parametrize("name", [".", "..", "..."])
def test_a_run_named_with_dots_only_is_refused(one_run_experiment, run_cli, tmp_path, dask_cluster, name):
    """`.` would put the run's folder on the experiment itself and `..` on its parent (`...` is
    dots only too): resume refuses the plan in one line and writes nothing, inside the experiment
    or beside it."""
    parent = tmp_path / "parent"
    folder = parent / "exp"
    shutil.copytree(one_run_experiment, folder)
    plan = json.loads((folder / "experiment.json").read_text())
    plan["runs"][0].update(name=name, state="stopped")  # unfinished: resume would fly it there
    (folder / "experiment.json").write_text(json.dumps(plan))
    before = folder_state(parent)
    result = run_cli("resume", folder, "--iterations", "3",
                     "--scheduler_address", dask_cluster.scheduler_address)
    assert_one_line_error(result, "experiment.json: run 0 is not a run of this experiment's plan")
    assert folder_state(parent) == before and sorted(p.name for p in parent.iterdir()) == ["exp"]
