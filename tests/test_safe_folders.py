"""A run folder from anyone is safe to open (issue 48): the results commands read archive.npz (or an
old folder's archive.csv), never a pickle; checkpoints are signed with the user's key, and resume
refuses any other (unsigned, another key's, changed by a byte) until told --trust."""

import json
import os
import pickle
import shutil
import stat
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

from qdsearch.analysis import run_folder
from qdsearch.base import signing
from qdsearch.base.flags import UsageError
from qdsearch.cli import commands
from qdsearch.store import archive_data
from util import (
    REFERENCE_ITERATIONS,
    archive_table,
    assert_one_line_error,
    assert_same_run,
    checkpoint_payload,
    folder_state,
    launch,
    read_checkpoint,
    saved_archive,
    stop_all,
    tiny_flags,
)


class Trap:
    """Unpickled, it makes the file `marker` (as any code a pickle holds would run)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def trapped(run_dir, marker):
    """archive.pkl and checkpoint.pkl of `run_dir` replaced by traps that make `marker`."""
    for name in ("archive.pkl", "checkpoint.pkl"):
        (run_dir / name).write_bytes(pickle.dumps(Trap(marker)))


def test_the_trap_is_live(tmp_path):
    """The traps below would make their file if anything unpickled them."""
    pickle.loads(pickle.dumps(Trap(tmp_path / "made")))
    assert (tmp_path / "made").exists()


def free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def watch_serves(run_dir) -> None:
    """`watch` as a real process serves its page (the page's document is made from the run's
    files when the page is asked for)."""
    port = free_port()
    server = launch("watch", run_dir, port=port)
    try:
        deadline = time.time() + 60
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
                    assert page.status == 200 and b"Bokeh" in page.read()
                return
            except OSError:
                assert time.time() < deadline and server.poll() is None, server.communicate()
                time.sleep(0.3)
    finally:
        stop_all([server])


def open_with_every_command(run_cli, run_dir, cluster, out):
    """Every results command on `run_dir` works."""
    address = ("--scheduler_address", cluster.scheduler_address)
    for args in (["video", run_dir, "--best"], ["elites", run_dir, "--top", 3],
                 ["trajectories", run_dir, "--best"],
                 ["evaluate", run_dir, "--env_seeds", 3, "--top", 2, *address],
                 ["explore", run_dir, *address], ["compare", run_dir, "--out", out / "compare.png"]):
        result = run_cli(*args)
        assert result.returncode == 0, (args, result.stderr)
    assert (run_dir / "videos" / "index.csv").is_file() and (run_dir / "explorer.html").is_file()
    watch_serves(run_dir)


def test_results_commands_and_warm_starts_never_unpickle(tmp_path, tiny_run, dask_cluster, run_cli,
                                                         run_process):
    run_dir, marker = tmp_path / "run", tmp_path / "marker"
    shutil.copytree(tiny_run, run_dir)
    trapped(run_dir, marker)

    open_with_every_command(run_cli, run_dir, dask_cluster, tmp_path)
    warm = run_cli("--iterations", 1, "--from_archive", run_dir / "archive.pkl",
                   "--outdir", tmp_path / "warm", "--scheduler_address", dask_cluster.scheduler_address)
    assert warm.returncode == 0, warm.stderr
    assert not marker.exists()

    before = folder_state(run_dir)
    assert_one_line_error(run_process("resume", run_dir), "checkpoint.pkl: not signed", "--trust")
    assert not marker.exists() and folder_state(run_dir) == before


@pytest.fixture(scope="module")
def cvt_run(tmp_path_factory, dask_cluster):
    run_dir = tmp_path_factory.mktemp("cvt") / "run"
    commands.search(**tiny_flags(dask_cluster, archive="cvt"), outdir=str(run_dir))
    return run_dir


@pytest.mark.parametrize("kind", ["grid", "cvt"])
def test_the_data_file_makes_the_pickled_archive_again(tiny_run, cvt_run, kind):
    """archive.npz, and an old folder's archive.csv, give the archive bit for bit, in its order."""
    run_dir = tiny_run if kind == "grid" else cvt_run
    pickled = saved_archive(run_dir)
    archive, config = run_folder.load_run(run_dir)
    from_csv = archive_data.archive_from_csv(run_dir / "archive.csv",
                                             archive_data.empty_archive(config, run_dir / "centroids.npy"))
    for made in (archive, from_csv):
        assert type(made) is type(pickled) and archive_table(made).equals(archive_table(pickled))
        assert made.data(return_type="pandas").equals(pickled.data(return_type="pandas"))
        assert np.array_equal(made.lower_bounds, pickled.lower_bounds)
        assert made.stats.num_elites == pickled.stats.num_elites
        assert made.stats.qd_score == pytest.approx(pickled.stats.qd_score, rel=1e-12)
        if kind == "cvt":
            assert np.array_equal(made.centroids, pickled.centroids)
    with np.load(run_dir / "archive.npz", allow_pickle=False) as data:
        assert int(data["format"]) == archive_data.ARCHIVE_FORMAT and str(data["kind"]) == kind
        recorded = json.loads(str(data["config"]))
    assert recorded == read_checkpoint(run_dir / "checkpoint.pkl")["config"]


def test_a_config_json_edited_against_its_archive_data_is_refused(tmp_path, tiny_run, run_cli):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps({**config, "env_seed": [53]}))
    assert_one_line_error(run_cli("elites", run_dir), "--env_seed", "archive.npz ran with")


def run_flags(cluster, **overrides):
    """The reference run's flags (tests/test_resume.py's), saved every 3 iterations."""
    return tiny_flags(cluster, **{"iterations": REFERENCE_ITERATIONS, "log_every": 3, **overrides})


def resume_twice(run_cli, run_dir, cluster, *fragments):
    """resume refuses the checkpoint in one line (exit 2), touching nothing; with --trust it signs
    it with the user's key and finishes the run."""
    before = folder_state(run_dir)
    address = ("--scheduler_address", cluster.scheduler_address)
    assert_one_line_error(run_cli("resume", run_dir, *address), "--trust", *fragments)
    assert folder_state(run_dir) == before
    result = run_cli("resume", run_dir, "--iterations", REFERENCE_ITERATIONS, "--trust", *address)
    assert result.returncode == 0, result.stderr
    assert "trusted (--trust), and signed with your key" in result.stdout
    assert signing.check_signature((run_dir / "checkpoint.pkl").read_bytes())[1] is None


def test_another_keys_checkpoint_needs_trust(tmp_path, dask_cluster, reference, run_cli, monkeypatch):
    run_dir, own = tmp_path / "run", os.environ["QDSEARCH_KEY"]
    monkeypatch.setenv("QDSEARCH_KEY", str(tmp_path / "theirs" / "key"))
    commands.search(**run_flags(dask_cluster, iterations=4), outdir=str(run_dir))
    monkeypatch.setenv("QDSEARCH_KEY", own)

    resume_twice(run_cli, run_dir, dask_cluster, "signed with another key")
    assert_same_run(run_dir, reference)


def test_a_checkpoint_changed_by_a_byte_is_refused(tmp_path, tiny_run, run_cli):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    data = bytearray((run_dir / "checkpoint.pkl").read_bytes())
    data[-100] ^= 1
    (run_dir / "checkpoint.pkl").write_bytes(bytes(data))
    before = folder_state(run_dir)
    assert_one_line_error(run_cli("resume", run_dir), "changed since", "--trust")
    assert folder_state(run_dir) == before


def test_an_old_folder_opens_everywhere_and_resumes_with_trust(tmp_path, dask_cluster, reference, run_cli):
    """A folder from before archive.npz and signing: archive.pkl, archive.csv, a plain pickle."""
    run_dir = tmp_path / "run"
    commands.search(**run_flags(dask_cluster, iterations=4, archive_pkl=True), outdir=str(run_dir))
    (run_dir / "archive.npz").unlink()
    (run_dir / "checkpoint.pkl").write_bytes(checkpoint_payload(run_dir / "checkpoint.pkl"))
    shutil.copytree(run_dir, tmp_path / "bare")

    open_with_every_command(run_cli, run_dir, dask_cluster, tmp_path)
    resume_twice(run_cli, run_dir, dask_cluster, "not signed")
    assert_same_run(run_dir, reference)
    assert (run_dir / "archive.npz").is_file()

    (tmp_path / "bare" / "archive.csv").unlink()  # nothing to open but the pickle: it is not opened
    assert_one_line_error(run_cli("elites", tmp_path / "bare"), "archive.npz: no such file",
                          "archive.pkl is not opened", "--trust writes it again")


def test_experiments_resume_with_their_own_key_and_trust_anothers(tmp_path, dask_cluster, run_cli,
                                                                  monkeypatch):
    """An experiment's runs resume as ever; an experiment from another key needs --trust."""
    folder, own = tmp_path / "exp", os.environ["QDSEARCH_KEY"]
    monkeypatch.setenv("QDSEARCH_KEY", str(tmp_path / "theirs" / "key"))
    commands.experiment(algorithms="cma_me", seeds="1-2", outdir=str(folder), iterations=2, n_emitters=2,
                           batch_size=6, log_every=2, pictures=False,
                           scheduler_address=dask_cluster.scheduler_address)
    monkeypatch.setenv("QDSEARCH_KEY", own)
    address = ("--scheduler_address", dask_cluster.scheduler_address)

    failed = run_cli("resume", folder, "--iterations", 3, *address)
    assert failed.returncode == 1 and "--trust" in (folder / "experiment.json").read_text()
    result = run_cli("resume", folder, "--iterations", 4, "--trust", *address)
    assert result.returncode == 0, result.stderr
    for name in [entry["name"] for entry in json.loads((folder / "experiment.json").read_text())["runs"]]:
        assert read_checkpoint(folder / name / "checkpoint.pkl")["iteration"] == 4


KEY_MAKER = ("import sys; from pathlib import Path; from qdsearch.base import signing; "
             "print(signing.user_key().hex())")


def test_the_key_is_made_once_by_processes_racing_for_it(tmp_path):
    from conftest import ROOT

    key = tmp_path / "config" / "qdsearch" / "key"
    environment = {**os.environ, "QDSEARCH_KEY": "", "XDG_CONFIG_HOME": str(tmp_path / "config")}
    makers = [subprocess.Popen([sys.executable, "-c", KEY_MAKER], cwd=ROOT, env=environment,
                               stdout=subprocess.PIPE, text=True) for _ in range(6)]
    keys = {maker.communicate(timeout=120)[0].strip() for maker in makers}
    assert keys == {key.read_text().strip()} and len(keys.pop()) == 64
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and stat.S_IMODE(key.parent.stat().st_mode) == 0o700
    assert [path.name for path in key.parent.iterdir()] == ["key"]  # no temporary file left


def test_a_key_others_may_read_is_refused(tmp_path, monkeypatch):
    key = tmp_path / "key"
    monkeypatch.setenv("QDSEARCH_KEY", str(key))
    signing.user_key()
    key.chmod(0o644)
    with pytest.raises(UsageError, match="chmod 600"):
        signing.user_key()


def object_array_npz(path):
    """An .npz whose `format` is an object array: loading it would unpickle."""
    np.savez(path, format=np.array([Trap(path.parent / "marker")], dtype=object))


@pytest.mark.parametrize("spoil", [
    lambda path: path.write_text("garbage"),
    lambda path: path.write_bytes(path.read_bytes()[:200]),
    object_array_npz,
], ids=["text", "truncated", "object-array"])
def test_a_spoiled_archive_npz_is_one_line_that_never_offers_to_unpickle(tmp_path, tiny_run, run_cli, spoil):
    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    spoil(run_dir / "archive.npz")
    before = folder_state(run_dir)
    result = run_cli("elites", run_dir)
    assert_one_line_error(result, f"{run_dir / 'archive.npz'}: not a readable archive data file")
    assert "allow_pickle" not in result.stderr and "unsafe" not in result.stderr
    assert "incompatible config" not in result.stderr
    assert folder_state(run_dir) == before and not (run_dir / "marker").exists()
