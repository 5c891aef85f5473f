"""The package as a library, for a notebook: importing it changes nothing in the process (the command
line sets what its bits need, and `qdsearch.hold_kernels` does the same on request), `read_run`
names each measure's column, and `fly_elite` rebuilds an elite's policy and flies it to the
archive's own numbers."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import qdsearch
from conftest import ROOT
from qdsearch import tasks
from qdsearch.base import kernels
from qdsearch.cli import commands
from util import tiny_flags

HELD = ("NUMBA_DISABLE_JIT", "MPLBACKEND", "MUJOCO_GL", "OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES",
        "XLA_FLAGS")


def settings_after(code: str, **env: str) -> dict:
    """What a fresh Python's `code` leaves of HELD, with none of them set beforehand but `env`;
    the code may print a JSON object of its own, returned under "printed"."""
    clean = {name: value for name, value in os.environ.items() if name not in HELD}
    finish = f"; import json, os; print(json.dumps({{n: os.environ.get(n) for n in {HELD!r}}}))"
    done = subprocess.run([sys.executable, "-c", code + finish], cwd=ROOT, env={**clean, **env},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    *printed, last = done.stdout.strip().splitlines()
    return {"printed": printed, **json.loads(last)}


def test_importing_the_package_and_every_layer_but_the_command_line_sets_nothing():
    modules = sorted(".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
                     for path in (ROOT / "qdsearch").rglob("*.py") if "cli" not in path.parts)
    assert len(modules) > 40 and "qdsearch.tasks" in modules and "qdsearch.analysis.notebook" in modules
    code = "import importlib; [importlib.import_module(m) for m in " + repr(modules) + "]"
    after = settings_after(code)
    assert not any(after[name] for name in HELD), after


def test_the_command_line_sets_what_its_bits_need_and_keeps_the_users_own():
    after = settings_after("import qdsearch.cli.app", MPLBACKEND="svg")
    assert after["NUMBA_DISABLE_JIT"] == "1" and after["MPLBACKEND"] == "svg"
    for name, (value, _) in kernels.settings().items():  # this machine's: its CPU, its EGL
        assert after[name] == (value if name != "MPLBACKEND" else "svg"), name


def test_hold_kernels_says_which_libraries_loaded_too_early():
    after = settings_after("import matplotlib, qdsearch; print(qdsearch.hold_kernels())")
    late = ["matplotlib", *(["numpy"] if kernels.avx2_kernels() else [])]  # (matplotlib loads numpy)
    assert after["printed"] == [repr(late)] and after["MPLBACKEND"] is None
    assert after["NUMBA_DISABLE_JIT"] == "1"  # numba had not loaded: held
    fresh = settings_after("import qdsearch; print(qdsearch.hold_kernels())")
    assert fresh["printed"] == ["[]"]


@pytest.mark.parametrize("flags", [{}, {"env_seed": "3,5", "reset": "each", "measures": "fuel,flight_time"},
                                   {"env": "Hopper-v5", "policy": "mlp", "hidden": "4"}],
                         ids=["lander", "two-resets-each", "hopper-mlp"])
def test_fly_elite_flies_every_elite_to_the_archives_numbers(tmp_path, dask_cluster, flags):
    folder = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, **flags), outdir=str(folder))
    found = qdsearch.read_run(folder)
    names = found.config["measures"]
    assert len(found.archive) > 3 and names
    for place, name in enumerate(names):  # each measure's column under its own name
        assert found.archive[name].equals(found.archive[f"measures_{place}"])
    for row in found.archive.index[:4]:
        flight = qdsearch.fly_elite(found, row)
        assert flight.objective == found.archive.loc[row, "objective"]
        assert flight.measures == {name: found.archive.loc[row, name] for name in names}
        assert len(flight.episodes) == len(found.config["env_seed"])
        assert np.mean(flight.episodes["objective"]) == flight.objective
    if flags.get("reset") == "each":  # each elite from resets of its own
        seeds = [tuple(qdsearch.fly_elite(folder, row).episodes["reset_seed"])
                 for row in found.archive.index[:4]]
        assert len(set(seeds)) == 4 and all(seed not in ((3, 5),) for seed in seeds)


def test_a_python_caller_reads_each_setting_by_its_keyword_and_the_command_line_by_its_flag(monkeypatch):
    """The messages name a setting through flags.named: the keyword to a Python caller (the
    package's own wording), the flag once the command line words them (as conftest.py does)."""
    from qdsearch.base import flags
    from qdsearch.tasks import check_episode

    monkeypatch.setitem(flags.NAMING, "style", "{}")  # a notebook's process: the command line never ran
    with pytest.raises(flags.UsageError) as python:
        flags.positive_int("workers", 0)
    assert str(python.value) == "workers must be a positive whole number, got 0"
    with pytest.raises(flags.UsageError, match=r"^terminate_when_unhealthy: env LunarLander-v3 has no"):
        check_episode("LunarLander-v3", tasks.Episode(None, True))
    with pytest.raises(flags.BadValue) as typed:
        flags.positive_int("workers", 0)
    assert (typed.value.setting, typed.value.value) == ("workers", 0)
    monkeypatch.setitem(flags.NAMING, "style", "--{}")  # as the command line words it: the error
    assert str(typed.value) == "--workers must be a positive whole number, got 0"  # raised before
    show = "import qdsearch.base.flags as f; print(f.named('env'))"
    assert settings_after(show)["printed"] == ["env"]
    assert settings_after("import qdsearch.cli; " + show)["printed"] == ["--env"]


def test_a_refused_value_says_which_setting_which_value_and_why_even_past_a_process():
    """A checker's refusal is a BadValue: its setting, its value and its words, the same after a
    pickle (a Dask worker's error comes back pickled)."""
    import pickle

    from qdsearch.base import flags

    with pytest.raises(flags.BadValue) as refused:
        flags.boolean("corrected", "perhaps")
    again = pickle.loads(pickle.dumps(refused.value))
    assert again.args == ("corrected", "perhaps", "must be true or false, got 'perhaps'")
    assert (again.setting, again.value, again.why) == again.args
    assert str(again) == str(refused.value) == "--corrected must be true or false, got 'perhaps'"


@pytest.mark.parametrize("typed, value", [
    *[(word, True) for word in ("true", "True", "yes", "1", True, np.True_)],
    *[(word, False) for word in ("false", "FALSE", "no", "0", False, np.False_)]])
def test_a_yes_or_no_flag_reads_the_words_a_user_types(typed, value):
    from qdsearch.base import flags

    assert flags.boolean("best", typed) is value


@pytest.mark.parametrize("value, ok", [(0, True), (2**32 - 1, True), (-1, False), (2**32, False),
                                       (True, False), (3.0, False)])
def test_a_seed_is_a_whole_number_numpy_and_box2d_take(value, ok):
    from qdsearch.base import flags

    if ok:
        assert flags.seed_number("env_seed", value) == value
    else:
        words = rf"^--env_seed must be a whole number from 0 to {2**32 - 1}, got {value!r}$"
        with pytest.raises(flags.BadValue, match=words) as refused:
            flags.seed_number("env_seed", value)
        assert refused.value.value is value


def test_a_commands_settings_are_made_from_the_values_given_each_checked_the_rest_defaulted():
    """settings_from: the values given, each through its flag's check; a field not given takes
    its flag's default (a Python caller need not name every flag)."""
    from qdsearch.base import flags
    from qdsearch.config import command_settings as cs
    from qdsearch.config.settings import ClusterSettings

    chosen = flags.settings_from(cs.Selection, {"top": 2, "best": "yes"})
    assert chosen == cs.Selection(cells=None, best=True, top=2, index=None, nearest=False)
    assert flags.settings_from(cs.WatchSettings, {}) == cs.WatchSettings(5006, "127.0.0.1")
    assert flags.settings_from(cs.WatchSettings, {"port": 65535}).port == 65535
    with pytest.raises(flags.BadValue, match=r"^--port must be at most 65535, got 65536$") as refused:
        flags.settings_from(cs.WatchSettings, {"port": 65536})
    assert (refused.value.setting, refused.value.value) == ("port", 65536)
    with pytest.raises(flags.BadValue, match=r"^--port must be a positive whole number, got 0$"):
        flags.settings_from(cs.WatchSettings, {"port": 0})
    with pytest.raises(flags.BadValue) as refused:
        flags.settings_from(cs.EliteFilter, {"top": -2})
    assert (refused.value.setting, refused.value.value) == ("top", -2)
    cluster = flags.settings_from(ClusterSettings, {"workers": 3, "scheduler_address": "tcp://h:1"})
    resumed = cs.resumed_cluster(flags.settings_from(cs.ResumeSettings, {"workers": None}), cluster)
    assert (resumed.workers, resumed.scheduler_address) == (None, "tcp://h:1")  # as the run was started
    assert cs.resumed_cluster(flags.settings_from(cs.ResumeSettings, {"workers": 1}), cluster).workers == 1
