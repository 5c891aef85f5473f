"""What a user sees in a terminal: the script run on a real pseudo-terminal (120 columns), its
bytes read as the terminal gets them. One line while the local cluster starts and one when it is
ready, one finished progress bar with nothing drawn after the closing lines, an experiment's bar
with the experiment's own figures, and no stray line after Ctrl-C. And where its output goes to a
pipe (a file, a batch job's log): no bar, a line per saved iteration; a CVT's k-means said first."""

import fcntl
import os
import pty
import re
import struct
import subprocess
import sys
import termios
import time

import pytest

from conftest import SCRIPT

pytestmark = pytest.mark.slow  # real processes on a pseudo-terminal (a search with a cluster of its own)

TINY = ["--n_emitters", "2", "--batch_size", "6", "--workers", "2", "--seed", "7"]


def on_a_terminal(*args, cwd, interrupt_when=None, timeout=240) -> tuple[str, int]:
    """Run the script on a pseudo-terminal; what it wrote there and its exit code. With
    `interrupt_when` (a test of the output so far), Ctrl-C is typed once it holds."""
    pid, fd = pty.fork()
    if pid == 0:  # the child: the terminal's size, then the script
        fcntl.ioctl(0, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
        os.chdir(cwd)
        os.execv(sys.executable, [sys.executable, str(SCRIPT), *map(str, args)])
    out, deadline, typed = b"", time.time() + timeout, False
    while time.time() < deadline:
        if interrupt_when and not typed and interrupt_when(out.decode(errors="replace")):
            os.write(fd, b"\x03")  # Ctrl-C, as the terminal sends it to the process group
            typed = True
        try:
            chunk = os.read(fd, 4096)
        except OSError:  # the child has closed the terminal
            break
        if not chunk:
            break
        out += chunk
    _, status = os.waitpid(pid, 0)
    return out.decode(errors="replace"), os.waitstatus_to_exitcode(status)


def frames(text: str, label: str) -> list[str]:
    """Every state of the progress bar `label` drawn, in order (each is drawn after a \\r)."""
    return [part for part in re.split(r"[\r\n]", text) if part.startswith(f"{label}:")]


def test_a_search_says_its_cluster_starts_and_draws_its_finished_bar_once(tmp_path):
    text, code = on_a_terminal("--iterations", "3", *TINY, "--outdir", tmp_path / "run", cwd=tmp_path)
    assert code == 0, text
    starting, ready = text.index("Starting a local Dask cluster of 2"), text.index("Dask cluster ready")
    assert starting < ready < text.index("search:")
    done = text.index("Done. iteration 3/3")
    assert frames(text[done:], "search") == []  # nothing redrawn under the closing lines
    finished = [frame for frame in frames(text, "search") if "3/3" in frame]
    assert finished and all(frame == finished[-1] for frame in finished[-1:])
    assert text[:done].rstrip(" \r\n").endswith(finished[-1].rstrip())  # the last frame, then Done


def test_an_experiments_bar_shows_its_runs_done_and_the_best_over_every_run(tmp_path, dask_cluster):
    text, code = on_a_terminal("experiment", "--algorithms", "cma_me", "--seeds", "1-3", "--iterations", "4",
                               *TINY[:4], "--max_in_flight", "3", "--pictures", "false",
                               "--scheduler_address", dask_cluster.scheduler_address,
                               "--outdir", tmp_path / "exp", cwd=tmp_path)
    assert code == 0, text
    shown = [re.search(r"runs_done=(\d+)/3, best=(-?[\d.]+|nan)", frame)
             for frame in frames(text, "experiment")]
    shown = [(int(m[1]), float(m[2])) for m in shown if m]
    assert shown and shown[-1][0] == 3
    assert [done for done, _ in shown] == sorted(done for done, _ in shown)
    bests = [best for _, best in shown if best == best]
    assert bests == sorted(bests)  # the best over every run never falls
    assert "qd=" not in "".join(frames(text, "experiment"))  # no one run's figures


def test_ctrl_c_says_one_stop_line_and_nothing_after_it(tmp_path):
    run_dir = tmp_path / "run"
    def under_way(out: str) -> bool:
        return "search:" in out and (run_dir / "checkpoint.pkl").exists()
    text, code = on_a_terminal("--iterations", "500", *TINY, "--outdir", run_dir, cwd=tmp_path,
                               interrupt_when=under_way)
    assert code == 130, text
    said = text[text.index("Stopped;"):]
    lines = [line for line in re.split(r"[\r\n]+", said) if line.strip()]
    assert len(lines) == 1 and f"resume {run_dir}" in lines[0], lines
    assert (run_dir / "checkpoint.pkl").exists()  # kept for resume


@pytest.fixture(scope="module")
def piped(tmp_path_factory, dask_cluster):
    """A tiny CVT search whose output goes to pipes, as to a file or a batch job's log: its
    stdout and stderr (read as bytes: text mode would turn a \\r into a \\n), and its folder."""
    run_dir = tmp_path_factory.mktemp("piped") / "run"
    result = subprocess.run([sys.executable, str(SCRIPT), "--iterations", "6", "--log_every", "2",
                             "--archive", "cvt", "--cells", "32", *TINY[:4], "--pictures", "false",
                             "--scheduler_address", dask_cluster.scheduler_address, "--outdir", str(run_dir)],
                            capture_output=True, timeout=240, cwd=run_dir.parent)
    assert result.returncode == 0, result.stderr
    return result.stdout.decode(), result.stderr.decode(), run_dir


def test_piped_output_has_no_bar_and_a_line_per_saved_iteration(piped):
    out, err, _ = piped
    assert "\r" not in out + err and "search:" not in out + err  # no bar's frames
    progress = [line for line in out.splitlines() if re.match(r"(Done\. )?iteration \d+/6:", line)]
    assert [line.split(":")[0] for line in progress] == [
        "iteration 2/6", "iteration 4/6", "Done. iteration 6/6"]


def test_a_cvt_run_says_it_makes_its_centroids_before_its_first_iteration(piped):
    out, _, _ = piped
    making = out.index("Making the CVT archive's 32 centroids (k-means over 100,000 points)...")
    assert making < out.index("iteration 2/6:")


def test_a_results_commands_flights_have_no_bar_in_a_pipe(piped, dask_cluster):
    """explore's (and evaluate's) flights: no bar's frames where the output is not a terminal."""
    *_, run_dir = piped
    result = subprocess.run([sys.executable, str(SCRIPT), "explore", str(run_dir), "--scheduler_address",
                             dask_cluster.scheduler_address], capture_output=True, timeout=240)
    assert result.returncode == 0, result.stderr
    assert b"\r" not in result.stdout + result.stderr and b"flights:" not in result.stderr
    assert (run_dir / "explorer.html").is_file()
