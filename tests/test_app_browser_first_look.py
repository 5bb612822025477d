"""A large upload in the real page (headless Chromium): the result panel shows a first look
at the render pass's size, then the full-resolution render replaces it, and Download saves
the full render only once it is there; a click on the photo does the same. An API client of
the same server gets the full render."""

from __future__ import annotations

import numpy as np
import pytest
from _browser import TIMEOUT_MS, click_photo_at, open_app
from PIL import Image

from app.imaging import DISPLAY_MAX_SIDE
from app.settings import FIRST_LOOK_MAX_SIDE, FIRST_LOOK_PIXELS

pytestmark = [pytest.mark.browser, pytest.mark.slow]

#: 4.32 MP, just over the first look's threshold
WIDTH, HEIGHT = 2400, 1800

#: every picture the result panel loads, with the status line and the Download button then
RECORDER = """
(() => {
    window.__loads = [];
    document.addEventListener("load", (e) => {
        const img = e.target;
        if (img.tagName === "IMG" && img.closest("#result")) {
            const button = document.querySelector("#download");
            window.__loads.push({
                w: img.naturalWidth, h: img.naturalHeight,
                status: document.querySelector("#info textarea")?.value ?? "",
                download: button ? !button.disabled : null,
            });
        }
    }, true);
})();
"""


def _large_photo(folder):
    assert WIDTH * HEIGHT > FIRST_LOOK_PIXELS
    rng = np.random.default_rng(5)
    cells = rng.integers(20, 236, size=(HEIGHT // 8, WIDTH // 8, 3), dtype=np.uint8)
    photo = folder / "large.jpg"
    Image.fromarray(cells.repeat(8, 0).repeat(8, 1)).save(photo, quality=90)
    return photo


def test_large_upload_first_look_then_full(app_server, chromium_launch_options, tmp_path):
    from playwright.sync_api import sync_playwright

    photo = _large_photo(tmp_path)
    server = app_server()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, errors=errors)
            page.evaluate(RECORDER)
            page.set_input_files("#input input[type=file]", str(photo))
            page.wait_for_function(
                """() => window.__loads.some((l) => l.status.includes("full render"))
                    && !document.querySelector("#download").disabled""",
                timeout=TIMEOUT_MS * 2,
            )
            loads = page.evaluate("() => window.__loads")
            label = page.locator("#download").inner_text()
            # a click on the photo: refocused at the pass's size first, then in full
            page.evaluate("() => { window.__loads = []; }")
            click_photo_at(page, WIDTH // 2, HEIGHT // 2)
            page.wait_for_function(
                """() => window.__loads.some((l) => l.status.includes("full render")
                    && l.status.includes("focused on the click"))""",
                timeout=TIMEOUT_MS * 2,
            )
            clicks = page.evaluate("() => window.__loads")
        finally:
            browser.close()
    assert not errors, errors
    first, last = loads[0], loads[-1]
    # the first look: the render pass's size, said in the status line, nothing to download
    assert (first["w"], first["h"]) == (FIRST_LOOK_MAX_SIDE, FIRST_LOOK_MAX_SIDE * 3 // 4)
    assert "first look render" in first["status"] and "full resolution follows" in first["status"]
    assert first["download"] is False
    # then the full render, shown at the display's size, and saved at the photo's
    assert (last["w"], last["h"]) == (DISPLAY_MAX_SIDE, DISPLAY_MAX_SIDE * 3 // 4)
    assert "full render" in last["status"] and "first look" not in last["status"]
    assert f"({WIDTH}x{HEIGHT})" in label
    first, last = clicks[0], clicks[-1]
    # a click's picture at the screen's size follows its first look within a few tenths of
    # a second, and may replace it before the browser has loaded it: the first look, when
    # it is seen, is the pass's size and says so
    if len(clicks) > 1 or first["w"] == FIRST_LOOK_MAX_SIDE:
        assert first["w"] == FIRST_LOOK_MAX_SIDE and "first look render" in first["status"]
        assert "focused on the click" in first["status"] and first["download"] is False
    assert last["w"] == DISPLAY_MAX_SIDE and "full render" in last["status"]
    assert "focused on the click" in last["status"]
    assert server.log.read_text().count("Traceback") == 0


def test_api_client_gets_the_full_render(app_server, tmp_path):
    from gradio_client import Client, handle_file

    photo = _large_photo(tmp_path)
    server = app_server()
    client = Client(server.url, verbose=False, analytics_enabled=False,
                    download_files=str(tmp_path / "dl"))  # fmt: skip
    out = client.predict(handle_file(str(photo)), None, "disparity (bright = near)", 0.5, 1.0,
                         0, 0.0, True, True, "Bokeh", "balanced", depth_source="auto",
                         hub_model="", api_name="/load")  # fmt: skip
    result, info = out[1], out[4]  # the session (state) is not an API output
    assert "full render" in info and "first look" not in info
    shown = Image.open(result["value"] if isinstance(result, dict) else result)
    assert shown.size == (DISPLAY_MAX_SIDE, DISPLAY_MAX_SIDE * 3 // 4)
    download = client.predict("PNG", api_name="/download")
    download = download["value"] if isinstance(download, dict) else download
    assert Image.open(download).size == (WIDTH, HEIGHT)
