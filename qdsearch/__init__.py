"""qdsearch: quality-diversity search of Gymnasium tasks with pyribs, on Dask; the package under
`python lunar_lander.py` (and the installed `lunar-lander`), whose command line is its top layer.

Map, a subpackage per layer from the bottom up: a module imports only the layers below its own
and, in its own layer, the modules its layer's map names before it (each layer's __init__.py);
tests/test_imports.py holds this, and docs/code.md draws it:
- base: errors and the checks of values, files, signatures, pickles, stopping, plots;
- tasks: the policies, the task families (lander, walker, locomotion) and their registry: an
  episode of any task;
- algorithms: the table of algorithms (pyribs' archives, emitters, schedulers) and the DQD rows'
  gradients;
- store: what a run writes of itself as data: metrics, the archive's data, trackers, the saver;
- config: every command's flags declared once, and a run's config made and read back;
- search: the cluster, the rollouts on it, the one run loop, search, resume and experiments;
- analysis: the commands that read runs (video, elites, evaluate, explore, watch, compare) and
  the notebook tables;
- cli: the command line: the commands, parsing, --help, exit codes.
"""

import ctypes.util
import os
import sys

# Plots are written to files, never shown: no display is needed (set before matplotlib loads).
os.environ.setdefault("MPLBACKEND", "Agg")
# MuJoCo renders videos headless through EGL (Debian's libegl1 and libegl-mesa0: Mesa's software
# renderer on a machine without a GPU), where the machine has it; MUJOCO_GL=osmesa picks libosmesa6.
# (MuJoCo loads the renderer MUJOCO_GL names when it is imported, so one that is missing would stop
# every MuJoCo episode, not only videos.)
if ctypes.util.find_library("EGL"):
    os.environ.setdefault("MUJOCO_GL", "egl")
# ribs' CMA-ES code is written for numba, which compiles it on the first ask/tell of a process
# (2.6-4.5 s). The compiled code's last bits differ (from the 26th iteration on, for 32 weights),
# and it is not much faster: 1.31 vs 1.39 ms per ask+tell for 32 weights (the lander), 1.79 vs
# 2.01 for 96 (the walker), 3.39 vs 4.02 for 216 (benchmarks/bench_ask_tell.py, 2026-11-24). So
# compilation is off unless asked for, and every search computes the same bits.
os.environ.setdefault("NUMBA_DISABLE_JIT", "1")


def cpu_flags() -> set[str]:
    """The CPU's feature flags as Linux lists them (avx2, fma, avx512f, ...); none elsewhere."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            return set(next(line for line in cpuinfo if line.startswith("flags")).split())
    except (OSError, StopIteration):
        return set()


def hold_x86_cpus_to_avx2_kernels() -> None:
    """OpenBLAS and numpy pick their kernels by the CPU when numpy loads, and CMA-ES's arithmetic
    gives other last bits on AVX-512 kernels than on AVX2 ones: the seed-42, 300-iteration lander
    archive differed between an AVX-512 and an AVX2 machine, and is the same on both held so
    (2026-11-28). So every x86-64 CPU with AVX2 and FMA runs OpenBLAS's Haswell kernels and
    numpy's AVX2 ones: a seed gives the same archive on a laptop and on any generation of cluster
    node, and a run resumed on another node ends as it would have. Only before numpy loads, and
    never over the user's own settings; config.json records the kernels a run used."""
    if "numpy" in sys.modules:
        return
    flags = cpu_flags()  # empty where not Linux: the libraries choose
    if {"avx2", "fma"} <= flags:
        os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
        if "avx512f" in flags:  # numpy 2.4's names of its AVX-512 kernels
            os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", "X86_V4,AVX512_ICL,AVX512_SPR")


hold_x86_cpus_to_avx2_kernels()

__all__ = ["read_run", "read_experiment"]  # the public API: docs/notebooks.md


def __getattr__(name: str):
    """`qdsearch.read_run` and `qdsearch.read_experiment`, imported when first used: the command
    line imports this package too, and answers --help without pandas and pyribs."""
    if name in __all__:
        from qdsearch.analysis import notebook

        return getattr(notebook, name)
    raise AttributeError(f"module 'qdsearch' has no attribute {name!r}")
