"""The command line: the commands, each a function of the package, run through Fire, with bad input
answered in one line and exit code 2, a fault of the machine in one line and exit code 1, and
-h or --help anywhere the command's page (help.py). `python lunar_lander.py ...` and the installed
`lunar-lander ...` both run `run_as_script`.

Map: COMMANDS, `command`, SCRIPT and INSTALLED (the command as typed), `help_text`, `main`, `run_as_script`,
`exit_now`.
"""

from __future__ import annotations

import inspect
import logging
import multiprocessing
import os
import signal
import sys
from pathlib import Path
from typing import Any, Callable

from qdsearch.base.flags import UsageError, did_you_mean, one_line, shown, summary
from qdsearch.base.run_files import RunError, fault_text
from qdsearch.base.stopping import STOP, Stopped
from qdsearch.cli.commands import (
    compare,
    elites,
    evaluate,
    experiment,
    explore,
    resume,
    search,
    trajectories,
    video,
    watch,
)
from qdsearch.cli.help import help_page
from qdsearch.cli.parsing import (
    as_typed,
    known_flags,
    reject_unknown_flags,
    text_flags,
    typed_flags,
    typed_setting,
)
from qdsearch.config.options import refuse_unused_row_flags
from qdsearch.config.settings import SEARCH_FLAGS

if multiprocessing.parent_process() is not None:
    # A local worker or saver process (multiprocessing starts them from the command line's main
    # module, which imports this one): Ctrl-C in a terminal reaches the whole process group, but
    # stopping is the main process's job (it abandons the iteration and closes the cluster).
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# The commands, by the name typed (commands.py: each imports its core module when it runs, so
# --help and bad input answer without loading the rest).
COMMANDS: dict[str, Callable] = {
    "search": search,
    "resume": resume,
    "experiment": experiment,
    "video": video,
    "elites": elites,
    "trajectories": trajectories,
    "evaluate": evaluate,
    "explore": explore,
    "compare": compare,
    "watch": watch,
}


def command(name: str) -> Callable:
    """The function of a command of COMMANDS."""
    return COMMANDS[name]


# The command as the user typed it (run_as_script tells which): the script, or the installed
# entry point (pyproject.toml's [project.scripts]).
SCRIPT, INSTALLED = "python lunar_lander.py", "lunar-lander"


def help_text(name: str, function: Callable, program: str = SCRIPT) -> str:
    """A command's --help page, titled as the command was typed; the main one (search's) lists
    every command too."""
    passed_on = {flag: SEARCH_FLAGS[flag] for flag in known_flags(function)
                 if flag not in inspect.signature(function).parameters}
    if name != "search":
        return help_page(f"{program} {name}", function, passed_on)
    commands = {other: ("(the default: no command name) " if other == "search" else "")
                + summary(command(other).__doc__ or "") for other in COMMANDS}
    return help_page(program, function, passed_on, commands)


def main(argv: list[str], program: str = SCRIPT) -> int:
    import fire

    name = argv[0] if argv and not argv[0].startswith("-") else "search"
    args = argv[1:] if argv and not argv[0].startswith("-") else argv
    STOP.install()
    try:
        if name not in COMMANDS:
            raise UsageError(f"unknown command {shown(name)}; {did_you_mean(name, COMMANDS)}")
        function = command(name)
        if "-h" in args or "--help" in args:  # help wherever it is asked, and nothing run (Fire's
            print(help_text(name, function, program), end="")  # -h is a flag's short name: --hidden)
            return 0
        reject_unknown_flags(function, args)
        if name == "search":  # a row's own flag typed where the run's row ignores it: the row typed,
            # else --config's run's (experiment: its own check)
            typed = dict(typed_flags(args))
            refuse_unused_row_flags([typed_setting(typed, "algorithm")], list(typed),
                                    [typed_setting(typed, "policy")])
        args = as_typed(args, text_flags(function))
        fire.Fire(function, command=args, name=program.removeprefix("python ")
                  + ("" if name == "search" else f" {name}"))
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
    """`python lunar_lander.py ...` or the installed `lunar-lander ...`: main, then a quick exit
    (see exit_now)."""
    program = INSTALLED if Path(sys.argv[0]).name == INSTALLED else SCRIPT
    try:
        exit_now(main(sys.argv[1:], program))
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
