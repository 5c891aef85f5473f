"""A streamlined LunarLander-v3: the same episode, bit for bit, for less of the cost (what a step
costs each way: benchmarks/bench_evaluation.py, its figures in docs/performance.md).

gym.make's env spends much of each step outside Box2D: wrappers, an action-space check, numpy
calls on 8 floats, two RNG draws, rebuilding body definitions on reset. This copy mirrors
gymnasium 1.4.0's lunar_lander.py operation for operation without those costs; the tests
(tests/test_fast_lander.py) compare it with gym.make over many policies on every run: re-run them
after upgrading gymnasium.

Map:
- the world's geometry in Box2D units (WIDTH, HEIGHT, HALF_W, PAD_Y...), which the results
  commands also use to draw a terrain and a lander;
- `seeded_randoms`: every random draw an episode makes, from its seed alone;
- `FastLunarLander`: the env, with `reset(seed=...)`, a gym-style `step` and the lean `advance`.
"""

from __future__ import annotations

import functools
import math

import Box2D
import numpy as np
from Box2D.b2 import edgeShape, fixtureDef, polygonShape, revoluteJointDef
from gymnasium.envs.box2d import lunar_lander as upstream
from gymnasium.utils import seeding

MAX_STEPS = 1000  # the TimeLimit gym.make("LunarLander-v3") adds
SCALE, FPS = upstream.SCALE, upstream.FPS
WIDTH, HEIGHT = upstream.VIEWPORT_W / SCALE, upstream.VIEWPORT_H / SCALE
# Same expressions as upstream, hence the same bits.
HALF_W, HALF_H = upstream.VIEWPORT_W / SCALE / 2, upstream.VIEWPORT_H / SCALE / 2
HELIPAD_Y = HEIGHT / 4
PAD_Y = HELIPAD_Y + upstream.LEG_DOWN / SCALE  # the lander's centre at rest on the pad: y = 0
_MAIN_Y, _SIDE_Y = upstream.MAIN_ENGINE_Y_LOCATION / SCALE, upstream.SIDE_ENGINE_HEIGHT / SCALE


@functools.lru_cache(maxsize=64)
def seeded_randoms(seed: int) -> tuple[list, tuple, list[float]]:
    """Terrain edges, initial force and engine dispersions: upstream's np_random calls.

    Upstream draws two dispersions on *every* step (firing or not, also in reset's own
    step), so all draws depend on the seed alone; one vectorised draw yields the same
    PCG64 stream, and the same bits, as upstream's scalar draws.
    """
    rng, _ = seeding.np_random(seed)
    chunks = 11
    height = rng.uniform(0, HEIGHT / 2, size=(chunks + 1,))
    chunk_x = [WIDTH / (chunks - 1) * i for i in range(chunks)]
    height[chunks // 2 - 2 : chunks // 2 + 3] = HELIPAD_Y
    smooth_y = [0.33 * (height[i - 1] + height[i + 0] + height[i + 1]) for i in range(chunks)]
    edges = [((chunk_x[i], smooth_y[i]), (chunk_x[i + 1], smooth_y[i + 1]))
             for i in range(chunks - 1)]
    force = tuple(rng.uniform(-upstream.INITIAL_RANDOM, upstream.INITIAL_RANDOM) for _ in range(2))
    dispersions = (rng.uniform(-1.0, +1.0, size=2 * (MAX_STEPS + 1)) / SCALE).tolist()
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
        x0, y0, dyn = WIDTH / 2, HEIGHT, Box2D.b2_dynamicBody  # upstream's initial_x, initial_y
        self._moon_def = _body_def(Box2D.b2_staticBody,
                                   shapes=edgeShape(vertices=[(0, 0), (WIDTH, 0)]))
        self._edge = edgeShape()
        self._edge_fixture = fixtureDef(shape=self._edge, density=0, friction=0.1)
        self._lander_def = _body_def(dyn, position=(x0, y0), angle=0.0, fixtures=fixtureDef(
            shape=polygonShape(vertices=[(x / SCALE, y / SCALE) for x, y in upstream.LANDER_POLY]),
            density=5.0, friction=0.1, categoryBits=0x0010, maskBits=0x001, restitution=0.0))
        self._leg_defs = [_body_def(
            dyn, position=(x0 - i * upstream.LEG_AWAY / SCALE, y0), angle=(i * 0.05), fixtures=fixtureDef(
                shape=polygonShape(box=(upstream.LEG_W / SCALE, upstream.LEG_H / SCALE)), density=1.0,
                restitution=0.0, categoryBits=0x0020, maskBits=0x001)) for i in [-1, +1]]
        self._joint_defs = [revoluteJointDef(
            localAnchorA=(0, 0), localAnchorB=(i * upstream.LEG_AWAY / SCALE, upstream.LEG_DOWN / SCALE),
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
        edges, force, self._disp = seeded_randoms(seed)
        self.world = world = Box2D.b2World(gravity=(0, self.gravity))
        world.contactListener = self._listener
        self.game_over, self.prev_shaping, self._t, self.helipad_y = False, None, 0, HELIPAD_Y
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
                ox = tip0 * d0 + side0 * (3 * d1 + direction * upstream.SIDE_ENGINE_AWAY / SCALE)
                oy = -tip1 * d0 - side1 * (3 * d1 + direction * upstream.SIDE_ENGINE_AWAY / SCALE)
                power = upstream.SIDE_ENGINE_POWER
                at = (px + ox - tip0 * 17 / SCALE, py + oy + tip1 * _SIDE_Y)
                lander.ApplyLinearImpulse((-ox * power * s_power, -oy * power * s_power), at, True)
        self.world.Step(1.0 / FPS, 6 * 30, 2 * 30)

        pos, vel, legs = lander.position, lander.linearVelocity, self.legs
        px, py, angle = pos.x, pos.y, lander.angle
        self._pose = px, py, angle
        x, y = (px - HALF_W) / HALF_W, (py - PAD_Y) / HALF_H
        vx, vy = vel.x * HALF_W / FPS, vel.y * HALF_H / FPS
        leg0 = 1.0 if legs[0].ground_contact else 0.0
        leg1 = 1.0 if legs[1].ground_contact else 0.0
        state = [x, y, vx, vy, angle, 20.0 * lander.angularVelocity / FPS, leg0, leg1]
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
