"""Run folders survive a full disk, a kill before the first checkpoint and a second writer.

The full-disk tests mount a real tmpfs of a few MB (root only; skipped, saying why, elsewhere).
"""

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys

import pytest

from conftest import ROOT
from qdsearch.cli import app as ll
from qdsearch.cli import commands
from util import (
    REFERENCE_ITERATIONS,
    Result,
    assert_one_line_error,
    assert_same_run,
    checkpoint_iteration,
    folder_state,
    launch,
    read_checkpoint,
    small_disk,
    tiny_flags,
    wait_for,
)

pytestmark = pytest.mark.slow  # real processes, signals, clusters: not in the quick subset

# The reference run's flags, saved after every iteration: a fault finds a write in progress.
FLAGS = tiny_flags(iterations=REFERENCE_ITERATIONS, log_every=1)


def fill(folder):
    """Take every byte left on folder's filesystem."""
    with open(folder / "filler", "wb") as file:
        with contextlib.suppress(OSError):
            while True:
                file.write(b"\0" * 65536)
                file.flush()


def test_full_disk_stops_the_search_with_one_line_and_resume_completes(tmp_path, dask_cluster,
                                                                        reference):
    with small_disk(tmp_path, "400k") as disk:
        run_dir = disk / "run"
        # with its pictures: its heatmaps' snapshots are what fill the disk
        process = launch(**{**FLAGS, "pictures": True}, outdir=run_dir,
                         scheduler_address=dask_cluster.scheduler_address)
        out, err = process.communicate(timeout=300)

        held = checkpoint_iteration(run_dir)
        assert 0 <= held < FLAGS["iterations"]
        assert_one_line_error(Result(process.returncode, out, err), "No space left on device",
                              str(run_dir), f"its checkpoint holds iteration {held}",
                              f"python lunar_lander.py resume {run_dir}", code=1)
        assert not list(run_dir.rglob(".*.tmp"))  # no half-written file left behind
        assert json.loads((run_dir / "config.json").read_text())["seed"] == FLAGS["seed"]

        subprocess.run(["mount", "-o", "remount,size=64m", str(disk)], check=True)  # room again
        commands.resume(str(run_dir), scheduler_address=dask_cluster.scheduler_address)
        assert_same_run(run_dir, reference)


@pytest.mark.parametrize("args", [
    ["video", "{run}", "--best"],
    ["trajectories", "{run}", "--top", "2"],
    ["elites", "{run}"],
    ["evaluate", "{run}", "--env_seeds", "3", "--top", "2", "--scheduler_address", "{address}"],
    ["compare", "{run}", "--out", "{run}/comparison"],
])
def test_every_writing_command_reports_a_full_disk_in_one_line(tmp_path, reference, dask_cluster,
                                                                capsys, args):
    with small_disk(tmp_path, "4m") as disk:
        run_dir = disk / "run"
        shutil.copytree(reference, run_dir)
        fill(disk)
        before = folder_state(run_dir)

        code = ll.main([arg.format(run=run_dir, address=dask_cluster.scheduler_address) for arg in args])

        assert_one_line_error(Result(code, "", capsys.readouterr().err), "No space left on device",
                              str(run_dir), code=1)
        assert folder_state(run_dir) == before


def test_killed_before_its_first_checkpoint_resume_starts_from_the_config(tmp_path, dask_cluster,
                                                                          reference):
    run_dir = tmp_path / "run"
    process = launch(**{**FLAGS, "workers": 1, "log_every": FLAGS["iterations"]},  # saved at its end
                     outdir=run_dir)  # starts a cluster of its own: slow
    wait_for(lambda: (run_dir / "config.json").exists(), process, "config.json")
    os.killpg(process.pid, signal.SIGKILL)
    process.communicate(timeout=60)
    assert not (run_dir / "checkpoint.pkl").exists()  # killed while its cluster was starting

    commands.resume(str(run_dir), scheduler_address=dask_cluster.scheduler_address)

    assert_same_run(run_dir, reference)
    config = json.loads((run_dir / "config.json").read_text())
    assert config["resumed"][0]["from_iteration"] == 0


def test_resume_refuses_a_folder_whose_config_is_unusable(tmp_path, capsys):
    (tmp_path / "config.json").write_text(json.dumps({"seed": "seven"}))
    before = folder_state(tmp_path)
    assert ll.main(["resume", str(tmp_path)]) == 2
    assert "config.json: not a usable run config" in capsys.readouterr().err
    assert folder_state(tmp_path) == before


def test_a_second_writer_is_refused_and_readers_go_on(tmp_path, dask_cluster, capsys):
    run_dir = tmp_path / "run"
    flags = {**FLAGS, "iterations": 40, "log_every": 2}
    process = launch(**flags, outdir=run_dir, scheduler_address=dask_cluster.scheduler_address)
    try:
        # archive.csv is a save's last archive file: the readers' archive.npz is there before it
        wait_for(lambda: checkpoint_iteration(run_dir) >= 2 and (run_dir / "archive.csv").exists(),
                 process, "a first saved iteration")

        assert ll.main(["resume", str(run_dir)]) == 2
        err = capsys.readouterr().err
        assert f"is being written by another lunar_lander.py process (pid {process.pid})" in err
        assert err.count("\n") == 1
        assert ll.main(["--iterations", "1", "--outdir", str(run_dir)]) == 2
        assert "already exists and is not empty" in capsys.readouterr().err
        assert ll.main(["elites", str(run_dir), "--top", "3"]) == 0  # readers take no lock
        assert ll.main(["compare", str(run_dir), "--out", str(tmp_path / "cmp")]) == 0
    finally:
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert json.loads((run_dir / "config.json").read_text())["resumed"] == []  # no resumption recorded
    held = read_checkpoint(run_dir / "checkpoint.pkl")["iteration"]
    # The writer has ended: its lock went with it.
    assert ll.main(["resume", str(run_dir), "--iterations", str(held + 1),
                    "--scheduler_address", dask_cluster.scheduler_address]) == 0
    assert read_checkpoint(run_dir / "checkpoint.pkl")["iteration"] == held + 1


def test_a_save_whose_saver_process_died_is_written_by_its_thread(tmp_path, tiny_run):
    """A saver process killed (out of memory, say) between two saves: the saver thread writes
    the folder itself, whole."""
    import logging

    from qdsearch.config import run_config
    from qdsearch.search.run import Run
    from qdsearch.store import saving

    run_dir = tmp_path / "run"
    shutil.copytree(tiny_run, run_dir)
    checkpoint = read_checkpoint(run_dir / "checkpoint.pkl")
    run = Run.from_checkpoint(run_dir, {**checkpoint, "config": run_config.check_run_config(
        checkpoint["config"])}, logging.getLogger("test"))
    savers = saving.Savers(processes=1)
    try:
        run.save(savers)  # in the saver process it starts
        run.settle()
        for pid in savers.processes._processes:
            os.kill(pid, signal.SIGKILL)
        for name in ("archive.csv", "heatmap.png", "progress.png"):
            (run_dir / name).unlink()
        run.save(savers)
        run.settle()
    finally:
        savers.close()
    assert all((run_dir / name).stat().st_size > 0 for name in ("archive.csv", "heatmap.png", "progress.png"))


# A fork server held at its start until the driver that starts it has gone on: Python runs
# sitecustomize at every interpreter's start; only the fork server has QD_TEST_HOLD set.
HOLD = """
import os, pathlib, time
if os.environ.get("QD_TEST_HOLD"):
    while not pathlib.Path(os.environ["QD_TEST_HOLD"]).exists():
        time.sleep(0.01)
"""
DRIVER = """
import os, pathlib, sys
from qdsearch.store import saving
os.environ["QD_TEST_HOLD"] = sys.argv[1]  # for the fork server it starts
processes = saving.saver_processes(2)  # as the driver's first save starts them
pathlib.Path(sys.argv[1]).write_text("the driver went on")
print(processes.submit(os.getppid).result() != os.getpid())  # forked by the fork server
processes.shutdown()
"""


def test_a_drivers_first_save_does_not_wait_for_its_fork_servers_start(tmp_path):
    """The fork server imports what a save needs (seconds): the saver thread waits for it, the
    driver's loop does not (it held every run of a driver, and its workers, at its first save)."""
    (tmp_path / "sitecustomize.py").write_text(HOLD)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    try:
        done = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path / "go")], env=env,
                              capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        (tmp_path / "go").write_text("")  # the held fork server goes on, and ends without its driver
        pytest.fail("the driver waited for its fork server, which waited for the driver")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True"]


def test_a_driver_killed_with_sigkill_leaves_no_saver_process_behind(tmp_path, off_loopback_cluster):
    import psutil  # distributed's own dependency

    run_dir = tmp_path / "run"
    process = launch(**{**FLAGS, "iterations": 10_000, "log_every": 1}, outdir=run_dir,
                     scheduler_address=off_loopback_cluster.scheduler_address)
    try:
        wait_for(lambda: checkpoint_iteration(run_dir) >= 3, process, "saves in its saver process")
        savers = psutil.Process(process.pid).children(recursive=True)
        assert savers  # the saver process, multiprocessing's fork server and resource tracker
    finally:
        os.kill(process.pid, signal.SIGKILL)  # the driver alone, not its group
        process.wait(timeout=60)
        process.stdout.close()  # a saver left behind would hold these open
        process.stderr.close()
    gone, alive = psutil.wait_procs(savers, timeout=10)
    assert not alive, [saver.cmdline() for saver in alive]
