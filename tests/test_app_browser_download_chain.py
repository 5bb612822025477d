"""Download follows every render, however fast they come (headless Debian Chromium through
Playwright).

Each full render disables Download and chains an event that writes the render's file and
enables it. Two renders in quick succession run that chained event twice; while the first
run still writes its file (a large PNG), the second trigger must queue one more run, not be
dropped. It was dropped (Gradio's default for chained events), and Download stayed disabled
under the second picture: 3 of 6 runs of this sequence with two busy loops beside the test,
and the first download of `test_app_browser_loupe.py` once in CI.

The photo is large and noisy, so its PNG takes a while to write; the blur switched off is
the photo itself, a render of a few milliseconds, whose chained events end while the PNG of
the blurred render before it is still being written. Two busy loops run beside the app, as on
a busy machine: on a quiet one the first file is mostly written before the second render ends
(the old wiring passed 8 quiet runs of 8, and failed 3 busy runs of 3).
"""

from __future__ import annotations

import contextlib
import subprocess
import sys

import numpy as np
import pytest
from _browser import TIMEOUT_MS, open_app, wait_status
from PIL import Image

pytestmark = [pytest.mark.browser, pytest.mark.slow]

WIDTH, HEIGHT = 2000, 1500
ROUNDS = 4


@contextlib.contextmanager
def _busy(loops: int = 2):
    """``loops`` processes spinning on a core each, stopped on exit."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(loops)]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def _download_state(page) -> dict:
    return page.evaluate(
        "() => { const b = document.querySelector('button#download, #download button');"
        " return {enabled: !!b && !b.disabled, label: b ? b.innerText : null}; }"
    )


def test_download_follows_renders_in_quick_succession(
    app_server, chromium_launch_options, tmp_path
):
    from playwright.sync_api import TimeoutError as PlaywrightTimeout
    from playwright.sync_api import sync_playwright

    rng = np.random.default_rng(5)
    photo = tmp_path / "noisy.png"
    Image.fromarray(rng.integers(0, 256, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)).save(photo)
    server = app_server()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, errors=errors)
            page.set_input_files("#input input[type=file]", str(photo))
            wait_status(page, "full render")
            page.get_by_text("Advanced", exact=True).click()
            page.locator("#format").get_by_text("PNG", exact=True).click()
            page.wait_for_function(
                "() => (document.querySelector('#download')?.innerText ?? '').includes('PNG')"
            )
            box = page.locator("#blur_on input[type=checkbox]")
            with _busy():
                for i in range(ROUNDS):
                    box.uncheck()
                    wait_status(page, "no blur", "full render")
                    box.check()
                    if i % 2:  # the blurred render shown first, its PNG still being written
                        wait_status(page, "full render", absent="no blur")
                    box.uncheck()
                    wait_status(page, "no blur", "full render")
                    try:
                        page.wait_for_function(
                            "() => { const b = document.querySelector("
                            "'button#download, #download button'); return b && !b.disabled; }",
                            timeout=TIMEOUT_MS,
                        )
                    except PlaywrightTimeout:
                        state = _download_state(page)
                        status = page.locator("#info textarea").input_value()
                        raise AssertionError(
                            f"round {i}: Download still disabled after {TIMEOUT_MS} ms under "
                            f"the render {status[:160]!r}; the button: {state}"
                        ) from None
                    state = _download_state(page)
                    assert f"Download PNG ({WIDTH}x{HEIGHT})" in state["label"], state
                    box.check()
                    wait_status(page, "full render", absent="no blur")
        finally:
            browser.close()
    assert not errors, errors
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
