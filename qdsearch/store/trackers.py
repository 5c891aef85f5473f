"""Trackers (--track): a run's metrics and pictures in TensorBoard, Weights & Biases or MLflow,
offline first, each iteration exactly once however often the run stops and resumes.

A run's saver thread (loop.py) hands its trackers their work after each save, and they do it in
a thread of their own: never in the loop that feeds the workers, nor in the saves it waits for.
They are given only what the checkpoint holds: at each save, the metrics rows since the last
tracked one (a scalar per row and metric, at its iteration) and the heatmap and progress
pictures. So a run stopped between two saves has tracked nothing it will fly again, and a resumed
run goes on from its checkpoint's iteration. Where a stop fell between a tracker's write and the
note of it (tracking.json), the tracker's own record is read back on resume (TensorBoard purges
later steps; MLflow's history says its last step; W&B ignores steps it has). A tracker that fails
is reported once, in one line, and switched off for the run; the search goes on.

- TensorBoard: event files in RUN/tensorboard (tensorboardX: no TensorFlow, no torch), and the
  scalars against evaluations in RUN/tensorboard/by_evaluations;
- Weights & Biases: offline unless WANDB_MODE says otherwise, its files in RUN/wandb (`wandb
  sync RUN/wandb/offline-run-*` uploads them); one W&B run per run, resumed by its id;
- MLflow: MLFLOW_TRACKING_URI, or a SQLite store beside the run (the experiment's folder for an
  experiment's runs, else the run folder: mlflow.db, artifacts in mlflow-artifacts/).
An experiment's runs are grouped by the experiment (W&B group, MLflow experiment, TensorBoard's
folders) and named by their folders, which name their setting and seed.

Map:
- `TrackedConfig`: what the trackers read of a run's settings;
- `TRACKERS` (the table --track picks from), `check_tracks` (the flag's check);
- `TensorBoard`, `Wandb`, `Mlflow`: open (resuming), log rows and pictures, close;
  `check_sqlite_store`: an MLflow store that cannot be opened, failed at once;
- `TrackerThread` (the one thread every tracker works in), `Tracking` (a run's trackers, their
  notes in tracking.json, faults reported once), `wait_for_trackers` (a drive's end).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import queue
import secrets
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any, Protocol

from qdsearch.base.flags import UsageError, clipped, did_you_mean, named, shown
from qdsearch.base.run_files import RunError, fault_text, write_json

SCALARS = ("qd_score", "coverage", "num_elites", "best_objective", "mean_objective", "evaluations")
# Each scalar is also logged against the evaluations spent (TensorBoard's by_evaluations folder,
# MLflow's by_evaluations/ metrics, their steps the evaluations; W&B's charts take qd/evaluations
# as their x): rows of different algorithms meet at equal budgets.
BY_EVALUATIONS = "by_evaluations"
PICTURES = ("heatmap.png", "progress.png")
NOTES = "tracking.json"  # per tracker: how far it has tracked, and its run's id


class TrackedConfig(Protocol):
    """What the trackers read of a run's settings (the config layer's RunConfig is one)."""

    algorithm: str
    seed: int
    track: list[str]
    experiment: str | None  # the experiment folder it is a run of

    def to_json(self) -> dict[str, Any]: ...


def group_of(config: TrackedConfig) -> str | None:
    """The experiment a run belongs to (its folder's name), or None for a lone search."""
    return Path(config.experiment).name if config.experiment else None


def seconds_per_iteration(rows: list[dict], before: dict | None) -> list[float]:
    """Each row's seconds since the previous row (elapsed_s counts the run's own time)."""
    previous = before["elapsed_s"] if before else 0.0
    out = []
    for row in rows:
        out.append(row["elapsed_s"] - previous)
        previous = row["elapsed_s"]
    return out


def picture(path: Path):
    """A PNG as an RGB array (what every tracker's image call takes)."""
    import matplotlib.image

    image = matplotlib.image.imread(path)
    return (image[..., :3] * 255).astype("uint8") if image.dtype != "uint8" else image[..., :3]


def event_file_suffix() -> str:
    """The end of a new event file's name, after tensorboardX's `events.out.tfevents.SECONDS.HOST`:
    the time in nanoseconds. A run resumed in the second its stop closed its files (a script's
    resume) would otherwise open the same name and empty the file, and TensorBoard reads a
    folder's files in the order of their names, the order their purges assume."""
    return f".{time.time_ns()}"


class TensorBoard:
    """Event files in RUN/tensorboard, written with tensorboardX."""

    module, package = "tensorboardX", "tensorboardX"

    def __init__(self, run_dir: Path, config: TrackedConfig, note: dict) -> None:
        from tensorboardX import SummaryWriter

        through = note.get("through", 0)
        # purge_step: events of later steps (written before a stop that the note missed) go
        self.writer = SummaryWriter(logdir=str(run_dir / "tensorboard"), filename_suffix=event_file_suffix(),
                                    purge_step=through + 1 if through else None, flush_secs=30)
        if not through:
            self.writer.add_text("config", "\n".join(f"    {k}: {v}" for k, v in config.to_json().items()), 0)
        self.note = {"through": through}
        self.logdir, self.by_evaluations = run_dir / "tensorboard" / BY_EVALUATIONS, None

    def evaluations_writer(self, first: dict):
        """The scalars against evaluations, in a folder of their own (a run of its own in
        TensorBoard): their steps are evaluations, so their purge on resume starts at the first
        row to be written again, not at an iteration."""
        from tensorboardX import SummaryWriter

        if self.by_evaluations is None:
            self.by_evaluations = SummaryWriter(
                logdir=str(self.logdir), flush_secs=30, filename_suffix=event_file_suffix(),
                purge_step=first["evaluations"] if self.note["through"] else None)
        return self.by_evaluations

    def log(self, rows: list[dict], seconds: list[float], pictures: dict[str, Any]) -> None:
        by_evaluations = self.evaluations_writer(rows[0])
        for row, spent in zip(rows, seconds):
            for name in SCALARS:
                if row[name] is not None:
                    self.writer.add_scalar(f"qd/{name}", row[name], row["iteration"])
                    by_evaluations.add_scalar(f"qd/{name}", row[name], row["evaluations"])
            self.writer.add_scalar("time/seconds_per_iteration", spent, row["iteration"])
        for name, image in pictures.items():
            self.writer.add_image(name, image, rows[-1]["iteration"], dataformats="HWC")
        self.writer.flush()
        by_evaluations.flush()

    def close(self) -> None:
        self.writer.close()
        if self.by_evaluations is not None:
            self.by_evaluations.close()


class Wandb:
    """A W&B run per run, offline unless WANDB_MODE says otherwise, its files in RUN/wandb."""

    module, package = "wandb", "wandb"

    def __init__(self, run_dir: Path, config: TrackedConfig, note: dict) -> None:
        import wandb

        run_id = note.get("id") or secrets.token_hex(4)  # W&B's own ids are 8 characters too
        self.run = wandb.init(project=os.environ.get("WANDB_PROJECT", "lunar_lander"), dir=str(run_dir),
                              id=run_id, name=run_dir.name, group=group_of(config),
                              config=config.to_json(), mode=os.environ.get("WANDB_MODE", "offline"),
                              resume="allow", reinit="create_new",
                              settings=wandb.Settings(silent=True, console="off"))
        self.run.define_metric("qd/*", step_metric="qd/evaluations")  # its charts' x: evaluations
        self.note = {"through": note.get("through", 0), "id": run_id}

    def log(self, rows: list[dict], seconds: list[float], pictures: dict[str, Any]) -> None:
        import wandb

        for i, (row, spent) in enumerate(zip(rows, seconds)):
            data = {f"qd/{name}": row[name] for name in SCALARS if row[name] is not None}
            data["time/seconds_per_iteration"] = spent
            if i == len(rows) - 1:
                data.update({name: wandb.Image(image) for name, image in pictures.items()})
            self.run.log(data, step=row["iteration"])

    def close(self) -> None:
        self.run.finish()


# How long MLflow tries a server before it fails (the user's own settings win): about 3 s.
MLFLOW_PATIENCE = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "2", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
                   "MLFLOW_HTTP_REQUEST_TIMEOUT": "5"}


class Mlflow:
    """An MLflow run per run, in MLFLOW_TRACKING_URI or a SQLite store beside the run."""

    module, package = "mlflow", "mlflow"

    def __init__(self, run_dir: Path, config: TrackedConfig, note: dict) -> None:
        # A tracking server that does not answer: MLflow's own retries (7, backing off from 2 s)
        # held a 2-iteration run 64 s; a few quick tries, then the one line of a failed tracker.
        for name, value in MLFLOW_PATIENCE.items():
            os.environ.setdefault(name, value)
        from mlflow import MlflowClient
        from mlflow.entities import Param

        # Its store's set-up notes are not ours, and its errors (a read-only store: a traceback of
        # 89 lines on the console) are the tracker's fault, said in Tracking's one line.
        logging.getLogger("mlflow").setLevel(logging.CRITICAL)

        home = Path(config.experiment) if group_of(config) else run_dir
        uri = os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{home.resolve() / 'mlflow.db'}"
        check_sqlite_store(uri)
        self.client = MlflowClient(tracking_uri=uri)
        name = group_of(config) or "lunar_lander"
        found = self.client.get_experiment_by_name(name)
        experiment = found.experiment_id if found else self.client.create_experiment(
            name, artifact_location=(home.resolve() / "mlflow-artifacts").as_uri())
        run_id = note.get("id")
        through = note.get("through", 0)
        if run_id is None:
            run_id = self.client.create_run(experiment, run_name=run_dir.name, tags={
                "seed": str(config.seed), "algorithm": config.algorithm}).info.run_id
            params = [Param(k, json.dumps(v)[:6000]) for k, v in config.to_json().items()]
            for start in range(0, len(params), 100):
                self.client.log_batch(run_id, params=params[start:start + 100])
        else:  # its history says how far it got, if a stop fell before the note
            history = self.client.get_metric_history(run_id, "qd_score")
            through = max([through, *(m.step for m in history)])
        self.run_id, self.note = run_id, {"through": through, "id": run_id}

    def log(self, rows: list[dict], seconds: list[float], pictures: dict[str, Any]) -> None:
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        metrics = [Metric(name, float(row[name]), now, row["iteration"])
                   for row in rows for name in SCALARS if row[name] is not None]
        metrics += [Metric(f"{BY_EVALUATIONS}/{name}", float(row[name]), now, row["evaluations"])
                    for row in rows for name in SCALARS if row[name] is not None]
        metrics += [Metric("seconds_per_iteration", spent, now, row["iteration"])
                    for row, spent in zip(rows, seconds)]
        for start in range(0, len(metrics), 1000):
            self.client.log_batch(self.run_id, metrics=metrics[start:start + 1000])
        for name, image in pictures.items():
            self.client.log_image(self.run_id, image, key=name, step=rows[-1]["iteration"])

    def close(self) -> None:
        self.client.set_terminated(self.run_id)


def check_sqlite_store(uri: str) -> None:
    """A SQLite store (sqlite:///PATH) that cannot be opened (its folder read-only, PATH a folder),
    said at once: MLflow tries one ten times, backing off, for 100 s."""
    if not uri.startswith("sqlite:///"):
        return
    path = Path(uri.removeprefix("sqlite:///").partition("?")[0])
    if str(path) in ("", ":memory:"):
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)  # as MLflow makes it
        with contextlib.closing(sqlite3.connect(path)) as store:
            store.execute("pragma schema_version")  # opens the file (sqlite opens it when first read)
    except (OSError, sqlite3.Error) as error:
        raise RunError(f"cannot open its store {path}: {fault_text(error)}") from None


TRACKERS: dict[str, type] = {"tensorboard": TensorBoard, "wandb": Wandb, "mlflow": Mlflow}


def installed(module: str) -> bool:
    """Whether a module can be imported here (without importing it: wandb and mlflow are slow)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a module set to None in sys.modules: as if missing
        return False


def check_tracks(name: str, value: Any) -> list[str]:
    """--track: trackers of TRACKERS, comma-separated (or a list), each installed."""
    if value in (None, "", (), []):
        return []
    names = [n.strip() for n in value.split(",")] if isinstance(value, str) else value
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise UsageError(f"{named(name)} must name trackers ({', '.join(TRACKERS)}), got {shown(value)}")
    for tracker in names:
        if tracker not in TRACKERS:
            raise UsageError(f"{named(name)} {shown(tracker)} is not a tracker; "
                             f"{did_you_mean(tracker, TRACKERS)}")
        if not installed(TRACKERS[tracker].module):
            raise UsageError(f"{named(name)} {tracker} needs the {TRACKERS[tracker].package} package: "
                             f"pip install -r requirements-trackers.txt")
    return list(dict.fromkeys(names))


class TrackerThread:
    """The one thread of a process in which every tracker works, in order: a tracker that stalls
    (a server that does not answer) holds up tracking, never a search, whose threads only hand
    it work. A daemon thread: a process whose tracker is stuck still ends (`wait` says so)."""

    def __init__(self) -> None:
        self.jobs: queue.Queue = queue.Queue()
        self.thread: threading.Thread | None = None

    def submit(self, job, *args) -> None:
        if self.thread is None or not self.thread.is_alive():
            self.thread = threading.Thread(target=self.work, name="trackers", daemon=True)
            self.thread.start()
        self.jobs.put((job, args))

    def work(self) -> None:
        while True:
            job, args = self.jobs.get()
            try:
                job(*args)
            except Exception:  # every job reports its own faults (Tracking.attempt)
                pass

    def wait(self, timeout: float) -> bool:
        """Whether every job handed over so far is done within `timeout` seconds."""
        if self.thread is None:
            return True
        done = threading.Event()
        self.submit(done.set)
        return done.wait(timeout)


TRACKER_THREAD = TrackerThread()
GRACE_S = 60.0  # how long a drive's end waits for its trackers to catch up


class Tracking:
    """A run's trackers, opened on first use in the tracker thread. Each save hands over the
    rows its trackers lack, and the pictures as they are now; a tracker that fails is reported
    once in the run's log and switched off."""

    def __init__(self, run_dir: Path, config: TrackedConfig, log: logging.Logger) -> None:
        self.dir, self.config, self.log = run_dir, config, log
        self.open: dict[str, Any] | None = None
        self.closed = False  # set in the tracker thread: a save handed over since is tracked, then closed

    def notes(self) -> dict:
        try:
            return json.loads((self.dir / NOTES).read_text())
        except (OSError, ValueError):
            return {}

    def attempt(self, name: str, action, *args) -> tuple[bool, Any]:
        """Do a tracker's action: whether it worked, and what it gave. Its fault switches the
        tracker off, said once in the run's log."""
        try:
            return True, action(*args)
        except Exception as error:  # a server down, a full disk, a library's own fault
            (self.open or {}).pop(name, None)
            root, seen = error, {id(error)}  # a library's own wrapper may say less than what it wraps
            while (inner := root.__cause__ or root.__context__) is not None and id(inner) not in seen:
                root = inner
                seen.add(id(inner))
            because = "" if root is error else f"; cause: {type(root).__name__}: {clipped(fault_text(root))}"
            self.log.warning(f"tracker {name} failed ({type(error).__name__}: {clipped(fault_text(error))}"
                             f"{because}); it is off for this run, which goes on")
            return False, None

    def save(self, metrics: list[dict]) -> None:
        """In the saver thread, after a save: the rows and pictures, handed to the tracker thread."""
        if self.config.track:
            pictures = {Path(name).stem: picture(self.dir / name) for name in PICTURES
                        if (self.dir / name).is_file()}
            TRACKER_THREAD.submit(self.track, list(metrics), pictures)

    def track(self, metrics: list[dict], pictures: dict[str, Any]) -> None:
        """In the tracker thread: each tracker's missing rows, then the note of how far each got."""
        if self.open is None:
            self.open, notes = {}, self.notes()
            for name in self.config.track:
                opened, tracker = self.attempt(name, TRACKERS[name], self.dir, self.config,
                                               notes.get(name, {}))
                if opened:
                    self.open[name] = tracker
        for name, tracker in list(self.open.items()):
            rows = [row for row in metrics if row["iteration"] > tracker.note["through"]]
            if not rows:
                continue
            before = next((row for row in reversed(metrics) if row["iteration"] < rows[0]["iteration"]), None)
            if self.attempt(name, tracker.log, rows, seconds_per_iteration(rows, before), pictures)[0]:
                tracker.note["through"] = rows[-1]["iteration"]
        self.attempt("notes", write_json, self.dir / NOTES,
                     {**self.notes(), **{name: t.note for name, t in self.open.items()}})
        if self.closed:  # a stop closes a run while its last save may still be on its way here
            self.close_all()

    def close(self) -> None:
        if self.config.track:
            TRACKER_THREAD.submit(self.close_all, True)

    def close_all(self, for_good: bool = False) -> None:
        """In the tracker thread: close every open tracker, so that what they were handed is
        written as the notes of how far they got say (TensorBoard's writers flush their files when
        closed, else every 30 s). `for_good`: the run's close, after the saves handed over before
        it (a save handed over later, as a stop's may be, is tracked and closed in its turn)."""
        self.closed = self.closed or for_good
        for name, tracker in list((self.open or {}).items()):
            self.attempt(name, tracker.close)
        self.open = None  # a save handed over later opens them again, from their notes


def wait_for_trackers(log: logging.Logger) -> None:
    """At a drive's end: the trackers' last rows written, or one line saying they were not."""
    if not TRACKER_THREAD.wait(GRACE_S):
        log.warning(f"the trackers had not caught up after {GRACE_S:.0f} s; what they lacked then "
                    f"is not tracked (every run's own files are complete)")
