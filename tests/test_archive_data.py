"""archive.npz and an old folder's archive.csv made back into real pyribs archives (grid and CVT),
bit for bit and in their order, without a cluster; and each kind of bad file refused in one line."""

import zipfile

import numpy as np
import pytest

from qdsearch import algorithms
from qdsearch.base.flags import UsageError
from qdsearch.base.run_files import write_csv
from qdsearch.config import options, run_config
from qdsearch.store import archive_data


def lander_config(kind: str):
    size = {"grid": 4} if kind == "grid" else {"archive": "cvt", "cells": 8, "grid": None}
    return run_config.check_run_config(options.with_task({**options.search_defaults(), "seed": 3, **size}))


def filled(kind: str):
    """A real archive of the lander's measures, filled by two adds (two runs of rising cells)."""
    config = lander_config(kind)
    archive = algorithms.ARCHIVES[kind]["make"](config)(seed=1)
    rng = np.random.default_rng(4)
    for _ in range(2):
        archive.add(rng.normal(size=(20, 32)), rng.normal(size=20) * 100,
                    rng.uniform([-1.0, -3.0], [1.0, 0.0], size=(20, 2)))
    return archive, config


def assert_same(made, archive) -> None:
    assert type(made) is type(archive)
    assert made.data(return_type="pandas").equals(archive.data(return_type="pandas"))
    for name in ("lower_bounds", "upper_bounds", *(("centroids",) if hasattr(archive, "centroids") else ())):
        assert np.array_equal(getattr(made, name), getattr(archive, name)), name
    assert (made.solution_dim, made.qd_score_offset) == (archive.solution_dim, archive.qd_score_offset)


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_archive_data_makes_the_archive_again(tmp_path, kind):
    archive, config = filled(kind)
    assert len(set(archive.data("index").tolist())) == len(archive) >= 8
    path = tmp_path / "archive.npz"
    archive_data.write_archive_data(path, archive, config.to_json())
    made, recorded = archive_data.read_archive_data(path)
    assert_same(made, archive)
    assert recorded == config.to_json() == archive_data.recorded_config(path)
    with np.load(path, allow_pickle=False) as data:
        assert set(data.files) == {"format", "kind", "solution_dim", "dims", "lower_bounds", "upper_bounds",
                                   "qd_score_offset", "config", *archive_data.ELITE_FIELDS,
                                   *(["centroids"] if kind == "cvt" else [])}
        assert list(data["dims"]) == ([4, 4] if kind == "grid" else [8])


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_an_old_folders_archive_csv_makes_the_archive_again(tmp_path, kind):
    archive, config = filled(kind)
    write_csv(tmp_path / "archive.csv", archive.data(return_type="pandas"))
    centroids = tmp_path / "centroids.npy"
    if kind == "cvt":
        np.save(centroids, archive.centroids)
    empty = archive_data.empty_archive(config, centroids)
    made = archive_data.archive_from_csv(tmp_path / "archive.csv", empty)
    assert_same(made, archive)
    table = archive.data(return_type="pandas").drop(columns="threshold")  # pyribs' older tables
    write_csv(tmp_path / "old.csv", table)
    again = archive_data.archive_from_csv(tmp_path / "old.csv", archive_data.empty_archive(config, centroids))
    assert again.data(return_type="pandas").drop(columns="threshold").equals(table)


def refused(action, *said: str) -> None:
    with pytest.raises(UsageError) as caught:
        action()
    assert "\n" not in str(caught.value) and all(words in str(caught.value) for words in said), caught.value


def test_bad_archive_data_is_refused_in_one_line(tmp_path):
    archive, config = filled("grid")
    good, path = tmp_path / "good.npz", tmp_path / "archive.npz"
    archive_data.write_archive_data(good, archive, config.to_json())
    with np.load(good, allow_pickle=False) as data:
        fields = dict(data)

    def written(**changes) -> None:
        np.savez(path, **{**fields, **changes})

    read = lambda: archive_data.read_archive_data(path)  # noqa: E731
    path.write_bytes(b"solution,objective\n1,2\n")
    refused(read, f"{path}: not a readable archive data file (not an .npz, a zip of numpy arrays)")
    written(kind=np.array([{"a": 1}], dtype=object))
    refused(read, f"{path}: not a readable archive data file (it holds pickled Python objects, which are "
                  "never loaded)")
    written(format=2)
    refused(read, f"{path}: archive data of format 2, not 1 (not written by lunar_lander.py, or by "
                  "another version of it?)")
    with zipfile.ZipFile(path, "w") as bare:
        bare.writestr("kind.npy", good.read_bytes()[:10])
    refused(read, f"{path}: archive data of format None, not 1")
    with zipfile.ZipFile(path, "w") as bare:  # numpy's own words for a bad array, not a pickle's
        bare.writestr("format.npy", b"\x93NUMPY garbage")
    refused(read, f"{path}: not a readable archive data file (we only support format version")
    written(dims=np.array([2**32, 2**32]))  # a product beyond int64's: counted as a float
    refused(read, f"(4294967296x4294967296 cells, more than any run's {options.MAX_CELLS:,})")
    written(dims=np.array([10**5, 10**5]))
    refused(read, f"{path}: not a readable archive data file (100000x100000 cells, more than any run's "
                  f"{options.MAX_CELLS:,})")
    written(kind="hexagonal")
    refused(read, f"{path}: not a readable archive data file (")
    written(solution=np.array([None], dtype=object))  # the config alone is read (config.json checked)
    assert archive_data.recorded_config(path) == config.to_json()
    written(config="{not json")
    refused(lambda: archive_data.recorded_config(path), f"{path}: its config is not readable JSON (")
    measures = fields["measures"].copy()
    measures[[0, 1]] = measures[[1, 0]]  # two elites swapped: each in the other's cell
    written(measures=measures)
    refused(read, f"{path}: its elites do not go back into the cells it says they held (not an archive "
                  "lunar_lander.py wrote, or changed since)")
    written(measures=fields["measures"][:, :1])
    refused(read, f"{path}: its elites do not fit its archive (", "measures")


def test_a_bad_archive_csv_or_centroids_file_is_refused_in_one_line(tmp_path):
    archive, config = filled("cvt")
    centroids, table = tmp_path / "centroids.npy", tmp_path / "archive.csv"
    centroids.write_bytes(b"not a numpy file")
    refused(lambda: archive_data.empty_archive(config, centroids),
            f"{centroids}: no readable centroids of the run's CVT archive (")
    np.save(centroids, archive.centroids)
    centroids.write_bytes(centroids.read_bytes()[:-40])  # cut short
    refused(lambda: archive_data.empty_archive(config, centroids),
            f"{centroids}: no readable centroids of the run's CVT archive (", "expected 128 bytes got 88")
    np.save(centroids, archive.centroids[:, :1])
    refused(lambda: archive_data.empty_archive(config, centroids),
            f"{centroids}: not the centroids of the run's archive (", "but it had shape (8, 1)")
    np.save(centroids, archive.centroids)
    empty = lambda: archive_data.empty_archive(config, centroids)  # noqa: E731
    saved = archive.data(return_type="pandas")
    write_csv(table, saved.drop(columns="objective"))
    refused(lambda: archive_data.archive_from_csv(table, empty()), f"{table}: not a readable archive table (",
            "objective")
    for column in ("threshold", "measures_0"):  # an elite's threshold, or its place, changed
        write_csv(table, saved.assign(**{column: saved[column].to_numpy()[::-1]}))
        refused(lambda: archive_data.archive_from_csv(table, empty()),
                f"{table}: its elites do not go back into the cells it says they held")


def test_numbered_columns_are_in_their_numbers_order():
    import pandas as pd

    table = pd.DataFrame(columns=["solution_10", "solution_2", "objective", "solution_0", "solution_x",
                                  "measures_1", "my_solution_1"])
    assert archive_data.numbered_columns(table, "solution") == ["solution_0", "solution_2", "solution_10"]
    assert archive_data.numbered_columns(table, "measures") == ["measures_1"]
