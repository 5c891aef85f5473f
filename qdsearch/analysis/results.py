"""Looking at a finished run: videos of chosen elites, the elite table and flight paths (the
explorer page is explorer.py's). None of these commands changes the run's archive.

Map:
- choosing elites (a Selection of command_settings.py): `parse_cells`, `parse_indices`,
  `select_elites`, `load_chosen_elites` (the run read by run_folder.py's readers);
- `video` (`Mp4Recorder`, `record_video`, `reflown`: each elite flown again must score exactly
  its stored objective), `elites` (`elite_table`, `solved_count`), `trajectories` (`fly_paths`,
  `path_figure`, `save_trajectory_plot`: the ground and axes drawn by the task's family);
  `add_to_index`: video and trajectories add to their index tables, never drop a row.
(`evaluate`, the elites flown on other terrains or seeds, is evaluation.py's.)
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import math
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from qdsearch.algorithms import ARCHIVES, kind_of
from qdsearch.analysis.run_folder import elite_rows, load_run, shown_terrain
from qdsearch.base.flags import UsageError, named, shown
from qdsearch.base.run_files import RunError, atomic_write, check_writable, fault_text, write_csv
from qdsearch.base.stopping import STOP
from qdsearch.config.command_settings import EliteFilter, Selection, Terrain
from qdsearch.config.run_config import RunConfig
from qdsearch.search.engine import averaged, per_terrain
from qdsearch.tasks import (
    ENVIRONMENTS,
    MEASURES,
    TASKS_OWN,
    Episode,
    episode_of,
    flown_seeds,
    make_env,
    renderer_missing,
    reset_seeds,
    returns_of,
)
from qdsearch.tasks.family import require_one_world
from qdsearch.tasks.policies import LINEAR, Policy, fly, rollout


def is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def parse_cells(cells: Any, measures: list[str]) -> list[tuple[float, ...]]:
    """--cells as points in the run's measures. Fire hands over what it could parse (a list of
    tuples, or one tuple) and the raw text otherwise, so both are accepted."""
    import ast

    points, size = cells, len(measures)
    if isinstance(points, str):
        with contextlib.suppress(ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            points = ast.literal_eval(points)
    if isinstance(points, (int, float)) and size == 1:
        points = [(points,)]
    if isinstance(points, (tuple, list)) and points and all(map(is_number, points)):
        points = [points] if len(points) == size or size > 1 else [(p,) for p in points]
    if not (isinstance(points, (tuple, list)) and points and all(
            isinstance(p, (tuple, list)) and len(p) == size and all(map(is_number, p)) for p in points)):
        example = "(" + ", ".join(f"{sum(MEASURES[m].range) / 2:g}" for m in measures) + ")"
        raise UsageError(f"{named('cells')} takes points of ({', '.join(measures)}) such as "
                         f'"[{example}]", got {shown(cells)}')
    return [tuple(float(v) for v in point) for point in points]


def parse_indices(index: Any, archive) -> list[int]:
    """--index as one archive cell index or several (the cell_index column of `elites`)."""
    values = list(index) if isinstance(index, (tuple, list)) else [index]
    cells = int(archive.cells)
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < cells:
            raise UsageError(f"{named('index')} takes cell indices from 0 to {cells - 1} (see the elites "
                             f"command's cell_index), got {shown(index)}")
    return values


def point_text(point) -> str:
    return "(" + ", ".join(f"{value:g}" for value in point) + ")"


def check_in_archive(archive, point: tuple[float, ...], measures: list[str]) -> None:
    ranges = ", ".join(f"{name} in [{lo:g}, {hi:g}]" for name, lo, hi in
                       zip(measures, archive.lower_bounds, archive.upper_bounds))
    if not all(lo <= p <= hi for p, lo, hi in zip(point, archive.lower_bounds, archive.upper_bounds)):
        raise UsageError(f"cell {point_text(point)} is outside the archive: {ranges}")


def pick(rows: dict[str, np.ndarray], i: int, name: str) -> dict:
    return {"name": name, **{field: values[i] for field, values in rows.items()}}


def nearest_occupied(archive, point: tuple[float, ...]) -> dict:
    """The elite whose cell is nearest the point's cell (ties: lowest index): counting in cells on
    a grid, between centroids (in units of the ranges) in a CVT archive."""
    rows, positions = elite_rows(archive), ARCHIVES[kind_of(archive)]["positions"]
    target = positions(archive, np.array([archive.index_of_single(point)]))[0]
    distance = np.linalg.norm(positions(archive, rows["index"]) - target, axis=1)
    return pick(rows, int(np.lexsort((rows["index"], distance))[0]), "")


def describe_elite(elite: dict, measures: list[str]) -> str:
    values = ", ".join(f"{name} {value:.3f}" for name, value in zip(measures, elite["measures"]))
    return f"objective {elite['objective']:.2f}, {values} (cell {elite['index']})"


def file_tag(point, measures: list[str]) -> str:
    """A point in the measures as a file-name part: x-0.40_v-0.10 (the MEASURES short names)."""
    return "_".join(f"{MEASURES[name].short}{value:.2f}" for name, value in zip(measures, point))


def elite_of_cell(archive, point: tuple[float, ...], measures: list[str], nearest: bool) -> dict:
    """The elite of the cell holding `point`, as archive.retrieve_single finds it; for an empty
    cell, the nearest occupied one if asked (else the error names it)."""
    check_in_archive(archive, point, measures)
    name = f"cell_{file_tag(point, measures)}"
    occupied, elite = archive.retrieve_single(point)
    if occupied:
        return {"name": name, **elite}
    near = nearest_occupied(archive, point)
    empty = f"the cell of {point_text(point)} (index {archive.index_of_single(point)}) is empty"
    if not nearest:
        raise UsageError(f"{empty}; the nearest occupied cell holds {describe_elite(near, measures)}; "
                         f"add {named('nearest')} to use it")
    print(f"{empty}; using the nearest occupied cell: {describe_elite(near, measures)}")
    return {**near, "name": f"{name}_nearest{near['index']}"}


def select_elites(archive, cells: Any = None, best: bool = False, top: int | None = None,
                  index: Any = None, nearest: bool = False, *, measures: list[str]) -> list[dict]:
    """The elites a results command shows (a Selection's fields, checked), each named for its
    file: the cells of the points `cells`, the best, the `top` K by objective, the cells of
    `index`, in that order."""
    measures = list(measures)
    if cells is None and not best and top is None and index is None:
        raise UsageError(f"choose elites with {named('cells')}, {named('best')}, {named('top')} or "
                         f"{named('index')}")
    rows, chosen = elite_rows(archive), []
    if cells is not None:
        chosen += [elite_of_cell(archive, point, measures, nearest)
                   for point in parse_cells(cells, measures)]
    if best:
        chosen.append(pick(rows, 0, "best"))
    if top is not None:
        chosen += [pick(rows, i, f"top{i + 1:02d}")
                   for i in range(min(top, len(rows["index"])))]
    if index is not None:
        where = {int(cell): i for i, cell in enumerate(rows["index"])}
        for cell in parse_indices(index, archive):
            if cell not in where:
                raise UsageError(f"cell index {cell} is empty (the elites command lists the occupied ones)")
            chosen.append(pick(rows, where[cell], f"index{cell}"))
    for elite in chosen:
        if not elite["name"].startswith("cell_"):
            elite["name"] += f"_{file_tag(elite['measures'], measures)}"
        elite["name"] += f"_obj{elite['objective']:.0f}"
    return chosen


class Mp4Recorder(gym.Wrapper):
    """Streams the frame after reset and after every step into an mp4 at the env's 50 fps, with
    imageio-ffmpeg. Not gymnasium's RecordVideo: it keeps every frame in memory, and its moviepy
    2.2 writer drops the last frame (the landing) whenever 1/fps summed over the frames falls
    short of their count (212 frames -> 4.2399999 s -> 211 written)."""

    def __init__(self, env: gym.Env, path: Path) -> None:
        super().__init__(env)
        self.path, self.frames, self._writer = path, 0, None

    def reset(self, **kwargs):
        result = self.env.reset(**kwargs)
        self._write_frame()
        return result

    def step(self, action):
        result = self.env.step(action)
        self._write_frame()
        return result

    def _write_frame(self) -> None:
        import imageio_ffmpeg

        frame = rendered(self.env)
        if self._writer is None:  # macro_block_size 8: 600x400 is encoded as is, not rescaled
            self._writer = imageio_ffmpeg.write_frames(
                str(self.path), (frame.shape[1], frame.shape[0]), fps=self.metadata["render_fps"],
                codec="libx264", pix_fmt_out="yuv420p", macro_block_size=8,
                ffmpeg_log_level="quiet")  # a failure is reported once, in one line (record_video)
            self._writer.send(None)
        self._writer.send(np.ascontiguousarray(frame))
        self.frames += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        super().close()


def rendered(env: gym.Env) -> np.ndarray:
    """The env's frame; a MuJoCo renderer whose library is missing is one line naming it."""
    try:
        return env.render()
    except gym.error.DependencyNotInstalled as error:  # pygame, say, for a Box2D or classic env
        raise UsageError(f"cannot draw {env.spec.id if env.spec else 'the env'}: {error}") from None
    except (ImportError, AttributeError, RuntimeError, OSError) as error:
        if not hasattr(env.unwrapped, "mujoco_renderer"):
            raise
        raise renderer_missing(error) from None


def load_chosen_elites(run_dir: Path, selection: Selection,
                       terrain: Terrain) -> tuple[RunConfig, list[dict], int]:
    """The run's config, the elites `selection` picks from its archive, and the terrain to show
    them on: the env seed `terrain` names, by default the run's first."""
    archive, config = load_run(run_dir)
    shown = shown_terrain(config, terrain.env_seed)
    check_writable(run_dir)  # before any elite is flown
    return config, select_elites(archive, **dataclasses.asdict(selection), measures=config.measures), shown


def reflown(elite: dict, config: RunConfig) -> tuple[float, list[float]]:
    """The elite flown again in its run's setting (every terrain, averaged as the engine does):
    rollouts are deterministic, so this is exactly its stored objective and measures."""
    env = make_env(config.fast_env, env_name=config.env, episode=episode_of(config))
    seeds, policy = reset_seeds(elite["solution"][None], config), config.network
    rows = [np.array([rollout(elite["solution"], int(seed), env, config.measures, env_name=config.env,
                              policy=policy) for seed in seeds[0]])]
    objectives, measures = averaged(per_terrain(rows, seeds))
    return float(objectives[0]), measures[0].tolist()


def record_video(solution: np.ndarray, env_seed: int, path: Path, env_name: str, policy: Policy = LINEAR,
                 episode: Episode = TASKS_OWN) -> None:
    """Fly a policy on the plain env, rendered headless (rgb_array) into an mp4 of episode length
    + 1 frames (the reset's frame first); written aside and moved into place whole."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=path.parent, prefix=".recording.") as tmp:
            env = Mp4Recorder(make_env(False, "rgb_array", env_name=env_name, episode=episode),
                              Path(tmp) / "flight.mp4")
            try:
                fly(solution, env_seed, env, env_name=env_name, policy=policy)
            finally:
                env.close()
            os.replace(env.path, path)
    except OSError as error:
        # When ffmpeg fails, Python sees only a broken pipe: a full disk is the usual cause.
        full = shutil.disk_usage(path.parent).free < 2**20 if path.parent.exists() else False
        cause = os.strerror(errno.ENOSPC) if full else fault_text(error)
        raise RunError(f"cannot write {path}: {cause}") from None


def video(run_dir: Path, selection: Selection, terrain: Terrain) -> None:
    """An mp4 per elite `selection` picks, flown on the env seed `terrain` names, into
    RUN_DIR/videos/ (listed in videos/index.csv); each elite flown again in its run's setting
    must score exactly its stored objective and measures (a warning says if not)."""
    config, chosen, shown = load_chosen_elites(run_dir, selection, terrain)
    folder, rows, measures = run_dir / "videos", [], config.measures
    for elite in chosen:
        STOP.check()  # Ctrl-C is acted on between videos (main defers it, see StopRequests)
        path, (seed,) = folder / f"{elite['name']}.mp4", flown_seeds(elite["solution"][None], shown, config)
        record_video(elite["solution"], seed, path, config.env, config.network, episode_of(config))
        print(f"{path}: {describe_elite(elite, measures)}")
        objective, values = reflown(elite, config)
        reproduced = objective == elite["objective"] and values == list(elite["measures"])
        if not reproduced:
            print(f"warning: flown again, {path.name} scored {objective!r} with measures {values}, "
                  f"not the stored {elite['objective']!r}, {list(elite['measures'])} "
                  f"(other library versions?)", file=sys.stderr)
        rows.append({"video": path.name, "env_seed": shown, "reset_seed": seed,
                     "cell_index": int(elite["index"]),
                     "objective": float(elite["objective"]),
                     **{name: float(value) for name, value in zip(measures, elite["measures"])},
                     "reflown_objective": objective, "reproduced": reproduced})
    add_to_index(folder / "index.csv", rows, "video")


def add_to_index(path: Path, rows: list[dict], key: str) -> None:
    """Add `rows` to the index table at `path`: an earlier call's rows stay (their files do too),
    and a row of a file written again replaces its old row (matched by its `key` column)."""
    import pandas as pd

    table = pd.DataFrame(rows)
    if path.is_file():
        try:
            earlier = pd.read_csv(path)
        except (OSError, ValueError, pd.errors.ParserError) as error:
            raise UsageError(f"{path}: unreadable ({fault_text(error)}); move it aside to start a new "
                             f"index") from None
        if key in earlier:
            table = pd.concat([earlier[~earlier[key].isin(table[key])], table], ignore_index=True)
    write_csv(path, table)


def elite_table(archive, measures: list[str], min_objective: float | None = None,
                top: int | None = None):
    """The archive's elites as a table (archive.data), best first, filtered and cut; the columns
    are named after the run's measures."""
    table = archive.data(["objective", "measures", "index"], return_type="pandas")
    table = table.sort_values(["objective", "index"], ascending=[False, True], ignore_index=True)
    if min_objective is not None:
        table = table[table["objective"] >= min_objective]
    if top is not None:
        table = table.head(top)
    columns = {"objective": "objective", **{f"measures_{i}": name for i, name in enumerate(measures)},
               "index": "cell_index"}
    return table.rename(columns=columns)[list(columns.values())].reset_index(drop=True)


def elites(run_dir: Path, chosen: EliteFilter) -> None:
    """Print the run's elites that `chosen` keeps, sorted by objective, and write them to
    RUN_DIR/elites.csv."""
    archive, config = load_run(run_dir)
    table = elite_table(archive, config.measures, chosen.min_objective, chosen.top)
    path = run_dir / "elites.csv"
    write_csv(path, table)
    print(table.to_string(index=False, float_format=lambda value: f"{value:.3f}")
          if len(table) else "no elites match")
    print(f"{len(table)} of {len(archive)} elites{solved_count(archive, config)}; written to {path}")


def solved_count(archive, config: RunConfig) -> str:
    """How many elites score the task's solved return or more, in its family's words: " (3 score
    200 or more: good landings)"."""
    task, least = ENVIRONMENTS[config.env], returns_of(config).solved
    solved = int((archive.data("objective") >= least).sum())
    return f" ({solved} score {least:g} or more: {task.family.solved_words})"


def fly_paths(chosen: list[dict], env_seed: int | list[int], env_name: str, policy: Policy = LINEAR,
              episode: Episode = TASKS_OWN) -> list[tuple[np.ndarray, int]]:
    """Each elite's path and the step marked on it, as its task's family draws them (the lander's
    (x, y) per step and its touchdown; the walker's hull and its last step), flown from
    `env_seed`'s reset (or each elite from its own, a list)."""
    env, paths, family = make_env(env_name=env_name, episode=episode), [], ENVIRONMENTS[env_name].family
    seeds = env_seed if isinstance(env_seed, list) else [env_seed] * len(chosen)
    for elite, seed in zip(chosen, seeds):
        STOP.check()
        path: list = []
        summary = fly(elite["solution"], seed, env, path, env_name=env_name, policy=policy)
        paths.append((np.array(path), family.marked_step(summary) - 1))
    return paths


def path_figure(chosen: list[dict], paths: list[tuple[np.ndarray, int]]):
    """A figure with each path coloured by its elite's objective and its marked step as a dot."""
    import matplotlib.pyplot as plt
    from matplotlib import cm, colors

    objectives = [float(elite["objective"]) for elite in chosen]
    norm = colors.Normalize(min(objectives) - 1e-9, max(objectives) + 1e-9)
    cmap = plt.get_cmap("viridis")
    fig, ax = plt.subplots(figsize=(11, 7))
    for elite, (path, step) in zip(chosen, paths):
        colour = cmap(norm(float(elite["objective"])))
        ax.plot(path[:, 0], path[:, 1], color=colour, lw=1.2, alpha=0.9,
                label=elite["name"] if len(chosen) <= 12 else None)
        ax.plot(*path[step], marker="o", ms=7, mec="black", color=colour, zorder=3)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, label="Objective", shrink=0.8)
    return fig, ax


def save_trajectory_plot(chosen: list[dict], paths: list[tuple[np.ndarray, int]], env_seed: int,
                         path: Path, env_name: str) -> None:
    """The chosen elites' paths on one page, drawn as their task's family draws them."""
    import matplotlib.pyplot as plt

    fig, ax = path_figure(chosen, paths)
    task = ENVIRONMENTS[env_name]
    title = task.family.draw_paths(ax, paths, env_seed, task)
    ax.set_title(title.format(len(chosen), env_seed))
    ax.legend(fontsize=7, loc="upper left")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100, bbox_inches="tight"))
    plt.close(fig)


def trajectories(run_dir: Path, selection: Selection, terrain: Terrain) -> None:
    """The paths of the elites `selection` picks, flown on the env seed `terrain` names, as their
    task's family draws them: RUN_DIR/trajectories.png, each drawing kept in
    RUN_DIR/trajectories/ and listed in its index.csv."""
    config, chosen, shown = load_chosen_elites(run_dir, selection, terrain)
    require_one_world(ENVIRONMENTS[config.env].family, config.reset, "trajectories")
    path, kept = run_dir / "trajectories.png", run_dir / "trajectories"
    seeds = flown_seeds(np.array([elite["solution"] for elite in chosen]), shown, config) if chosen else []
    paths = fly_paths(chosen, seeds, config.env, config.network, episode_of(config))
    save_trajectory_plot(chosen, paths, shown, path, config.env)
    kept.mkdir(exist_ok=True)
    drawing = kept / f"trajectories_{1 + len(list(kept.glob('trajectories_*.png'))):03d}.png"
    atomic_write(drawing, lambda f: f.write(path.read_bytes()))
    add_to_index(kept / "index.csv", [
        {"picture": drawing.name, "env_seed": shown, "cell_index": int(elite["index"]),
         "objective": float(elite["objective"]),
         **{name: float(value) for name, value in zip(config.measures, elite["measures"])}}
        for elite in chosen], "picture")
    for elite in chosen:
        print(f"{elite['name']}: {describe_elite(elite, config.measures)}")
    print(f"written to {path} (and kept as {drawing}, listed in {kept / 'index.csv'})")
