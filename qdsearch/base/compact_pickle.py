"""Pickles of a search's state that grow with its archives' elites, not their cells.

A pyribs archive keeps its data in an ArrayStore of dense arrays, a row per cell: a 32 x 32 grid
of 128,128-MLP HalfCheetah policies holds 1,024 x 19,590 weights (160 MB) with 8 elites in it.
Only the occupied rows mean anything (pyribs masks the others on every read, and allocates them
with np.empty), so the checkpoint and the driver's snapshot keep those rows alone and give the
others zeros when unpickled. Everything else pickles as pickle does, bit for bit.

Map: `dumps` (a pickle with every ArrayStore compacted), `compact_transfers` (so are those sent
to another process by multiprocessing: the saver processes), `compact_store` (the reducer) and
`restore_store` (what unpickling calls: the module must stay importable under this name).
"""

from __future__ import annotations

import copyreg
import io
import pickle
from typing import Any

import numpy as np


def restore_store(state: dict[str, Any], rows: np.ndarray, fields: dict[str, np.ndarray],
                  capacity: int) -> Any:
    """An ArrayStore from its compacted state: each field's occupied `rows` put back in a dense
    array of zeros (its unoccupied rows, which nothing reads)."""
    from ribs.archives import ArrayStore

    store = ArrayStore.__new__(ArrayStore)
    dense = {}
    for name, values in fields.items():
        dense[name] = np.zeros((capacity, *values.shape[1:]), dtype=values.dtype)
        dense[name][rows] = values
    store.__setstate__({**state, "_fields": dense})  # (pyribs' own: its array module by name)
    return store


def compact_store(store: Any) -> tuple:
    """The reducer of an ArrayStore: its state with each field's occupied rows alone."""
    state = store.__getstate__()
    occupied = np.asarray(state["_props"]["occupied"])
    rows = np.flatnonzero(occupied)
    fields = {name: np.ascontiguousarray(values[rows]) for name, values in state.pop("_fields").items()}
    return restore_store, (state, rows, fields, int(state["_props"]["capacity"]))


def compact_transfers() -> None:
    """multiprocessing's pickles (a save handed to a saver process) compact every ArrayStore."""
    from multiprocessing.reduction import ForkingPickler

    from ribs.archives import ArrayStore

    ForkingPickler.register(ArrayStore, compact_store)


def dumps(obj: Any) -> bytes:
    """`obj` pickled (highest protocol), every pyribs ArrayStore in it compacted."""
    from ribs.archives import ArrayStore  # (here: pyribs' import is slow, and --help needs none)

    buffer = io.BytesIO()
    pickler = pickle.Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.dispatch_table = {**copyreg.dispatch_table, ArrayStore: compact_store}
    pickler.dump(obj)
    return buffer.getvalue()
