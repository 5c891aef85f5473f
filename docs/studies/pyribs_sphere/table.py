#!/usr/bin/env python
"""The study's table (README.md): each run's final QD score and coverage, recomputed from its
archive.csv and checked against its metrics.json, each row's mean beside pyribs' published mean
and SD (pyribs_table.csv), and the row's z against it.

    python docs/studies/pyribs_sphere/table.py outputs/pyribs_sphere

Writes table.md and table.csv (a line per run) beside this file.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pandas as pd

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))  # the repository's root: qdsearch

import qdsearch  # noqa: E402

CELLS = 10_000  # sphere.py's 100 x 100 grid, and its CVT's cells
PYRIBS_TRIALS = 20
OUTSIDE = 3.0  # |z| beyond which a row falls outside pyribs' (README.md)

# sphere.py's name of each of our settings, by (algorithm, archive); None: not in its table.
SPHERE_PY = {("map_elites", "grid"): "map_elites", ("map_elites", "cvt"): "cvt_map_elites",
             ("line_map_elites", "grid"): "line_map_elites",
             ("line_map_elites", "cvt"): "line_cvt_map_elites",
             ("me_map_elites", "grid"): "me_map_elites", ("cma_me", "grid"): "cma_me_imp",
             ("cma_me_mu", "grid"): "cma_me_imp_mu", ("cma_me_rd", "grid"): "cma_me_rd",
             ("cma_mae", "grid"): "cma_mae", ("ns_cma", "grid"): "ns_cma", ("nslc", "grid"): "nslc",
             ("dds", "grid"): "dds", ("cma_mega", "grid"): "cma_mega", ("cma_maega", "grid"): "cma_maega"}


def run_line(run) -> dict:
    """A run's final numbers from its archive.csv (offset 0: the QD score is the objectives' sum),
    refused unless metrics.json's last row says the same at 10,000 iterations."""
    objectives = run.archive["objective"]
    qd_score, coverage = float(objectives.sum()), len(objectives) / CELLS
    last = run.metrics.iloc[-1]
    if not (math.isclose(last["qd_score"], qd_score, rel_tol=1e-9) and last["num_elites"] == len(objectives)
            and last["iteration"] == 10_000):
        raise SystemExit(f"{run.path}: its metrics.json does not match its archive.csv at 10,000 iterations")
    config = run.config
    return {"algorithm": config["algorithm"], "archive": config["archive"], "setting": run.setting,
            "sphere_py": SPHERE_PY.get((config["algorithm"], config["archive"])), "seed": config["seed"],
            "qd_score": qd_score, "coverage": coverage, "elapsed_s": float(last["elapsed_s"])}


def z_score(ours: pd.Series, mean: float, sd: float) -> float:
    """Our mean's distance from pyribs', in standard errors of the difference (pyribs' SD for
    both); an SD of 0 with any difference: infinite."""
    error = sd * math.sqrt(1 / len(ours) + 1 / PYRIBS_TRIALS)
    difference = float(ours.mean()) - mean
    return difference / error if error else (0.0 if difference == 0 else math.copysign(math.inf, difference))


def row_line(setting: str, runs: pd.DataFrame, published: pd.DataFrame) -> dict:
    first = runs.iloc[0]
    # sphere.py's name of the row (None, read back from the frame as NaN: not in its table)
    theirs_name = first["sphere_py"] if isinstance(first["sphere_py"], str) else None
    line = {"row": first["algorithm"] + (" (CVT)" if first["archive"] == "cvt" else ""),
            "sphere.py": theirs_name or "(not in its table)", "trials": len(runs)}
    for metric, scale, digits in (("qd_score", 1, ",.0f"), ("coverage", 100, ".2f")):
        values = runs[metric] * scale  # the mean, and the range of our trials
        low, mean, high = (f"{value:{digits}}" for value in (values.min(), values.mean(), values.max()))
        line[f"ours: {metric}"] = f"{mean} [{low}, {high}]"
        if theirs_name:
            theirs = published.loc[theirs_name]
            mean, sd = theirs[f"{metric}_mean"], theirs[f"{metric}_sd"]
            line[f"pyribs: {metric}"] = f"{mean * scale:{digits}} ± {sd * scale:{digits}}"
            line[f"z: {metric}"] = round(z_score(runs[metric], mean, sd), 1)
    if theirs_name:
        outside = max(abs(line["z: qd_score"]), abs(line["z: coverage"])) > OUTSIDE
        line["verdict"] = "outside" if outside else "within"
    return line


def markdown(table: pd.DataFrame) -> str:
    """A markdown table (pandas' to_markdown needs tabulate, which is not installed)."""
    rows = [list(table.columns), ["---"] * len(table.columns), *table.astype(str).values.tolist()]
    return "".join("| " + " | ".join(row) + " |\n" for row in rows)


def main(folder: str) -> None:
    lines = pd.DataFrame([run_line(run) for run in qdsearch.read_experiment(folder)])
    lines.to_csv(HERE / "table.csv", index=False)
    published = pd.read_csv(HERE / "pyribs_table.csv", index_col="row")
    table = pd.DataFrame([row_line(setting, runs, published)
                          for setting, runs in lines.groupby("setting", sort=False)])
    (HERE / "table.md").write_text(markdown(table.astype(object).fillna("")))
    print(table.astype(object).fillna("").to_string(index=False))


if __name__ == "__main__":
    main(sys.argv[1])
