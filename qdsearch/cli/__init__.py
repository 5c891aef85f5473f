"""qdsearch.cli: the command line, on top of every other layer (none imports it).

Map, imports going down the list only:
- help: a command's --help page, drawn from its signature, docstring and flag tables;
- parsing: the words typed, checked before Fire parses them, and the values Fire would misread;
- app: the commands (COMMANDS), `main` (exit codes, the one-line messages) and `run_as_script`.
"""

from qdsearch.base.kernels import hold_kernels

hold_kernels()  # before numpy, numba, matplotlib or MuJoCo loads: the command line's bits

from qdsearch.base.flags import name_settings_as  # noqa: E402 (it loads numpy)

name_settings_as("--{}")  # the messages name each setting as its flag
