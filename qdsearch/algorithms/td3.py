"""TD3 for the learning rows (pga_me, cma_mega_td3_es), written in JAX as dqd-rl's
src/objectives/gym_control/td3.py writes it in PyTorch (after Fujimoto's TD3): a replay buffer of
every flown transition, a twin critic of the return, a greedy actor trained on it, and the two
ways the rows use the critic: PGA-ME's policy-gradient variation of parents, and CMA-MEGA (TD3,
ES)'s objective gradient at an emitter's point.

JAX is optional (requirements-learning.txt): this module is imported only by a run of a learning
row (search/learning.py), never by the package's other modules.

Bits. Every random draw is numpy's, from the learner's own Generator, pickled with its state: the
buffer's batches and the target noise are drawn here and handed to the compiled steps, which draw
nothing. The compiled steps give the same bits in every process and at any thread count
(docs/learning.md); the command line caps XLA's kernels at AVX2 as it holds numpy's
(base/kernels.py). The learner's whole state is numpy arrays (`state`, `restore`), so a checkpoint
holds no JAX object.

The actor is the run's policy itself (policies.py's layout: each layer's W, row-major, then its
bias; tanh hidden layers, a tanh of the last layer's outputs), so a flat solution of the archive
is an actor and back without conversion. The critic is dqd-rl's: two ReLU networks of
CRITIC_HIDDEN units over (observation, action), PyTorch's default initialisation.

Map:
- the settings: BATCH, DISCOUNT, TAU, POLICY_DELAY, TARGET_NOISE, NOISE_CLIP, ADAM_LR, PG_STEPS,
  PG_LR, PG_BATCH, GRADIENT_STATES, CRITIC_HIDDEN;
- `ReplayBuffer`: a FIFO of transition rows (float32; `columns` says their layout), its `state`;
- `Learner`: `train` (critic steps), `improve` (PGA-ME's variation), `objective_gradients`
  (CMA-MEGA (TD3, ES)'s), `greedy` (the actor's weights), `state` / `restore`;
- the compiled functions (`compiled`): `actor_forward`, `critic_forward`, `adam`, the train step.
"""

from __future__ import annotations

import functools
import types
import warnings
from typing import Any

# JAX warns at any fork once it runs threads: every process the package starts afterwards is a
# fresh interpreter (subprocess's fork and exec, the savers' fork server, Dask's spawned workers),
# never a bare fork that would inherit JAX's threads, so the warning says nothing here.
warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from qdsearch.tasks.policies import Policy, layer_sizes  # noqa: E402
from qdsearch.tasks.transitions import transition_width  # noqa: E402

BATCH = 256  # transitions per critic step (dqd-rl's batch_size)
DISCOUNT = 0.99
TAU = 0.005  # the targets' soft update (dqd-rl's target_update_rate)
POLICY_DELAY = 2  # the actor and the targets move every 2nd critic step (target_update_freq)
TARGET_NOISE = 0.2  # the target action's smoothing noise (smoothing_noise_variance, used as a std)
NOISE_CLIP = 0.5
ADAM_LR = 3e-4  # the critic's and the greedy actor's Adam (adam_learning_rate)
PG_STEPS = 10  # PGA-ME: Adam steps on a parent (gradient_steps)
PG_LR = 1e-3  # and their learning rate (gradient_learning_rate)
PG_BATCH = 256  # states per such step (pg_batch_size)
GRADIENT_STATES = 65_536  # CMA-MEGA (TD3, ES): states averaged for a point's objective gradient
CRITIC_HIDDEN = (256, 256)
ADAM_BETAS, ADAM_EPS = (0.9, 0.999), 1e-8  # PyTorch's Adam defaults


class ReplayBuffer:
    """A FIFO of `capacity` transitions, each a float32 row as tasks/transitions.py records it."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int) -> None:
        self.capacity, self.obs_dim, self.act_dim = capacity, obs_dim, act_dim
        self.rows = np.empty((capacity, transition_width(obs_dim, act_dim)), dtype=np.float32)
        self.next = 0  # where the next row goes
        self.size = 0

    def columns(self) -> dict[str, slice]:
        o, a = self.obs_dim, self.act_dim
        return {"obs": slice(0, o), "action": slice(o, o + a), "reward": slice(o + a, o + a + 1),
                "next_obs": slice(o + a + 1, 2 * o + a + 1), "done": slice(2 * o + a + 1, 2 * o + a + 2)}

    def add(self, rows: np.ndarray) -> None:
        """Append transition rows in order, the oldest overwritten once the buffer is full (rows
        added at once land where added one by one would)."""
        count = len(rows)
        kept = np.asarray(rows, dtype=np.float32)[-self.capacity:]  # the others would be overwritten
        start = (self.next + count - len(kept)) % self.capacity
        fits = min(len(kept), self.capacity - start)  # up to the end, the rest from the start
        self.rows[start:start + fits] = kept[:fits]
        self.rows[:len(kept) - fits] = kept[fits:]
        self.next = int((self.next + count) % self.capacity)
        self.size = min(self.capacity, self.size + count)

    def sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        """Rows drawn uniformly with replacement, in an array of `shape` + (columns,)."""
        return self.rows[rng.integers(0, self.size, size=shape)]

    def state(self) -> dict[str, Any]:
        """The buffer as numpy data: its rows held (in place order) and where the next goes."""
        return {"capacity": self.capacity, "obs_dim": self.obs_dim, "act_dim": self.act_dim,
                "rows": self.rows[:self.size].copy(), "next": self.next}

    @classmethod
    def restore(cls, state: dict[str, Any]) -> ReplayBuffer:
        buffer = cls(state["capacity"], state["obs_dim"], state["act_dim"])
        buffer.rows[:len(state["rows"])] = state["rows"]
        buffer.size, buffer.next = len(state["rows"]), state["next"]
        return buffer


class Learner:
    """The run's TD3: buffer, twin critic and its target, greedy actor and its target, their Adam
    moments, the steps taken and the numpy Generator every draw comes from.

    `shape` is the task's (actions, observations); `policy` the run's, whose layout the actor
    shares; `x0` the greedy actor's start (the run's emitters' start)."""

    def __init__(self, policy: Policy, shape: tuple[int, int], x0: np.ndarray, capacity: int,
                 seed: int) -> None:
        self.shape, self.hidden, self.biases = shape, policy.hidden, policy.row.biases
        self.buffer = ReplayBuffer(capacity, shape[1], shape[0])
        self.rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7D3]))
        critic = [critic_params(self.rng, shape[1] + shape[0]) for _ in range(2)]
        actor = jnp.asarray(x0, dtype=jnp.float32)
        self.critic, self.critic_target, self.critic_opt = critic, critic, adam_state(critic)
        self.actor, self.actor_target, self.actor_opt = actor, actor, adam_state(actor)
        self.steps = 0  # critic steps taken, over the whole run

    @property
    def functions(self) -> Any:
        return compiled(self.shape, self.hidden, self.biases)

    def train(self, steps: int) -> None:
        """`steps` critic steps on batches of the buffer (the actor and targets every
        POLICY_DELAY-th); none while the buffer is empty."""
        if self.buffer.size == 0 or steps == 0:
            return
        batches = self.buffer.sample(self.rng, (steps, BATCH))
        noise = self.rng.standard_normal((steps, BATCH, self.shape[0]), dtype=np.float32)
        carry = (self.critic, self.critic_target, self.critic_opt, self.actor, self.actor_target,
                 self.actor_opt, jnp.int32(self.steps))
        carry = self.functions.train(carry, jnp.asarray(batches), jnp.asarray(noise))
        (self.critic, self.critic_target, self.critic_opt, self.actor, self.actor_target,
         self.actor_opt, _) = carry
        self.steps += steps

    def observations(self, count: int) -> np.ndarray:
        """`count` observations drawn from the buffer."""
        return self.buffer.sample(self.rng, (count,))[:, self.buffer.columns()["obs"]]

    def improve(self, parents: np.ndarray) -> np.ndarray:
        """PGA-ME's variation: each parent after PG_STEPS Adam steps (PG_LR, fresh moments) up the
        critic's first Q over its own PG_STEPS x PG_BATCH states of the buffer; as it is while the
        buffer is empty (a warm start's first iteration: its archive is full, its buffer not)."""
        parents = np.asarray(parents, dtype=np.float64)
        if len(parents) == 0 or self.buffer.size == 0:  # no state to climb on (a warm start's first)
            return parents
        states = self.observations(len(parents) * PG_STEPS * PG_BATCH)
        states = states.reshape(len(parents), PG_STEPS, PG_BATCH, -1)
        improved = self.functions.improve(self.critic[0], jnp.asarray(parents, dtype=jnp.float32),
                                          jnp.asarray(states))
        return np.asarray(improved, dtype=np.float64)

    def objective_gradients(self, points: np.ndarray) -> np.ndarray:
        """The gradient of the critic's first Q, averaged over GRADIENT_STATES states of the
        buffer, at each point's policy; random directions while the buffer is empty (dqd-rl's)."""
        points = np.asarray(points, dtype=np.float64)
        if self.buffer.size == 0:
            return self.rng.standard_normal(points.shape)
        states = jnp.asarray(self.observations(GRADIENT_STATES))
        gradients = self.functions.objective_gradients(jnp.asarray(points, dtype=jnp.float32),
                                                       self.critic[0], states)
        return np.asarray(gradients, dtype=np.float64)

    def greedy(self) -> np.ndarray:
        """The greedy actor's weights, as a solution."""
        return np.asarray(self.actor, dtype=np.float64)

    def state(self) -> dict[str, Any]:
        """Everything but the buffer, as numpy arrays (the buffer: `buffer.state()`)."""
        as_numpy = functools.partial(jax.tree_util.tree_map, np.asarray)
        return {"shape": self.shape, "hidden": self.hidden, "biases": self.biases, "steps": self.steps,
                "rng": self.rng.bit_generator.state,
                **{name: as_numpy(getattr(self, name)) for name in NETWORKS}}

    @classmethod
    def restore(cls, state: dict[str, Any], buffer: dict[str, Any]) -> Learner:
        learner = cls.__new__(cls)
        learner.shape, learner.hidden = tuple(state["shape"]), tuple(state["hidden"])
        learner.biases = state["biases"]
        learner.steps, learner.rng = state["steps"], np.random.default_rng()
        learner.rng.bit_generator.state = state["rng"]
        for name in NETWORKS:
            setattr(learner, name, jax.tree_util.tree_map(jnp.asarray, state[name]))
        learner.buffer = ReplayBuffer.restore(buffer)
        return learner


NETWORKS = ("critic", "critic_target", "critic_opt", "actor", "actor_target", "actor_opt")


def critic_params(rng: np.random.Generator, inputs: int) -> list[tuple[jnp.ndarray, jnp.ndarray]]:
    """One critic's layers (W as inputs x outputs, b), drawn as PyTorch's nn.Linear draws them:
    uniform in +-1/sqrt(inputs)."""
    widths, layers = [inputs, *CRITIC_HIDDEN, 1], []
    for fan_in, fan_out in zip(widths[:-1], widths[1:]):
        bound = 1.0 / np.sqrt(fan_in)
        layers.append((jnp.asarray(rng.uniform(-bound, bound, (fan_in, fan_out)), dtype=jnp.float32),
                       jnp.asarray(rng.uniform(-bound, bound, fan_out), dtype=jnp.float32)))
    return layers


def adam_state(params: Any) -> tuple[Any, Any, jnp.ndarray]:
    """Adam's first and second moments (zeros like `params`) and its step count."""
    zeros = jax.tree_util.tree_map(jnp.zeros_like, params)
    return zeros, zeros, jnp.int32(0)


def adam(params: Any, grads: Any, state: tuple, lr: float) -> tuple[Any, tuple]:
    """One step of PyTorch's Adam (bias-corrected moments, eps outside the root)."""
    m, v, t = state
    t = t + 1
    (b1, b2), tree = ADAM_BETAS, jax.tree_util.tree_map
    m = tree(lambda m, g: b1 * m + (1 - b1) * g, m, grads)
    v = tree(lambda v, g: b2 * v + (1 - b2) * g * g, v, grads)
    params = tree(lambda p, m, v: p - lr * (m / (1 - b1 ** t)) / (jnp.sqrt(v / (1 - b2 ** t)) + ADAM_EPS),
                  params, m, v)
    return params, (m, v, t)


@functools.lru_cache(maxsize=8)
def compiled(shape: tuple[int, int], hidden: tuple[int, ...], biases: bool) -> Any:
    """The compiled steps for one task shape and policy (compiled once per process)."""
    sizes = layer_sizes(shape, hidden)
    obs_dim, act_dim = shape[1], shape[0]

    def actor_forward(flat: jnp.ndarray, obs: jnp.ndarray) -> jnp.ndarray:
        """Actions of the policy `flat` for rows of observations (policies.py's forward pass)."""
        at, h = 0, obs
        for out, inputs in sizes:
            weights = flat[at:at + out * inputs].reshape(out, inputs)
            at += out * inputs
            h = h @ weights.T
            if biases:
                h, at = h + flat[at:at + out], at + out
            h = jnp.tanh(h)  # hidden layers, and the last one's tanh for a box of actions
        return h

    def critic_forward(layers: list, obs: jnp.ndarray, actions: jnp.ndarray) -> jnp.ndarray:
        h = jnp.concatenate([obs, actions], axis=-1)
        for weights, bias in layers[:-1]:
            h = jax.nn.relu(h @ weights + bias)
        weights, bias = layers[-1]
        return (h @ weights + bias)[..., 0]

    def value(flat: jnp.ndarray, q1: list, obs: jnp.ndarray) -> jnp.ndarray:
        """The critic's first Q of the policy's actions, averaged over the states."""
        return critic_forward(q1, obs, actor_forward(flat, obs)).mean()

    columns = ReplayBuffer(1, obs_dim, act_dim).columns()

    def train_step(carry: tuple, batch: tuple) -> tuple[tuple, None]:
        critic, critic_target, critic_opt, actor, actor_target, actor_opt, steps = carry
        rows, noise = batch
        obs, actions = rows[:, columns["obs"]], rows[:, columns["action"]]
        reward, done = rows[:, columns["reward"]][:, 0], rows[:, columns["done"]][:, 0]
        next_obs = rows[:, columns["next_obs"]]
        smoothing = jnp.clip(noise * TARGET_NOISE, -NOISE_CLIP, NOISE_CLIP)
        next_actions = jnp.clip(actor_forward(actor_target, next_obs) + smoothing, -1.0, 1.0)
        target_q = jnp.minimum(critic_forward(critic_target[0], next_obs, next_actions),
                               critic_forward(critic_target[1], next_obs, next_actions))
        target = jax.lax.stop_gradient(reward + (1.0 - done) * DISCOUNT * target_q)

        def critic_loss(twin: list) -> jnp.ndarray:
            return sum(((critic_forward(q, obs, actions) - target) ** 2).mean() for q in twin)

        critic, critic_opt = adam(critic, jax.grad(critic_loss)(critic), critic_opt, ADAM_LR)
        steps = steps + 1

        def delayed(parts: tuple) -> tuple:
            actor, actor_target, actor_opt, critic_target = parts
            grads = jax.grad(lambda flat: -value(flat, critic[0], obs))(actor)
            actor, actor_opt = adam(actor, grads, actor_opt, ADAM_LR)
            soft = functools.partial(jax.tree_util.tree_map, lambda t, p: TAU * p + (1 - TAU) * t)
            return actor, soft(actor_target, actor), actor_opt, soft(critic_target, critic)

        actor, actor_target, actor_opt, critic_target = jax.lax.cond(
            steps % POLICY_DELAY == 0, delayed, lambda parts: parts,
            (actor, actor_target, actor_opt, critic_target))
        return (critic, critic_target, critic_opt, actor, actor_target, actor_opt, steps), None

    @jax.jit
    def train(carry: tuple, batches: jnp.ndarray, noise: jnp.ndarray) -> tuple:
        return jax.lax.scan(train_step, carry, (batches, noise))[0]

    def improve_one(q1: list, flat: jnp.ndarray, states: jnp.ndarray) -> jnp.ndarray:
        def step(carry: tuple, obs: jnp.ndarray) -> tuple[tuple, None]:
            flat, opt = carry
            grads = jax.grad(lambda flat: -value(flat, q1, obs))(flat)
            return adam(flat, grads, opt, PG_LR), None
        return jax.lax.scan(step, (flat, adam_state(flat)), states)[0][0]

    improve = jax.jit(jax.vmap(improve_one, in_axes=(None, 0, 0)))
    objective_gradients = jax.jit(jax.vmap(jax.grad(value), in_axes=(0, None, None)))
    return types.SimpleNamespace(train=train, improve=improve, objective_gradients=objective_gradients,
                                 actor_forward=actor_forward)
