#!/usr/bin/env python
"""The README's picture of a tracked search in TensorBoard: `tensorboard --logdir RUN/tensorboard`
served on loopback, its Time Series page opened in headless Chromium (Debian's chromium, driven by
Playwright) with the heatmap's card shown at the last save, beside the QD-score curve.

    python lunar_lander.py --iterations 60 --log_every 10 --seed 42 --track tensorboard \
        --outdir outputs/tb_demo
    python docs/scripts/tensorboard_screenshot.py outputs/tb_demo --out docs/pictures/tensorboard.png
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import fire
from playwright.sync_api import sync_playwright

CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-quic",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def screenshot(run_dir: str, out: str = "docs/pictures/tensorboard.png") -> None:
    """Serve the run's event files, show the heatmap and QD score cards, and save the view."""
    port = free_port()
    logdir = str(Path(run_dir))  # its run: the run folder's tensorboard/
    server = subprocess.Popen([sys.executable, "-m", "tensorboard.main", "--logdir", logdir,
                               "--host", "127.0.0.1", "--port", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": 1200, "height": 620})
            deadline = time.time() + 60
            while True:
                try:
                    page.goto(f"http://127.0.0.1:{port}/?pinnedCards=&tagFilter=heatmap%7Cqd_score#timeseries")
                    break
                except Exception:
                    if time.time() > deadline:
                        raise
                    time.sleep(0.5)
            page.wait_for_selector("img", timeout=60000)  # the heatmap's card has loaded
            page.get_by_role("button", name="Settings").click()  # the settings pane closed
            page.wait_for_timeout(3000)
            page.screenshot(path=out)
            browser.close()
    finally:
        server.terminate()
        server.wait(timeout=30)
    print(f"wrote {out}")


if __name__ == "__main__":
    fire.Fire(screenshot)
