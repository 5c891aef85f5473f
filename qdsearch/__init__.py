"""qdsearch: quality-diversity search of Gymnasium tasks with pyribs, on Dask; the package under
`python lunar_lander.py`, which is its command line (the package never imports it).

Map, a module per role, imports going down the list only:
- flags: the `Flag` entry, the checkers, UsageError;
- run_files: locks, atomic writes, JSON and pickles, logs; RunError;
- signing: the user's key (QDSEARCH_KEY, or ~/.config/qdsearch/key) and the checkpoints signed
  with it, their signature checked before anything is unpickled (resume --trust adopts another's);
- compact_pickle: the checkpoint's and the snapshots' pickles, an archive's occupied cells alone;
- stopping: Ctrl-C and SIGTERM (`STOP`), acted on where stopping is safe;
- plots: heatmaps and progress curves;
- trackers: TensorBoard, W&B and MLflow (--track), offline first, each iteration once;
- pinning: a local cluster's worker per core pinned to it (a Dask worker plugin);
- cluster: the Dask cluster, found, checked and joined with bounded waits, or started locally;
  the package shipped to workers that lack it;
- policies: the policies a solution makes (POLICIES: linear, mlp; `Policy`);
- gradients: the DQD rows' gradients, estimated from mirrored samples flown around a point;
- family: what a task family declares (`Family`, `Environment` with its env's spaces, `Measure`),
  `require_drawing`;
- fast_lander: the streamlined Lunar Lander (bitwise gym.make's);
- lander, walker, locomotion: a module per task family (locomotion: MuJoCo's robots, a family
  each): its rows, its episode, how it is drawn;
- tasks: the families gathered from FAMILY_MODULES (`register_family`): ENVIRONMENTS, MEASURES;
  the episode's rules (`Episode`); an episode of any policy (`fly`, `rollout`);
- algorithms: ALGORITHMS (the DQD rows too), what a row holds in memory, and `build_scheduler`;
- engine: chunks of rollouts on the workers, sized by what shares the cluster, back in order;
- options: every command's flags, declared once, and the bounds on sizes;
- metrics: a run's metrics rows;
- archive_data: a run's archive as data (archive.npz: numpy, already a dependency, keeps every
  float64 bit, which a CSV may not, and holds arrays of any shape, a CVT's centroids too), made
  back into its pyribs archive without unpickling; archive.csv of folders from before it;
- saving: a run folder's files, written while the loop goes on (saver threads; on a cluster
  joined by its address, saver processes);
- run_config: the typed RunConfig made from the flags, `upgrade` of old folders, config.json and
  the checkpoint read back;
- loop: the one run loop (`Run`, `Driver`);
- run: `search` and `resume` of a run folder;
- parts: an experiment split into parts, each its own process: the plan written once, a state
  file per part;
- experiment_folder: experiment.json read and checked, a setting's label (what compare reads);
- experiments: `experiment` (many runs through the one loop on one cluster), `resume`;
- run_folder: what the results commands read of a run folder (`load_run`, `elite_rows`): data
  files only, never a pickle, so a folder from anyone is safe to open;
- results: `video`, `elites`, `trajectories`, and choosing elites;
- evaluation: `evaluate`: the elites flown on other terrains, or on new seeds (corrected archive);
- explorer: `explore`, the page (explorer_page.html) and the poses it plays;
- live: `watch`, a live page of a run (Bokeh), redrawn from its files;
- stats: statistics across seeds (BCa, rliable's IQM and P(A>B) with stratified bootstrap, Holm);
- compared_runs: what `compare` reads of its runs (corrected metrics, a cut at a budget);
- comparison: `compare` and its statistics;
- notebook: run folders as pandas tables, the public API (`read_run`, `read_experiment`).
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
        from qdsearch import notebook

        return getattr(notebook, name)
    raise AttributeError(f"module 'qdsearch' has no attribute {name!r}")
