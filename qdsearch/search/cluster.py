"""The Dask cluster a command flies its policies on: found and checked before anything is
written, joined with every wait bounded and stoppable, started locally (again, if a worker dies
while it starts), and reported in one line when it is lost.

Map:
- finding a scheduler: `scheduler_of` (--scheduler_address, or --scheduler_file through
  `read_scheduler_file`, which waits for it: `wait_for_file`), `check_scheduler_reachable`,
  `scheduler_identity` (the bounded handshake that tells a Dask scheduler from a web server or a
  silent port) and `wait_for_workers` (the first worker, up to --worker_timeout);
- `dask_client`: a client of that scheduler or of a new local cluster (`start_local_cluster`, in
  the memory there is: `check_local_memory`; a worker per core pinned to it: pinning.py), the
  code shipped to it (`ship_code`); a lost scheduler leaves it as a `SchedulerLost`;
  `shares_this_machine` tells whether its workers run on the driver's machine (`is_loopback`);
- the quiet: `quiet_dask_logs` (with `not_a_future_released_late`), `not_dask_stop`,
  `QUIET_CLUSTER` (`QUIET_ENVIRONMENT` for the processes started by hand); `preloading` imports
  what a run needs while its cluster starts.
Every wait is stoppable: Ctrl-C and SIGTERM (stopping.py's STOP) end it at once.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

from qdsearch.base.flags import UsageError, clipped, named, positive_float, shown
from qdsearch.base.run_files import RunError, fault_text
from qdsearch.base.stopping import STOP
from qdsearch.config.settings import ClusterSettings


class SchedulerLost(RunError):
    """The cluster's scheduler is gone (ended, killed, its job preempted): the command stops, and
    a run keeps its last checkpoint."""


# ------------------------------------------------------------------------------------------------
# Finding the scheduler, before anything is written
# ------------------------------------------------------------------------------------------------

# A Dask scheduler answers the handshake in milliseconds (measured here: ~3 ms, no workers); a web
# server or a port that accepts and stays silent never does. The handshake waits at most this, or
# --scheduler_timeout if shorter (whose default is sized for a batch job's scheduler to start).
HANDSHAKE_TIMEOUT = 20.0
WORKER_POLL = 0.5  # s between asking the scheduler whether a worker has joined


def scheduler_of(cluster: ClusterSettings) -> str | None:
    """The address of the Dask scheduler a command joins (None: it starts a local cluster), found
    and checked before anything is written: --scheduler_address, or the address in
    --scheduler_file once that file appears (a batch job's scheduler writes it when it starts).
    The scheduler must answer as one, and have a worker within --worker_timeout.

    DASK_SCHEDULER_ADDRESS in the environment is not used: a variable left over from another job
    must not send runs to another cluster unasked (dask_client says so when it is set).
    """
    address, path = cluster.scheduler_address, cluster.scheduler_file
    if address is not None and path is not None:
        raise UsageError(f"give {named('scheduler_address')} or {named('scheduler_file')}, not both")
    timeout = positive_float("scheduler_timeout", cluster.scheduler_timeout)
    if path is not None:
        address = read_scheduler_file(path, timeout)
    if address is None:
        if cluster.workers is not None:
            check_local_memory(cluster.workers)
        return None
    if not isinstance(address, str):
        raise UsageError(f"{named('scheduler_address')} must be an address such as tcp://HOST:PORT, got "
                         f"{clipped(address)}")
    handshake = min(timeout, HANDSHAKE_TIMEOUT)
    identity = check_scheduler_reachable(address, path, handshake)
    wait_for_workers(address, identity, positive_float("worker_timeout", cluster.worker_timeout),
                     handshake)
    return address


# A scheduler file found unreadable is read again for this long: the scheduler may be writing it.
UNFINISHED_FILE_WAIT = 2.0
# A wait for a scheduler file longer than this is said in one line, as a wait for workers is (a
# file that is there, or a short --scheduler_timeout, keeps a refusal to its one line).
SAY_FILE_WAIT_AFTER = 1.0


def read_scheduler_file(given: Any, timeout: float) -> str:
    """The scheduler's address in a scheduler file, waiting up to `timeout` seconds for the file
    to appear (`wait_for_file`), and a moment more (UNFINISHED_FILE_WAIT, or `timeout` if
    shorter) for a file still being written."""
    if not str(given).strip():
        raise UsageError(f"{named('scheduler_file')} is empty: name the file the scheduler writes")
    path = Path(str(given))
    wait_for_file(path, timeout)
    give_up = time.monotonic() + min(timeout, UNFINISHED_FILE_WAIT)
    while True:
        try:
            address = json.loads(path.read_text())["address"]
            if isinstance(address, str):
                return address
            why = f"its address is {clipped(address)}"
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as error:
            why = f"{type(error).__name__}: {clipped(fault_text(error))}"
        if time.monotonic() >= give_up:
            raise UsageError(f"{path}: not a Dask scheduler file ({why})")
        time.sleep(0.2)


def wait_for_file(path: Path, timeout: float) -> None:
    """Return once `path` is a file, saying so once if it takes more than SAY_FILE_WAIT_AFTER
    seconds (a job started before its scheduler's); a UsageError after `timeout` seconds, or at
    once for a folder. Ctrl-C stops the wait."""
    start, said = time.monotonic(), False
    while not path.is_file():
        STOP.check()
        if path.is_dir():
            raise UsageError(f"{path} is a folder, not a scheduler file")
        waited = time.monotonic() - start
        if waited > timeout:
            raise UsageError(f"{path}: no scheduler file appeared in {timeout:g} s (is the "
                             f"scheduler running? {named('scheduler_timeout')} waits longer)")
        if not said and waited >= SAY_FILE_WAIT_AFTER:
            print(f"waiting for the scheduler file {path} to appear (up to {timeout:g} s, "
                  f"{named('scheduler_timeout')})", file=sys.stderr, flush=True)
            said = True
        time.sleep(0.2)


def check_scheduler_reachable(address: str, scheduler_file: Any = None,
                              handshake: float = HANDSHAKE_TIMEOUT) -> dict:
    """The scheduler's identity, or a UsageError before anything is written: a malformed address,
    nobody listening (for a scheduler file: a stale file, left by a scheduler that has ended), or
    a peer that is not a Dask scheduler."""
    import socket

    from distributed.comm import get_address_host_port

    source = f" (named by {scheduler_file}: a file left by a scheduler that has ended?)" if (
        scheduler_file is not None) else ""
    try:
        host, port = get_address_host_port(address)
        with STOP.interruptible():
            socket.create_connection((host, port), timeout=handshake).close()
    except (OSError, ValueError) as error:
        raise UsageError(f"cannot reach the Dask scheduler at {clipped(address)}{source}: "
                         f"{clipped(fault_text(error))}") from None
    return scheduler_identity(address, handshake)


def scheduler_identity(address: str, timeout: float = HANDSHAKE_TIMEOUT) -> dict:
    """What the scheduler at `address` says of itself (its worker count among it), asked with
    Dask's own protocol and security settings, within `timeout` seconds; Ctrl-C stops the wait."""
    import asyncio

    from distributed.comm import connect
    from distributed.security import Security

    async def ask() -> Any:
        comm = await connect(address, timeout=timeout, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "n_workers": 0})
            return await comm.read()
        finally:
            comm.abort()

    try:
        with STOP.interruptible():
            reply = in_own_thread(lambda: asyncio.run(asyncio.wait_for(ask(), timeout)))
        why = f"it answered {shown(reply)}"
    except (asyncio.TimeoutError, TimeoutError):
        reply, why = None, f"no answer in {timeout:g} s"
    except Exception as error:  # anything the comm layer raises on a peer speaking another protocol
        reply, why = None, f"{type(error).__name__}: {clipped(fault_text(error))}"
    if not (isinstance(reply, dict) and reply.get("type") == "Scheduler"
            and isinstance(reply.get("n_workers"), int)):
        raise UsageError(f"{clipped(address)} is not a Dask scheduler ({why}); give the address "
                         f"(or scheduler file) of a running `dask scheduler`")
    return reply


def in_own_thread(work: Callable[[], Any]) -> Any:
    """`work()`, run in a thread of its own (an event loop of its own, whatever loop this thread
    runs, such as Playwright's) while this one waits, stoppable by Ctrl-C; its fault is raised."""
    import concurrent.futures
    import threading

    done: concurrent.futures.Future = concurrent.futures.Future()

    def run() -> None:
        try:
            done.set_result(work())
        except BaseException as error:
            done.set_exception(error)

    threading.Thread(target=run, name="handshake", daemon=True).start()
    return done.result()


def wait_for_workers(address: str, identity: dict, timeout: float,
                     handshake: float = HANDSHAKE_TIMEOUT) -> None:
    """Return once the scheduler has a worker, saying what it waits for meanwhile; a UsageError
    after `timeout` seconds without one (Ctrl-C stops the wait)."""
    if identity["n_workers"]:
        return
    print(f"waiting for workers at {clipped(address)}: none has joined yet (up to {timeout:g} s, "
          f"{named('worker_timeout')})", file=sys.stderr, flush=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        STOP.check()
        time.sleep(min(WORKER_POLL, max(0.0, deadline - time.monotonic())))
        STOP.check()
        if scheduler_identity(address, handshake)["n_workers"]:
            return
    raise UsageError(f"no worker joined the Dask scheduler at {clipped(address)} in {timeout:g} s; "
                     f"start some (dask worker --scheduler-file FILE), or {named('worker_timeout')} waits "
                     f"longer")


# ------------------------------------------------------------------------------------------------
# Joining it, or starting a local cluster
# ------------------------------------------------------------------------------------------------

@contextlib.contextmanager
def dask_client(workers: int, scheduler_address: str | None, log: logging.Logger,
                drawing: bool = True) -> Iterator[Any]:
    """A Dask client: of an existing cluster if `scheduler_address` is given (left running on
    exit), else of a new local cluster of `workers` single-threaded processes (shut down on exit),
    started while this process imports what it will need (`drawing`: matplotlib too).
    A scheduler lost while the block runs ends it with a SchedulerLost.

    A local cluster listens on localhost only: it runs whatever code it is sent.
    """
    import dask
    from dask.distributed import Client

    from qdsearch.search.pinning import pin_workers

    for name in ("asyncio", "tornado.application"):  # once: the same filter is kept once
        logging.getLogger(name).addFilter(not_dask_stop)
    # A client that loses its scheduler logs each failed reconnection and closed comm with a
    # traceback; the loss is reported once, in one line (SchedulerLost).
    quiet_dask_logs()
    if scheduler_address:
        try:
            with STOP.interruptible():
                client = Client(scheduler_address, timeout=f"{HANDSHAKE_TIMEOUT}s")
        except (OSError, ValueError) as error:
            raise UsageError(f"cannot connect to the Dask scheduler at {clipped(scheduler_address)}: "
                             f"{clipped(fault_text(error))}") from None
        with client, losing_the_scheduler(client, scheduler_address):
            ship_code(client)
            log.info(f"Dask cluster at {scheduler_address}: {len(client.nthreads())} worker(s); "
                     f"{dashboard_of(client)}")
            yield client
        return
    if os.environ.get("DASK_SCHEDULER_ADDRESS"):
        log.info("note: DASK_SCHEDULER_ADDRESS is set, but this command starts a cluster of its own; "
                 f"to join that scheduler, pass {named('scheduler_address')} (or {named('scheduler_file')})")
    # A busy port 8787 (another run's dashboard) is fine: Dask picks another and we print it.
    warnings.filterwarnings("ignore", message="Port 8787 is already in use")
    # The imports are over before the search starts: ribs' CMA-ES rebuilds its thread-pool
    # controller whenever the number of imported modules has changed.
    # Its start takes seconds (~10 s on a loaded machine): said before, and when it is ready.
    log.info(f"Starting a local Dask cluster of {workers} worker process(es)...")
    with preloading(RUN_IMPORTS + (DRAWING_IMPORTS if drawing else ())), dask.config.set(QUIET_CLUSTER):
        cluster = start_local_cluster(workers, log)
    quiet_dask_logs()  # LocalCluster's silence_logs set its own level
    with cluster, Client(cluster) as client, losing_the_scheduler(client, cluster.scheduler_address):
        pin_workers(client, workers)
        log.info(f"Dask cluster ready: {workers} worker process(es); dashboard {client.dashboard_link}")
        yield client


LOCAL_START_TRIES = 3  # a worker process killed while the cluster starts fails the whole start
# What a local worker process holds: 81 MB measured here once it has flown the lander (the
# libraries, the env, Dask's own); the rest is headroom for the walker's and larger tasks.
WORKER_MEMORY = 120e6


def check_local_memory(workers: int) -> None:
    """Refuse a local cluster whose worker processes would not fit in the memory free now."""
    import psutil

    need, free = workers * WORKER_MEMORY, psutil.virtual_memory().available
    if need > free:
        raise UsageError(f"{named('workers')} {workers} would need about {need / 1e9:.1f} GB "
                         f"({WORKER_MEMORY / 1e6:.0f} MB per worker process), but {free / 1e9:.1f} GB "
                         f"is free; give fewer")


def start_local_cluster(workers: int, log: logging.Logger):
    """A local cluster of `workers` single-threaded worker processes on localhost. A worker killed
    while it starts ("Nanny failed to start") fails LocalCluster as a whole, which then closes
    what it started: it is started again, as a worker lost later would be replaced."""
    from dask.distributed import LocalCluster

    check_local_memory(workers)
    for attempt in range(1, LOCAL_START_TRIES + 1):
        STOP.check()
        try:
            # The worker processes write to this terminal: a worker outliving its scheduler by a
            # heartbeat (seen after a start was tried again) logs an ERROR with a traceback.
            # Every fault a user must know of reaches them through this process, in one line.
            return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                host="127.0.0.1", dashboard_address="127.0.0.1:8787",
                                silence_logs=logging.CRITICAL)
        except Exception as error:
            if attempt == LOCAL_START_TRIES:
                raise RunError(f"could not start a local Dask cluster of {workers} worker "
                               f"process(es) in {LOCAL_START_TRIES} tries: {fault_text(error)}") from None
            log.info(f"a worker process failed while the local cluster started "
                     f"({fault_text(error)}); starting it again")


@contextlib.contextmanager
def losing_the_scheduler(client, address: str) -> Iterator[None]:
    """A fault while the client has lost its scheduler (its tasks cancelled, its comms closed) is
    the scheduler's loss, reported as such in one line, not the fault of whatever was waiting."""
    try:
        yield
    except Exception as error:
        if client.status != "running" and not isinstance(error, SchedulerLost):
            raise SchedulerLost(f"lost the Dask scheduler at {clipped(address)} "
                                f"({clipped(fault_text(error))})") from None
        raise


def shares_this_machine(client) -> bool:
    """Whether the client's workers run on the driver's machine for certain: a local cluster it
    started, or one whose every worker listens on a loopback address (`dask worker`s started here
    on 127.0.0.1). Workers on any other address are taken to have cores of their own."""
    from distributed.comm import get_address_host

    if client.cluster is not None:
        return True
    hosts = [get_address_host(address) for address in client.scheduler_info()["workers"]]
    return bool(hosts) and all(map(is_loopback, hosts))


def is_loopback(host: str) -> bool:
    """Whether `host` (an IP address or a name) is this machine's loopback."""
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # another name
        return False


def dashboard_of(client) -> str:
    """The dashboard's link where one answers; a scheduler started with --no-dashboard still
    names port 8787 (its HTTP server answers there, without the dashboard's pages). A HEAD of the
    page tells them apart (Bokeh's page refuses the method with 405, a missing one is 404) in a
    few ms, where a GET would render the page (~1 s of the scheduler's CPU)."""
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(urllib.request.Request(client.dashboard_link, method="HEAD"), timeout=2):
            return f"dashboard {client.dashboard_link}"
    except urllib.error.HTTPError as error:
        return f"dashboard {client.dashboard_link}" if error.code == 405 else "no dashboard"
    except (OSError, ValueError):
        return "no dashboard"


PACKAGE = Path(__file__).resolve().parents[1]  # the package qdsearch: what a worker needs of our code


def package_files() -> list[Path]:
    """The package's code and pages, in its layers' folders (as digest_of_importable_package reads
    them)."""
    return [path for path in sorted(PACKAGE.rglob("*"))
            if path.suffix in (".py", ".html") and "__pycache__" not in path.parts]


def ship_code(client) -> None:
    """Make this exact package importable by the scheduler and every worker of a cluster.

    Tasks refer to their functions by module and name (`qdsearch.search.engine.fly_chunk`,
    `qdsearch.analysis.explorer.record_poses`), so the scheduler (which unpickles task graphs) and the
    workers must import the package. Machines elsewhere have the libraries but not this code, or
    an older copy: then the package is uploaded as a zip (Dask puts it on their path, for workers
    that join later too). Where all already import these very files (a local cluster), nothing is
    sent.
    """
    def digest_of_importable_package(name: str) -> str | None:  # runs remotely
        import hashlib
        import importlib.util
        from pathlib import Path

        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            return None
        folder = Path(list(spec.submodule_search_locations)[0])
        digest = hashlib.sha256()
        for path in sorted(folder.rglob("*")):
            if path.suffix in (".py", ".html") and "__pycache__" not in path.parts:
                digest.update(path.relative_to(folder).as_posix().encode() + path.read_bytes())
        return digest.hexdigest()

    ours = digest_of_importable_package(PACKAGE.name)
    theirs = [client.run_on_scheduler(digest_of_importable_package, PACKAGE.name),
              *client.run(digest_of_importable_package, PACKAGE.name).values()]
    if any(digest != ours for digest in theirs):
        # Dask reads the file's bytes as it uploads, and keeps them for workers that join later:
        # the zip and its folder go once it is sent (no command leaves one in the temp folder).
        with tempfile.TemporaryDirectory(prefix="qdsearch-") as folder:
            client.upload_file(str(package_zip(Path(folder))))


def package_zip(folder: Path) -> Path:
    """The package's files zipped, in `folder`."""
    import zipfile

    path = folder / f"{PACKAGE.name}.zip"
    with zipfile.ZipFile(path, "w") as archive:
        for file in package_files():
            archive.write(file, f"{PACKAGE.name}/{file.relative_to(PACKAGE).as_posix()}")
    return path


# What a run imports while its cluster starts (ribs alone brings scikit-learn, scipy, numba and
# pandas: ~2 s of the main process), and what a run that draws (--pictures) imports besides: one
# that writes its data alone never imports matplotlib (docs/performance.md#fixed-cost).
RUN_IMPORTS = ("ribs.archives", "ribs.emitters", "ribs.schedulers", "pandas.io.formats.csvs", "tqdm")
DRAWING_IMPORTS = ("ribs.visualize", "matplotlib.pyplot", "matplotlib.backends.backend_agg")


@contextlib.contextmanager
def preloading(modules: tuple[str, ...]) -> Iterator[None]:
    """Import `modules` in a thread while the block runs. A local cluster's start is mostly the
    main process waiting for its worker processes to spawn and import: time to import what comes
    next. An import that fails here (even one of Python's rare cross-thread import deadlocks)
    costs nothing: the module is imported again where it is used."""
    import threading

    def load() -> None:
        for module in modules:
            with contextlib.suppress(Exception):
                importlib.import_module(module)

    thread = threading.Thread(target=load, name="preload", daemon=True)
    thread.start()
    try:
        yield
    finally:
        thread.join()


def quiet_dask_logs() -> None:
    """Dask's own log lines (and their tracebacks) stay out of the console: every fault a user
    must know of is reported by this script, in one line."""
    for name in ("distributed", "distributed.client"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    # A batch of big networks (200 of 19,590 weights: 31 MB) is a large graph to Dask, which says
    # so on every send; the weights must reach the workers whichever way they are sent.
    warnings.filterwarnings("ignore", "Sending large graph", UserWarning)
    if sys.unraisablehook is not not_a_future_released_late:
        sys.unraisablehook = not_a_future_released_late


def not_a_future_released_late(unraisable: Any) -> None:
    """Python's hook for the faults of a `__del__`, less Dask's futures': a future collected after
    its client has closed (the run stopped, its scheduler lost) can fail to release itself, and
    its `__del__` means to be silent then, but knows only the interpreter's end, which exit_now
    skips (dask/distributed#8500). Seen once in the suite, after an experiment's SIGTERM."""
    where = getattr(unraisable.object, "__qualname__", ""), getattr(unraisable.object, "__module__", "")
    if where != ("Future.__del__", "distributed.client"):
        sys.__unraisablehook__(unraisable)


def not_dask_stop(record: logging.LogRecord) -> bool:
    """Ctrl-C during a gather leaves Dask's wait task with its AllExit, which asyncio would print
    with a traceback when it is collected; a scheduler lost while results are being fetched leaves
    as_completed's tasks with a closed comm, which tornado prints so. The stop and the loss are
    ours to report, in one line."""
    return not (record.exc_info and type(record.exc_info[1]).__name__ in ("AllExit", "CommClosedError"))


# Dask's housekeeping (memory checks every 100 ms per worker, system monitor every 500 ms,
# event-loop ticks every 20 ms) and each worker's statistical profiler (the dashboard's Profile
# page, which samples the running task's stack every 10 ms and takes the GIL from its rollouts)
# cost CPU that the rollouts need: at this pace an idle 2-worker cluster takes ~1/5 of what it
# takes at Dask's, and a busy one drives its runs faster (docs/performance.md#dask-housekeeping).
QUIET_CLUSTER = {"distributed.worker.memory.monitor-interval": "1s",
                 "distributed.admin.system-monitor.interval": "2s",
                 "distributed.admin.tick.interval": "200ms",
                 "distributed.worker.profile.enabled": False}
# The same settings for schedulers and workers started by hand (`dask scheduler`, `dask worker`:
# docs/slurm.sbatch), which read them from their environment.
QUIET_ENVIRONMENT = {"DASK_" + key.upper().replace(".", "__").replace("-", "_"): str(value)
                     for key, value in QUIET_CLUSTER.items()}
