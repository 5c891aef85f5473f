"""qdsearch.cli: the command line, on top of every other layer (none imports it).

Map, imports going down the list only:
- signatures: a command's signature made from its settings' flag tables (`takes`);
- help: a command's --help page, drawn from its signature, docstring and flag tables;
- parsing: the words typed, checked before Fire parses them, and the values Fire would misread;
- commands: each command's function as Fire calls it (its flags, its --help), making its
  settings and calling the core;
- app: the command table (COMMANDS), `main` (exit codes, the one-line messages) and
  `run_as_script`.
"""

from qdsearch.base.kernels import hold_kernels

hold_kernels()  # before numpy, numba, matplotlib or MuJoCo loads: the command line's bits

from qdsearch.base.flags import NAMING  # noqa: E402 (it loads numpy)

NAMING["style"] = "--{}"  # the messages name each setting as its flag (data, not a call: see conftest.py)
