"""A command's signature made from the flag tables: `takes` gives a command function the flags of
its settings classes as keyword arguments, so that Fire's parsing, --help (help.py) and a direct
call all see one declaration; and tells a command which flags a call gave (`given`).

Map: `takes`, GIVEN, `flag_table` (the flags a command took from the tables), `with_flag_help`.
"""

from __future__ import annotations

import functools
import inspect
import textwrap
from typing import Any, Callable

from qdsearch.base.flags import Flag


def takes(*tables: dict[str, Flag]) -> Callable[[Callable], Callable]:
    """Give a command that takes `**flags` the flags of `tables` as ordinary keyword arguments.

    The command's signature becomes its own parameters followed by the tables' flags with their
    defaults, and its docstring's Args section gains each flag's help line (for Python's help());
    Fire parses the command line by the signature, and help_page renders --help from the tables
    (flag_table). A call binds its arguments to that signature (a misspelt keyword is a
    TypeError, as for any function) and passes every flag, defaulted.

    A command that declares a keyword-only `given` is told which flags the call gave, whatever
    their values (a flag typed beside a file wins over the file's value even at its default):
    `given` is hidden from the signature, and every flag of such a command is keyword-only, since
    Fire passes a positional parameter's default itself but a keyword-only one's only when typed.
    So the command line and a direct call give alike.
    """
    flags = {name: flag for table in tables for name, flag in table.items()}

    def decorate(function: Callable) -> Callable:
        own = inspect.signature(function)
        tells = GIVEN in own.parameters and own.parameters[GIVEN].kind is inspect.Parameter.KEYWORD_ONLY
        keep = [p for p in own.parameters.values()
                if not (p.kind is p.VAR_KEYWORD and p.name == "flags") and not (tells and p.name == GIVEN)]
        at = next((i for i, p in enumerate(keep) if p.kind in (p.KEYWORD_ONLY, p.VAR_KEYWORD)), len(keep))
        # keyword-only after *run_dirs (compare), or where the command is told what was given
        spread = any(p.kind is p.VAR_POSITIONAL for p in keep)
        kind = inspect.Parameter.KEYWORD_ONLY if tells or spread else inspect.Parameter.POSITIONAL_OR_KEYWORD
        added = [inspect.Parameter(name, kind, default=flag.default)
                 for name, flag in flags.items() if name not in own.parameters]
        if tells:
            keep = [p.replace(kind=p.KEYWORD_ONLY) if p.kind is p.POSITIONAL_OR_KEYWORD
                    and p.default is not p.empty else p for p in keep]
        signature = own.replace(parameters=keep[:at] + added + keep[at:])
        rest = next((p.name for p in keep if p.kind is p.VAR_KEYWORD), None)  # experiment's **search_flags
        # a command with *args (compare's *run_dirs) is called with them, and what comes before, by place
        ahead = next(([q.name for q in keep[:i + 1]] for i, p in enumerate(keep)
                      if p.kind is p.VAR_POSITIONAL), [])

        @functools.wraps(function)
        def command(*args: Any, **kwargs: Any) -> Any:
            bound = signature.bind(*args, **kwargs)
            given = frozenset({*(name for name in bound.arguments if name != rest),
                               *bound.arguments.get(rest, {})})
            bound.apply_defaults()
            arguments = dict(bound.arguments)
            extra = arguments.pop(rest) if rest else {}
            *before, spread = [arguments.pop(name) for name in ahead] or [()]  # compare's *run_dirs
            return function(*before, *spread, **arguments, **extra, **({GIVEN: given} if tells else {}))

        command.__signature__ = signature
        FLAG_TABLES[command] = {name: flags[name] for name in flags if name not in own.parameters}
        command.__doc__ = with_flag_help(function.__doc__ or "", FLAG_TABLES[command])
        return command
    return decorate


GIVEN = "given"  # the keyword-only parameter through which `takes` tells a command the flags given


# The flags each command took from the tables, kept here and not as an attribute of the command:
# Fire lists a function's public attributes as commands of their own ("GROUPS ... flag_table").
FLAG_TABLES: dict[Callable, dict[str, Flag]] = {}


def flag_table(function: Callable) -> dict[str, Flag]:
    """The flags a command took from the tables through `takes` (none for the others)."""
    return FLAG_TABLES.get(function, {})


def with_flag_help(doc: str, flags: dict[str, Flag]) -> str:
    """The docstring with a Google-style Args line per flag (for Python's help(); --help is help_page's)."""
    doc = inspect.cleandoc(doc)
    lines = [textwrap.fill(f"{name}: {flag.help}", 96, initial_indent="    ", subsequent_indent="        ",
                           break_on_hyphens=False) for name, flag in flags.items()]
    if "\nArgs:\n" not in doc:
        doc += "\n\nArgs:"
    head, _, tail = doc.partition("\nArgs:\n")
    return "\n".join([head, "Args:", *(tail.splitlines() if tail else []), *lines])
