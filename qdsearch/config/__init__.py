"""qdsearch.config: a run's settings, declared once and read back.

Map, imports going down the list only:
- settings: a run's settings, a frozen dataclass per concern, each flag a typed field (its
  default, help and check), and RunConfig, all of them; the search's flag tables made from them;
- options: the other commands' flags, and the checks of what flags make together (a config's
  task, policy, budget, sizes and memory);
- run_config: a RunConfig made from flags or a recorded config (`check_run_config`, every value
  checked once; `upgrade` of old folders), config.json and the checkpoint read back.
"""
