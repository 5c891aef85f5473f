"""qdsearch.analysis: looking at finished (or running) searches; nothing here writes a run.

Map, imports going down the list only:
- run_folder: what the results commands read of a run folder (`load_run`, `elite_rows`): data
  files only, never a pickle, so a folder from anyone is safe to open;
- results: `video`, `elites`, `trajectories`, and choosing elites;
- evaluation: `evaluate`: the elites flown on other terrains, or on new seeds (corrected archive);
- explorer: `explore`, the page (explorer_page.html) and the poses it plays;
- live: `watch`, a live page of a run (Bokeh), redrawn from its files;
- stats: statistics across seeds (BCa, rliable's IQM and P(A>B) with stratified bootstrap, Holm);
- compared_runs: what `compare` reads of its runs (corrected metrics, a cut at a budget);
- comparison: `compare` and its statistics;
- notebook: run folders as pandas tables, the public API (`read_run`, `read_experiment`).
"""
