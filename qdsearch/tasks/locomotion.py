"""The MuJoCo locomotion families: the QD-RL benchmark's Hopper, Walker2d, HalfCheetah and Ant
(Gymnasium's v5 tasks), each a family of its own robot, sharing one episode function.

The measures are the QD-RL literature's: for the `*_uni` tasks (Hopper-v5, Walker2d-v5,
HalfCheetah-v5, Ant-v5 here) the share of steps each foot touches the floor, read from MuJoCo's
own contacts (a contact between the foot's geom and the floor's); for `ant_omni`, the torso's
final x-y position, with the forward reward left out of the objective. docs/locomotion.md says how
each matches the literature's definition.

Map:
- `Robot` (a robot's torso, feet and view) and `Stride` (what an episode records);
- the episode: `fly_robot` (with `feet_touching`);
- how it is drawn: `position`, `pose` (the torso, then each capsule's ends, projected on the
  view's plane), `scene`, `draw_paths`;
- the declarations: ROBOTS, their families (`robot_family`; ROBOT_FAMILIES), ENVIRONMENTS and
  MEASURES rows (`foot_measures`).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from qdsearch.tasks.family import Environment, Family, Measure, OnStep

FLOOR = 0  # the floor is geom 0 in every robot's model


@dataclasses.dataclass(frozen=True, kw_only=True)
class Robot:
    """A MuJoCo robot: its name in measures, its feet (geoms, in the measures' order), and the plane
    it is seen in (planar robots from the side: x and height; the Ant from above: x and y)."""

    name: str
    title: str
    feet: tuple[str, ...]
    top: bool = False  # seen from above (the Ant walks the plane); else from the side

    def plane(self) -> list[int]:
        """The world axes the view shows: x and y from above, x and z from the side."""
        return [0, 1] if self.top else [0, 2]


@dataclasses.dataclass
class Stride:
    """A locomotion episode summed up, for the measures and the objective."""

    reward: float = 0.0  # the episode's total reward
    forward: float = 0.0  # its forward part (info["reward_forward"] summed): ant_omni leaves it out
    steps: int = 0
    contacts: list[int] = dataclasses.field(default_factory=list)  # steps each foot touches the floor
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the torso's position after the reset
    end: tuple[float, float, float] = (0.0, 0.0, 0.0)  # and at the end
    heights: float = 0.0  # the torso's height, summed over the steps

    def share(self, foot: int) -> float:
        return self.contacts[foot] / max(self.steps, 1)


def feet_touching(data: Any, feet: list[int]) -> list[bool]:
    """Which feet (geom ids) touch the floor in this step's contacts. A loop over the step's few
    contacts: numpy's isin over them cost ~24 us a step, a fifth of a HalfCheetah step; this ~2."""
    touching = set()
    if data.ncon:
        for first, second in data.contact.geom[:data.ncon].tolist():
            if first == FLOOR:
                touching.add(second)
            elif second == FLOOR:
                touching.add(first)
    return [foot in touching for foot in feet]


def fly_robot(act: Callable, env_seed: int, env: gym.Env, task: Environment,
              on_step: OnStep | None = None, *, robot: Robot) -> Stride:
    """One episode of the policy `act` from the reset of `env_seed` (MuJoCo's tasks
    draw their initial state's noise from it)."""
    import mujoco

    obs, _ = env.reset(seed=env_seed)
    model, data = env.unwrapped.model, env.unwrapped.data
    feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, foot) for foot in robot.feet]
    scratch, torso = mujoco.MjData(model), mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
    stride = Stride(contacts=[0] * len(feet), start=tuple(torso_at(model, data, scratch, torso)))
    done = False
    total, forward, heights, steps, contacts = 0.0, 0.0, 0.0, 0, np.zeros(len(feet), dtype=np.int64)
    while not done:
        action = act(obs)
        obs, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
        steps += 1
        total += reward
        forward += info["reward_forward"]
        contacts += feet_touching(data, feet)  # found at the last substep's start, as MuJoCo does
        heights += torso_at(model, data, scratch, torso)[2]
        if on_step is not None:
            on_step(action, obs)
    stride.reward, stride.forward, stride.steps, stride.heights = float(total), float(forward), steps, heights
    stride.contacts, stride.end = [int(c) for c in contacts], tuple(torso_at(model, data, scratch, torso))
    return stride


def torso_at(model: Any, data: Any, scratch: Any, torso: int) -> list[float]:
    """The torso's position in the state the simulation has reached. mj_step computes positions
    before it integrates, so data's lag a substep behind; they are computed again on a scratch
    copy of the state, leaving the env's own data as the env reads it (the Ant's forward reward
    reads the lagging positions: refreshing them there changed its returns)."""
    import mujoco

    scratch.qpos[:] = data.qpos
    mujoco.mj_kinematics(model, scratch)
    return scratch.xpos[torso].tolist()


def without_forward_reward(stride: Stride) -> float:
    """ant_omni's objective: the return less its forward reward (survival, control and contact
    costs), so no direction pays more than another."""
    return stride.reward - stride.forward


# ---- how an episode is drawn ------------------------------------------------------------------

def position(env: gym.Env, obs: np.ndarray, *, robot: Robot) -> tuple[float, float]:
    """A path's point: the torso on the view's plane (x and height; from above, x and y)."""
    torso = env.unwrapped.data.body("torso").xpos
    return float(torso[robot.plane()[0]]), float(torso[robot.plane()[1]])


def marked_step(stride: Stride) -> int:
    return stride.steps


def capsules(model: Any) -> list[int]:
    """The geoms the page draws as segments: every capsule (the floor and spheres are not)."""
    import mujoco

    return [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE]


def pose(env: gym.Env, action: Any, *, robot: Robot) -> list[float]:
    """A frame of the explorer page: the torso's position on the view's plane, then each
    capsule's two ends (its centre -/+ its half length along its axis), projected on it."""
    model, data = env.unwrapped.model, env.unwrapped.data
    u, v = robot.plane()
    values = [float(data.body("torso").xpos[u]), float(data.body("torso").xpos[v])]
    for g in capsules(model):
        axis = data.geom_xmat[g].reshape(3, 3)[:, 2] * model.geom_size[g][1]
        ends = (data.geom_xpos[g] - axis, data.geom_xpos[g] + axis)
        values += [float(ends[0][u]), float(ends[0][v]), float(ends[1][u]), float(ends[1][v])]
    return values


def scene(env_seed: int, task: Environment, *, robot: Robot) -> dict:
    """What the explorer page draws: the floor (a line from the side, a 1 m grid from above), the
    torso (a sphere's disc from above) and each capsule as a segment of its width; the view
    follows the torso."""
    quiet_mujoco()
    env = gym.make(task.gym_id, **task.kwargs)
    model = env.unwrapped.model
    colours = ("#cc9966", "#805533")
    bodies = []
    if robot.top:  # the Ant's torso is a sphere
        bodies.append({"circle": [0, 1], "radius": float(model.geom_size[1][0]), "colours": colours})
    bodies += [{"segment": [2 + 4 * i, 3 + 4 * i, 4 + 4 * i, 5 + 4 * i],
                "width": 2 * float(model.geom_size[g][0]), "colours": colours}
               for i, g in enumerate(capsules(model))]
    env.close()
    if robot.top:
        lines = ([[[k, -40.0], [k, 40.0]] for k in range(-40, 41)]
                 + [[[-40.0, k], [40.0, k]] for k in range(-40, 41)])
        statics = [{"points": line, "fill": None, "stroke": "#c8d2c8"} for line in lines]
        view = {"width": 8.0, "height": 16 / 3, "follow": [0.5, 0.5]}
    else:
        statics = [{"points": [[-1000.0, -5.0], [1000.0, -5.0], [1000.0, 0.0], [-1000.0, 0.0]],
                    "fill": "#99b399", "stroke": "#667a66"}]
        view = {"width": 6.0, "height": 4.0, "follow": [0.3, None], "low": -0.5}
    return {**view, "fps": round(1 / env.unwrapped.dt), "episode": "Run", "sky": "#eef2f7",
            "path": "#36c", "statics": statics, "bodies": bodies}


def draw_paths(ax, paths: list[tuple[np.ndarray, int]], env_seed: int, task: Environment, *,
               robot: Robot) -> str:
    """The torsos' paths: from above for the Ant (x-y, start at the origin), else x and height
    over the floor."""
    if robot.top:
        ax.plot([0], [0], marker="+", color="black", ms=12, label="start")
        ax.set_aspect("equal")
        ax.set_xlabel("x of the torso (m)")
        ax.set_ylabel("y of the torso (m)")
        return "Torso paths of {} elites from above, reset noise of seed {} (dots: the end)"
    ax.axhline(0.0, color="0.5", lw=2, zorder=0)
    ax.set_xlabel("x of the torso (m)")
    ax.set_ylabel("height of the torso (m)")
    return "Torso paths of {} elites, reset noise of seed {} (dots: the end)"


# ---- the declarations ------------------------------------------------------------------------

ROBOTS = {  # the feet, in the measures' order, are the geoms at the ends of the legs
    "hopper": Robot(name="hopper", title="Hopper", feet=("foot_geom",)),
    "walker2d": Robot(name="walker2d", title="Walker2d", feet=("foot_geom", "foot_left_geom")),  # right, left
    "halfcheetah": Robot(name="halfcheetah", title="HalfCheetah", feet=("bfoot", "ffoot")),  # back, front
    # the ankles at (+x, +y), (-x, +y), (-x, -y), (+x, -y) of the torso (the Ant faces +x)
    "ant": Robot(name="ant", title="Ant", feet=("left_ankle_geom", "right_ankle_geom", "third_ankle_geom",
                                                "fourth_ankle_geom"), top=True),
}

# The explorer's poses in centimetres: a good HalfCheetah runs ~100 m in an episode, and int16
# holds +-327 m at that scale.
POSE_SCALE_CM = 1e2


def quiet_mujoco() -> None:
    """MuJoCo's warnings (Gymnasium's Ant model uses a deprecated attribute) go to Python's log at
    debug level, not to a MUJOCO_LOG.TXT in the user's folder and the terminal."""
    import logging

    try:
        import mujoco
    except ImportError:  # gym.make says what to install
        return
    mujoco.set_mju_user_warning(logging.getLogger("mujoco").debug)


def robot_family(robot: Robot, pose_size: int) -> Family:
    """A robot's family: the shared functions, each told the robot."""
    return Family(
        name=robot.name, title=robot.title, fly=functools.partial(fly_robot, robot=robot),
        seed_noun="reset seed", solved_words="gaits at the reward threshold", prepare=quiet_mujoco,
        position=functools.partial(position, robot=robot), marked_step=marked_step,
        draw_paths=functools.partial(draw_paths, robot=robot), pose=functools.partial(pose, robot=robot),
        pose_scale=(POSE_SCALE_CM,) * pose_size, scene=functools.partial(scene, robot=robot))


# The pose's size: the torso's two coordinates and 4 per capsule (hopper 4, walker2d 7,
# halfcheetah 8, ant 12 capsules).
HOPPER = robot_family(ROBOTS["hopper"], 2 + 4 * 4)
WALKER2D = robot_family(ROBOTS["walker2d"], 2 + 4 * 7)
HALFCHEETAH = robot_family(ROBOTS["halfcheetah"], 2 + 4 * 8)
ANT = robot_family(ROBOTS["ant"], 2 + 4 * 12)
ROBOT_FAMILIES = (HOPPER, WALKER2D, HALFCHEETAH, ANT)

ANT_KWARGS = {"include_cfrc_ext_in_observation": False}  # 27 observations, as in the QD-RL tasks

# Every policy's action is a tanh of its last layer (the linear one's: tanh(W @ obs)): each task's
# action box is [-1, 1]. A robot earns its reward every step, so its range is declared per step
# (per_step) and a run's is that times its episode's length, as QDax's reward_offset. The QD
# offsets are below the lowest returns of random policies and below the worst a policy can do
# by its control cost (docs/locomotion.md); "solved" and CQD's top are Gymnasium's reward
# thresholds over its 1,000 steps (Walker2d has none: 5 a step, as the others' scale); the
# heatmaps' colours top out above the best returns of 300-iteration runs.
NOISE = "the reset's noise"  # what --env_seed seeds in a MuJoCo task
ENVIRONMENTS: dict[str, Environment] = {
    "Hopper-v5": Environment(
        gym_id="Hopper-v5", family=HOPPER, measures=("hopper_foot1",), qd_offset=-0.1, env_seed=NOISE,
        solved=3.8, heat=(-0.1, 1.5), objective_max=3.8, per_step=True),
    "Walker2d-v5": Environment(
        gym_id="Walker2d-v5", family=WALKER2D, measures=("walker2d_foot1", "walker2d_foot2"),
        qd_offset=-0.1, env_seed=NOISE, solved=5.0, heat=(-0.1, 1.5), objective_max=5.0, per_step=True),
    "HalfCheetah-v5": Environment(
        gym_id="HalfCheetah-v5", family=HALFCHEETAH, measures=("halfcheetah_foot1", "halfcheetah_foot2"),
        qd_offset=-4.0, env_seed=NOISE, solved=4.8, heat=(-1.0, 1.5), objective_max=4.8, per_step=True),
    "Ant-v5": Environment(
        gym_id="Ant-v5", kwargs=ANT_KWARGS, family=ANT,
        measures=("ant_foot1", "ant_foot2", "ant_foot3", "ant_foot4"), qd_offset=-5.0, env_seed=NOISE,
        solved=6.0, heat=(-1.0, 1.5), archive="cvt", objective_max=6.0, per_step=True),
    # The Ant in every direction: the final position as measures, no reward for going forward.
    "ant_omni": Environment(
        gym_id="Ant-v5", kwargs=ANT_KWARGS, family=ANT, measures=("final_x", "final_y"), qd_offset=-4.0,
        env_seed=NOISE, solved=1.0, heat=(-1.0, 1.0), objective_max=1.0, per_step=True,
        objective=without_forward_reward),
}


def foot_measures(family: Family, robot: Robot, names: tuple[str, ...]) -> dict[str, Measure]:
    """A robot's foot-contact measures: the share of steps each foot touches the floor."""
    return {f"{robot.name}_foot{i + 1}": Measure(
        label=f"Share of steps the {robot.title}'s {name} touches the floor", range=(0.0, 1.0),
        short=f"{robot.name[0]}f{i + 1}", of=lambda stride, i=i: stride.share(i), families=(family,))
        for i, name in enumerate(names)}


MEASURES: dict[str, Measure] = {
    **foot_measures(HOPPER, ROBOTS["hopper"], ("foot",)),
    **foot_measures(WALKER2D, ROBOTS["walker2d"], ("right foot", "left foot")),
    **foot_measures(HALFCHEETAH, ROBOTS["halfcheetah"], ("back foot", "front foot")),
    **foot_measures(ANT, ROBOTS["ant"], ("foot 1 (+x,+y)", "foot 2 (-x,+y)", "foot 3 (-x,-y)",
                                         "foot 4 (+x,-y)")),
    # ant_omni's: where the torso ends, x and y, in QDax's [-30, 30] m
    "final_x": Measure(label="Final x of the torso (m)", range=(-30.0, 30.0), short="x",
                       of=lambda s: s.end[0], families=(ANT,)),
    "final_y": Measure(label="Final y of the torso (m)", range=(-30.0, 30.0), short="y",
                       of=lambda s: s.end[1], families=(ANT,)),
    # Cheap and telling for every robot: how far forward, and how high the torso is carried.
    "forward_distance": Measure(label="Distance the torso moved along x (m)", range=(-10.0, 50.0),
                                short="dx", of=lambda s: s.end[0] - s.start[0], families=ROBOT_FAMILIES),
    "torso_height": Measure(label="Mean height of the torso (m)", range=(0.0, 2.0), short="z",
                            of=lambda s: s.heights / max(s.steps, 1), families=ROBOT_FAMILIES),
}
