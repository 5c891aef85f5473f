"""The BipedalWalker family: the walker on grassland and on the hardcore course, everything about
them.

Map:
- the episode: `Walk` (what it records), `renew_world`, `fly_walker`;
- how it is drawn: `position` and `marked_step` (the hull's path and its end), `pose` (the
  explorer's frames), `scene` (the page's ground, obstacles and bodies), `draw_paths` (the
  trajectories picture);
- the declarations: WALKER (the family), its ENVIRONMENTS rows and MEASURES rows.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import Box2D
import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d import bipedal_walker as upstream

from qdsearch.tasks.family import Environment, Family, Measure, OnStep


@dataclasses.dataclass
class Walk:
    """A BipedalWalker episode summed up, for the walker measures."""

    reward: float = 0.0  # the episode's total reward: the objective
    steps: int = 0
    contacts: list[int] = dataclasses.field(default_factory=lambda: [0, 0])  # steps on which each
    # lower leg touches the ground (observations 8 and 13)
    distance: float = 0.0  # the hull's x at the end less its x at the start, in metres
    hull_angles: float = 0.0  # the hull's angle (observation 0), summed over the steps

    def share(self, leg: int) -> float:
        return self.contacts[leg] / max(self.steps, 1)


def renew_world(walker: Any) -> None:
    """Give a BipedalWalker a new Box2D world before its reset. Its reset only destroys the last
    episode's bodies, and a world that has held them solves contacts in another order: episodes
    in a reused env differed from a fresh env's. With a new world they are the same, bit for bit
    (tests/test_environments.py flies both)."""
    walker._destroy()
    walker.world = Box2D.b2World()


def fly_walker(act: Callable, env_seed: int, env: gym.Env, task: Environment,
               on_step: OnStep | None = None) -> Walk:
    """One BipedalWalker episode of the policy `act` on the terrain of `env_seed`."""
    renew_world(env.unwrapped)
    obs, _ = env.reset(seed=env_seed)
    hull, walk, done = env.unwrapped.hull, Walk(), False
    start_x, contacts, total_reward, angles, steps = hull.position.x, [0, 0], 0.0, 0.0, 0
    while not done:
        action = act(obs)
        obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        steps += 1
        total_reward += reward
        angles += float(obs[0])  # in float64: a float32 sum drifts over 1,600 steps
        contacts[0] += obs[8] > 0.5
        contacts[1] += obs[13] > 0.5
        if on_step is not None:
            on_step(action, obs)
    walk.reward, walk.steps, walk.contacts = total_reward, steps, contacts
    walk.distance, walk.hull_angles = float(hull.position.x - start_x), float(angles)
    return walk


# ---- how a walk is drawn -----------------------------------------------------------------------

def position(env: gym.Env, obs: np.ndarray) -> tuple[float, float]:
    """A path's point: the hull's (x, y) in metres (the hull of this episode: reset makes one)."""
    hull = env.unwrapped.hull.position
    return float(hull.x), float(hull.y)


def marked_step(walk: Walk) -> int:
    """A path marks where the episode ends."""
    return walk.steps


def pose(env: gym.Env, action: Any) -> list[float]:
    """A frame of the explorer page: the hull's and the four leg segments' x, y and angle."""
    walker = env.unwrapped
    return [value for body in (walker.hull, *walker.legs)
            for value in (body.position.x, body.position.y, body.angle)]


POSE_SCALE = (1e2, 1e2, 1e4) * 5  # 1 cm (the course is ~90 m) and 0.1 mrad: 30 bytes a step
POSE_ANGLES = (2, 5, 8, 11, 14)


def course(env_seed: int, task: Environment) -> tuple[list, list, float]:
    """The course of a terrain, as the env builds it: its ground polygons, its obstacles' polygons
    (the hardcore course's stumps, stair steps and pit walls: bodies of their own) and its end."""
    def points(vertices) -> list[list[float]]:
        return [[round(float(x), 4), round(float(y), 4)] for x, y in vertices]

    env = gym.make(task.gym_id, **task.kwargs)
    env.reset(seed=env_seed)
    ground = [points(poly) for poly, _ in env.unwrapped.terrain_poly]
    obstacles = [points(body.transform * vertex for vertex in fixture.shape.vertices)
                 for body in env.unwrapped.terrain for fixture in body.fixtures
                 if isinstance(fixture.shape, Box2D.b2PolygonShape)]
    end = float(env.unwrapped.terrain_x[-1])
    env.close()
    return ground, obstacles, end


def scene(env_seed: int, task: Environment) -> dict:
    """What the explorer page draws (see explorer_page.html), as the env draws it: the sky, the
    grass, the obstacles, and per frame the four leg segments (the far leg darker) and the hull;
    the view follows the hull."""
    ground, obstacles, _ = course(env_seed, task)
    statics = ([{"points": poly, "fill": "#66994c", "stroke": "#4c7f33"} for poly in ground]
               + [{"points": poly, "fill": "#ffffff", "stroke": "#999999"} for poly in obstacles])
    # the leg segments' half sizes (LEG_W and LEG_H are in metres already)
    halves = [[upstream.LEG_W / 2, upstream.LEG_H / 2], [0.8 * upstream.LEG_W / 2, upstream.LEG_H / 2]] * 2
    bodies = [{"points": [[-w, -h], [w, -h], [w, h], [-w, h]], "at": [3 * i, 3 * i + 1, 3 * i + 2],
               "colours": ("#b266cc" if i < 3 else "#8c4ca6", "#4d2666")}
              for i, (w, h) in enumerate(halves, start=1)]
    bodies.append({"points": [[x / upstream.SCALE, y / upstream.SCALE] for x, y in upstream.HULL_POLY],
                   "at": [0, 1, 2], "colours": ("#8066e6", "#4d4d80")})
    return {"width": upstream.VIEWPORT_W / upstream.SCALE, "height": upstream.VIEWPORT_H / upstream.SCALE,
            "fps": upstream.FPS, "episode": "Walk", "sky": "#e6e6ff", "path": "#c33", "follow": [0.2, None],
            "statics": statics, "bodies": bodies}


def draw_paths(ax, paths: list[tuple[np.ndarray, int]], env_seed: int, task: Environment) -> str:
    """The walkers' hull height against distance over the course's ground, where each ends."""
    ground, _, end_of_course = course(env_seed, task)
    for poly in ground:
        ax.fill(*zip(*poly), color="0.75", lw=0, zorder=0)
    end = max(float(path[:, 0].max()) for path, _ in paths)
    ax.set_xlim(0, min(end_of_course, end + 5))
    low = min(float(path[:, 1].min()) for path, _ in paths)
    ax.set_ylim(max(0.0, low - 2), max(float(path[:, 1].max()) for path, _ in paths) + 1)
    ax.set_xlabel("x of the hull (m)")
    ax.set_ylabel("height of the hull (m; heights are stretched)")
    return "Hull paths of {} elites on terrain {} (dots: the episode's end)"


# ---- the declarations ------------------------------------------------------------------------

WALKER = Family(name="walker", title="BipedalWalker", fly=fly_walker, seed_noun="terrain",
                seed_shapes_world=True, solved_words="walks to the far end", position=position,
                marked_step=marked_step, draw_paths=draw_paths, pose=pose, pose_scale=POSE_SCALE,
                pose_angles=POSE_ANGLES, scene=scene)

# Hull angle, speeds, 4 joints' angles and speeds, 2 foot contacts, 10 lidar readings; 4 torques.
# The QD offsets are below the lowest returns of real runs (docs/environments.md).
ENVIRONMENTS: dict[str, Environment] = {
    # An episode ends when the hull touches the ground, or after 1,600 steps.
    "BipedalWalker-v3": Environment(
        gym_id="BipedalWalker-v3", family=WALKER, measures=("foot1_contact", "foot2_contact"),
        qd_offset=-300.0, env_seed="the grassland's heights", solved=300.0),
    # The same walker among stumps, pits and stairs, for up to 2,000 steps.
    "BipedalWalkerHardcore-v3": Environment(
        gym_id="BipedalWalkerHardcore-v3", family=WALKER, measures=("foot1_contact", "foot2_contact"),
        qd_offset=-350.0, env_seed="the obstacles and the grassland", solved=300.0),
}

MEASURES: dict[str, Measure] = {
    # The QD literature's walker measures (Cully et al. 2015's duty factor): the share of steps
    # each foot touches the ground.
    "foot1_contact": Measure(label="Share of steps foot 1 touches the ground", range=(0.0, 1.0),
                             short="foot1", of=lambda w: w.share(0), families=(WALKER,)),
    "foot2_contact": Measure(label="Share of steps foot 2 touches the ground", range=(0.0, 1.0),
                             short="foot2", of=lambda w: w.share(1), families=(WALKER,)),
    # How far, and how fast: the course is ~88 m from the start to its end.
    "distance": Measure(label="Distance walked (m)", range=(-10.0, 90.0), short="dist",
                        of=lambda w: w.distance, families=(WALKER,)),
    "speed": Measure(label="Mean speed (m/s)", range=(-1.0, 3.0), short="speed",
                     of=lambda w: w.distance * 50 / max(w.steps, 1), families=(WALKER,)),  # 50 steps a second
    "hull_angle": Measure(label="Mean hull angle (rad)", range=(-1.0, 1.0), short="hull",
                          of=lambda w: w.hull_angles / max(w.steps, 1), families=(WALKER,)),
}
