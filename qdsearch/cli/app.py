"""The command line: the commands, each a function of the package, run through Fire, with bad input
answered in one line and exit code 2, a fault of the machine in one line and exit code 1, and
-h or --help anywhere the command's page (help.py). `python lunar_lander.py ...` and the installed
`lunar-lander ...` both run `run_as_script`.

Map: COMMANDS, `command`, `help_text`, `main`, `run_as_script`, `exit_now`.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import multiprocessing
import os
import signal
import sys
from typing import Any, Callable

from qdsearch.base.flags import UsageError, did_you_mean, one_line, shown, summary
from qdsearch.base.run_files import RunError, fault_text
from qdsearch.base.stopping import STOP, Stopped
from qdsearch.cli.help import help_page
from qdsearch.cli.parsing import as_typed, known_flags, reject_unknown_flags, text_flags, typed_flags
from qdsearch.config.options import refuse_unused_row_flags
from qdsearch.config.settings import SEARCH_FLAGS

if multiprocessing.parent_process() is not None:
    # A local worker or saver process (multiprocessing starts them from the command line's main
    # module, which imports this one): Ctrl-C in a terminal reaches the whole process group, but
    # stopping is the main process's job (it abandons the iteration and closes the cluster).
    signal.signal(signal.SIGINT, signal.SIG_IGN)


# The commands, each the package module and function that implement it: a command's module is
# imported only when it is run, so `--help` and bad input answer without loading the rest.
COMMANDS: dict[str, tuple[str, str]] = {
    "search": ("qdsearch.search.run", "search"),
    "resume": ("qdsearch.search.experiments", "resume"),
    "experiment": ("qdsearch.search.experiments", "experiment"),
    "video": ("qdsearch.analysis.results", "video"),
    "elites": ("qdsearch.analysis.results", "elites"),
    "trajectories": ("qdsearch.analysis.results", "trajectories"),
    "evaluate": ("qdsearch.analysis.evaluation", "evaluate"),
    "explore": ("qdsearch.analysis.explorer", "explore"),
    "compare": ("qdsearch.analysis.comparison", "compare"),
    "watch": ("qdsearch.analysis.live", "watch"),
}


def command(name: str) -> Callable:
    """The function of a command of COMMANDS."""
    module, function = COMMANDS[name]
    return getattr(importlib.import_module(module), function)


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
            from qdsearch.search.run import typed_setting  # else --config's run's (experiment: its own check)

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
