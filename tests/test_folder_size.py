"""A run folder grows with its archive's elites, not its cells: the checkpoint and the driver's
snapshots keep an archive's occupied rows alone (compact_pickle), and archive.pkl, a row per cell,
is written only with --archive_pkl."""

import pickle

import numpy as np
import pytest
from ribs.archives import GridArchive

from qdsearch.base import compact_pickle
from qdsearch.cli import commands
from util import archive_table, read_checkpoint, run_archive, tiny_flags

WEIGHTS = 20_000


def filled_archive(elites: int, seed: int = 0) -> GridArchive:
    """A CMA-MAE-style 32 x 32 archive (thresholds of its own) of `elites` random solutions."""
    archive = GridArchive(solution_dim=WEIGHTS, dims=(32, 32), ranges=[(0, 1), (0, 1)],
                          learning_rate=0.5, threshold_min=-10.0)
    rng = np.random.default_rng(seed)
    archive.add(rng.normal(size=(elites, WEIGHTS)), rng.normal(size=elites), rng.uniform(size=(elites, 2)))
    return archive


def test_a_compact_pickle_holds_the_occupied_rows_and_the_archive_goes_on_as_before():
    archive = filled_archive(8)
    compact = compact_pickle.dumps(archive)
    assert len(compact) < 8 * WEIGHTS * 8 + 200_000 < len(pickle.dumps(archive)) / 100
    copy = pickle.loads(compact)
    assert archive_table(copy).equals(archive_table(archive))
    store, original = copy._store, archive._store
    occupied = original._props["occupied"]
    assert np.array_equal(store._props["occupied"], occupied)
    for name, values in original._fields.items():
        assert np.array_equal(store._fields[name][occupied], values[occupied]), name
        assert not store._fields[name][~occupied].any(), name  # zeros: nothing reads them
    batch = filled_archive(30, seed=1).data()  # the same adds to both: the same archives after
    for target in (archive, copy):
        target.add(batch["solution"], batch["objective"], batch["measures"])
    assert archive_table(copy).equals(archive_table(archive))
    assert np.array_equal(copy._store._fields["threshold"][copy._store._props["occupied"]],
                          archive._store._fields["threshold"][archive._store._props["occupied"]])


def test_an_archive_sent_to_a_saver_process_is_compact_too():
    """multiprocessing pickles what a save hands a saver process: ArrayStores compacted there too."""
    from multiprocessing.reduction import ForkingPickler

    archive = filled_archive(8)
    compact_pickle.compact_transfers()
    sent = bytes(ForkingPickler.dumps(archive))
    assert len(sent) < 8 * WEIGHTS * 8 + 200_000
    assert archive_table(pickle.loads(sent)).equals(archive_table(archive))


@pytest.mark.slow  # a MuJoCo run of a 19,590-weight network
def test_a_128_128_mlp_run_on_a_32x32_grid_writes_a_folder_in_proportion_to_its_elites(
        tmp_path, dask_cluster, recwarn):
    """(Its batch of 80 networks is 12.5 MB, a graph Dask would warn of on every send: not here.)"""
    folder = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, env="HalfCheetah-v5", policy="mlp", hidden="128,128", grid=32,
                            algorithm="map_elites", n_emitters=1, batch_size=80, episode_length=5,
                            iterations=2, log_every=1), outdir=str(folder))
    assert not [w for w in recwarn if "large graph" in str(w.message)]
    archive = run_archive(folder)
    weights = 17 * 128 + 128 + 128 * 128 + 128 + 128 * 6 + 6  # 17 -> 128 -> 128 -> 6, with biases
    assert weights == 19_590 and 1 <= len(archive) <= 36  # 5 steps: contact shares in sixths
    per_elite = weights * 8  # bytes of one elite's float64 weights
    sizes = {path.name: path.stat().st_size for path in folder.iterdir() if path.is_file()}
    assert "archive.pkl" not in sizes
    # (the scheduler keeps its last batch of 80 for its tell: a batch, not the cells)
    assert sizes["checkpoint.pkl"] < (len(archive) + 80) * per_elite + 2_000_000
    assert sizes["archive.npz"] < len(archive) * per_elite + 100_000
    # the CSV's text: ~21 bytes a weight
    assert sum(sizes.values()) < len(archive) * 30 * weights + 80 * per_elite + 4_000_000
    assert sum(sizes.values()) < 32 * 32 * per_elite / 4  # a dense copy of its cells: 160 MB
    checkpoint = read_checkpoint(folder / "checkpoint.pkl")
    assert archive_table(checkpoint["scheduler"].result_archive).equals(archive)
    asked = tmp_path / "asked"
    commands.search(**tiny_flags(dask_cluster, iterations=1, archive_pkl=True), outdir=str(asked))
    with open(asked / "archive.pkl", "rb") as file:
        assert archive_table(pickle.load(file)).equals(run_archive(asked))
