"""The process settings a search's bits and headless drawing need, set by the command line before
numpy, numba, matplotlib and MuJoCo load; importing the package sets none of them. A notebook
that wants the command line's bits calls `qdsearch.hold_kernels()` first, before numpy loads.

Map: `hold_kernels` (SETTINGS: what it sets, each only where the user has not), `cpu_flags`,
`avx2_kernels`.
"""

from __future__ import annotations

import ctypes.util
import os
import sys


def cpu_flags() -> set[str]:
    """The CPU's feature flags as Linux lists them (avx2, fma, avx512f, ...); none elsewhere."""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            return set(next(line for line in cpuinfo if line.startswith("flags")).split())
    except (OSError, StopIteration):
        return set()


def avx2_kernels() -> dict[str, str]:
    """OpenBLAS and numpy pick their kernels by the CPU when numpy loads, and CMA-ES's arithmetic
    gives other last bits on AVX-512 kernels than on AVX2 ones (docs/performance.md). So every
    x86-64 CPU with AVX2 and FMA runs OpenBLAS's Haswell kernels and numpy's AVX2 ones: a seed
    gives the same archive on a laptop and on any generation of cluster node, and a run resumed on
    another node ends as it would have. config.json records the kernels a run used."""
    flags = cpu_flags()  # empty where not Linux: the libraries choose
    if not {"avx2", "fma"} <= flags:
        return {}
    held = {"OPENBLAS_CORETYPE": "Haswell"}
    if "avx512f" in flags:  # numpy 2.4's names of its AVX-512 kernels
        held["NPY_DISABLE_CPU_FEATURES"] = "X86_V4,AVX512_ICL,AVX512_SPR"
    return held


def settings() -> dict[str, tuple[str, str]]:
    """Each environment variable hold_kernels sets: its value, and the library that reads it when
    it loads (a setting made after that load does nothing)."""
    held = {
        # ribs' CMA-ES code is written for numba, whose compiled code's last bits differ from the
        # plain code's after a few dozen iterations, and is barely faster (docs/performance.md):
        # every search computes the plain code's bits.
        "NUMBA_DISABLE_JIT": ("1", "numba"),
        # Plots are written to files, never shown: no display is needed.
        "MPLBACKEND": ("Agg", "matplotlib"),
        **{name: (value, "numpy") for name, value in avx2_kernels().items()},
    }
    # The learning rows' JAX (optional) compiles for the CPU it finds: held to AVX2 as numpy is,
    # which on an AVX-512 machine gives the same bits as its own choice (docs/learning.md).
    if avx2_kernels():
        held["XLA_FLAGS"] = ("--xla_cpu_max_isa=AVX2", "jax")
    # MuJoCo renders videos headless through EGL (Debian's libegl1 and libegl-mesa0: Mesa's
    # software renderer on a machine without a GPU), where the machine has it; MUJOCO_GL=osmesa
    # picks libosmesa6. (MuJoCo loads the renderer MUJOCO_GL names when it is imported, so one
    # that is missing would stop every MuJoCo episode, not only videos.)
    if ctypes.util.find_library("EGL"):
        held["MUJOCO_GL"] = ("egl", "mujoco")
    return held


def hold_kernels() -> list[str]:
    """Set what the command line's searches run with, where the user has not set it: numba off,
    x86-64 CPUs held to AVX2's kernels (numpy's, JAX's), matplotlib drawing to files, MuJoCo
    rendering headless.
    Returns the libraries already loaded whose settings come too late in this process (call it
    first, before numpy, in a fresh kernel); its children (Dask's local workers) inherit the rest."""
    late = []
    for name, (value, library) in settings().items():
        if name not in os.environ:
            if library in sys.modules:
                late.append(library)
            else:
                os.environ[name] = value
    return sorted(set(late))
