"""The Lunar Lander family: the tutorial's task and its continuous twin, everything about them.

Map:
- the episode: `Flight` (what it records), `burn` (a throttle's engine powers), `fly_lander`;
- how it is drawn: `position` and `marked_step` (a path and its touchdown), `pose` with
  `engine_powers` (the explorer's frames), `scene` (the page's ground, helipad and bodies),
  `terrain` and `draw_paths` (the trajectories picture);
- the declarations: LANDER (the family), its ENVIRONMENTS rows and MEASURES rows.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d import lunar_lander as upstream

from qdsearch.tasks.family import Environment, Family, Measure, OnStep
from qdsearch.tasks.fast_lander import (
    FPS,
    HALF_H,
    HALF_W,
    HEIGHT,
    HELIPAD_Y,
    PAD_Y,
    SCALE,
    WIDTH,
    FastLunarLander,
    seeded_randoms,
)

NOOP, LEFT, MAIN, RIGHT = range(4)  # Lunar Lander's discrete actions: engines off, or one fires


@dataclasses.dataclass
class Flight:
    """A Lunar Lander episode summed up: everything a lander measure may read, in a single pass.

    "Touchdown" is the first step on which either leg touches the ground. A lander that never
    touches it has no touchdown; its impact observation is then its last one. `firings` counts
    each engine's firings; with throttles (the continuous lander) it sums their power, as the
    env's fuel cost does.
    """

    reward: float = 0.0  # the episode's total reward: the objective
    steps: int = 0
    touchdown: np.ndarray | None = None  # the observation at touchdown
    touchdown_step: int | None = None
    last: np.ndarray | None = None  # the last observation
    min_y_velocity: float = math.inf  # the fastest descent of the whole episode
    max_tilt: float = 0.0  # the largest |angle| up to touchdown (the whole episode without one)
    firings: list[float] = dataclasses.field(default_factory=lambda: [0] * 4)

    @property
    def impact(self) -> np.ndarray:
        return self.last if self.touchdown is None else self.touchdown


def burn(firings: list[float], action: np.ndarray) -> None:
    """The continuous lander's engine powers of one step, as its env computes them: the main
    engine fires at half to full power when action[0] > 0, a side engine when |action[1]| > 0.5."""
    if action[0] > 0.0:
        firings[MAIN] += (min(float(action[0]), 1.0) + 1.0) * 0.5
    if abs(action[1]) > 0.5:
        firings[RIGHT if action[1] > 0 else LEFT] += min(abs(float(action[1])), 1.0)


def fly_lander(act: Callable, env_seed: int, env: gym.Env, task: Environment,
               on_step: OnStep | None = None) -> Flight:
    """One Lunar Lander episode of the policy `act` on the terrain of `env_seed`; `on_step` is
    called with each step's action and observation."""
    obs, _ = env.reset(seed=env_seed)
    flight, firings, done, continuous = Flight(), [0] * 4, False, task.continuous
    total_reward, min_y_velocity, max_tilt, touchdown, steps = 0.0, math.inf, 0.0, None, 0
    while not done:
        action = act(obs)
        if continuous:
            burn(firings, action)
        else:
            firings[action] += 1
        obs, reward, terminated, truncated, _ = env.step(action)
        done = terminated or truncated
        steps += 1
        total_reward += reward
        if obs[3] < min_y_velocity:
            min_y_velocity = obs[3]
        if touchdown is None:
            max_tilt = max(max_tilt, abs(float(obs[4])))
            if obs[6] or obs[7]:
                touchdown, flight.touchdown_step = obs, steps
        if on_step is not None:
            on_step(action, obs)
    flight.reward, flight.steps, flight.touchdown, flight.last = total_reward, steps, touchdown, obs
    flight.min_y_velocity, flight.max_tilt, flight.firings = float(min_y_velocity), max_tilt, firings
    return flight


# ---- how a landing is drawn --------------------------------------------------------------------

def position(env: gym.Env, obs: np.ndarray) -> tuple[float, float]:
    """A flight path's point: the observation's (x, y) (x: -1 and 1 are the screen's edges; y: 0 is
    the lander's centre resting on the helipad)."""
    return float(obs[0]), float(obs[1])


def marked_step(flight: Flight) -> int:
    """A path marks the touchdown (the last step if there is none)."""
    return flight.touchdown_step or flight.steps


def engine_powers(action: Any) -> tuple[float, float]:
    """The lander's (main, side) engine powers of an action: a discrete one fires one engine at
    full power; a continuous one as `burn` weighs it (side < 0: the left engine)."""
    if action is None:
        return 0.0, 0.0
    if np.ndim(action) == 0:
        return {MAIN: (1.0, 0.0), LEFT: (0.0, -1.0), RIGHT: (0.0, 1.0)}.get(int(action), (0.0, 0.0))
    firings = [0.0] * 4
    burn(firings, action)
    return firings[MAIN], firings[RIGHT] - firings[LEFT]


def pose(env: gym.Env, action: Any) -> list[float]:
    """A frame of the explorer page: the lander's x, y and angle, the two legs' angles (a leg hangs
    from the lander's centre by its joint, so its position follows from its angle), the main
    engine's power (0, or 0.5 to 1) and the side engines' (negative: the left one)."""
    lander = env.unwrapped
    return [lander.lander.position.x, lander.lander.position.y, lander.lander.angle,
            lander.legs[0].angle, lander.legs[1].angle, *engine_powers(action)]


# 1 mm and 0.1 mrad, in int16: 14 bytes a step (what a whole page weighs: README, `explore`).
POSE_SCALE = (1e3, 1e3, 1e4, 1e4, 1e4, 1e4, 1e4)
POSE_ANGLES = (2, 3, 4)

BODY, FLAME = ("#8066e6", "#4d4d80"), ("#ff9a1f", "#ff5a00")  # fill and stroke, as the env's


def scene(env_seed: int, task: Environment) -> dict:
    """What the explorer page draws (see explorer_page.html): the black sky, the terrain, the
    helipad's flags, and per frame the legs, the engines' flames (as long as their power) and the
    body. The view is the env's own, 600 x 400 pixels of 1/SCALE m."""
    edges, _, _ = seeded_randoms(env_seed)
    pixel = 1 / SCALE
    statics = [{"points": [[0.0, 0.0], edges[0][0], *(end for _, end in edges), [WIDTH, 0.0]],
                "fill": "#fff", "stroke": None}]
    for x in (edges[3][1][0], edges[5][1][0]):  # the helipad's flags
        top = HELIPAD_Y + 50 * pixel
        statics += [{"points": [[x, HELIPAD_Y], [x, top]], "fill": None, "stroke": "#fff"},
                    {"points": [[x, top], [x, top - 10 * pixel], [x + 25 * pixel, top - 5 * pixel]],
                     "fill": "#cccc00", "stroke": None}]
    away, down = upstream.LEG_AWAY * pixel, upstream.LEG_DOWN * pixel
    w, h = upstream.LEG_W * pixel, upstream.LEG_H * pixel  # half sizes, as Box2D's box takes them
    leg = [[-w, -h], [w, -h], [w, h], [-w, h]]
    bodies = [{"points": leg, "at": [0, 1, 3 + i], "offset": [-side * away, -down], "colours": BODY}
              for i, side in enumerate((-1, 1))]
    bodies += [  # a flame's last point moves out with its engine's power ("grow" per unit)
        {"points": [[-0.15, -0.25], [0.15, -0.25], [0.0, -0.25]], "at": [0, 1, 2], "power": 5,
         "sign": 1, "grow": [0.0, -0.65], "colours": FLAME},
        # the left engine (side < 0) pushes from the lander's right, and the other way round
        {"points": [[0.45, 0.05], [0.45, 0.25], [0.45, 0.15]], "at": [0, 1, 2], "power": 6,
         "sign": -1, "grow": [0.5, 0.0], "colours": FLAME},
        {"points": [[-0.45, 0.05], [-0.45, 0.25], [-0.45, 0.15]], "at": [0, 1, 2], "power": 6,
         "sign": 1, "grow": [-0.5, 0.0], "colours": FLAME},
        {"points": [[x * pixel, y * pixel] for x, y in upstream.LANDER_POLY], "at": [0, 1, 2],
         "colours": BODY}]
    return {"width": WIDTH, "height": HEIGHT, "fps": FPS, "episode": "Landing", "sky": "#000", "path": "#6cf",
            "follow": None, "statics": statics, "bodies": bodies}


def terrain(env_seed: int) -> np.ndarray:
    """The ground line of a terrain, (x, y) in the observation's units (as flight paths)."""
    edges, _, _ = seeded_randoms(env_seed)
    points = np.array([edges[0][0], *(end for _, end in edges)])
    return np.column_stack([(points[:, 0] - HALF_W) / HALF_W, (points[:, 1] - PAD_Y) / HALF_H])


def draw_paths(ax, paths: list[tuple[np.ndarray, int]], env_seed: int, task: Environment) -> str:
    """The tutorial's "many ways to land": flight paths over the terrain, impacts marked. Equal
    metres on both axes (x and y are scaled differently)."""
    ground = terrain(env_seed)
    ax.fill_between(ground[:, 0], ground[:, 1], ground[:, 1].min() - 0.2, color="0.75", zorder=0)
    ax.plot([-0.2, 0.2], [ground[5, 1]] * 2, color="gold", lw=4, label="helipad", zorder=1)
    ax.set_aspect(HALF_H / HALF_W)
    ax.set_xlim(-1.05, 1.05)
    ax.set_ylim(ground[:, 1].min() - 0.2, max(1.5, max(float(f[:, 1].max()) for f, _ in paths) + 0.05))
    ax.set_xlabel("x (observation units: -1 and 1 are the screen edges)")
    ax.set_ylabel("y of the lander's centre (0: resting on the helipad)")
    return "Flight paths of {} elites on terrain {} (dots: touchdown)"


# ---- the declarations ------------------------------------------------------------------------

LANDER = Family(name="lander", title="Lunar Lander", fly=fly_lander, seed_noun="terrain",
                seed_shapes_world=True, solved_words="good landings", position=position,
                marked_step=marked_step, draw_paths=draw_paths, pose=pose, pose_scale=POSE_SCALE,
                pose_angles=POSE_ANGLES, scene=scene)

# Observation (x, y, vx, vy, angle, spin, leg1, leg2). The QD offsets are below the lowest
# returns of real runs (docs/environments.md).
ENVIRONMENTS: dict[str, Environment] = {
    # The tutorial's: 4 actions (engines off, or one of three fires).
    "LunarLander-v3": Environment(
        gym_id="LunarLander-v3", family=LANDER, measures=("impact_x", "impact_y_velocity"),
        qd_offset=-600.0, env_seed="the terrain and the initial push", solved=200.0, fast=FastLunarLander),
    # Throttles instead of switches: main engine and lateral engine, each in [-1, 1].
    "LunarLanderContinuous-v3": Environment(
        gym_id="LunarLander-v3", kwargs={"continuous": True}, family=LANDER,
        measures=("impact_x", "impact_y_velocity"), qd_offset=-1200.0,
        env_seed="the terrain and the initial push", solved=200.0),
}

# Each measure of a run is computed per terrain and averaged over its terrains. The ranges hold
# what the policies of real runs reach (docs/terrains.md).
MEASURES: dict[str, Measure] = {
    # The tutorial's two: where and how fast the lander comes down (without a touchdown: its last
    # x-position and its fastest descent).
    "impact_x": Measure(label="Impact x-position", range=(-1.0, 1.0), short="x",
                        of=lambda f: f.impact[0], families=(LANDER,)),
    "impact_y_velocity": Measure(
        label="Impact y-velocity", range=(-3.0, 0.0), short="v", descending=True, families=(LANDER,),
        of=lambda f: f.min_y_velocity if f.touchdown is None else f.touchdown[3]),
    "impact_x_velocity": Measure(label="Impact x-velocity", range=(-3.0, 3.0), short="vx",
                                 of=lambda f: f.impact[2], families=(LANDER,)),
    # Angles are not wrapped: a lander that tumbles goes past pi, into the edge cells.
    "impact_angle": Measure(label="Impact angle (rad)", range=(-math.pi, math.pi), short="angle",
                            of=lambda f: f.impact[4], families=(LANDER,)),
    # Fuel in main-engine firings at full power: a side firing costs a tenth of one, as in the
    # env's reward (with throttles: each firing weighed by its power).
    "fuel": Measure(label="Fuel burnt (main-engine firings)", range=(0.0, 600.0), short="fuel",
                    of=lambda f: f.firings[MAIN] + 0.1 * (f.firings[LEFT] + f.firings[RIGHT]),
                    families=(LANDER,)),
    # A lander falling freely touches down after ~51 steps; one that hovers flies all 1000.
    "flight_time": Measure(label="Steps to touchdown", range=(50.0, 1000.0), short="steps",
                           of=lambda f: f.steps if f.touchdown_step is None else f.touchdown_step,
                           families=(LANDER,)),
    "max_tilt": Measure(label="Largest tilt before touchdown (rad)", range=(0.0, math.pi), short="tilt",
                        of=lambda f: f.max_tilt, families=(LANDER,)),
}
