"""The words typed, read before Fire parses them: the flags a command knows, the flags typed, the
mistakes Fire would answer with a page of usage (or not at all), and the values Fire would misread.

Map: `known_flags`, `text_flags`, `typed_flags`, `positional_words`, `reject_unknown_flags`,
`as_typed`; `typed_setting` (a search's algorithm or policy as typed, or its --config run's: whose
own flags main refuses where they are unused).
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Callable

from qdsearch.base.flags import UsageError, did_you_mean, shown
from qdsearch.cli.signatures import flag_table
from qdsearch.config.run_config import recorded_settings
from qdsearch.config.settings import SEARCH_FLAGS


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


def as_typed(args: list[str], text_flags: set[str]) -> list[str]:
    """The command line with the values of `text_flags` quoted, so that Fire hands them over as
    typed: Fire reads a value as a Python literal, and "fuel," would become the tuple ("fuel",),
    its stray comma lost before the check could see it."""
    typed, args = [], list(args)
    while args:
        arg = args.pop(0)
        name, is_value_inline, value = arg[2:].partition("=") if arg.startswith("--") else ("", "", "")
        if name.replace("-", "_") not in text_flags:
            typed.append(arg)
        elif is_value_inline:
            typed.append(f"--{name}={value!r}")
        elif args and not args[0].startswith("--"):
            typed += [arg, repr(args.pop(0))]
        else:  # a flag with no value (Fire reads it as True): the check refuses it
            typed.append(arg)
    return typed


def typed_setting(typed: dict[str, str | None], flag: str) -> str:
    """What a search typed so runs with for `flag` (its algorithm, its policy): the value typed,
    else that of the run --config names, else the default (the command line's check of a row's
    own flags typed)."""
    if typed.get(flag) is not None:
        return str(typed[flag]).strip("'\"")
    if typed.get("config") is None:
        return SEARCH_FLAGS[flag].default
    return recorded_settings(Path(str(typed["config"])))[flag]
