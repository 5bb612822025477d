"""Live at any size and the 100 % loupe in the real page (headless Chromium): a photo larger
than the screen's side is shown at that side while Download saves its full resolution; a click
on the result shows the region around it at full resolution, the download's own pixels there;
a new aperture renders the loupe's region again."""

from __future__ import annotations

import numpy as np
import pytest
from _browser import (
    TIMEOUT_MS,
    fetch_image,
    open_app,
    result_src,
    type_value,
    wait_new_result,
    wait_status,
)
from PIL import Image

from app.settings import LOUPE_SIZE, SCREEN_SIDE
from d2f_core.metrics import psnr

pytestmark = [pytest.mark.browser, pytest.mark.slow]

WIDTH, HEIGHT = 2400, 1800


def _write_photo(folder):
    """A 2400x1800 textured photo, and its depth: a ramp from the nearest (left) to the
    farthest (right)."""
    rng = np.random.default_rng(11)
    cells = rng.integers(30, 226, size=(HEIGHT // 4, WIDTH // 4, 3), dtype=np.uint8)
    image = cells.repeat(4, 0).repeat(4, 1)
    path = folder / "large.png"
    Image.fromarray(image).save(path)
    ramp = np.tile(np.linspace(1.0, 0.0, WIDTH, dtype=np.float32), (HEIGHT, 1))
    depth = folder / "large_disparity.png"
    Image.fromarray((ramp * 65535).round().astype(np.uint16)).save(depth)
    return path, depth, image


def _download(page, tmp_path) -> np.ndarray:
    page.wait_for_function(
        "() => { const b = document.querySelector('button#download, #download button');"
        " return b && !b.disabled; }",
        timeout=TIMEOUT_MS,
    )
    with page.expect_download() as info:
        page.locator("button#download, #download button").first.click()
    path = tmp_path / info.value.suggested_filename
    info.value.save_as(path)
    return np.asarray(Image.open(path).convert("RGB"))


def test_screen_picture_download_and_loupe(app_server, chromium_launch_options, tmp_path):
    from playwright.sync_api import sync_playwright

    photo, depth, image = _write_photo(tmp_path)
    w, h = LOUPE_SIZE
    server = app_server()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, height=1300, errors=errors, accept_downloads=True)
            page.set_input_files("#input input[type=file]", str(photo))
            wait_status(page, "full render", "shown at 1600x1200")
            # the ramp as depth, focused a quarter of the way in: x = 600 is sharp
            page.get_by_text("Your own depth map (optional)").click()
            page.set_input_files("#depth input[type=file]", str(depth))
            wait_status(page, "your disparity map")
            type_value(page, "focus", "0.25")
            wait_status(page, "focus 0.250", "full render")
            # the same picture in a photographer's words, above the details
            page.wait_for_function(
                "() => (document.querySelector('#summary')?.innerText ?? '')"
                ".includes('Focus 25 % of the way back')"
            )
            assert "sharp from" in page.locator("#summary").inner_text()
            wait_new_result(page, None)
            shown = page.evaluate(
                "() => { const i = document.querySelector('#result img');"
                " return [i.naturalWidth, i.naturalHeight]; }"
            )
            assert shown == [SCREEN_SIDE, SCREEN_SIDE * HEIGHT // WIDTH]
            full = _download(page, tmp_path)
            assert full.shape == (HEIGHT, WIDTH, 3)

            # a click on the result at (400, 300) of its 1600x1200 picture: the region around
            # (600, 450) of the photo, at full resolution: the download's pixels there
            old = result_src(page, "#loupe img")
            box = page.locator("#result img").bounding_box()
            x, y = 400.5 * box["width"] / shown[0], 300.5 * box["height"] / shown[1]
            page.locator("#result img").click(position={"x": x, "y": y})
            src_loupe = wait_new_result(page, old, "#loupe img")
            loupe = fetch_image(page, src_loupe)
            assert loupe.shape == (h, w, 3)
            label = page.locator("#loupe").inner_text()
            assert f"100 % view: {w}x{h} px at" in label
            x0, y0 = (int(v) for v in label.split(" at (")[1].split(")")[0].split(", "))
            assert abs(x0 + w / 2 - 600) <= 3 and abs(y0 + h / 2 - 450) <= 3
            assert psnr(loupe / 255.0, full[y0 : y0 + h, x0 : x0 + w] / 255.0) >= 40.0
            # its middle, on the focal plane (the ramp leaves its sides out of focus): the photo
            mid = (slice(h // 2 - 12, h // 2 + 12), slice(w // 2 - 12, w // 2 + 12))
            region = image[y0 : y0 + h, x0 : x0 + w].astype(int)
            assert np.abs(loupe.astype(int) - region)[mid].mean() < 3.0

            # focused far away: the result and the loupe follow, the region blurred
            type_value(page, "focus", "0.9")
            wait_status(page, "focus 0.900", "full render")
            again = fetch_image(page, wait_new_result(page, src_loupe, "#loupe img"))
            assert np.abs(again.astype(int) - region)[mid].mean() > 10.0
            refreshed = _download(page, tmp_path)
            assert psnr(again / 255.0, refreshed[y0 : y0 + h, x0 : x0 + w] / 255.0) >= 40.0
        finally:
            browser.close()
    assert not errors, errors
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
