"""qdsearch.base: what every layer uses, knowing nothing of tasks, searches or the command line.

Map, imports going down the list only:
- kernels: what the command line sets before numpy and the rest load (`hold_kernels`);
- flags: the `Flag` entry, the checkers, UsageError;
- run_files: locks, atomic writes, JSON and pickles (a moved module's pickles found where it is
  now), logs; RunError;
- signing: the user's key (QDSEARCH_KEY, or ~/.config/qdsearch/key) and the checkpoints signed
  with it, their signature checked before anything is unpickled (resume --trust adopts another's);
- compact_pickle: the checkpoint's and the snapshots' pickles, an archive's occupied cells alone;
- stopping: Ctrl-C and SIGTERM (`STOP`), acted on where stopping is safe;
- plots: heatmaps and progress curves.
"""
