"""Flags: how a setting is declared once as a flag, and how every value a user gives is checked.

A settings class (config/settings.py, config/command_settings.py) declares each setting as a
field made by `flag`: its default, its --help line, its check and its part in experiments. A
command's table of flags is made from such classes (`flags_of`), and a command's values become
its class through `settings_from`. The command line (qdsearch.cli) makes its commands' signatures
and --help from the tables and parses the text typed; nothing here knows it.

Map:
- `UsageError`: bad input, reported as one line and exit code 2; `BadValue`, one setting's
  value refused (which setting, which value, why);
- `named` (by NAMING's style): how a message names a setting;
- the checkers, each `(setting name, value) -> checked value`: `positive_int`,
  `whole_number_up_to`, `seed_number`, `positive_float`, `finite_number`, `number_up_to`,
  `fraction`, `boolean`, `one_of`, `seed_list`, `distinct_names`; `listed` splits a list as
  typed; `shown` quotes a bad value, `clipped` cuts a library's message, `one_line` keeps a
  message on one line;
- `nearest` and `did_you_mean`: how every refusal of a name (a task, an algorithm, a measure,
  a tracker, a command, a flag) ends, with the name the user most likely meant;
- `Flag`, `flag` (a settings class's field that is a flag), `flags_of` (a class's flags as a
  command's table), `check_flags` (values through their entries' checks), `settings_from`
  (a settings class from a command's values);
- `summary`: a docstring's first line (the tables' rows describe themselves by it).
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
import re
import unicodedata
from typing import Any, Callable, Iterable, TypeVar

import numpy as np


class UsageError(Exception):
    """Bad input from the user: reported as one line (the command line: on stderr, exit code 2).
    Its words name each setting through `named`."""


class BadValue(UsageError):
    """A setting's value refused: which setting, which value, and why (the words after the
    setting's name). Its line names the setting as whoever reports it words settings (`named`
    when it is read, not when it is raised)."""

    def __init__(self, setting: str, value: Any, why: str) -> None:
        super().__init__(setting, value, why)
        self.setting, self.value, self.why = setting, value, why

    def __str__(self) -> str:
        return f"{named(self.setting)} {self.why}"


# How a message names a setting: as the keyword a Python caller passes (env), unless whoever
# reports the messages words them otherwise: the command line sets "--{}" (--env) when it loads.
NAMING = {"style": "{}"}


def named(setting: str) -> str:
    """A setting as a message names it: `env` to a Python caller, `--env` on the command line."""
    return NAMING["style"].format(setting)


Check = Callable[[str, Any], Any]
T = TypeVar("T")


def positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise BadValue(name, value, f"must be a positive whole number, got {shown(value)}")
    return value


def whole_number_up_to(most: int) -> Check:
    """A check for a positive whole number of at most `most` (a size: bounded before anything
    is allocated or written)."""
    def check(name: str, value: Any) -> int:
        if positive_int(name, value) > most:
            raise BadValue(name, value, f"must be at most {most:,}, got {shown(value)}")
        return value
    return check


MAX_SEED = 2**32 - 1  # what numpy's and Box2D's seeding take
MAX_SEEDS = 10_000  # seeds in one list or range (terrains to fly every policy on, runs per setting)


def seed_number(name: str, value: Any) -> int:
    """One seed: a whole number from 0 to MAX_SEED."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_SEED:
        raise BadValue(name, value, f"must be a whole number from 0 to {MAX_SEED}, got {shown(value)}")
    return value


def positive_float(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise BadValue(name, value, f"must be a positive number, got {shown(value)}")
    return float(value)


def finite_number(name: str, value: Any) -> float:
    """Any real number, as a float (a QD offset)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise BadValue(name, value, f"must be a number, got {shown(value)}")
    return float(value)


def number_up_to(most: float) -> Check:
    """A check for a positive number of at most `most`."""
    def check(name: str, value: Any) -> float:
        if positive_float(name, value) > most:
            raise BadValue(name, value, f"must be at most {most:g}, got {shown(value)}")
        return float(value)
    return check


def fraction(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise BadValue(name, value, f"must be a number in (0, 1], got {shown(value)}")
    return float(value)


def boolean(name: str, value: Any) -> bool:
    """Fire passes --flag=false as the string 'false' (and --flag alone as True)."""
    words = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if str(value).lower() in words:
        return words[str(value).lower()]
    raise BadValue(name, value, f"must be true or false, got {shown(value)}")


def one_of(choices: dict) -> Check:
    """A check that the value is a key of `choices` (a table such as ALGORITHMS)."""
    def check(name: str, value: Any) -> str:
        if not isinstance(value, str) or value not in choices:
            raise BadValue(name, value, f"{shown(value)} is unknown; {did_you_mean(value, choices)}")
        return value
    return check


def nearest(name: str, choices: Iterable[str]) -> str | None:
    """The choice a mistyped name most likely meant, or None if none is near: case and - against _
    aside (sep-cma-mae: sep_cma_mae), the one choice the name is the head of, its words before an
    underscore (line: line_map_elites, which difflib would take for map_elites); else
    difflib's closest match to a choice or to the tail of one after an underscore (y_vel:
    impact_y_velocity, whose head a user may not know)."""
    def fold(text: str) -> str:
        return text.lower().replace("-", "_")

    choices = list(choices)
    headed = [choice for choice in choices if fold(choice).startswith(fold(name) + "_")]
    if len(headed) == 1:  # a head names its choice; two choices of one head (cma: ...) are left to difflib
        return headed[0]
    names = {fold(choice): choice for choice in choices}
    if match := difflib.get_close_matches(fold(name), list(names), n=1):  # whole names first: a
        return names[match[0]]  # tail never hides a name (--seed: --seeds, not --env_seed)
    tails = {}
    for choice in choices:
        parts = choice.split("_")
        for start in range(1, len(parts)):
            tails.setdefault(fold("_".join(parts[start:])), choice)
    match = difflib.get_close_matches(fold(name), list(tails), n=1)
    return tails[match[0]] if match else None


def did_you_mean(name: Any, choices: Iterable[str], prefix: str = "") -> str:
    """How a refusal of a name that is not one of `choices` ends: the nearest choice as the fix
    if one is near ("did you mean sep_cma_mae?"), else the choices. `prefix` is how a choice is
    typed (-- for a flag)."""
    choices = list(choices)
    near = nearest(str(name), choices)
    return f"did you mean {prefix}{near}?" if near else f"choose from {prefix}" + f", {prefix}".join(choices)


def listed(value: Any) -> list[str]:
    """The items of a list flag: Fire's list or tuple, or the text as typed, "a,b" or "[a, b]"
    (Fire leaves as text a list it cannot read as a literal, such as [cma_me, cma-mae]: split at
    its commas, brackets and quotes off, each item is named as the user typed it)."""
    if isinstance(value, (list, tuple)):
        return [str(item).strip() for item in value]
    text = str(value).strip()
    if len(text) > 1 and text[0] + text[-1] in ("[]", "()"):
        text = text[1:-1]
    return [item.strip().strip("'\"").strip() for item in text.split(",")]


def seed_list(name: str, value: Any) -> list[int]:
    """Seeds as a range 0-19, a list 3,5,8 or both (0-4,10), each from 0 to MAX_SEED and at most
    MAX_SEEDS in all (counted before any list is built); Fire may have made a number or a tuple
    of it already."""
    parts = [str(part) for part in value] if isinstance(value, (tuple, list)) else str(value).split(",")
    bounds = []
    for part in parts:
        match = re.fullmatch(r"\s*(\d{1,20})\s*(?:-\s*(\d{1,20})\s*)?", part)
        first, last = (int(match[1]), int(match[2] or match[1])) if match else (0, -1)
        if isinstance(value, bool) or not match or last < first or last > MAX_SEED:
            raise BadValue(name, value, f"takes seeds from 0 to {MAX_SEED} such as 52, 0-19, 3,5,8 or "
                             f"0-4,10; got {shown(value)}")
        bounds.append((first, last))
    if not bounds:
        raise BadValue(name, value, f"takes at least one seed, such as 52, 0-19 or 3,5,8; got "
                         f"{shown(value)}")
    if (count := sum(last - first + 1 for first, last in bounds)) > MAX_SEEDS:
        raise BadValue(name, value, f"lists {count:,} seeds; at most {MAX_SEEDS:,}")
    return list(dict.fromkeys(seed for first, last in bounds for seed in range(first, last + 1)))


def one_line(text: str) -> str:
    """A message as one line: line breaks and other control characters (a hostile folder name
    may hold them) written as their escapes."""
    return "".join(char.encode("unicode_escape").decode() if unicodedata.category(char) in
                   ("Cc", "Zl", "Zp") else char for char in text)


def shown(value: Any, limit: int = 80) -> str:
    """A value as an error message quotes it: its repr, cut to `limit` characters, on one line."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def clipped(text: str, limit: int = 200) -> str:
    """A message's text (a library's error, which may quote what it was given whole) cut to
    `limit` characters."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


def distinct_names(table: dict, noun: str, most: int) -> Check:
    """A check for 1 to `most` distinct keys of `table` (such as MEASURES), as "a,b" or a list;
    a name not in `table` is the one refused, with the name it likely meant."""
    def check(name: str, value: Any) -> list[str]:
        names = listed(value) if isinstance(value, (str, tuple, list)) else []
        if unknown := [n for n in names if n and n not in table]:
            raise BadValue(name, value, f"{shown(unknown[0])} is not one of the {noun}; "
                             + did_you_mean(unknown[0], table))
        if "" in names or not 1 <= len(names) <= most or len(set(names)) != len(names):
            raise BadValue(name, value, f"takes 1 to {most} different {noun} of {', '.join(table)}; "
                             f"got {shown(value)}")
        return names
    return check


@dataclasses.dataclass(frozen=True)
class Flag:
    """One flag, declared once: what it defaults to, what --help says, how a value is checked
    (None, a drawn seed or a default folder, always passes), and its part in experiments."""

    default: Any
    help: str
    check: Check | None = None  # None: any value passes (a path, an address)
    sweep: bool = False  # experiment: a list of values is one more axis of its grid
    per_run: bool = False  # experiment sets it for each run itself (the seed, the folder...)
    label: int = 0  # >0: a value other than the default names a run's setting, at this place
    before: Any = None  # what runs recorded before the flag existed ran with (None: the default)
    text: bool = False  # the command line hands its check the text as typed (not Fire's literal)


def flag(default: Any, help: str, check: Check | None = None, **parts: Any) -> Any:
    """A field of a settings class that is a flag: its Flag entry (default, --help line, check,
    part in experiments) in the field's metadata. The field has no default of its own: a config
    is made from values that were all given and checked."""
    return dataclasses.field(metadata={"flag": Flag(default, help, check, **parts)})


def flags_of(*sections: type) -> dict[str, Flag]:
    """The flags of settings classes, in their fields' order: a command's table."""
    return {field.name: field.metadata["flag"] for section in sections
            for field in dataclasses.fields(section) if "flag" in field.metadata}


def check_flags(table: dict[str, Flag], values: dict[str, Any]) -> dict[str, Any]:
    """The values with each one that has an entry (and a check) in `table` checked."""
    return {name: value if value is None or name not in table or table[name].check is None
            else table[name].check(name, value) for name, value in values.items()}


def settings_from(section: type[T], values: dict[str, Any]) -> T:
    """A settings class made from a command's values: each of its fields' (one not among them:
    its flag's default), through its flag's check once (None passes: a value not given)."""
    table = flags_of(section)
    given = {name: values.get(name, entry.default) for name, entry in table.items()}
    return section(**check_flags(table, given))


def summary(doc: str) -> str:
    """A docstring's first paragraph, on one line."""
    return " ".join(inspect.cleandoc(doc).split("\n\n")[0].split())
