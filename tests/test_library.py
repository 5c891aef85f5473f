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

HELD = ("NUMBA_DISABLE_JIT", "MPLBACKEND", "MUJOCO_GL", "OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")


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
