"""docs/extending.md, followed: the toy family written there goes into a module of its own outside
the package, is registered as tasks.py registers its own, and a real search flies it on the
session's Dask workers. Also: the rows' dimensions come from their envs' spaces (read on first
use, never at import), registration refuses clashing rows, and a family that is not drawn is
refused in one line by the commands that draw."""

import dataclasses
import json
import math
import subprocess
import sys

import gymnasium as gym
import pandas as pd
import pytest
from gymnasium.envs.classic_control.cartpole import CartPoleEnv

from conftest import ROOT
from qdsearch import tasks
from qdsearch.base.flags import UsageError
from qdsearch.cli import commands
from qdsearch.search import loop
from qdsearch.tasks import family
from util import assert_one_line_error, tiny_flags

DOC = ROOT / "docs" / "extending.md"
TOY = "toy_cartpole"  # the module's name in the doc's example
TOY_ENV = "CartPole-v1"


def doc_module(header: str = f"# {TOY}.py") -> str:
    """The doc's Python block that opens with `header`, as a file holds it (the list's indent off)."""
    blocks = DOC.read_text().split("```python\n")[1:]
    block = next(block.split("```", 1)[0] for block in blocks if block.lstrip().startswith(header))
    lines = block.splitlines()
    indent = len(lines[0]) - len(lines[0].lstrip())
    return "\n".join(line[indent:] for line in lines) + "\n"


@pytest.fixture
def tables_restored():
    """The tables as they were once the test is over, in this process (a session's workers keep
    what they were given: the toy's names are its own)."""
    saved = dict(tasks.ENVIRONMENTS), dict(tasks.MEASURES), list(tasks.FAMILIES), list(sys.path)
    yield
    for table, rows in zip((tasks.ENVIRONMENTS, tasks.MEASURES), saved[:2]):
        table.clear()
        table.update(rows)
    tasks.FAMILIES[:] = saved[2]
    sys.path[:] = saved[3]
    for name in [name for name in sys.modules if name.startswith("toy_")]:
        del sys.modules[name]


@pytest.fixture
def toy_family(tmp_path, dask_client, tables_restored, monkeypatch):
    """The doc's module, written outside the package and registered in this process and on the
    session cluster's workers (on their path too), as tasks.py registers FAMILY_MODULES. The
    workers keep it: its names are the toy's own."""
    (tmp_path / f"{TOY}.py").write_text(doc_module())

    def on_path_and_registered(folder: str) -> None:  # in this process, then on each worker
        if folder not in sys.path:
            sys.path.insert(0, folder)
        tasks.register_family(TOY)

    on_path_and_registered(str(tmp_path))
    dask_client.run(on_path_and_registered, str(tmp_path))
    # The saver processes of a search on a cluster joined by its address import tasks afresh and
    # know FAMILY_MODULES' families alone: a family registered at run time saves in threads.
    monkeypatch.setattr(loop, "SAVER_PROCESSES", 0)
    return sys.modules[TOY]


def test_a_search_flies_the_docs_toy_family_on_the_clusters_workers(toy_family, dask_cluster, tmp_path,
                                                                     run_cli, monkeypatch):
    task = tasks.ENVIRONMENTS[TOY_ENV]
    assert task.family in tasks.FAMILIES
    assert tasks.family_measures(task.family) == ["cart_x", "balanced_steps"]
    assert (task.shape, task.continuous) == ((2, 4), False)  # CartPole's Discrete(2) of 4 observations
    run_dir = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, env=TOY_ENV), outdir=str(run_dir))

    table = pd.read_csv(run_dir / "archive.csv")
    assert len(table) > 1 and len([c for c in table.columns if c.startswith("solution_")]) == 8
    for i, name in enumerate(task.measures):
        low, high = tasks.MEASURES[name].range
        assert table[f"measures_{i}"].between(low, high).all(), name
    last = json.loads((run_dir / "metrics.json").read_text())[-1]
    assert last["num_elites"] == len(table)
    # CartPole pays 1 a step: whole returns, so the hand sum is exact in any order.
    assert last["qd_score"] == math.fsum(table["objective"] - task.qd_offset)
    assert json.loads((run_dir / "config.json").read_text())["measures"] == list(task.measures)

    # Not drawn: the commands that draw it say so in one line; the others serve it.
    assert_one_line_error(run_cli("trajectories", run_dir, "--best"), "trajectories", "CartPole",
                          "cannot be drawn")
    for command in ("trajectories", "explore"):
        assert not task.family.draws(command)
        with pytest.raises(UsageError, match=f"{command}: the CartPole family cannot be drawn"):
            family.require_drawing(task.family, command)
    assert run_cli("elites", run_dir).returncode == 0
    assert run_cli("video", run_dir, "--best").returncode == 0  # CartPole's own frames
    assert len(list((run_dir / "videos").glob("*.mp4"))) == 1
    # An env that renders no frames: the video command says so in one line.
    frameless = gym.envs.registration.EnvSpec("FramelessCartPole-v0", entry_point=FramelessCartPole,
                                              max_episode_steps=500)
    monkeypatch.setitem(gym.registry, frameless.id, frameless)
    monkeypatch.setitem(tasks.ENVIRONMENTS, TOY_ENV, dataclasses.replace(task, gym_id=frameless.id))
    assert_one_line_error(run_cli("video", run_dir, "--best"), "--env CartPole-v1 cannot be drawn",
                          "FramelessCartPole-v0 renders no rgb_array frames")


class FramelessCartPole(CartPoleEnv):
    """CartPole rendering no frames, as an env may."""

    metadata = {"render_modes": [], "render_fps": 50}


def test_registration_refuses_a_clash_and_measures_of_another_family(tmp_path, tables_restored):
    text = doc_module()
    stray = (text.replace('"CartPole-v1"', '"StrayPole"').replace('"cart_x"', '"stray_x"')
             .replace('"balanced_steps"', '"stray_steps"')
             .replace('measures=("stray_x", "stray_steps")', 'measures=("fuel",)'))  # the lander's
    for name, module in ((TOY, text), ("toy_again", text), ("toy_stray", stray)):
        (tmp_path / f"{name}.py").write_text(module)
    sys.path.insert(0, str(tmp_path))
    tasks.register_family(TOY)
    tasks.register_family(TOY)  # its rows are there already: nothing changes
    assert tasks.FAMILIES.count(sys.modules[TOY].CARTPOLE) == 1 and TOY_ENV in tasks.ENVIRONMENTS
    with pytest.raises(ValueError, match="toy_again: CartPole-v1, balanced_steps, cart_x already named"):
        tasks.register_family("toy_again")
    with pytest.raises(ValueError, match="--env StrayPole's default measures fuel are not measures of its"):
        tasks.register_family("toy_stray")
    assert "StrayPole" not in tasks.ENVIRONMENTS and "stray_x" not in tasks.MEASURES


# Each row's policy, W's shape (actions x observations), as its env's spaces give it.
SHAPES = {"LunarLander-v3": (4, 8), "LunarLanderContinuous-v3": (2, 8), "BipedalWalker-v3": (4, 24),
          "BipedalWalkerHardcore-v3": (4, 24), "Hopper-v5": (3, 11), "Walker2d-v5": (6, 17),
          "HalfCheetah-v5": (6, 17), "Ant-v5": (8, 27), "ant_omni": (8, 27)}


def test_every_rows_dimensions_come_from_its_envs_spaces_read_on_first_use():
    assert {name: row.shape for name, row in tasks.ENVIRONMENTS.items() if name in SHAPES} == SHAPES
    assert tasks.ENVIRONMENTS["LunarLander-v3"].solution_dim == 32
    # A fresh process gathers every table and makes no env: --help stays quick, MuJoCo unloaded.
    code = ("import sys; from qdsearch import tasks; from qdsearch.config import options; "
            "print(sum('spaces' in row.__dict__ for row in tasks.ENVIRONMENTS.values()), "
            "'mujoco' in sys.modules, len(tasks.ENVIRONMENTS))")
    made, mujoco, rows = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                                        text=True, check=True).stdout.split()
    assert (made, mujoco, int(rows)) == ("0", "False", len(tasks.ENVIRONMENTS))


def test_a_family_declares_its_drawing_whole_or_is_refused_by_name():
    lander = tasks.ENVIRONMENTS["LunarLander-v3"].family
    assert lander.draws("trajectories") and lander.draws("explore")
    partial = family.Family(name="half", title="Half drawn", fly=lander.fly, pose=lander.pose)
    with pytest.raises(UsageError, match=r"explore: the Half drawn family cannot be drawn \(it declares "
                                         r"no pose_scale, scene;"):
        family.require_drawing(partial, "explore")
    with pytest.raises(TypeError):
        family.Family("positional", "no", lander.fly)  # every field by name
