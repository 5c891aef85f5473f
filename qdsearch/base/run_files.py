"""The files of run and experiment folders: written whole or not at all, read back with one line
of error, and guarded so that one process at a time writes a folder.

Map:
- `RunError`: a fault of the machine (a full disk), not of the input: exit code 1;
- folders: `folder_lock` (flock: a kill -9 leaves no stale lock), `new_folder` (never writes
  over a folder that holds anything; removed again if the command is refused in it:
  `make_folders`, `remove_unworked`), `check_writable`;
- writing: `atomic_write` (a temporary file, then os.replace), `write_json`, `write_pickle`,
  `write_csv`;
- reading: FILE_BOUNDS, `check_regular`, `check_present`, `open_regular` and `read_regular`
  (only a regular file, within its kind's bound: every reader of a run's files, a plan or a key
  reads through them),
  `read_run_json`, `unpickle` (a UsageError that names the file and the fault; only for a file
  whose signature was checked: signing.py);
- `fault_text`: any fault as one line; logs: `make_logger` (console and run.log), `console_log`;
- `library_versions`: what config.json records of the libraries a run ran with (`cpu_kernels`).
"""

from __future__ import annotations

import contextlib
import datetime
import io
import json
import logging
import os
import pickle
import platform
import stat
import sys
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable, Iterator

from qdsearch.base.flags import UsageError, named


class RunError(Exception):
    """A fault of the machine, not of the input (a full disk, a lost cluster): one line on stderr,
    exit code 1, and nothing already written is lost."""


LOCK_FILE = ".lock"  # in every folder being written; holds the writer's pid


@contextlib.contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Be the only writer of `folder` while the block runs, or refuse with the holder's pid.

    An OS lock (flock) on folder/.lock: the kernel drops it when its process ends, however it ends,
    so a kill -9 never leaves a stale lock. Readers (elites, compare) take no lock.
    """
    import fcntl

    try:
        fd = os.open(folder / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError as error:
        raise UsageError(f"cannot write the folder {folder}: {error.strerror or error}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise UsageError(f"{folder} is being written by another lunar_lander.py process "
                             f"(pid {holder}); wait for it to end, or stop it") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def holds_files(folder: Path) -> bool:
    """Whether `folder` exists with anything in it but a lock file (or is not a folder)."""
    return folder.exists() and (not folder.is_dir() or any(
        path.name != LOCK_FILE for path in folder.iterdir()))


@contextlib.contextmanager
def new_folder(outdir: str | None, name: str) -> Iterator[Path]:
    """A new, empty run (or experiment) folder, locked for this process: an existing one is never
    written over, not even by a second command started into the same --outdir at the same moment.
    By default outputs/<timestamp>_<name>."""
    if outdir is None:
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        run_dir = Path("outputs") / f"{stamp}_{name}"
        run_dir = next(p for p in [run_dir, *(Path(f"{run_dir}_{i}") for i in range(2, 1000))]
                       if not p.exists())
    else:
        run_dir = Path(outdir)
    taken = UsageError(f"{run_dir} already exists and is not empty; choose another {named('outdir')} "
                       f"(to continue a run there: python lunar_lander.py resume {run_dir})")
    if run_dir.is_symlink() and not run_dir.exists():
        raise UsageError(f"{run_dir} is a symbolic link to {os.readlink(run_dir)}, which does not "
                         f"exist; choose another {named('outdir')}")
    if run_dir.exists() and not run_dir.is_dir():
        raise UsageError(f"{run_dir} exists and is not a folder; choose another {named('outdir')}")
    if holds_files(run_dir):
        raise taken
    check_parent_folder(run_dir)
    made = make_folders(run_dir)
    try:
        with folder_lock(run_dir):
            if holds_files(run_dir):  # another process filled it between the check and the lock
                raise taken
            yield run_dir
    except UsageError:  # refused before any work: the folder goes, as if never asked for
        remove_unworked(run_dir, made)
        raise


def make_folders(folder: Path) -> list[Path]:
    """Make `folder` and its missing parents; the folders made, outermost first. If one can't be
    made (a name too long, a read-only disk), those made before it are removed again."""
    missing = [path for path in [*reversed(folder.parents), folder] if not path.exists()]
    made: list[Path] = []
    for path in missing:
        try:
            path.mkdir()
        except FileExistsError:  # made meanwhile by another process: not ours to remove
            continue
        except OSError as error:
            remove_unworked(folder, made)
            raise UsageError(f"cannot write the run folder {folder}: {error.strerror or error}") from None
        made.append(path)
    return made


# What a command writes in a new folder before any work; a folder holding nothing else may go.
BEFORE_ANY_WORK = {LOCK_FILE, "config.json", "run.log", "experiment.json", "experiment.log"}


def remove_unworked(folder: Path, made: list[Path]) -> None:
    """Remove what a refused command wrote in `folder`, and the folders of `made` (innermost
    first), if it holds nothing but what a command writes before any work; anything else (a
    checkpoint, another's file) keeps them all."""
    try:
        names = {path.name for path in folder.iterdir()}
    except OSError:  # never made (its name too long, say)
        names = set()
    if not names <= BEFORE_ANY_WORK:
        return
    with contextlib.suppress(OSError):
        for name in names - ({LOCK_FILE} if folder not in made else set()):
            (folder / name).unlink()
        for path in reversed(made):
            path.rmdir()  # only if empty: a file someone else put there keeps it


def check_parent_folder(path: Path) -> None:
    """Refuse a path under something that is not a folder (a file named as a folder on the way)."""
    for parent in Path(path).parents:
        if parent.exists():
            if not parent.is_dir():
                raise UsageError(f"cannot write {path}: {parent} is not a folder")
            return


UMASK = os.umask(0o022)
os.umask(UMASK)


def check_writable(folder: Path) -> None:
    """Refuse, before any work, a folder where nothing can be written (a read-only disk)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".write-test.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as error:
        raise UsageError(f"cannot write in {folder}: {error.strerror or error}") from None


def atomic_write(path: Path, write: Callable[[Any], None], mode: str = "wb") -> None:
    """Write `path` via a temporary file and os.replace, so a crash never leaves half a file.

    A failed write (a full disk, say) leaves the previous file whole and raises a RunError that
    names `path`, not the temporary file the error happened in.
    """
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.chmod(tmp, 0o666 & ~UMASK)  # mkstemp makes files private; outputs are ordinary files
        with os.fdopen(fd, mode) as file:
            write(file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException as error:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(error, OSError):
            raise RunError(f"cannot write {path}: {error.strerror or error}") from None
        raise


def write_json(path: Path, data: Any) -> None:
    atomic_write(path, lambda f: json.dump(data, f, indent=2), mode="w")


def write_pickle(path: Path, obj: Any) -> None:
    atomic_write(path, lambda f: pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL))


KIB, MIB, GIB = 1 << 10, 1 << 20, 1 << 30
# The most bytes a file of each kind that is read back may hold, and what it is called: far above
# any real run's (options.py's MAX_* bound what a run makes), yet a bound on what is read into
# memory. Readers name the kind; a run folder's files are named after their file.
FILE_BOUNDS: dict[str, tuple[int, str]] = {
    # its scheduler: the archive (below) and each emitter's state (a CMA-ES covariance each)
    "checkpoint.pkl": (32 * GIB, "a checkpoint"),
    # 1,000,000 cells (MAX_CELLS) of 2,000 float64 weights; runs of larger policies have fewer cells
    "archive.npz": (16 * GIB, "an archive data file"),
    "archive.csv": (48 * GIB, "an archive table"),  # the same as text: up to 24 characters a float
    # a row per iteration (~250 bytes of indented JSON) of 1,000,000 iterations (MAX_ITERATIONS)
    "metrics.json": (GIB, "a metrics file"),
    # the flags (10,000 terrains at most: ~70 KB), the command line and a record per resume
    "config.json": (64 * MIB, "a run config"),
    # 1,000,000 cells (MAX_CELLS) in 10 measures (MAX_MEASURES) of float64: 80 MB
    "centroids.npy": (128 * MIB, "a centroids file"),
    # experiment.json (each run's flags and state), a part's state.json, corrected.json
    "JSON": (GIB, "a JSON record"),
    "plan": (64 * MIB, "a plan file"),  # an experiment's flags, lists of values
    "key": (4 * KIB, "a signing key"),  # 64 hex digits and a newline
}
FILE_TYPES = {stat.S_IFDIR: "a folder", stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device",
              stat.S_IFIFO: "a named pipe", stat.S_IFSOCK: "a socket"}
READ_CHUNK = 64 * MIB  # what a read asks for past a file's size (os.read allocates what it asks)


def byte_size(size: int) -> str:
    """A number of bytes as people read it: 512 bytes, 4.0 KiB, 1.5 GiB."""
    for unit, name in ((GIB, "GiB"), (MIB, "MiB"), (KIB, "KiB")):
        if size >= unit:
            return f"{size / unit:.1f} {name}"
    return f"{size} bytes"


def check_regular(path: Path, kind: str, found: os.stat_result | None = None) -> os.stat_result:
    """The stat of `path` (`found`: of the file opened there), through links, if it is a regular
    file within its kind's bound (FILE_BOUNDS); else a one-line UsageError that says what it is.
    A link to a regular file is followed: run folders and their files may be links (to another
    disk, to a data store's cache); what is refused is what a link may lead to (a device that
    never ends, a pipe that blocks, a folder)."""
    label = FILE_BOUNDS[kind][1]
    via = f" (a link to {os.readlink(path)})" if os.path.islink(path) else ""
    try:
        found = os.stat(path) if found is None else found
    except FileNotFoundError:
        if via:
            raise UsageError(f"{path} is a link to {os.readlink(path)}, which does not exist; "
                             f"{label} must be a regular file") from None
        raise UsageError(f"{path}: no such file") from None
    except OSError as error:
        raise UsageError(f"{path}: not readable ({error.strerror or error})") from None
    if not stat.S_ISREG(found.st_mode):
        what = FILE_TYPES.get(stat.S_IFMT(found.st_mode), "not a file")
        raise UsageError(f"{path} is {what}{via}; {label} must be a regular file")
    if found.st_size > FILE_BOUNDS[kind][0]:
        raise UsageError(f"{path} is {byte_size(found.st_size)}, more than the "
                         f"{byte_size(FILE_BOUNDS[kind][0])} {label} may hold")
    return found


def check_present(folder: Path, files: dict[str, str]) -> None:
    """Each of `files` (name: kind) in `folder`, where there is one (a link to nowhere included),
    is a regular file within its bound (check_regular): for readers that pass over a missing file."""
    for name, kind in files.items():
        if os.path.lexists(folder / name):
            check_regular(folder / name, kind)


@contextlib.contextmanager
def open_regular(path: Path, kind: str) -> Iterator[BinaryIO]:
    """`path` open for reading, a regular file within its kind's bound (check_regular, before it
    is opened and again of the file opened: replaced since?), for a reader that takes only the
    parts it needs (an .npz's arrays); `read_regular` reads one whole. Faults are one line."""
    check_regular(path, kind)  # before it is opened: opening a device or a pipe may block or act
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as error:
        raise UsageError(f"{path}: not readable ({error.strerror or error})") from None
    with os.fdopen(fd, "rb") as file:
        check_regular(path, kind, os.fstat(fd))
        yield file


def read_regular(path: Path, kind: str) -> bytes:
    """The bytes of `path`, a regular file (open_regular) of at most its kind's bound: no more
    than the bound and a byte are ever read, so a file that grows while it is read is refused
    too. A one-line UsageError names the file and the fault."""
    with open_regular(path, kind) as file:
        try:
            return read_bounded(file.fileno(), path, kind, os.fstat(file.fileno()).st_size)
        except OSError as error:
            raise UsageError(f"{path}: not readable ({error.strerror or error})") from None


def read_bounded(fd: int, path: Path, kind: str, size: int) -> bytes:
    """What the open file `fd` holds, of `size` bytes when it was opened: read until its end, or
    refused once it has given more than its kind's bound."""
    (limit, label), chunks, total = FILE_BOUNDS[kind], [], 0
    while total <= limit:
        # the rest of its size and a byte, to see its end; past its size, a chunk at a time (one
        # read gives less than 2 GiB)
        want = min(limit + 1 - total, size - total + 1 if total <= size else READ_CHUNK, GIB)
        if not (chunk := os.read(fd, want)):
            return b"".join(chunks)  # (one chunk, as a file mostly is, is not copied)
        chunks.append(chunk)
        total += len(chunk)
    raise UsageError(f"{path} grew past the {byte_size(limit)} {label} may hold while it was read")


def read_run_json(run_dir: Path, name: str) -> Any:
    """A JSON file of a run folder, or a UsageError naming what is missing or wrong."""
    path = run_dir / name
    if not run_dir.is_dir():
        raise UsageError(f"{run_dir}: no such run folder")
    if not os.path.lexists(path):  # a link to nowhere is there: check_regular says what it is
        raise UsageError(f"{path}: no such file (is {run_dir} a run folder of lunar_lander.py?)")
    try:
        return json.loads(read_regular(path, name if name in FILE_BOUNDS else "JSON"))
    except (UnicodeDecodeError, ValueError) as error:
        raise UsageError(f"{path}: not readable JSON ({error})") from None


# Where the package's modules that a pickle may name lived before the package had layers: a
# checkpoint names the function that rebuilds an archive's rows (compact_pickle.restore_store).
MOVED_MODULES = {"qdsearch.compact_pickle": "qdsearch.base.compact_pickle"}


class MovedModulesUnpickler(pickle.Unpickler):
    """pickle's Unpickler, which finds a class or function of a module that has moved where it is
    now: a checkpoint written before the move resumes."""

    def find_class(self, module: str, name: str) -> Any:
        return super().find_class(MOVED_MODULES.get(module, module), name)


def unpickle(payload: bytes, path: Path, what: str) -> Any:
    """The pickled bytes of the file `path` loaded, or a UsageError that names the file and what
    is wrong. Loading a pickle runs any code it holds: only signing.py's `read_signed_pickle`
    calls this, once the file's signature says it is the user's own (or they trust it)."""
    try:
        return MovedModulesUnpickler(io.BytesIO(payload)).load()
    except Exception as error:  # truncated, corrupt, or not a pickle at all
        raise UsageError(f"{path}: not a readable {what} ({type(error).__name__}: {error})") from None


def write_csv(path: Path, table) -> None:
    """A pandas table as CSV (pandas 3 writes floats that read back bit for bit)."""
    atomic_write(path, lambda f: table.to_csv(f, index=False), mode="w")


def fault_text(error: BaseException) -> str:
    """An OSError (or our RunError) as one line: the file and the cause, without a traceback."""
    if isinstance(error, OSError) and error.filename:
        return f"{error.filename}: {error.strerror or error}"
    return (str(error).strip().splitlines() or [type(error).__name__])[0]


class QuietFileHandler(logging.FileHandler):
    """run.log is a copy of the console: a failed write (a full disk) must not print a traceback;
    the fault is reported once, by the write that matters."""

    def handleError(self, record: logging.LogRecord) -> None:
        pass


def make_logger(path: Path, name: str = "lunar_lander", console: bool = True) -> logging.Logger:
    """Messages go to the console (if asked) and, appended, to the file `path`."""
    log = logging.getLogger(name)
    log.setLevel(logging.INFO)
    log.propagate = False
    close_logger(log)
    logfile = QuietFileHandler(path, encoding="utf-8", delay=True)
    logfile.setFormatter(logging.Formatter("%(asctime)s %(message)s", "%Y-%m-%d %H:%M:%S"))
    log.addHandler(logfile)
    if console:
        log.addHandler(logging.StreamHandler(sys.stdout))
    return log


def close_logger(log: logging.Logger) -> None:
    for handler in list(log.handlers):
        log.removeHandler(handler)
        handler.close()



def console_log() -> logging.Logger:
    """Messages of commands that only read a run: printed, not appended to its run.log."""
    log = logging.getLogger("lunar_lander.results")
    log.setLevel(logging.INFO)
    log.propagate = False
    log.handlers = [logging.StreamHandler(sys.stdout)]  # today's stdout, not the first call's
    return log


def library_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    packages = ["ribs", "gymnasium", "box2d", "dask", "distributed", "numpy"]
    try:  # the learning rows' library, where installed (requirements-learning.txt)
        learning = {"jax": version("jax")}
    except PackageNotFoundError:
        learning = {}
    return {"python": platform.python_version(), **{name: version(name) for name in packages},
            **learning, "kernels": cpu_kernels()}


def cpu_kernels() -> str:
    """numpy's OpenBLAS, the CPU kernels it runs and numpy's own ("0.3.31 Haswell, X86_V3"): runs
    agree bit for bit only on the same kernels (qdsearch/__init__.py holds x86-64 CPUs to AVX2's)."""
    import numpy
    from threadpoolctl import threadpool_info

    found = [f"{lib['version']} {lib.get('architecture')}" for lib in threadpool_info()
             if lib.get("internal_api") == "openblas" and "numpy" in lib.get("filepath", "")]
    try:
        simd = ",".join(numpy.__config__.CONFIG["SIMD Extensions"]["found"]) or "baseline"
    except (AttributeError, KeyError, TypeError):
        simd = "unknown"
    return f"{found[0] if found else 'unknown'}, {simd}"
