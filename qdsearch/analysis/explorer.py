"""The explorer: one self-contained page (explorer_page.html, filled in here) to browse a run's
archive and watch any elite's episode, played from poses recorded on the cluster; a benchmark
function's elite, which has no episode, is shown as its point (bars, or the arm it bends).

Map:
- `explorer_page`: the page with the run's data in a JSON block and a policy that lets only its
  own script run;
- poses (each task family says what they hold), recorded on the workers by `record_poses`
  (`record_flight`), gathered by `flown_flights`; a function's points: `point_flights`;
- `explorer_data` (the page's JSON; `shown_flights`: poses and scene, or points) and the
  `explore` command.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import gymnasium as gym
import numpy as np

from qdsearch.algorithms import cvt_positions, kind_of, task_of
from qdsearch.analysis.run_folder import elite_rows, load_run, shown_terrain
from qdsearch.base.run_files import atomic_write, check_writable, console_log
from qdsearch.config.command_settings import Terrain
from qdsearch.config.options import checked
from qdsearch.config.run_config import RunConfig
from qdsearch.config.settings import ClusterSettings
from qdsearch.search.cluster import dask_client, scheduler_of
from qdsearch.search.engine import gather_with_progress, worker_env
from qdsearch.store.metrics import load_metrics
from qdsearch.tasks import (
    ENVIRONMENTS,
    MEASURES,
    TASKS_OWN,
    Episode,
    episode_of,
    flown_seeds,
    returns_of,
)
from qdsearch.tasks.family import require_drawing, require_one_world
from qdsearch.tasks.policies import LINEAR, Policy, fly

# The explorer's page: plain HTML, CSS and JavaScript, no library, nothing fetched; `explore`
# fills in its /*DATA*/ (the run's data) and /*POLICY*/ (its Content-Security-Policy).
EXPLORER_PAGE = Path(__file__).with_name("explorer_page.html")
# In the data block, what could end it or start markup is written as a JSON escape (JSON.parse
# reads it back as the same character): the data can't close its <script>, whatever a run
# folder's name holds. json.dumps already escapes U+2028 and U+2029 (ensure_ascii).
JSON_IN_HTML = {ord("<"): "\\u003c", ord(">"): "\\u003e", ord("&"): "\\u0026"}


def explorer_page(data: dict) -> str:
    """The page with the run's data in a JSON block that no browser executes, and a policy that
    lets only the page's own script run (by its hash): no inline handler, no other script, nothing
    fetched. So nothing a run's name or label holds can run when the page is opened."""
    import base64
    import hashlib
    import re

    page = EXPLORER_PAGE.read_text()
    code = re.search(r"<script>(.*?)</script>", page, re.DOTALL)[1]
    digest = base64.b64encode(hashlib.sha256(code.encode()).digest()).decode()
    policy = (f"default-src 'none'; script-src 'sha256-{digest}'; style-src 'unsafe-inline'; "
              f"img-src data:; base-uri 'none'; form-action 'none'")
    block = json.dumps(data, separators=(",", ":")).translate(JSON_IN_HTML)
    return page.replace("/*POLICY*/", policy, 1).replace("/*DATA*/", block, 1)

# The explorer page: every elite's episode, recorded as poses and packed into the page. Per step,
# the task family's `pose` gives what its scene's bodies are placed by, quantised to int16 (the
# family's `pose_scale`: units per metre or radian; its `pose_angles` wrapped to [-pi, pi]) and
# sent as base64; the page decodes them into an Int16Array.

def record_poses(solutions: np.ndarray, env_seeds: list[int], env_name: str, policy: Policy = LINEAR,
                 episode: Episode = TASKS_OWN) -> list[np.ndarray]:
    """Runs on a worker: each solution's episode as quantised poses (steps + 1, pose size), the
    reset's pose first, flown as `policy` from its reset seed in the env `rollout` flies it in."""
    env = worker_env(env_name, True, episode)
    return [record_flight(solution, seed, env, env_name, policy)
            for solution, seed in zip(solutions, env_seeds)]


def record_flight(solution: np.ndarray, env_seed: int, env: gym.Env, env_name: str,
                  policy: Policy = LINEAR) -> np.ndarray:
    family = ENVIRONMENTS[env_name].family
    env.reset(seed=env_seed)
    poses = [family.pose(env, None)]  # reset's; fly resets again, to the same pose
    fly(solution, env_seed, env, on_step=lambda action, obs: poses.append(family.pose(env, action)),
        env_name=env_name, policy=policy)
    values = np.array(poses)
    angles = list(family.pose_angles)
    values[:, angles] = (values[:, angles] + np.pi) % (2 * np.pi) - np.pi
    return np.clip(np.round(values * family.pose_scale), -32767, 32767).astype("<i2")


PAGE_BINS = 50  # a CVT archive's map on the page: its first two measures' ranges cut 50 x 50


def page_cells(archive, indices: np.ndarray) -> tuple[list[int], np.ndarray]:
    """The page's map and each elite's cell on it: a grid's own cells; for a CVT archive, the bin
    of its cell's centroid (the best elite of a bin is shown, as over a grid's third measure)."""
    if kind_of(archive) != "cvt":
        return [int(d) for d in archive.dims], archive.int_to_grid_index(indices)
    bins = np.clip((cvt_positions(archive, indices)[:, :2] * PAGE_BINS).astype(int), 0, PAGE_BINS - 1)
    return [PAGE_BINS] * min(2, archive.measure_dim), bins


def packed(values: np.ndarray) -> str:
    """An array's bytes in base64, as the page decodes them into a typed array."""
    import base64

    return base64.b64encode(values.tobytes()).decode()


def point_flights(rows: dict) -> list[np.ndarray]:
    """A benchmark function's elites as the page draws them: no episode, each a 'flight' of one
    pose, the point itself (float32: what the page draws)."""
    return [np.asarray(solution, dtype="<f4")[None, :] for solution in rows["solution"]]


def shown_flights(task, flights: list[np.ndarray], env_seed: int) -> dict:
    """The page's data of what it draws: an episode's packed poses and its scene, or a benchmark
    function's points and how its family draws one (`point_view`)."""
    if task.function:
        points = np.concatenate(flights)
        return {"poses": "", "pose_scale": [], "world": {"episode": "The elite's point"},
                "point": {**task.family.point_view, "dim": int(points.shape[1]), "values": packed(points)}}
    return {"poses": packed(np.concatenate(flights)), "pose_scale": list(task.family.pose_scale),
            "world": task.family.scene(env_seed, task)}


def explorer_data(archive, config: RunConfig, rows: dict, flights: list[np.ndarray], env_seed: int,
                  run_dir: Path, metrics: list[dict]) -> dict:
    """What the page shows, as JSON: cells with their elites, packed flights (a benchmark
    function's: its points), the seed they were flown on (named as the task's family names it),
    curves."""
    import matplotlib

    offsets = np.cumsum([0, *(len(poses) for poses in flights)])
    dims, grid = page_cells(archive, rows["index"])
    robust = {}
    if (run_dir / "robustness.csv").is_file():
        import pandas as pd

        with contextlib.suppress(OSError, ValueError, KeyError):
            table = pd.read_csv(run_dir / "robustness.csv")
            robust = {int(r["cell_index"]): (float(r["mean_objective"]), float(r["solved_share"]))
                      for r in table.to_dict("records")}
    elites = [{"index": int(index), "gx": int(cell[0]), "gy": int(cell[1]) if len(cell) > 1 else 0,
               "objective": float(objective), "measures": [float(m) for m in measures],
               "offset": int(offset), "steps": int(len(poses) - 1),
               **({"robust": robust[int(index)]} if int(index) in robust else {})}
              for index, cell, objective, measures, offset, poses
              in zip(rows["index"], grid, rows["objective"], rows["measures"], offsets, flights)]
    magma, task = matplotlib.colormaps["magma"], task_of(config)
    return {
        "run": str(run_dir), "algorithm": config.algorithm, "env_seed": env_seed,
        "seed_noun": task.family.seed_noun,  # the page's words for env_seed ("terrain 52")
        "env": config.env,
        "measures": [{"name": name, "label": MEASURES[name].label, "descending": MEASURES[name].descending,
                      "range": [float(lo), float(hi)]}
                     for name, lo, hi in zip(config.measures, archive.lower_bounds, archive.upper_bounds)],
        "dims": dims, "heat_range": list(returns_of(config).heat),
        "colormap": [matplotlib.colors.to_hex(magma(i / 255)) for i in range(256)],
        "elites": elites, **shown_flights(task, flights, env_seed),
        "metrics": [{k: row.get(k) for k in ("iteration", "evaluations", "qd_score", "coverage",
                                             "best_objective")} for row in metrics],
        "robustness": bool(robust),
    }


def flown_flights(rows: dict, config: RunConfig, shown: int, workers: int,
                  scheduler_address: str | None) -> list[np.ndarray]:
    """Every elite flown again on the cluster, on the env seed shown, its poses recorded."""
    with dask_client(workers, scheduler_address, console_log()) as client:
        chunks = np.array_split(rows["solution"], max(1, min(len(rows["solution"]) // 25, 64)))
        futures = [client.submit(record_poses, chunk, flown_seeds(chunk, shown, config), config.env,
                                 config.network, episode_of(config), pure=False, retries=3)
                   for chunk in chunks]
        return [flight for chunk in gather_with_progress(client, futures) for flight in chunk]


def explore(run_dir: Path, terrain: Terrain, cluster: ClusterSettings) -> None:
    """Write RUN_DIR/explorer.html, every elite flown again on the cluster `cluster` names, on
    the env seed `terrain` names, to record its poses: one self-contained page to browse the
    archive and watch any elite's episode."""
    archive, config = load_run(run_dir)
    task = task_of(config)
    require_drawing(task.family, "explore", points=bool(task.function))
    require_one_world(task.family, config.reset, "explore")
    shown = shown_terrain(config, terrain.env_seed)
    workers, run = checked("workers", cluster.workers), run_dir
    metrics = load_metrics(run)  # a corrupt file is refused before the elites are flown
    check_writable(run)
    scheduler_address = scheduler_of(cluster)
    rows = elite_rows(archive)
    flights = (point_flights(rows) if task.function  # a point: no episode, no cluster
               else flown_flights(rows, config, shown, workers, scheduler_address))
    data = explorer_data(archive, config, rows, flights, shown, run, metrics)
    page = explorer_page(data)
    atomic_write(run / "explorer.html", lambda f: f.write(page), mode="w")
    size = (run / "explorer.html").stat().st_size
    shown_as = "each its point" if task.function else f"{sum(len(poses) for poses in flights):,} poses"
    print(f"{len(rows['index'])} elites, {shown_as}: wrote {run / 'explorer.html'} ({size / 1e6:.1f} MB); "
          "open it in a browser")
