"""The MuJoCo locomotion rows and the CVT archive: the measures are what MuJoCo's own contacts and
positions say, traced by hand; a CVT run keeps its centroids and every command reads it; missing
pieces (MuJoCo, its renderer's library) are one line. The every-row tests of test_environments.py
fly these rows too (the same episode everywhere, 1 worker = 2, resume, an experiment's twin)."""

import json
import os
import subprocess
import sys
from xml.etree import ElementTree

import mujoco
import numpy as np
import pytest

from conftest import ROOT, SCRIPT
from qdsearch import tasks
from qdsearch.analysis import results
from qdsearch.cli import commands
from qdsearch.config import run_config
from qdsearch.tasks import locomotion, policies
from util import (
    assert_one_line_error,
    assert_same_run,
    folder_state,
    read_checkpoint,
    run_archive,
    saved_archive,
    tiny_flags,
)

ROBOT_ROWS = ["Hopper-v5", "Walker2d-v5", "HalfCheetah-v5", "Ant-v5", "ant_omni"]


def feet_in_the_model(env) -> list[str]:
    """The robot's feet as its MuJoCo model (the XML the env loads) has them, not as our table
    names them: the geoms of the bodies at the ends of the legs (bodies without bodies inside),
    in the file's order (Walker2d: the right foot, then the left)."""
    root = ElementTree.parse(env.unwrapped.fullpath).getroot()
    return [geom.get("name") for body in root.iter("body") if body.find("body") is None
            for geom in body.findall("geom")]


def hand_trace(env_name: str, solution: np.ndarray, seed: int) -> dict:
    """One episode stepped by hand on gym.make's env: each foot's contact steps (MuJoCo's contact
    list, read pair by pair, for the feet read from the model's XML), the torso from the env's
    info, the rewards."""
    task = tasks.ENVIRONMENTS[env_name]
    env = tasks.plain_env(env_name)
    obs, _ = env.reset(seed=seed)
    model, data = env.unwrapped.model, env.unwrapped.data
    feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) for name in feet_in_the_model(env)]
    assert len(feet) == len(locomotion.ROBOTS[task.family.name].feet) and -1 not in feet
    height = torso_height(env)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    start, weights = data.qpos[:2].copy(), solution.reshape(task.action_dim, task.obs_dim)
    contacts, rewards, forward, steps, done, info = [0] * len(feet), 0.0, 0.0, 0, False, {}
    heights = 0.0
    while not done:
        obs, reward, terminated, truncated, info = env.step(np.tanh(weights @ obs))
        done, steps = terminated or truncated, steps + 1
        rewards, forward = rewards + reward, forward + info["reward_forward"]
        heights += height(data.qpos)
        for i, foot in enumerate(feet):
            contacts[i] += any({int(data.contact[k].geom1), int(data.contact[k].geom2)} == {foot, floor}
                               for k in range(data.ncon))
    return {"shares": [c / steps for c in contacts], "start": start, "x": info["x_position"],
            "y": info.get("y_position"), "return": rewards, "forward": forward, "steps": steps,
            "height": heights / steps}


def torso_height(env):
    """The torso's height from the joints, as the model's XML places it: a free joint (the Ant)
    holds it; a planar robot's is the torso's place plus its slide joint rootz, less its ref."""
    model = env.unwrapped.model
    torso = ElementTree.parse(env.unwrapped.fullpath).getroot().find(".//body[@name='torso']")
    rootz = torso.find("joint[@name='rootz']")
    if rootz is None:
        return lambda qpos: float(qpos[2])
    at = model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "rootz")]
    base = float(torso.get("pos").split()[2]) - float(rootz.get("ref", "0"))
    return lambda qpos: base + float(qpos[at])


@pytest.mark.parametrize("env_name", ROBOT_ROWS)
def test_locomotion_measures_match_a_hand_made_trace(env_name):
    task = tasks.ENVIRONMENTS[env_name]
    names = tuple(tasks.family_measures(task.family))
    env = tasks.make_env(env_name=env_name)
    touched = feet_apart = 0
    for solution in np.random.default_rng(5).normal(size=(3, task.solution_dim)) * 0.5:
        trace = hand_trace(env_name, solution, 11)
        objective, *values = policies.rollout(solution, 11, env, names, env_name=env_name)
        measured = dict(zip(names, values))
        feet = [name for name in names if "_foot" in name]
        assert [measured[name] for name in feet] == trace["shares"]
        feet_apart += len(set(trace["shares"])) > 1  # the feet's measures can tell them apart
        assert measured["torso_height"] == pytest.approx(trace["height"], abs=1e-9)
        assert measured["forward_distance"] == pytest.approx(trace["x"] - trace["start"][0], abs=1e-9)
        if "final_y" in measured:
            assert (measured["final_x"], measured["final_y"]) == pytest.approx((trace["x"], trace["y"]))
        expected = trace["return"] - (trace["forward"] if env_name == "ant_omni" else 0.0)
        assert objective == pytest.approx(expected, rel=1e-12, abs=1e-9)
        touched += sum(trace["shares"]) > 0
    assert touched > 0  # some foot of some policy touched the floor: the measure can tell
    assert feet_apart > 0 or len(feet) == 1  # a foot read twice would not pass unseen


def test_ant_omni_leaves_the_forward_reward_out_of_the_objective():
    solution = np.random.default_rng(2).normal(size=tasks.ENVIRONMENTS["Ant-v5"].solution_dim) * 0.5
    uni = policies.rollout(solution, 4, tasks.make_env(env_name="Ant-v5"), env_name="Ant-v5")
    omni = policies.rollout(solution, 4, tasks.make_env(env_name="ant_omni"), env_name="ant_omni")
    trace = hand_trace("Ant-v5", solution, 4)
    assert uni[0] - omni[0] == pytest.approx(trace["forward"]) and trace["forward"] != 0


@pytest.fixture(scope="module")
def cvt_run(tmp_path_factory, dask_cluster):
    """A tiny CVT run of the lander on two measures (the Voronoi heatmap) and its config."""
    run_dir = tmp_path_factory.mktemp("cvt") / "run"
    commands.search(**tiny_flags(dask_cluster, archive="cvt", cells=40, iterations=4, pictures=True),
               outdir=str(run_dir))
    return run_dir


def test_a_cvt_run_keeps_its_centroids_and_resumes_to_its_twin(cvt_run, tmp_path, dask_cluster):
    archive, config = results.load_run(cvt_run)
    assert type(archive).__name__ == "CVTArchive" and config.archive == "cvt" and config.cells == 40
    assert config.grid is None and np.array_equal(np.load(cvt_run / "centroids.npy"), archive.centroids)
    assert len(archive) > 5
    resumed = tmp_path / "resumed"
    commands.search(**tiny_flags(dask_cluster, archive="cvt", cells=40, iterations=2), outdir=str(resumed))

    commands.resume(str(resumed), iterations=4, scheduler_address=dask_cluster.scheduler_address)
    assert_same_run(resumed, cvt_run)
    assert np.array_equal(np.load(resumed / "centroids.npy"), archive.centroids)  # seeded: the same


@pytest.mark.slow
def test_every_command_reads_a_cvt_run(cvt_run, tmp_path, run_cli, dask_cluster):
    run_dir = tmp_path / "run"
    subprocess.run(["cp", "-r", str(cvt_run), str(run_dir)], check=True)
    before = run_archive(run_dir)
    archive, _ = results.load_run(run_dir)
    empty = next(i for i in range(archive.cells) if i not in set(archive.data("index")))
    point = archive.centroids[empty]
    address = ["--scheduler_address", dask_cluster.scheduler_address]
    cell = f"[({point[0]}, {point[1]})]"
    assert_one_line_error(run_cli("video", str(run_dir), "--cells", cell), "is empty", "--nearest")
    for args in (["video", str(run_dir), "--cells", cell, "--nearest"],
                 ["elites", str(run_dir), "--top", "3"],
                 ["trajectories", str(run_dir), "--top", "3"],
                 ["evaluate", str(run_dir), "--env_seeds", "3-4", "--top", "4", *address],
                 ["evaluate", str(run_dir), "--corrected", "--repeats", "2", *address],
                 ["explore", str(run_dir), *address],
                 ["compare", str(run_dir), "--out", str(tmp_path / "c")],
                 ["compare", str(run_dir), "--corrected", "--out", str(tmp_path / "fixed")]):
        result = run_cli(*args)
        assert result.returncode == 0, (args, result.stderr)
    assert len(list((run_dir / "videos").glob("*nearest*.mp4"))) == 1
    for name in ("trajectories.png", "robustness_heatmap.png", "corrected_heatmap.png", "explorer.html",
                 "heatmap.png"):
        assert (run_dir / name).stat().st_size > 10_000, name
    corrected = saved_archive(run_dir, "corrected_archive")
    assert np.array_equal(corrected.centroids, archive.centroids)  # the run's cells, refilled
    assert (tmp_path / "c.csv").is_file() and (tmp_path / "fixed_scores.png").is_file()
    assert run_archive(run_dir).equals(before)  # nothing changed the run's archive


@pytest.mark.slow
def test_a_config_edited_to_another_archive_kind_is_refused(cvt_run, tmp_path, run_cli):
    run_dir = tmp_path / "run"
    subprocess.run(["cp", "-r", str(cvt_run), str(run_dir)], check=True)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, "archive": "grid", "grid": 50, "cells": None}))
    before = folder_state(run_dir)
    assert_one_line_error(run_cli("elites", str(run_dir)), "--archive 'grid'", "ran with 'cvt'")
    assert folder_state(run_dir) == before


@pytest.mark.slow
def test_four_feet_on_a_cvt_archive_and_a_grid_of_four(tmp_path, dask_cluster):
    """Ant-v5 takes a CVT archive by default; a grid of 4 measures is refused only by its size."""
    config = run_config.check_run_config(read_checkpoint(
        _tiny(tmp_path / "ant", dask_cluster, env="Ant-v5") / "checkpoint.pkl")["config"])
    assert config.archive == "cvt" and len(config.measures) == 4
    grid4 = _tiny(tmp_path / "grid4", dask_cluster, env="Ant-v5", archive="grid", grid=3)
    archive, _ = results.load_run(grid4)
    assert tuple(archive.dims) == (3, 3, 3, 3)


def _tiny(run_dir, cluster, **flags):
    commands.search(**tiny_flags(cluster, iterations=1, **flags), outdir=str(run_dir))
    return run_dir


@pytest.mark.slow
def test_a_mujoco_task_without_mujoco_is_one_line_and_writes_nothing(tmp_path):
    """A real process in which `import mujoco` fails, as on a machine without it."""
    code = ("import sys, runpy; sys.modules['mujoco'] = None; sys.argv = sys.argv[1:]; "
            "runpy.run_path(sys.argv[0], run_name='__main__')")
    result = subprocess.run([sys.executable, "-c", code, str(SCRIPT), "--env", "Hopper-v5",
                             "--iterations", "1", "--outdir", str(tmp_path / "run")],
                            capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert_one_line_error(result, "--env Hopper-v5", "MuJoCo is not installed", "pip install")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_renderer_without_its_library_is_one_line(tmp_path, dask_cluster):
    """MUJOCO_GL=osmesa on a machine without libOSMesa: MuJoCo can't load its renderer."""
    import ctypes.util

    if ctypes.util.find_library("OSMesa"):
        pytest.skip("this machine has libOSMesa: a missing renderer can't be shown here")
    run_dir = _tiny(tmp_path / "hopper", dask_cluster, env="Hopper-v5")
    env = {name: value for name, value in os.environ.items() if name != "PYOPENGL_PLATFORM"}
    env["MUJOCO_GL"] = "osmesa"  # (this process's MuJoCo set PYOPENGL_PLATFORM for its EGL)
    result = subprocess.run([sys.executable, str(SCRIPT), "video", str(run_dir), "--best"],
                            capture_output=True, text=True, cwd=ROOT, timeout=300, env=env)
    assert_one_line_error(result, "MUJOCO_GL=osmesa", "apt-get install -y libosmesa6", code=1)
    assert not (run_dir / "videos").exists() or not list((run_dir / "videos").glob("*.mp4"))
