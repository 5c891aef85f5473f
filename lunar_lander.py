#!/usr/bin/env python
"""Search Gymnasium's Lunar Lander for many different good landings with CMA-ME (pyribs), on Dask;
and other Gymnasium tasks through the same tables: the continuous lander, BipedalWalker (and its
hardcore course), and MuJoCo's Hopper, Walker2d, HalfCheetah and Ant.

The problem, the algorithm and the results follow the pyribs tutorial "Using CMA-ME to Land a Lunar
Lander Like a Space Shuttle"; this script adds what a research run needs around them: a Dask
evaluation engine, seeded and repeatable runs, checkpoints, metrics, plots and a CLI.

    python lunar_lander.py --iterations 300 --workers 2     # search; writes outputs/<run>/
    python lunar_lander.py --algorithm cma_mae               # or map_elites; default cma_me
    python lunar_lander.py --measures fuel,flight_time --env_seed 0-4   # other axes, 5 terrains
    python lunar_lander.py --env Hopper-v5                   # another task: a row of ENVIRONMENTS
    python lunar_lander.py resume outputs/RUN                # continue a run from its checkpoint
    python lunar_lander.py experiment --algorithms "[cma_me, cma_mae]" --seeds 1-5   # many runs
    python lunar_lander.py video outputs/RUN --cells "[(-0.4, -0.1)]"   # or --best, --top K
    python lunar_lander.py elites outputs/RUN --min_objective 200       # table of elites
    python lunar_lander.py trajectories outputs/RUN --top 10            # flight paths picture
    python lunar_lander.py evaluate outputs/RUN --env_seeds 0-19        # robustness on terrains
    python lunar_lander.py explore outputs/RUN                          # browse, watch landings
    python lunar_lander.py compare outputs/RUN_A outputs/EXPERIMENT     # statistics across seeds
    python lunar_lander.py COMMAND --help                    # every flag of a command

The work is done by the package `qdsearch`, in layers (docs/code.md draws them): base, tasks,
algorithms, store, config, search, analysis, and on top the command line, `qdsearch.cli`, which
this script runs. `pip install -e .` installs the same command as `lunar-lander`.
"""

from qdsearch.cli.app import run_as_script

if __name__ == "__main__":
    run_as_script()
