#!/usr/bin/env python
"""Search Gymnasium's Lunar Lander for many different good landings with CMA-ME (pyribs), on Dask;
and other Gymnasium tasks through the same tables: the continuous lander, BipedalWalker (and its
hardcore course), and MuJoCo's Hopper, Walker2d, HalfCheetah and Ant.

The problem, the algorithm and the results follow the pyribs tutorial "Using CMA-ME to Land a Lunar
Lander Like a Space Shuttle"; this script adds what a research run needs around them: a Dask
evaluation engine, seeded and repeatable runs, checkpoints, metrics, plots and a CLI.

    python lunar_lander.py --iterations 300 --workers 2     # search; writes outputs/<run>/
    python lunar_lander.py --algorithm cma_mae               # or map_elites; default cma_me
    python lunar_lander.py --measures fuel,flight_time --env_seed 0-4   # other axes, 5 terrains
    python lunar_lander.py --env Hopper-v5                   # another task: a row of ENVIRONMENTS
    python lunar_lander.py resume outputs/RUN                # continue a run from its checkpoint
    python lunar_lander.py experiment --algorithms "[cma_me, cma_mae]" --seeds 1-5   # many runs
    python lunar_lander.py video outputs/RUN --cells "[(-0.4, -0.1)]"   # or --best, --top K
    python lunar_lander.py elites outputs/RUN --min_objective 200       # table of elites
    python lunar_lander.py trajectories outputs/RUN --top 10            # flight paths picture
    python lunar_lander.py evaluate outputs/RUN --env_seeds 0-19        # robustness on terrains
    python lunar_lander.py explore outputs/RUN                          # browse, watch landings
    python lunar_lander.py compare outputs/RUN_A outputs/EXPERIMENT     # statistics across seeds
    python lunar_lander.py COMMAND --help                    # every flag of a command

The work is done by the package `qdsearch`, one module per role, each opening with a map of
itself; this script is its command line (COMMANDS, `main`: bad input is one line and exit code 2,
a fault of the machine one line and exit code 1; -h or --help anywhere is the command's page,
`help_text`, drawn from the flag tables by qdsearch.flags.help_page). A search tells the
tutorial's story:
1. the problem: a task is a row of ENVIRONMENTS (`qdsearch/lander.py`: the Gymnasium id, the
   linear policy's shape, default measures, QD offset) and a measure a row of MEASURES; an
   episode (`fly_lander`) flies the policy W @ obs, and its total reward is the objective;
2. the flags become a typed, checked RunConfig (`qdsearch/options.py` declares each flag once,
   `qdsearch/run_config.py` makes the config and reads old folders);
3. build the scheduler (`qdsearch/algorithms.py`: a row of ALGORITHMS made into pyribs' archive,
   emitters and Scheduler, seeded from --seed);
4. each iteration (`qdsearch/loop.py`, the one loop of search, resume and experiment): `Run.ask`
   the emitters for solutions, `Run.send` them to the Dask workers in chunks (`qdsearch/engine.py`,
   `qdsearch/cluster.py`), `Run.take` the chunks back, `Run.tell` the scheduler, and every
   log_every iterations checkpoint and refresh the run folder (heatmap, metrics, archive);
5. look at the archive: `qdsearch/results.py` (video, elites, trajectories),
   `qdsearch/evaluation.py` (evaluate: other terrains, the corrected archive),
   `qdsearch/explorer.py` (explore), `qdsearch/comparison.py` (compare).
The package never imports this script.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import os
import signal
import sys
from typing import Any, Callable

from qdsearch.flags import UsageError, as_typed, did_you_mean, flag_table, help_page, one_line, shown, summary
from qdsearch.options import SEARCH_FLAGS, refuse_unused_row_flags
from qdsearch.run_files import RunError, fault_text
from qdsearch.stopping import STOP, Stopped

if __name__ == "__mp_main__":
    # A local worker (Dask spawns its processes from this script): Ctrl-C in a terminal reaches
    # the whole process group, but stopping is the main process's job (it abandons the iteration
    # and closes the cluster), so workers ignore it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# The commands, each the package module and function that implement it: a command's module is
# imported only when it is run, so `--help` and bad input answer without loading the rest.
COMMANDS: dict[str, tuple[str, str]] = {
    "search": ("qdsearch.run", "search"), "resume": ("qdsearch.experiments", "resume"),
    "experiment": ("qdsearch.experiments", "experiment"), "video": ("qdsearch.results", "video"),
    "elites": ("qdsearch.results", "elites"), "trajectories": ("qdsearch.results", "trajectories"),
    "evaluate": ("qdsearch.evaluation", "evaluate"), "explore": ("qdsearch.explorer", "explore"),
    "compare": ("qdsearch.comparison", "compare"), "watch": ("qdsearch.live", "watch"),
}


def command(name: str) -> Callable:
    """The function of a command of COMMANDS."""
    module, function = COMMANDS[name]
    return getattr(importlib.import_module(module), function)


def known_flags(function: Callable) -> list[str]:
    """The flags a command takes: its signature's, and for experiment those of search it passes
    on to every run."""
    parameters = inspect.signature(function).parameters
    known = [name for name, p in parameters.items() if p.kind is not p.VAR_KEYWORD]
    if any(p.kind is p.VAR_KEYWORD for p in parameters.values()):  # experiment's **search_flags
        known += [name for name, flag in SEARCH_FLAGS.items() if not flag.per_run and name not in known]
    return known


def text_flags(function: Callable) -> set[str]:
    """The flags of a command whose checks read the text as typed (Flag.text)."""
    entries = {**{name: SEARCH_FLAGS[name] for name in known_flags(function) if name in SEARCH_FLAGS},
               **flag_table(function)}
    return {name for name, flag in entries.items() if flag.text}


def typed_flags(args: list[str]) -> list[tuple[str, str | None]]:
    """The flags typed on the command line, in order, each with its value as typed (None: a flag
    alone); nothing after `--`."""
    typed = []
    for i, arg in enumerate(args):
        if arg == "--":
            break
        if arg.startswith("--"):
            name, equals, value = arg[2:].partition("=")
            following = args[i + 1] if i + 1 < len(args) and not args[i + 1].startswith("--") else None
            typed.append((name.replace("-", "_"), value if equals else following))
    return typed


def reject_unknown_flags(function: Callable, args: list[str]) -> None:
    """Fire would print a page of usage for a mistyped flag; one line naming it, and the flag it
    likely meant, is clearer. A flag given twice is refused too, and a word no argument of the
    command takes (Fire would run the command, then look the word up in what it returned)."""
    known, given = known_flags(function), set()
    for name, _ in typed_flags(args):
        if name not in known:
            raise UsageError(f"unknown flag --{name}; {did_you_mean(name, known, '--')}")
        if name in given:  # Fire would silently keep the last
            raise UsageError(f"--{name} is given twice; give each flag once")
        given.add(name)
    parameters = inspect.signature(function).parameters.values()
    room = sum(p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in parameters)
    words = positional_words(args)
    if len(words) > room and not any(p.kind is p.VAR_POSITIONAL for p in parameters):
        raise UsageError(f"unexpected argument {shown(words[room])}; give flags as --name value")


def positional_words(args: list[str]) -> list[str]:
    """The words typed that are neither a flag nor a flag's value (as typed_flags reads them):
    a command's positional arguments (RUN_DIR); nothing after `--`."""
    words, value_next = [], False
    for arg in args:
        if arg == "--":
            break
        if arg.startswith("--"):
            value_next = "=" not in arg
        elif value_next:
            value_next = False
        else:
            words.append(arg)
    return words


def help_text(name: str, function: Callable) -> str:
    """A command's --help page; the main one (search's) lists every command too."""
    passed_on = {flag: SEARCH_FLAGS[flag] for flag in known_flags(function)
                 if flag not in inspect.signature(function).parameters}
    if name != "search":
        return help_page(f"lunar_lander.py {name}", function, passed_on)
    commands = {other: ("(the default: no command name) " if other == "search" else "")
                + summary(command(other).__doc__ or "") for other in COMMANDS}
    return help_page("lunar_lander.py", function, passed_on, commands)


def main(argv: list[str]) -> int:
    import fire

    name = argv[0] if argv and not argv[0].startswith("-") else "search"
    args = argv[1:] if argv and not argv[0].startswith("-") else argv
    STOP.install()
    try:
        if name not in COMMANDS:
            raise UsageError(f"unknown command {shown(name)}; {did_you_mean(name, COMMANDS)}")
        function = command(name)
        if "-h" in args or "--help" in args:  # help wherever it is asked, and nothing run (Fire's
            print(help_text(name, function), end="")  # -h is a flag's short name: --hidden)
            return 0
        reject_unknown_flags(function, args)
        if name == "search":  # a row's own flag typed where the run's row ignores it: the row typed,
            from qdsearch.run import typed_setting  # else --config's run's (experiment: its own check)

            typed = dict(typed_flags(args))
            refuse_unused_row_flags([typed_setting(typed, "algorithm")], list(typed),
                                    [typed_setting(typed, "policy")])
        args = as_typed(args, text_flags(function))
        fire.Fire(function, command=args, name="lunar_lander.py" if name == "search" else name)
    except UsageError as error:
        print(f"error: {one_line(str(error))}", file=sys.stderr)
        return 2
    except (RunError, OSError) as error:  # OSError: any fault not already described better
        print(f"error: {one_line(fault_text(error))}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as stop:
        if not isinstance(stop, Stopped):  # else its line is said
            print("stopped", file=sys.stderr)
        return 130
    return 0


def run_as_script() -> None:
    """`python lunar_lander.py ...`: main, then a quick exit (see exit_now)."""
    try:
        exit_now(main(sys.argv[1:]))
    except SystemExit as done:  # Fire's own usage messages (exit code 2)
        exit_now(done.code)


def exit_now(code: Any) -> None:
    """Leave as sys.exit would, without the interpreter's teardown of ribs, dask, matplotlib and
    the rest (most of a second here): every file is written and closed, the cluster is down."""
    if not isinstance(code, int):
        if code is not None:
            print(code, file=sys.stderr)
        code = 0 if code is None else 1
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run_as_script()
