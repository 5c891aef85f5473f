"""A run's range of objectives follows its episode (--qd_offset and the rest: family.Returns), and
--reset each gives every evaluation its own reset, the same on any worker and after a resume.

Each number is checked against one computed here by other means: offsets by multiplying the
declared per-step values, QD scores by summing archive.csv, reset seeds by hashing the weights
with hashlib, objectives by flying gym.make's env by hand.
"""

import hashlib
import json
import math
import re
import struct

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest

from qdsearch import algorithms, tasks
from qdsearch.base.flags import UsageError, check_flags
from qdsearch.cli import commands
from qdsearch.config import options, run_config, settings
from qdsearch.config.options import search_defaults
from qdsearch.config.run_config import check_run_config
from qdsearch.search import experiments
from util import LANDER, assert_one_line_error, run_archive, run_metrics, tiny_flags

CHEETAH = "HalfCheetah-v5"


def config_of(**flags):
    """The config search makes of these flags (nothing flown)."""
    return run_config.search_config({**search_defaults(), "seed": 3, **flags})


def test_a_robots_offset_is_its_per_step_offset_times_the_episodes_length():
    """The issue's case: 50 steps record half the offset of 100; the default is the task's 1,000."""
    half, whole = config_of(env=CHEETAH, episode_length=50), config_of(env=CHEETAH, episode_length=100)
    assert (half.qd_offset, whole.qd_offset) == (-200.0, -400.0)
    assert config_of(env=CHEETAH).qd_offset == -4000.0 == tasks.ENVIRONMENTS[CHEETAH].qd_offset * 1000
    hopper = tasks.returns_of(config_of(env="Hopper-v5", episode_length=200))
    assert (hopper.offset, hopper.solved, hopper.top, hopper.heat) == (-20.0, 760.0, 760.0, (-20.0, 300.0))


def test_a_recorded_offset_is_the_runs_and_the_rest_follows_its_episode():
    returns = tasks.returns_of(config_of(env=CHEETAH, episode_length=50, qd_offset=-7))
    assert (returns.offset, returns.solved, returns.top, returns.heat) == (-7.0, 240.0, 240.0, (-50.0, 75.0))


@pytest.mark.parametrize("value", [float("nan"), float("inf"), True, "-5", None])
def test_a_qd_offset_must_be_a_number(value):
    if value is None:  # unset: the task's
        assert check_flags(settings.SEARCH_FLAGS, {"qd_offset": None}) == {"qd_offset": None}
        return
    with pytest.raises(UsageError, match=f"^--qd_offset must be a number, got {re.escape(repr(value))}$"):
        check_flags(settings.SEARCH_FLAGS, {"qd_offset": value})
    assert check_flags(settings.SEARCH_FLAGS, {"qd_offset": -3}) == {"qd_offset": -3.0}


def test_the_lander_keeps_its_offset_whatever_the_episode():
    """The lander is paid once for landing or crashing: its range does not follow the length."""
    assert config_of(env=LANDER, episode_length=100).qd_offset == config_of(env=LANDER).qd_offset == -600.0
    assert tasks.returns_of(config_of(env=LANDER, episode_length=100)).solved == 200.0


def test_the_offset_is_the_archives_and_cma_maes_floor():
    config = config_of(env=CHEETAH, episode_length=30, algorithm="cma_mae")
    archive = algorithms.grid_archives(config)()
    assert archive.qd_score_offset == -120.0
    assert algorithms.soft_archive(config)["threshold_min"] == -120.0


def test_a_given_offset_is_kept_and_a_run_from_before_keeps_the_old_one(tmp_path):
    """--qd_offset given wins; a config.json from before the flag ran with the task's offset at
    its own length, whatever its --episode_length (upgrade); --episode_length given beside
    --config takes the offset along, unless --qd_offset is given too."""
    assert config_of(env=CHEETAH, episode_length=50, qd_offset=-7).qd_offset == -7.0
    old = config_of(env=CHEETAH, episode_length=100).to_json()
    del old["qd_offset"], old["reset"]
    path = tmp_path / "config.json"
    path.write_text(json.dumps(old))
    assert run_config.recorded_settings(path)["qd_offset"] == -4000.0
    assert run_config.recorded_settings(path)["reset"] == "fixed"
    assert options.legacy_offset({}) == {"qd_offset": -600.0}  # from before --env: the lander
    assert options.legacy_offset({"env": "Hopper-v5", "episode_length": 10}) == {"qd_offset": -100.0}
    assert options.legacy_offset({"env": "Pendulum-v1"}) == {}  # refused as an --env later
    flags = {**search_defaults(), "episode_length": 25}
    assert run_config.search_config(flags, {"episode_length"}, path).qd_offset == -100.0
    flags = {**search_defaults(), "episode_length": 25, "qd_offset": -1}
    assert run_config.search_config(flags, {"episode_length", "qd_offset"}, path).qd_offset == -1.0


def test_each_run_of_an_experiment_has_the_offset_of_its_own_episode():
    axes, common, seeds = experiments.experiment_grid("cma_me", "1", {
        "env": CHEETAH, "episode_length": [20, 40], "n_emitters": 1})
    runs = experiments.experiment_runs(axes, common, seeds)
    assert [entry["config"]["qd_offset"] for entry in runs] == [-80.0, -160.0]
    assert all("qd_offset" not in entry["setting"] for entry in runs)


@pytest.mark.slow  # real MuJoCo runs on the cluster
def test_a_short_halfcheetah_runs_scores_and_report_use_its_own_range(tmp_path, dask_cluster, capsys):
    """metrics.json's QD score is archive.csv's objectives less -4 x 20 each; compare's report
    states that offset, the solved return (4.8 x 20) and the elites' mean objective."""
    folders = []
    for seed in (1, 2):
        folder = tmp_path / f"run{seed}"
        commands.search(**tiny_flags(dask_cluster, env=CHEETAH, episode_length=20, seed=seed),
                        outdir=str(folder))
        folders.append(folder)
        table = pd.read_csv(folder / "archive.csv")
        last = run_metrics(folder)[-1]
        assert json.loads((folder / "config.json").read_text())["qd_offset"] == -80.0
        assert math.isclose(last["qd_score"], math.fsum(table["objective"] + 80.0), rel_tol=1e-12)
        assert math.isclose(last["mean_objective"], table["objective"].mean(), rel_tol=1e-12)
    commands.compare(*map(str, folders), out=str(tmp_path / "cmp.png"))
    report = (tmp_path / "cmp.md").read_text()
    assert "less the offset -80" in report and "returns at least 96" in report
    header = next(line for line in report.splitlines() if line.startswith("| setting"))
    assert header.split(" | ")[2:4] == ["qd_score", "mean_objective"]
    rows = pd.read_csv(tmp_path / "cmp.csv")
    assert list(rows["qd_offset"]) == [-80.0, -80.0]
    cells = [(pd.read_csv(f / "archive.csv")["objective"] >= 96.0).sum() for f in folders]
    assert list(rows["solved_cells"]) == cells


# ---- --reset each ---------------------------------------------------------------------------


def hashed_seed(solution: np.ndarray, run_seed: int, env_seed: int) -> int:
    """The reset --reset each gives a solution, by the rule docs/locomotion.md states."""
    digest = hashlib.blake2b(np.asarray(solution, dtype="<f8").tobytes(), digest_size=4,
                             key=struct.pack("<QQ", run_seed, env_seed)).digest()
    return int.from_bytes(digest, "little")


def test_each_solution_gets_its_own_reset_from_the_run_seed_env_seed_and_weights():
    solutions = np.random.default_rng(0).normal(size=(5, 32))
    config = config_of(reset="each", env_seed=[52, 7], seed=11)
    seeds = tasks.reset_seeds(solutions, config)
    assert seeds.tolist() == [[hashed_seed(s, 11, 52), hashed_seed(s, 11, 7)] for s in solutions]
    assert len({int(seed) for seed in seeds.ravel()}) == 10  # all different
    assert tasks.reset_seeds(solutions, config.replace(reset="fixed")).tolist() == [[52, 7]] * 5
    assert tasks.flown_seeds(solutions, 7, config) == seeds[:, 1].tolist()
    recorded = {**config.to_json(), "env_seed": [52]}
    del recorded["reset"]  # a run from before --reset
    before = check_run_config(recorded)
    assert tasks.reset_seeds(solutions, before).tolist() == [[52]] * 5
    assert tasks.flown_seeds(solutions, 7, before) == [7] * 5


def hand_flown(solution, seed: int) -> float:
    """The linear policy's return on gym.make's lander from reset `seed`."""
    env = gym.make(LANDER)
    weights = np.asarray(solution).reshape(4, 8)
    obs, _ = env.reset(seed=seed)
    total, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(int(np.argmax(weights @ obs)))
        total, done = total + reward, terminated or truncated
    env.close()
    return total


@pytest.mark.slow  # real runs, a resume, a second cluster
def test_a_reset_each_run_is_the_same_on_one_and_two_workers_and_after_a_resume(
        tmp_path, dask_cluster, one_worker_cluster):
    flags = dict(reset="each", iterations=4, log_every=2)
    straight, alone, resumed = tmp_path / "two", tmp_path / "one", tmp_path / "resumed"
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(straight))
    commands.search(**tiny_flags(one_worker_cluster, **flags), outdir=str(alone))
    commands.search(**tiny_flags(dask_cluster, **{**flags, "iterations": 2}), outdir=str(resumed))
    commands.resume(str(resumed), iterations=4, scheduler_address=dask_cluster.scheduler_address)
    archive = run_archive(straight)
    assert archive.equals(run_archive(alone)) and archive.equals(run_archive(resumed))
    assert run_metrics(straight) == run_metrics(resumed)
    fixed = tmp_path / "fixed"
    commands.search(**tiny_flags(dask_cluster, **{**flags, "reset": "fixed"}), outdir=str(fixed))
    assert not archive.equals(run_archive(fixed))
    # every elite's objective is its return from its own reset, flown by hand
    for row in archive.head(6).to_dict("records"):
        solution = np.array([row[f"solution_{i}"] for i in range(32)])
        assert hand_flown(solution, hashed_seed(solution, 7, 52)) == row["objective"]


@pytest.mark.slow  # a video is rendered
def test_the_results_commands_fly_an_elite_from_its_own_reset(tmp_path, dask_cluster, run_cli):
    folder = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, reset="each", iterations=2), outdir=str(folder))
    result = run_cli("video", folder, "--top", "2")  # (top: by objective)
    assert result.returncode == 0, result.stderr
    index = pd.read_csv(folder / "videos" / "index.csv")
    assert index["reproduced"].all() and len(index) == 2
    archive = run_archive(folder).set_index("index")
    for row in index.to_dict("records"):
        solution = archive.loc[row["cell_index"], [f"solution_{i}" for i in range(32)]].to_numpy(float)
        assert row["reset_seed"] == hashed_seed(solution, 7, 52)
    evaluated = run_cli("evaluate", folder, "--env_seeds", 52, "--top", 2)  # not a reset it flew
    assert evaluated.returncode == 0 and "searched on" not in evaluated.stdout, evaluated.stderr
    for command, *args in (("trajectories", "--best"), ("explore",)):
        assert_one_line_error(run_cli(command, folder, *args),
                              f"{command}: each elite of this --reset each run flew its own terrain")
