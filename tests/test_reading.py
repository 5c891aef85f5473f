"""The one reader of a run's files, plans and keys (run_files: check_regular, read_regular,
read_bounded, read_run_json), on real files, links, a folder, a named pipe and a device: what it
refuses and how it words it, what it reads (every byte, nothing past its bound), and how much
memory a read asks for. Quick: no run, no cluster (test_file_bounds has the commands' cases)."""

import contextlib
import os
import resource
import stat

import pytest

from qdsearch.base import run_files
from qdsearch.base.flags import UsageError

MIB = 1 << 20


@pytest.mark.parametrize("size, shown", [(0, "0 bytes"), (1023, "1023 bytes"), (1024, "1.0 KiB"),
                                         (1536, "1.5 KiB"), (3 * MIB, "3.0 MiB"), (MIB - 1, "1024.0 KiB"),
                                         (5 << 30, "5.0 GiB"), ((3 << 30) // 2, "1.5 GiB")])
def test_a_size_is_said_in_its_unit(size, shown):
    assert run_files.byte_size(size) == shown


def refusal(path, kind="plan") -> str:
    with pytest.raises(UsageError) as refused:
        run_files.read_regular(path, kind)
    return str(refused.value)


def test_what_is_no_regular_file_is_named_as_what_it_is(tmp_path):
    os.mkfifo(tmp_path / "pipe")
    (tmp_path / "folder").mkdir()
    (tmp_path / "to_null").symlink_to("/dev/null")
    (tmp_path / "nowhere").symlink_to(tmp_path / "gone")
    label = "a plan file must be a regular file"
    assert refusal(tmp_path / "missing") == f"{tmp_path / 'missing'}: no such file"
    assert refusal(tmp_path / "folder") == f"{tmp_path / 'folder'} is a folder; {label}"
    assert refusal(tmp_path / "pipe") == f"{tmp_path / 'pipe'} is a named pipe; {label}"  # never opened
    assert refusal(tmp_path / "to_null") == (f"{tmp_path / 'to_null'} is a character device (a link to "
                                             f"/dev/null); {label}")
    assert refusal(tmp_path / "nowhere") == (f"{tmp_path / 'nowhere'} is a link to {tmp_path / 'gone'}, "
                                             f"which does not exist; {label}")
    assert refusal(tmp_path / "to_null", "key") == (f"{tmp_path / 'to_null'} is a character device (a link "
                                                    f"to /dev/null); a signing key must be a regular file")


def test_an_unreadable_file_says_why(tmp_path):
    (tmp_path / "folder").mkdir()
    with pytest.raises(UsageError) as refused:
        run_files.check_regular(tmp_path / "folder" / "x" / "y", "plan")  # through a missing folder
    assert str(refused.value) == f"{tmp_path / 'folder' / 'x' / 'y'}: no such file"
    (tmp_path / "file").write_text("")
    with pytest.raises(UsageError) as refused:
        run_files.check_regular(tmp_path / "file" / "inside", "plan")  # a file taken for a folder
    assert str(refused.value) == f"{tmp_path / 'file' / 'inside'}: not readable (Not a directory)"


def test_the_stat_given_is_the_one_judged(tmp_path):
    """read_regular judges the file it opened (its fstat), not what the path names by then."""
    (tmp_path / "plan.toml").write_text("seeds = 1\n")
    (tmp_path / "folder").mkdir()
    with pytest.raises(UsageError, match="is a folder"):
        run_files.check_regular(tmp_path / "plan.toml", "plan", os.stat(tmp_path / "folder"))
    assert stat.S_ISREG(run_files.check_regular(tmp_path / "plan.toml", "plan").st_mode)


def test_a_file_at_its_bound_is_read_whole_and_a_byte_more_is_refused(tmp_path, monkeypatch):
    monkeypatch.setitem(run_files.FILE_BOUNDS, "plan", (10, "a plan file"))
    (tmp_path / "plan.toml").write_bytes(b"0123456789")
    assert run_files.read_regular(tmp_path / "plan.toml", "plan") == b"0123456789"
    (tmp_path / "plan.toml").write_bytes(b"0123456789!")
    assert refusal(tmp_path / "plan.toml") == (f"{tmp_path / 'plan.toml'} is 11 bytes, more than the 10 "
                                               f"bytes a plan file may hold")
    (tmp_path / "empty").write_bytes(b"")
    assert run_files.read_regular(tmp_path / "empty", "plan") == b""


def test_bytes_that_come_in_pieces_are_read_whole(tmp_path):
    """A pipe gives its bytes in as many reads as it takes (a file that grew since it was
    opened): every piece is kept, in order, up to the bound."""
    given, taken = os.pipe()
    os.write(taken, b"seeds = 1\nalgorithms = ['cma_me']\n")
    os.close(taken)
    try:
        assert run_files.read_bounded(given, tmp_path / "plan.toml", "plan", 0) == (
            b"seeds = 1\nalgorithms = ['cma_me']\n")
    finally:
        os.close(given)


@contextlib.contextmanager
def little_memory():
    """This process may take 40 MiB more address space while the test runs: a read that asked for
    its kind's whole bound (a checkpoint's 32 GiB), a gigabyte or a 64 MiB chunk at once fails."""
    with open("/proc/self/status") as status:
        used = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (used + 40 * MIB, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


@pytest.mark.parametrize("size", [1000, 24 * MIB])
def test_a_file_of_a_kind_with_a_large_bound_is_read_in_little_memory(tmp_path, size):
    """A read asks for what the file holds and a byte (then a byte, to see its end), not for its
    kind's bound nor a chunk: a 24 MiB file is read within 40 MiB."""
    (tmp_path / "checkpoint.pkl").write_bytes(b"x" * size)
    with little_memory():
        read = run_files.read_regular(tmp_path / "checkpoint.pkl", "checkpoint.pkl")
    assert len(read) == size and read == b"x" * size


def test_a_run_folders_json_is_read_within_its_own_bound(tmp_path, monkeypatch):
    with pytest.raises(UsageError) as refused:
        run_files.read_run_json(tmp_path / "nowhere", "config.json")
    assert str(refused.value) == f"{tmp_path / 'nowhere'}: no such run folder"
    with pytest.raises(UsageError) as refused:
        run_files.read_run_json(tmp_path, "config.json")
    assert str(refused.value) == (f"{tmp_path / 'config.json'}: no such file (is {tmp_path} a run folder "
                                  f"of lunar_lander.py?)")
    (tmp_path / "config.json").write_text('{"seed": 3}')
    assert run_files.read_run_json(tmp_path, "config.json") == {"seed": 3}
    monkeypatch.setitem(run_files.FILE_BOUNDS, "config.json", (5, "a run config"))
    with pytest.raises(UsageError) as refused:
        run_files.read_run_json(tmp_path, "config.json")
    assert str(refused.value) == (f"{tmp_path / 'config.json'} is 11 bytes, more than the 5 bytes a run "
                                  f"config may hold")
    (tmp_path / "experiment.json").write_text('{"runs": [}')
    with pytest.raises(UsageError) as refused:
        run_files.read_run_json(tmp_path, "experiment.json")  # any other JSON: its own bound
    assert str(refused.value).startswith(f"{tmp_path / 'experiment.json'}: not readable JSON (")


def test_files_there_are_checked_and_files_not_there_passed_over(tmp_path):
    (tmp_path / "metrics.json").write_text("[]")
    run_files.check_present(tmp_path, {"metrics.json": "metrics.json", "archive.csv": "archive.csv"})
    (tmp_path / "archive.csv").symlink_to(tmp_path / "gone")
    with pytest.raises(UsageError) as refused:
        run_files.check_present(tmp_path, {"metrics.json": "metrics.json", "archive.csv": "archive.csv"})
    assert str(refused.value) == (f"{tmp_path / 'archive.csv'} is a link to {tmp_path / 'gone'}, which does "
                                  f"not exist; an archive table must be a regular file")
