"""The benchmark functions: the sphere and Rastrigin of pyribs' examples/sphere.py and the planar
arm of the QD literature, as task families. A solution is the point itself (no policy, no
episode); a batch of points is scored at once, in the driver's process, where it costs
microseconds (a round trip to a Dask worker costs a millisecond).

Each task's dimension is the run's --dim (the arm's joints), its default the task's `dim`.

Map:
- the functions: `sphere_points`, `rastrigin_points` (pyribs' shift, clipping and objective
  normalisation to [0, 100]), `arm_points` (pyribs' arm tutorial: the joints' variance to
  minimise, the hand's position); `Points` (what they return: a batch's arrays);
- their exact gradients, for the DQD rows that take a task's own (cma_mega, cma_maega, as
  sphere.py's): `sphere_gradients`, `rastrigin_gradients`, `arm_gradients` (a `Points` whose
  arrays are each value's gradient, a row per point);
- `no_episode` (a function family's `fly`: there is none to fly);
- the declarations: SPHERE, RASTRIGIN, ARM (the families), their ENVIRONMENTS and MEASURES rows.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from qdsearch.tasks.family import Environment, Family, Measure, NoEpisode

BOUND = 5.12  # sphere.py's clipping bound of each coordinate (Fontaine 2020, section 4)
SHIFT = 0.4 * BOUND  # sphere.py moves the optimum from 0 to 2.048 in every coordinate


@dataclasses.dataclass(frozen=True)
class Points:
    """A batch of points scored: each array has a row per point."""

    objective: np.ndarray
    first: np.ndarray  # the sphere's measures: the clipped coordinates' sums over each half
    second: np.ndarray
    # (A gradients function's Points holds each value's gradient: arrays of (points, dim).)


def clipped_halves(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sphere.py's measures: each coordinate outside [-5.12, 5.12] folded in as 5.12 / x, then the
    sums of the first dim // 2 coordinates and of the rest."""
    clipped = points.copy()
    outside = np.abs(clipped) > BOUND
    clipped[outside] = BOUND / clipped[outside]
    half = points.shape[1] // 2
    return clipped[:, :half].sum(axis=1), clipped[:, half:].sum(axis=1)


def normalised(raw: np.ndarray, worst: float) -> np.ndarray:
    """A cost in [0, worst] as sphere.py's objective: 100 at 0, 0 at `worst`."""
    return (raw - worst) / (0.0 - worst) * 100.0


def sphere_points(points: np.ndarray) -> Points:
    """pyribs' sphere: the squared distance to (2.048, ...), 100 at the optimum and 0 where every
    coordinate is -5.12."""
    dim = points.shape[1]
    raw = np.sum(np.square(points - SHIFT), axis=1)
    return Points(normalised(raw, (-BOUND - SHIFT) ** 2 * dim), *clipped_halves(points))


def rastrigin_points(points: np.ndarray) -> Points:
    """Rastrigin, shifted and normalised as sphere.py does the sphere: 10 dim + sum(z^2 - 10
    cos(2 pi z)) of z = x - 2.048, 100 at the optimum and 0 where every coordinate is -5.12."""
    dim = points.shape[1]

    def cost(z: np.ndarray) -> np.ndarray:
        return 10.0 * dim + np.sum(np.square(z) - 10.0 * np.cos(2.0 * math.pi * z), axis=-1)

    worst = float(cost(np.full(dim, -BOUND - SHIFT)))
    return Points(normalised(cost(points - SHIFT), worst), *clipped_halves(points))


def arm_points(points: np.ndarray) -> Points:
    """pyribs' arm tutorial: a planar arm of unit links with these joint angles. Its objective is
    minus the angles' variance (an arm bent evenly), its measures the hand's (x, y)."""
    angles = np.cumsum(points, axis=1)
    return Points(-np.var(points, axis=1), np.cos(angles).sum(axis=1), np.sin(angles).sum(axis=1))


def clipped_halves_gradients(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gradients of `clipped_halves`' two sums: 1 for a coordinate inside [-5.12, 5.12], the
    derivative of 5.12 / x outside, each sum's in its half and 0 in the other."""
    slope = np.ones_like(points)
    outside = np.abs(points) > BOUND
    slope[outside] = -BOUND / np.square(points[outside])
    half = points.shape[1] // 2
    first, second = slope.copy(), slope
    first[:, half:], second[:, :half] = 0.0, 0.0
    return first, second


def normalised_slope(raw_gradient: np.ndarray, worst: float) -> np.ndarray:
    """The gradient of `normalised` from the cost's."""
    return raw_gradient * (-100.0 / worst)


def sphere_gradients(points: np.ndarray) -> Points:
    """The gradients of `sphere_points`' objective and measures."""
    worst = (-BOUND - SHIFT) ** 2 * points.shape[1]
    return Points(normalised_slope(2.0 * (points - SHIFT), worst), *clipped_halves_gradients(points))


def rastrigin_gradients(points: np.ndarray) -> Points:
    """The gradients of `rastrigin_points`' objective and measures."""
    dim, z = points.shape[1], points - SHIFT
    z_worst = -BOUND - SHIFT
    worst = dim * (10.0 + z_worst ** 2 - 10.0 * math.cos(2.0 * math.pi * z_worst))
    raw = 2.0 * z + 20.0 * math.pi * np.sin(2.0 * math.pi * z)
    return Points(normalised_slope(raw, worst), *clipped_halves_gradients(points))


def arm_gradients(points: np.ndarray) -> Points:
    """The gradients of `arm_points`' objective and hand: joint j turns every link from j on, so
    the hand's x moves by minus the sum of sin over those links' angles, its y by the cos's."""
    angles = np.cumsum(points, axis=1)
    from_joint = lambda values: np.cumsum(values[:, ::-1], axis=1)[:, ::-1]  # noqa: E731 (sums over i >= j)
    variance = -2.0 * (points - points.mean(axis=1, keepdims=True)) / points.shape[1]
    return Points(variance, -from_joint(np.sin(angles)), from_joint(np.cos(angles)))


def objective_of(points: Points) -> np.ndarray:
    """A function task's objective: the function's value, normalised as its row says."""
    return points.objective


def no_episode(*args: Any) -> Any:
    """A function family's episode: there is none (the results commands that fly one refuse first:
    tasks.make_env)."""
    raise NoEpisode("a benchmark function has no episode")


# The explorer draws a point of the sphere or Rastrigin as its coordinates' bars (the halves that
# make the two measures apart, the clipping bound dashed), an arm's as the arm.
BARS = {"kind": "bars", "bound": BOUND, "halves": True}
SPHERE = Family(name="sphere", title="Sphere", fly=no_episode, seed_noun="seed",
                solved_words="points within 1 of the optimum", point_view=BARS)
RASTRIGIN = Family(name="rastrigin", title="Rastrigin", fly=no_episode, seed_noun="seed",
                   solved_words="points within 1 of the optimum", point_view=BARS)
ARM = Family(name="arm", title="Planar arm", fly=no_episode, seed_noun="seed",
             solved_words="arms bent with a variance of 0.01 or less", point_view={"kind": "arm"})

SEED = "nothing (a function has no randomness)"
ENVIRONMENTS: dict[str, Environment] = {
    # sphere.py's: 100 dimensions, objectives in [0, 100], QD score counted from 0.
    "sphere": Environment(gym_id="", family=SPHERE, measures=("sum_first_half", "sum_second_half"),
                          qd_offset=0.0, env_seed=SEED, solved=99.0, heat=(0.0, 100.0),
                          objective_max=100.0, function=sphere_points, dim=100, objective=objective_of,
                          gradients=sphere_gradients),
    "rastrigin": Environment(gym_id="", family=RASTRIGIN, measures=("sum_first_half", "sum_second_half"),
                             qd_offset=0.0, env_seed=SEED, solved=99.0, heat=(0.0, 100.0),
                             objective_max=100.0, function=rastrigin_points, dim=100,
                             objective=objective_of, gradients=rastrigin_gradients),
    # pyribs' arm tutorial: 12 joints. Minus a variance: the offset is that of angles spread
    # evenly over [-pi, pi] (pi^2 / 3), which every search starting at 0 stays above.
    "arm": Environment(gym_id="", family=ARM, measures=("hand_x", "hand_y"), qd_offset=-math.pi ** 2 / 3,
                       env_seed=SEED, solved=-0.01, heat=(-1.0, 0.0), objective_max=0.0,
                       function=arm_points, dim=12, objective=objective_of, gradients=arm_gradients),
}

# The ranges grow with the dimension: sphere.py's +-5.12 dim / 2 for each half's sum, and the
# arm's reach, its joints' count (a link each, of length 1).
MEASURES: dict[str, Measure] = {
    "sum_first_half": Measure(label="Sum of the first half's clipped coordinates", range=(-BOUND, BOUND),
                              short="s1", of=lambda p: p.first, families=(SPHERE, RASTRIGIN),
                              per_dim=0.5),
    "sum_second_half": Measure(label="Sum of the second half's clipped coordinates", range=(-BOUND, BOUND),
                               short="s2", of=lambda p: p.second, families=(SPHERE, RASTRIGIN),
                               per_dim=0.5),
    "hand_x": Measure(label="Hand x-position", range=(-1.0, 1.0), short="x", of=lambda p: p.first,
                      families=(ARM,), per_dim=1.0),
    "hand_y": Measure(label="Hand y-position", range=(-1.0, 1.0), short="y", of=lambda p: p.second,
                      families=(ARM,), per_dim=1.0),
}
