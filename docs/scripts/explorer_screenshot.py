#!/usr/bin/env python
"""The README's picture of the explorer: a page written by `explore`, opened in headless Chromium
(Debian's chromium, driven by Playwright), one cell's landing played to a given step and paused,
with the cell's numbers shown as on hover.

    python docs/scripts/explorer_screenshot.py outputs/seed42/explorer.html --cell 798 --step 191 \
        --out docs/pictures/explorer.png
"""

from __future__ import annotations

from pathlib import Path

import fire
from playwright.sync_api import sync_playwright

CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-quic",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def screenshot(page_file: str, cell: int = 798, step: int = 191,
               out: str = "docs/pictures/explorer.png") -> None:
    """Open the page, play the elite of `cell` to `step`, hover its cell, and save the view."""
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_FLAGS)
        page = browser.new_page(viewport={"width": 1440, "height": 640})
        page.goto(Path(page_file).resolve().as_uri())
        page.wait_for_function("window.explorerReady > 0", timeout=60000)
        box = page.locator("#heatmap").bounding_box()
        gx, row, size, pad = page.evaluate(f"""(() => {{
            const e = DATA.elites.find(e => e.index === {cell});
            return [e.gx, cellRow(e.gy), CELL, PAD]; }})()""")
        centre = (box["x"] + pad + (gx + 0.5) * size, box["y"] + (row + 0.5) * size)
        page.mouse.click(*centre)
        while page.evaluate("step") < step:  # polled from here: the page's CSP forbids eval
            page.wait_for_timeout(20)
        page.click("#play")  # pause
        page.evaluate(f"show({step}); window.scrollTo(0, 0)")
        page.mouse.move(*centre)
        page.screenshot(path=out)
        browser.close()
    print(f"wrote {out}")


if __name__ == "__main__":
    fire.Fire(screenshot)
