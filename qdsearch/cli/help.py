"""A command's --help page, drawn from its signature, its docstring and the flag tables.

Map: `help_page` (NAME, SYNOPSIS, DESCRIPTION, COMMANDS, POSITIONAL ARGUMENTS, FLAGS, FLAGS PASSED
ON TO EVERY RUN), its entries (`listing`, `flag_item`, `help_item`, `wrapped`, `shown_default`),
and what it reads of a docstring (`description`, `documented_arguments`).
"""

from __future__ import annotations

import inspect
import re
import textwrap
from typing import Any, Callable

from qdsearch.base.flags import Flag, summary
from qdsearch.cli.signatures import flag_table

# --help is drawn here from the signature and the tables, not by Fire, which builds its page by
# parsing the docstring: any wrapped line "word ...: text" starts a new argument there (--workers'
# help ended at "flying the"), a default of None prints as "Type: Optional[]", its short names
# clash (-h for --hidden, while -h is help) and public attributes show as GROUPS. Escaping each
# quirk would be a fight with its parser over every new help text; drawn from the Flag entries,
# the page says exactly what they declare. Fire still parses the command line.
WIDTH = 100  # of a help page's lines


def help_page(program: str, function: Callable, passed_on: dict[str, Flag] | None = None,
              commands: dict[str, str] | None = None) -> str:
    """A command's --help: NAME (its docstring's first paragraph), SYNOPSIS, DESCRIPTION (the rest
    before Args), COMMANDS (the main page's: name to summary), its positional arguments, its FLAGS
    (a table's help for a flag it took, its docstring's Args for its own) and, for a command that
    passes flags on (experiment's **search_flags), those flags with their tables' help. `program`
    is the command as typed ("python lunar_lander.py video", "lunar-lander video")."""
    doc, table = function.__doc__ or "", flag_table(function)
    documented = documented_arguments(doc)
    parameters = list(inspect.signature(function).parameters.values())
    positional = [p for p in parameters if p.default is p.empty and p.kind is not p.VAR_KEYWORD]
    words = [p.name.upper() + ("..." if p.kind is p.VAR_POSITIONAL else "") for p in positional]
    passes = next((documented.get(p.name, "") for p in parameters if p.kind is p.VAR_KEYWORD), "")
    sections = {
        "NAME": wrapped(f"{program.removeprefix('python ')} - {summary(doc)}", 4),
        "SYNOPSIS": wrapped(" ".join([program, *words, "[--FLAG=VALUE ...]"]), 4),
        "DESCRIPTION": textwrap.indent(description(doc), "    "),
        "COMMANDS": listing(f"{program} COMMAND --help: a command's own page.",
                            [help_item(name, text) for name, text in (commands or {}).items()]),
        "POSITIONAL ARGUMENTS": listing("", [help_item(word, documented.get(p.name, ""))
                                             for word, p in zip(words, positional)]),
        "FLAGS": listing("", [flag_item(p.name, table[p.name].help if p.name in table
                                        else documented.get(p.name, ""), p.default)
                              for p in parameters if p.default is not p.empty]),
        "FLAGS PASSED ON TO EVERY RUN": listing(passes, [flag_item(name, flag.help, flag.default)
                                                         for name, flag in (passed_on or {}).items()]),
    }
    return "\n\n".join(f"{head}\n{body.rstrip()}" for head, body in sections.items() if body) + "\n"


def listing(lead: str, items: list[str]) -> str:
    """A section of entries, after its lead paragraph if it has one ("": none; no entries: no section)."""
    return "\n".join(([wrapped(lead, 4), ""] if lead else []) + items) if items else ""


def flag_item(name: str, text: str, default: Any) -> str:
    """A flag's entry: --name=NAME, its default and its whole help."""
    return help_item(f"--{name}={name.upper()}", text, default)


def help_item(head: str, text: str, default: Any = None) -> str:
    """One entry of a page: its head, then its default as typed (if it has one) and its text whole."""
    default_line = [f"        Default: {shown_default(default)}"] if shown_default(default) else []
    return "\n".join([f"    {head}", *default_line, wrapped(text, 8)])


def wrapped(text: str, indent: int) -> str:
    """Text as the page's indented lines, broken at spaces only (a line broken after a hyphen
    reads as two words once joined: "ME-MAP- Elites")."""
    return textwrap.fill(" ".join(text.split()), WIDTH, initial_indent=" " * indent,
                         subsequent_indent=" " * indent, break_on_hyphens=False, break_long_words=False)


def shown_default(value: Any) -> str:
    """A default as a user would type it (true, 1-5, cma_me), or "" for none (None, an empty list):
    the flag's help says what its absence means (drawn, the task's own)."""
    if value is None or value == [] or value == ():
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    return ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)


def description(doc: str) -> str:
    """A docstring's paragraphs after the first, up to its Args, as written."""
    head = inspect.cleandoc(doc).partition("\nArgs:\n")[0]
    return head.partition("\n\n")[2].strip()


def documented_arguments(doc: str) -> dict[str, str]:
    """A docstring's Args, each argument's text on one line. An argument starts at the section's
    own indent ("name: text"); a deeper line goes on the one before, whatever colons it holds
    (Fire's parser took "array: docs/clusters.md" in --part's text for an argument)."""
    arguments: dict[str, str] = {}
    name = None
    for line in inspect.cleandoc(doc).partition("\nArgs:\n")[2].splitlines():
        if not line.startswith(" "):  # the section's end
            break
        if entry := re.match(r" {4}\**(\w+)(?: \([^)]*\))?: ?(.*)", line):
            name, arguments[entry[1]] = entry[1], entry[2]
        elif name:
            arguments[name] += " " + line.strip()
    return arguments
