"""`watch`: the live page of a run, served by a real `watch` process, read in headless Chromium
while the run goes on: its data are the run's files, and it follows them as the run is resumed."""

import signal
import socket
import time

import pandas as pd
import pytest

from qdsearch import tasks
from qdsearch.cli import commands
from util import assert_one_line_error, launch, run_metrics, tiny_flags

pytestmark = pytest.mark.slow  # a server process and a browser


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def page_value(page, expression: str):
    return page.evaluate(f"(() => {{ const doc = Bokeh.documents[0]; return {expression}; }})()")


def test_the_live_page_shows_the_runs_files_and_follows_a_resume(tmp_path, dask_cluster, browser):
    """Two pages on one server (two tabs): each follows the resume, whichever refreshes first."""
    run_dir = tmp_path / "<i>run&"  # a hostile name: escaped where the page shows it
    commands.search(**tiny_flags(dask_cluster, iterations=2, log_every=1), outdir=str(run_dir))
    port = free_port()
    server = launch("watch", run_dir, port=port)
    try:
        page = browser.new_page()
        deadline = time.time() + 60
        while True:
            try:
                page.goto(f"http://127.0.0.1:{port}/")
                break
            except Exception:
                assert time.time() < deadline and server.poll() is None, server.communicate()
                time.sleep(0.3)
        page.wait_for_function("window.Bokeh && Bokeh.documents.length > 0", timeout=60000)
        archive = pd.read_csv(run_dir / "archive.csv")
        elites = "doc.get_model_by_name('elites').data"
        assert page_value(page, f"{elites}.objective.length") == len(archive)
        assert sorted(page_value(page, f"Array.from({elites}.objective)")) == sorted(archive["objective"])
        assert page_value(page, "Array.from(doc.get_model_by_name('metrics').data.iteration)") == [1, 2]
        # the y-velocity axis as heatmap.png draws it: the fastest impacts (most negative) on top
        y_range = page_value(page, "[doc.get_model_by_name('archive').y_range.start, "
                                   "doc.get_model_by_name('archive').y_range.end]")
        assert y_range == [0.0, -3.0] and tasks.MEASURES["impact_y_velocity"].descending
        headline = page_value(page, "doc.get_model_by_name('headline').text")
        assert "&lt;i&gt;run&amp;" in headline and "iteration 2 of 2" in headline

        second = browser.new_page()
        second.goto(f"http://127.0.0.1:{port}/")
        second.wait_for_function("window.Bokeh && Bokeh.documents.length > 0", timeout=60000)

        commands.resume(str(run_dir), iterations=5, scheduler_address=dask_cluster.scheduler_address)
        resumed = "Bokeh.documents[0].get_model_by_name('metrics').data.iteration.length === 5"
        for shown in (page, second):
            shown.wait_for_function(resumed, timeout=30000)
            assert page_value(shown, "Array.from(doc.get_model_by_name('metrics').data.qd_score)") == [
                row["qd_score"] for row in run_metrics(run_dir)]
            shown.close()
    finally:
        server.send_signal(signal.SIGTERM)
        out, err = server.communicate(timeout=30)
    assert server.returncode == 130 and "Traceback" not in err


def test_watch_refuses_what_it_cannot_serve(run_cli, tiny_run, tmp_path):
    assert_one_line_error(run_cli("watch", tmp_path / "missing"), "no such run folder")
    assert_one_line_error(run_cli("watch", tiny_run, "--port", "70000"), "--port must be at most 65535")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        assert_one_line_error(run_cli("watch", tiny_run, "--port", taken.getsockname()[1]), "cannot serve on")
