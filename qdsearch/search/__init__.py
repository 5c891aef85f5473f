"""qdsearch.search: running searches: the cluster, the rollouts on it, the one run loop, and
experiments of many runs.

Map, imports going down the list only:
- pinning: a local cluster's worker per core pinned to it (a Dask worker plugin);
- cluster: the Dask cluster, found, checked and joined with bounded waits, or started locally;
  the package shipped to workers that lack it;
- engine: chunks of rollouts on the workers, sized by what shares the cluster, back in order;
- learning: a learning row's TD3 learner in its run: the greedy actor, the critic's steps while a
  batch flies, the transitions into the buffer once an iteration is told;
- loop: the one run loop (`Driver`, `OneRun`): any number of runs sent, taken back and told;
- run: one run (`Run`: its ask, its batch on the cluster, its tell, its checkpoint and folder),
  `search` and `resume` of a run folder;
- parts: an experiment split into parts, each its own process: the plan written once, a state
  file per part;
- experiment_folder: experiment.json read and checked, a setting's label (what compare reads);
- experiments: `experiment` (many runs through the one loop on one cluster), `resume`.
"""
