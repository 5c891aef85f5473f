"""qdsearch.config: a run's settings, declared once and read back.

Map, imports going down the list only:
- options: every command's flags, declared once, and the bounds on sizes;
- run_config: the typed RunConfig made from the flags, `upgrade` of old folders, config.json and
  the checkpoint read back.
"""
