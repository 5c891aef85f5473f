"""qdsearch.config: a run's settings, declared once and read back.

Map, imports going down the list only:
- settings: a run's settings, a frozen dataclass per concern, each flag a typed field (its
  default, help and check), and RunConfig, all of them; the search's flag tables made from them;
- command_settings: the other commands' settings (resume, video, elites, evaluate, experiment,
  compare, watch...), declared the same way, and their tables;
- options: the checks of what a run's flags make together (a config's task, budget, sizes and
  memory);
- run_config: a RunConfig made from flags (`search_config`, with --config's file: `settings_of`)
  or a recorded config (`check_run_config`, every value checked once; `upgrade` of old folders),
  config.json and the checkpoint read back.
"""
