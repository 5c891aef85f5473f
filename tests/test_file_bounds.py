"""Only regular files are read back, each within its kind's bound (issue 60): a checkpoint,
archive, metrics, config, plan or key file that is a link to a device, a link to nowhere or a
folder, or that holds more than its bound, is one line naming it, exit 2, nothing written, and
never read whole (run_files.read_regular). A link to a regular file is read as the file. Beside
them, the guards of a folder from anyone: a signing key its group may use, an archive.npz whose
cells disagree with its measures, and read_run's promise never to unpickle."""

import os
import pickle
import resource
import shutil
import socket

import numpy as np
import pandas as pd
import pytest

import qdsearch
from qdsearch.analysis import live
from qdsearch.base import run_files, signing
from qdsearch.base.flags import UsageError
from qdsearch.config import run_config
from util import assert_one_line_error, folder_state

GIB = 1 << 30


class Trap:
    """Unpickled, it makes the file `marker` (as any code a pickle holds would run; as
    test_safe_folders' trap)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


@pytest.fixture
def bounded_memory():
    """While the test runs, this process may take at most 1 GiB more memory (RLIMIT_DATA): a reader
    that read a link to /dev/zero whole would fail at once, not take the shared machine's memory."""
    with open("/proc/self/status") as status:
        used = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmData:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_DATA)
    bound = used + GIB if hard == resource.RLIM_INFINITY else min(used + GIB, hard)  # (infinity is -1)
    resource.setrlimit(resource.RLIMIT_DATA, (bound, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_DATA, (soft, hard))


def spoil(path, how: str, tmp_path) -> None:
    """`path` replaced by what is no regular file: a link to /dev/zero, a link to nowhere, a folder."""
    path.unlink(missing_ok=True)
    if how == "folder":
        path.mkdir()
    else:
        path.symlink_to("/dev/zero" if how == "device" else tmp_path / "gone")


SPOILS = {"device": "is a character device (a link to /dev/zero)", "nowhere": "which does not exist",
          "folder": "is a folder"}


def state(folder) -> tuple:
    """Every name in `folder` (links and folders too) and every file's bytes."""
    return sorted(os.listdir(folder)), folder_state(folder)


def copied(tiny_run, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    return run_dir


@pytest.mark.parametrize("how", SPOILS)
def test_resume_refuses_a_checkpoint_that_is_no_regular_file(tmp_path, tiny_run, run_cli, dask_cluster,
                                                             bounded_memory, how):
    """Never taken for "no checkpoint yet" (which would start the run over from iteration 0)."""
    run_dir = copied(tiny_run, tmp_path)
    spoil(run_dir / "checkpoint.pkl", how, tmp_path)
    before = state(run_dir)
    result = run_cli("resume", run_dir, "--iterations", 4,
                     "--scheduler_address", dask_cluster.scheduler_address)
    assert_one_line_error(result, f"{run_dir / 'checkpoint.pkl'} ", SPOILS[how], "must be a regular file")
    assert state(run_dir) == before


@pytest.mark.parametrize("how", SPOILS)
def test_compare_and_read_run_refuse_an_archive_csv_that_is_no_regular_file(tmp_path, tiny_run, run_cli,
                                                                            bounded_memory, how):
    run_dir = copied(tiny_run, tmp_path)
    spoil(run_dir / "archive.csv", how, tmp_path)
    before = state(run_dir)
    result = run_cli("compare", run_dir, "--out", tmp_path / "compare.png")
    assert_one_line_error(result, f"{run_dir / 'archive.csv'} ", SPOILS[how])
    with pytest.raises(UsageError) as refused:
        qdsearch.read_run(run_dir)
    assert str(refused.value).startswith(f"{run_dir / 'archive.csv'} ") and SPOILS[how] in str(refused.value)
    assert state(run_dir) == before and not list(tmp_path.glob("compare*"))


def test_the_watch_page_shows_no_elites_of_a_device_and_watch_refuses_it(tmp_path, tiny_run, run_process,
                                                                         bounded_memory):
    run_dir = copied(tiny_run, tmp_path)
    config = run_config.load_checked_config(run_dir)
    assert len(live.elite_columns(run_dir, config)["x"]) == len(pd.read_csv(run_dir / "archive.csv"))
    spoil(run_dir / "archive.csv", "device", tmp_path)
    assert live.elite_columns(run_dir, config) == {"x": [], "y": [], "objective": []}  # read, bounded
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    # a process with a time limit: a watch that served the folder would never end by itself
    result = run_process("watch", run_dir, "--port", port, timeout=60)
    assert_one_line_error(result, f"{run_dir / 'archive.csv'} is a character device")


@pytest.mark.parametrize("how", SPOILS)
def test_experiment_refuses_a_plan_that_is_no_regular_file(tmp_path, run_cli, bounded_memory, how):
    plan = tmp_path / "plan.toml"
    spoil(plan, how, tmp_path)
    result = run_cli("experiment", "--plan", plan, "--outdir", tmp_path / "exp")
    assert_one_line_error(result, f"--plan {plan} ", SPOILS[how], "a plan file must be a regular file")
    assert not (tmp_path / "exp").exists()


def test_a_plan_over_its_bound_is_refused(tmp_path, run_cli, monkeypatch):
    plan = tmp_path / "plan.toml"
    plan.write_text('algorithms = "cma_me"\nseeds = "1-2"\niterations = 1\n')
    monkeypatch.setitem(run_files.FILE_BOUNDS, "plan", (plan.stat().st_size - 1, "a plan file"))
    result = run_cli("experiment", "--plan", plan, "--outdir", tmp_path / "exp")
    assert_one_line_error(result, f"--plan {plan} is {plan.stat().st_size} bytes, more than the "
                                  f"{plan.stat().st_size - 1} bytes a plan file may hold")
    assert not (tmp_path / "exp").exists()


@pytest.mark.parametrize("name, command", [
    ("checkpoint.pkl", ["resume", "{run}", "--iterations", "4", "--scheduler_address", "{address}"]),
    ("config.json", ["elites", "{run}"]),
    ("archive.npz", ["elites", "{run}"]),
    ("metrics.json", ["compare", "{run}", "--out", "{tmp}/compare.png"]),
    ("archive.csv", ["compare", "{run}", "--out", "{tmp}/compare.png"]),
])
def test_a_file_just_over_its_bound_is_refused(tmp_path, tiny_run, dask_cluster, run_cli, monkeypatch, name,
                                               command):
    run_dir = copied(tiny_run, tmp_path)
    size = (run_dir / name).stat().st_size
    label = run_files.FILE_BOUNDS[name][1]
    monkeypatch.setitem(run_files.FILE_BOUNDS, name, (size - 1, label))
    before = state(run_dir)
    result = run_cli(*[part.format(run=run_dir, tmp=tmp_path, address=dask_cluster.scheduler_address)
                       for part in command])
    assert_one_line_error(result, f"{run_dir / name} is ", f"more than the {run_files.byte_size(size - 1)} "
                                                           f"{label} may hold")
    assert state(run_dir) == before and not (tmp_path / "compare.png").exists()
    monkeypatch.setitem(run_files.FILE_BOUNDS, name, (size, label))  # at its bound: read
    assert run_files.read_regular(run_dir / name, name) == (run_dir / name).read_bytes()


def test_a_file_that_grows_while_read_is_read_no_further_than_its_bound(tmp_path, monkeypatch):
    """What a file gives past the size it had when opened counts too (here a pipe's bytes, which no
    size foretells): no more than the bound and a byte are read."""
    monkeypatch.setitem(run_files.FILE_BOUNDS, "plan", (100, "a plan file"))
    given, taken = os.pipe()
    os.write(taken, b"x" * 300)
    os.close(taken)
    try:
        with pytest.raises(UsageError, match="grew past the 100 bytes a plan file may hold"):
            run_files.read_bounded(given, tmp_path / "plan.toml", "plan", 0)
        assert len(os.read(given, 1000)) == 300 - 101  # the rest is left unread
    finally:
        os.close(given)


def test_links_to_regular_files_are_read_as_the_files(tmp_path, tiny_run, run_cli):
    """A run folder that is a link, and files that are links to regular files (another disk, a
    data store's cache), are read as ever."""
    store, run_dir = tmp_path / "store", tmp_path / "linked"
    shutil.copytree(tiny_run, store)
    (tmp_path / "run").mkdir()
    for name in ("archive.npz", "archive.csv", "config.json", "metrics.json"):
        (tmp_path / "run" / name).symlink_to(store / name)
    run_dir.symlink_to(tmp_path / "run")
    result = run_cli("elites", run_dir, "--top", 2)
    assert result.returncode == 0, result.stderr
    assert len(qdsearch.read_run(run_dir).archive) == len(pd.read_csv(store / "archive.csv"))


@pytest.mark.parametrize("mode, refused", [(0o640, True), (0o660, True), (0o604, True), (0o620, True),
                                           (0o600, False), (0o400, False)])
def test_a_key_its_group_or_others_may_use_is_refused(tmp_path, monkeypatch, mode, refused):
    key = tmp_path / "key"
    monkeypatch.setenv("QDSEARCH_KEY", str(key))
    made = signing.user_key()
    key.chmod(mode)
    if refused:
        with pytest.raises(UsageError, match=f"chmod 600 {key}"):
            signing.user_key()
    else:
        assert signing.user_key() == made and len(made) == 32


@pytest.mark.parametrize("how", SPOILS)
def test_a_key_that_is_no_regular_file_is_named_so(tmp_path, tiny_run, run_cli, monkeypatch, bounded_memory,
                                                   how):
    """QDSEARCH_KEY naming a folder (or a device) is one line that says so, not a chmod to make."""
    key, run_dir = tmp_path / "keys", copied(tiny_run, tmp_path)
    spoil(key, how, tmp_path)
    monkeypatch.setenv("QDSEARCH_KEY", str(key))
    before = state(run_dir)
    result = run_cli("resume", run_dir)
    assert_one_line_error(result, f"{key} ", SPOILS[how], "a signing key must be a regular file")
    assert "chmod" not in result.stderr and state(run_dir) == before


def test_an_archive_npz_whose_cells_disagree_with_its_measures_is_refused(tmp_path, tiny_run, run_cli):
    """One elite's cell index changed by hand to an empty cell: the elites go back by their
    measures, into other cells than the file says, and it is refused."""
    run_dir = copied(tiny_run, tmp_path)
    with np.load(run_dir / "archive.npz", allow_pickle=False) as data:
        fields = dict(data)
    assert run_cli("elites", run_dir, "--top", 1).returncode == 0
    cells = int(np.prod(fields["dims"]))
    free = next(cell for cell in range(cells) if cell not in set(fields["index"].tolist()))
    fields["index"] = fields["index"].copy()
    fields["index"][len(fields["index"]) // 2] = free
    with open(run_dir / "archive.npz", "wb") as file:
        np.savez(file, **fields)
    before = state(run_dir)
    assert_one_line_error(run_cli("elites", run_dir), f"{run_dir / 'archive.npz'}: its elites do not go back "
                                                      f"into the cells it says they held")
    assert state(run_dir) == before


@pytest.mark.parametrize("pickled", ["trap", "garbage"])
def test_read_run_never_unpickles(tmp_path, tiny_run, pickled):
    """read_run reads archive.csv (and config.json, metrics.json), whatever archive.pkl and
    checkpoint.pkl hold: a pickle that would make a file, or garbage."""
    run_dir, marker = copied(tiny_run, tmp_path), tmp_path / "marker"
    payload = pickle.dumps(Trap(marker)) if pickled == "trap" else b"\x80\x05garbage"
    if pickled == "trap":  # it is live: unpickled, it makes its file
        pickle.loads(payload)
        assert marker.exists()
        marker.unlink()
    for name in ("archive.pkl", "checkpoint.pkl"):
        (run_dir / name).write_bytes(payload)
    found = qdsearch.read_run(run_dir)
    table = pd.read_csv(run_dir / "archive.csv")
    assert np.array_equal(found.archive.get_field("objective"), table["objective"].to_numpy())
    assert len(found.metrics) == 3 and not marker.exists()
