"""What a task family is: the types every family module fills in, and the linear policy they share.

A family (lander.py, walker.py) is a group of Gymnasium tasks flown by one episode function and
told apart by one set of measures. It declares itself once, as a `Family` value, and its tasks and
measures as rows that point to it; tasks.py gathers the family modules' rows into the tables
--env and --measures pick from. Every field is named where it is given (the types are
keyword-only), and what a row can read from its environment is not typed by hand: the policy's
shape and kind come from the env's spaces. A family flies whatever policy it is given
(policies.py), as an `act` from observation to action.

Map:
- `Family`: a family's episode function, the words the commands name its things with (what an
  env seed is, what a solved score is called) and, optionally, how the results commands draw it
  (path points, the step a path marks, poses for the explorer page, the page's scene, the
  trajectories picture); DRAWN_BY and `require_drawing` (a command that draws what the family
  leaves undrawn is one line);
- `Environment`: a task a search can fly (a row of ENVIRONMENTS): `make` (gym.make's env, a
  missing simulator or renderer in one line: `renderer_missing`, GL_PACKAGES) and `spaces`
  (read once, on first use), whence the policy's `shape`, `continuous` and `solution_dim` (of
  the linear policy); a benchmark function's row (functions.py) sets `function`, `dim` and
  `gradients` instead (`shape_for`: its shape at a run's --dim), and `make` refuses it (`NoEpisode`);
- `Returns`: the range of a run's objectives (its QD offset, solved return, CQD's top and the
  heatmaps' colours), `Environment.returns` (a task's, for an episode's length);
- `Measure`: a behaviour solutions are told apart by (a row of MEASURES); `bounds`, its range in a
  run (a benchmark function's grows with its dimension: `per_dim`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from qdsearch.base.flags import UsageError, named, one_line
from qdsearch.base.run_files import RunError

OnStep = Callable[[Any, np.ndarray], None]  # called with each step's action and observation


class NoEpisode(UsageError):
    """What flies an episode (an env, a video, a path) asked of a benchmark function, which has
    none: its message says which task and what was asked."""


@dataclasses.dataclass(frozen=True, eq=False, kw_only=True)
class Family:
    """A family of tasks: one episode function, one set of measures, and how it is drawn.

    Families are compared by identity: a task's measures are the rows whose `families` hold its
    own. The drawing fields are optional: a family without them searches, resumes, evaluates and
    compares as any other, and the commands that would draw it say in one line that they can't
    (`require_drawing`); `video` needs only its env's own renderer.
    """

    name: str  # in --help and in messages
    title: str  # how --help introduces its measures
    fly: Callable[..., Any]  # (act, env_seed, env, task, on_step) -> the episode's summary; act:
    # obs -> action, the policy flown
    # The words the commands name its things with (a task's own words never show for another's):
    seed_noun: str = "seed"  # what one --env_seed value is (the lander's "terrain"): "terrain 52"
    seed_shapes_world: bool = False  # a seed makes the ground the pictures draw (a terrain), so
    # one picture can't hold elites flown from resets of their own (--reset each)
    solved_words: str = "solved episodes"  # what scoring the task's `solved` return or more is
    # (the lander's "good landings"): "3 score 200 or more: good landings"
    prepare: Callable[[], None] = lambda: None  # called before one of its envs is made
    # what `trajectories` draws:
    position: Callable[[gym.Env, np.ndarray], tuple[float, float]] | None = None  # a path's point
    # after a step
    marked_step: Callable[[Any], int] | None = None  # the step (1-based) a path marks, from the
    # episode's summary
    draw_paths: Callable[[Any, list, int, Environment], str] | None = None  # the picture's ground
    # and axes on a matplotlib Axes; returns its title with {} for the count and the terrain
    # what `explore` draws:
    pose: Callable[[gym.Env, Any], list[float]] | None = None  # what the page draws a step from
    pose_scale: tuple[float, ...] = ()  # each pose column's units per int16 step (metres, radians)
    pose_angles: tuple[int, ...] = ()  # the pose's columns that are angles (wrapped to [-pi, pi])
    scene: Callable[[int, Environment], dict] | None = None  # the page's world and bodies
    # (explorer_page.html)
    # what `explore` draws a benchmark function's point as (it has no episode): {"kind": "bars"}
    # (each coordinate a bar; "bound": the dashed lines; "halves": the measures' halves coloured)
    # or {"kind": "arm"} (the planar arm of unit links, its joints at the point's angles)
    point_view: dict[str, Any] | None = None

    def undeclared(self, command: str) -> list[str]:
        """The fields `command` (a key of DRAWN_BY) draws the family with that it leaves unset."""
        return [field for field in DRAWN_BY[command] if not getattr(self, field)]

    def draws(self, command: str) -> bool:
        return not self.undeclared(command)


# What each command that draws a family's episodes needs the family to declare.
DRAWN_BY = {"trajectories": ("position", "marked_step", "draw_paths"),
            "explore": ("pose", "pose_scale", "scene"), "explore points": ("point_view",)}


def require_drawing(family: Family, command: str, points: bool = False) -> None:
    """Refuse, in one line, a command that draws (`trajectories`, `explore`) a family that does not
    declare how (`points`: a benchmark function's points, explored without an episode); called
    before any episode is flown."""
    if missing := family.undeclared(command + " points" if points else command):
        raise UsageError(f"{command}: the {family.title} family cannot be drawn (it declares no "
                         f"{', '.join(missing)}; docs/extending.md)")


def require_one_world(family: Family, reset: str, command: str) -> None:
    """Refuse, in one line, one picture of elites each flown from its own terrain (--reset each
    of a family whose seed makes its ground): it has no one ground to draw them on."""
    if reset == "each" and family.seed_shapes_world:
        raise UsageError(f"{command}: each elite of this {named('reset')} each run flew its own "
                         f"{family.seed_noun}, which one picture can't draw; the video command "
                         f"shows each elite as it was flown")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Environment:
    """A Gymnasium task a search can fly (a row of ENVIRONMENTS, picked by --env).

    A policy maps its `obs_dim` observations to `action_dim` actions, both read from the env's
    spaces (`shape`); the linear policy W @ obs has `solution_dim` weights (policies.py has the
    others). Its family flies the episode and gives its measures; `objective` says what of the
    episode is maximised.
    """

    gym_id: str
    kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)  # gym.make's, besides the id
    family: Family
    measures: tuple[str, ...]  # the default --measures
    qd_offset: float  # below (almost) every return: QD score counts every elite
    env_seed: str  # what --env_seed picks in this task
    solved: float  # the return its env calls solved
    fast: Callable[[], gym.Env] | None = None  # a streamlined copy, bitwise the same
    heat: tuple[float, float] = (-300.0, 300.0)  # the heatmaps' colour range of objectives
    objective_max: float = 350.0  # a return above (almost) every policy's: CQD's normalisation
    # True: qd_offset, solved, heat and objective_max are per step of an episode, and a run's are
    # those times its episode's length (a robot earns its reward every step; the lander's landing
    # and crash are paid once, so its range does not follow the episode's length)
    per_step: bool = False
    archive: str = "grid"  # the default --archive (a CVT for measures too many for a grid)
    objective: Callable[[Any], float] = lambda summary: summary.reward  # of an episode's summary:
    # its total reward, unless the task says otherwise (ant_omni leaves the forward reward out)
    # A benchmark function (functions.py): a batch of points -> their summary (arrays), scored in
    # the driver; a solution is the point, of --dim coordinates (`dim`: the default). None: a
    # Gymnasium task, flown by its family's episode function.
    function: Callable[[np.ndarray], Any] | None = None
    dim: int | None = None
    # A function's exact gradients: a batch of points -> a summary whose values are each value's
    # gradient (the DQD rows that take a task's own read it: cma_mega, cma_maega). None: none.
    gradients: Callable[[np.ndarray], Any] | None = None

    @property
    def own_length(self) -> int | None:
        """The steps of the task's own episode (gym.make's max_episode_steps in its spec; a
        function's: none)."""
        return None if self.function else gym.spec(self.gym_id).max_episode_steps

    def shape_for(self, dim: int | None) -> tuple[int, int]:
        """W's shape in a run of `dim` (--dim, None: the task's own): a function's point is a
        linear policy of one constant observation, (dim, 1); a Gymnasium task's is `shape`."""
        return (dim or self.dim, 1) if self.function else self.shape

    def returns(self, length: int | None = None, qd_offset: float | None = None) -> Returns:
        """The range of a run's objectives when its episodes last at most `length` steps (None: the
        task's own), its QD offset `qd_offset` if the run recorded one."""
        scale = (length or self.own_length or 1) if self.per_step else 1
        offset = self.qd_offset * scale if qd_offset is None else qd_offset
        return Returns(offset=offset, solved=self.solved * scale, top=self.objective_max * scale,
                       heat=(self.heat[0] * scale, self.heat[1] * scale))

    def make(self, render_mode: str | None = None, name: str | None = None, **rules: Any) -> gym.Env:
        """gym.make's env of the task, its family prepared (`rules`: gym.make's keywords for a run's
        episodes, tasks.Episode's). A simulator that is not installed
        (MuJoCo), or a headless renderer whose library is missing, is one line naming the row
        (`name`, its --env; else its gym id)."""
        if self.function:
            raise NoEpisode(f"{named('env')} {name} is a benchmark function: it has no episode to fly or "
                            "draw")
        try:
            self.family.prepare()
            return gym.make(self.gym_id, render_mode=render_mode, **{**self.kwargs, **rules})
        except gym.error.DependencyNotInstalled as error:
            raise UsageError(f"{named('env')} {name or self.gym_id} needs a package that is not installed "
                             f"({one_line(str(error))[:200]}): pip install -r requirements.txt") from None
        except (ImportError, AttributeError, RuntimeError) as error:
            if not os.environ.get("MUJOCO_GL") or "mujoco" in sys.modules:  # not MuJoCo's import failing
                raise
            raise renderer_missing(error) from None

    @functools.cached_property
    def spaces(self) -> tuple[gym.Space, gym.Space]:
        """The task's observation and action spaces, from an env made on first use (once per row
        and process): made at import, the simulators' imports would slow every command, --help
        too. tasks.check_spaces says whether the linear policy can serve them."""
        env = self.make()
        try:
            return env.observation_space, env.action_space
        finally:
            env.close()

    @property
    def continuous(self) -> bool:
        """Actions in a box: tanh(W @ obs), each component in [-1, 1]; else (Discrete) the argmax
        of W @ obs picks one of `action_dim` (a function has no actions: False)."""
        return not self.function and isinstance(self.spaces[1], gym.spaces.Box)

    @property
    def shape(self) -> tuple[int, int]:
        """W's shape: a row per action (a choice, or a component of the box), a column per
        observation (a function's default point: its `dim` coordinates of one constant input)."""
        if self.function:
            return self.dim, 1
        obs, act = self.spaces
        return int(act.n) if isinstance(act, gym.spaces.Discrete) else int(act.shape[0]), int(obs.shape[0])

    @property
    def action_dim(self) -> int:
        return self.shape[0]

    @property
    def obs_dim(self) -> int:
        return self.shape[1]

    @property
    def solution_dim(self) -> int:
        """The linear policy's weights (a run's own policy: `Policy.size(task.shape)`)."""
        return self.action_dim * self.obs_dim

@dataclasses.dataclass(frozen=True, kw_only=True)
class Returns:
    """The range of a run's objectives, from its task and episode's length (Environment.returns)."""

    offset: float  # the QD offset: QD score sums each elite's objective less this; CMA-MAE's floor
    solved: float  # the return that solves the task: the solved cells, `elites`' count
    top: float  # a return above (almost) every policy's: CQD's obj_max, the normalised QD score
    heat: tuple[float, float]  # the heatmaps' and the explorer's colour range


# The Debian packages each of MuJoCo's headless renderers (MUJOCO_GL) needs.
GL_PACKAGES = {"egl": "libegl1 libegl-mesa0", "osmesa": "libosmesa6"}


def renderer_missing(error: BaseException) -> RunError:
    """One line for a MuJoCo renderer whose library the machine lacks, naming what to install."""
    gl = os.environ.get("MUJOCO_GL", "")
    needs = GL_PACKAGES.get(gl, " or ".join(GL_PACKAGES.values()))
    return RunError(f"MuJoCo cannot render headless here through MUJOCO_GL={gl} "
                    f"({one_line(str(error))[:200]}): apt-get install -y {needs}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Measure:
    """One behaviour solutions are told apart by: its axis label, its range in the archive (values
    outside fall into the edge cells), a short name for file names, how an episode's summary gives
    it, and the families whose summary that is (several robots may share a measure)."""

    label: str
    range: tuple[float, float]
    short: str
    of: Callable[[Any], float]
    families: tuple[Family, ...]
    descending: bool = False  # its axis drawn from the lower bound at the top (the tutorial puts the
    # fastest impacts, the most negative y-velocities, on top)
    per_dim: float | None = None  # a benchmark function's: its range is `range` times this times
    # the run's dimension (sphere.py's +-5.12 dim / 2)

    def bounds(self, dim: int | None) -> tuple[float, float]:
        """Its range in a run of dimension `dim` (a benchmark function's --dim; else ignored)."""
        if self.per_dim is None or dim is None:
            return self.range
        return self.range[0] * self.per_dim * dim, self.range[1] * self.per_dim * dim
