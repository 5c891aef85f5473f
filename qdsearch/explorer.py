"""The explorer: one self-contained page (explorer_page.html, filled in here) to browse a run's
archive and watch any elite's episode, played from poses recorded on the cluster.

Map:
- `explorer_page`: the page with the run's data in a JSON block and a policy that lets only its
  own script run;
- poses, per family of tasks: `POSE_SCALE`, `ANGLES`, `POSES` (`lander_pose` with
  `engine_powers`, `walker_pose`), recorded on the workers by `record_poses` (`record_flight`);
- the world around them, per family: `WORLDS` (`lander_world`, `walker_world`);
- `explorer_data` (the page's JSON) and the `explore` command.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d import lunar_lander as upstream

from qdsearch.algorithms import task_of
from qdsearch.cluster import dask_client, scheduler_of
from qdsearch.engine import gather_with_progress, worker_env
from qdsearch.fast_env import FPS, HEIGHT, HELIPAD_Y, SCALE, WIDTH, seeded_randoms
from qdsearch.flags import takes
from qdsearch.options import CLUSTER_FLAGS, TERRAIN_FLAGS, checked
from qdsearch.plots import HEATMAP_RANGE
from qdsearch.results import elite_rows, load_run, shown_terrain
from qdsearch.run import load_metrics
from qdsearch.run_files import atomic_write, check_writable, console_log
from qdsearch.tasks import (
    ENVIRONMENTS,
    LEFT,
    MAIN,
    MEASURES,
    RIGHT,
    burn,
    fly,
    make_env,
)

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

# The explorer page: every elite's flight, recorded as poses and packed into the page. Per step,
# a family's pose gives the drawing, quantised to int16 (POSE_SCALE: units per metre or radian;
# angles wrapped to [-pi, pi]) and sent as base64; the page decodes them into an Int16Array.
# - lander: x, y and angle, the two legs' angles (a leg hangs from the lander's centre by its
#   joint, so its position follows from its angle), the main engine's power (0, or 0.5 to 1) and
#   the side engines' (negative: the left one): 1 mm and 0.1 mrad, ~14 bytes a step, ~9 MB for a
#   full 300-iteration archive (~615,000 steps);
# - walker: the hull's and the four leg segments' x, y and angle: 1 cm (the course is ~90 m)
#   and 0.1 mrad, 30 bytes a step.
POSE_SCALE = {"lander": (1e3, 1e3, 1e4, 1e4, 1e4, 1e4, 1e4), "walker": (1e2, 1e2, 1e4) * 5}
ANGLES = {"lander": [2, 3, 4], "walker": [2, 5, 8, 11, 14]}  # the pose's columns that are angles


def engine_powers(action: Any) -> tuple[float, float]:
    """The lander's (main, side) engine powers of an action: a discrete one fires one engine at
    full power; a continuous one as tasks.burn weighs it (side < 0: the left engine)."""
    if action is None:
        return 0.0, 0.0
    if np.ndim(action) == 0:
        return {MAIN: (1.0, 0.0), LEFT: (0.0, -1.0), RIGHT: (0.0, 1.0)}.get(int(action), (0.0, 0.0))
    firings = [0.0] * 4
    burn(firings, action)
    return firings[MAIN], firings[RIGHT] - firings[LEFT]


def lander_pose(env: gym.Env, action: Any) -> list[float]:
    lander = env.unwrapped
    return [lander.lander.position.x, lander.lander.position.y, lander.lander.angle,
            lander.legs[0].angle, lander.legs[1].angle, *engine_powers(action)]


def walker_pose(env: gym.Env, action: Any) -> list[float]:
    walker = env.unwrapped
    return [value for body in (walker.hull, *walker.legs)
            for value in (body.position.x, body.position.y, body.angle)]


POSES = {"lander": lander_pose, "walker": walker_pose}


def record_poses(solutions: np.ndarray, env_seed: int, env_name: str) -> list[np.ndarray]:
    """Runs on a worker: each solution's episode as quantised poses (steps + 1, pose size), the
    reset's pose first, flown in the env `rollout` flies it in."""
    env = worker_env(env_name, True)
    return [record_flight(solution, env_seed, env, env_name) for solution in solutions]


def record_flight(solution: np.ndarray, env_seed: int, env: gym.Env, env_name: str) -> np.ndarray:
    family = ENVIRONMENTS[env_name].family
    pose = POSES[family]
    env.reset(seed=env_seed)
    poses = [pose(env, None)]  # reset's; fly resets again, to the same pose
    fly(solution, env_seed, env, on_step=lambda action, obs: poses.append(pose(env, action)),
        env_name=env_name)
    values = np.array(poses)
    angles = ANGLES[family]
    values[:, angles] = (values[:, angles] + np.pi) % (2 * np.pi) - np.pi
    return np.clip(np.round(values * POSE_SCALE[family]), -32767, 32767).astype("<i2")


def lander_world(env_seed: int, env_name: str) -> dict:
    """What the page draws around a lander: the terrain, the helipad, the lander's shape."""
    edges, _, _ = seeded_randoms(env_seed)
    return {"width": WIDTH, "height": HEIGHT, "scale": SCALE, "helipad_y": HELIPAD_Y,
            "helipad_x": [edges[3][1][0], edges[5][1][0]],
            "ground": [edges[0][0], *(end for _, end in edges)],
            "lander": [[x / SCALE, y / SCALE] for x, y in upstream.LANDER_POLY],
            "leg": [upstream.LEG_AWAY / SCALE, upstream.LEG_DOWN / SCALE, upstream.LEG_W / SCALE,
                    upstream.LEG_H / SCALE], "fps": FPS}


def walker_world(env_seed: int, env_name: str) -> dict:
    """What the page draws around a walker: the ground's polygons (grass, pits, stairs' outline),
    the hardcore course's obstacles (stumps, stair steps, pit walls: bodies of their own, drawn
    as the env draws them), the hull's shape and the leg segments' half sizes."""
    import Box2D
    from gymnasium.envs.box2d import bipedal_walker as walker

    def points(vertices) -> list[list[float]]:
        return [[round(float(x), 4), round(float(y), 4)] for x, y in vertices]

    env = make_env(False, env_name=env_name)
    env.reset(seed=env_seed)
    terrain = [points(poly) for poly, _ in env.unwrapped.terrain_poly]
    obstacles = [points(body.transform * vertex for vertex in fixture.shape.vertices)
                 for body in env.unwrapped.terrain for fixture in body.fixtures
                 if isinstance(fixture.shape, Box2D.b2PolygonShape)]
    env.close()
    return {"width": walker.VIEWPORT_W / walker.SCALE, "height": walker.VIEWPORT_H / walker.SCALE,
            "terrain": terrain, "obstacles": obstacles,
            "hull": [[x / walker.SCALE, y / walker.SCALE] for x, y in walker.HULL_POLY],
            "legs": [[walker.LEG_W / 2, walker.LEG_H / 2], [0.8 * walker.LEG_W / 2, walker.LEG_H / 2]] * 2,
            "fps": walker.FPS}


WORLDS = {"lander": lander_world, "walker": walker_world}


def explorer_data(archive, config: dict, rows: dict, flights: list[np.ndarray], env_seed: int,
                  run_dir: Path, metrics: list[dict]) -> dict:
    """What the page shows, as JSON: cells with their elites, packed flights, terrain, curves."""
    import base64

    import matplotlib

    offsets = np.cumsum([0, *(len(poses) for poses in flights)])
    grid = archive.int_to_grid_index(rows["index"])
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
    magma, family = matplotlib.colormaps["magma"], task_of(config).family
    return {
        "run": str(run_dir), "algorithm": config["algorithm"], "env_seed": env_seed,
        "env": config["env"], "kind": family,
        "measures": [{"name": name, "label": MEASURES[name].label, "descending": MEASURES[name].descending,
                      "range": [float(lo), float(hi)]}
                     for name, lo, hi in zip(config["measures"], archive.lower_bounds, archive.upper_bounds)],
        "dims": [int(d) for d in archive.dims], "heat_range": list(HEATMAP_RANGE),
        "colormap": [matplotlib.colors.to_hex(magma(i / 255)) for i in range(256)],
        "elites": elites, "pose_scale": list(POSE_SCALE[family]),
        "poses": base64.b64encode(np.concatenate(flights).tobytes()).decode(),
        "world": WORLDS[family](env_seed, config["env"]),
        "metrics": [{k: row.get(k) for k in ("iteration", "evaluations", "qd_score", "coverage",
                                             "best_objective")} for row in metrics],
        "robustness": bool(robust),
    }


@takes(CLUSTER_FLAGS, TERRAIN_FLAGS)
def explore(run_dir: str, **flags: Any) -> None:
    """Write RUN_DIR/explorer.html: one self-contained page to browse the archive and watch any
    landing. It opens offline in any current browser (no server, nothing fetched): the heatmap
    (hover a cell for its numbers, click it to watch its elite land), a sortable table of the best
    elites, and the run's progress curves. Every elite is flown again on the cluster to record its
    poses, so the page plays exactly the flight that `video` renders.

    Args:
        run_dir: A run folder written by this script.
    """
    env_seed, workers = flags["env_seed"], flags["workers"]
    archive, config = load_run(run_dir)
    shown = shown_terrain(config, env_seed)
    workers, run = checked("workers", workers), Path(str(run_dir))
    metrics = load_metrics(run)  # a corrupt file is refused before the elites are flown
    check_writable(run)
    scheduler_address = scheduler_of(flags)
    rows = elite_rows(archive)
    with dask_client(workers, scheduler_address, console_log()) as client:
        chunks = np.array_split(rows["solution"], max(1, min(len(rows["solution"]) // 25, 64)))
        futures = [client.submit(record_poses, chunk, shown, config["env"], pure=False, retries=3)
                   for chunk in chunks]
        flights = [flight for chunk in gather_with_progress(client, futures) for flight in chunk]
    data = explorer_data(archive, config, rows, flights, shown, run, metrics)
    page = explorer_page(data)
    atomic_write(run / "explorer.html", lambda f: f.write(page), mode="w")
    size = (run / "explorer.html").stat().st_size
    print(f"{len(rows['index'])} elites, {sum(len(poses) for poses in flights):,} poses: wrote "
          f"{run / 'explorer.html'} ({size / 1e6:.1f} MB); open it in a browser")
