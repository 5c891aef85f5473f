"""A run folder's archive as data, safe to open whoever wrote it: archive.npz (and evaluate's
corrected_archive.npz), read by numpy without unpickling anything and made back into the pyribs
archive it was; and, for folders from before archive.npz, their archive.csv.

Why numpy's .npz: numpy is a dependency already; it keeps every float64 bit (a CSV keeps them
only if its writer printed every digit); and it holds arrays of any shape, such as a CVT
archive's centroids. archive.pkl is written only with --archive_pkl (pyribs users load it), and
no command reads it: loading a pickle runs any code it holds.

An archive.npz holds `format` (ARCHIVE_FORMAT), the archive's `kind` (grid, cvt), `solution_dim`,
`dims` (a CVT's: its cells), `lower_bounds`, `upper_bounds`, `qd_score_offset`, a CVT's
`centroids`, every elite's `solution`, `objective`, `measures`, `threshold` and `index` (pyribs'
archive.data()), and `config`, the run's config as JSON text.

Map:
- ARCHIVE_FORMAT; `write_archive_data`;
- `read_archive_data` (the archive, and the config it was saved with; `archive_fields`),
  `recorded_config` (the config alone: what config.json is checked against);
- `archive_from_csv` (a folder from before archive.npz: its CSV on the cells of its config,
  `empty_archive`);
- `rebuilt`: the elites added to an empty archive of their cells, checked to be what was saved
  (in its order too).
"""

from __future__ import annotations

import io
import json
import re
import types
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from qdsearch.algorithms import ARCHIVES, MAX_CELLS, RowConfig, archive_shape, kind_of
from qdsearch.base.flags import UsageError
from qdsearch.base.run_files import FILE_BOUNDS, atomic_write, fault_text, open_regular, read_regular

ARCHIVE_FORMAT = 1  # an archive.npz of another format is refused, not misread
ELITE_FIELDS = ("solution", "objective", "measures", "threshold", "index")  # pyribs' archive.data()
# What a file that is not the archive it claims to be raises while it is made back (a MemoryError:
# cells or weights beyond any run's).
BAD_DATA = (KeyError, ValueError, TypeError, IndexError, MemoryError)


def write_archive_data(path: Path, archive: Any, recorded: dict[str, Any]) -> None:
    """The archive (of a kind of ARCHIVES) and its run's config as recorded (config.json's JSON) as
    an .npz, written whole or not at all."""
    kind = kind_of(archive)
    fields = {"format": ARCHIVE_FORMAT, "kind": kind, "solution_dim": archive.solution_dim,
              "dims": archive.dims if kind == "grid" else [archive.cells],
              "lower_bounds": archive.lower_bounds, "upper_bounds": archive.upper_bounds,
              "qd_score_offset": archive.qd_score_offset, "config": json.dumps(recorded),
              **archive.data(list(ELITE_FIELDS))}
    if kind == "cvt":
        fields["centroids"] = archive.centroids
    atomic_write(path, lambda file: np.savez(file, **fields))


def archive_fields(path: Path, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The arrays of an archive.npz (`names` only, if given), read without unpickling, of
    ARCHIVE_FORMAT; or a one-line refusal."""
    # only the arrays asked for are read (the config alone is a few bytes of a large archive's)
    with open_regular(path, "archive.npz") as file:
        if not zipfile.is_zipfile(file):  # numpy's own message would offer to unpickle it
            raise UsageError(f"{path}: not a readable archive data file (not an .npz, a zip of numpy "
                             f"arrays)")
        try:
            file.seek(0)
            with np.load(file, allow_pickle=False) as data:
                # its arrays unpacked are bounded as the file is (a few zipped bytes may unpack to any size)
                if sum(member.file_size for member in data.zip.infolist()) > FILE_BOUNDS["archive.npz"][0]:
                    raise ValueError("its arrays unpacked are larger than any run's archive")
                fields = {name: data[name] for name in (data.files if names is None else ("format", *names))}
        except Exception as error:  # not a zip of .npy files; a field missing; an object array
            why = ("it holds pickled Python objects, which are never loaded" if "pickle" in str(error)
                   else fault_text(error))  # (numpy's own words would offer to unpickle them)
            raise UsageError(f"{path}: not a readable archive data file ({why})") from None
    found = fields.get("format", np.array(None, dtype=object))
    if found.shape != () or found.item() != ARCHIVE_FORMAT:
        raise UsageError(f"{path}: archive data of format {found!s}, not {ARCHIVE_FORMAT} (not "
                         f"written by lunar_lander.py, or by another version of it?)")
    return fields


def read_archive_data(path: Path) -> tuple[Any, dict]:
    """An archive.npz made back into its pyribs archive, and the config it was saved with."""
    fields = archive_fields(path)
    try:
        kind = str(fields["kind"])
        like = types.SimpleNamespace(
            solution_dim=int(fields["solution_dim"]), dims=tuple(int(d) for d in fields["dims"]),
            lower_bounds=fields["lower_bounds"], upper_bounds=fields["upper_bounds"],
            qd_score_offset=float(fields["qd_score_offset"]), centroids=fields.get("centroids"))
        if np.prod(like.dims, dtype=float) > MAX_CELLS:
            raise ValueError(f"{'x'.join(map(str, like.dims))} cells, more than any run's {MAX_CELLS:,}")
        config = json.loads(str(fields["config"]))
        empty = ARCHIVES[kind]["empty_like"](like)
    except BAD_DATA as error:
        raise UsageError(f"{path}: not a readable archive data file ({fault_text(error)})") from None
    return rebuilt(empty, fields, path), config


def recorded_config(path: Path) -> Any:
    """The config an archive.npz was saved with (JSON), without making its archive."""
    text = str(archive_fields(path, ("config",))["config"])
    try:
        return json.loads(text)
    except ValueError as error:
        raise UsageError(f"{path}: its config is not readable JSON ({error})") from None


def empty_archive(config: RowConfig, centroids: Path) -> Any:
    """An empty archive of a run's cells, from its settings and, for a CVT archive,
    its centroids.npy."""
    if config.archive == "grid":
        return ARCHIVES["grid"]["make"](config)()
    try:
        found = np.load(io.BytesIO(read_regular(centroids, "centroids.npy")), allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        raise UsageError(f"{centroids}: no readable centroids of the run's CVT archive "
                         f"({fault_text(error)})") from None
    from ribs.archives import CVTArchive

    try:
        return CVTArchive(**archive_shape(config), centroids=found)
    except BAD_DATA as error:
        raise UsageError(f"{centroids}: not the centroids of the run's archive "
                         f"({fault_text(error)})") from None


def numbered_columns(table: Any, name: str) -> list[str]:
    """A CSV's columns name_0, name_1, ... (pyribs' names of an array field's columns), in order."""
    found = {int(match[1]): column for column in table.columns
             if (match := re.fullmatch(rf"{name}_(\d+)", str(column)))}
    return [found[i] for i in sorted(found)]


def archive_from_csv(path: Path, empty: Any) -> Any:
    """An archive.csv (written by pandas from archive.data(), its floats in their shortest exact
    text, which pandas reads back bit for bit) made back into `empty`, an archive of its cells."""
    import pandas as pd

    try:
        table = pd.read_csv(io.BytesIO(read_regular(path, "archive.csv")))
        elites = {"solution": table[numbered_columns(table, "solution")].to_numpy(np.float64),
                  "objective": table["objective"].to_numpy(np.float64),
                  "measures": table[numbered_columns(table, "measures")].to_numpy(np.float64),
                  "index": table["index"].to_numpy(np.int64)}
        if "threshold" in table:
            elites["threshold"] = table["threshold"].to_numpy(np.float64)
    except (OSError, *BAD_DATA) as error:
        raise UsageError(f"{path}: not a readable archive table ({fault_text(error)})") from None
    return rebuilt(empty, elites, path)


def rebuilt(archive: Any, elites: dict[str, np.ndarray], path: Path) -> Any:
    """`archive` (empty) with the saved elites added by their measures, in their saved order: its
    data() then holds what was saved, field by field, bit for bit and in the same order (an
    emitter that samples elites, a warm start, a CQD score's sums see the archive as the run
    left it), which is checked: a file whose elites would land in other cells is refused.

    A batch add inserts its elites in the order of their cells, and data() lists cells in the
    order they were first filled: so each run of rising cell numbers is added as one batch (a
    run's archive holds a run of them per iteration that filled new cells)."""
    saved = {name: np.asarray(elites[name]) for name in ELITE_FIELDS if name in elites}
    rising = np.split(np.arange(len(saved["index"])), np.flatnonzero(np.diff(saved["index"]) <= 0) + 1)
    try:
        for batch in rising:
            archive.add(saved["solution"][batch], saved["objective"][batch], saved["measures"][batch])
    except BAD_DATA as error:
        raise UsageError(f"{path}: its elites do not fit its archive ({fault_text(error)})") from None
    made = archive.data(list(saved))
    if not all(np.array_equal(made[name], saved[name]) for name in saved):
        raise UsageError(f"{path}: its elites do not go back into the cells it says they held (not "
                         f"an archive lunar_lander.py wrote, or changed since)")
    return archive
