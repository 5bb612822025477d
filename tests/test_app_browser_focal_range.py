"""The focal range in the real page (headless Chromium): a click on a subject that is deep
sets the focus and a range covering it, so the whole subject is sharp; the Focal range
slider shows that range, and set to 0 it gives the thin lens again, which blurs the
subject's near and far ends. The status line gives the d2f render command of each picture."""

from __future__ import annotations

import numpy as np
import pytest
from _browser import (
    changed_result,
    click_photo_at,
    fetch_image,
    open_app,
    result_src,
    wait_status,
)
from PIL import Image

pytestmark = [pytest.mark.browser, pytest.mark.slow]

WIDTH, HEIGHT = 960, 720
#: the subject: a box whose disparity runs from 0.70 (left) to 0.86 (right), before a wall
BOX = (120, 160, 520, 560)


def _write_scene(folder):
    rng = np.random.default_rng(3)
    cells = rng.integers(30, 226, size=(HEIGHT // 2, WIDTH // 2, 3), dtype=np.uint8)
    image = cells.repeat(2, 0).repeat(2, 1)
    disparity = np.full((HEIGHT, WIDTH), 0.1, np.float32)
    x0, y0, x1, y1 = BOX
    disparity[y0:y1, x0:x1] = np.linspace(0.70, 0.86, x1 - x0, dtype=np.float32)
    photo, depth = folder / "deep.png", folder / "deep_disparity.png"
    Image.fromarray(image).save(photo)
    Image.fromarray((disparity * 65535).round().astype(np.uint16)).save(depth)
    return photo, depth, image


def _status(page) -> str:
    return page.locator("#info textarea").input_value()


def _slider(page, elem: str) -> float:
    return float(page.locator(f"#{elem} input[type=range]").input_value())


def _result(page, old):
    return fetch_image(page, changed_result(page, old))


def test_click_sets_a_range_and_the_slider_changes_it(
    app_server, chromium_launch_options, sharpness, tmp_path
):
    from playwright.sync_api import sync_playwright

    photo, depth, image = _write_scene(tmp_path)
    x0, y0, x1, y1 = BOX
    # the subject's near and far ends, a little inside its edges (a thin lens focused on its
    # middle blurs both), and the wall
    ends = [(x0 + 8, y0 + 8, x0 + 80, y1 - 8), (x1 - 80, y0 + 8, x1 - 8, y1 - 8)]
    wall = (x1 + 40, 20, WIDTH - 20, HEIGHT - 20)
    server = app_server()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, errors=errors)
            page.set_input_files("#input input[type=file]", str(photo))
            wait_status(page, "full render")
            page.get_by_text("Your own depth map (optional)").click()
            page.set_input_files("#depth input[type=file]", str(depth))
            wait_status(page, "your disparity map")
            assert _slider(page, "focal_range") == 0.0  # a new photo: the thin lens
            box = page.locator("#blur input[data-testid=number-input]")
            box.click()
            box.fill("1")
            box.press("Enter")
            wait_status(page, "f/1, blur", "full render")

            # 1. a click on the subject's middle: the focus and a range that covers it
            old = result_src(page)
            click_photo_at(page, (x0 + x1) // 2, (y0 + y1) // 2)
            page.wait_for_function(
                "() => parseFloat(document.querySelector('#focal_range input[type=range]')"
                ".value) > 0.1"
            )
            span = _slider(page, "focal_range")
            assert 0.14 <= span <= 0.25, span  # the subject is 0.16 deep
            # the click's render, or the render of the page's values that follows it (the
            # aperture box's release when it still had the keyboard focus), whose status
            # line has no note of the click
            info = wait_status(page, f"focal range {span:g} |", "full render")
            assert f"--focal-range {span:g}" in info
            wide = _result(page, old)
            for end in ends:
                assert sharpness(wide, end) >= 0.95 * sharpness(image, end)
            assert sharpness(wide, wall) < 0.5 * sharpness(image, wall)

            # 2. the slider set to 0: the thin lens blurs the subject's ends
            old = result_src(page)
            box = page.locator("#focal_range input[data-testid=number-input]")
            box.click()
            box.fill("0")
            box.press("Enter")
            info = wait_status(page, "--focal-range 0 ", "full render")
            assert "focal range 0" not in info.split(" | reproduce: ")[0]
            assert "--focal-range 0" in info
            thin = _result(page, old)
            for end in ends:
                assert sharpness(thin, end) < 0.9 * sharpness(wide, end)
        finally:
            browser.close()
    assert not errors, errors
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
