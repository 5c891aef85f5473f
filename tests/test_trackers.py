"""--track: tiny searches with each tracker offline, read back with each tool's own reader
(TensorBoard's EventAccumulator, W&B's offline run files, MLflow's client on its local store):
every iteration's metrics once, as metrics.json has them, the pictures of every save, the
config, an experiment's runs grouped, a resumed run going on, a failing tracker one line."""

import importlib.util
import json
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

# Every test process collects this file; only the one that runs it imports the trackers' libraries
# and their readers (~2 s of CPU).
if missing := [name for name in ("tensorboardX", "wandb", "mlflow") if not importlib.util.find_spec(name)]:
    pytest.skip(f"no {', '.join(missing)}: pip install -r requirements-trackers.txt", allow_module_level=True)

from conftest import ROOT, SCRIPT  # noqa: E402
from qdsearch.cli import commands
from qdsearch.search import experiments  # noqa: E402
from qdsearch.store import trackers  # noqa: E402
from util import (  # noqa: E402
    assert_one_line_error,
    launch,
    run_archive,
    tiny_flags,
    wait_for,
    wandb_history,
    wandb_records,
)

ALL = "tensorboard,wandb,mlflow"
TRACKED = dict(iterations=6, log_every=3, pictures=True)


@pytest.fixture(autouse=True)
def offline(monkeypatch):
    """The trackers as on a node without network: W&B offline, MLflow's store in the folder."""
    for name in ("WANDB_MODE", "WANDB_API_KEY", "MLFLOW_TRACKING_URI"):
        monkeypatch.delenv(name, raising=False)


@pytest.fixture(scope="module")
def tracked(tmp_path_factory, dask_cluster):
    """A tiny search tracked by all three, and its twin tracked by none."""
    root = tmp_path_factory.mktemp("tracked")
    commands.search(**tiny_flags(dask_cluster, **TRACKED, track=ALL), outdir=str(root / "run"))
    commands.search(**tiny_flags(dask_cluster, **TRACKED), outdir=str(root / "plain"))
    return root / "run", root / "plain"


def metrics_of(run_dir):
    return json.loads((run_dir / "metrics.json").read_text())


def tensorboard_of(run_dir, folder="tensorboard"):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir / folder), size_guidance={"scalars": 0, "images": 0})
    events.Reload()
    return events


def mlflow_client(store):
    """MLflow's own client of the store (a folder's mlflow.db)."""
    from mlflow import MlflowClient

    return MlflowClient(tracking_uri=f"sqlite:///{store.resolve() / 'mlflow.db'}")


def mlflow_of(run_dir, store=None):
    notes = json.loads((run_dir / trackers.NOTES).read_text())
    client = mlflow_client(store or run_dir)
    return client, notes["mlflow"]["id"]


@pytest.mark.slow  # real tracked searches
def test_every_tracker_holds_every_iterations_metrics_once(tracked):
    run_dir, plain = tracked
    rows = metrics_of(run_dir)
    steps = [row["iteration"] for row in rows]
    assert run_archive(run_dir).equals(run_archive(plain))  # tracking changes no result
    events = tensorboard_of(run_dir)
    by_evaluations = tensorboard_of(run_dir / "tensorboard", "by_evaluations")
    history = [h for h in wandb_history(run_dir) if "qd/qd_score" in h]
    client, run_id = mlflow_of(run_dir)
    for name in trackers.SCALARS:
        values = [row[name] for row in rows]
        board = events.Scalars(f"qd/{name}")
        assert [e.step for e in board] == steps
        assert [e.value for e in board] == pytest.approx(values, rel=1e-6)  # TensorBoard's float32
        assert [h["_step"] for h in history] == steps and [h[f"qd/{name}"] for h in history] == values
        logged = client.get_metric_history(run_id, name)
        assert [m.step for m in logged] == steps and [m.value for m in logged] == values
        # and against the evaluations spent: TensorBoard's by_evaluations run, MLflow's metric
        spent = [row["evaluations"] for row in rows]
        board = by_evaluations.Scalars(f"qd/{name}")
        assert [e.step for e in board] == spent
        assert [e.value for e in board] == pytest.approx(values, rel=1e-6)
        logged = client.get_metric_history(run_id, f"{trackers.BY_EVALUATIONS}/{name}")
        assert [m.step for m in logged] == spent and [m.value for m in logged] == values
    assert spent == [12 * step for step in steps]  # 2 emitters x 6 solutions an iteration
    # W&B draws every qd/ metric against qd/evaluations
    [metric] = [m for m in wandb_records(run_dir, "metric") if m.glob_name == "qd/*"]
    assert metric.step_metric == "qd/evaluations"


@pytest.mark.slow  # real tracked searches
def test_the_pictures_of_every_save_and_the_config_are_tracked(tracked):
    run_dir, _ = tracked
    saves = [3, 6]
    events = tensorboard_of(run_dir)
    for name in ("heatmap", "progress"):
        assert [e.step for e in events.Images(name)] == saves
    assert "config/text_summary" in events.Tags()["tensors"]
    pictured = [h["_step"] for h in wandb_history(run_dir) if "heatmap/_type" in h]
    assert pictured == saves
    assert len(list(run_dir.glob("wandb/offline-run-*/files/media/images/heatmap*.png"))) == 2
    [record] = wandb_records(run_dir, "run")
    config = {item.key: json.loads(item.value_json) for item in record.config.update}
    assert config["seed"] == 7 and config["algorithm"] == "cma_me" and config["track"] == ALL.split(",")
    client, run_id = mlflow_of(run_dir)
    logged = client.get_run(run_id)
    assert logged.data.params["seed"] == "7" and logged.data.params["algorithm"] == '"cma_me"'
    assert {a.path for a in client.list_artifacts(run_id)} >= {"images"}


@pytest.mark.slow  # real tracked searches
def test_a_stopped_and_resumed_run_tracks_each_iteration_once(tmp_path, dask_cluster):
    run_dir = tmp_path / "run"
    # The test signals as it sees the first save (iteration 3's): without pictures to draw,
    # the stop held iteration 3 (3 tries here, 2026-11-29); 15 iterations leave it room to land.
    # (The pictures a tracker holds are the `tracked` run's.)
    flags = {**tiny_flags(dask_cluster, iterations=15, log_every=3, track=ALL), "outdir": run_dir}
    process = launch(*[], **flags)
    wait_for((run_dir / "metrics.json").exists, process, "the run's first save")
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    commands.resume(str(run_dir), scheduler_address=dask_cluster.scheduler_address)

    steps = list(range(1, 16))
    assert [e.step for e in tensorboard_of(run_dir).Scalars("qd/qd_score")] == steps
    assert [e.step for e in tensorboard_of(run_dir / "tensorboard", "by_evaluations").Scalars(
        "qd/qd_score")] == [row["evaluations"] for row in metrics_of(run_dir)]
    assert [h["_step"] for h in wandb_history(run_dir) if "qd/qd_score" in h] == steps
    assert len(list(run_dir.glob("wandb/offline-run-*"))) == 2  # one W&B run, resumed by its id
    assert len({record.run_id for record in wandb_records(run_dir, "run")}) == 1
    # the run's own clock goes on across the stop, and so do the trackers' seconds per iteration
    elapsed = [row["elapsed_s"] for row in metrics_of(run_dir)]
    assert all(later > earlier for earlier, later in zip(elapsed, elapsed[1:])), elapsed
    spent = [e.value for e in tensorboard_of(run_dir).Scalars("time/seconds_per_iteration")]
    assert spent == pytest.approx(np.diff([0.0, *elapsed]).tolist(), abs=1e-5)
    client, run_id = mlflow_of(run_dir)
    assert sorted(m.step for m in client.get_metric_history(run_id, "qd_score")) == steps
    assert [m.value for m in client.get_metric_history(run_id, "qd_score")] == [
        row["qd_score"] for row in metrics_of(run_dir)]


@pytest.mark.slow  # real tracked searches
def test_an_experiments_runs_are_grouped_by_it(tmp_path, dask_cluster):
    folder = tmp_path / "exp"
    commands.experiment(algorithms="cma_me", seeds="1-2", iterations=2, n_emitters=2, batch_size=6,
                           log_every=2, track="wandb,mlflow", outdir=str(folder),
                           scheduler_address=dask_cluster.scheduler_address)
    runs = [folder / entry["name"] for entry in experiments.read_experiment(folder)["runs"]]
    client = mlflow_client(folder)
    experiment = client.get_experiment_by_name("exp")
    logged = client.search_runs([experiment.experiment_id])
    assert sorted(r.info.run_name for r in logged) == sorted(r.name for r in runs)
    for run_dir in runs:
        [record] = wandb_records(run_dir, "run")
        assert record.run_group == "exp" and record.display_name == run_dir.name


@pytest.mark.slow  # real tracked searches
def test_a_failing_tracker_is_one_line_and_the_search_goes_on(tmp_path, dask_cluster, tracked, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:9")  # nothing listens there
    for name in trackers.MLFLOW_PATIENCE:  # MLflow's tries as the tracker sets them
        monkeypatch.delenv(name, raising=False)
    run_dir = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, **TRACKED, track="tensorboard,mlflow"), outdir=str(run_dir))
    lines = [line for line in (run_dir / "run.log").read_text().splitlines() if "failed (" in line]
    assert len(lines) == 1 and "tracker mlflow failed" in lines[0] and "goes on" in lines[0]
    assert run_archive(run_dir).equals(run_archive(tracked[1]))
    assert [e.step for e in tensorboard_of(run_dir).Scalars("qd/qd_score")] == list(range(1, 7))


@pytest.mark.slow  # a real tracked search
def test_a_store_that_cannot_be_opened_fails_the_tracker_at_once(tmp_path, dask_cluster, monkeypatch, capsys):
    """MLflow tries a SQLite store it cannot open ten times, backing off, for 100 s (a store in a
    read-only folder, as a user's may be; here its file is a folder, which root cannot open
    either): the run said nothing of it and waited out the trackers' 60 s. Its failure is said
    at once, with its reason, in run.log and on the console, and the run ends complete."""
    store = tmp_path / "store" / "mlflow.db"
    store.mkdir(parents=True)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")
    run_dir = tmp_path / "run"
    commands.search(**tiny_flags(dask_cluster, iterations=2, log_every=1, track="mlflow"),
                    outdir=str(run_dir))
    log = (run_dir / "run.log").read_text()
    failed = [line for line in log.splitlines() if "tracker mlflow failed" in line]
    assert len(failed) == 1 and f"cannot open its store {store}" in failed[0], log
    assert "had not caught up" not in log
    assert capsys.readouterr().out.count("tracker mlflow failed") == 1
    assert [row["iteration"] for row in metrics_of(run_dir)] == [1, 2]
    written = {p.name for p in run_dir.iterdir()}
    assert {"checkpoint.pkl", "archive.npz", "archive.csv", "config.json"} <= written


@pytest.mark.slow  # the tracked run's metrics
def test_a_save_handed_over_after_its_run_is_closed_is_tracked_whole(tracked, tmp_path):
    """A stop closes a run while its last save is still in the saver thread: that save reaches the
    tracker thread after the close. Its rows are tracked and written all the same (TensorBoard's
    writers flush their files when closed, else every 30 s), as far as the notes say."""
    import logging

    from qdsearch.config import run_config

    run_dir, _ = tracked
    config = run_config.load_run_config(run_dir).replace(track=["tensorboard", "mlflow"])
    tracking = trackers.Tracking(tmp_path, config, logging.getLogger("test_trackers"))
    tracking.close()
    tracking.save(metrics_of(run_dir))
    trackers.wait_for_trackers(tracking.log)
    rows = metrics_of(run_dir)
    notes = json.loads((tmp_path / trackers.NOTES).read_text())
    assert notes["tensorboard"]["through"] == rows[-1]["iteration"]
    assert [e.step for e in tensorboard_of(tmp_path).Scalars("qd/qd_score")] == [r["iteration"] for r in rows]
    assert [e.step for e in tensorboard_of(tmp_path / "tensorboard", "by_evaluations").Scalars(
        "qd/qd_score")] == [r["evaluations"] for r in rows]
    client, run_id = mlflow_of(tmp_path)  # closed, as a run is at its end: nothing left unwritten
    assert client.get_run(run_id).info.status == "FINISHED"
    assert [m.step for m in client.get_metric_history(run_id, "qd_score")] == [r["iteration"] for r in rows]


def test_a_run_resumed_in_the_second_it_stopped_keeps_the_events_before(tmp_path):
    """tensorboardX names an event file by the second and the host: the resumed run's files were the
    stopped run's, emptied, when both opened in one second (the first rows lost from by_evaluations
    in a loaded suite). Each writer's file is its own, and read in the order written."""
    import time

    from qdsearch.config import run_config

    config = run_config.check_run_config(tiny_flags(track="tensorboard"))
    rows = [{"iteration": i, "evaluations": 12 * i, **{name: float(i) for name in trackers.SCALARS
                                                       if name != "evaluations"}} for i in range(1, 7)]
    time.sleep(1 - time.time() % 1)  # at the start of a second: both runs open their files in it
    for first, last in ((0, 3), (3, 6)):
        tracker = trackers.TensorBoard(tmp_path, config, {"through": first})
        tracker.log(rows[first:last], [0.1] * 3, {})
        tracker.close()
    assert [e.step for e in tensorboard_of(tmp_path).Scalars("qd/qd_score")] == [1, 2, 3, 4, 5, 6]
    assert [e.step for e in tensorboard_of(tmp_path / "tensorboard", "by_evaluations").Scalars(
        "qd/qd_score")] == [12, 24, 36, 48, 60, 72]
    assert len(list((tmp_path / "tensorboard").glob("events.out.tfevents.*"))) == 2


def test_an_unreachable_tracking_server_fails_the_tracker_within_seconds(tmp_path, monkeypatch):
    """MLflow's own retries (7, backing off from 2 s) held a 2-iteration run 64 s for a server that
    does not answer; the tracker tries a few times, quickly, then fails (one line, in the run)."""
    import time

    from qdsearch.config import run_config

    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:9")
    for name in trackers.MLFLOW_PATIENCE:
        monkeypatch.delenv(name, raising=False)
    config = run_config.check_run_config(tiny_flags(track="mlflow"))
    started = time.monotonic()
    with pytest.raises(Exception, match="127.0.0.1"):
        trackers.Mlflow(tmp_path, config, {})
    assert time.monotonic() - started < 20


@pytest.mark.slow  # real tracked searches
def test_a_missing_tracker_package_is_one_line_and_writes_nothing(tmp_path):
    """A real process in which `import wandb` fails, as on a machine without it."""
    code = ("import sys, runpy; sys.modules['wandb'] = None; sys.argv = sys.argv[1:]; "
            "runpy.run_path(sys.argv[0], run_name='__main__')")
    result = subprocess.run([sys.executable, "-c", code, str(SCRIPT), "--track", "wandb", "--iterations", "1",
                             "--outdir", str(tmp_path / "run")], capture_output=True, text=True, cwd=ROOT,
                            timeout=120, env={**os.environ})
    assert_one_line_error(result, "--track wandb needs the wandb package",
                          "pip install -r requirements-trackers.txt")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("value, fragment", [("tensorbord", "'tensorbord' is not a tracker"),
                                             ("[1, 2]", "--track must name trackers")])
def test_a_bad_track_is_one_line(run_cli, tmp_path, value, fragment):
    assert_one_line_error(run_cli("--track", value, "--outdir", tmp_path / "run"), fragment)
    assert not (tmp_path / "run").exists()
