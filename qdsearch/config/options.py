"""The checks of what a run's flags make together.

Map:
- (settings.py's ROW_FLAGS, POLICY_FLAGS and BUDGETS, read here:) `own_flags` and `ignores`,
  `refuse_unused_row_flags` (an algorithm's or a policy's own flag given where no row uses it);
- what values make together, on the values while a config is made (dicts): `checked` (a value
  through its flag's check), `with_task` (a config's measures, checked against its task, and its
  archive's cells), `with_dim`, `with_offset`, `legacy_offset`, `resumed_budget`, `with_budget`;
  `search_defaults` and `before_the_flags` (what runs recorded before a flag existed ran with);
- what a made config may not hold (a RunConfig): `check_sizes` (`solutions_per_iteration`,
  `check_rollouts`: the sizes flags make together), `check_memory`, `check_learning` (a
  learning row's task and library).
"""

from __future__ import annotations

import importlib.util
import os
from typing import Any

from qdsearch.algorithms import (
    ALGORITHMS,
    MAX_CELLS,
    evaluations_per_iteration,
    memory_needed,
)
from qdsearch.base.flags import (
    UsageError,
    named,
)
from qdsearch.config.settings import (
    BUDGETS,
    DEFAULT_CVT_CELLS,
    DEFAULT_GRID,
    MAX_GRID_MEASURES,
    MAX_ITERATIONS,
    MAX_ROLLOUTS,
    MAX_SOLUTIONS,
    ROW_FLAGS,
    SEARCH_FLAGS,
    RunConfig,
    unchecked,
)
from qdsearch.tasks import (
    DEFAULT_ENV,
    ENVIRONMENTS,
    MEASURES,
    check_episode,
    episode_of,
    family_measures,
    has_gradients,
    shape_of,
)
from qdsearch.tasks.policies import POLICIES

# The flags only some algorithms use (each row of ALGORITHMS names its own).


def own_flags(algorithm: str) -> tuple[str, ...]:
    """The flags only some algorithms use that this one does (cma_mae: learning_rate), as its
    row of ALGORITHMS declares."""
    return ALGORITHMS[algorithm].flags


def ignores(algorithm: str, flag: str) -> bool:
    """Whether the algorithm ignores the flag (another algorithm's own, like cma_mae's rate)."""
    return flag in ROW_FLAGS and flag not in own_flags(algorithm)


def refuse_unused_row_flags(algorithms: list[str], given: list[str], policies: list[str]) -> None:
    """A row's own flag (cma_mae's --learning_rate, the mlp policy's --hidden) given to rows none
    of which use it (of `algorithms`, of `policies`) is refused, as an unknown flag is: it would
    be recorded and silently change nothing. So are two budgets: --evaluations sets the
    iterations."""
    if set(BUDGETS) <= set(given):
        raise UsageError(f"{named('iterations')} and {named('evaluations')} are two budgets; give one")
    for table, rows, one, several in ((ALGORITHMS, algorithms, named("algorithm"), named("algorithms")),
                                      (POLICIES, policies, named("policy"), named("policy"))):
        chosen = list(dict.fromkeys(row for row in rows if row in table))  # others: refused later
        for typed in given:
            users = [name for name, row in table.items() if typed in row.flags]
            if chosen and users and not set(chosen) & set(users):
                who = (f"{one} {chosen[0]} does not" if len(chosen) == 1
                       else f"none of {several} {', '.join(chosen)}")
                raise UsageError(f"{named(typed)} is a flag of {', '.join(users)} only; {who} use it")


def check_sizes(config: RunConfig) -> None:
    """The sizes that flags make together are bounded too: the archive's cells, the solutions
    asked per iteration (a DQD row's gradient batch too) and the rollouts they are flown in."""
    solutions, made_by = solutions_per_iteration(config)
    if config.archive == "grid" and (cells := config.grid ** len(config.measures)) > MAX_CELLS:
        raise UsageError(f"{named('grid')} {config.grid} with {len(config.measures)} measures makes "
                         f"{cells:,} cells; at most {MAX_CELLS:,}")
    if solutions > MAX_SOLUTIONS:
        raise UsageError(f"{made_by} asks {solutions:,} solutions per iteration; at most {MAX_SOLUTIONS:,}")
    check_rollouts(solutions, len(config.env_seed), "per iteration")


def solutions_per_iteration(config: RunConfig) -> tuple[int, str]:
    """The solutions an iteration asks, and the flags that make the number: n_emitters x
    batch_size, or a DQD row's emitters each with its point and gradient samples if more (ME-ES's:
    their samples), so that a refusal names the flag to lower."""
    n_emitters, batch, row = config.n_emitters, config.batch_size, ALGORITHMS[config.algorithm]
    if row.es_steps:
        samples = config.es_samples
        return n_emitters * samples, f"{named('n_emitters')} {n_emitters} x {named('es_samples')} {samples}"
    made = {f"{named('n_emitters')} {n_emitters} x {named('batch_size')} {batch}": n_emitters * batch}
    if row.samples:
        samples = config.es_samples
        gradients = f"{named('n_emitters')} {n_emitters} x (1 + {named('es_samples')} {samples})"
        made[gradients] = n_emitters * (1 + samples)
    made_by = max(made, key=made.get)  # the first of equals: the batch
    return made[made_by], made_by


def check_rollouts(solutions: int, terrains: int, when: str) -> None:
    """At most MAX_ROLLOUTS rollouts in one batch: their results are held at once."""
    if solutions * terrains > MAX_ROLLOUTS:
        raise UsageError(f"{solutions:,} solutions on {terrains:,} env seed(s) make "
                         f"{solutions * terrains:,} rollouts {when}; at most {MAX_ROLLOUTS:,}")


def checked(name: str, value: Any) -> Any:
    """A value checked as the flag `name` of SEARCH_FLAGS checks it (None included: refused)."""
    return SEARCH_FLAGS[name].check(name, value)


def with_task(config: dict[str, Any]) -> dict[str, Any]:
    """The config with its task's default measures if it names none, its measures checked against
    its task (a walker has no impact x), and its archive's cells: --grid for a grid (at most
    MAX_GRID_MEASURES measures), --cells for a CVT (at least 2^measures: fewer cells can't tell
    apart even the two halves of each measure's range)."""
    env = config["env"]
    task = ENVIRONMENTS[env]
    measures = list(task.measures if config.get("measures") is None else config["measures"])
    if wrong := [name for name in measures if task.family not in MEASURES[name].families]:
        raise UsageError(f"{named('measures')} {wrong[0]} is not a measure of {named('env')} {env}; its "
                         "measures: "
                         + ", ".join(family_measures(task.family)))
    archive, grid, cells = config.get("archive") or task.archive, config.get("grid"), config.get("cells")
    if archive == "grid":
        if cells is not None:
            raise UsageError(f"{named('cells')} is for {named('archive')} cvt; a grid archive has "
                             f"{named('grid')} cells along "
                             "each measure")
        if len(measures) > MAX_GRID_MEASURES:
            raise UsageError(f"{named('measures')}: {len(measures)} measures on a grid archive; a grid takes "
                             f"at most {MAX_GRID_MEASURES} (its cells grow as {named('grid')}^measures): use "
                             f"{named('archive')} cvt")
        grid = DEFAULT_GRID if grid is None else grid
    else:
        if grid is not None:
            raise UsageError(f"{named('grid')} is for {named('archive')} grid; a CVT archive has "
                             f"{named('cells')} centroids")
        cells = DEFAULT_CVT_CELLS if cells is None else cells
        if cells < 2 ** len(measures):
            raise UsageError(f"{named('cells')} {cells} is too few for {len(measures)} measures: a CVT "
                             "archive "
                             f"needs at least 2^{len(measures)} = {2 ** len(measures)} cells")
    config = {**config, "env": env, "measures": measures, "archive": archive, "grid": grid, "cells": cells}
    check_episode(env, episode_of(unchecked(config)))
    return with_budget(with_dim(config))


# What a benchmark function has no use for: the flags of episodes and of networks.
EPISODE_FLAGS = ("episode_length", "terminate_when_unhealthy")


def with_dim(config: dict[str, Any]) -> dict[str, Any]:
    """A benchmark function's --dim (its own unless given), and what it can't take refused: an
    episode's flags, a network, a row that learns from episodes (the learning rows' transitions,
    ME-ES's observations). --dim is refused for a Gymnasium task, whose size its spaces give, and
    a row of exact gradients for a task that has none."""
    env, dim, task = config["env"], config.get("dim"), ENVIRONMENTS[config["env"]]
    row = ALGORITHMS.get(config.get("algorithm") or "")
    if row is not None and row.exact and not has_gradients(env):
        algorithm = config["algorithm"]
        raise UsageError(f"{named('algorithm')} {algorithm} takes a benchmark function's exact "
                         f"gradients; {named('env')} {env} has none ({algorithm}_es estimates them)")
    if not task.function:
        if dim is not None:
            raise UsageError(f"{named('dim')} is for the benchmark functions; {named('env')} {env} takes its "
                             "size from its spaces")
        return config
    if dim is not None and dim < 2:
        raise UsageError(f"{named('dim')} {dim}: a benchmark function takes 2 coordinates at least")
    if given := [name for name in EPISODE_FLAGS if config.get(name) is not None]:
        raise UsageError(f"{named(given[0])}: {named('env')} {env} is a benchmark function, with no episode")
    if (config.get("policy") or "linear") != "linear":
        raise UsageError(f"{named('policy')} {config['policy']}: a solution of {named('env')} {env} is its "
                         "point (the linear policy of one constant input)")
    if row is not None and (row.es_steps or row.learns is not None):
        raise UsageError(f"{named('algorithm')} {config['algorithm']} learns from episodes; {named('env')} "
                         f"{env} is a benchmark function, with none")
    return {**config, "dim": dim or task.dim}


def with_offset(config: dict[str, Any]) -> dict[str, Any]:
    """The config's --qd_offset: its task's for its episode's length unless given or recorded
    (each run of an experiment its own: a swept --episode_length has offsets of its own)."""
    if config.get("qd_offset") is not None:
        return config
    length = episode_of(unchecked(config)).length
    return {**config, "qd_offset": ENVIRONMENTS[config["env"]].returns(length).offset}


def legacy_offset(recorded: dict[str, Any]) -> dict[str, Any]:
    """What a run recorded before --qd_offset ran with: its task's offset at the task's own
    episode length, whatever its --episode_length (the offsets did not follow the episode then)."""
    env = recorded.get("env", DEFAULT_ENV)  # (a recorded qd_offset is laid over this: upgrade)
    return {"qd_offset": ENVIRONMENTS[env].returns().offset} if env in ENVIRONMENTS else {}


def resumed_budget(config: dict[str, Any], iterations: int | None, evaluations: int | None) -> dict[str, Any]:
    """A run's iterations and evaluations once resumed to `iterations` or `evaluations` (one of
    them, or neither: its own): a budget in iterations past its own drops its evaluations."""
    if iterations is not None and evaluations is not None:
        raise UsageError(f"{named('iterations')} and {named('evaluations')} are two budgets; give one")
    if evaluations is not None:
        return with_budget({**config, "evaluations": checked("evaluations", evaluations)})
    if iterations is None:
        return config
    iterations = checked("iterations", iterations)
    return {**config, "iterations": iterations,
            "evaluations": None if iterations > config["iterations"] else config.get("evaluations")}


def with_budget(config: dict[str, Any]) -> dict[str, Any]:
    """With --evaluations, the iterations are the most whose evaluations fit in it (every
    iteration of a row flies as many: evaluations_per_iteration)."""
    if config.get("evaluations") is None or config.get("algorithm") is None:  # (an experiment's
        return config  # flags common to its algorithms: each run's config has its own)
    per_iteration = evaluations_per_iteration(unchecked(config))
    if config["evaluations"] < per_iteration:
        raise UsageError(f"{named('evaluations')} {config['evaluations']:,} is less than one iteration of "
                         f"{named('algorithm')} {config['algorithm']}, which flies {per_iteration:,}")
    return {**config, "iterations": min(config["evaluations"] // per_iteration, MAX_ITERATIONS)}


def check_memory(config: RunConfig) -> None:
    """Refuse, before anything is written, a row whose emitters and archives would not fit in the
    machine's memory with this policy (a full CMA-ES covariance grows as the weights squared:
    ~3.5 GB at Ant-v5's 21,000 weights of a 128x128 network), naming the rows that fit."""
    weights = config.network.size(shape_of(config))
    room = MEMORY_SHARE * physical_memory()

    def needs(algorithm: str) -> float:
        return memory_needed(config.replace(algorithm=algorithm), weights)

    if (needed := needs(config.algorithm)) <= room:
        return
    fits = [name for name in ALGORITHMS if needs(name) <= room]
    raise UsageError(f"{named('algorithm')} {config.algorithm} would hold ~{needed / 1e9:,.1f} GB for "
                     f"{weights:,} weights ({config.n_emitters} emitters), more than "
                     f"{MEMORY_SHARE:.0%} of this machine's {room / MEMORY_SHARE / 1e9:.1f} GB; rows "
                     f"that fit: {', '.join(fits) or 'none'} (or fewer emitters, a smaller "
                     f"{named('hidden')} or {named('buffer_size')})")


def check_learning(config: RunConfig) -> None:
    """A learning row (one with a TD3 critic: ALGORITHMS' `learns`) needs a task whose actions are
    a box (the critic takes the action as an input, the actor's gradient goes through it) and the
    optional JAX (requirements-learning.txt): refused before anything is written, naming either."""
    if ALGORITHMS[config.algorithm].learns is None:
        return
    if not ENVIRONMENTS[config.env].continuous:
        able = [name for name, task in ENVIRONMENTS.items() if task.continuous]
        raise UsageError(f"{named('algorithm')} {config.algorithm} learns a critic of continuous actions; "
                         f"{named('env')} {config.env} has a choice of actions. Tasks it can learn: "
                         f"{', '.join(able)}")
    if importlib.util.find_spec(LEARNING_LIBRARY) is None:
        raise UsageError(f"{named('algorithm')} {config.algorithm} learns with JAX, which is not "
                         "installed: pip install -r requirements-learning.txt")


LEARNING_LIBRARY = "jax"  # what the learning rows' td3.py imports (optional)
MEMORY_SHARE = 0.5  # of the machine's memory a run's driver may plan to hold


def physical_memory() -> float:
    """The machine's memory in bytes."""
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def search_defaults() -> dict[str, Any]:
    return {name: flag.default for name, flag in SEARCH_FLAGS.items()}


def before_the_flags() -> dict[str, Any]:
    """What runs recorded before a flag existed ran with, where that is not today's default."""
    return {name: flag.before for name, flag in SEARCH_FLAGS.items() if flag.before is not None}
