"""A RunConfig's two constructors (config/run_config.py): `check_run_config` from a record and
`search_config` from a search's flags, each checking every value once, and what they share; the
policy's settings checked together (settings.py's `with_policy`, `for_policy`) and the `network`
a config makes once. Quick: no rollout, no cluster; each refusal's words are checked whole."""

import pytest

from qdsearch.base.flags import UsageError, named
from qdsearch.config.options import search_defaults, with_task
from qdsearch.config.run_config import check_run_config, search_config
from qdsearch.config.settings import DEFAULT_HIDDEN, SEARCH_FLAGS, for_policy, with_policy
from qdsearch.tasks import ENVIRONMENTS
from qdsearch.tasks.policies import LINEAR, Policy

RECORD = with_task({**search_defaults(), "seed": 3})  # a whole record, as config.json holds one
LATER = "not a field of this version's runs (written by a later version?)"


def refusal(make, *args) -> str:
    with pytest.raises(UsageError) as caught:
        make(*args)
    return str(caught.value)


def flags(**given) -> dict:
    """A search's flags as the command line hands them over: every flag, its default unless given."""
    return {**{name: flag.default for name, flag in SEARCH_FLAGS.items()}, **given}


def test_a_record_that_is_not_a_dict_is_refused_naming_what_it_is():
    assert refusal(check_run_config, [1]) == "holds a list, not the flags of a run"
    assert refusal(check_run_config, None) == "holds a NoneType, not the flags of a run"


@pytest.mark.parametrize("count, listed", [(1, "'f0'"), (3, "'f0', 'f1', 'f2'"),
                                           (4, "'f0', 'f1', 'f2' and 1 more"),
                                           (6, "'f0', 'f1', 'f2' and 3 more")])
def test_a_record_with_fields_of_a_later_version_names_three_and_counts_the_rest(count, listed):
    record = {**RECORD, **{f"f{i}": i for i in range(count)}}
    assert refusal(check_run_config, record) == f"holds {listed}, {LATER}"


def test_a_record_keeps_its_records_and_refuses_one_of_another_type():
    config = check_run_config({**RECORD, "created": "then", "command": ["a", "b"], "resumed": []})
    assert (config.created, config.command, config.resumed) == ("then", ["a", "b"], [])
    assert refusal(check_run_config, {**RECORD, "created": 5}) == "created is 5, not a str | None"
    assert refusal(check_run_config, {**RECORD, "command": "x"}) == "command is 'x', not a list[str]"


def test_a_null_is_refused_where_the_flag_has_a_value_by_default_and_a_path_must_be_text():
    assert refusal(check_run_config, {**RECORD, "iterations": None}) == f"{named('iterations')} is null"
    assert refusal(check_run_config, {**RECORD, "outdir": 5}) == (
        f"{named('outdir')} is 5, not a path or an address")
    assert check_run_config({**RECORD, "outdir": None, "evaluations": None}).outdir is None
    assert refusal(check_run_config, {**RECORD, "seed": -1}) == (
        f"{named('seed')} must be a whole number from 0 to 4294967295, got -1")
    assert refusal(check_run_config, {**RECORD, "seed": None}) == (  # a record names its seed
        f"{named('seed')} must be a whole number from 0 to 4294967295, got None")


def test_a_record_names_its_archive_and_its_cells():
    assert refusal(check_run_config, {**RECORD, "archive": None}) == f"{named('archive')} is null"
    assert refusal(check_run_config, {**RECORD, "grid": None}) == f"{named('grid')} is null"
    cvt = {**RECORD, "archive": "cvt", "grid": None, "cells": None}
    assert refusal(check_run_config, cvt) == f"{named('cells')} is null"
    assert check_run_config({**cvt, "cells": 64}).cells == 64


def test_a_record_is_completed_once_what_its_flags_make_together():
    """Its task's measures, its network's layers, its offset for its episode, and its sizes
    bounded (completed)."""
    config = check_run_config({**RECORD, "measures": None, "policy": "mlp", "hidden": None,
                                          "episode_length": 200, "qd_offset": None})
    assert config.measures == list(ENVIRONMENTS[config.env].measures)
    assert config.hidden == list(DEFAULT_HIDDEN) and config.network == Policy("mlp", DEFAULT_HIDDEN)
    assert config.qd_offset == ENVIRONMENTS[config.env].returns(200).offset
    assert refusal(check_run_config, {**RECORD, "grid": 2000}) == (
        f"{named('grid')} 2000 with 2 measures makes 4,000,000 cells; at most 1,000,000")
    assert check_run_config({**RECORD, "grid": 1000}).grid == 1000  # 1,000,000 cells: the most
    most = check_run_config({**RECORD, "n_emitters": 1000, "batch_size": 100})  # 100,000 solutions
    assert most.n_emitters * most.batch_size == 100_000
    assert refusal(check_run_config, {**RECORD, "n_emitters": 1000, "batch_size": 101}) == (
        f"{named('n_emitters')} 1000 x {named('batch_size')} 101 asks 101,000 solutions per iteration; "
        "at most 100,000")
    widest = {**RECORD, "n_emitters": 1000, "batch_size": 100, "env_seed": list(range(100))}
    assert len(check_run_config(widest).env_seed) == 100  # 10,000,000 rollouts: the most
    assert refusal(check_run_config, {**widest, "env_seed": list(range(101))}) == (
        "100,000 solutions on 101 env seed(s) make 10,100,000 rollouts per iteration; at most 10,000,000")


def test_a_search_s_flags_are_checked_once_into_a_config_with_a_seed():
    config = search_config(flags(seed=7, iterations=3))
    assert (config.seed, config.iterations, config.archive, config.grid) == (7, 3, "grid", 50)
    assert config.measures == list(ENVIRONMENTS[config.env].measures)
    drawn = {search_config(flags()).seed for _ in range(20)}  # from [0, 2^31): some above 2^20
    assert all(0 <= seed < 2**31 for seed in drawn) and len(drawn) > 1 and max(drawn) > 2**20
    assert search_config(flags(seed=1, outdir=2024)).outdir == "2024"  # Fire's number, as typed
    assert refusal(search_config, flags(iterations=None)) == f"{named('iterations')} is null"
    assert refusal(search_config, flags(grid="abc")) == (
        f"{named('grid')} must be a positive whole number, got 'abc'")


def test_a_search_refuses_a_learning_row_on_a_task_of_choices():
    able = [name for name, task in ENVIRONMENTS.items() if task.continuous]
    assert "Hopper-v5" in able and "LunarLander-v3" not in able
    assert refusal(search_config, flags(algorithm="pga_me")) == (
        f"{named('algorithm')} pga_me learns a critic of continuous actions; {named('env')} LunarLander-v3 "
        f"has a choice of actions. Tasks it can learn: {', '.join(able)}")


def test_a_policy_s_flags_are_checked_together():
    assert with_policy({"policy": "mlp"})["hidden"] == list(DEFAULT_HIDDEN)
    given = [8, 4]
    made = with_policy({"policy": "mlp", "hidden": given})
    assert made["hidden"] == [8, 4] and made["hidden"] is not given  # a list of its own
    assert with_policy({"policy": "linear"}) == {"policy": "linear"}
    assert with_policy({}) == {}  # no policy: the linear one
    for kind in ("linear", None):
        assert refusal(with_policy, {"policy": kind, "hidden": [8]}) == (f"{named('hidden')} is a flag of "
            f"{named('policy')} mlp; {named('policy')} linear has no hidden layers")
    assert for_policy({"policy": "linear", "hidden": [8], "n_emitters": 2}) == {
        "policy": "linear", "hidden": None, "n_emitters": 2}
    assert for_policy({"hidden": [8]}) == {"hidden": None}
    assert for_policy({"policy": "mlp", "hidden": [8]}) == {"policy": "mlp", "hidden": [8]}


def test_a_config_makes_its_network_once_and_anew_when_replaced():
    linear = check_run_config(RECORD)
    assert linear.network == LINEAR and linear.network.start_rule == ""
    mlp = check_run_config({**RECORD, "policy": "mlp", "hidden": [8, 4], "start": "zeros"})
    assert mlp.network == Policy("mlp", (8, 4), "zeros") and mlp.network is mlp.network
    assert mlp.replace(hidden=[3]).network == Policy("mlp", (3,), "zeros")
    assert "network" not in mlp.to_json()  # a config.json holds the flags, not what they make


def test_a_search_checks_each_value_once(monkeypatch):
    """The constructor from flags checks each flag once (the one from a record, in its turn): a
    search's checks and what its flags make together are not run twice."""
    import dataclasses

    seen = []
    for name in ("grid", "policy", "env_seed"):
        entry = SEARCH_FLAGS[name]
        monkeypatch.setitem(SEARCH_FLAGS, name, dataclasses.replace(
            entry, check=lambda flag, value, check=entry.check: seen.append(flag) or check(flag, value)))
    config = search_config(flags(seed=5, grid=20, policy="linear", env_seed=[3, 4]))
    assert (config.grid, config.policy, config.env_seed) == (20, "linear", [3, 4])
    assert sorted(seen) == ["env_seed", "grid", "policy"]
    seen.clear()
    assert check_run_config(config.to_json()) == config
    assert sorted(seen) == ["env_seed", "grid", "policy"]


def test_a_row_beyond_the_machine_s_memory_is_refused_with_its_numbers():
    """A 1024,1024 network on Ant-v5: CMA-ME's five full covariances hold far more than any
    machine; the refusal's weights, its size and the machine's memory, each computed apart."""
    import re

    from qdsearch.algorithms import ALGORITHMS

    actions, observations = ENVIRONMENTS["Ant-v5"].shape
    weights = (observations + 1) * 1024 + 1025 * 1024 + 1025 * actions  # two layers with biases
    with open("/proc/meminfo") as meminfo:
        machine = int(meminfo.readline().split()[1]) * 1024 / 1e9  # MemTotal, in kB
    wide = flags(env="Ant-v5", policy="mlp", hidden=[1024, 1024], algorithm="cma_me", seed=1)
    words = refusal(search_config, wide)
    found = re.fullmatch(rf"{named('algorithm')} cma_me would hold ~([\d,.]+) GB for ([\d,]+) weights "
                         rf"\(5 emitters\), more than 50% of this machine's ([\d.]+) GB; rows that fit: (.+) "
                         rf"\(or fewer emitters, a smaller {named('hidden')} or {named('buffer_size')}\)",
                         words)
    assert found, words
    held, told, memory, fits = found.groups()
    covariances = 5 * weights**2 * 8 / 1e9  # five float64 covariances, the least CMA-ES holds
    assert int(told.replace(",", "")) == weights == 1_086_472
    assert covariances <= float(held.replace(",", "")) <= 10 * covariances
    assert abs(float(memory) - machine) <= 0.051
    assert fits == "none" or set(fits.split(", ")) <= set(ALGORITHMS) - {"cma_me", "cma_mae"}
    widest = flags(env="Ant-v5", policy="mlp", hidden=[4096] * 8, algorithm="cma_me", seed=1)
    assert "117,616,648 weights" in (words := refusal(search_config, widest))  # 8 layers: none fits
    assert words.split("rows that fit: ")[1].startswith("none (or fewer emitters")


def test_a_learning_row_without_its_library_is_refused_naming_the_install(monkeypatch):
    from qdsearch.config import options

    monkeypatch.setattr(options, "LEARNING_LIBRARY", "qdsearch_absent_library")  # as if JAX were not there
    assert refusal(search_config, flags(env="Hopper-v5", algorithm="cma_mega_td3_es", seed=2)) == (
        f"{named('algorithm')} cma_mega_td3_es learns with JAX, which is not installed: pip install -r "
        "requirements-learning.txt")
    monkeypatch.undo()  # the test command installs JAX (requirements-learning.txt)
    learning = flags(env="Hopper-v5", algorithm="cma_mega_td3_es", seed=2)
    assert search_config(learning).algorithm == "cma_mega_td3_es"
