#!/usr/bin/env python
"""Search Gymnasium's Lunar Lander for many different good landings with CMA-ME (pyribs), on Dask.

The problem, the algorithm and the results follow the pyribs tutorial "Using CMA-ME to Land a Lunar
Lander Like a Space Shuttle"; this script adds what a research run needs around them: a Dask
evaluation engine, seeded and repeatable runs, checkpoints, metrics, plots and a CLI.

    python lunar_lander.py --iterations 300 --workers 2      # search; writes outputs/<run>/
    python lunar_lander.py resume outputs/RUN                 # continue a run from its checkpoint
    python lunar_lander.py --algorithm cma_mae                # or map_elites; default cma_me
    python lunar_lander.py compare outputs/RUN_A outputs/RUN_B  # plot and tabulate runs side by side
    python lunar_lander.py --help                             # every flag
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import importlib
import json
import math
import logging
import os
import pickle
import platform
import secrets
import signal
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

import Box2D
import gymnasium as gym
import numpy as np
from Box2D.b2 import edgeShape, fixtureDef, polygonShape, revoluteJointDef
from gymnasium.envs.box2d import lunar_lander as upstream
from gymnasium.utils import seeding

# Plots are written to files, never shown: no display is needed (set before matplotlib loads).
os.environ.setdefault("MPLBACKEND", "Agg")

# Dask spawns worker processes that re-import this script, so the heavy libraries that only the
# main process needs (ribs, matplotlib, dask itself) are imported inside the functions using them.
if __name__ == "__mp_main__":
    # A local worker: Ctrl-C in a terminal reaches the whole process group, but stopping is the
    # main process's job (it abandons the iteration and closes the cluster), so workers ignore it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class UsageError(Exception):
    """Bad input from the user: reported as one line on stderr with a non-zero exit."""


# ================================================================================================
# The problem: a linear policy flying Lunar Lander on a fixed terrain
# ================================================================================================

ENV_ID = "LunarLander-v3"
ACTION_DIM, OBS_DIM = 4, 8  # discrete actions; observation (x, y, vx, vy, angle, spin, leg1, leg2)
SOLUTION_DIM = ACTION_DIM * OBS_DIM


def make_env(fast: bool = True, render_mode: str | None = None) -> gym.Env:
    """The environment rollouts fly in: the streamlined copy below, or gym.make's plain one
    (needed to render, and kept as the reference the streamlined one is tested against)."""
    if fast and render_mode is None:
        return FastLunarLander()
    return gym.make(ENV_ID, render_mode=render_mode)


def rollout(solution: np.ndarray, env_seed: int, env: gym.Env,
            trajectory: list | None = None) -> tuple[float, float, float]:
    """Fly the policy action = argmax(W @ obs) for one episode on the terrain of `env_seed`.

    Returns (objective, impact x-position, impact y-velocity): the objective is the episode's total
    reward; the measures are taken when either leg first touches the ground, or, if the lander never
    touches it, they are the last x-position and the fastest descent (minimum y-velocity).
    With a `trajectory` list, each step's (x, y) position is appended to it.
    """
    weights = np.asarray(solution, dtype=np.float64).reshape(ACTION_DIM, OBS_DIM)
    # W.dot(obs) makes the same BLAS call as W @ obs (same bits) for less overhead; a strided W
    # would take matmul's non-BLAS path, so it keeps matmul.
    scores = weights.dot if weights.flags.c_contiguous else weights.__matmul__
    obs, _ = env.reset(seed=env_seed)
    total_reward, impact, min_y_velocity = 0.0, None, np.inf
    done = False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(int(scores(obs).argmax()))
        done = terminated or truncated
        total_reward += reward
        if obs[3] < min_y_velocity:
            min_y_velocity = obs[3]
        if impact is None and (obs[6] or obs[7]):
            impact = (obs[0], obs[3])
        if trajectory is not None:
            trajectory.append((float(obs[0]), float(obs[1])))
    if impact is None:
        impact = (obs[0], min_y_velocity)
    return float(total_reward), float(impact[0]), float(impact[1])


# ------------------------------------------------------------------------------------------------
# A streamlined LunarLander-v3: the same episode, bit for bit, for about two thirds of the cost.
# gym.make's env spends much of each step outside Box2D: wrappers, an action-space check, numpy
# calls on 8 floats, two RNG draws, rebuilding body definitions on reset. This copy mirrors
# gymnasium 1.4.0's lunar_lander.py operation for operation without those costs; the tests
# compare it with gym.make over many policies on every run (re-run them after upgrading).
# ------------------------------------------------------------------------------------------------

MAX_STEPS = 1000  # the TimeLimit gym.make("LunarLander-v3") adds
_S, _FPS = upstream.SCALE, upstream.FPS
_W, _H = upstream.VIEWPORT_W / _S, upstream.VIEWPORT_H / _S
# Same expressions as upstream, hence the same bits.
_HALF_W, _HALF_H = upstream.VIEWPORT_W / _S / 2, upstream.VIEWPORT_H / _S / 2
_HELIPAD_Y = _H / 4
_PAD_Y = _HELIPAD_Y + upstream.LEG_DOWN / _S
_MAIN_Y, _SIDE_Y = upstream.MAIN_ENGINE_Y_LOCATION / _S, upstream.SIDE_ENGINE_HEIGHT / _S


@functools.lru_cache(maxsize=64)
def _seeded_randoms(seed: int) -> tuple[list, tuple, list[float]]:
    """Terrain edges, initial force and engine dispersions: upstream's np_random calls.

    Upstream draws two dispersions on *every* step (firing or not, also in reset's own
    step), so all draws depend on the seed alone; one vectorised draw yields the same
    PCG64 stream, and the same bits, as upstream's scalar draws.
    """
    rng, _ = seeding.np_random(seed)
    chunks = 11
    height = rng.uniform(0, _H / 2, size=(chunks + 1,))
    chunk_x = [_W / (chunks - 1) * i for i in range(chunks)]
    height[chunks // 2 - 2 : chunks // 2 + 3] = _HELIPAD_Y
    smooth_y = [0.33 * (height[i - 1] + height[i + 0] + height[i + 1]) for i in range(chunks)]
    edges = [((chunk_x[i], smooth_y[i]), (chunk_x[i + 1], smooth_y[i + 1]))
             for i in range(chunks - 1)]
    force = tuple(rng.uniform(-upstream.INITIAL_RANDOM, upstream.INITIAL_RANDOM) for _ in range(2))
    dispersions = (rng.uniform(-1.0, +1.0, size=2 * (MAX_STEPS + 1)) / _S).tolist()
    return edges, force, dispersions


def _body_def(body_type: int, **kwargs) -> Box2D.b2BodyDef:
    """A reusable body definition (upstream passes the same kwargs on every reset)."""
    return Box2D.b2BodyDef(type=body_type, **kwargs)


class FastLunarLander(upstream.LunarLander):
    """Discrete LunarLander-v3 (default kwargs, no rendering) with a lean `advance`.

    Reuse one instance for many rollouts; every `reset` needs a seed. Engine particles
    are never created (upstream creates them only when rendering); np_random is unused.
    """

    def __init__(self) -> None:
        super().__init__()
        x0, y0, dyn = _W / 2, _H, Box2D.b2_dynamicBody  # upstream's initial_x, initial_y
        self._moon_def = _body_def(Box2D.b2_staticBody,
                                   shapes=edgeShape(vertices=[(0, 0), (_W, 0)]))
        self._edge = edgeShape()
        self._edge_fixture = fixtureDef(shape=self._edge, density=0, friction=0.1)
        self._lander_def = _body_def(dyn, position=(x0, y0), angle=0.0, fixtures=fixtureDef(
            shape=polygonShape(vertices=[(x / _S, y / _S) for x, y in upstream.LANDER_POLY]),
            density=5.0, friction=0.1, categoryBits=0x0010, maskBits=0x001, restitution=0.0))
        self._leg_defs = [_body_def(
            dyn, position=(x0 - i * upstream.LEG_AWAY / _S, y0), angle=(i * 0.05), fixtures=fixtureDef(
                shape=polygonShape(box=(upstream.LEG_W / _S, upstream.LEG_H / _S)), density=1.0,
                restitution=0.0, categoryBits=0x0020, maskBits=0x001)) for i in [-1, +1]]
        self._joint_defs = [revoluteJointDef(
            localAnchorA=(0, 0), localAnchorB=(i * upstream.LEG_AWAY / _S, upstream.LEG_DOWN / _S),
            enableMotor=True, enableLimit=True, maxMotorTorque=upstream.LEG_SPRING_TORQUE,
            motorSpeed=+0.3 * i, lowerAngle=+0.9 - 0.5 if i == -1 else -0.9,
            upperAngle=+0.9 if i == -1 else -0.9 + 0.5) for i in [-1, +1]]
        self._listener = upstream.ContactDetector(self)
        self._disp: list[float] = []
        self._t = 0  # steps taken in this world, reset's own step included

    def reset(self, *, seed: int, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Build a new world as upstream does (same calls, same order), then its no-op step."""
        if seed is None:
            raise ValueError("FastLunarLander.reset needs an explicit seed")
        edges, force, self._disp = _seeded_randoms(seed)
        self.world = world = Box2D.b2World(gravity=(0, self.gravity))
        world.contactListener = self._listener
        self.game_over, self.prev_shaping, self._t, self.helipad_y = False, None, 0, _HELIPAD_Y
        self.moon = world.CreateBody(self._moon_def)
        for p1, p2 in edges:  # CreateFixture copies the shape, so one edgeShape serves all
            self._edge.vertex1, self._edge.vertex2 = p1, p2
            self.moon.CreateFixture(self._edge_fixture)
        self.lander = world.CreateBody(self._lander_def)
        self.lander.ApplyForceToCenter(force, True)
        self.legs = []
        for leg_def, joint_def in zip(self._leg_defs, self._joint_defs):
            leg = world.CreateBody(leg_def)
            leg.ground_contact = False
            joint_def.bodyA, joint_def.bodyB = self.lander, leg
            joint_def.referenceAngle = leg.angle - self.lander.angle  # as pybox2d's kwargs init
            leg.joint = world.CreateJoint(joint_def)
            self.legs.append(leg)
        return np.array(self.advance(0)[0], dtype=np.float32), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Gym-style step, with the 1000-step time limit (fast_rollout uses `advance`)."""
        state, reward, terminated = self.advance(action)
        return np.array(state, dtype=np.float32), reward, terminated, self._t > MAX_STEPS, {}

    def advance(self, action: int) -> tuple[list[float], float, bool]:
        """One step with upstream's arithmetic in plain floats; the state is not yet float32.

        The engines use the lander pose read after the previous world.Step (nothing moves
        the lander in between), which saves four Box2D property reads per firing step.
        """
        lander, t = self.lander, self._t
        self._t = t + 1
        m_power = s_power = 0.0
        if action:
            px, py, angle = self._pose
            tip0, tip1 = math.sin(angle), math.cos(angle)
            side0, side1 = -tip1, tip0
            d0, d1 = self._disp[2 * t], self._disp[2 * t + 1]
            if action == 2:
                m_power = 1.0
                ox = tip0 * (_MAIN_Y + 2 * d0) + side0 * d1
                oy = -tip1 * (_MAIN_Y + 2 * d0) - side1 * d1
                power, at = upstream.MAIN_ENGINE_POWER, (px + ox, py + oy)
                lander.ApplyLinearImpulse((-ox * power * m_power, -oy * power * m_power), at, True)
            else:
                s_power = 1.0
                direction = action - 2
                ox = tip0 * d0 + side0 * (3 * d1 + direction * upstream.SIDE_ENGINE_AWAY / _S)
                oy = -tip1 * d0 - side1 * (3 * d1 + direction * upstream.SIDE_ENGINE_AWAY / _S)
                power = upstream.SIDE_ENGINE_POWER
                at = (px + ox - tip0 * 17 / _S, py + oy + tip1 * _SIDE_Y)
                lander.ApplyLinearImpulse((-ox * power * s_power, -oy * power * s_power), at, True)
        self.world.Step(1.0 / _FPS, 6 * 30, 2 * 30)

        pos, vel, legs = lander.position, lander.linearVelocity, self.legs
        px, py, angle = pos.x, pos.y, lander.angle
        self._pose = px, py, angle
        x, y = (px - _HALF_W) / _HALF_W, (py - _PAD_Y) / _HALF_H
        vx, vy = vel.x * _HALF_W / _FPS, vel.y * _HALF_H / _FPS
        leg0 = 1.0 if legs[0].ground_contact else 0.0
        leg1 = 1.0 if legs[1].ground_contact else 0.0
        state = [x, y, vx, vy, angle, 20.0 * lander.angularVelocity / _FPS, leg0, leg1]
        shaping = (-100 * math.sqrt(x * x + y * y) - 100 * math.sqrt(vx * vx + vy * vy)
                   - 100 * abs(angle) + 10 * leg0 + 10 * leg1)  # math.sqrt == np.sqrt, bitwise
        reward = 0.0 if self.prev_shaping is None else shaping - self.prev_shaping
        self.prev_shaping = shaping
        reward = reward - m_power * 0.30 - s_power * 0.03
        if not lander.awake:  # checked last upstream, so it wins
            return state, 100.0, True
        if self.game_over or abs(x) >= 1.0:
            return state, -100.0, True
        return state, reward, False


# ================================================================================================
# The algorithm: an archive of elites, emitters that propose solutions, a scheduler tying them
# ================================================================================================

GRID_DIMS = (50, 50)
MEASURE_RANGES = ((-1.0, 1.0), (-3.0, 0.0))  # impact x-position, impact y-velocity
MEASURE_LABELS = ("Impact x-position", "Impact y-velocity")
QD_SCORE_OFFSET = -600.0  # almost every policy scores above -600, so QD score counts every elite

# One row per algorithm, in the spirit of pyribs' examples/sphere.py: the archive's extra kwargs,
# whether a separate result archive keeps the elites, and the emitter class with its kwargs, each
# a small function of the run's config. All rows share the grid, the seeds, x0 and the batch size,
# so every algorithm asks n_emitters * batch_size solutions per iteration.
# - cma_me: the tutorial's CMA-ME (EvolutionStrategyEmitter, two-stage improvement ranker).
# - cma_mae: pyribs' CMA-MAE tutorial and sphere.py's "cma_mae" row: a soft archive with
#   learning_rate (--learning_rate, 0.01 there) and threshold_min (0 there for objectives in
#   [0, 100]; here the QD offset -600, below almost every episode's reward), a plain result archive
#   of the same grid that keeps the best solutions (metrics, heatmaps and archive.pkl come from
#   it), and emitters with the "imp" ranker, "mu" selection and "basic" restarts.
# - map_elites: sphere.py's "map_elites" row: GaussianEmitters that mutate random elites with a
#   fixed sigma (--sigma0). The policy argmax(W @ obs) ignores W's scale and the search starts
#   from zeros, so only sigma relative to the elites' weights matters, as for CMA-ES's sigma0.
ALGORITHMS: dict[str, dict[str, Any]] = {
    "cma_me": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config["sigma0"], "ranker": "2imp"},
    },
    "cma_mae": {
        "archive": lambda config: {"learning_rate": config["learning_rate"],
                                   "threshold_min": QD_SCORE_OFFSET},
        "result_archive": True,
        "emitter": "EvolutionStrategyEmitter",
        "emitter_kwargs": lambda config: {"sigma0": config["sigma0"], "ranker": "imp",
                                          "selection_rule": "mu", "restart_rule": "basic"},
    },
    "map_elites": {
        "archive": lambda config: {},
        "result_archive": False,
        "emitter": "GaussianEmitter",
        "emitter_kwargs": lambda config: {"sigma": config["sigma0"]},
    },
}


def derive_seeds(seed: int, count: int) -> list[int]:
    """Independent seeds for the archive and each emitter, all fixed by the one run seed."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(count)]


def build_scheduler(config: dict[str, Any], x0: np.ndarray | None = None):
    """The archive, emitters and scheduler of `config["algorithm"]`, seeded from `config["seed"]`.

    The emitters start from `x0` (default: zeros, as in the tutorial).
    """
    from ribs.archives import GridArchive
    from ribs import emitters as ribs_emitters
    from ribs.schedulers import Scheduler

    spec = ALGORITHMS[config["algorithm"]]
    # A result archive's seed comes last, so the other seeds are those of a run without one.
    archive_seed, *emitter_seeds, result_seed = derive_seeds(config["seed"], config["n_emitters"] + 2)
    grid = dict(solution_dim=SOLUTION_DIM, dims=GRID_DIMS, ranges=MEASURE_RANGES,
                qd_score_offset=QD_SCORE_OFFSET)
    archive = GridArchive(**grid, seed=archive_seed, **spec["archive"](config))
    result_archive = GridArchive(**grid, seed=result_seed) if spec["result_archive"] else None
    emitter_class = getattr(ribs_emitters, spec["emitter"])
    emitters = [
        emitter_class(
            archive,
            x0=np.zeros(SOLUTION_DIM) if x0 is None else x0,
            batch_size=config["batch_size"],
            seed=emitter_seed,
            **spec["emitter_kwargs"](config),
        )
        for emitter_seed in emitter_seeds
    ]
    return Scheduler(archive, emitters, result_archive=result_archive)


# ================================================================================================
# The evaluation engine: batches of rollouts on a Dask cluster
# ================================================================================================

_WORKER_ENVS: dict[bool, gym.Env] = {}  # one environment per worker process, reused across tasks


def evaluate_chunk(solutions: np.ndarray, env_seed: int, fast_env: bool = True) -> np.ndarray:
    """Runs on a worker: roll out a chunk of solutions; rows of (objective, x, y-velocity).

    A chunk of solutions per task (not one task per solution) keeps the scheduler's per-task cost
    small next to the rollouts, and the environment is kept between tasks: reset(seed) gives the
    same episode bit for bit as a fresh environment, without paying for gym.make each time.
    """
    env = _WORKER_ENVS.get(fast_env)
    if env is None:
        env = _WORKER_ENVS[fast_env] = make_env(fast_env)
    return np.array([rollout(solution, env_seed, env) for solution in solutions]).reshape(-1, 3)


CHUNKS_PER_WORKER = 4  # enough chunks to even out episodes of 60 to 1000 steps across workers


def by_reference(function: Callable) -> Callable:
    """The same function, reached through this script's import name instead of `__main__`.

    Dask pickles functions of `__main__` by value into every task; through the module name they
    travel as a short reference that workers resolve by importing this script.
    """
    if function.__module__ != "__main__":
        return function
    return getattr(importlib.import_module(Path(__file__).stem), function.__name__)


def evaluate(client, solutions: np.ndarray, env_seed: int,
             fast_env: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Objectives and measures of `solutions`, in their order, evaluated on the Dask cluster.

    Results come back in the order of the solutions whatever the number of workers, so a fixed
    seed gives the same archive on 1 or 100 workers. Tasks of a worker that dies are retried.
    """
    workers = max(1, sum(client.nthreads().values()))
    chunks = np.array_split(solutions, min(len(solutions), CHUNKS_PER_WORKER * workers))
    futures = client.map(
        by_reference(evaluate_chunk), chunks, env_seed=env_seed, fast_env=fast_env, pure=False,
        retries=3,
    )
    results = np.concatenate(client.gather(futures))
    return results[:, 0], results[:, 1:]


@contextlib.contextmanager
def dask_client(workers: int, scheduler_address: str | None, log: logging.Logger) -> Iterator[Any]:
    """A Dask client: of an existing cluster if `scheduler_address` is given (left running on
    exit), else of a new local cluster of `workers` single-threaded processes (shut down on exit).

    A local cluster listens on localhost only: it runs whatever code it is sent.
    """
    from dask.distributed import Client, LocalCluster
    from distributed.diagnostics.plugin import UploadFile

    if scheduler_address:
        with Client(scheduler_address, timeout="30s") as client:
            # Workers elsewhere have the libraries but not this script (or an older copy): ship
            # this one to every worker, including those that join later. Only workers run it.
            client.register_plugin(UploadFile(str(Path(__file__).resolve())))
            log.info(f"Dask cluster at {scheduler_address}: {len(client.nthreads())} worker(s); "
                     f"dashboard {client.dashboard_link}")
            yield client
        return
    # A busy port 8787 (another run's dashboard) is fine: Dask picks another and we print it.
    warnings.filterwarnings("ignore", message="Port 8787 is already in use")
    with LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address="127.0.0.1:8787",
        silence_logs=logging.ERROR,
    ) as cluster, Client(cluster) as client:
        log.info(f"Dask cluster: {workers} worker process(es); dashboard {client.dashboard_link}")
        yield client


# ================================================================================================
# The run loop: ask -> evaluate -> tell, with metrics and checkpoints
# ================================================================================================

class StopRequests:
    """Ctrl-C and SIGTERM, acted on only where stopping is safe.

    A signal only records the request, except inside `interruptible()` (waiting for the cluster's
    results), where it stops the wait at once. So a stop never cuts a checkpoint write, an import
    or a tell in half: the iteration in flight is abandoned and the last completed one is kept.
    """

    def __init__(self) -> None:
        self.requested = False
        self._raise_now = False

    def install(self) -> None:
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, self._on_signal)

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.requested = True
        if self._raise_now:
            self._raise_now = False
            raise KeyboardInterrupt

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        self.check()
        self._raise_now = True
        try:
            yield
        finally:
            self._raise_now = False


STOP = StopRequests()
CHECKPOINT_FORMAT = "lunar_lander.checkpoint/1"
UMASK = os.umask(0o022)
os.umask(UMASK)


def atomic_write(path: Path, write: Callable[[Any], None], mode: str = "wb") -> None:
    """Write `path` via a temporary file and os.replace, so a crash never leaves half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.chmod(tmp, 0o666 & ~UMASK)  # mkstemp makes files private; outputs are ordinary files
        with os.fdopen(fd, mode) as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_json(path: Path, data: Any) -> None:
    atomic_write(path, lambda f: json.dump(data, f, indent=2), mode="w")


def write_pickle(path: Path, obj: Any) -> None:
    atomic_write(path, lambda f: pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL))


def iteration_metrics(archive, iteration: int, evaluations: int, elapsed: float) -> dict:
    """One row of metrics.json: the archive's state after `iteration` iterations."""
    stats = archive.stats
    return {
        "iteration": iteration,
        "evaluations": evaluations,
        "coverage": float(stats.coverage),
        "num_elites": int(stats.num_elites),
        "qd_score": float(stats.qd_score),
        "best_objective": float(stats.obj_max) if stats.num_elites else None,
        "mean_objective": float(stats.obj_mean) if stats.num_elites else None,
        "elapsed_s": round(elapsed, 3),
    }


def make_checkpoint(scheduler_bytes: bytes, metrics: list[dict], config: dict) -> dict:
    """Everything needed to continue a run. The scheduler is pickled as one object: its emitters
    share its archive, and CMA-ES state and RNGs come along, so a resumed run asks the same."""
    return {
        "format": CHECKPOINT_FORMAT,
        "scheduler": pickle.loads(scheduler_bytes),
        "metrics": list(metrics),
        "iteration": metrics[-1]["iteration"] if metrics else 0,  # metrics may start at iteration 0
        "config": config,
    }


def run_loop(run_dir: Path, checkpoint: dict, client, iterations: int, log: logging.Logger) -> dict:
    """Iterate ask -> evaluate -> tell up to `iterations`, refreshing outputs every log_every.

    After each tell the scheduler is snapshotted in memory (pickled, ~1 ms): a stop while the cluster
    evaluates (ask has already moved the emitters on) or any error still writes a checkpoint of the
    last completed iteration. The iteration in flight is abandoned, never half-recorded.
    """
    from tqdm import tqdm

    config, scheduler, metrics = checkpoint["config"], checkpoint["scheduler"], checkpoint["metrics"]
    snapshot = pickle.dumps(scheduler, protocol=pickle.HIGHEST_PROTOCOL)
    start = checkpoint["iteration"]
    elapsed = metrics[-1]["elapsed_s"] if metrics else 0.0
    evaluations = metrics[-1]["evaluations"] if metrics else 0
    bar = tqdm(range(start + 1, iterations + 1), initial=start, total=iterations, unit="it",
               desc="search", dynamic_ncols=True)
    try:
        for iteration in bar:
            STOP.check()
            tic = time.perf_counter()
            solutions = scheduler.ask()
            with STOP.interruptible():
                objectives, measures = evaluate(client, solutions, config["env_seed"], config["fast_env"])
            scheduler.tell(objectives, measures)
            elapsed += time.perf_counter() - tic
            evaluations += len(solutions)
            snapshot = pickle.dumps(scheduler, protocol=pickle.HIGHEST_PROTOCOL)
            row = iteration_metrics(scheduler.result_archive, iteration, evaluations, elapsed)
            metrics.append(row)
            bar.set_postfix(coverage=f"{row['coverage']:.3f}", qd=f"{row['qd_score']:.4g}",
                            best=f"{row['best_objective'] or float('nan'):.1f}", refresh=False)
            if iteration % config["log_every"] == 0 and iteration < iterations:
                log.info(describe_progress(row, iterations))
                save_outputs(run_dir, make_checkpoint(snapshot, metrics, config))
    except BaseException:
        bar.close()
        if metrics and metrics[-1]["iteration"] > start:  # iterations done since the last save
            write_pickle(run_dir / "checkpoint.pkl", make_checkpoint(snapshot, metrics, config))
        raise
    bar.close()
    return make_checkpoint(snapshot, metrics, config)


def describe_progress(row: dict, iterations: int) -> str:
    best = row["best_objective"]
    return (f"iteration {row['iteration']}/{iterations}: {row['evaluations']} evaluations, "
            f"coverage {row['coverage']:.3f}, QD score {row['qd_score']:.0f}, "
            f"best {best if best is None else round(best, 1)}, "
            f"{row['elapsed_s'] / max(row['iteration'], 1):.2f} s/iteration")


# ================================================================================================
# The outputs: archive files, heatmaps and progress plots in the run folder
# ================================================================================================

HEATMAP_RANGE = (-300, 300)


def save_heatmap(archive, path: Path, title: str) -> None:
    """The tutorial's heatmap: objective per cell, faster impacts at the bottom."""
    import matplotlib.pyplot as plt
    from ribs.visualize import grid_archive_heatmap

    fig, ax = plt.subplots(figsize=(8, 6))
    grid_archive_heatmap(archive, ax=ax, vmin=HEATMAP_RANGE[0], vmax=HEATMAP_RANGE[1])
    ax.invert_yaxis()
    ax.set_xlabel(MEASURE_LABELS[0])
    ax.set_ylabel(MEASURE_LABELS[1])
    ax.set_title(title)
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100, bbox_inches="tight"))
    plt.close(fig)


PROGRESS_PANELS = (("qd_score", "QD score"), ("coverage", "Coverage"),
                   ("best_objective", "Best objective"))


def save_progress_plot(metrics: list[dict], path: Path) -> None:
    """QD score, coverage and best objective over iterations, side by side."""
    save_metric_panels({"": metrics}, "iteration", "Iteration", path)


def save_metric_panels(runs: dict[str, list[dict]], x_key: str, x_label: str, path: Path) -> None:
    """One panel per metric of PROGRESS_PANELS, one line per run (labelled if it has a label)."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PROGRESS_PANELS), figsize=(15, 4))
    for ax, (key, label) in zip(axes, PROGRESS_PANELS):
        for run_label, metrics in runs.items():
            values = [np.nan if row[key] is None else row[key] for row in metrics]
            ax.plot([row[x_key] for row in metrics], values, label=run_label or None)
        ax.set_xlabel(x_label)
        ax.set_title(label)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    if any(runs):  # beside the panels, where it hides no curve
        axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1), fontsize="small")
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=100, bbox_inches="tight"))
    plt.close(fig)


def save_outputs(run_dir: Path, checkpoint: dict) -> None:
    """Refresh every file of the run folder from a checkpoint; the checkpoint goes first."""
    write_pickle(run_dir / "checkpoint.pkl", checkpoint)
    write_json(run_dir / "metrics.json", checkpoint["metrics"])
    archive = checkpoint["scheduler"].result_archive
    iteration = checkpoint["iteration"]
    write_pickle(run_dir / "archive.pkl", archive)
    table = archive.data(return_type="pandas")
    atomic_write(run_dir / "archive.csv", lambda f: table.to_csv(f, index=False), mode="w")
    title = f"{checkpoint['config']['algorithm']} after {iteration} iterations"
    save_heatmap(archive, run_dir / "heatmaps" / f"heatmap_{iteration:05d}.png", title)
    save_heatmap(archive, run_dir / "heatmap.png", title)
    save_progress_plot(checkpoint["metrics"], run_dir / "progress.png")


# ================================================================================================
# The commands
# ================================================================================================


def library_versions() -> dict[str, str]:
    from importlib.metadata import version

    packages = ["ribs", "gymnasium", "box2d", "dask", "distributed", "numpy"]
    return {"python": platform.python_version(), **{name: version(name) for name in packages}}


def positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise UsageError(f"--{name} must be a positive whole number, got {value!r}")
    return value


def non_negative_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise UsageError(f"--{name} must be a whole number >= 0, got {value!r}")
    return value


def positive_float(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise UsageError(f"--{name} must be a positive number, got {value!r}")
    return float(value)


def fraction(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise UsageError(f"--{name} must be a number in (0, 1], got {value!r}")
    return float(value)


def boolean(name: str, value: Any) -> bool:
    """Fire passes --flag=false as the string 'false' (and --flag alone as True)."""
    words = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if str(value).lower() in words:
        return words[str(value).lower()]
    raise UsageError(f"--{name} must be true or false, got {value!r}")


def one_of(choices: dict) -> Callable[[str, Any], str]:
    def check(name: str, value: Any) -> str:
        if value not in choices:
            raise UsageError(f"--{name} must be one of {', '.join(choices)}, got {value!r}")
        return value
    return check


# How each search flag is checked; None (a drawn seed, a default folder) passes unchecked.
FLAG_CHECKS: dict[str, Callable[[str, Any], Any]] = {
    "iterations": positive_int,
    "workers": positive_int,
    "seed": non_negative_int,
    "env_seed": non_negative_int,
    "algorithm": one_of(ALGORITHMS),
    "n_emitters": positive_int,
    "sigma0": positive_float,
    "batch_size": positive_int,
    "learning_rate": fraction,
    "log_every": positive_int,
    "fast_env": boolean,
}


def check_flags(flags: dict[str, Any]) -> dict[str, Any]:
    return {name: value if value is None or name not in FLAG_CHECKS
            else FLAG_CHECKS[name](name, value) for name, value in flags.items()}


def prepare_run_dir(outdir: str | None, seed: int) -> Path:
    """A new, empty, writable run folder: an existing run is never written over."""
    if outdir is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        run_dir = Path("outputs") / f"{stamp}_seed{seed}"
        run_dir = next(p for p in [run_dir, *(Path(f"{run_dir}_{i}") for i in range(2, 1000))]
                       if not p.exists())
    else:
        run_dir = Path(outdir)
    if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
        raise UsageError(f"{run_dir} already exists and is not empty; choose another --outdir "
                         f"(to continue a run there: python lunar_lander.py resume {run_dir})")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(run_dir / ".write_test", lambda f: f.write(b""))
        os.unlink(run_dir / ".write_test")
    except OSError as error:
        raise UsageError(f"cannot write the run folder {run_dir}: {error.strerror or error}") from None
    return run_dir


def make_logger(run_dir: Path) -> logging.Logger:
    """Messages go to the console and, appended, to the run folder's run.log."""
    log = logging.getLogger("lunar_lander")
    log.setLevel(logging.INFO)
    log.propagate = False
    for handler in list(log.handlers):
        log.removeHandler(handler)
        handler.close()
    console = logging.StreamHandler(sys.stdout)
    logfile = logging.FileHandler(run_dir / "run.log", encoding="utf-8")
    logfile.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%Y-%m-%d %H:%M:%S"))
    for handler in (console, logfile):
        log.addHandler(handler)
    return log


def execute(run_dir: Path, iterations: int, workers: int, scheduler_address: str | None,
            begin: Callable[[Any, logging.Logger], dict]) -> dict:
    """Start (or join) a Dask cluster, get the starting checkpoint from `begin`, run the loop and
    write the final outputs. The cluster is shut down however this ends."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    log = make_logger(run_dir)
    with logging_redirect_tqdm(loggers=[log]):
        log.info(f"Run folder: {run_dir}")
        try:
            with dask_client(workers, scheduler_address, log) as client:
                checkpoint = begin(client, log)
                checkpoint = run_loop(run_dir, checkpoint, client, iterations, log)
        except KeyboardInterrupt:
            log.info(f"Stopped. The checkpoint holds the last completed iteration; continue with: "
                     f"python lunar_lander.py resume {run_dir}")
            raise
        save_outputs(run_dir, checkpoint)
        if checkpoint["metrics"]:
            log.info("Done. " + describe_progress(checkpoint["metrics"][-1], iterations))
    return checkpoint


def fresh_checkpoint(config: dict, client, log: logging.Logger, seed_archive=None) -> dict:
    """Iteration 0 of a new run, written at once so the folder always holds a checkpoint.

    With `seed_archive` (a warm start), its elites are first flown again in this run's setting
    (another terrain, say) and inserted, and the emitters start from the best of them.
    """
    metrics, x0, scheduler = [], None, None
    if seed_archive is not None:
        elites = seed_archive.data(["solution"])["solution"]
        objectives, measures = evaluate(client, elites, config["env_seed"], config["fast_env"])
        x0 = elites[int(np.argmax(objectives))]
        scheduler = build_scheduler(config, x0=x0)
        for archive in {id(a): a for a in (scheduler.archive, scheduler.result_archive)}.values():
            archive.add(elites, objectives, measures)
        metrics.append(iteration_metrics(scheduler.result_archive, 0, len(elites), 0.0))
        log.info(f"Warm start: {len(elites)} elites re-evaluated, {metrics[0]['num_elites']} kept; "
                 f"emitters start from the best (objective {objectives.max():.1f})")
    checkpoint = {"format": CHECKPOINT_FORMAT, "scheduler": scheduler or build_scheduler(config),
                  "metrics": metrics, "iteration": 0, "config": config}
    write_pickle(Path(config["outdir"]) / "checkpoint.pkl", checkpoint)
    return checkpoint


def search(
    iterations: int = 300,
    workers: int = 2,
    seed: int | None = None,
    env_seed: int = 52,
    algorithm: str = "cma_me",
    n_emitters: int = 5,
    sigma0: float = 1.0,
    batch_size: int = 30,
    learning_rate: float = 0.01,
    log_every: int = 25,
    outdir: str | None = None,
    scheduler_address: str | None = None,
    from_archive: str | None = None,
    fast_env: bool = True,
) -> None:
    """Search Lunar Lander landings with a QD algorithm and write a run folder.

    Each iteration asks the emitters for solutions, flies them on a local Dask cluster and tells
    the results back. Every log_every iterations (and at the end) the run folder is refreshed:
    checkpoint.pkl, archive.pkl, archive.csv, metrics.json, heatmap.png, heatmaps/, progress.png,
    config.json and run.log. Other commands: resume RUN_DIR (see: lunar_lander.py resume --help),
    compare RUN_DIR... (see: lunar_lander.py compare --help).

    Args:
        iterations: Number of ask-evaluate-tell iterations.
        workers: Number of Dask worker processes (one thread each) evaluating rollouts.
        seed: Seed of the archive and emitters; drawn and recorded in config.json if omitted.
            The same seed gives the same archive whatever the number of workers.
        env_seed: Seed of the Lunar Lander terrain every policy is flown on.
        algorithm: Which QD algorithm: cma_me (the tutorial's CMA-ME), cma_mae (CMA-MAE) or
            map_elites (MAP-Elites with Gaussian mutation); each asks n_emitters * batch_size
            solutions per iteration.
        n_emitters: Number of emitters.
        sigma0: Initial step size of each emitter (CMA-ES sigma); map_elites: the fixed sigma
            of its Gaussian mutation.
        batch_size: Solutions each emitter proposes per iteration.
        learning_rate: cma_mae only: how fast a cell's threshold follows its improvements (0.01:
            pyribs' CMA-MAE setting; 1 makes the archive CMA-ME's).
        log_every: Log a line and refresh the run folder every this many iterations.
        outdir: Run folder; default outputs/<timestamp>_seed<seed>. Must be new or empty.
        scheduler_address: Address of a running Dask scheduler (tcp://HOST:PORT) to evaluate on
            instead of starting a local cluster; --workers is then ignored.
        from_archive: Warm start: an archive.pkl of an earlier run whose elites are re-evaluated
            in this run's setting to fill the archive first; the emitters start from the best.
        fast_env: Fly rollouts in the streamlined LunarLander-v3 (bitwise identical results,
            about a third less time per step); false uses gym.make's plain environment.
    """
    flags = check_flags(dict(locals()))
    seed_archive = load_archive(Path(from_archive)) if from_archive else None
    if flags["seed"] is None:
        flags["seed"] = secrets.randbelow(2**31)
    run_dir = prepare_run_dir(flags["outdir"], flags["seed"])
    config = {**flags, "outdir": str(run_dir), "created": datetime.datetime.now().isoformat(),
              "command": sys.argv, "versions": library_versions()}
    if from_archive:
        config["from_archive"] = str(Path(from_archive).resolve())
    write_json(run_dir / "config.json", config)
    execute(run_dir, config["iterations"], config["workers"], scheduler_address,
            lambda client, log: fresh_checkpoint(config, client, log, seed_archive))


def resume(run_dir: str, iterations: int | None = None, workers: int | None = None,
           scheduler_address: str | None = None) -> None:
    """Continue the run in run_dir from its checkpoint, exactly as if it had never stopped.

    Args:
        run_dir: A run folder written by this script.
        iterations: Total iterations to reach; default: those the run was started with. A larger
            number extends a finished run.
        workers: Number of Dask worker processes; default: as the run was started.
        scheduler_address: Address of a running Dask scheduler to evaluate on instead.
    """
    path = Path(run_dir)
    checkpoint = load_checkpoint(path / "checkpoint.pkl")
    config = checkpoint["config"]
    iterations = positive_int("iterations", config["iterations"] if iterations is None else iterations)
    workers = positive_int("workers", config["workers"] if workers is None else workers)
    if iterations < checkpoint["iteration"]:
        raise UsageError(f"{path} is already at iteration {checkpoint['iteration']}; "
                         f"--iterations must be at least that")
    config = {**config, "iterations": max(iterations, config["iterations"]),
              "resumed": [*config.get("resumed", []), {
                  "at": datetime.datetime.now().isoformat(), "from_iteration": checkpoint["iteration"],
                  "to_iteration": iterations, "workers": workers}]}
    write_json(path / "config.json", config)
    execute(path, iterations, workers, scheduler_address,
            lambda client, log: {**checkpoint, "config": config})


def read_pickle(path: Path, what: str) -> Any:
    """Unpickle a file of ours, or raise a UsageError that names the file and what is wrong.

    Pickles can run code when loaded: only load files you trust (archive.csv is for sharing).
    """
    if not path.is_file():
        raise UsageError(f"{path}: no such file (expected {what})")
    try:
        with open(path, "rb") as file:
            return pickle.load(file)
    except Exception as error:  # truncated, corrupt, or not a pickle at all
        raise UsageError(f"{path}: not a readable {what} ({type(error).__name__}: {error})") from None


def check_archive(archive: Any, path: Path) -> None:
    """The archive must be a grid of this problem: same solution size, grid and measure ranges."""
    from ribs.archives import GridArchive

    if not isinstance(archive, GridArchive):
        raise UsageError(f"{path}: holds a {type(archive).__name__}, not a GridArchive")
    shape = (archive.solution_dim, tuple(archive.dims), np.round(archive.lower_bounds, 9).tolist(),
             np.round(archive.upper_bounds, 9).tolist())
    expected = (SOLUTION_DIM, GRID_DIMS, [lo for lo, _ in MEASURE_RANGES], [hi for _, hi in MEASURE_RANGES])
    if shape != expected:
        raise UsageError(f"{path}: archive of another shape (solution size, grid, lower and upper "
                         f"bounds {shape}; this problem needs {expected})")


def load_archive(path: Path):
    archive = read_pickle(path, "archive pickle")
    check_archive(archive, path)
    if len(archive) == 0:
        raise UsageError(f"{path}: the archive is empty; nothing to start from")
    return archive


def search_defaults() -> dict[str, Any]:
    import inspect

    return {name: parameter.default for name, parameter in inspect.signature(search).parameters.items()}


def load_checkpoint(path: Path) -> dict:
    """A checkpoint written by this script and consistent with this script's problem."""
    if not path.is_file():
        raise UsageError(f"{path}: no checkpoint there (is {path.parent} a run folder of lunar_lander.py?)")
    checkpoint = read_pickle(path, "checkpoint")
    if not isinstance(checkpoint, dict) or checkpoint.get("format") != CHECKPOINT_FORMAT:
        raise UsageError(f"{path}: not a lunar_lander checkpoint (holds a {type(checkpoint).__name__})")
    from ribs.schedulers import Scheduler

    try:
        # A checkpoint from before a flag existed ran with that flag's default.
        config = checkpoint["config"] = {**search_defaults(), **checkpoint["config"]}
        metrics, iteration = checkpoint["metrics"], checkpoint["iteration"]
        check_flags({name: config[name] for name in FLAG_CHECKS})
        if not isinstance(checkpoint["scheduler"], Scheduler):
            raise UsageError(f"holds a {type(checkpoint['scheduler']).__name__}, not a Scheduler")
    except (KeyError, TypeError, UsageError) as error:
        raise UsageError(f"{path}: checkpoint of an incompatible config ({error})") from None
    if [row["iteration"] for row in metrics if row["iteration"] > 0] != list(range(1, iteration + 1)):
        raise UsageError(f"{path}: its metrics do not match its iteration {iteration}")
    check_archive(checkpoint["scheduler"].archive, path)
    return checkpoint


# ================================================================================================
# Comparing runs: QD score, coverage and best objective against evaluations, and a final table
# ================================================================================================

COMPARED = ("evaluations", "coverage", "num_elites", "qd_score", "best_objective", "mean_objective")
SOLVED = 200  # Gymnasium counts an episode reward of 200 or more as solving Lunar Lander


def solved_cells(run_dir: Path) -> int | None:
    """Cells of the final archive holding a landing that solves the task (None without archive.csv):
    QD score and coverage count crashes too; this counts only the good landings."""
    import pandas as pd

    try:
        objectives = pd.read_csv(run_dir / "archive.csv", usecols=["objective"])["objective"]
        return int((objectives >= SOLVED).sum())
    except (OSError, ValueError):
        return None


def read_run_json(run_dir: Path, name: str) -> Any:
    """A JSON file of a run folder, or a UsageError naming what is missing or wrong."""
    path = run_dir / name
    if not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such run folder")
    if not path.is_file():
        raise UsageError(f"{path}: no such file (is {run_dir} a run folder of lunar_lander.py?)")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise UsageError(f"{path}: not readable JSON ({error})") from None


def load_run_metrics(run_dir: Path) -> tuple[dict, list[dict]]:
    """A run's config and its metrics rows (at least one, each with every compared field)."""
    config, metrics = read_run_json(run_dir, "config.json"), read_run_json(run_dir, "metrics.json")
    if not isinstance(config, dict):
        raise UsageError(f"{run_dir / 'config.json'}: not a run config")
    if not (isinstance(metrics, list) and metrics
            and all(isinstance(row, dict) and set(COMPARED) <= row.keys() for row in metrics)):
        raise UsageError(f"{run_dir / 'metrics.json'}: no metrics to compare")
    return config, metrics


SETTING_FLAGS = ("env_seed", "n_emitters", "batch_size", "sigma0", "learning_rate")


def run_setting(config: dict) -> str:
    """The algorithm, and the flags shaping it that differ from their defaults: runs of one
    setting with different seeds are repeats of one experiment."""
    defaults = search_defaults()
    changed = [f"{flag}={config[flag]}" for flag in SETTING_FLAGS
               if flag in config and config[flag] != defaults[flag]]
    return " ".join([str(config.get("algorithm", "?")), *changed])


def run_labels(run_dirs: list[Path], configs: list[dict]) -> list[str]:
    """'setting seed N' for each run, or the folders as given when that would be ambiguous."""
    labels = [f"{run_setting(config)} seed {config.get('seed', '?')}" for config in configs]
    return labels if len(set(labels)) == len(labels) else [str(run_dir) for run_dir in run_dirs]


def comparison_outputs(out: str | None, overwrite: bool) -> tuple[Path, Path]:
    """The PNG and the CSV next to it: by default new files under outputs/; never an existing
    file unless --overwrite."""
    if out is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        candidates = [Path("outputs") / f"compare_{stamp}{suffix}.png" for suffix in
                      ["", *(f"_{i}" for i in range(2, 1000))]]
        png = next(p for p in candidates if not p.exists() and not p.with_suffix(".csv").exists())
    else:
        png = Path(out) if Path(out).suffix.lower() == ".png" else Path(f"{out}.png")
    existing = [str(p) for p in (png, png.with_suffix(".csv")) if p.exists()]
    if existing and not overwrite:
        raise UsageError(f"{' and '.join(existing)} already exist(s); choose another --out "
                         f"or pass --overwrite")
    return png, png.with_suffix(".csv")


def comparison_table(labels: list[str], run_dirs: list[Path], configs: list[dict],
                     runs: list[list[dict]]):
    """One row per run: its final metrics, with the algorithm and seed that produced them."""
    import pandas as pd

    table = pd.DataFrame([
        {"run": label, "folder": str(run_dir), "setting": run_setting(config),
         "seed": config.get("seed"), "iterations": metrics[-1]["iteration"],
         **{key: metrics[-1][key] for key in COMPARED}, f"cells_{SOLVED}+": solved_cells(run_dir)}
        for label, run_dir, config, metrics in zip(labels, run_dirs, configs, runs)
    ])
    table[f"cells_{SOLVED}+"] = pd.to_numeric(table[f"cells_{SOLVED}+"])  # None (no archive.csv): NaN
    return table


def format_table(table) -> str:
    """The table as aligned text, with as many digits as a reader compares."""
    whole, decimals = "{:.0f}".format, "{:.1f}".format
    formats = {"evaluations": whole, "num_elites": whole, "coverage": "{:.4f}".format,
               "qd_score": "{:,.0f}".format, "best_objective": decimals, "mean_objective": decimals,
               f"cells_{SOLVED}+": whole}
    shown = table.drop(columns=["folder"], errors="ignore")
    return shown.to_string(index=False, formatters={k: v for k, v in formats.items() if k in shown})


def compare(*run_dirs: str, out: str | None = None, overwrite: bool = False) -> None:
    """Compare runs: QD score, coverage and best objective against evaluations on one PNG, and a
    table of their final values (printed, and written as CSV next to the PNG).

    Runs of the same batch, iterations and env seed give an equal-budget comparison.

    Args:
        run_dirs: Run folders written by this script (each needs config.json and metrics.json).
        out: The PNG to write (the CSV gets the same name with .csv); default: a new
            outputs/compare_<timestamp>.png.
        overwrite: Replace the PNG and CSV if they already exist.
    """
    if not run_dirs:
        raise UsageError("compare needs at least one run folder: "
                         "python lunar_lander.py compare RUN_A RUN_B ...")
    overwrite = boolean("overwrite", overwrite)
    paths = [Path(str(run_dir)) for run_dir in run_dirs]
    configs, runs = zip(*(load_run_metrics(path) for path in paths))
    png, csv = comparison_outputs(None if out is None else str(out), overwrite)
    labels = run_labels(paths, list(configs))
    table = comparison_table(labels, paths, list(configs), list(runs))
    try:
        save_metric_panels(dict(zip(labels, runs)), "evaluations", "Evaluations", png)
        atomic_write(csv, lambda f: table.to_csv(f, index=False), mode="w")
    except OSError as error:
        raise UsageError(f"cannot write {png} and {csv}: {error.strerror or error}") from None
    print(format_table(table.drop(columns=["setting"])))  # the run's label names its setting
    if table["evaluations"].nunique() > 1:
        print("note: the runs end at different numbers of evaluations; compare at an equal budget")
    if table["setting"].duplicated().any():
        numbers = [*COMPARED, f"cells_{SOLVED}+"]
        means = table.groupby("setting", sort=False)[numbers].mean().reset_index()
        print("\nmean over the runs of each setting (the seeds of one algorithm and flags):\n"
              + format_table(means))
    print(f"wrote {png} and {csv}")


# ================================================================================================
# Command-line entry point
# ================================================================================================

COMMANDS: dict[str, Callable] = {"search": search, "resume": resume, "compare": compare}


def reject_unknown_flags(command: Callable, args: list[str]) -> None:
    """Fire would print a page of usage for a mistyped flag; one line naming it is clearer."""
    import inspect

    known = set(inspect.signature(command).parameters)
    for arg in args:
        if arg.startswith("--") and arg not in ("--help", "--"):
            name = arg[2:].split("=", 1)[0].replace("-", "_")
            if name not in known:
                raise UsageError(f"unknown flag --{name}; valid flags: "
                                 + ", ".join(f"--{flag}" for flag in known))


def main(argv: list[str]) -> int:
    import fire

    name = argv[0] if argv and not argv[0].startswith("-") else "search"
    args = argv[1:] if argv and not argv[0].startswith("-") else argv
    STOP.install()
    try:
        if name not in COMMANDS:
            raise UsageError(f"unknown command {name!r}; commands: {', '.join(COMMANDS)}")
        reject_unknown_flags(COMMANDS[name], args)
        fire.Fire(COMMANDS[name], command=args, name="lunar_lander.py" if name == "search" else name)
    except UsageError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
