#!/usr/bin/env python
"""Which autodiff library for the TD3 rows (PGA-ME, CMA-MEGA (TD3, ES)): their learning at dqd-rl's
sizes on this machine's CPU, with PyTorch or with JAX, and whether it is bitwise repeatable.

The work of one generation, as dqd-rl sets it (config/algorithms/td3.gin, pga_me.gin,
cma_mega_td3_es.gin): a twin critic (obs + act -> 256 -> 256 -> 1, ReLU) trained 300 steps on
batches of 256 (TD3: smoothed target actions, min of the target twins, the actor and the soft
target updates every 2nd step; Adam at 3e-4); PGA-ME's policy-gradient variation of 49 parents,
each 10 Adam steps (1e-3) of -Q1(s, pi(s)) on its own batch of 256; CMA-MEGA (TD3, ES)'s objective
gradient, -Q1(s, pi(s)) over 65,536 states, with respect to the policy's weights (obs -> 128 ->
128 -> act, tanh). The networks are written by hand in each library (no torch.nn, no flax), so
both do the same arithmetic.

Each part is timed `rounds` times (the median is printed), and the parameters after a fixed
sequence are hashed: run twice, and with 1 and 2 threads, equal hashes mean bitwise repeatable.
Run it with a Python that has the library (docs/learning.md says how they were installed):

    /tmp/vt/bin/python benchmarks/bench_autodiff.py --library torch --env Hopper-v5
    /tmp/vj/bin/python benchmarks/bench_autodiff.py --library jax --env Hopper-v5 --threads 1
"""

from __future__ import annotations

import hashlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

import fire
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CRITIC, POLICY, BATCH, STATES = (256, 256), (128, 128), 256, 65_536
CRITIC_STEPS, PARENTS, PG_STEPS = 300, 49, 10
GAMMA, TAU, NOISE, CLIP = 0.99, 0.005, 0.2, 0.5


def shapes(env: str) -> tuple[int, int]:
    """(actions, observations) of a task (qdsearch's ENVIRONMENTS)."""
    import qdsearch

    qdsearch.hold_kernels()
    from qdsearch import tasks

    return tasks.ENVIRONMENTS[env].shape


def layer_sizes(inputs: int, hidden: tuple[int, ...], outputs: int) -> list[tuple[int, int]]:
    sizes = [inputs, *hidden, outputs]
    return list(zip(sizes[:-1], sizes[1:]))


def initial(rng: np.random.Generator, sizes: list[tuple[int, int]]) -> list[np.ndarray]:
    """Glorot-uniform weights and zero biases, float32, as a flat list [W1, b1, W2, b2, ...]."""
    params = []
    for fan_in, fan_out in sizes:
        bound = np.sqrt(6 / (fan_in + fan_out))
        params += [rng.uniform(-bound, bound, (fan_in, fan_out)).astype(np.float32),
                   np.zeros(fan_out, np.float32)]
    return params


def replay(rng: np.random.Generator, obs: int, act: int, size: int = 100_000) -> dict[str, np.ndarray]:
    """A replay buffer of made-up transitions (the arithmetic does not depend on their values)."""
    return {"obs": rng.normal(size=(size, obs)).astype(np.float32),
            "act": rng.uniform(-1, 1, (size, act)).astype(np.float32),
            "rew": rng.normal(size=size).astype(np.float32),
            "next": rng.normal(size=(size, obs)).astype(np.float32),
            "done": (rng.random(size) < 0.01).astype(np.float32)}


def torch_parts(act: int, obs: int, threads: int):
    """The three parts of a generation, in PyTorch (CPU, deterministic algorithms)."""
    import torch

    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    rng = np.random.default_rng(0)
    as_t = lambda arrays: [torch.tensor(a, requires_grad=True) for a in arrays]  # noqa: E731
    critic_sizes = layer_sizes(obs + act, CRITIC, 1)
    q1, q2 = as_t(initial(rng, critic_sizes)), as_t(initial(rng, critic_sizes))
    actor = as_t(initial(rng, layer_sizes(obs, POLICY, act)))
    targets = [[p.detach().clone() for p in net] for net in (q1, q2, actor)]
    buffer = {k: torch.tensor(v) for k, v in replay(rng, obs, act).items()}
    critic_opt = torch.optim.Adam(q1 + q2, lr=3e-4)
    actor_opt = torch.optim.Adam(actor, lr=3e-4)
    generator = torch.Generator().manual_seed(1)

    def mlp(params, x, out=None, relu=True):
        for i in range(0, len(params) - 2, 2):
            x = (torch.relu if relu else torch.tanh)(x @ params[i] + params[i + 1])
        x = x @ params[-2] + params[-1]
        return torch.tanh(x) if out == "tanh" else x

    def q(params, o, a):
        return mlp(params, torch.cat([o, a], 1))

    def pi(params, o):
        return mlp(params, o, "tanh", relu=False)

    def critic_steps():
        for step in range(CRITIC_STEPS):
            rows = torch.randint(len(buffer["obs"]), (BATCH,), generator=generator)
            o, a, r, n, d = (buffer[k][rows] for k in ("obs", "act", "rew", "next", "done"))
            with torch.no_grad():
                noise = (torch.randn(a.shape, generator=generator) * NOISE).clamp(-CLIP, CLIP)
                na = (pi(targets[2], n) + noise).clamp(-1, 1)
                lowest = torch.minimum(q(targets[0], n, na), q(targets[1], n, na))
                target = r[:, None] + GAMMA * (1 - d[:, None]) * lowest
            loss = ((q(q1, o, a) - target) ** 2).mean() + ((q(q2, o, a) - target) ** 2).mean()
            critic_opt.zero_grad()
            loss.backward()
            critic_opt.step()
            if step % 2:
                actor_loss = -q(q1, o, pi(actor, o)).mean()
                actor_opt.zero_grad()
                actor_loss.backward()
                actor_opt.step()
                with torch.no_grad():
                    for net, target_net in zip((q1, q2, actor), targets):
                        for p, t in zip(net, target_net):
                            t.mul_(1 - TAU).add_(TAU * p)

    def pg_variation():
        for _ in range(PARENTS):
            child = [p.detach().clone().requires_grad_(True) for p in actor]
            opt = torch.optim.Adam(child, lr=1e-3)
            rows = torch.randint(len(buffer["obs"]), (BATCH * PG_STEPS,), generator=generator)
            for step in range(PG_STEPS):
                o = buffer["obs"][rows[step * BATCH:(step + 1) * BATCH]]
                loss = -q(q1, o, pi(child, o)).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()

    def objective_gradient():
        rows = torch.randint(len(buffer["obs"]), (STATES,), generator=generator)
        o = buffer["obs"][rows]
        child = [p.detach().clone().requires_grad_(True) for p in actor]
        (-q(q1, o, pi(child, o)).mean()).backward()
        return torch.cat([p.grad.flatten() for p in child])

    def state():
        return [p.detach().numpy() for p in q1 + q2 + actor]

    return critic_steps, pg_variation, objective_gradient, state


def jax_parts(act: int, obs: int, threads: int):
    """The three parts of a generation, in JAX (CPU; jit-compiled; Adam by hand)."""
    os.environ["XLA_FLAGS"] = " ".join([f"--xla_cpu_multi_thread_eigen={'true' if threads > 1 else 'false'}",
                                        os.environ.get("XLA_FLAGS", "")])
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    q1, q2 = initial(rng, layer_sizes(obs + act, CRITIC, 1)), initial(rng, layer_sizes(obs + act, CRITIC, 1))
    actor = initial(rng, layer_sizes(obs, POLICY, act))
    buffer = {k: jnp.asarray(v) for k, v in replay(rng, obs, act).items()}

    def mlp(params, x, tanh_out):
        for i in range(0, len(params) - 2, 2):
            x = (jnp.tanh if tanh_out else jax.nn.relu)(x @ params[i] + params[i + 1])
        x = x @ params[-2] + params[-1]
        return jnp.tanh(x) if tanh_out else x

    def q(params, o, a):
        return mlp(params, jnp.concatenate([o, a], 1), False)

    def adam(params, grads, m, v, t, lr):
        m = [0.9 * mi + 0.1 * g for mi, g in zip(m, grads)]
        v = [0.999 * vi + 0.001 * g * g for vi, g in zip(v, grads)]
        scale = lr * jnp.sqrt(1 - 0.999 ** t) / (1 - 0.9 ** t)
        return [p - scale * mi / (jnp.sqrt(vi) + 1e-8) for p, mi, vi in zip(params, m, v)], m, v

    zeros = lambda params: [jnp.zeros_like(p) for p in params]  # noqa: E731

    @jax.jit
    def critic_step(carry, key):
        (q1, q2, actor, t1, t2, ta, cm, cv, am, av, step) = carry
        k1, k2 = jax.random.split(key)
        rows = jax.random.randint(k1, (BATCH,), 0, len(buffer["obs"]))
        o, a, r, n, d = (buffer[k][rows] for k in ("obs", "act", "rew", "next", "done"))
        noise = jnp.clip(jax.random.normal(k2, a.shape) * NOISE, -CLIP, CLIP)
        na = jnp.clip(mlp(ta, n, True) + noise, -1, 1)
        target = r[:, None] + GAMMA * (1 - d[:, None]) * jnp.minimum(q(t1, n, na), q(t2, n, na))

        def loss(critics):
            return ((q(critics[0], o, a) - target) ** 2).mean() + ((q(critics[1], o, a) - target) ** 2).mean()

        grads = jax.grad(loss)((q1, q2))
        flat, cm, cv = adam(q1 + q2, grads[0] + grads[1], cm, cv, step + 1, 3e-4)
        q1, q2 = flat[:len(q1)], flat[len(q1):]

        def delayed(args):
            actor, t1, t2, ta, am, av = args
            g = jax.grad(lambda p: -q(q1, o, mlp(p, o, True)).mean())(actor)
            actor, am, av = adam(actor, g, am, av, step // 2 + 1, 3e-4)
            soft = lambda net, tgt: [(1 - TAU) * t + TAU * p for p, t in zip(net, tgt)]  # noqa: E731
            return actor, soft(q1, t1), soft(q2, t2), soft(actor, ta), am, av

        actor, t1, t2, ta, am, av = jax.lax.cond(step % 2 == 1, delayed, lambda args: args,
                                                 (actor, t1, t2, ta, am, av))
        return (q1, q2, actor, t1, t2, ta, cm, cv, am, av, step + 1), None

    @jax.jit
    def pg_parent(q1, actor, key):
        rows = jax.random.randint(key, (PG_STEPS, BATCH), 0, len(buffer["obs"]))

        def one(carry, batch):
            child, m, v, t = carry
            o = buffer["obs"][batch]
            g = jax.grad(lambda p: -q(q1, o, mlp(p, o, True)).mean())(child)
            child, m, v = adam(child, g, m, v, t + 1, 1e-3)
            return (child, m, v, t + 1), None

        return jax.lax.scan(one, (actor, zeros(actor), zeros(actor), 0), rows)[0][0]

    @jax.jit
    def objective(q1, actor, key):
        o = buffer["obs"][jax.random.randint(key, (STATES,), 0, len(buffer["obs"]))]
        grads = jax.grad(lambda p: -q(q1, o, mlp(p, o, True)).mean())(actor)
        return jnp.concatenate([g.ravel() for g in grads])

    carry = [(q1, q2, actor, [p for p in q1], [p for p in q2], [p for p in actor],
              zeros(q1 + q2), zeros(q1 + q2), zeros(actor), zeros(actor), 0)]
    keys = {"key": jax.random.PRNGKey(1)}

    def next_key():
        keys["key"], key = jax.random.split(keys["key"])
        return key

    def critic_steps():
        carry[0], _ = jax.lax.scan(critic_step, carry[0], jax.random.split(next_key(), CRITIC_STEPS))
        jax.block_until_ready(carry[0])

    def pg_variation():
        for _ in range(PARENTS):
            jax.block_until_ready(pg_parent(carry[0][0], carry[0][2], next_key()))

    def objective_gradient():
        return jax.block_until_ready(objective(carry[0][0], carry[0][2], next_key()))

    def state():
        return [np.asarray(p) for p in carry[0][0] + carry[0][1] + carry[0][2]]

    return critic_steps, pg_variation, objective_gradient, state


PARTS = {"torch": torch_parts, "jax": jax_parts}


def bench(library: str = "torch", env: str = "Hopper-v5", threads: int = 1, rounds: int = 3) -> None:
    """Print (and append to benchmarks/autodiff_results.json) each part's median seconds and the
    hash of the parameters after one round of each."""
    act, obs = shapes(env)
    critic_steps, pg_variation, objective_gradient, state = PARTS[library](act, obs, threads)
    first = {}
    for name, part in (("critic_300_steps", critic_steps), ("pg_variation_49_parents", pg_variation),
                       ("objective_gradient_65536", objective_gradient)):
        clock = time.perf_counter()
        part()  # the first call: JAX compiles here
        first[name] = time.perf_counter() - clock
    digest = hashlib.sha256(b"".join(np.ascontiguousarray(p).tobytes() for p in state())).hexdigest()[:16]
    timed = {}
    for name, part in (("critic_300_steps", critic_steps), ("pg_variation_49_parents", pg_variation),
                       ("objective_gradient_65536", objective_gradient)):
        times = []
        for _ in range(rounds):
            clock = time.perf_counter()
            part()
            times.append(time.perf_counter() - clock)
        timed[name] = round(statistics.median(times), 4)
    row = {"library": library, "version": version(library), "env": env, "threads": threads,
           "median_s": timed, "first_call_s": {k: round(v, 3) for k, v in first.items()},
           "params_after_one_round": digest, "xla_flags": os.environ.get("XLA_FLAGS", ""),
           "date": time.strftime("%Y-%m-%d"),
           "command": " ".join(["python", *sys.argv])}
    print(json.dumps(row, indent=1))
    out = Path(__file__).with_name("autodiff_results.json")
    rows = json.loads(out.read_text()) if out.exists() else []
    out.write_text(json.dumps([*rows, row], indent=1) + "\n")


def version(library: str) -> str:
    return __import__(library).__version__


if __name__ == "__main__":
    fire.Fire(bench)
