"""The words a user reads (issue 60): a refusal names the flags that made its number, a name that
heads one choice means it, a folder of the wrong kind is named with what to pass instead, and a
task's things are called by its own family's words, never the lander's. (Each task's words on the
explorer page and in `elites` are checked with its run in test_environments.py; an experiment
folder given to a results command in test_experiment.py.)"""

import shutil

import pytest

import qdsearch
from qdsearch import algorithms, tasks
from qdsearch.base import flags
from qdsearch.base.flags import UsageError
from qdsearch.config import options, settings
from util import LANDER, assert_one_line_error


def help_entry(page: str, flag: str) -> str:
    """A flag's entry of a --help page, its lines joined: what a user reads of that flag."""
    lines = page.splitlines()
    start = lines.index(f"    --{flag}={flag.upper()}") + 1
    entry = []
    for line in lines[start:]:
        if not line.startswith("        "):
            break
        entry.append(line.strip())
    return " ".join(part for part in entry if not part.startswith("Default: "))


@pytest.mark.parametrize("algorithm, flags, made", [
    ("cma_mega_es", dict(n_emitters=20, es_samples=10000),
     (200_020, "--n_emitters 20 x (1 + --es_samples 10000)")),
    ("cma_mega_es", dict(n_emitters=20, batch_size=6000), (120_000, "--n_emitters 20 x --batch_size 6000")),
    ("cma_mega_es", dict(n_emitters=3, batch_size=101, es_samples=100),  # equal: the batch's words
     (303, "--n_emitters 3 x --batch_size 101")),
    ("me_es", dict(n_emitters=20, es_samples=10000), (200_000, "--n_emitters 20 x --es_samples 10000")),
    ("cma_mega", dict(n_emitters=1000, batch_size=1), (1000, "--n_emitters 1000 x --batch_size 1")),
    ("cma_me", dict(n_emitters=7, batch_size=9, es_samples=10000), (63, "--n_emitters 7 x --batch_size 9")),
])
def test_the_solutions_of_an_iteration_and_the_flags_that_make_them(algorithm, flags, made):
    """The larger of the batch and a DQD row's points with their samples (the first of equals: the
    batch); ME-ES's samples alone; no samples for a row that flies none."""
    config = {**options.search_defaults(), "algorithm": algorithm, **flags}
    assert options.solutions_per_iteration(settings.unchecked(config)) == made


@pytest.mark.parametrize("args, line", [
    (["--algorithm", "cma_mega_es", "--n_emitters", 20, "--es_samples", 10000],
     "error: --n_emitters 20 x (1 + --es_samples 10000) asks 200,020 solutions per iteration; at most "
     "100,000"),
    (["--algorithm", "cma_mega_es", "--n_emitters", 20, "--batch_size", 6000],
     "error: --n_emitters 20 x --batch_size 6000 asks 120,000 solutions per iteration; at most 100,000"),
    (["--algorithm", "me_es", "--n_emitters", 20, "--es_samples", 10000],  # its samples, no batch
     "error: --n_emitters 20 x --es_samples 10000 asks 200,000 solutions per iteration; at most 100,000"),
    (["experiment", "--algorithms", "cma_me,cma_maega_es", "--n_emitters", 20, "--es_samples", 10000],
     "error: --n_emitters 20 x (1 + --es_samples 10000) asks 200,020 solutions per iteration; at most "
     "100,000"),
])
def test_a_refused_size_names_the_flags_that_made_it(run_cli, tmp_path, args, line):
    """A DQD row's gradient samples make its iteration large: the refusal names --es_samples, not
    the --batch_size (30) the user left alone; a large batch is still named as the batch."""
    result = run_cli(*args)
    assert_one_line_error(result)
    assert result.stderr.strip() == line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, line", [
    (["--algorithm", "line"], "error: --algorithm 'line' is unknown; did you mean line_map_elites?"),
    (["experiment", "--algorithms", "[cma_me, LINE]"],
     "error: --algorithms 'LINE' is unknown; did you mean line_map_elites?"),
    (["--env", "Hopper"], "error: --env 'Hopper' is unknown; did you mean Hopper-v5?"),
])
def test_a_name_that_heads_one_choice_is_taken_for_it(run_cli, tmp_path, args, line):
    """difflib alone takes line for map_elites; its word is line_map_elites's head."""
    result = run_cli(*args)
    assert_one_line_error(result)
    assert result.stderr.strip() == line


@pytest.mark.parametrize("typed, choices, meant", [
    ("line", algorithms.ALGORITHMS, "line_map_elites"), ("from", settings.SEARCH_FLAGS, "from_archive"),
    ("max", tasks.MEASURES, "max_tilt"),
    # a head of several choices names none of them: difflib's nearest whole name, as before
    ("impact", tasks.MEASURES, "impact_x"), ("seeds", settings.SEARCH_FLAGS, "seed"),
    ("cma_mega_", algorithms.ALGORITHMS, "cma_mega"),  # cma_mega_es and cma_mega_td3_es
])
def test_a_head_wins_only_when_it_heads_one_choice(typed, choices, meant):
    assert flags.nearest(typed, choices) == meant


@pytest.mark.parametrize("typed, choices, meant", [
    # - for _ and any case: the head, the whole name or the tail as if typed with _
    ("CMA-MAEGA", algorithms.ALGORITHMS, "cma_maega_es"),
    ("Sep-CMA-MAE", algorithms.ALGORITHMS, "sep_cma_mae"),
    ("hopper-V5", tasks.ENVIRONMENTS, "Hopper-v5"),
    # a tail after any underscore, for a head the user may not know; whole names come first
    ("y_vel", tasks.MEASURES, "impact_y_velocity"), ("Y-VELOCITY", tasks.MEASURES, "impact_y_velocity"),
    ("x_velocty", tasks.MEASURES, "impact_x_velocity"), ("seed", settings.SEARCH_FLAGS, "seed"),
    ("sed", settings.SEARCH_FLAGS, "seed"), ("nothing_near", algorithms.ALGORITHMS, None),
])
def test_the_nearest_name_is_found_whatever_the_case_dashes_or_head(typed, choices, meant):
    assert flags.nearest(typed, choices) == meant


@pytest.mark.parametrize("typed", ["cma_mu", "cma_mega", "sep_cma", "impact_y_vel", "max_tit", "env_sed"])
def test_a_name_typed_with_dashes_or_capitals_is_taken_as_with_underscores(typed):
    for choices in (algorithms.ALGORITHMS, settings.SEARCH_FLAGS, tasks.MEASURES):
        assert flags.nearest(typed.replace("_", "-").upper(), choices) == flags.nearest(typed, choices)


def test_read_experiment_of_a_run_folder_says_it_is_a_run(tiny_run):
    """Not "RUN/experiment.json: no such file (is RUN a run folder of lunar_lander.py?)": it is one."""
    with pytest.raises(UsageError) as refused:
        qdsearch.read_experiment(tiny_run)
    assert str(refused.value) == (f"{tiny_run}: a run folder, not an experiment folder (it has config.json, "
                                  f"no experiment.json); read it with qdsearch.read_run('{tiny_run}')")
    assert qdsearch.read_run(tiny_run).config["seed"] == 7  # the function it names reads it


def test_search_help_says_what_a_seed_is_to_each_family(run_cli):
    """--help is every task's: a seed is the terrain of the landers and walkers, a robot's reset
    seed (MuJoCo has no terrain)."""
    search = run_cli("--help").stdout
    assert help_entry(search, "env_seed") == (
        "The env seed(s) every policy is flown on (the terrain for Lunar Lander, BipedalWalker; the reset "
        "seed for Hopper, Walker2d, HalfCheetah, Ant): one seed (52), a range (0-4), a list (3,5,8) or "
        "both (0-4,10). With several seeds the objective is the mean return over them, and each measure "
        "is its per-seed values averaged.")
    for command in ("video", "trajectories", "explore"):
        assert help_entry(run_cli(command, "--help").stdout, "env_seed") == (
            "The env seed to fly on (the terrain for Lunar Lander, BipedalWalker; the reset seed for Hopper, "
            "Walker2d, HalfCheetah, Ant), one of the run's; default: the run's first.")


def test_help_pages_name_no_lander_thing_as_every_tasks(run_cli):
    """200 is the lander's good landing, not every task's; explore plays any task's episode."""
    assert help_entry(run_cli("elites", "--help").stdout, "min_objective") == (
        "Only elites scoring at least this; the last line counts those at the task's solved return "
        "(LunarLander-v3's 200: good landings; BipedalWalker-v3's 300).")
    explore = run_cli("explore", "--help").stdout
    assert "landing" not in explore and "watch any elite's episode" in " ".join(explore.split())


def test_elites_counts_the_landers_good_landings(run_cli, tiny_run, tmp_path):
    """The last line of `elites` counts the elites at the task's solved return, in its words."""
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    result = run_cli("elites", run_dir, "--top", 3)
    assert result.returncode == 0, result.stderr
    archive = qdsearch.read_run(run_dir).archive
    good = int((archive["objective"] >= tasks.ENVIRONMENTS[LANDER].solved).sum())
    assert result.stdout.splitlines()[-1] == (f"3 of {len(archive)} elites ({good} score 200 or more: "
                                              f"good landings); written to {run_dir / 'elites.csv'}")


def test_the_command_that_continues_an_experiment_is_the_one_to_type():
    from pathlib import Path

    from qdsearch.search.experiment_folder import resume_command

    assert resume_command(Path("outputs/exp")) == "python lunar_lander.py resume outputs/exp"
    assert resume_command(Path("outputs/exp"), 2, 5) == "python lunar_lander.py resume outputs/exp --part 2/5"
