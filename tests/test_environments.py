"""Every Gymnasium row of ENVIRONMENTS (the benchmark functions: tests/test_functions.py): its
policy fits its task, an episode is the same wherever it is flown, its measures are what a
hand-made trace says, its runs are as exact as Lunar Lander's (1 worker = 2, resume = straight, an
experiment's run = its lone twin), every command works on it, and bad input about tasks is one
line."""

import base64
import json
import shutil

import gymnasium as gym
import imageio_ffmpeg
import numpy as np
import pandas as pd
import pytest

from qdsearch import tasks
from qdsearch.analysis import results
from qdsearch.cli import commands
from qdsearch.search import engine
from qdsearch.tasks import family, lander, policies, walker
from util import (
    assert_one_line_error,
    assert_same_run,
    folder_state,
    page_data,
    run_archive,
    tiny_env,
    tiny_episode,
    tiny_flags,
)

RNG = np.random.default_rng(20)
EPISODE_ROWS = [name for name, task in tasks.ENVIRONMENTS.items() if not task.function]  # (functions: points)
OTHER_ROWS = [name for name in EPISODE_ROWS if name != tasks.DEFAULT_ENV]
WALKER = "BipedalWalker-v3"
# The rows whose videos are made: each of Box2D's scenes, and one of MuJoCo's robots (they share
# one renderer, which draws in software, on every core, where there is no GPU: the suite's costliest
# frames).
VIDEO_ROWS = ["LunarLanderContinuous-v3", WALKER, "BipedalWalkerHardcore-v3", "HalfCheetah-v5"]
# What a user reads of a task's seed and of its solved score: its own family's words (MuJoCo has no
# terrain, and a robot does not land).
FAMILY_WORDS = {"lander": ("terrain", "good landings"), "walker": ("terrain", "walks to the far end")}
ROBOT_WORDS = ("reset seed", "gaits at the reward threshold")


def words_of(env_name: str) -> tuple[str, str]:
    return FAMILY_WORDS.get(tasks.ENVIRONMENTS[env_name].family.name, ROBOT_WORDS)


def random_solutions(env_name: str, count: int = 4) -> np.ndarray:
    return RNG.normal(size=(count, tasks.ENVIRONMENTS[env_name].solution_dim)) * 0.5


@pytest.mark.parametrize("env_name", EPISODE_ROWS)
def test_an_episode_is_the_same_wherever_it_is_flown(env_name, dask_client):
    """A fresh env, a reused one (another order), a rendering one and a Dask worker agree."""
    tasks.check_spaces(env_name)
    task, solutions = tasks.ENVIRONMENTS[env_name], random_solutions(env_name)
    fresh = [policies.rollout(s, 3, tasks.make_env(env_name=env_name), env_name=env_name) for s in solutions]
    env = tasks.make_env(env_name=env_name)
    reused = [policies.rollout(s, 3, env, env_name=env_name) for s in solutions[::-1]][::-1]
    rendering = tasks.make_env(False, "rgb_array", env_name=env_name)
    rendering.reset(seed=0)
    rendering.render()  # a frame drawn before the episode changes nothing
    remote = dask_client.submit(engine.fly_chunk, engine.Chunk(solutions, np.full(len(solutions), 3),
                                                               task.measures, env_name), pure=False).result()
    assert fresh == reused
    assert policies.rollout(solutions[0], 3, rendering, env_name=env_name) == fresh[0]
    assert remote.tolist() == [list(row) for row in fresh]
    assert len({row[0] for row in fresh}) == len(fresh)  # the policies do differ


def test_walker_measures_match_a_hand_made_trace():
    for solution in random_solutions(WALKER, 3):
        env = gym.make(WALKER)  # a fresh one: a reused walker env drifts (walker.renew_world)
        obs, _ = env.reset(seed=5)
        start, done, trace = env.unwrapped.hull.position.x, False, []
        while not done:
            obs, reward, terminated, truncated, _ = env.step(np.tanh(solution.reshape(4, 24) @ obs))
            trace.append((obs, reward))
            done = terminated or truncated
        names = tasks.family_measures(walker.WALKER)
        result = policies.rollout(solution, 5, tasks.make_env(env_name=WALKER), names, env_name=WALKER)
        steps = len(trace)
        expected = {
            "foot1_contact": sum(o[8] == 1 for o, _ in trace) / steps,
            "foot2_contact": sum(o[13] == 1 for o, _ in trace) / steps,
            "distance": env.unwrapped.hull.position.x - start,
            "speed": (env.unwrapped.hull.position.x - start) / (steps / 50),
            "hull_angle": sum(float(o[0]) for o, _ in trace) / steps,
        }
        assert result[0] == sum(r for _, r in trace)
        assert dict(zip(names, result[1:])) == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_the_continuous_landers_fuel_weighs_each_firing_by_its_power():
    env, name = gym.make("LunarLander-v3", continuous=True), "LunarLanderContinuous-v3"
    for solution in random_solutions(name, 3):  # (a reused lander env flies the same episodes)
        obs, _ = env.reset(seed=9)
        done, fuel, steps = False, 0.0, 0
        while not done:
            main, side = np.tanh(solution.reshape(2, 8) @ obs)
            fuel += (np.clip(main, 0, 1) + 1) / 2 if main > 0 else 0.0  # the env's m_power
            fuel += 0.1 * np.clip(abs(side), 0.5, 1) if abs(side) > 0.5 else 0.0  # its s_power
            obs, _, terminated, truncated, _ = env.step(np.array([main, side]))
            done, steps = terminated or truncated, steps + 1
        result = policies.rollout(solution, 9, tasks.make_env(env_name=name), ("fuel",), env_name=name)
        assert result[1] == pytest.approx(fuel, rel=1e-12) and result[1] > 0


@pytest.fixture(scope="module")
def task_runs(tmp_path_factory, dask_cluster):
    """A tiny finished run of each row besides the default, on the shared cluster."""
    runs = {}
    for env_name in OTHER_ROWS:
        runs[env_name] = tmp_path_factory.mktemp("tasks") / env_name
        commands.search(**tiny_flags(dask_cluster, env=env_name), outdir=str(runs[env_name]))
    return runs


@pytest.mark.slow
@pytest.mark.parametrize("env_name", OTHER_ROWS)
def test_one_worker_and_a_resumed_run_equal_the_straight_run(env_name, task_runs, tmp_path,
                                                            dask_cluster, one_worker_cluster):
    straight = task_runs[env_name]
    config = json.loads((straight / "config.json").read_text())
    assert config["env"] == env_name and config["measures"] == list(tasks.ENVIRONMENTS[env_name].measures)
    archive = run_archive(straight)
    assert len(archive) > 0 and archive["solution_0"].notna().all()
    commands.search(**tiny_flags(one_worker_cluster, env=env_name), outdir=str(tmp_path / "one"))
    assert_same_run(tmp_path / "one", straight)
    commands.search(**tiny_flags(dask_cluster, env=env_name, iterations=1),
               outdir=str(tmp_path / "resumed"))
    commands.resume(str(tmp_path / "resumed"), iterations=3,
                       scheduler_address=dask_cluster.scheduler_address)
    assert_same_run(tmp_path / "resumed", straight)


def experiment_flags(search_flags: dict) -> dict:
    """A search's flags, as an experiment passes them to its runs (it sets seed and algorithm)."""
    return {k: v for k, v in search_flags.items() if k not in ("seed", "algorithm")}


@pytest.mark.slow
@pytest.mark.parametrize("env_name", OTHER_ROWS)
def test_an_experiments_run_equals_its_lone_twin(env_name, task_runs, tmp_path, dask_cluster):
    flags = experiment_flags(tiny_flags(dask_cluster, env=env_name))
    commands.experiment(algorithms="cma_me", seeds="7", outdir=str(tmp_path / "exp"), **flags)
    [entry] = json.loads((tmp_path / "exp" / "experiment.json").read_text())["runs"]
    assert_same_run(tmp_path / "exp" / entry["name"], task_runs[env_name])


@pytest.fixture(scope="module")
def walker_experiment(tmp_path_factory, dask_cluster):
    folder = tmp_path_factory.mktemp("walkers") / "experiment"
    flags = experiment_flags(tiny_flags(dask_cluster, env=WALKER, iterations=2))
    commands.experiment(algorithms=["cma_me", "cma_mae"], seeds="7-8", outdir=str(folder), **flags)
    return folder


@pytest.mark.slow
def test_a_walker_experiment_equals_its_lone_twins_and_compares(walker_experiment, tmp_path,
                                                               dask_cluster, run_cli):
    commands.search(**tiny_flags(dask_cluster, env=WALKER, iterations=2, seed=8),
               outdir=str(tmp_path / "twin"))
    name = "cma_me_seed8"  # its setting's label less what every setting shares
    assert_same_run(walker_experiment / name, tmp_path / "twin")
    result = run_cli("compare", str(walker_experiment), "--out", str(tmp_path / "walkers.png"))
    assert result.returncode == 0, result.stderr
    report = (tmp_path / "walkers.md").read_text()
    assert report.startswith("| setting | runs | qd_score |")
    assert "| cma_me | 2 |" in report
    assert "BipedalWalker-v3" in report and "returns at least 300" in report
    stats = pd.read_csv(tmp_path / "walkers_settings.csv")
    assert set(stats["setting"]) == {"cma_me", "cma_mae learning_rate=0.5"}
    assert stats["ci95_low"].notna().any()


@pytest.mark.slow
@pytest.mark.parametrize("env_name", VIDEO_ROWS)
def test_a_video_has_a_frame_per_step_and_its_elite_reflies_exactly(env_name, task_runs, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(task_runs[env_name], run_dir)
    commands.video(str(run_dir), best=True)
    index = pd.read_csv(run_dir / "videos" / "index.csv")
    assert index["reproduced"].tolist() == [True]
    solution = run_archive(run_dir).sort_values("objective").iloc[-1].filter(like="solution_").to_numpy()
    steps = policies.fly(solution, 52, tiny_env(env_name), env_name=env_name).steps
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(run_dir / "videos" / index["video"][0]))
    assert frames == steps + 1
    assert "warning" not in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.parametrize("env_name", OTHER_ROWS)
def test_elites_of_every_row_are_listed_and_reflown_exactly(env_name, task_runs, tmp_path, capsys):
    """What video checks of the elite it shows (flown again, it scores its stored objective and
    measures), without the rendering, for the rows VIDEO_ROWS leave out too; the last line counts
    the elites at the task's solved return in its own words."""
    run_dir = tmp_path / "run"
    shutil.copytree(task_runs[env_name], run_dir)
    commands.elites(str(run_dir), top=2)
    table = pd.read_csv(run_dir / "elites.csv")
    assert list(table.columns) == ["objective", *tasks.ENVIRONMENTS[env_name].measures, "cell_index"]
    archive, config = results.load_run(run_dir)
    task = tasks.ENVIRONMENTS[env_name]  # a robot's solved return is per step of its episode
    solved = task.solved * (config.episode_length if task.per_step else 1)
    good = int((archive.data("objective") >= solved).sum())
    assert capsys.readouterr().out.splitlines()[-1] == (
        f"{len(table)} of {len(archive)} elites ({good} score {solved:g} or more: {words_of(env_name)[1]}); "
        f"written to {run_dir / 'elites.csv'}")
    for elite in results.select_elites(archive, top=2, measures=config.measures):
        assert results.reflown(elite, config) == (elite["objective"], list(elite["measures"]))


@pytest.mark.slow
def test_walker_trajectories_are_its_hull_paths(task_runs, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(task_runs[WALKER], run_dir)
    commands.trajectories(str(run_dir), top=3)
    assert (run_dir / "trajectories.png").stat().st_size > 10_000
    chosen = results.select_elites(results.load_run(run_dir)[0], top=3,
                                   measures=list(tasks.TUTORIAL_MEASURES))
    env = tiny_env(WALKER)
    paths = results.fly_paths(chosen, 52, WALKER, episode=tiny_episode(WALKER))
    for elite, (path, end) in zip(chosen, paths):
        walk = policies.fly(elite["solution"], 52, env, env_name=WALKER)
        assert len(path) == walk.steps and end == walk.steps - 1
        assert path[-1, 0] - path[0, 0] == pytest.approx(walk.distance, abs=0.2)  # one step's move


def action_trace(solution: np.ndarray, env: gym.Env, env_name: str) -> list:
    actions: list = []
    policies.fly(solution, 52, env, on_step=lambda action, obs: actions.append(action), env_name=env_name)
    return actions


@pytest.mark.slow
@pytest.mark.parametrize("env_name", OTHER_ROWS)
def test_explore_draws_every_row(env_name, task_runs, tmp_path, dask_cluster, browser):
    run_dir = tmp_path / "run"
    shutil.copytree(task_runs[env_name], run_dir)
    commands.explore(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
    data, task = page_data(run_dir), tasks.ENVIRONMENTS[env_name]
    scale = np.array(data["pose_scale"])
    poses = np.frombuffer(base64.b64decode(data["poses"]), "<i2").reshape(-1, len(scale)) / scale
    assert data["pose_scale"] == list(task.family.pose_scale)
    assert len(poses) == sum(e["steps"] + 1 for e in data["elites"])
    solutions = dict(zip(*results.load_run(run_dir)[0].data(["index", "solution"]).values()))
    env = tiny_env(env_name)
    for elite in data["elites"][:3]:
        path: list = []
        policies.fly(solutions[elite["index"]], 52, env, path, env_name=env_name)
        actions = action_trace(solutions[elite["index"]], env, env_name)
        flown = poses[elite["offset"] + 1:elite["offset"] + 1 + elite["steps"]]
        if task.family is lander.LANDER:  # the throttles: the main engine's flame whenever it fires
            assert ((flown[:, 5] > 0) == np.array([a[0] > 0 for a in actions])).all()
        else:  # the walker's hull, a robot's torso: the path's points, to the centimetre
            assert np.abs(flown[:, :2] - np.array(path)).max() < 0.006
    page = browser.new_page(viewport={"width": 1300, "height": 1000})
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto((run_dir / "explorer.html").as_uri())
    page.wait_for_function("window.explorerReady > 0", timeout=20000)
    page.locator("#elites tbody tr").first.click()
    page.wait_for_function("() => step >= Math.min(3, current.steps)")  # its bodies drawn as it plays
    assert errors == [] and page.title() == f"{env_name} archive explorer"
    assert page.locator("#episode").text_content() == task.family.scene(52, task)["episode"]
    seed = f"{words_of(env_name)[0]} 52"  # HalfCheetah's page: "reset seed 52", not "terrain 52"
    assert page.locator("#subtitle").text_content() == (f"{run_dir}: cma_me, {len(data['elites'])} "
                                                        f"elites, flown on {seed}")
    assert page.locator("#info").text_content().endswith(f" steps on {seed}")
    page.close()


@pytest.mark.slow
@pytest.mark.parametrize("env_name", OTHER_ROWS)
def test_a_seed_that_is_not_the_runs_is_named_as_its_task_names_it(env_name, task_runs, run_cli):
    run_dir = task_runs[env_name]
    before = folder_state(run_dir)
    result = run_cli("video", run_dir, "--best", "--env_seed", "7")
    assert_one_line_error(result)
    noun = words_of(env_name)[0]
    assert result.stderr.strip() == (f"error: --env_seed 7 is not a {noun} of this run (it was flown on 52); "
                                     f"to fly its elites on other {noun}s, use: python lunar_lander.py "
                                     f"evaluate RUN --env_seeds 7")
    assert folder_state(run_dir) == before


@pytest.mark.slow
def test_evaluate_a_walkers_elites_on_other_terrains(task_runs, tmp_path, dask_cluster):
    run_dir = tmp_path / "run"
    shutil.copytree(task_runs[WALKER], run_dir)
    commands.evaluate(str(run_dir), env_seeds="3-4", top=2,
                                scheduler_address=dask_cluster.scheduler_address)
    table = pd.read_csv(run_dir / "robustness.csv")
    env, rows = tiny_env(WALKER), results.elite_rows(results.load_run(run_dir)[0])
    solutions = dict(zip(rows["index"], rows["solution"]))
    assert len(table) == 2
    for row in table.to_dict("records"):
        solution = solutions[row["cell_index"]]
        direct = [policies.rollout(solution, seed, env, env_name=WALKER)[0] for seed in (3, 4)]
        assert row["objective_seed3"] == direct[0] and row["objective_seed4"] == direct[1]
        assert row["solved_share"] == np.mean(np.array(direct) >= 300)


@pytest.mark.slow
def test_evaluate_says_a_robots_seeds_are_reset_seeds(task_runs, tmp_path, dask_cluster, capsys):
    """evaluate's lines in the task's words: a robot has reset seeds, not a lander's terrains."""
    run_dir = tmp_path / "run"
    shutil.copytree(task_runs["HalfCheetah-v5"], run_dir)
    commands.evaluate(str(run_dir), env_seeds="52,3", top=1,
                        scheduler_address=dask_cluster.scheduler_address)
    out = capsys.readouterr().out
    assert "note: the run searched on reset seed(s) [52] too; they are not new to its elites" in out
    assert "1 elites on 2 reset seeds: mean objective " in out and " on every reset seed, " in out
    assert "terrain" not in out


@pytest.mark.parametrize("args, fragments", [
    (["--env", "CartPole-v1"], ["--env", "CartPole-v1", "BipedalWalker-v3"]),
    (["--env", WALKER, "--measures", "impact_x"], ["impact_x", WALKER, "foot1_contact"]),
    (["--measures", "foot1_contact"], ["foot1_contact", "LunarLander-v3", "impact_x"]),
])
def test_unknown_tasks_and_other_tasks_measures_are_refused(run_cli, tmp_path, args, fragments):
    result = run_cli("--iterations", "1", "--outdir", str(tmp_path / "run"), *args)
    assert_one_line_error(result, *fragments)
    assert not (tmp_path / "run").exists()


def test_a_row_the_linear_policy_cannot_serve_is_refused(run_cli, tmp_path, monkeypatch):
    """Pendulum's torque is a box of [-2, 2]: tanh(W @ obs) can't reach it."""
    row = family.Environment(gym_id="Pendulum-v1", family=walker.WALKER, measures=("foot1_contact",),
                             qd_offset=-2000.0, env_seed="nothing", solved=0.0)
    monkeypatch.setitem(tasks.ENVIRONMENTS, "Pendulum-v1", row)
    for command in ([], ["experiment", "--seeds", "1"]):
        result = run_cli(*command, "--env", "Pendulum-v1", "--iterations", "1",
                         "--outdir", str(tmp_path / "run"))
        assert_one_line_error(result, "Pendulum-v1", "can't serve", "Box(-2.0, 2.0")
        assert not (tmp_path / "run").exists()


def test_an_archive_of_another_task_is_refused_as_a_warm_start(run_cli, tmp_path, tiny_run):
    before = folder_state(tiny_run)
    result = run_cli("--env", WALKER, "--from_archive", str(tiny_run / "archive.pkl"),
                     "--iterations", "1", "--outdir", str(tmp_path / "run"))
    assert_one_line_error(result, "32 weights", "96", "another task")
    assert not (tmp_path / "run").exists() and folder_state(tiny_run) == before
