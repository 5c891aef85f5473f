#!/usr/bin/env python
"""Our run of a benchmark function against pyribs' own loop: is a sphere run bounded by pyribs' ask
and tell, not by us?

pyribs' examples/sphere.py needs torch, loguru and tabulate, which this project does not install;
its loop is rebuilt here from pyribs alone (`pyribs_loop`: sphere.py's scheduler for the row, its
sphere function, its metrics appended after every tell and its archive.csv at the end, without
its heatmap pictures). Our side is the command a user types, writing its folder once at the end
(--log_every the iterations, --pictures false). Both are whole processes timed by the tool library's
farm-bench (paired A/B runs, medians, the ratio A/B pair by pair), on one core, one after the other;
a second, quicker process start-up of pyribs' is in its times too.

pyribs' loop runs twice against ours: as pyribs runs once installed (numba compiling its CMA-ES
code), and like for like (numba off and numpy's kernels held, as the command line runs every
search: docs/performance.md says why).

    python benchmarks/bench_functions.py bench --rows map_elites,cma_me --iterations 1000 --runs 3

One result file, benchmarks/functions_results.json (each row's farm-bench report, and the command).
"""

from __future__ import annotations

import datetime
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# sphere.py's rows (its CONFIG) as our flags: the row names are ours (sphere.py's in brackets).
OUR_FLAGS = {
    "map_elites": "--algorithm map_elites --n_emitters 1 --batch_size 540 --sigma0 0.5",
    "cma_me": "--algorithm cma_me --n_emitters 15 --batch_size 36 --sigma0 0.5",  # (cma_me_imp)
}




def pyribs_variants() -> dict[str, str]:
    """How pyribs' loop is started: as installed, and with the settings the command line holds
    for ours (qdsearch.base.kernels: numba off, numpy's and OpenBLAS's kernels)."""
    sys.path.insert(0, str(ROOT))
    from qdsearch.base.kernels import settings

    held = " ".join(f"{name}={value}" for name, (value, library) in settings().items()
                    if library in ("numba", "numpy"))
    return {"as installed (numba on)": "", "like for like (numba off, kernels held)": f"env {held} "}


def pyribs_scheduler(row: str, dim: int, seed: int):
    """sphere.py's scheduler of the row: a 100 x 100 grid of +-5.12 dim / 2, x0 zeros, each
    emitter seeded from a SeedSequence of the seed."""
    import numpy as np
    from ribs.archives import GridArchive
    from ribs.emitters import EvolutionStrategyEmitter, GaussianEmitter
    from ribs.schedulers import Scheduler

    bound = dim / 2 * 5.12
    archive = GridArchive(solution_dim=dim, dims=(100, 100), ranges=[(-bound, bound)] * 2, seed=seed)
    seeds = np.random.SeedSequence(seed).spawn(15)
    if row == "map_elites":
        emitters = [GaussianEmitter(archive, x0=np.zeros(dim), sigma=0.5, batch_size=540, seed=seeds[0])]
    else:
        emitters = [EvolutionStrategyEmitter(archive, x0=np.zeros(dim), sigma0=0.5, ranker="2imp",
                                             selection_rule="filter", restart_rule="no_improvement",
                                             batch_size=36, seed=s) for s in seeds]
    return Scheduler(archive, emitters)


def sphere(solutions):
    """sphere.py's objective and measures (the gradients it also returns are not asked here)."""
    import numpy as np

    dim, shift = solutions.shape[1], 0.4 * 5.12
    worst = (-5.12 - shift) ** 2 * dim
    objectives = (np.sum(np.square(solutions - shift), axis=1) - worst) / (0.0 - worst) * 100
    clipped = solutions.copy()
    outside = (clipped < -5.12) | (clipped > 5.12)
    clipped[outside] = 5.12 / clipped[outside]
    measures = np.stack([clipped[:, :dim // 2].sum(axis=1), clipped[:, dim // 2:].sum(axis=1)], axis=1)
    return objectives, measures


def pyribs_loop(row: str, iterations: int, outdir: str, dim: int = 100, seed: int = 1) -> None:
    """In a process of its own: sphere.py's main loop without its pictures."""
    scheduler = pyribs_scheduler(row, dim, seed)
    metrics = {"qd_score": [], "coverage": []}
    for _ in range(iterations):
        solutions = scheduler.ask()
        objectives, measures = sphere(solutions)
        scheduler.tell(objectives, measures)
        metrics["qd_score"].append(scheduler.result_archive.stats.qd_score)
        metrics["coverage"].append(scheduler.result_archive.stats.coverage)
    Path(outdir).mkdir(parents=True, exist_ok=True)
    scheduler.result_archive.data(return_type="pandas").to_csv(Path(outdir) / "archive.csv")
    print(json.dumps({name: float(values[-1]) for name, values in metrics.items()}))


def without_paths(text: str, tmp: str) -> str:
    """The result file's text with no path of this machine: the repository's root, the
    interpreter and the temporary folder as a reader types them."""
    return text.replace(f"{ROOT}/", "").replace(sys.executable, "python").replace(tmp, "$TMP")


def bench(rows: str | tuple = "map_elites,cma_me", iterations: int = 1000, runs: int = 3,
          out: str = str(ROOT / "benchmarks" / "functions_results.json")) -> None:
    """Each row: our run (A) against pyribs' loop (B), farm-bench's paired report."""
    results = {"date": datetime.date.today().isoformat(), "command": " ".join(sys.argv),
               "iterations": iterations, "rows": {}}
    with tempfile.TemporaryDirectory() as tmp:
        # Fire reads "a,b" as a tuple
        for row in (rows.split(",") if isinstance(rows, str) else rows):
            ours = (f"{sys.executable} {ROOT / 'lunar_lander.py'} --env sphere --dim 100 --grid 100 "
                    f"{OUR_FLAGS[row]} --iterations {iterations} --log_every {iterations} --pictures false "
                    f"--seed 1 --outdir {tmp}/ours_{row}")
            # each run a new folder: ours must be new or empty
            ours = f"rm -rf {tmp}/ours_{row}; exec {ours}"
            results["rows"][row] = {"ours": ours}
            for variant, environment in pyribs_variants().items():
                loop = f"{sys.executable} {__file__} loop {row} {iterations} {tmp}/pyribs_{row}"
                theirs = f"{environment}{loop}"
                report = subprocess.run(["farm-bench", "-n", str(runs), "--timeout", "3600",
                                         "--vs", f"sh -c '{theirs}'", "--", "sh", "-c", ours],
                                        capture_output=True, text=True, check=True).stdout
                print(f"== {row}, pyribs {variant}\n{report}", flush=True)
                results["rows"][row][variant] = {"pyribs": theirs, "report": report}
    Path(out).write_text(without_paths(json.dumps(results, indent=1), tmp) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    import fire

    fire.Fire({"bench": bench, "loop": pyribs_loop})
