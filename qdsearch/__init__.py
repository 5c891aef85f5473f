"""qdsearch: quality-diversity search of Gymnasium tasks with pyribs, on Dask; the package under
`python lunar_lander.py` (and the installed `lunar-lander`), whose command line is its top layer.

Map, a subpackage per layer from the bottom up: a module imports only the layers below its own
and, in its own layer, the modules its layer's map names before it (each layer's __init__.py);
tests/test_imports.py holds this, and docs/code.md draws it:
- base: errors and the checks of values, files, signatures, pickles, stopping, plots;
- tasks: the policies, the task families (lander, walker, locomotion) and their registry: an
  episode of any task;
- algorithms: the table of algorithms (pyribs' archives, emitters, schedulers) and the DQD rows'
  gradients;
- store: what a run writes of itself as data: metrics, the archive's data, trackers, the saver;
- config: every command's flags declared once, and a run's config made and read back;
- search: the cluster, the rollouts on it, the one run loop, search, resume and experiments;
- analysis: the commands that read runs (video, elites, evaluate, explore, watch, compare) and
  the notebook tables;
- cli: the command line: the commands, parsing, --help, exit codes.
"""

# The public API (docs/notebooks.md): each name, and the module that holds it. Importing the
# package changes nothing in the process; hold_kernels sets what the command line sets.
PUBLIC = {"read_run": "qdsearch.analysis.notebook", "read_experiment": "qdsearch.analysis.notebook",
          "fly_elite": "qdsearch.analysis.notebook", "hold_kernels": "qdsearch.base.kernels"}
__all__ = list(PUBLIC)


def __getattr__(name: str):
    """The public API's names, each imported when first used: the command line imports this
    package too, and answers --help without pandas and pyribs."""
    if name in PUBLIC:
        import importlib

        return getattr(importlib.import_module(PUBLIC[name]), name)
    raise AttributeError(f"module 'qdsearch' has no attribute {name!r}")
