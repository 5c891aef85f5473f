"""The benchmark functions (qdsearch/tasks/functions.py): sphere, Rastrigin and the planar arm held
against their formulas written out here point by point (pyribs' examples/sphere.py and its arm
tutorial), and real runs of them: scored in the driver with no cluster, every elite's objective and
measures as the formulas give them, the same whatever --workers, after kill -9 and resume, and every
results command on them (those that fly an episode: one line)."""

import json
import math
import signal
import time

import numpy as np
import pandas as pd
import pytest

from qdsearch.algorithms import build_scheduler
from qdsearch.cli import commands
from qdsearch.config import options, run_config
from qdsearch.config.settings import unchecked
from qdsearch.tasks import (
    ENVIRONMENTS,
    MEASURES,
    evaluate_points,
    has_gradients,
    make_env,
    measure_bounds,
    point_gradients,
    scored_here,
    shape_of,
)
from qdsearch.tasks.family import NoEpisode
from qdsearch.tasks.policies import fly
from util import (
    assert_killed_then_resumed_as_its_twin,
    assert_one_line_error,
    assert_same_run,
    checkpoint_iteration,
    launch,
    read_checkpoint,
    run_archive,
    run_metrics,
    saved_archive,
    tiny_flags,
    wait_for,
)


def sphere_by_hand(point):
    """pyribs' sphere.py, one point: shift 2.048, worst at -5.12 everywhere, [0, 100]."""
    shift, dim = 0.4 * 5.12, len(point)
    raw = sum((x - shift) ** 2 for x in point)
    worst = dim * (-5.12 - shift) ** 2
    return 100.0 * (raw - worst) / (0.0 - worst)


def rastrigin_by_hand(point):
    shift, dim = 0.4 * 5.12, len(point)

    def cost(xs):
        return 10 * dim + sum((x - shift) ** 2 - 10 * math.cos(2 * math.pi * (x - shift)) for x in xs)

    worst = cost([-5.12] * dim)
    return 100.0 * (cost(point) - worst) / (0.0 - worst)


def halves_by_hand(point):
    """sphere.py's measures: a coordinate outside [-5.12, 5.12] counts as 5.12 / x."""
    folded = [x if -5.12 <= x <= 5.12 else 5.12 / x for x in point]
    half = len(point) // 2
    return sum(folded[:half]), sum(folded[half:])


def arm_by_hand(angles):
    """pyribs' arm tutorial: minus the angles' variance; the hand at the end of unit links."""
    mean = sum(angles) / len(angles)
    x = y = total = 0.0
    for angle in angles:
        total += angle
        x, y = x + math.cos(total), y + math.sin(total)
    return -sum((a - mean) ** 2 for a in angles) / len(angles), x, y


BY_HAND = {
    "sphere": lambda p: (sphere_by_hand(p), *halves_by_hand(p)),
    "rastrigin": lambda p: (rastrigin_by_hand(p), *halves_by_hand(p)),
    "arm": arm_by_hand,
}


@pytest.mark.parametrize("env", list(BY_HAND))
def test_the_functions_score_points_as_their_formulas(env):
    """Random points, some far outside the clipping bound, and the optimum: every row as the
    formula gives it, the batch scored at once."""
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.normal(0, 4, size=(20, 7)), rng.uniform(-30, 30, size=(5, 7)),
                             np.full((1, 7), 2.048)])
    rows = evaluate_points(points, ENVIRONMENTS[env].measures, env_name=env)
    assert rows.shape == (26, 3)
    for point, row in zip(points, rows):
        np.testing.assert_allclose(row, BY_HAND[env](list(point)), rtol=1e-12, atol=1e-9)
    if env != "arm":
        assert rows[-1, 0] == pytest.approx(100.0)  # the optimum
        assert rows[-1, 1] == pytest.approx(3 * 2.048)  # 7 coordinates: 3 in the first half


@pytest.mark.parametrize("env", list(BY_HAND))
def test_the_exact_gradients_are_the_formulas_slopes(env):
    """Each point's Jacobian (objective, then each measure) against central differences of the
    formulas written out above, coordinates inside and beyond the clipping bound alike."""
    rng = np.random.default_rng(5)
    points = np.concatenate([rng.normal(0, 3, size=(6, 7)), rng.uniform(-20, 20, size=(3, 7))])
    points = points[np.all(np.abs(np.abs(points) - 5.12) > 1e-3, axis=1)]  # not on the fold's kink
    jacobians = point_gradients(points, ENVIRONMENTS[env].measures, env_name=env)
    assert jacobians.shape == (len(points), 3, 7) and has_gradients(env)
    step = 1e-6
    for point, jacobian in zip(points, jacobians):
        for j in range(7):
            up, down = point.copy(), point.copy()
            up[j] += step
            down[j] -= step
            slope = (np.array(BY_HAND[env](list(up))) - np.array(BY_HAND[env](list(down)))) / (2 * step)
            np.testing.assert_allclose(jacobian[:, j], slope, rtol=1e-5, atol=1e-6)
    one = point_gradients(points, ("sum_second_half",) if env != "arm" else ("hand_y",), env_name=env)
    np.testing.assert_array_equal(one, jacobians[:, [0, 2]])  # the measures asked, in their order
    assert not has_gradients("LunarLander-v3")


def test_an_iteration_of_exact_gradients_counts_no_samples():
    """The size check and the evaluations count each point, not the --es_samples it never flies."""
    from qdsearch.algorithms import evaluations_per_iteration

    config = {**options.search_defaults(), "algorithm": "cma_mega", "n_emitters": 1000, "batch_size": 1}
    assert options.solutions_per_iteration(unchecked(config)) == (1000, "--n_emitters 1000 x --batch_size 1")
    row = type("Config", (), {**config, "es_samples": 100})
    assert evaluations_per_iteration(row) == 2000  # each point, and its one branched solution


def test_the_gradients_at_the_clipping_bound_and_of_integer_points():
    """At exactly +-5.12 a coordinate is kept, so its slope is 1 (sphere.py's clip mask is strict
    too); integer points, as a notebook may pass them, get the float slopes of 5.12 / x beyond."""
    jacobian = point_gradients(np.array([[5.12, -5.12, 6, -8]]), ("sum_first_half", "sum_second_half"),
                               env_name="sphere")[0]
    np.testing.assert_allclose(jacobian[1], [1.0, 1.0, 0.0, 0.0])
    integers = point_gradients(np.array([[6, 1, -7, 0]]), ("sum_first_half", "sum_second_half"),
                               env_name="rastrigin")[0]
    np.testing.assert_allclose(integers[1:], [[-5.12 / 36, 1, 0, 0], [0, 0, -5.12 / 49, 1]], rtol=1e-12)


@pytest.mark.slow  # real runs
@pytest.mark.parametrize("algorithm", ["cma_mega", "cma_maega"])
def test_a_run_on_exact_gradients_is_pyribs_told_the_formulas_and_resumes_as_its_twin(tmp_path, algorithm):
    """sphere.py's loop by hand (ask_dqd, tell_dqd of the points' values and Jacobians, then ask
    and tell) on the run's own config gives the run's archive; each iteration counts its points
    and its batch; a run stopped at 3 iterations and resumed to 6 ends as the straight run."""
    flags = dict(env="sphere", dim=6, algorithm=algorithm, n_emitters=2, batch_size=5, sigma0=1.0,
                 log_every=3)
    commands.search(**tiny_flags(**flags, iterations=6), outdir=str(tmp_path / "run"))
    scheduler = build_scheduler(run_config.load_run_config(tmp_path / "run"))
    measures = ENVIRONMENTS["sphere"].measures
    for _ in range(6):
        points = scheduler.ask_dqd()
        rows = np.array([BY_HAND["sphere"](list(point)) for point in points])
        scheduler.tell_dqd(rows[:, 0], rows[:, 1:], point_gradients(points, measures, env_name="sphere"))
        batch = scheduler.ask()
        rows = np.array([BY_HAND["sphere"](list(point)) for point in batch])
        scheduler.tell(rows[:, 0], rows[:, 1:])
    data = scheduler.result_archive.data(return_type="pandas")
    run = run_archive(tmp_path / "run")
    assert len(run) == len(data) > 10
    np.testing.assert_allclose(np.sort(run["objective"]), np.sort(data["objective"]), rtol=1e-12)
    assert [row["evaluations"] for row in run_metrics(tmp_path / "run")] == [12 * i for i in range(1, 7)]
    commands.search(**tiny_flags(**flags, iterations=3), outdir=str(tmp_path / "resumed"))
    commands.resume(str(tmp_path / "resumed"), iterations=6)
    assert_same_run(tmp_path / "run", tmp_path / "resumed")


def test_points_on_the_clipping_bound_and_of_integers_score_as_the_formula():
    """A coordinate of exactly +-5.12 is kept (sphere.py folds only those beyond); integer points,
    as a notebook may pass them, are scored as floats; one measure alone is one column."""
    points = np.array([[5, 6, -7, 0, 1, -2], [3, 3, 3, 3, 3, 3]])
    rows = evaluate_points(points, ("sum_first_half", "sum_second_half"), env_name="sphere")
    for point, row in zip(points, rows):
        np.testing.assert_allclose(row, BY_HAND["sphere"]([float(x) for x in point]), rtol=1e-12)
    edge = np.array([[5.12, -1.0, 5.13, 1.0]])
    assert evaluate_points(edge, ("sum_first_half",), env_name="rastrigin")[0, 1] == pytest.approx(4.12)
    second = evaluate_points(edge, ("sum_second_half",), env_name="sphere")
    assert second.shape == (1, 2) and second[0, 1] == pytest.approx(5.12 / 5.13 + 1)


def test_only_the_functions_are_scored_in_the_driver_and_none_flies_an_episode():
    assert [name for name in ENVIRONMENTS if scored_here(name)] == ["sphere", "rastrigin", "arm"]
    with pytest.raises(NoEpisode, match="arm is a benchmark function"):
        make_env(env_name="arm")
    with pytest.raises(NoEpisode, match="^a benchmark function has no episode$"):
        fly(np.zeros(12), 0, None, env_name="arm")


@pytest.mark.slow  # a real run
def test_a_search_of_the_sphere_holds_what_the_formula_gives(tmp_path, run_cli):
    """A real run, scored in the driver (no cluster started): every elite's stored objective and
    measures are the formula's for its solution, of --dim coordinates, in a grid of sphere.py's
    bounds (+-5.12 dim / 2)."""
    run_dir = tmp_path / "run"
    result = run_cli("--env", "sphere", "--dim", "10", "--iterations", "5", "--seed", "2",
                     "--n_emitters", "2", "--batch_size", "8", "--sigma0", "0.5", "--pictures", "false",
                     "--outdir", str(run_dir))
    assert result.returncode == 0, result.stderr
    log = (run_dir / "run.log").read_text()
    assert "Scoring the points in this process" in log and "Dask" not in log
    archive = saved_archive(run_dir)
    assert archive.solution_dim == 10
    np.testing.assert_allclose(archive.lower_bounds, [-25.6, -25.6])
    np.testing.assert_allclose(archive.upper_bounds, [25.6, 25.6])
    data = archive.data()
    assert len(data["solution"]) > 10
    for solution, objective, measures in zip(data["solution"], data["objective"], data["measures"]):
        np.testing.assert_allclose([objective, *measures], BY_HAND["sphere"](list(solution)), rtol=1e-12)
    metrics = run_metrics(run_dir)
    assert metrics[-1]["evaluations"] == 5 * 16
    assert metrics[-1]["qd_score"] == pytest.approx(float(np.sum(data["objective"])))  # offset 0


@pytest.mark.slow  # real runs
@pytest.mark.parametrize("env", ["arm", "rastrigin"])
def test_a_function_run_is_the_same_whatever_the_workers(tmp_path, env):
    """--workers names a cluster the points never go to: 1 and 2 give the same run."""
    for workers in (1, 2):
        commands.search(**tiny_flags(env=env, dim=6, workers=workers, iterations=6),
                        outdir=str(tmp_path / f"w{workers}"))
    assert_same_run(tmp_path / "w1", tmp_path / "w2")


@pytest.mark.slow  # a real run
def test_a_function_run_killed_and_resumed_is_its_twin(tmp_path, one_worker_cluster, dask_cluster):
    """kill -9 past its third iteration's checkpoint, then resume: bit for bit the uninterrupted run."""
    assert_killed_then_resumed_as_its_twin(tmp_path, dask_cluster, one_worker_cluster,
                                           dict(env="sphere", dim=8, iterations=300, algorithm="map_elites"))


@pytest.mark.slow  # a real run
def test_a_function_run_stopped_keeps_its_last_iteration(tmp_path):
    """Ctrl-C: the stop is acted on between two iterations, and the checkpoint holds the last one
    told (no snapshot is taken after each tell: the scheduler itself is checkpointed), whatever the
    log interval; resumed, the run ends as its twin. A DQD row: its two batches are one step."""
    flags = dict(env="sphere", dim=8, algorithm="cma_mega_es", es_samples=4, log_every=1000)
    commands.search(**tiny_flags(**flags, iterations=3000), outdir=str(tmp_path / "twin"))
    run_dir = tmp_path / "stopped"
    process = launch(**{**tiny_flags(**flags, iterations=100_000), "outdir": run_dir})
    wait_for(lambda: (run_dir / "checkpoint.pkl").is_file(), process, "the run under way")
    time.sleep(0.5)  # some iterations past the first checkpoint, none saved
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 130 and "Traceback" not in err, err
    checkpoint = read_checkpoint(run_dir / "checkpoint.pkl")
    stopped_at = checkpoint_iteration(run_dir)
    assert 0 < stopped_at < 3000
    assert [row["iteration"] for row in checkpoint["metrics"]] == list(range(1, stopped_at + 1))
    commands.resume(str(run_dir), iterations=3000)
    assert run_archive(run_dir).equals(run_archive(tmp_path / "twin"))
    assert run_metrics(run_dir) == run_metrics(tmp_path / "twin")


@pytest.mark.slow  # a real run
def test_the_results_commands_read_a_function_run(tmp_path, run_cli):
    """elites, evaluate (the points scored again: the same) and an experiment compared; video and
    trajectories, which fly an episode, say in one line there is none."""
    folder = tmp_path / "exp"
    result = run_cli("experiment", "--env", "arm", "--dim", "5", "--algorithms", "cma_me,line_map_elites",
                     "--seeds", "1-2", "--iterations", "4", "--n_emitters", "2", "--batch_size", "6",
                     "--pictures", "false", "--outdir", str(folder))
    assert result.returncode == 0, result.stderr
    runs = [folder / entry["name"] for entry in json.loads((folder / "experiment.json").read_text())["runs"]]
    assert run_cli("compare", str(folder)).returncode == 0
    assert (folder / "compare.csv").is_file()
    run = runs[0]
    assert run_cli("elites", str(run), "--top", "2").returncode == 0
    listed = pd.read_csv(run / "elites.csv")
    archive = run_archive(run).sort_values("objective", ascending=False)
    assert list(listed.columns) == ["objective", "hand_x", "hand_y", "cell_index"]
    assert listed["objective"].tolist() == archive["objective"].head(2).tolist()
    assert run_cli("evaluate", str(folder), "--corrected", "--repeats", "2").returncode == 0
    for each in runs:
        corrected = json.loads((each / "corrected.json").read_text())
        assert corrected["qd_score"] == pytest.approx(corrected["run"]["qd_score"], rel=1e-12)
        assert corrected["num_elites"] == corrected["run"]["num_elites"]
    for command in ("video", "trajectories"):
        assert_one_line_error(run_cli(command, str(run), "--best"), "arm is a benchmark function", code=2)


@pytest.mark.parametrize("flags, line", [
    (("--env", "sphere", "--dim", "1"), "--dim 1: a benchmark function takes 2 coordinates at least"),
    (("--env", "LunarLander-v3", "--dim", "5"),
     "--dim is for the benchmark functions; --env LunarLander-v3 takes its size from its spaces"),
    (("--env", "sphere", "--policy", "mlp"),
     "--policy mlp: a solution of --env sphere is its point (the linear policy of one constant input)"),
    (("--env", "arm", "--algorithm", "pga_me"),
     "--algorithm pga_me learns from episodes; --env arm is a benchmark function, with none"),
    (("--env", "rastrigin", "--algorithm", "me_es"),
     "--algorithm me_es learns from episodes; --env rastrigin is a benchmark function, with none"),
    (("--env", "sphere", "--episode_length", "10"),
     "--episode_length: --env sphere is a benchmark function, with no episode"),
    (("--env", "Hopper-v5", "--algorithm", "cma_maega"),
     "--algorithm cma_maega takes a benchmark function's exact gradients; --env Hopper-v5 has none "
     "(cma_maega_es estimates them)"),
])
def test_what_a_function_cannot_take_is_one_line(tmp_path, run_cli, flags, line):
    result = run_cli(*flags, "--iterations", "2", "--outdir", str(tmp_path / "run"))
    assert_one_line_error(result)
    assert result.stderr.strip() == f"error: {line}"
    assert not (tmp_path / "run").exists()


def test_the_measures_ranges_grow_with_the_dimension():
    """sphere.py's bounds, +-5.12 dim / 2 for each half's sum; the arm's reach, its joints; a
    Gymnasium task's measures keep their ranges."""
    assert MEASURES["sum_first_half"].bounds(10) == pytest.approx((-25.6, 25.6))
    assert MEASURES["sum_second_half"].bounds(100) == pytest.approx((-256.0, 256.0))
    assert MEASURES["hand_y"].bounds(12) == pytest.approx((-12.0, 12.0))
    assert MEASURES["impact_x"].bounds(None) == (-1.0, 1.0)
    config = run_config.check_run_config(options.with_task(dict(options.search_defaults(), env="arm", dim=5,
                                                                seed=1)))
    assert measure_bounds(config) == [pytest.approx((-5.0, 5.0))] * 2 and shape_of(config) == (5, 1)


def test_flags_not_yet_set_take_the_functions_own():
    """An experiment's common flags leave a swept flag unset (None): the policy is then the run's
    own (linear), the algorithm each run's, the dimension the function's."""
    common = options.with_dim({"env": "arm", "policy": None, "algorithm": None, "dim": None})
    assert common["dim"] == 12 and common["policy"] is None
    assert options.with_dim({"env": "sphere", "dim": 7})["dim"] == 7


def test_env_seeds_and_resets_change_nothing_of_a_function(tmp_path, run_cli):
    """A point has no resets: several --env_seed values and --reset each give the run of one seed."""
    tiny = ("--env", "sphere", "--dim", "4", "--iterations", "3", "--n_emitters", "2", "--batch_size", "5",
            "--seed", "3", "--pictures", "false")
    for name, extra in (("one", ()), ("many", ("--env_seed", "0-4", "--reset", "each"))):
        result = run_cli(*tiny, *extra, "--outdir", str(tmp_path / name))
        assert result.returncode == 0, result.stderr
    assert run_archive(tmp_path / "many").equals(run_archive(tmp_path / "one"))
    assert run_metrics(tmp_path / "many") == run_metrics(tmp_path / "one")


def test_the_smallest_function_has_two_coordinates(tmp_path, run_cli):
    result = run_cli("--env", "sphere", "--dim", "2", "--iterations", "1", "--n_emitters", "1",
                     "--batch_size", "4", "--pictures", "false", "--outdir", str(tmp_path / "run"))
    assert result.returncode == 0, result.stderr
    assert saved_archive(tmp_path / "run").solution_dim == 2
